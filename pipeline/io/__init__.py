"""Files: decoding frames (``read``), what a file is before decoding it (``probe``),
EXIF (``exif``), atomic writers (``write``), lens profiles (``profiles``),
``stack.toml`` (``stackfile``) and content hashes (``hashing``).
"""

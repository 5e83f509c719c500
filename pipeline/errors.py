"""The project's exceptions.

Every error a user can cause by input (a file, a parameter, a camera) derives
from :class:`FlexdofError`; the CLI prints those as one line and exits non-zero.
Third-party failures (rawpy, cv2, usb) are wrapped with ``raise ... from err``.
"""


class FlexdofError(Exception):
    """Base class of errors reported to the user as one line."""


class InputError(FlexdofError, ValueError):
    """A file, parameter or setting is invalid; the message names it and the fix."""


class TetherError(FlexdofError):
    """A tethered camera or its USB transport failed."""

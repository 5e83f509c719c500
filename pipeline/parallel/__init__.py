"""Dask graphs: the streaming weighted sum of a stack (``accumulate``), tiled
deconvolution (``tiling``) and the scheduler in use (``scheduler``).
"""

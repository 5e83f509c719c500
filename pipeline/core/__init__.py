"""The paper's cores: arrays in, arrays out, no files, dask, USB, CLI or TOML.

optics (Eqs. 1, 2, 9), lens (the lens/sensor dataclass), psf (Eqs. 3-7), spectra
(Eq. 8, MTFs), motion (Secs. 4-8), weights (Sec. 9 and flexible DOFs), stack_kernel
(the focal stack's IPSF), deconvolve, simulate, scene, align, defocus, colour, quality.
"""

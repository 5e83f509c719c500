"""flexdof: flexible depth-of-field photography.

Implements Kuthirummal, Nagahara, Zhou and Nayar, "Flexible Depth of Field
Photography", IEEE TPAMI 2011: extended DOF from focus sweeps and focal stacks
(Sec. 4, 8, 9), discontinuous, tilted and non-planar DOFs (Sec. 5-7).

Cores (``optics``, ``psf``, ``motion``, ``weights``, ``align``, ``deconvolve``,
``simulate``) take and return arrays; I/O, dask, USB and the CLI sit at the edges.
"""

__version__ = "0.1.0"

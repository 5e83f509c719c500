"""Deconvolution of a sweep image by its IPSF (Sec. 4.2): Wiener, Richardson-Lucy, sparse prior.

``common`` holds the input checks, the noise estimate, the padded domain and the
:class:`Plan`; ``wiener``, ``rl`` and ``sparse`` one method each; ``dispatch`` plans
and runs a method (:func:`deconvolve`, :func:`plan`, :func:`restore`).
"""

from pipeline.core.deconvolve.common import (
    METHODS,
    PRIORS,
    Plan,
    check_kernel,
    estimate_noise_sigma,
    filter_depth,
)
from pipeline.core.deconvolve.dispatch import (
    deconvolve,
    plan,
    restore,
    richardson_lucy,
    sparse,
    wiener,
)
from pipeline.core.deconvolve.sparse import hyper_laplacian_prox
from pipeline.core.deconvolve.wiener import kernel_variance

__all__ = [
    "METHODS",
    "PRIORS",
    "Plan",
    "check_kernel",
    "deconvolve",
    "estimate_noise_sigma",
    "filter_depth",
    "hyper_laplacian_prox",
    "kernel_variance",
    "plan",
    "restore",
    "richardson_lucy",
    "sparse",
    "wiener",
]

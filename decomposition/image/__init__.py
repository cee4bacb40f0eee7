"""The whole-cube decomposition: what the pixels of one image share.

:func:`decompose_image` decomposes an image of profiles ``(Y, X, L)`` as one problem: the
instrument and the parameters the user declares global are estimated once from all pixels
(``shared=``), and neighbouring pixels inform each other (``spatial=True``).  Per pixel it runs
:func:`decomposition.decompose`; this package sits above it and never below.
"""
from .api import ImageOptions, decompose_image, halo_pixels  # noqa: F401

__all__ = ["decompose_image", "ImageOptions", "halo_pixels"]

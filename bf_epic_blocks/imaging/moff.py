"""MOFF baseline: the original EPIC correlator (grid the E-fields on one w = 0 plane, FFT, square).

:func:`moff_image` equals, to ~epsilon, the exact DFT image of the same data with every antenna's
z set to 0: the antenna heights (the w term) are ignored, which is the wide-field error the seed
paper measures (14-34 % of the peak for a +-1 m z spread at 74 MHz). It shares the gridding machinery
of :mod:`.wstack` (ES kernel, oversampled FFT grid, periodic wrapping of antennas beyond the grid's
Nyquist limit, which is exact at the image pixels) with a single plane and no w-kernel.
"""
from __future__ import annotations

from .pixels import LMGrid
from .wstack import _field_image

__all__ = ["moff_image"]


def moff_image(efield, xyz_m, freq_hz, grid: LMGrid, *, epsilon=1e-4, products=None,
               remove_autocorr=False, weights=None, sigma=2.0):
    """MOFF (z-ignored) image, (nchan, nprod, grid.npix), float32/float64 in efield's namespace.

    Same arguments as :func:`~.wstack.wstack_image`; ``xyz_m[:, 2]`` is ignored.
    """
    return _field_image(efield, xyz_m, freq_hz, grid, epsilon=epsilon, products=products,
                        remove_autocorr=remove_autocorr, weights=weights, sigma=sigma, use_w=False,
                        direct=None)

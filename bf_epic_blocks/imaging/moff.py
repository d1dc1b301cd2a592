"""MOFF baseline: the original EPIC correlator (grid the E-fields on one w = 0 plane, FFT, square).

:func:`moff_image` equals, to ~epsilon, the exact DFT image of the same data with every antenna's
z set to 0: the antenna heights (the w term) are ignored, which is the wide-field error the seed
paper measures (14-34 % of the peak for a +-1 m z spread at 74 MHz). It shares the gridding machinery
of :mod:`.fieldgrid` (ES kernel, oversampled FFT grid, periodic wrapping of antennas beyond the grid's
Nyquist limit, which is exact at the image pixels) with a single plane and no w-kernel.

Two flavours, because the voltages are not phased to any centre (PHYSICS.md):

* ``phase_zenith=False``: z ignored outright; equals the DFT with z = 0. This drops the whole
  w n term, so even the zenith is defocused by the antenna heights.
* ``phase_zenith=True``: the voltages are first phased to the zenith (x_a exp(-2 pi i nu z_a / c),
  exact), then gridded on one plane: equals the DFT with the w (n - 1) term dropped, the
  single-plane EPIC imager as deployed and as the seed paper measures it.
"""
from __future__ import annotations

import math

from ..conventions import SIGMA, SPEED_OF_LIGHT_M_S
from ._xp import get_xp
from .pixels import LMGrid
from .fieldgrid import field_image

__all__ = ["moff_image"]


def moff_image(efield, xyz_m, freq_hz, grid: LMGrid, *, epsilon=1e-4, products=None,
               remove_autocorr=False, weights=None, sigma=2.0, phase_zenith=False):
    """MOFF (z-ignored) image, (nchan, nprod, grid.npix), float32/float64 in efield's namespace.

    Same arguments as :func:`~.wstack.wstack_image`; ``xyz_m[:, 2]`` is ignored after the optional
    zenith phasing (``phase_zenith``, see the module docstring).
    """
    if phase_zenith:
        xp = get_xp(efield)
        z = xp.asarray(xyz_m, dtype=xp.float64)[:, 2]
        f = xp.asarray(freq_hz, dtype=xp.float64)
        cyc = f[:, None] * z[None, :] / SPEED_OF_LIGHT_M_S
        cyc = cyc - xp.rint(cyc)
        efield = efield * xp.exp((-SIGMA * 2j * math.pi) * cyc)[None, :, :, None].astype(efield.dtype)
    return field_image(efield, xyz_m, freq_hz, grid, epsilon=epsilon, products=products,
                        remove_autocorr=remove_autocorr, weights=weights, sigma=sigma, use_w=False,
                        direct=None)

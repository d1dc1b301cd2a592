"""The math room: pure functions on NumPy or CuPy arrays (work happens where the arrays live).

Public API::

    from bf_epic_blocks import imaging
    img = imaging.dirty_image(efield, xyz_m, freq_hz, pixels_lm, remove_autocorr=False,
                              method="auto", precision="fp32", products=None)

plus :class:`DFTOperator` (build once, image many gulps), pixel-set helpers (:func:`lm_grid`,
:func:`lm_list`, :func:`lm_from_azalt`) and the cost model (:mod:`.cost`).
"""
from . import cost
from .dft import DFTOperator, ImageAccumulator, dirty_image, geometric_operator, geometric_phase_cycles
from .pixels import LMGrid, azalt_from_lm, check_lm, lm_from_azalt, lm_grid, lm_list, n_from_lm
from .moff import moff_image
from .products import resolve_products
from .sanitize import zero_nonfinite
from .wstack import CovarianceGridder, GriddedAccumulator, cov_wgrid_image, gridded_accumulator, wstack_image

__all__ = [
    "DFTOperator", "ImageAccumulator", "LMGrid", "azalt_from_lm", "check_lm", "cost", "dirty_image",
    "geometric_operator", "geometric_phase_cycles", "lm_from_azalt", "lm_grid", "lm_list", "n_from_lm",
    "resolve_products", "wstack_image", "cov_wgrid_image", "moff_image", "GriddedAccumulator",
    "CovarianceGridder", "gridded_accumulator", "zero_nonfinite",
]

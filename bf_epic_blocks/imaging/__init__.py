"""The math room: pure functions on NumPy or CuPy arrays (work happens where the arrays live).

Public API::

    from bf_epic_blocks import imaging
    img = imaging.dirty_image(efield, xyz_m, freq_hz, pixels_lm, remove_autocorr=False,
                              method="auto", precision="fp32", products=None)

plus :class:`DFTOperator` (build once, image many gulps), the accuracy resolver (:func:`resolve`,
:class:`Problem`, :class:`Plan`; :mod:`.plan`), the imaging routes (:func:`make_route`; :mod:`.routes`),
pixel-set helpers (:func:`lm_grid`, :func:`lm_list`, :func:`lm_from_azalt`) and the cost model
(:mod:`.cost`).
"""
from . import cost
from .dft import DFTOperator, ImageAccumulator, dirty_image, geometric_operator, geometric_phase_cycles
from .pixels import LMGrid, azalt_from_lm, check_lm, lm_from_azalt, lm_grid, lm_list, n_from_lm
from .moff import moff_image
from .plan import Plan, Problem, resolve
from .products import resolve_products
from .routes import make_route
from .sanitize import zero_nonfinite
from .wstack import CovarianceGridder, GriddedAccumulator, cov_wgrid_image, gridded_accumulator, wstack_image

__all__ = [
    "CovarianceGridder", "DFTOperator", "GriddedAccumulator", "ImageAccumulator", "LMGrid", "Plan", "Problem",
    "azalt_from_lm", "check_lm", "cost", "cov_wgrid_image", "dirty_image", "geometric_operator",
    "geometric_phase_cycles", "gridded_accumulator", "lm_from_azalt", "lm_grid", "lm_list", "make_route",
    "moff_image", "n_from_lm", "resolve", "resolve_products", "wstack_image", "zero_nonfinite",
]

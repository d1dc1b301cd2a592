"""WStackBlock: the gridded rivals of the DFT imager, as a drop-in block.

Same input and header conventions as :class:`~.dft_imager.DFTImagerBlock`, same output layout on a
regular l-m grid (NaN below the horizon). Routes (:mod:`bf_epic_blocks.imaging.wstack`):

* ``route="efield"``: E-field w-stacking (grid, FFT per w-plane, Fresnel term, |.|^2 per sample);
* ``route="covariance"``: R = X X^H then visibility w-gridding (ducc0 on the CPU, CuPy on the GPU);
* ``route="auto"``: covariance when the integration is at least as long as the array has antennas
  (it is then the cheaper one by far: tools/bench/bench_wstack.py measures both), else E-field;
* ``moff=True``: the original EPIC/MOFF single-plane imager that ignores z (wide-field error).
``tolerance`` is the accuracy knob, as for the DFT imager: the largest relative error of the image
against the exact DFT image's peak; it sets the gridder's epsilon (epsilon = tolerance / 4, the
gridders' tested bound being 4 epsilon; :mod:`bf_epic_blocks.imaging.plan`). The route and epsilon
come from :func:`bf_epic_blocks.imaging.plan.resolve`, like the DFT imager's mode.
Only antenna patterns of kind None are supported here: use the DFT imager to fold a pattern.
"""
from __future__ import annotations

import numpy as np

from ..imaging import plan as planner
from ..imaging.pixels import LMGrid
from ..imaging.wstack import gridded_accumulator
from . import _compat
from .dft_imager import DFTImagerBlock
from .engines import GriddedEngine


class WStackBlock(DFTImagerBlock):
    """Gridded imager block (w-stacking / covariance w-gridding / MOFF) on an :class:`LMGrid`.

    tolerance : None (4e-4: gridder epsilon 1e-4) or the largest relative image error, in
                [4e-14, 0.4].   route : 'auto' | 'efield' | 'covariance' (an expert override;
                auto: covariance when ``accumulate`` >= the antennas used).   moff : the MOFF imager.
    plan : instead of tolerance / route, a Plan resolved for this problem (see DFTImagerBlock).
    """

    imager_kind = "wstack"

    def __init__(self, iring, grid, accumulate, tolerance=None, products=None, remove_autocorr=False,
                 route="auto", moff=False, *args, **kwargs):
        if "epsilon" in kwargs:
            raise TypeError("WStackBlock: epsilon is set by tolerance now (the largest relative image error; "
                            "epsilon = tolerance / 4): pass tolerance=4 * epsilon")
        if not isinstance(grid, LMGrid):
            raise TypeError(f"WStackBlock images a regular grid: pass an LMGrid (imaging.lm_grid(N)), got "
                            f"{type(grid).__name__}; for pixel lists use DFTImagerBlock")
        if route not in planner.GRIDDED_METHODS:
            raise ValueError(f"WStackBlock: route must be one of {planner.GRIDDED_METHODS}, got {route!r}")
        if kwargs.get("precision") is not None:
            raise ValueError("WStackBlock: its work precision follows tolerance; give tolerance, not precision")
        self.moff = bool(moff)
        if self.moff:
            self.imager_kind = "moff"
        given = kwargs.get("plan")
        self.epsilon = given.epsilon if given is not None else planner.gridded_epsilon(tolerance, self.imager_kind)
        super().__init__(iring, grid, accumulate, products=products, remove_autocorr=remove_autocorr,
                         method=route if given is None else "auto", pattern=None, tolerance=tolerance, *args,
                         **kwargs)
        # the gridder's CPU path imports these on the block's thread (see _compat.import_now)
        _compat.import_now("scipy.fft", "scipy.sparse")

    def _build(self, lm):
        """This sequence's engine: the gridded accumulator of the route, fed complex voltages
        (:class:`~.engines.GriddedEngine`)."""
        lay, xp = self._lay, self._xp
        if self._pattern_name:
            raise ValueError("WStackBlock cannot fold an antenna pattern; set calibration pattern to none or use "
                             "DFTImagerBlock")
        live = ~lay["flags"]
        nant_used = int(live.any(axis=1).sum())
        self._resolve(self._hdr, lm, nant_used)
        self.epsilon = self.plan.epsilon
        acc = gridded_accumulator(lay["xyz_m"], lay["freq_hz"], self.pixels, lay["npol"], route=self.plan.method,
                                  epsilon=self.plan.epsilon, products=self.products,
                                  remove_autocorr=self.remove_autocorr,
                                  weights=live[None].astype(np.complex128), xp=xp)
        self.img_stats["operator_builds"] += 1
        return GriddedEngine(acc, lm, nant_used=nant_used, npix=self.pixels.npix,
                             accumulate=self.accumulate, dtype=lay["dtype"], name=type(self).__name__)


def wstack(iring, grid, accumulate, *args, **kwargs):
    """Factory for :class:`WStackBlock`."""
    return WStackBlock(iring, grid, accumulate, *args, **kwargs)

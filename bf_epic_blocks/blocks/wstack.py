"""WStackBlock: the gridded rivals of the DFT imager, as a drop-in block.

Same input and header conventions as :class:`~.dft_imager.DFTImagerBlock`, same output layout on a
regular l-m grid (NaN below the horizon). Routes (:mod:`bf_epic_blocks.imaging.wstack`):

* ``route="efield"``: E-field w-stacking (grid, FFT per w-plane, Fresnel term, |.|^2 per sample);
* ``route="covariance"``: R = X X^H then visibility w-gridding (ducc0 on the CPU, CuPy on the GPU);
* ``route="auto"``: covariance when the integration is at least as long as the array has antennas
  (it is then the cheaper one by far: tools/bench_wstack.py measures both), else E-field;
* ``moff=True``: the original EPIC/MOFF single-plane imager that ignores z (wide-field error).
``epsilon`` is the accuracy relative to the exact DFT image's peak (error <= 4 epsilon, tested).
Only antenna patterns of kind None are supported here: use the DFT imager to fold a pattern.
"""
from __future__ import annotations

import numpy as np

from ..imaging.pixels import LMGrid
from ..imaging.wstack import gridded_accumulator
from .dft_imager import DFTImagerBlock
from .engines import GriddedEngine


class WStackBlock(DFTImagerBlock):
    """Gridded imager block (w-stacking / covariance w-gridding / MOFF) on an :class:`LMGrid`."""

    imager_kind = "wstack"

    def __init__(self, iring, grid, accumulate, epsilon=1e-4, products=None, remove_autocorr=False,
                 route="auto", moff=False, *args, **kwargs):
        if not isinstance(grid, LMGrid):
            raise TypeError(f"WStackBlock images a regular grid: pass an LMGrid (imaging.lm_grid(N)), got "
                            f"{type(grid).__name__}; for pixel lists use DFTImagerBlock")
        if not (0 < float(epsilon) <= 0.1):
            raise ValueError(f"WStackBlock: epsilon must be in (0, 0.1], got {epsilon!r}")
        if kwargs.get("tolerance") is not None:
            raise ValueError("WStackBlock: its accuracy is set by epsilon, not tolerance")
        if route not in ("auto", "efield", "covariance"):
            raise ValueError(f"WStackBlock: route must be 'auto', 'efield' or 'covariance', got {route!r}")
        super().__init__(iring, grid, accumulate, products=products, remove_autocorr=remove_autocorr,
                         method=route, precision="fp32" if epsilon >= 1e-5 else "fp64", pattern=None,
                         *args, **kwargs)
        self.epsilon, self.moff = float(epsilon), bool(moff)
        if self.moff:
            self.imager_kind = "moff"

    def _build(self, lm):
        """This sequence's engine: the gridded accumulator of the route, fed complex voltages
        (:class:`~.engines.GriddedEngine`)."""
        lay, xp = self._lay, self._xp
        if self._pattern_name:
            raise ValueError("WStackBlock cannot fold an antenna pattern; set calibration pattern to none or use "
                             "DFTImagerBlock")
        live = ~lay["flags"]
        route = self.method
        if self.moff:
            route = "moff"
        elif route == "auto":
            route = "covariance" if self.accumulate >= lay["nstand"] else "efield"
        acc = gridded_accumulator(lay["xyz_m"], lay["freq_hz"], self.pixels, lay["npol"], route=route,
                                  epsilon=self.epsilon, products=self.products,
                                  remove_autocorr=self.remove_autocorr,
                                  weights=live[None].astype(np.complex128), xp=xp)
        self.img_stats["operator_builds"] += 1
        return GriddedEngine(acc, lm, nant_used=int(live.any(axis=1).sum()), npix=self.pixels.npix,
                             accumulate=self.accumulate, dtype=lay["dtype"], name=type(self).__name__)


def wstack(iring, grid, accumulate, *args, **kwargs):
    """Factory for :class:`WStackBlock`."""
    return WStackBlock(iring, grid, accumulate, *args, **kwargs)

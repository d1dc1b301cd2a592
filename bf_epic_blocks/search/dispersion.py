"""Per-channel dispersion delays in whole images, from the one dispersion law
(:func:`bf_epic_blocks.conventions.dispersion_delay_s`): a burst of dispersion measure DM (pc cm^-3)
reaches frequency f later than the band's highest channel by ``4.149 ms * DM * ((f/GHz)^-2 -
(f_ref/GHz)^-2)``."""
from __future__ import annotations

import numpy as np

from ..conventions import dispersion_delay_s

__all__ = ["dm_delays"]


def dm_delays(dms, freq_hz, dt_s):
    """Per-trial, per-channel delays in whole images, (ndm, nchan) int64, relative to the highest
    channel: ``round(dispersion_delay_s(dm, f_c, max(f)) / dt_s)``."""
    f = np.asarray(freq_hz, dtype=np.float64)
    d = dispersion_delay_s(np.asarray(dms, dtype=np.float64)[:, None], f[None, :], f.max())
    return np.rint(d / float(dt_s)).astype(np.int64)

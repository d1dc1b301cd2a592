"""The search room: finding short bursts in image time series (above the math room, below the blocks).

* :mod:`.dispersion` -- per-channel delays in whole images (the law itself is
  :func:`bf_epic_blocks.conventions.dispersion_delay_s`);
* :mod:`.tree` -- the tree dedispersion (FDMT), whole-series and streaming, CPU and GPU;
* :mod:`.statistics` -- :class:`TransientSearch`: dedispersion, sliding statistics, boxcar S/N and
  threshold crossings, streaming, on NumPy or CuPy;
* :mod:`.clustering` -- crossings into candidates (friends of friends), DM sidelobes, false rates, a
  candidate's DM between trials;
* :mod:`.localisation` -- the array's beam and the point source that explains an event;
* :mod:`.settings` -- :class:`SearchSettings`, the one object a search block is configured by.
"""
from .clustering import Crossings, cluster_crossings, dm_sidelobe_snr, expected_false_rate, refine_peak
from .dispersion import dm_delays
from .localisation import ArrayBeam, beam_power, locate_point_source
from .settings import SearchSettings
from .statistics import TREE_CHANNELS, TransientSearch
from .tree import FDMTPlan, HalfRows, StreamingFDMT, effective_back, fdmt

__all__ = ["ArrayBeam", "Crossings", "FDMTPlan", "HalfRows", "SearchSettings", "StreamingFDMT", "TREE_CHANNELS",
           "TransientSearch", "beam_power", "cluster_crossings", "dm_delays", "dm_sidelobe_snr", "effective_back",
           "expected_false_rate", "fdmt", "locate_point_source", "refine_peak"]

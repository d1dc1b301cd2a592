"""The sky: catalogue sources and their directions (astropy), and the simulated E-field generator.

* :mod:`.catalogue` -- :class:`Source`, :data:`KNOWN_SOURCES`, :func:`source_directions` and the
  time/place/frame helpers (ICRS <-> (l, m)) the writers use.
* :mod:`.efield` -- :func:`simulate_efield` (F-engine voltages of a point-source sky, PHYSICS.md's
  data model) and :func:`quantize_ci4`.
* :mod:`.fastsim` -- the counter-based generator the simulated-sky block runs (GPU kernel and CPU twin).
* :mod:`.diffuse` -- an analytic model of the diffuse Galactic emission, its covariance across a
  station and the eigenmodes the generator simulates it with.
* :mod:`.corrupt` -- :class:`~.corrupt.GainCorruption`: chosen gains, deaf and noisy inputs, the
  truth a calibration test solves for.
* :mod:`.watch` -- watchlist targets (catalogue, ICRS, solar-system bodies) and their (l, m) over many times.
"""
from .catalogue import (KNOWN_SOURCES, REF_FREQ_HZ, Source, SourceDirections, as_location, as_time,
                        icrs_to_lm, lm_to_icrs, north_angle_deg, resolve_source, resolve_sources,
                        source_directions, zenith_icrs, zenith_pointings)
from .efield import quantize_ci4, simulate_efield

__all__ = ["KNOWN_SOURCES", "REF_FREQ_HZ", "Source", "SourceDirections", "as_location", "as_time",
           "icrs_to_lm", "lm_to_icrs", "north_angle_deg", "resolve_source", "resolve_sources",
           "source_directions", "zenith_icrs", "zenith_pointings", "quantize_ci4", "simulate_efield"]

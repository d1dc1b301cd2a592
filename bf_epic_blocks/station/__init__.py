"""The station: LSL station tables (positions, cable delays and gains, flags) and offline set-up.

* :mod:`.tables` -- :class:`StationTable` and :func:`load_station` (LSL's lwasv / lwana / lwa1 or an
  SSMIF file), flags, the vectorised cable model, the header round trip.
* :mod:`.offline` -- :func:`configure_offline`: LSL telemetry and data-cache refreshes off, astropy's
  IERS downloads off, so nothing reaches for the network.
"""
from .offline import configure_offline
from .tables import GOOD_STATUS, STATION_NAMES, StationTable, load_station

__all__ = ["configure_offline", "GOOD_STATUS", "STATION_NAMES", "StationTable", "load_station"]

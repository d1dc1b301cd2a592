"""Readers and writers: LWA TBF F-engine captures in; FITS cubes, pixel tables and PNG quicklooks out.

* :mod:`.tbf` -- the TBF (frequency-domain transient buffer) reader.
* :mod:`.fits` -- SIN-projected FITS cubes and FITS/NPZ pixel tables (arrays plus time, location,
  frequencies and products; no rings).
* :mod:`.quicklook` -- PNG quicklooks of all-sky images.
"""
from .tbf import (TBFData, TBFError, TBFInfo, TBFWarning, iter_tbf_gulps, pack_ci4, read_tbf,
                  scan_tbf, time_tag_to_time, unpack_ci4)

__all__ = ["TBFData", "TBFError", "TBFInfo", "TBFWarning", "iter_tbf_gulps", "pack_ci4", "read_tbf",
           "scan_tbf", "time_tag_to_time", "unpack_ci4"]

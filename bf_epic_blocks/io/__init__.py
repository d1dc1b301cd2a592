"""Readers and writers: LWA TBF F-engine captures in; FITS cubes, pixel tables and PNG quicklooks out.

* :mod:`.tbf` -- the TBF (frequency-domain transient buffer) reader.
* :mod:`.tbx` -- the TBX (NDP transient buffer) reader and writer, and the one-frame parser.
* :mod:`.formats` -- :func:`detect_format`: TBF or TBX, by the frame id.
* :mod:`.fits` -- SIN-projected FITS cubes and FITS/NPZ pixel tables (arrays plus time, location,
  frequencies and products; no rings).
* :mod:`.quicklook` -- PNG quicklooks of all-sky images.
* :mod:`.watchfile` -- the watchlist's HDF5 file of per-target spectra (SWMR) and its dynamic-spectrum PNG.
"""
from .formats import FrameFormatError, detect_format
from .tbf import (TBFData, TBFError, TBFInfo, TBFWarning, iter_tbf_gulps, pack_ci4, read_tbf,
                  scan_tbf, time_tag_to_time, unpack_ci4)
from .tbx import (TBXData, TBXError, TBXFrame, TBXInfo, TBXWarning, iter_tbx_gulps, parse_tbx_frame, read_tbx,
                  scan_tbx, write_tbx)

__all__ = ["TBFData", "TBFError", "TBFInfo", "TBFWarning", "iter_tbf_gulps", "pack_ci4", "read_tbf",
           "scan_tbf", "time_tag_to_time", "unpack_ci4", "FrameFormatError", "detect_format", "TBXData", "TBXError",
           "TBXFrame", "TBXInfo", "TBXWarning", "iter_tbx_gulps", "parse_tbx_frame", "read_tbx", "scan_tbx",
           "write_tbx"]

"""File readers: LWA TBF (frequency-domain transient buffer) F-engine captures.

See :mod:`bf_epic_blocks.io.tbf`.
"""
from .tbf import (TBFData, TBFError, TBFInfo, TBFWarning, iter_tbf_gulps, pack_ci4, read_tbf,
                  scan_tbf, time_tag_to_time, unpack_ci4)

__all__ = ["TBFData", "TBFError", "TBFInfo", "TBFWarning", "iter_tbf_gulps", "pack_ci4", "read_tbf",
           "scan_tbf", "time_tag_to_time", "unpack_ci4"]

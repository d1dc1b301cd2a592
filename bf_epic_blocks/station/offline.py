"""Keep LSL and astropy off the network.

Call :func:`configure_offline` before anything imports ``lsl`` (``bf_epic_blocks.station``
does so itself). It is idempotent and cheap after the first call.

Why:

* LSL reads its configuration directory once, at import, from the environment variable
  ``LSLCONFIGDIR`` (default ``~/.lsl``; see ``lsl/config.py``). From there it (a) starts a telemetry
  client that spawns a subprocess uploading usage data (section ``[ telemetry ] enabled``), and (b)
  keeps a data cache of SSMIF/antenna files that it re-checks against a web server once the cached
  copy is older than ``[ download ] refresh_age`` days (14 by default; ``lsl/common/data_access.py``).
  We point ``LSLCONFIGDIR`` at a folder owned by this package holding an ``lsl.cfg`` with telemetry
  disabled, a refresh age of 100 years and a short download timeout, so LSL serves the station files
  it ships with and never waits on a server.
* astropy downloads IERS-A Earth-orientation tables when a time is beyond its bundled table
  (``iers.conf.auto_download``); we switch that off, accept stale tables
  (``auto_max_age = None``, ``iers_degraded_accuracy = 'warn'``) and, by default, forbid internet
  access for astropy's data downloads altogether (``astropy.utils.data.conf.allow_internet``) so any
  remaining attempt fails at once instead of timing out. Coordinates then use the bundled tables
  (sub-arcsecond errors at most, irrelevant at LWA resolution).

If the user has set ``LSLCONFIGDIR`` already, it is respected (with ``respect_existing=True``, the
default) and only an lsl.cfg missing there is written. If ``lsl`` was imported before this call, the
directory can no longer change; telemetry is then switched off for this session in memory
(``lsl.misc.telemetry.ignore``) and a warning says so.
"""
from __future__ import annotations

import os
import sys
import tempfile
import warnings
from pathlib import Path

__all__ = ["configure_offline", "lsl_config_dir", "LSL_CFG_SETTINGS"]

#: The settings written to lsl.cfg: {section: {key: value}} (keys from LSL's lsl/config.py).
LSL_CFG_SETTINGS = {
    "telemetry": {"enabled": False},
    # days; LSL compares the data cache age with refresh_age * 86400 s before asking a server
    "download": {"refresh_age": 36500, "timeout": 5},
}

_STATE: dict = {"done": False, "dir": None}


def lsl_config_dir() -> Path:
    """The package-owned LSL configuration folder (``$XDG_CACHE_HOME`` or ``~/.cache``, else a temp dir)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "bf_epic_blocks" / "lslcfg"


def _lsl_version() -> str | None:
    # importlib.metadata, not lsl.version: importing any lsl module reads the config directory.
    try:
        from importlib.metadata import PackageNotFoundError, version
        try:
            return version("lsl")
        except PackageNotFoundError:
            return None
    except ImportError:  # pragma: no cover
        return None


def _cfg_text() -> str:
    lines = ["# LSL Configuration File (written by bf_epic_blocks.station.offline)"]
    v = _lsl_version()
    if v is not None:
        # A matching version line stops LSL from rewriting the file at exit.
        lines.append(f"# LSL Version: {v}")
    for section, items in LSL_CFG_SETTINGS.items():
        lines.append("")
        lines.append(f"[ {section} ]")
        for k, val in items.items():
            lines.append(f"{k} = {val}")
    return "\n".join(lines) + "\n"


def _write_cfg(folder: Path, overwrite: bool) -> bool:
    """Write lsl.cfg in ``folder``; False if the folder is not writable."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        cfg = folder / "lsl.cfg"
        text = _cfg_text()
        if cfg.exists() and (not overwrite or cfg.read_text() == text):
            return True
        tmp = folder / f"lsl.cfg.{os.getpid()}.tmp"
        tmp.write_text(text)
        os.replace(tmp, cfg)  # atomic: a concurrent reader sees the old or the new file, not half
        return True
    except OSError:
        return False


def _configure_lsl(respect_existing: bool) -> Path | None:
    if "lsl.config" in sys.modules:
        # Too late to move the folder: LSL has read it. Silence telemetry for this session only.
        try:
            from lsl.misc import telemetry
            telemetry.ignore()
        except Exception:  # pragma: no cover - telemetry API differs between LSL versions
            pass
        warnings.warn("configure_offline() was called after lsl was imported; LSL keeps its "
                      "configuration folder, telemetry was disabled for this session only",
                      RuntimeWarning, stacklevel=3)
        return None
    existing = os.environ.get("LSLCONFIGDIR")
    if existing and respect_existing:
        folder = Path(existing)
        _write_cfg(folder, overwrite=False)
        return folder
    folder = lsl_config_dir()
    if not _write_cfg(folder, overwrite=True):
        folder = Path(tempfile.gettempdir()) / f"bf_epic_blocks-lslcfg-{os.getuid() if hasattr(os, 'getuid') else 0}"
        if not _write_cfg(folder, overwrite=True):  # pragma: no cover - no writable place at all
            warnings.warn("configure_offline(): no writable folder for LSL's configuration; LSL "
                          "will use its defaults (telemetry on, 14-day data refresh)", RuntimeWarning,
                          stacklevel=3)
            return None
    os.environ["LSLCONFIGDIR"] = str(folder)
    return folder


def _configure_astropy(allow_internet: bool) -> None:
    try:
        from astropy.utils import iers
        from astropy.utils.data import conf as data_conf
    except ImportError:  # astropy absent: nothing to configure
        return
    iers.conf.auto_download = False
    iers.conf.auto_max_age = None
    iers.conf.iers_degraded_accuracy = "warn"
    if not allow_internet:
        data_conf.allow_internet = False


def configure_offline(*, respect_existing: bool = True, allow_internet: bool = False) -> Path | None:
    """Make LSL and astropy work without a network. Idempotent.

    Parameters
    ----------
    respect_existing : keep a ``LSLCONFIGDIR`` the user already set (writing an lsl.cfg there only
        if it has none); False always uses the package-owned folder :func:`lsl_config_dir`.
    allow_internet : leave astropy's ``allow_internet`` as it is (True) or forbid it (False, default).

    Returns
    -------
    The LSL configuration folder in use, or None if lsl was already imported (folder unchanged).
    """
    if _STATE["done"]:
        return _STATE["dir"]
    folder = _configure_lsl(respect_existing)
    _configure_astropy(allow_internet)
    _STATE.update(done=True, dir=folder)
    return folder

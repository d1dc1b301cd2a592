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

__all__ = ["configure_offline", "lsl_config_dir", "LSL_CFG_SETTINGS", "iers_table"]

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


#: the IERS table's columns astropy's Earth-orientation lookups read (``IERS.ut1_utc``, ``pm_xy``,
#: ``dcip_xy`` and the IERS_A source flags), as ``IERS_A.read`` leaves them (A and B combined)
_IERS_COLUMNS = ("MJD", "UT1_UTC", "PM_x", "PM_y", "dX_2000A", "dY_2000A", "UT1Flag", "PolPMFlag", "NutFlag")


def _iers_cache_file(data_path) -> Path:
    import hashlib
    from importlib.metadata import version
    st = os.stat(data_path)
    key = f"{version('astropy')}:{Path(data_path).resolve()}:{st.st_size}:{st.st_mtime_ns}"
    return lsl_config_dir().parent / "iers" / f"iers_a-{hashlib.sha1(key.encode()).hexdigest()[:16]}.npz"


def iers_table():
    """astropy's default Earth-orientation table (``IERS_Auto``, the bundled IERS-A file combined
    with IERS-B), parsed once per astropy version and IERS data file and then kept as ``.npz`` under
    the user's cache folder (``~/.cache/bf_epic_blocks/iers``).

    astropy parses the 3.4-MB fixed-width IERS-A text on the first coordinate transform of every
    process, which takes over a second of every ``bf-epic run`` and holds the GIL while the
    pipeline's other threads wait. A cached table fills ``IERS_Auto``'s own slot, so every later astropy transform in the process
    uses it and gives what the parsed file gives, value for value. Needs
    :func:`configure_offline` (no downloads) to have run; returns the table.
    """
    import numpy as np
    from astropy import units as u
    from astropy.table import QTable
    from astropy.utils import iers
    if iers.IERS_Auto.iers_table is not None:
        return iers.IERS_Auto.iers_table
    path = None
    try:
        path = _iers_cache_file(iers.IERS_A_FILE)
        with np.load(path, allow_pickle=False) as z:
            cols = {k: (z[k] * u.Unit(str(z[f"unit_{k}"])) if f"unit_{k}" in z else z[k]) for k in _IERS_COLUMNS}
            meta = {"predictive_index": int(z["predictive_index"]), "predictive_mjd": float(z["predictive_mjd"]),
                    "data_path": str(iers.IERS_A_FILE), "readme_path": str(iers.IERS_A_README)}
        iers.IERS_Auto.iers_table = iers.IERS_Auto(QTable(cols, meta=meta))
        return iers.IERS_Auto.iers_table
    except (OSError, KeyError, ValueError, TypeError):
        pass            # no cache yet, or one from another layout: parse the file and write it
    table = iers.IERS_Auto.open()
    if path is not None:
        try:
            arrays = {}
            for k in _IERS_COLUMNS:
                col = table[k]
                unit = getattr(col, "unit", None)
                arrays[k] = np.asarray(col.value if unit is not None else col)
                if unit is not None:
                    arrays[f"unit_{k}"] = np.array(str(unit))
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")
            np.savez(tmp, predictive_index=table.meta["predictive_index"],
                     predictive_mjd=table.meta["predictive_mjd"], **arrays)
            os.replace(tmp, path)
        except OSError:
            pass        # a read-only cache costs the next run the parse, nothing else
    return table


def _set_iers_conf(iers_module) -> None:
    conf = iers_module.conf
    conf.auto_download = False
    conf.auto_max_age = None
    conf.iers_degraded_accuracy = "warn"


def _forbid_internet(data_module) -> None:
    data_module.conf.allow_internet = False


class _WhenLoaded:
    """A meta-path finder that calls ``then(module)`` right after one of ``modules`` has executed.

    Importing ``astropy.utils.iers`` pulls in astropy.table, units, time... (about a second
    without bytecode caches), and a recording imaged on a GPU needs no astropy in the process that runs the blocks
    at all (its FITS are written by a helper process). So :func:`configure_offline` does not import
    astropy to set its options: they are applied by this hook the moment astropy's own modules load,
    before any code can use them (the module is configured before its importer sees it)."""

    def __init__(self, hooks):
        self.hooks = dict(hooks)          # module name -> then(module)

    def find_spec(self, name, path, target=None):
        then = self.hooks.pop(name, None)
        if then is None:
            return None
        if not self.hooks and self in sys.meta_path:
            sys.meta_path.remove(self)
        spec = None
        for finder in sys.meta_path:
            if finder is self or not hasattr(finder, "find_spec"):
                continue
            spec = finder.find_spec(name, path, target)
            if spec is not None:
                break
        if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
            return spec
        inner = spec.loader

        class _Loader:
            def create_module(self, spec):
                return inner.create_module(spec)

            def exec_module(self, module):
                inner.exec_module(module)
                then(module)

            def __getattr__(self, attr):      # get_code, get_source, is_package, ... for tools that ask
                return getattr(inner, attr)
        spec.loader = _Loader()
        return spec


def _configure_astropy(allow_internet: bool) -> None:
    """astropy's IERS and data options (module docstring), set now where astropy's modules are already
    loaded, else the moment they load (:class:`_WhenLoaded`); astropy is never imported here."""
    hooks = {"astropy.utils.iers.iers": _set_iers_conf}
    if not allow_internet:
        hooks["astropy.utils.data"] = _forbid_internet
    pending = {}
    for name, then in hooks.items():
        if name in sys.modules:
            then(sys.modules[name])
        else:
            pending[name] = then
    if pending:
        sys.meta_path.insert(0, _WhenLoaded(pending))


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

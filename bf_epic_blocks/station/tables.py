"""LWA station metadata from LSL: stand positions, antenna flags and cable terms.

:func:`load_station` turns an LSL station (``lwasv``, ``lwana``, ``lwa1``) or an SSMIF file into a
:class:`StationTable` of plain NumPy arrays in the project's conventions:

* Stand axis in LSL's antenna (digitizer) order, which is the order of TBF payloads: LSL
  ``station.antennas[k]`` is stand index ``k // 2`` (``stand_ids[k // 2]``), polarisation ``k % 2``
  with pol 0 = X = N-S dipole, pol 1 = Y = E-W dipole. For LWA-SV and LWA-NA the stand ids run
  1..N in order; for LWA1 they do not (digitizer order), which is why ``stand_ids`` is kept.
* ``xyz_m`` (nstand, 3): metres East, North, Up from the station centre (LSL ``stand.x/.y/.z``).
* ``flags`` (nstand, 2) bool, True = bad: LSL ``combined_status != 33`` (antenna status 3 and FEE
  status 3 = both OK), OR-ed with user flags.
* Cable terms per antenna and channel: delay ``tau`` (s) and power gain ``G`` from LSL's cable model
  (``Cable.delay``/``Cable.gain``, vectorised over frequency). The raw voltage carries
  ``sqrt(G) exp(-2 pi i nu tau)``; :meth:`StationTable.cable_weights` is the calibration factor
  ``exp(+2 pi i nu tau) / sqrt(G)`` (0 where flagged), see docs/CONVENTIONS.md.

``to_header`` / ``from_header`` carry a table through a JSON ring header (the ``station`` entry of
docs/HEADERS.md). A table rebuilt from a
header has no LSL cable objects; it answers ``cable_delay_s``/``cable_gain`` for the frequencies
that were stored with ``to_header(freq_hz=...)`` only.
"""
from __future__ import annotations

import functools
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from .offline import configure_offline

__all__ = ["StationTable", "load_station", "station_for_capture", "STATION_NAMES", "GOOD_STATUS"]

#: Station names LSL knows with antennas (``ovrolwa`` has none).
STATION_NAMES = ("lwasv", "lwana", "lwa1")
_ALIASES = {"lwasv": "lwasv", "lwana": "lwana", "lwa1": "lwa1", "lwavl": "lwa1"}
#: LSL ``Antenna.combined_status`` meaning antenna and FEE both OK (10 * 3 + 3).
GOOD_STATUS = 33
_POLS = {"x": (0,), "y": (1,), "both": (0, 1)}


def _norm_name(name: str) -> str:
    return "".join(ch for ch in name.lower() if ch.isalnum())


@dataclass
class StationTable:
    """Stand positions, flags and cable terms of one LWA station (see the module docstring).

    Attributes
    ----------
    name : station name, lower case ('lwasv', 'lwana', 'lwa1', or the SSMIF's station name).
    lat_deg, lon_deg, elev_m : geodetic position of the station centre (WGS84; deg, deg, m).
    stand_ids : int (nstand,), LSL stand ids in antenna order (stand index s <-> antennas 2s, 2s+1).
    xyz_m : float64 (nstand, 3), East, North, Up metres from the station centre.
    flags : bool (nstand, 2), True = do not use (status flags OR user flags).
    combined_status : int (nstand, 2), LSL antenna+FEE status (33 = good); -1 if unknown.
    location : astropy EarthLocation built from lat/lon/elev (derived, not an init argument).
    """
    name: str
    lat_deg: float
    lon_deg: float
    elev_m: float
    stand_ids: np.ndarray
    xyz_m: np.ndarray
    flags: np.ndarray
    combined_status: np.ndarray
    cables: Sequence[Any] | None = field(default=None, repr=False)
    cable_table: Mapping[str, np.ndarray] | None = field(default=None, repr=False)

    def __post_init__(self):
        self.stand_ids = np.asarray(self.stand_ids, dtype=np.int64)
        self.xyz_m = np.asarray(self.xyz_m, dtype=np.float64)
        self.flags = np.asarray(self.flags, dtype=bool)
        self.combined_status = np.asarray(self.combined_status, dtype=np.int64)
        n = len(self.stand_ids)
        for what, arr, shape in (("xyz_m", self.xyz_m, (n, 3)), ("flags", self.flags, (n, 2)),
                                 ("combined_status", self.combined_status, (n, 2))):
            if arr.shape != shape:
                raise ValueError(f"StationTable.{what}: expected shape {shape} for {n} stands, got {arr.shape}")
        if self.cables is not None and len(self.cables) != 2 * n:
            raise ValueError(f"StationTable.cables: expected {2 * n} cables (stand-major, pol minor), "
                             f"got {len(self.cables)}")

    @functools.cached_property
    def location(self):
        """astropy EarthLocation (WGS84) of the station; built when first asked for, so a pipeline that
        needs none does not import astropy.coordinates (0.1-0.5 s) while it starts."""
        from astropy import units as u
        from astropy.coordinates import EarthLocation
        return EarthLocation.from_geodetic(lon=self.lon_deg * u.deg, lat=self.lat_deg * u.deg,
                                           height=self.elev_m * u.m, ellipsoid="WGS84")

    # ------------------------------------------------------------------ basic facts
    @property
    def nstand(self) -> int:
        return len(self.stand_ids)

    @property
    def nant(self) -> int:
        """Number of antennas (2 * nstand): antenna k = stand index k // 2, pol k % 2."""
        return 2 * self.nstand

    @property
    def good(self) -> np.ndarray:
        """bool (nstand, 2): not flagged."""
        return ~self.flags

    def stand_index(self, stand_id: int) -> int:
        """Row of LSL stand id ``stand_id``; ValueError if the station has no such stand."""
        hit = np.flatnonzero(self.stand_ids == int(stand_id))
        if hit.size == 0:
            raise ValueError(f"station {self.name!r} has no stand {stand_id}; stand ids run "
                             f"{self.stand_ids.min()}..{self.stand_ids.max()} ({self.nstand} stands)")
        return int(hit[0])

    def with_flags(self, extra_flags) -> "StationTable":
        """A copy with ``extra_flags`` (see :func:`load_station`) OR-ed into ``flags``."""
        flags = self.flags.copy()
        for i, entry in enumerate(extra_flags or []):
            if isinstance(entry, (int, np.integer)) and not isinstance(entry, bool):
                entry = {"stand": int(entry)}
            if not isinstance(entry, Mapping) or "stand" not in entry:
                raise ValueError(f"extra_flags[{i}]: expected {{stand: int, pol: 'X'|'Y'|'both'}} or a "
                                 f"stand number, got {entry!r}")
            unknown = set(entry) - {"stand", "pol"}
            if unknown:
                raise ValueError(f"extra_flags[{i}]: unknown key(s) {sorted(unknown)}; allowed: stand, pol")
            stand = entry["stand"]
            if isinstance(stand, bool) or not isinstance(stand, (int, np.integer)):
                raise ValueError(f"extra_flags[{i}].stand: expected an integer stand id, got {stand!r}")
            pol = entry.get("pol", "both")
            pol = "both" if pol is None else pol
            if not isinstance(pol, str) or pol.lower() not in _POLS:
                raise ValueError(f"extra_flags[{i}].pol: expected 'X', 'Y' or 'both', got {pol!r}")
            try:
                row = self.stand_index(stand)
            except ValueError as e:
                raise ValueError(f"extra_flags[{i}]: {e}") from None
            flags[row, list(_POLS[pol.lower()])] = True
        return StationTable(self.name, self.lat_deg, self.lon_deg, self.elev_m, self.stand_ids.copy(),
                            self.xyz_m.copy(), flags, self.combined_status.copy(), self.cables,
                            self.cable_table)

    # ------------------------------------------------------------------ cable terms
    def _freqs(self, freq_hz) -> np.ndarray:
        f = np.atleast_1d(np.asarray(freq_hz, dtype=np.float64))
        if f.ndim != 1 or f.size == 0 or not np.all(np.isfinite(f)) or np.any(f <= 0):
            raise ValueError(f"freq_hz: expected a 1-D array of positive frequencies in Hz, got {freq_hz!r}")
        return f

    def _cable_terms(self, freq_hz) -> tuple[np.ndarray, np.ndarray]:
        """(delay_s, power_gain), each float64 (nstand, 2, nchan)."""
        f = self._freqs(freq_hz)
        if self.cables is not None:
            # LSL's cable objects are vectorised over frequency; one call per antenna (<= 512).
            d = np.stack([np.broadcast_to(np.asarray(c.delay(f), np.float64), f.shape) for c in self.cables])
            g = np.stack([np.broadcast_to(np.asarray(c.gain(f), np.float64), f.shape) for c in self.cables])
            return d.reshape(self.nstand, 2, f.size), g.reshape(self.nstand, 2, f.size)
        if self.cable_table is None:
            raise ValueError(f"station {self.name!r} has no cable model (rebuilt from a header without "
                             "cable terms); write the header with to_header(freq_hz=...)")
        tf = np.asarray(self.cable_table["freq_hz"], np.float64)
        cols, missing = [], []
        for x in f:
            hit = np.flatnonzero(np.abs(tf - x) <= 1e-3)  # mHz: JSON keeps floats exact anyway
            (cols.append(int(hit[0])) if hit.size else missing.append(float(x)))
        if missing:
            raise ValueError(f"station {self.name!r} (from a header) has cable terms only for its stored "
                             f"{tf.size} frequencies {tf.min():.6g}..{tf.max():.6g} Hz; not for "
                             f"{missing[:4]}{' ...' if len(missing) > 4 else ''}")
        cols = np.array(cols)
        return (np.asarray(self.cable_table["delay_s"], np.float64)[..., cols],
                np.asarray(self.cable_table["gain"], np.float64)[..., cols])

    def cable_delay_s(self, freq_hz) -> np.ndarray:
        """Cable delay tau, float64 seconds, (nstand, 2, nchan) for channel frequencies ``freq_hz`` (Hz)."""
        return self._cable_terms(freq_hz)[0]

    def cable_gain(self, freq_hz) -> np.ndarray:
        """Cable power gain G (P_out = G P_in; < 1), float64 (nstand, 2, nchan)."""
        return self._cable_terms(freq_hz)[1]

    def cable_weights(self, freq_hz) -> np.ndarray:
        """Calibration factor exp(+2 pi i nu tau) / sqrt(G), complex128 (nchan, nstand, 2); 0 where flagged.

        Multiply raw voltages (…, nchan, nstand, 2) by it to remove the cable terms (sigma = +1 data model).
        """
        f = self._freqs(freq_hz)
        d, g = self._cable_terms(f)
        # phase in float64 from the product nu * tau (~20 cycles at 74 MHz): no float32 anywhere
        w = np.exp(2j * np.pi * f * d) / np.sqrt(g)
        w[self.flags] = 0.0
        return np.ascontiguousarray(np.moveaxis(w, -1, 0))

    # ------------------------------------------------------------------ header round trip
    def to_header(self, freq_hz=None) -> dict:
        """A JSON-serialisable dict of this table: the ``station`` entry of an E-field sequence header
        (docs/HEADERS.md): ``name``, ``lat_deg``, ``lon_deg``, ``elev_m``, ``stand_ids``, ``xyz_m``
        (nstand x 3), ``flags`` (nstand x 2), ``combined_status``, ``antenna_order``. With
        ``freq_hz`` (the channel centres), also ``cable_delay_s`` and ``cable_gain`` (nstand x 2 x nchan)
        and ``cable_freq_hz``, so that :meth:`from_header` can answer for those frequencies."""
        hdr = {
            "name": self.name,
            "lat_deg": float(self.lat_deg), "lon_deg": float(self.lon_deg), "elev_m": float(self.elev_m),
            "antenna_order": "antenna k = stand index k//2, pol k%2 (0 = X = N-S, 1 = Y = E-W)",
            "stand_ids": self.stand_ids.tolist(),
            "xyz_m": self.xyz_m.tolist(),
            "flags": self.flags.tolist(),
            "combined_status": self.combined_status.tolist(),
        }
        if freq_hz is not None:
            f = self._freqs(freq_hz)
            d, g = self._cable_terms(f)
            hdr.update(cable_freq_hz=f.tolist(), cable_delay_s=d.tolist(), cable_gain=g.tolist())
        return hdr

    @classmethod
    def from_header(cls, d: Mapping) -> "StationTable":
        """Rebuild a table from :meth:`to_header`'s dict (exact: floats survive JSON unchanged).

        Cable terms are kept only if ``cable_delay_s``, ``cable_gain`` and ``cable_freq_hz`` are all
        present (a calibration block removes the first two once it has applied them).
        """
        need = ("name", "lat_deg", "lon_deg", "elev_m", "stand_ids", "xyz_m", "flags")
        missing = [k for k in need if k not in d]
        if missing:
            raise ValueError(f"station header lacks key(s) {missing}; expected the dict of StationTable.to_header")
        n = len(d["stand_ids"])
        status = d.get("combined_status", np.full((n, 2), -1).tolist())
        table = None
        if all(d.get(k) is not None for k in ("cable_freq_hz", "cable_delay_s", "cable_gain")):
            table = {"freq_hz": np.asarray(d["cable_freq_hz"], np.float64),
                     "delay_s": np.asarray(d["cable_delay_s"], np.float64),
                     "gain": np.asarray(d["cable_gain"], np.float64)}
            nf = table["freq_hz"].size
            for k in ("delay_s", "gain"):
                if table[k].shape != (n, 2, nf):
                    raise ValueError(f"station header cable_{k}: expected shape "
                                     f"{(n, 2, nf)} (nstand, 2, len(cable_freq_hz)), got {table[k].shape}")
        return cls(str(d["name"]), float(d["lat_deg"]), float(d["lon_deg"]), float(d["elev_m"]),
                   np.asarray(d["stand_ids"], np.int64), np.asarray(d["xyz_m"], np.float64),
                   np.asarray(d["flags"], bool), np.asarray(status, np.int64), None, table)


def _from_lsl(station, name: str) -> StationTable:
    ants = list(station.antennas)
    if len(ants) == 0 or len(ants) % 2:
        raise ValueError(f"station {name!r}: LSL lists {len(ants)} antennas; expected a positive even "
                         "number (two polarisations per stand)")
    nstand = len(ants) // 2
    stands = [ants[2 * s].stand for s in range(nstand)]
    for k, a in enumerate(ants):
        # the TBF/LSL order this package relies on; fail loudly if an SSMIF breaks it
        if a.stand.id != stands[k // 2].id or a.pol != k % 2:
            raise ValueError(f"station {name!r}: LSL antenna {k} is stand {a.stand.id} pol {a.pol}; expected "
                             f"stand {stands[k // 2].id} pol {k % 2} (antenna k = stand k//2, pol k%2)")
    status = np.array([a.combined_status for a in ants], dtype=np.int64).reshape(nstand, 2)
    return StationTable(
        name=name,
        lat_deg=math.degrees(float(station.lat)), lon_deg=math.degrees(float(station.long)),
        elev_m=float(station.elev),
        stand_ids=np.array([s.id for s in stands], dtype=np.int64),
        xyz_m=np.array([[s.x, s.y, s.z] for s in stands], dtype=np.float64),
        flags=status != GOOD_STATUS,
        combined_status=status,
        cables=[a.cable for a in ants],
    )


def _cache_file(name_or_path, freq) -> Path | None:
    """Where the station table for these frequencies is cached (None: no LSL version to key it by).

    The key is the LSL version (its shipped station files), the station name or the SSMIF's path,
    size and modification time, and the frequencies' bytes: a change to any of them misses."""
    import hashlib
    from importlib.metadata import PackageNotFoundError, version
    try:
        lsl_version = version("lsl")
    except PackageNotFoundError:
        return None
    h = hashlib.sha1()
    src = str(name_or_path)
    if Path(src).is_file():
        st = os.stat(src)
        src = f"{Path(src).resolve()}:{st.st_size}:{st.st_mtime_ns}"
    for part in (lsl_version, src, np.ascontiguousarray(freq, np.float64).tobytes()):
        h.update(part if isinstance(part, bytes) else part.encode())
    from .offline import lsl_config_dir
    return lsl_config_dir().parent / "stations" / f"{_norm_name(Path(str(name_or_path)).stem)}-{h.hexdigest()[:16]}.npz"


def _load_cached(path) -> StationTable | None:
    try:
        with np.load(path, allow_pickle=False) as z:
            return StationTable(name=str(z["name"]), lat_deg=float(z["lat_deg"]), lon_deg=float(z["lon_deg"]),
                                elev_m=float(z["elev_m"]), stand_ids=z["stand_ids"], xyz_m=z["xyz_m"],
                                flags=z["flags"], combined_status=z["combined_status"],
                                cable_table={"freq_hz": z["freq_hz"], "delay_s": z["delay_s"], "gain": z["gain"]})
    except (OSError, KeyError, ValueError):
        return None     # unreadable or from another layout: rebuilt from LSL and written again


def _save_cached(path, table: StationTable, freq) -> None:
    delay, gain = table._cable_terms(freq)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")
        np.savez(tmp, name=table.name, lat_deg=table.lat_deg, lon_deg=table.lon_deg, elev_m=table.elev_m,
                 stand_ids=table.stand_ids, xyz_m=table.xyz_m, flags=table.flags,
                 combined_status=table.combined_status, freq_hz=np.asarray(freq, np.float64), delay_s=delay,
                 gain=gain)
        os.replace(tmp, path)     # whole files only, also with runs in parallel
    except OSError:
        pass                      # a read-only cache costs the next run LSL's import, nothing else


def load_station(name_or_path, *, extra_flags=None, freq_hz=None, write_cache=True) -> StationTable:
    """Station metadata from LSL.

    Parameters
    ----------
    name_or_path : 'lwasv', 'lwana' or 'lwa1' (case, '-' and '_' ignored; 'lwavl' = 'lwa1'), or the
        path of an SSMIF file (.txt or .dat) parsed by ``lsl.common.stations.parse_ssmif``.
    extra_flags : list of ``{stand: int, pol: 'X' | 'Y' | 'both'}`` (pol optional, default 'both'; stand =
        LSL stand id) or bare stand ids; flagged on top of the status flags. Unknown stands or pols
        raise ValueError.

    freq_hz : the frequencies the caller will ask cable terms for, or None. Given, the table (with
        the cable delays and gains at those frequencies, as LSL's cable model gives them) is cached
        under the user's cache folder and later calls with the same station, LSL version and
        frequencies read that file instead of importing LSL (whose import, through SciPy, takes
        seconds of every run's start-up). The cached table answers cable terms for those frequencies only.
    write_cache : False: a cached table is read where there is one, but LSL's is not written (a caller
        that needs no cable terms, and must not compute them for every channel, still skips LSL's import).

    Requires LSL (``pip install lsl``); :func:`configure_offline` is applied first so that LSL and
    astropy never wait on a network.
    """
    configure_offline()
    cache = None
    if freq_hz is not None and isinstance(name_or_path, (str, os.PathLike)):
        cache = _cache_file(name_or_path, freq_hz)
        table = _load_cached(cache) if cache is not None and cache.is_file() else None
        if table is not None:
            return table.with_flags(extra_flags) if extra_flags else table
    try:
        from lsl.common import stations
    except ImportError as e:  # pragma: no cover - lsl is a declared dependency of the station extra
        raise ImportError("load_station needs the LWA Software Library: pip install lsl "
                          "(tools/install_system_deps.sh installs what it builds against)") from e
    if isinstance(name_or_path, (str, os.PathLike)) and _norm_name(str(name_or_path)) in _ALIASES \
            and not Path(name_or_path).is_file():
        key = _ALIASES[_norm_name(str(name_or_path))]
        table = _from_lsl(getattr(stations, key), key)
    elif isinstance(name_or_path, (str, os.PathLike)):
        path = Path(name_or_path)
        if not path.is_file():
            raise ValueError(f"station {str(name_or_path)!r}: not a known station name "
                             f"({', '.join(STATION_NAMES)}) and no SSMIF file at that path")
        if path.suffix not in (".txt", ".dat"):
            raise ValueError(f"SSMIF file {path}: expected a .txt (text) or .dat (binary) SSMIF, got {path.suffix!r}")
        st = stations.parse_ssmif(str(path))
        table = _from_lsl(st, _norm_name(st.name) or path.stem)
    else:
        raise TypeError(f"load_station: expected a station name or an SSMIF path, got {type(name_or_path).__name__}")
    if cache is not None and write_cache:
        _save_cached(cache, table, table._freqs(freq_hz))
    return table.with_flags(extra_flags) if extra_flags else table


def station_for_capture(station, hint: str, nstand: int, what: str, advice: str) -> StationTable:
    """The station of a capture: ``station`` (a :class:`StationTable`, a name or SSMIF path for
    :func:`load_station`, or None = the capture's own ``hint``), checked to have the capture's
    ``nstand`` stands. ``what`` names the capture in the error ("TBF file", "udp://...: the packets"),
    ``advice`` says what to do about a mismatch."""
    st = load_station(hint) if station is None else station
    if not isinstance(st, StationTable):
        st = load_station(st)
    if st.nstand != nstand:
        raise ValueError(f"{what} carry {nstand} stands but station {st.name!r} has {st.nstand}; {advice}")
    return st

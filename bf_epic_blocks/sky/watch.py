"""A watchlist: named directions whose spectra the imager records at every image, and where they are.

Design
------
A target is a catalogue source (``CygA``), a fixed ICRS position (``{name, ra_deg, dec_deg}``) or a
solar-system body (``{name, body: sun}``, placed by astropy's built-in ephemeris, nothing
downloaded). Each may carry an observing window (``start``/``stop``, UTC) outside which it is not
recorded, and off-source reference directions (``offsets_deg``) that follow it.

* Directions use the catalogue's convention (PHYSICS.md; :func:`.catalogue.icrs_to_lm`): l East,
  m North, through astropy ``AltAz`` without refraction, from :func:`..imaging.pixels.lm_from_azalt`.
  One astropy transform covers every time of a batch (erfa is elementwise), as
  :func:`.catalogue.zenith_pointings` does.
* A body's recorded (ra, dec) is the ICRS direction of its apparent topocentric position: the ICRS
  of its pixel, as :func:`.catalogue.lm_to_icrs` would give it, so that it matches the images' WCS.
  The Moon's parallax (up to ~1 deg) is in it; a geocentric or barycentric position would not be.
* Offsets are reference directions for subtracting the sky around a target: ``[east_deg, north_deg]``
  pairs, great-circle offsets from the target's ICRS position along RA (East) and Dec (North), as
  astropy's ``SkyCoord.spherical_offsets_by`` defines them. They are fixed on the sky for fixed
  targets and move with a body.
* Directions are ordered target by target: a target, then its offsets
  (:attr:`TargetDirections.target_index` maps a direction to its target).
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from ..imaging.pixels import lm_from_azalt
from .catalogue import KNOWN_SOURCES, _iers_offline, _key, as_location

__all__ = ["WATCH_BODIES", "WATCH_KINDS", "WatchTarget", "TargetDirections", "direction_names", "parse_targets",
           "target_lm"]

#: Bodies astropy's built-in ephemeris places (``astropy.coordinates.get_body``), without the Earth
#: and the Earth-Moon barycentre, which are not in a ground station's sky.
WATCH_BODIES = ("sun", "moon", "mercury", "venus", "mars", "jupiter", "saturn", "uranus", "neptune")
WATCH_KINDS = ("catalogue", "icrs", "body")

_ENTRY_KEYS = ("name", "ra_deg", "dec_deg", "body", "start", "stop", "offsets_deg")
_WINDOW_SLACK_S = 1e-6
_NAME = re.compile(r"[^/\s]+")   # an HDF5 group name: no slash; no spaces, as the YAML's names


@dataclass(frozen=True)
class WatchTarget:
    """One watched direction.

    kind : 'catalogue' (ra/dec from :data:`.catalogue.KNOWN_SOURCES`), 'icrs' or 'body'.
    ra_deg, dec_deg : ICRS position, degrees (catalogue and icrs targets; None for a body).
    body : a name of :data:`WATCH_BODIES` (body targets; else None).
    start, stop : astropy Time (UTC) or None: the window the target is recorded in, ends included
        (to a microsecond).
    offsets_deg : ((east_deg, north_deg), ...) reference directions around the target (module doc).
    """
    name: str
    kind: str
    ra_deg: float | None = None
    dec_deg: float | None = None
    body: str | None = None
    start: object = None
    stop: object = None
    offsets_deg: tuple = field(default=())

    @property
    def moving(self) -> bool:
        """Whether the ICRS position changes with time (a solar-system body)."""
        return self.kind == "body"

    @property
    def ndir(self) -> int:
        """Directions of this target: itself and its offsets."""
        return 1 + len(self.offsets_deg)


def _known_text() -> str:
    return (f"catalogue names: {', '.join(KNOWN_SOURCES)}; bodies: {', '.join(WATCH_BODIES)}; "
            "or give {name, ra_deg, dec_deg} or {name, body}")


def _catalogue_name(name: str) -> str | None:
    """The catalogue's spelling of ``name`` ('Cyg A', 'cyga' -> 'CygA'), or None."""
    by_key = {_key(k): k for k in KNOWN_SOURCES}
    return by_key.get(_key(name))


def _time(v, name, what):
    from astropy.time import Time
    if v is None:
        return None
    if isinstance(v, Time):
        if not v.isscalar:
            raise ValueError(f"watch target {name!r}: {what} must be a single time, got shape {v.shape}")
        return v.utc
    try:
        return Time(str(v).strip().rstrip("Z"), scale="utc")
    except Exception as e:
        raise ValueError(f"watch target {name!r}: {what} must be an ISO UTC time or astropy Time, "
                         f"got {v!r} ({str(e).splitlines()[0][:80] if str(e) else type(e).__name__})") from None


def _float(v, name, what, lo, hi):
    if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)):
        raise ValueError(f"watch target {name!r}: {what} must be a number, got {v!r}")
    x = float(v)
    if not (math.isfinite(x) and lo <= x <= hi):
        raise ValueError(f"watch target {name!r}: {what} must be in [{lo:g}, {hi:g}], got {v!r}")
    return x


def _offsets(v, name):
    if v is None:
        return ()
    if not isinstance(v, (list, tuple)):
        raise ValueError(f"watch target {name!r}: offsets_deg must be a list of [east_deg, north_deg] pairs, got {v!r}")
    out = []
    for i, p in enumerate(v):
        if not isinstance(p, (list, tuple)) or len(p) != 2:
            raise ValueError(f"watch target {name!r}: offsets_deg[{i}] must be a pair [east_deg, north_deg], got {p!r}")
        out.append((_float(p[0], name, f"offsets_deg[{i}][0]", -180.0, 180.0),
                    _float(p[1], name, f"offsets_deg[{i}][1]", -180.0, 180.0)))
    return tuple(out)


def _one_target(entry) -> WatchTarget:
    if isinstance(entry, WatchTarget):
        return entry
    if isinstance(entry, str):   # a bare catalogue name takes the catalogue's spelling ('Cyg A' -> 'CygA')
        entry = {"name": _catalogue_name(entry) or entry}
    if not isinstance(entry, Mapping):
        raise ValueError(f"a watch target must be a name or a mapping {{name, ...}}, got {entry!r}")
    unknown = sorted(set(entry) - set(_ENTRY_KEYS))
    if unknown:
        raise ValueError(f"watch target {entry.get('name', entry)!r}: unknown key(s) {unknown}; "
                         f"allowed: {', '.join(_ENTRY_KEYS)}")
    name = entry.get("name")
    if not isinstance(name, str) or not _NAME.fullmatch(name):
        raise ValueError(f"a watch target needs a name without spaces or slashes, got {name!r}")
    has_radec = entry.get("ra_deg") is not None or entry.get("dec_deg") is not None
    body = entry.get("body")
    if has_radec and body is not None:
        raise ValueError(f"watch target {name!r}: give ra_deg/dec_deg or body, not both")
    if has_radec:
        if entry.get("ra_deg") is None or entry.get("dec_deg") is None:
            raise ValueError(f"watch target {name!r}: give both ra_deg and dec_deg")
        kind, ra, dec = "icrs", _float(entry["ra_deg"], name, "ra_deg", 0.0, 360.0), \
            _float(entry["dec_deg"], name, "dec_deg", -90.0, 90.0)
        ra %= 360.0
    elif body is not None:
        if not isinstance(body, str) or body.lower() not in WATCH_BODIES:
            raise ValueError(f"watch target {name!r}: unknown body {body!r}; bodies: {', '.join(WATCH_BODIES)}")
        kind, ra, dec, body = "body", None, None, body.lower()
    else:   # a name alone: the catalogue's, or a body's
        cat = _catalogue_name(name)
        if cat is not None:
            kind, ra, dec = "catalogue", KNOWN_SOURCES[cat].ra_deg, KNOWN_SOURCES[cat].dec_deg
        elif name.lower() in WATCH_BODIES:
            kind, ra, dec, body = "body", None, None, name.lower()
        else:
            raise ValueError(f"unknown watch target {name!r}; {_known_text()}")
    start = _time(entry.get("start"), name, "start")
    stop = _time(entry.get("stop"), name, "stop")
    if start is not None and stop is not None and stop < start:
        raise ValueError(f"watch target {name!r}: window stop {stop.isot} is before start {start.isot}")
    return WatchTarget(name, kind, ra, dec, body, start, stop, _offsets(entry.get("offsets_deg"), name))


def parse_targets(entries) -> list[WatchTarget]:
    """:class:`WatchTarget` objects from YAML-like entries, in order.

    Each entry is a catalogue name (``'CygA'``; 'Cyg A', 'cyga' too) or a body name (``'sun'``), or
    a mapping with ``name`` and one of: nothing else (a catalogue or body name), ``ra_deg`` and
    ``dec_deg`` (ICRS, degrees), ``body`` (one of :data:`WATCH_BODIES`); optional ``start``/``stop``
    (ISO UTC strings or astropy Time) and ``offsets_deg`` (a list of [east_deg, north_deg] pairs).
    A single entry may be given without a list. ValueError, naming the entry and what is allowed,
    for an unknown name or body, a repeated name, or a window that stops before it starts.
    """
    if isinstance(entries, (str, Mapping, WatchTarget)):
        entries = [entries]
    targets = [_one_target(e) for e in entries]
    names = [t.name for t in targets]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"watch target names must be unique; repeated: {', '.join(dup)}")
    return targets


class TargetDirections:
    """Where the watch targets' directions are at each time (:func:`target_lm`).

    lm : (ntime, ndir, 2) float64 direction cosines (l East, m North); NaN below the horizon.
    up : (ntime, ndir) bool, altitude > 0 (as :func:`.catalogue.source_directions` keeps sources).
    in_window : (ntime, ndir) bool, the time within the target's window (True without one).
    alt_deg, az_deg : (ntime, ndir) topocentric altitude and azimuth (North through East), degrees.
    ra_deg, dec_deg : (ntime, ndir) ICRS direction used at each time (constant for fixed targets).
    target_index : (ndir,) int, the target of each direction; names : (ndir,) 'CygA', 'CygA+off1', ...
    targets : the :class:`WatchTarget` list; time : the astropy Time (ntime,).
    """

    def __init__(self, **kw):
        self.__dict__.update(kw)

    @property
    def active(self) -> np.ndarray:
        """(ntime, ndir) bool: above the horizon and within the window, the directions to record."""
        return self.up & self.in_window


def direction_names(targets):
    """(names, target index) of every direction, in :func:`target_lm`'s order: a target ('CygA'), then its
    offsets ('CygA+off1', ...)."""
    names, index = [], []
    for i, t in enumerate(targets):
        names.append(t.name)
        names += [f"{t.name}+off{j + 1}" for j in range(len(t.offsets_deg))]
        index += [i] * t.ndir
    return names, np.asarray(index, np.int64)


def _with_offsets(coord, offsets):
    """(..., 1 + noff) ICRS SkyCoord: ``coord`` (...) and its great-circle offsets (module doc)."""
    import astropy.units as u
    from astropy.coordinates import SkyCoord
    ra = coord.ra.deg[..., None]
    dec = coord.dec.deg[..., None]
    if not offsets:
        return SkyCoord(ra=ra * u.deg, dec=dec * u.deg, frame="icrs")
    off = np.asarray(offsets, np.float64)
    base = SkyCoord(ra=ra * u.deg, dec=dec * u.deg, frame="icrs")
    moved = base.spherical_offsets_by(off[:, 0] * u.deg, off[:, 1] * u.deg)
    return SkyCoord(ra=np.concatenate([ra, moved.ra.deg], axis=-1) * u.deg,
                    dec=np.concatenate([dec, moved.dec.deg], axis=-1) * u.deg, frame="icrs")


def target_lm(targets, times, location) -> TargetDirections:
    """Direction cosines of the watch targets (and their offsets) at each of ``times``.

    targets : :class:`WatchTarget` list or entries for :func:`parse_targets`.
    times : astropy Time, scalar or 1-D (ntime,), or ISO strings (UTC).
    location : astropy EarthLocation or (lon_deg, lat_deg, height_m).

    Fixed directions go through one ICRS -> AltAz transform broadcast over (ntime, ndir); each body
    through one ``get_body`` call over all the times. Returns a :class:`TargetDirections`.
    """
    import astropy.units as u
    from astropy.coordinates import AltAz, SkyCoord, get_body
    from astropy.time import Time

    targets = parse_targets(targets)
    t = times if isinstance(times, Time) else Time(times, scale="utc")
    t = t.reshape(-1) if not t.isscalar else t.reshape(1)
    ntime = t.shape[0]
    loc = as_location(location)
    names, index = direction_names(targets)
    ndir = len(names)
    ra = np.empty((ntime, ndir))
    dec = np.empty((ntime, ndir))
    alt = np.empty((ntime, ndir))
    az = np.empty((ntime, ndir))
    starts = np.cumsum([0] + [tg.ndir for tg in targets])

    with _iers_offline():
        fixed = [i for i, tg in enumerate(targets) if not tg.moving]
        if fixed:
            cols = np.concatenate([np.arange(starts[i], starts[i + 1]) for i in fixed])
            c = [_with_offsets(SkyCoord(ra=targets[i].ra_deg * u.deg, dec=targets[i].dec_deg * u.deg,
                                        frame="icrs"), targets[i].offsets_deg) for i in fixed]
            fra = np.concatenate([x.ra.deg for x in c])
            fdec = np.concatenate([x.dec.deg for x in c])
            aa = SkyCoord(ra=fra[None, :] * u.deg, dec=fdec[None, :] * u.deg, frame="icrs").transform_to(
                AltAz(obstime=t[:, None], location=loc))   # pressure 0: no refraction
            ra[:, cols], dec[:, cols] = fra[None, :], fdec[None, :]
            alt[:, cols], az[:, cols] = aa.alt.deg, aa.az.deg
        frame = AltAz(obstime=t, location=loc)
        for i, tg in enumerate(targets):
            if not tg.moving:
                continue
            cols = np.arange(starts[i], starts[i + 1])
            seen = get_body(tg.body, t, loc).transform_to(frame)
            # the ICRS of the apparent direction (no distance): the ICRS of the body's pixel
            icrs = SkyCoord(az=seen.az, alt=seen.alt, frame=frame).icrs
            c = _with_offsets(icrs, tg.offsets_deg)
            ra[:, cols], dec[:, cols] = c.ra.deg, c.dec.deg
            alt[:, cols[0]], az[:, cols[0]] = seen.alt.deg, seen.az.deg
            if len(cols) > 1:
                aa = c[:, 1:].transform_to(AltAz(obstime=t[:, None], location=loc))
                alt[:, cols[1:]], az[:, cols[1:]] = aa.alt.deg, aa.az.deg

    lm = np.full((ntime, ndir, 2), np.nan)
    up = alt > 0
    if np.any(up):
        lm[up] = lm_from_azalt(az[up], alt[up])
    in_window = np.ones((ntime, ndir), bool)
    for i, tg in enumerate(targets):
        w = np.ones(ntime, bool)
        # ends included to a microsecond: an image time computed as start + k * dt lands on a round
        # window end only to the last bit of astropy's two-double time
        if tg.start is not None:
            w &= (t - tg.start).to_value(u.s) >= -_WINDOW_SLACK_S
        if tg.stop is not None:
            w &= (tg.stop - t).to_value(u.s) >= -_WINDOW_SLACK_S
        in_window[:, starts[i]:starts[i + 1]] = w[:, None]
    return TargetDirections(lm=lm, up=up, in_window=in_window, alt_deg=alt, az_deg=az, ra_deg=ra, dec_deg=dec,
                            target_index=index, names=names, targets=targets, time=t)

"""Sky sources and where they are: the catalogue, and directions with astropy.

* :class:`Source` / :data:`KNOWN_SOURCES` / :func:`resolve_source`: point sources by name (Cyg A,
  Cas A, Tau A, Vir A) or by ICRS, topocentric or (l, m) position, with a power-law spectrum.
* :func:`source_directions`: their direction cosines (l East, m North, n Up; PHYSICS.md) seen from
  a station at a time, through astropy ``AltAz`` (no refraction).
* Time, place and frames for the image writers: :func:`as_time`, :func:`as_location`,
  :func:`zenith_icrs`, :func:`north_angle_deg`, :func:`zenith_pointings` (many times at once),
  :func:`lm_to_icrs`, :func:`icrs_to_lm`.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from ..imaging.pixels import azalt_from_lm, lm_from_azalt

__all__ = ["KNOWN_SOURCES", "SUN", "Source", "SourceDirections", "resolve_source", "resolve_sources",
           "source_directions", "REF_FREQ_HZ", "zenith_icrs", "north_angle_deg", "zenith_pointings", "lm_to_icrs", "icrs_to_lm",
           "as_time", "as_location"]

log = logging.getLogger(__name__)

REF_FREQ_HZ = 74e6


@dataclass(frozen=True)
class Source:
    """A point source. Exactly one position form: ICRS (ra_deg, dec_deg), topocentric (az_deg,
    alt_deg; azimuth North through East), or direction cosines (l, m; above the horizon)."""
    name: str
    flux_jy: float
    spectral_index: float = 0.0
    ref_freq_hz: float = REF_FREQ_HZ
    ra_deg: float | None = None
    dec_deg: float | None = None
    az_deg: float | None = None
    alt_deg: float | None = None
    l: float | None = None
    m: float | None = None
    body: str | None = None

    @property
    def frame(self) -> str:
        """'icrs', 'altaz', 'lm' or 'body' (a solar-system body, placed by astropy's built-in ephemeris)."""
        if self.body is not None:
            return "body"
        return "icrs" if self.ra_deg is not None else ("altaz" if self.az_deg is not None else "lm")

    def flux_at(self, freq_hz) -> np.ndarray:
        """Flux density (Jy) at ``freq_hz`` (power law about ref_freq_hz)."""
        return self.flux_jy * (np.asarray(freq_hz, np.float64) / self.ref_freq_hz) ** self.spectral_index


#: Bright northern A-team sources: ICRS (J2000) positions; 74 MHz flux densities and spectral
#: indices are rough (tens of per cent: Cas A fades ~1%/yr, the spectra curve), for simulation only.
KNOWN_SOURCES: dict[str, Source] = {
    "CygA": Source("CygA", 17000.0, -0.58, ra_deg=299.8681525, dec_deg=40.7339156),
    "CasA": Source("CasA", 17000.0, -0.72, ra_deg=350.8500000, dec_deg=58.8150000),
    "TauA": Source("TauA", 1800.0, -0.27, ra_deg=83.6330833, dec_deg=22.0145000),
    "VirA": Source("VirA", 2100.0, -0.86, ra_deg=187.7059308, dec_deg=12.3911233),
}

#: The Sun, placed at the data's time by astropy's built-in ephemeris. Its flux is the quiet Sun's at
#: 74 MHz (a ~1e6 K corona over a disk ~0.6 deg across: ~1.6e4 Jy); the active Sun is brighter by up
#: to orders of magnitude, so a model with the Sun sets a flux scale good to a factor, not a per cent.
SUN = Source("Sun", 16000.0, 0.0, body="sun")


def _key(name: str) -> str:
    return "".join(ch for ch in name.lower() if ch.isalnum())


_BY_KEY = {_key(k): v for k, v in {**KNOWN_SOURCES, "Sun": SUN}.items()}
_DICT_KEYS = {"name", "flux_jy", "spectral_index", "ref_freq_hz", "ra_deg", "dec_deg", "az_deg",
              "alt_deg", "l", "m"}


def resolve_source(spec) -> Source:
    """A :class:`Source` from a catalogue name ('CygA', 'Cyg A', 'cyga', 'cyg-a'), a Source, or a dict
    ``{name, flux_jy, ra_deg, dec_deg}`` (or ``az_deg, alt_deg`` or ``l, m`` instead of ra/dec;
    optional ``spectral_index`` (default 0), ``ref_freq_hz`` (default 74e6))."""
    if isinstance(spec, Source):
        return spec
    if isinstance(spec, str):
        try:
            return _BY_KEY[_key(spec)]
        except KeyError:
            raise ValueError(f"unknown source {spec!r}; known: {', '.join(KNOWN_SOURCES)}, Sun, or give a dict "
                             "{name, flux_jy, ra_deg, dec_deg}") from None
    if not isinstance(spec, Mapping):
        raise TypeError(f"a source must be a name, a Source or a dict, got {type(spec).__name__}")
    unknown = set(spec) - _DICT_KEYS
    if unknown:
        raise ValueError(f"source {spec.get('name', spec)!r}: unknown key(s) {sorted(unknown)}; "
                         f"allowed: {sorted(_DICT_KEYS)}")
    name = str(spec.get("name", "source"))
    if "flux_jy" not in spec:
        raise ValueError(f"source {name!r}: missing flux_jy")
    forms = [f for f in (("ra_deg", "dec_deg"), ("az_deg", "alt_deg"), ("l", "m")) if any(k in spec for k in f)]
    if len(forms) != 1 or not all(k in spec for k in forms[0]):
        raise ValueError(f"source {name!r}: give exactly one position pair: (ra_deg, dec_deg), "
                         f"(az_deg, alt_deg) or (l, m); got keys {sorted(spec)}")
    vals = {k: float(spec[k]) for k in forms[0]}
    flux = float(spec["flux_jy"])
    if not math.isfinite(flux) or flux < 0:
        raise ValueError(f"source {name!r}: flux_jy must be finite and >= 0, got {spec['flux_jy']!r}")
    if "dec_deg" in vals and not -90 <= vals["dec_deg"] <= 90:
        raise ValueError(f"source {name!r}: dec_deg must be in [-90, 90], got {vals['dec_deg']}")
    if "l" in vals and vals["l"] ** 2 + vals["m"] ** 2 > 1:
        raise ValueError(f"source {name!r}: l^2 + m^2 must be <= 1, got l={vals['l']}, m={vals['m']}")
    return Source(name, flux, float(spec.get("spectral_index", 0.0)),
                  float(spec.get("ref_freq_hz", REF_FREQ_HZ)), **vals)


def resolve_sources(sources) -> list[Source]:
    """:func:`resolve_source` on each entry (a single name/dict/Source is accepted too)."""
    if isinstance(sources, (str, Mapping, Source)):
        sources = [sources]
    return [resolve_source(s) for s in sources]


class SourceDirections(tuple):
    """``(l, m, alt)`` float64 arrays (alt in radians) of the sources above the horizon.

    Unpacks as a 3-tuple; also carries ``az`` (rad, North through East), ``n`` (= sin alt, float64),
    ``sources`` (the kept :class:`Source` objects, same order) and ``dropped`` (names of sources at or
    below the horizon).
    """

    def __new__(cls, l, m, alt, az, n, sources, dropped):
        self = super().__new__(cls, (l, m, alt))
        self.az, self.n, self.sources, self.dropped = az, n, list(sources), list(dropped)
        return self

    @property
    def l(self):
        return self[0]

    @property
    def m(self):
        return self[1]

    @property
    def alt(self):
        return self[2]

    @property
    def names(self) -> list[str]:
        return [s.name for s in self.sources]


def source_directions(sources, time=None, location=None) -> SourceDirections:
    """Direction cosines of ``sources`` seen from ``location`` (astropy EarthLocation) at ``time``.

    ICRS sources go through astropy ``AltAz`` (no refraction); l = cos(alt) sin(az) (East),
    m = cos(alt) cos(az) (North). Sources with alt <= 0 are dropped, listed in ``.dropped`` and logged.
    ``time``/``location`` are needed only for ICRS sources and solar-system bodies (the Sun).
    """
    srcs = resolve_sources(sources)
    moving = [s.name for s in srcs if s.frame in ("icrs", "body")]
    if not moving:
        return _directions(srcs, np.zeros(len(srcs)), np.zeros(len(srcs)))
    if time is None or location is None:
        raise ValueError(f"sources {moving} have ICRS positions or are solar-system bodies: source_directions "
                         "needs time (astropy Time or ISO string) and location (EarthLocation)")
    from astropy.time import Time
    t = time if isinstance(time, Time) else Time(time, scale="utc")
    if not t.isscalar:
        raise ValueError("source_directions: time must be a single instant (the sky is frozen)")
    return source_directions_at(srcs, t.reshape(1), location)[0]


def source_directions_at(sources, times, location) -> list[SourceDirections]:
    """:func:`source_directions` at each of ``times`` (astropy Time, 1-D, or ISO strings): one astropy
    transform for every time (a transform's cost is mostly its fixed part), each time's directions the
    same as :func:`source_directions` gives for it alone. Returns a list, one per time."""
    srcs = resolve_sources(sources)
    from astropy import units as u
    from astropy.coordinates import AltAz, SkyCoord, get_body
    from astropy.time import Time
    t = times if isinstance(times, Time) else Time(times, scale="utc")
    t = t.reshape(-1) if not t.isscalar else t.reshape(1)
    alt = np.zeros((t.shape[0], len(srcs)))
    az = np.zeros_like(alt)
    icrs = [i for i, s in enumerate(srcs) if s.frame == "icrs"]
    bodies = [i for i, s in enumerate(srcs) if s.frame == "body"]
    if (icrs or bodies) and location is None:
        raise ValueError(f"sources {[srcs[i].name for i in icrs + bodies]} have ICRS positions or are "
                         "solar-system bodies: source_directions_at needs a location (EarthLocation)")
    with _iers_offline():
        if icrs:
            c = SkyCoord(ra=np.array([[srcs[i].ra_deg for i in icrs]]) * u.deg,
                         dec=np.array([[srcs[i].dec_deg for i in icrs]]) * u.deg, frame="icrs")
            aa = c.transform_to(AltAz(obstime=t[:, None], location=location))
            alt[:, icrs], az[:, icrs] = aa.alt.to_value(u.rad), aa.az.to_value(u.rad)
        for i in bodies:   # astropy's built-in ephemeris: nothing downloaded
            aa = get_body(srcs[i].body, t, location).transform_to(AltAz(obstime=t, location=location))
            alt[:, i], az[:, i] = aa.alt.to_value(u.rad), aa.az.to_value(u.rad)
    return [_directions(srcs, alt[k].copy(), az[k].copy()) for k in range(t.shape[0])]


def _directions(srcs, alt, az):
    """The SourceDirections of ``srcs`` from their ICRS and body (alt, az) (radians, (nsrc,), filled in
    by the caller; the other frames' entries are set here)."""
    for i, s in enumerate(srcs):
        if s.frame == "altaz":
            alt[i], az[i] = math.radians(s.alt_deg), math.radians(s.az_deg)
    l = np.cos(alt) * np.sin(az)
    m = np.cos(alt) * np.cos(az)
    n = np.sin(alt)
    for i, s in enumerate(srcs):
        if s.frame == "lm":
            rho = math.hypot(s.l, s.m)
            l[i], m[i] = s.l, s.m
            # (1 - rho)(1 + rho) keeps n accurate near the horizon
            n[i] = math.sqrt(max(0.0, (1.0 - rho) * (1.0 + rho)))
            alt[i] = math.atan2(n[i], rho)
            az[i] = math.atan2(s.l, s.m) % (2 * math.pi)
    keep = alt > 0
    dropped = [s.name for s, k in zip(srcs, keep) if not k]
    if dropped:
        log.debug("sources below the horizon dropped: %s", ", ".join(dropped))
    return SourceDirections(l[keep], m[keep], alt[keep], az[keep], n[keep],
                            [s for s, k in zip(srcs, keep) if k], dropped)


def _iers_offline():
    """Context in which astropy uses its bundled IERS tables instead of downloading (offline), read
    from this package's cache of the parsed table (:func:`..station.offline.iers_table`)."""
    from astropy.utils import iers
    from ..station.offline import iers_table
    ctx = iers.conf.set_temp("auto_download", False)
    iers_table()
    return ctx


def as_time(time):
    """An astropy Time (UTC) from a Time, ISO string or datetime."""
    from astropy.time import Time
    if isinstance(time, Time):
        if not time.isscalar:
            raise ValueError(f"expected a single time, got an array of shape {time.shape}")
        return time
    try:
        return Time(time, scale="utc")
    except Exception as e:
        raise ValueError(f"time must be an astropy Time or an ISO UTC string, got {time!r} ({e})") from None


def as_location(location):
    """An astropy EarthLocation from an EarthLocation or (lon_deg, lat_deg, height_m)."""
    import astropy.units as u
    from astropy.coordinates import EarthLocation
    if isinstance(location, EarthLocation):
        return location
    try:
        lon, lat, h = (float(x) for x in location)
    except Exception:
        raise TypeError(f"location must be an astropy EarthLocation or (lon_deg, lat_deg, height_m), "
                        f"got {location!r}") from None
    return EarthLocation.from_geodetic(lon * u.deg, lat * u.deg, h * u.m)


def _altaz_frame(time, location):
    from astropy.coordinates import AltAz
    return AltAz(obstime=as_time(time), location=as_location(location))  # pressure 0: no refraction


def zenith_pointings(times, location):
    """(ra_deg, dec_deg, north_deg) of the local zenith in ICRS at each of ``times`` (an astropy Time,
    scalar or 1-D array, or anything :func:`as_time` takes): arrays shaped like ``times``.

    ``north_deg`` is the position angle (deg, East of ICRS North) of local North (+m) as seen at the
    zenith. One vectorised transform for all the times: the numbers are those of a transform per
    time (erfa is elementwise), so an image series' WCS costs one call per batch, not per image."""
    import astropy.units as u
    from astropy.coordinates import AltAz, SkyCoord
    from astropy.time import Time
    t = times if isinstance(times, Time) else as_time(times)
    scalar = t.isscalar
    t = t.reshape(-1) if not scalar else t.reshape(1)
    n = t.shape[0]
    d = 0.05  # deg: a short step keeps aberration's non-rotation part negligible in the angle
    frame = AltAz(obstime=t, location=as_location(location))   # pressure 0: no refraction
    with _iers_offline():
        c = SkyCoord(az=np.zeros((2, n)) * u.deg, alt=np.array([[90.0] * n, [90.0 - d] * n]) * u.deg,
                     frame=frame).icrs
    ra, dec, north = c.ra.deg[0], c.dec.deg[0], c[0].position_angle(c[1]).deg
    if scalar:
        return float(ra[0]), float(dec[0]), float(north[0])
    return np.asarray(ra, np.float64), np.asarray(dec, np.float64), np.asarray(north, np.float64)


def zenith_icrs(time, location) -> tuple[float, float]:
    """(ra_deg, dec_deg) in ICRS of the local zenith at ``time`` (see :func:`zenith_pointings`)."""
    ra, dec, _ = zenith_pointings(as_time(time), location)
    return ra, dec


def north_angle_deg(time, location) -> float:
    """Position angle (deg, East of ICRS North) of local North (+m) as seen at the zenith."""
    return zenith_pointings(as_time(time), location)[2]


def lm_to_icrs(pixels_lm, time, location):
    """ICRS (ra_deg, dec_deg) arrays for (npix, 2) direction cosines (l East, m North)."""
    import astropy.units as u
    from astropy.coordinates import SkyCoord
    az, alt = azalt_from_lm(np.asarray(pixels_lm, dtype=np.float64).reshape(-1, 2))
    with _iers_offline():
        c = SkyCoord(az=az * u.deg, alt=alt * u.deg, frame=_altaz_frame(time, location)).icrs
    return np.asarray(c.ra.deg), np.asarray(c.dec.deg)


def icrs_to_lm(ra_deg, dec_deg, time, location):
    """Direction cosines (l, m) and altitude (deg) of ICRS positions; l, m are NaN below the horizon.

    Returns (lm (n, 2) float64, alt_deg (n,)).
    """
    import astropy.units as u
    from astropy.coordinates import SkyCoord
    ra = np.atleast_1d(np.asarray(ra_deg, dtype=np.float64))
    dec = np.atleast_1d(np.asarray(dec_deg, dtype=np.float64))
    with _iers_offline():
        aa = SkyCoord(ra=ra * u.deg, dec=dec * u.deg, frame="icrs").transform_to(_altaz_frame(time, location))
    az, alt = np.asarray(aa.az.deg), np.asarray(aa.alt.deg)
    lm = np.full((alt.size, 2), np.nan)
    up = alt >= 0
    if np.any(up):
        lm[up] = lm_from_azalt(az[up], alt[up])
    return lm, alt

"""The LWA station's image database format, OIMS (Orville's ``OrvilleImageDB``): write version 6, read 1-6.

Orville (lwa-project/orville_wideband_imager) writes its all-sky images into ``.oims`` files that the
station's archive, ``OIMS2fits`` and the oarfish classifier read. This module writes and reads that format
from its published layout, so that our images go where the station's tools look; it does not import
Orville (a station's machine need not have it). Everything is little-endian and packed (no padding):

* bytes 0-23: the version string ``OrvilleImageDBv006``, NUL-padded;
* the file header, 132 bytes (``<24s24s24sidiIdd24s``): imager version, station, Stokes names joined by
  commas (nstokes = their count), ngrid, pixel size (degrees), nchan, flags (bit 0: integrations in time
  order), start and stop (MJD UTC of the first start and the last end), compression (``none``);
* per integration: a 140-byte entry header (``<Iddddddd24sddddiiiiii``: sync word 0xC0DECAFE, start MJD,
  length in days, fill fraction, LST in turns, first and last channel's frequency and the spacing in Hz,
  weighting, phase centre RA, Dec, azimuth, altitude in degrees, four ASP settings (-1 unknown), payload
  bytes (-1: raw float32), extended-attribute bytes (-1: none)); then the images, float32
  (nchan, nstokes, ngrid, ngrid); then nchan uint8, non-zero for a flagged channel; then the JSON of the
  extended attributes, where there are any.

Versions 1-5 differ in the headers' sizes and fields (1: no fill, azimuth, altitude; 1-2: no channel
mask; 1-3: no ASP settings; 1-4: no weighting; 1-5: no compression, payload or extended attributes) and
have records of one size; the reader takes them all. Compressed version-6 files (fpzip, zfp) are named
and refused: no library this package depends on decodes them.

Orientation (what ``OIMS2fits`` and LWATV assume): axis 2 of each image runs South to North (m up), the
last axis East to West (RA decreasing, East on the left as the sky is seen from below), the phase centre
(the zenith) at 0-based pixel ((ngrid - 1) / 2, (ngrid - 1) / 2) and pixels ``pixel_size`` = 130 / ngrid
degrees apart in the sine projection. :func:`oims_lm` gives each pixel's (l, m), so that an imager can
image those directions exactly; :func:`from_lm_image` turns an image indexed [m, l] on those pixels into
OIMS's orientation.
"""
from __future__ import annotations

import json
import os
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["OimsWriter", "OimsFormatError", "read_oims", "oims_lm", "from_lm_image", "VERSION", "SYNC_WORD",
           "FLAG_SORTED"]

VERSION = "OrvilleImageDBv006"
SYNC_WORD = 0xC0DECAFE
FLAG_SORTED = 0x0001
_FILE_HDR_V6 = struct.Struct("<24s24s24sidiIdd24s")          # 132 bytes
_FILE_HDR_V1 = struct.Struct("<24s24s24sidiIdd")              # 108 bytes (versions 1-5)
_FILE_FIELDS = ("imager_version", "station", "stokes_params", "ngrid", "pixel_size", "nchan", "flags",
                "start_time", "stop_time", "compression")
#: per version: (entry struct, its field names)
_ENTRY = {
    1: (struct.Struct("<I8d"), ("sync_word", "start_time", "int_len", "lst", "start_freq", "stop_freq",
                                      "bandwidth", "center_ra", "center_dec")),
    2: (struct.Struct("<I11d"), ("sync_word", "start_time", "int_len", "fill", "lst", "start_freq",
                                          "stop_freq", "bandwidth", "center_ra", "center_dec", "center_az",
                                          "center_alt")),
    4: (struct.Struct("<I11d4i"), ("sync_word", "start_time", "int_len", "fill", "lst", "start_freq",
                                              "stop_freq", "bandwidth", "center_ra", "center_dec", "center_az",
                                              "center_alt", "asp_filter", "asp_atten_1", "asp_atten_2",
                                              "asp_atten_3")),
    5: (struct.Struct("<I7d24s4d4i"), ("sync_word", "start_time", "int_len", "fill", "lst", "start_freq",
                                                "stop_freq", "bandwidth", "weighting", "center_ra", "center_dec",
                                                "center_az", "center_alt", "asp_filter", "asp_atten_1",
                                                "asp_atten_2", "asp_atten_3")),
    6: (struct.Struct("<I7d24s4d6i"), ("sync_word", "start_time", "int_len", "fill", "lst",
                                                  "start_freq", "stop_freq", "bandwidth", "weighting", "center_ra",
                                                  "center_dec", "center_az", "center_alt", "asp_filter",
                                                  "asp_atten_1", "asp_atten_2", "asp_atten_3", "payload",
                                                  "extended")),
}
_ENTRY[3] = _ENTRY[2]
#: each version's entry header size in bytes, as the format defines it
ENTRY_BYTES = {1: 68, 2: 92, 3: 92, 4: 108, 5: 132, 6: 140}


class OimsFormatError(ValueError):
    """The bytes are not an OIMS file this module can read (version, sync word, size, compression), or an
    image does not fit the file it is added to."""


def _text(b: bytes) -> str:
    return b.split(b"\0", 1)[0].decode("ascii", "replace")


def _field24(name, value) -> bytes:
    b = str(value).encode("ascii")
    if len(b) > 24:
        raise OimsFormatError(f"OIMS: {name} {value!r} is longer than the 24 bytes the format holds")
    return b


def oims_lm(ngrid: int, pixel_size_deg: float | None = None) -> np.ndarray:
    """(ngrid, ngrid, 2) float64: the (l, m) of each pixel [row, column] of an OIMS image (axis 2 North,
    the last axis West, the zenith at ((ngrid - 1) / 2, (ngrid - 1) / 2), ``pixel_size_deg`` (default
    130 / ngrid, as Orville and OIMS2fits' WCS use) apart in the sine projection, where the offset of
    a direction in degrees is degrees(l) and degrees(m)). Pixels beyond the horizon (l^2 + m^2 >= 1)
    are included; an imager leaves them out."""
    n = int(ngrid)
    if n < 2:
        raise OimsFormatError(f"OIMS: ngrid must be >= 2, got {ngrid!r}")
    cell = np.radians(130.0 / n if pixel_size_deg is None else float(pixel_size_deg))
    k = (np.arange(n) - (n - 1) / 2.0) * cell
    m, minus_l = np.meshgrid(k, k, indexing="ij")
    return np.stack([-minus_l, m], axis=-1)


def from_lm_image(img) -> np.ndarray:
    """An image indexed [..., m, l] (l East increasing, as this package's grids) on the pixels of
    :func:`oims_lm` read as [row, -column], in OIMS's orientation [..., m, West]: the last axis reversed."""
    return np.ascontiguousarray(np.asarray(img)[..., ::-1])


@dataclass
class OimsWriter:
    """Write images into an OIMS file (version 6, uncompressed), one integration at a time.

    path : the file; an existing file is appended to when ``append`` (its header must match: version 6,
        uncompressed, the same station, Stokes, ngrid, pixel size and nchan), else replaced.
    station : the station's name (e.g. ``LWASV``; ASCII, at most 24 bytes). stokes : product names (OIMS2fits
    needs the four ``I,Q,U,V`` or ``XX,XY,YX,YY``). ngrid, nchan : image side and channels.
    pixel_size_deg : default 130 / ngrid (what OIMS2fits' WCS assumes). imager_version : written in the header.

    The header's start, stop and time-order flag are written at :meth:`close` (as Orville's writer does);
    a file whose writer died keeps zeros there and is still read, since readers walk the records.
    """

    path: Path
    station: str
    stokes: tuple
    ngrid: int
    nchan: int
    pixel_size_deg: float | None = None
    imager_version: str = "bf_epic_blocks"
    append: bool = False
    nint: int = field(default=0, init=False)

    def __post_init__(self):
        self.path = Path(self.path)
        self.stokes = tuple(str(s) for s in self.stokes)
        self.ngrid, self.nchan = int(self.ngrid), int(self.nchan)
        if not self.station:
            raise OimsFormatError("OIMS: a station name is required")
        if self.ngrid < 2 or self.nchan < 1 or not self.stokes:
            raise OimsFormatError(f"OIMS: ngrid >= 2, nchan >= 1 and at least one Stokes name are needed, got "
                                  f"ngrid={self.ngrid}, nchan={self.nchan}, stokes={self.stokes}")
        self.pixel_size_deg = 130.0 / self.ngrid if self.pixel_size_deg is None else float(self.pixel_size_deg)
        self._hdr = dict(imager_version=_field24("imager_version", self.imager_version),
                         station=_field24("station", self.station),
                         stokes_params=_field24("stokes", ",".join(self.stokes)), ngrid=self.ngrid,
                         pixel_size=self.pixel_size_deg, nchan=self.nchan, flags=FLAG_SORTED, start_time=0.0,
                         stop_time=0.0, compression=b"none")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.append and self.path.is_file() and self.path.stat().st_size > 24:
            got = read_oims(self.path, data=False)
            h = got["header"]
            want = dict(version=6, station=self.station, stokes_params=",".join(self.stokes), ngrid=self.ngrid,
                        pixel_size=self.pixel_size_deg, nchan=self.nchan, compression="none")
            bad = {k: (h[k], v) for k, v in want.items() if h[k] != v}
            if bad:
                raise OimsFormatError(f"OIMS: cannot append to {self.path}: its header differs ("
                                      + ", ".join(f"{k} {a!r} in the file, {b!r} here" for k, (a, b) in bad.items())
                                      + ")")
            self._hdr.update(flags=h["flags"], start_time=h["start_time"], stop_time=h["stop_time"])
            self.nint = len(got["entries"])
            self._f = open(self.path, "r+b")
            self._f.seek(0, os.SEEK_END)
        else:
            self._f = open(self.path, "wb")
            self._f.write(struct.pack("<24s", VERSION.encode()))
            self._write_header()
            self._f.flush()

    def _write_header(self):
        self._f.seek(24)
        self._f.write(_FILE_HDR_V6.pack(*(self._hdr[k] for k in _FILE_FIELDS)))

    def add(self, data, *, start_mjd: float, int_len_s: float, freq_hz, lst_turns: float = 0.0, fill: float = 1.0,
            center_ra_deg: float = 0.0, center_dec_deg: float = 0.0, center_az_deg: float = 0.0,
            center_alt_deg: float = 90.0, weighting: str = "natural", mask=None, extended=None) -> None:
        """Append one integration.

        data : (nchan, nstokes, ngrid, ngrid) images in OIMS's orientation (:func:`from_lm_image`), Jy or
            the imager's units; written as little-endian float32. start_mjd : its start, MJD UTC.
        int_len_s : its length in seconds (stored in days). freq_hz : (nchan,) channel centres, uniformly
            spaced (the header keeps the first, the last and the spacing). lst_turns : mean local sidereal
            time as a fraction of a turn (0-1). center_* : the phase centre (the zenith for an all-sky image).
        mask : (nchan,) bool, True for a flagged channel (default none). extended : a JSON-serialisable
            mapping stored after the mask (version 6's extended attributes), or None.
        """
        d = np.asarray(data, dtype="<f4")
        want = (self.nchan, len(self.stokes), self.ngrid, self.ngrid)
        if d.shape != want:
            raise OimsFormatError(f"OIMS: images must be (nchan, nstokes, ngrid, ngrid) = {want}, got {d.shape}")
        f = np.asarray(freq_hz, np.float64).reshape(-1)
        if f.size != self.nchan:
            raise OimsFormatError(f"OIMS: {self.nchan} channel frequencies needed, got {f.size}")
        df = float(f[1] - f[0]) if f.size > 1 else 0.0
        if f.size > 2 and not np.allclose(np.diff(f), df, rtol=1e-9, atol=1e-6):
            raise OimsFormatError("OIMS: channel frequencies must be uniformly spaced (first + k x spacing)")
        if not int_len_s > 0:
            raise OimsFormatError(f"OIMS: the integration length must be > 0 s, got {int_len_s!r}")
        m = np.zeros(self.nchan, np.uint8) if mask is None else np.asarray(mask, bool).reshape(-1).astype(np.uint8)
        if m.size != self.nchan:
            raise OimsFormatError(f"OIMS: the channel mask needs {self.nchan} entries, got {m.size}")
        ext = b"" if extended is None else json.dumps(extended).encode()
        int_len = float(int_len_s) / 86400.0
        self._f.write(_ENTRY[6][0].pack(SYNC_WORD, float(start_mjd), int_len, float(fill), float(lst_turns),
                                        float(f[0]), float(f[-1]), df, _field24("weighting", weighting),
                                        float(center_ra_deg), float(center_dec_deg), float(center_az_deg),
                                        float(center_alt_deg), -1, -1, -1, -1, -1, len(ext) if ext else -1))
        self._f.write(d.tobytes())
        self._f.write(m.tobytes())
        self._f.write(ext)
        self._f.flush()
        h = self._hdr
        end = float(start_mjd) + int_len
        if self.nint and end <= h["stop_time"]:
            h["flags"] &= ~FLAG_SORTED
        h["start_time"] = float(start_mjd) if not self.nint else min(h["start_time"], float(start_mjd))
        h["stop_time"] = max(h["stop_time"], end)
        self.nint += 1

    def close(self) -> None:
        """Write the header's start, stop and flags, and close (again: nothing)."""
        if getattr(self, "_f", None) is None:
            return
        self._write_header()
        self._f.close()
        self._f = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def read_oims(path, *, data: bool = True) -> dict:
    """Read an OIMS file of any version 1-6 (uncompressed).

    Returns ``{'header': dict, 'entries': [dict, ...], 'data': float32 (nint, nchan, nstokes, ngrid, ngrid)
    or None, 'mask': bool (nint, nchan)}``. The header has ``version`` (1-6), ``station``, ``stokes_params``
    (a string) and ``stokes`` (its names), ``ngrid``, ``pixel_size`` (degrees), ``nchan``, ``flags``,
    ``start_time``/``stop_time`` (MJD UTC) and ``compression``; each entry its header's fields (times in MJD
    and days, frequencies in Hz, angles in degrees; fields a version lacks are absent) and
    ``extended_attributes`` (a dict, version 6). Raises :class:`OimsFormatError` naming what is wrong.

    The file is memory-mapped, not read: an hour of whole-band images is tens of GB. Where the records
    are evenly spaced (no extended attributes, as most files), ``data`` is a read-only view of the map,
    read from disk as it is indexed; otherwise the images are copied into one array.
    """
    p = Path(path)
    size = p.stat().st_size
    if size < 24:
        raise OimsFormatError(f"{p}: {size} bytes: too short for an OIMS file (24-byte version string)")
    raw = np.memmap(p, np.uint8, mode="r")
    name = bytes(raw[:24]).rstrip(b"\0").decode("ascii", "replace")
    if not name.startswith("OrvilleImageDBv") or name[-3:] not in {f"{v:03d}" for v in range(1, 7)}:
        raise OimsFormatError(f"{p}: not an OIMS file (version string {name!r}, expected OrvilleImageDBv001..v006)")
    version = int(name[-3:])
    fh = _FILE_HDR_V6 if version == 6 else _FILE_HDR_V1
    if len(raw) < 24 + fh.size:
        raise OimsFormatError(f"{p}: {len(raw)} bytes: shorter than the version-{version} file header")
    vals = fh.unpack_from(raw, 24)
    h = dict(zip(_FILE_FIELDS, vals))
    for k in ("imager_version", "station", "stokes_params", "compression"):
        if k in h:
            h[k] = _text(h[k])
    h.setdefault("compression", "none")
    h["version"] = version
    h["stokes"] = [s for s in h["stokes_params"].split(",") if s]
    comp = h["compression"].lower()
    if comp != "none":
        raise OimsFormatError(f"{p}: compressed with {h['compression']!r}; only uncompressed OIMS files are read "
                              "here (Orville's OrvilleImageDB with fpzip or zfpy reads these)")
    nchan, nst, ng = int(h["nchan"]), len(h["stokes"]), int(h["ngrid"])
    es, names = _ENTRY[version]
    img_bytes = 4 * nchan * nst * ng * ng
    mask_bytes = nchan if version >= 3 else 0
    pos = 24 + fh.size
    entries, offsets = [], []
    while pos < len(raw):
        if pos + es.size > len(raw):
            raise OimsFormatError(f"{p}: {len(raw) - pos} bytes at offset {pos}: a truncated integration header")
        e = dict(zip(names, es.unpack_from(raw, pos)))
        if e["sync_word"] != SYNC_WORD:
            raise OimsFormatError(f"{p}: integration {len(entries)} at offset {pos}: sync word "
                                  f"{e['sync_word']:#010x}, expected {SYNC_WORD:#010x}")
        if "weighting" in e:
            e["weighting"] = _text(e["weighting"])
        payload = e.get("payload", -1)
        if payload > 0:
            raise OimsFormatError(f"{p}: integration {len(entries)} holds a compressed payload")
        body = pos + es.size
        ext_len = e.get("extended", -1)
        end = body + img_bytes + mask_bytes + max(ext_len, 0)
        if end > len(raw):
            raise OimsFormatError(f"{p}: integration {len(entries)} at offset {pos} needs {end - pos} bytes, "
                                  f"{len(raw) - pos} are left: the file is truncated")
        if ext_len > 0:
            e["extended_attributes"] = json.loads(bytes(raw[body + img_bytes + mask_bytes:end]).decode())
        offsets.append(body)
        entries.append(e)
        pos = end
    out = {"header": h, "entries": entries, "data": None,
           "mask": np.zeros((len(entries), nchan), bool)}
    for i, body in enumerate(offsets):
        if mask_bytes:
            out["mask"][i] = np.frombuffer(raw, np.uint8, nchan, body + img_bytes) != 0
    if data:
        shape = (nchan, nst, ng, ng)
        steps = set(np.diff(offsets).tolist())
        if not offsets:
            out["data"] = np.zeros((0,) + shape, np.float32)
        elif len(steps) <= 1:                                 # evenly spaced: a view of the map
            inner = (nst * ng * ng * 4, ng * ng * 4, ng * 4, 4)
            out["data"] = np.ndarray((len(offsets),) + shape, "<f4", buffer=raw, offset=offsets[0],
                                     strides=(steps.pop() if steps else img_bytes,) + inner)
        else:
            out["data"] = np.stack([np.frombuffer(raw, "<f4", img_bytes // 4, b).reshape(shape) for b in offsets])
    return out

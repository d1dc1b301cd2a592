"""Reading and writing the sequence headers our blocks share (documented in docs/HEADERS.md).

Pure functions on header dicts: the blocks call them from ``on_sequence`` so that a bad header
fails there, before any data moves, with a TypeError/ValueError saying what was expected.
"""
from __future__ import annotations

import numpy as np

from ..conventions import FS_HZ
from ..runtime.header import plain_copy

EFIELD_LABELS = ("time", "freq", "station", "pol")
EFIELD_DTYPES = ("ci4", "ci8", "ci16", "cf32", "cf64")


def _tensor(hdr, who):
    t = hdr.get("_tensor")
    if not isinstance(t, dict) or "shape" not in t or "dtype" not in t:
        raise TypeError(f"{who}: the header has no valid '_tensor' (with 'dtype' and 'shape')")
    return t


def efield_layout(hdr, who="block"):
    """Validate an E-field header; returns a dict with nchan, nstand, npol, dtype, freq_hz (nchan,),
    dt_s, t0_s, ticks_per_frame, time_tag, xyz_m (nstand, 3) float64 and flags (nstand, npol) bool.

    Expected: labels ['time', 'freq', 'station', 'pol'] (in that order), shape [-1, nchan, nstand, npol],
    dtype one of ci4/ci8/ci16/cf32/cf64, channel frequencies in ``freq_hz`` or the 'freq' scale
    [first centre Hz, step Hz], the station table in ``station`` (``xyz_m``, optional ``flags``).
    """
    t = _tensor(hdr, who)
    labels = list(t.get("labels") or [])
    if labels != list(EFIELD_LABELS):
        raise ValueError(f"{who}: expected E-field axes labelled {list(EFIELD_LABELS)}, got {labels or 'no labels'}")
    shape = list(t["shape"])
    if len(shape) != 4 or shape[0] != -1:
        raise ValueError(f"{who}: expected _tensor shape [-1, nchan, nstation, npol], got {shape}")
    dtype = t["dtype"]
    if dtype not in EFIELD_DTYPES:
        raise TypeError(f"{who}: E-field dtype must be one of {EFIELD_DTYPES}, got {dtype!r}")
    _, nchan, nstand, npol = shape
    if npol not in (1, 2):
        raise ValueError(f"{who}: npol must be 1 or 2, got {npol}")
    scales = list(t.get("scales") or [None] * 4)
    if "freq_hz" in hdr:
        freq = np.asarray(hdr["freq_hz"], dtype=np.float64)
    elif scales[1] is not None:
        f0, df = scales[1]
        freq = f0 + df * np.arange(nchan)
    else:
        raise ValueError(f"{who}: no channel frequencies: give header 'freq_hz' or _tensor scales[1] = [f0_hz, df_hz]")
    if freq.shape != (nchan,) or not np.all(freq > 0):
        raise ValueError(f"{who}: channel frequencies must be {nchan} positive values in Hz, got {freq.shape}")
    t0_s = float(scales[0][0]) if scales[0] is not None else int(hdr.get("time_tag", 0)) / FS_HZ
    if scales[0] is not None:
        dt_s = float(scales[0][1])
    elif nchan > 1:
        dt_s = 1.0 / abs(float(freq[1] - freq[0]))
    elif "chan_bw_hz" in hdr:
        dt_s = 1.0 / float(hdr["chan_bw_hz"])
    else:
        raise ValueError(f"{who}: cannot tell the sample time: give _tensor scales[0] = [t0_s, dt_s]")
    st = hdr.get("station")
    if not isinstance(st, dict) or "xyz_m" not in st:
        raise ValueError(f"{who}: the header needs a 'station' table with 'xyz_m' (nstation x 3 metres ENU)")
    xyz = np.asarray(st["xyz_m"], dtype=np.float64)
    if xyz.shape != (nstand, 3):
        raise ValueError(f"{who}: station xyz_m is shaped {xyz.shape}; the data have {nstand} stations, expected ({nstand}, 3)")
    flags = np.zeros((nstand, npol), bool)
    if st.get("flags") is not None:
        f = np.asarray(st["flags"], dtype=bool)
        if f.ndim == 1:
            f = f[:, None]
        try:
            flags = np.broadcast_to(f, (nstand, npol)).copy()
        except ValueError:
            raise ValueError(f"{who}: station flags shaped {f.shape} do not fit ({nstand}, {npol})") from None
    return {"nchan": nchan, "nstand": nstand, "npol": npol, "dtype": dtype, "freq_hz": freq,
            "dt_s": dt_s, "t0_s": t0_s, "ticks_per_frame": int(round(dt_s * FS_HZ)), "time_tag": int(hdr.get("time_tag", 0)),
            "xyz_m": xyz, "flags": flags}


def efield_header(name, time_tag, freq_hz, dt_s, station, dtype="ci4", npol=2, t0_s=None, **extra):
    """A valid E-field sequence header (for sources and tests).

    station : dict with at least ``xyz_m`` (nstand, 3); optional ``flags``, ``name``, location keys,
    ``cable_delay_s``/``cable_gain`` (nstand, npol, nchan).
    """
    freq = np.asarray(freq_hz, dtype=np.float64)
    nstand = len(station["xyz_m"])
    df = float(freq[1] - freq[0]) if len(freq) > 1 else 1.0 / dt_s
    t0 = float(time_tag) / FS_HZ if t0_s is None else float(t0_s)
    hdr = {
        "name": name,
        "time_tag": int(time_tag),
        "_tensor": {"dtype": dtype, "shape": [-1, len(freq), nstand, npol],
                    "labels": list(EFIELD_LABELS), "scales": [[t0, float(dt_s)], [float(freq[0]), df], None, None],
                    "units": ["s", "Hz", None, None]},
        "freq_hz": [float(v) for v in freq],
        "station": _jsonable(station),
    }
    hdr.update(_jsonable(extra))
    return hdr


def image_header(name, time_tag, freq_hz, dt_s, grid, station, products=("I",)):
    """An image sequence header as DFTImagerBlock writes it (docs/HEADERS.md), for feeding the image
    blocks (search, integrator, writers) without an imager.

    Images (time, freq, pol, m, l) float32 on ``grid`` (an :class:`~bf_epic_blocks.imaging.LMGrid`),
    ``freq_hz`` (nchan,) Hz, one image per ``dt_s`` seconds from ``time_tag`` (ticks of
    :data:`~bf_epic_blocks.conventions.FS_HZ`); ``station`` a dict with ``name`` and the location keys
    ``lat_deg``, ``lon_deg``, ``elev_m``; ``products`` the pol axis' names.
    """
    freq = [float(f) for f in np.asarray(freq_hz, dtype=np.float64)]
    size, ax0 = grid.size, float(grid.axis[0])
    df = freq[1] - freq[0] if len(freq) > 1 else 0.0
    return {"name": name, "time_tag": int(time_tag),
            "_tensor": {"dtype": "f32", "shape": [-1, len(freq), len(products), size, size],
                        "labels": ["time", "freq", "pol", "m", "l"],
                        "scales": [[time_tag / FS_HZ, dt_s], [freq[0], df], None, [ax0, grid.cell], [ax0, grid.cell]]},
            "freq_hz": freq, "pol_products": list(products),
            "pixels": {"kind": "grid", "size": size, "cell": grid.cell, "npix_imaged": grid.npix},
            "imager": {"kind": "dft", "method": "direct", "integration_ticks": int(round(dt_s * FS_HZ))},
            "station": _jsonable(station)}


_PLAIN = {float, int, str, bool, type(None)}


def _jsonable(obj):
    """``obj`` with NumPy arrays and scalars made Python lists and scalars (tuples become lists).

    Lists of plain scalars are copied without a per-item call: a station's cable terms for 132
    channels are 135,000 floats, which the per-item walk took 150 ms of a live stream's first packet
    to check (20 ms now; 2 cores)."""
    t = type(obj)
    if t in _PLAIN:
        return obj
    if t is dict:
        return {k: _jsonable(v) for k, v in obj.items()}
    if t is list or t is tuple:
        if all(type(v) in _PLAIN for v in obj):
            return list(obj)
        return [_jsonable(v) for v in obj]
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist() if obj.dtype.kind in "biuf" else _jsonable(obj.tolist())
    if isinstance(obj, (np.bool_,)):
        return bool(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.floating):
        return float(obj)
    return obj


def derived_header(hdr):
    """A deep copy of ``hdr`` for an output sequence (headers must never be shared between rings)."""
    return plain_copy(hdr)


#: station keys that describe voltages channel by channel: an imager's output leaves them behind
VOLTAGE_STATION_KEYS = ("cable_delay_s", "cable_gain")


def derived_image_header(hdr):
    """:func:`derived_header` for an imager's output: the same, without ``station.cable_delay_s`` /
    ``cable_gain`` (nstation x npol x nchan). Nothing after an imager can apply cable terms (the imager
    folded them in, or they were not asked for), and at a whole band's 784 channels they are 16 MB of
    JSON that every later ring copied and checked (several seconds of a run's start, holding the
    interpreter lock)."""
    st = hdr.get("station")
    if isinstance(st, dict) and any(k in st for k in VOLTAGE_STATION_KEYS):
        hdr = {**hdr, "station": {k: v for k, v in st.items() if k not in VOLTAGE_STATION_KEYS}}
    return derived_header(hdr)


def image_layout(hdr, who="block"):
    """Validate an image header written by the imagers (docs/HEADERS.md); returns a dict with
    ``kind`` ('grid' or 'list'), ``grid`` (LMGrid of the imaged pixels, or None), ``lm`` (npix, 2) of the imaged pixels,
    ``pixel_index`` (npix,) flat indices into the frame's pixel axes (N*N for grids), nchan, nprod,
    products, freq_hz (nchan,), t0_s, dt_s (seconds per image), time_tag, integration_ticks,
    frame_shape (the frame's axes after time).
    """
    from ..imaging.pixels import LMGrid, lm_grid
    t = _tensor(hdr, who)
    labels = list(t.get("labels") or [])
    shape = list(t["shape"])
    if labels == ["time", "freq", "pol", "m", "l"] and len(shape) == 5 and shape[0] == -1:
        pix = hdr.get("pixels") or {}
        if pix.get("kind") != "grid" or "size" not in pix:
            raise ValueError(f"{who}: a gridded image header needs pixels = {{kind: grid, size, cell}}, got {pix!r}")
        grid = lm_grid(int(pix["size"]), cell=pix.get("cell"))
        if shape[3:] != [grid.size, grid.size]:
            raise ValueError(f"{who}: image shape {shape} does not match the {grid.size}x{grid.size} grid")
        kind, lm, index = "grid", grid.lm, np.flatnonzero(grid.mask)
        if pix.get("index") is not None:
            # only some of the pixels above the horizon imaged (a minimum elevation; one GPU's part)
            sub = np.asarray(pix["index"], dtype=np.int64).ravel()
            pos = np.searchsorted(index, sub)
            if sub.size == 0 or np.any(pos >= index.size) or np.any(index[np.minimum(pos, index.size - 1)] != sub) \
                    or np.any(np.diff(sub) <= 0):
                raise ValueError(f"{who}: header pixels.index must be increasing flat indices of pixels above the "
                                 f"horizon of the {grid.size}x{grid.size} grid")
            lm, index = lm[pos], sub
            mask = np.zeros_like(grid.mask)
            mask.flat[sub] = True
            grid = LMGrid(size=grid.size, cell=grid.cell, lm=lm, mask=mask)
    elif labels == ["time", "freq", "pol", "pixel"] and len(shape) == 4 and shape[0] == -1:
        grid = None
        lm = np.asarray((hdr.get("pixels") or {}).get("lm"), dtype=np.float64)
        if lm.shape != (shape[3], 2):
            raise ValueError(f"{who}: header pixels.lm must be ({shape[3]}, 2), got {lm.shape}")
        kind, index = "list", np.arange(shape[3])
    else:
        raise ValueError(f"{who}: expected an imager's output, labels ['time','freq','pol','m','l'] or "
                         f"['time','freq','pol','pixel'] with shape [-1, ...]; got labels {labels}, shape {shape}")
    if t["dtype"] not in ("f16", "f32", "f64"):
        raise TypeError(f"{who}: images must be real floats (f32), got dtype {t['dtype']!r}")
    nchan, nprod = int(shape[1]), int(shape[2])
    scales = list(t.get("scales") or [None] * len(shape))
    if "freq_hz" in hdr:
        freq = np.asarray(hdr["freq_hz"], dtype=np.float64)
    elif scales[1] is not None:
        freq = scales[1][0] + scales[1][1] * np.arange(nchan)
    else:
        raise ValueError(f"{who}: no channel frequencies: give header 'freq_hz' or _tensor scales[1]")
    if freq.shape != (nchan,):
        raise ValueError(f"{who}: {nchan} channels but freq_hz has shape {freq.shape}")
    products = list(hdr.get("pol_products") or [f"P{i}" for i in range(nprod)])
    if len(products) != nprod:
        raise ValueError(f"{who}: pol_products {products} do not match the {nprod} products of the data")
    imager = hdr.get("imager") or {}
    if scales[0] is None:
        raise ValueError(f"{who}: no time axis scale: give _tensor scales[0] = [t0_s, seconds per image]")
    t0_s, dt_s = float(scales[0][0]), float(scales[0][1])
    ticks = int(imager.get("integration_ticks") or round(dt_s * FS_HZ))
    return {"kind": kind, "grid": grid, "lm": lm, "pixel_index": index, "nchan": nchan, "nprod": nprod,
            "products": products, "freq_hz": freq, "t0_s": t0_s, "dt_s": dt_s,
            "time_tag": int(hdr.get("time_tag", 0)), "integration_ticks": ticks, "frame_shape": shape[1:]}


def grid_pixels_header(size, cell, mask):
    """The image header's ``pixels`` for images on a ``size`` x ``size`` l, m grid of step ``cell`` of which
    the pixels where ``mask`` (N, N) holds are imaged: kind, size, cell, npix_imaged, and ``index`` (their
    flat indices, increasing) where they are not all the pixels above the horizon (a minimum elevation,
    or one part of a pixel split), so that readers (:func:`image_layout`) take exactly the pixels that
    hold values."""
    from ..imaging.pixels import lm_grid
    mask = np.asarray(mask, bool)
    out = {"kind": "grid", "size": int(size), "cell": float(cell), "npix_imaged": int(mask.sum())}
    if not np.array_equal(mask, lm_grid(int(size), cell=cell).mask):
        out["index"] = np.flatnonzero(mask).tolist()
    return out


def station_location(hdr):
    """astropy EarthLocation of the header's station (``station.lat_deg/lon_deg/elev_m``), or None."""
    st = hdr.get("station") or {}
    if "lat_deg" not in st or "lon_deg" not in st:
        return None
    from astropy.coordinates import EarthLocation
    return EarthLocation.from_geodetic(st["lon_deg"], st["lat_deg"], st.get("elev_m", 0.0))

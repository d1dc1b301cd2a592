"""TBF reader: real LWA-SV (ADP) and LWA-NA (NDP) files, hand-decoded bytes, corrupted copies."""
import struct
import warnings

import numpy as np
import pytest

from bf_epic_blocks.io.tbf import (TBFError, TBFWarning, iter_tbf_gulps, pack_ci4, read_tbf, scan_tbf,
                                   time_tag_to_time, unpack_ci4)
from lwa_data import NA, SV

needs_sv = pytest.mark.skipif(not SV.is_file(), reason=f"real LWA-SV TBF file not found at {SV} "
                                                      "(set BF_EPIC_DATA to the folder holding it)")
needs_na = pytest.mark.skipif(not NA.is_file(), reason=f"real LWA-NA TBF file not found at {NA} "
                                                      "(set BF_EPIC_DATA to the folder holding it)")
SV_FRAME = 24 + 12 * 256 * 2   # 6168
NA_FRAME = 24 + 12 * 64 * 2    # 1560


def hand_decode(raw: bytes, frame_offset: int, nstand: int, c: int, s: int, p: int) -> complex:
    """Decode one sample straight from the bytes: payload index (c * nstand + s) * 2 + p."""
    b = raw[frame_offset + 24 + (c * nstand + s) * 2 + p]
    hi, lo = b >> 4, b & 0xF
    re = hi - 16 if hi > 7 else hi
    im = lo - 16 if lo > 7 else lo
    return complex(re, im)


def read_quiet(path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", TBFWarning)
        return read_tbf(path)


# ------------------------------------------------------------------------------------- real files
@pytest.mark.real_data
@needs_sv
def test_lwasv_shape_freq_time_and_truncation_warning():
    with pytest.warns(TBFWarning, match="5160 trailing bytes"):
        d = read_tbf(SV)
    assert d.data.dtype == np.uint8
    assert d.data.shape == (1, 60, 256, 2)
    np.testing.assert_array_equal(d.channels, np.arange(2348, 2408))
    assert d.chan_bw_hz == 25e3
    assert d.freq_hz[0] == pytest.approx(58.700e6) and d.freq_hz[-1] == pytest.approx(60.175e6)
    assert d.station_hint == "lwasv" and d.frame_id == 1 and d.nstand == 256
    assert d.sample_ticks == 7840
    assert d.stats["frames_read"] == 5 and d.stats["frames_missing"] == 0
    assert d.stats["truncated_bytes"] == 36000 - 5 * SV_FRAME
    assert d.times[0].isot == "2015-11-13T00:59:22.000"


@pytest.mark.real_data
@needs_na
def test_lwana_shape_freq_time():
    d = read_tbf(NA)
    assert d.data.shape == (1, 84, 64, 2)
    np.testing.assert_array_equal(d.channels, np.r_[640:688, 2176:2212])
    assert d.chan_bw_hz == 196e6 / 8192 == 23925.78125
    np.testing.assert_allclose(d.freq_hz, d.channels * 23925.78125)
    assert d.station_hint == "lwana" and d.frame_id == 5 and d.nstand == 64
    assert d.stats == dict(frames_read=7, frames_expected=7, frames_missing=0, frames_duplicate=0,
                           time_gaps=0, truncated_bytes=0)
    from astropy.time import Time
    dt = (d.times[0] - Time("2024-04-29T21:55:30", scale="utc")).sec
    assert abs(dt) < 1e-3   # the tag is 2.6 us before the second


@pytest.mark.real_data
@needs_sv
@needs_na
def test_samples_match_hand_decoding():
    for path, nstand, cases in [
        # (frame index in file, channel within frame, stand, pol)
        (SV, 256, [(0, 0, 0, 0), (2, 5, 100, 1), (4, 11, 255, 1), (3, 7, 17, 0)]),
        (NA, 64, [(0, 0, 0, 0), (1, 3, 10, 1), (3, 11, 63, 0), (6, 6, 31, 1)]),
    ]:
        raw = path.read_bytes()
        d = read_quiet(path)
        x = d.unpack(np.complex128)
        fb = 24 + 12 * nstand * 2
        for f, c, s, p in cases:
            first_chan = struct.unpack(">h", raw[f * fb + 12: f * fb + 14])[0]
            k = int(np.flatnonzero(d.channels == first_chan + c)[0])
            assert x[0, k, s, p] == hand_decode(raw, f * fb, nstand, c, s, p)
        # whole-frame check against a plain Python decode of one frame (independent of the LUT)
        f = 1
        first_chan = struct.unpack(">h", raw[f * fb + 12: f * fb + 14])[0]
        k0 = int(np.flatnonzero(d.channels == first_chan)[0])
        ref = np.array([[[hand_decode(raw, f * fb, nstand, c, s, p) for p in range(2)]
                         for s in range(nstand)] for c in range(12)])
        np.testing.assert_array_equal(x[0, k0:k0 + 12], ref)


def test_ci4_roundtrip_all_values():
    vals = np.array([complex(r, i) for r in range(-8, 8) for i in range(-8, 8)])
    packed = pack_ci4(vals)
    assert packed.dtype == np.uint8 and len(np.unique(packed)) == 256
    np.testing.assert_array_equal(unpack_ci4(packed, np.complex128), vals)
    assert pack_ci4(np.array([3 - 2j]))[0] == 0x3E   # high nibble real 3, low nibble imag -2 = 0xE
    np.testing.assert_array_equal(unpack_ci4(np.array([0x3E], np.uint8), "int8"), [[3, -2]])
    with pytest.raises(ValueError, match="-8..7"):
        pack_ci4(np.array([8 + 0j]))
    with pytest.raises(TypeError, match="uint8"):
        unpack_ci4(np.array([1, 2], dtype=np.int32))


@pytest.mark.real_data
@pytest.mark.parametrize("name", ["lwasv", "lwana"])
def test_lsl_antenna_order_matches_tbf_axes(name):
    """antenna k = stand index k // 2, pol k % 2 -- LSL's order and the (nstand, 2) axes of the reader."""
    from bf_epic_blocks.station.offline import configure_offline
    configure_offline()   # before lsl is imported: LSL reads its config folder at import
    pytest.importorskip("lsl")
    from lsl.common import stations
    ants = getattr(stations, name).antennas
    path = SV if name == "lwasv" else NA
    if not path.is_file():
        pytest.skip(f"TBF file not found at {path}")
    d = read_quiet(path)
    assert 2 * d.nstand == len(ants)
    for k, a in enumerate(ants):
        assert a.stand is ants[2 * (k // 2)].stand and a.pol == k % 2
    flat = d.data.reshape(d.ntime, d.nchan, 2 * d.nstand)
    for k in (0, 1, 2, 3, 2 * d.nstand - 1):
        np.testing.assert_array_equal(flat[..., k], d.data[..., k // 2, k % 2])


def test_time_tag_conversion_keeps_precision():
    tt = np.array([0, 196_000_000 * 1_700_000_000 + 7840], dtype=np.int64)
    t = time_tag_to_time(tt)
    assert t[0].isot == "1970-01-01T00:00:00.000"
    assert ((t[1] - time_tag_to_time(196_000_000 * 1_700_000_000)).sec) == pytest.approx(40e-6, abs=1e-9)


# ------------------------------------------------------------------------------- corrupted copies
def _frames(raw: bytes, fb: int):
    return [raw[i:i + fb] for i in range(0, len(raw) - len(raw) % fb, fb)]


def _with_time(frame: bytes, dt_ticks: int) -> bytes:
    tt = struct.unpack(">q", frame[16:24])[0] + dt_ticks
    return frame[:16] + struct.pack(">q", tt) + frame[24:]


def _patch(frame: bytes, offset: int, fmt: str, value) -> bytes:
    n = struct.calcsize(fmt)
    return frame[:offset] + struct.pack(fmt, value) + frame[offset + n:]


@pytest.mark.real_data
@needs_na
def test_bad_sync_word_names_byte_offset(tmp_path):
    frames = _frames(NA.read_bytes(), NA_FRAME)
    frames[3] = b"\x00\x11\x22\x33" + frames[3][4:]
    p = tmp_path / "badsync.dat"
    p.write_bytes(b"".join(frames))
    with pytest.raises(TBFError, match=rf"byte offset {3 * NA_FRAME} \(frame 3\): bad sync word 0x00112233") as e:
        read_tbf(p)
    assert e.value.offset == 3 * NA_FRAME and isinstance(e.value, ValueError)


@pytest.mark.real_data
@needs_na
@pytest.mark.parametrize("field,fmt,value,what", [
    (14, ">h", 32, "stand count"),
    (4, ">B", 1, "frame id"),
    (12, ">h", 641, "not aligned"),
    (12, ">h", -12, "negative"),
])
def test_inconsistent_frame_raises_with_offset(tmp_path, field, fmt, value, what):
    frames = _frames(NA.read_bytes(), NA_FRAME)
    frames[5] = _patch(frames[5], field, fmt, value)
    p = tmp_path / "bad.dat"
    p.write_bytes(b"".join(frames))
    with pytest.raises(TBFError, match=rf"byte offset {5 * NA_FRAME} \(frame 5\): .*{what}") as e:
        read_tbf(p)
    assert e.value.offset == 5 * NA_FRAME


def test_not_a_tbf_file(tmp_path):
    p = tmp_path / "junk.dat"
    p.write_bytes(b"\x01" * 100)
    with pytest.raises(TBFError, match=r"byte offset 0 \(frame 0\): bad sync word 0x01010101"):
        read_tbf(p)
    p.write_bytes(b"\xde\xc0")
    with pytest.raises(TBFError, match="shorter than one TBF header"):
        read_tbf(p)
    with pytest.raises(FileNotFoundError):
        read_tbf(tmp_path / "absent.dat")


def _three_times(dropped=(), shuffle=False, seed=0):
    """LWA-NA frames repeated at 3 consecutive time tags (8192 ticks apart), frames optionally dropped."""
    base = _frames(NA.read_bytes(), NA_FRAME)
    frames = [_with_time(f, t * 8192) for t in range(3) for f in base]
    keep = [f for i, f in enumerate(frames) if i not in dropped]
    if shuffle:
        keep = [keep[i] for i in np.random.default_rng(seed).permutation(len(keep))]
    return keep


@pytest.mark.real_data
@needs_na
def test_dropped_middle_frame_zero_filled_and_counted(tmp_path):
    ref = read_tbf(NA)
    p = tmp_path / "drop.dat"
    p.write_bytes(b"".join(_three_times(dropped=(7 + 2,))))   # time 1, third frame (first chan 652)
    d = read_tbf(p)
    assert d.data.shape == (3, 84, 64, 2)
    assert d.stats["frames_missing"] == 1 and d.stats["frames_read"] == 20
    np.testing.assert_array_equal(np.diff(d.time_tags), [8192, 8192])
    k = int(np.flatnonzero(d.channels == 652)[0])
    assert not d.data[1, k:k + 12].any()                       # zero-filled
    mask = np.ones(84, bool)
    mask[k:k + 12] = False
    np.testing.assert_array_equal(d.data[1, mask], ref.data[0, mask])
    np.testing.assert_array_equal(d.data[0], ref.data[0])
    np.testing.assert_array_equal(d.data[2], ref.data[0])


@pytest.mark.real_data
@needs_na
def test_interleaved_out_of_order_and_gulps(tmp_path):
    p1, p2 = tmp_path / "ordered.dat", tmp_path / "shuffled.dat"
    p1.write_bytes(b"".join(_three_times()))
    p2.write_bytes(b"".join(_three_times(shuffle=True)))
    a, b = read_tbf(p1), read_tbf(p2)
    np.testing.assert_array_equal(a.data, b.data)
    np.testing.assert_array_equal(a.time_tags, b.time_tags)
    gulps = list(iter_tbf_gulps(p2, 2))
    assert [g.ntime for g in gulps] == [2, 1]
    np.testing.assert_array_equal(np.concatenate([g.data for g in gulps]), a.data)
    np.testing.assert_array_equal(np.concatenate([g.time_tags for g in gulps]), a.time_tags)
    for key in a.stats:
        assert sum(g.stats[key] for g in gulps) == a.stats[key]
    with pytest.raises(ValueError, match="gulp_ntime"):
        next(iter_tbf_gulps(p1, 0))


@pytest.mark.real_data
@needs_na
def test_missing_time_tag_counted_as_gap_and_duplicates(tmp_path):
    frames = _three_times(dropped=tuple(range(7, 14)))   # time 1 absent altogether
    frames.append(frames[0])                             # a repeated frame
    p = tmp_path / "gap.dat"
    p.write_bytes(b"".join(frames))
    d = read_tbf(p)
    assert d.ntime == 2 and d.stats["time_gaps"] == 1 and d.stats["frames_duplicate"] == 1
    assert d.stats["frames_missing"] == 0
    gulps = list(iter_tbf_gulps(p, 1))
    assert sum(g.stats["time_gaps"] for g in gulps) == 1


@pytest.mark.real_data
@needs_na
def test_truncated_file_stops_cleanly(tmp_path):
    raw = NA.read_bytes()
    p = tmp_path / "trunc.dat"
    p.write_bytes(raw[:len(raw) - 700])
    with pytest.warns(TBFWarning, match="860 trailing bytes"):
        d = read_tbf(p)
    assert d.stats["truncated_bytes"] == 860 and d.stats["frames_read"] == 6
    # the lost frame held the only copy of block 676..687, so those channels are gone
    np.testing.assert_array_equal(d.channels, np.r_[640:676, 2176:2212])
    ref = read_tbf(NA)
    np.testing.assert_array_equal(d.data[0, :36], ref.data[0, :36])
    p.write_bytes(raw[:NA_FRAME - 1])
    with pytest.raises(TBFError, match="no complete frame"):
        read_tbf(p)


@pytest.mark.real_data
@needs_sv
def test_scan_matches_read():
    with pytest.warns(TBFWarning):
        info = scan_tbf(SV)
    assert info.nframe == 5 and info.frame_bytes == SV_FRAME and info.nstand == 256
    assert info.station_hint == "lwasv" and info.engine == "ADP" and info.nchan == 60
    np.testing.assert_array_equal(info.channels, np.arange(2348, 2408))


# ------------------------------------------------------------------ raw gulps (the GPU's read path)
def _written(tmp_path, name, ntime=50, nchan=24, nstand=4, order=None, drop=None, seed=0):
    from bf_epic_blocks.io.tbf import write_tbf
    data = np.random.default_rng(seed).integers(0, 256, (ntime, nchan, nstand, 2), dtype=np.uint8)
    p = tmp_path / name
    write_tbf(p, data, 1200, 10**15, frame_id=5, order=order)
    if drop is not None:   # cut one frame out of the file
        fb = 24 + 12 * nstand * 2
        raw = p.read_bytes()
        p.write_bytes(raw[:drop * fb] + raw[(drop + 1) * fb:])
    return p, data


def _strip(p, g):
    """A RawGulp's samples read the way the GPU path reads them (pread_start on reader threads),
    headers stripped here."""
    import os
    from concurrent.futures import ThreadPoolExecutor
    from bf_epic_blocks.blocks.sources import pread_start, pread_wait
    buf = np.empty(g.nbytes, np.uint8)
    fd = os.open(p, os.O_RDONLY)
    try:
        with ThreadPoolExecutor(3) as pool:
            pread_wait(pread_start(fd, buf, g.offset, pool, piece=1000))
    finally:
        os.close(fd)
    return buf.reshape(g.ntime, g.nblock, g.frame_bytes)[:, :, g.header_bytes:].reshape(g.ntime, -1, 4, 2)


def test_raw_gulps_are_the_file_s_bytes_and_irregular_gulps_fall_back(tmp_path):
    from bf_epic_blocks.io.tbf import RawGulp
    p, data = _written(tmp_path, "ordered.tbf")
    gulps = list(iter_tbf_gulps(p, 16, raw=True))
    assert [type(g) for g in gulps] == [RawGulp] * 4 and [g.ntime for g in gulps] == [16, 16, 16, 2]
    np.testing.assert_array_equal(np.concatenate([_strip(p, g) for g in gulps]), data)
    ref = read_tbf(p)
    for key in ("frames_read", "frames_missing", "time_gaps"):
        assert sum(g.stats[key] for g in gulps) == ref.stats[key]
    np.testing.assert_array_equal(np.concatenate([g.time_tags for g in gulps]), ref.time_tags)
    # two blocks of sample 20 swapped, and a frame of sample 40 missing: those gulps are gathered
    order = np.arange(100)
    order[[40, 41]] = order[[41, 40]]
    p2, data2 = _written(tmp_path, "swapped.tbf", order=order, seed=1)
    kinds = [type(g).__name__ for g in iter_tbf_gulps(p2, 16, raw=True)]
    assert kinds == ["RawGulp", "TBFData", "RawGulp", "RawGulp"]
    p3, _ = _written(tmp_path, "dropped.tbf", drop=81, seed=2)
    got = list(iter_tbf_gulps(p3, 16, raw=True))
    assert [type(g).__name__ for g in got] == ["RawGulp", "RawGulp", "TBFData", "RawGulp"]
    assert got[2].stats["frames_missing"] == 1
    out = np.concatenate([_strip(p2, g) if isinstance(g, RawGulp) else g.data
                          for g in iter_tbf_gulps(p2, 16, raw=True)])
    np.testing.assert_array_equal(out, data2)


@pytest.mark.gpu
@pytest.mark.parametrize("fmt", ["tbf", "tbx"])
def test_a_gpu_ring_gets_the_file_s_samples_through_raw_gulps(tmp_path, fmt):
    """TBFSourceBlock / TBXSourceBlock writing a 'cuda' ring (file bytes -> pinned -> GPU, headers
    stripped there) give the samples the host reader gives, for in-order and irregular gulps."""
    from bf_epic_blocks.imaging._xp import gpu_available
    if not gpu_available():
        pytest.skip("needs CuPy and a CUDA device")
    pytest.importorskip("lsl")
    from bf_epic_blocks.blocks import ArraySinkBlock, bfp
    from bf_epic_blocks.blocks.sources import TBFSourceBlock, TBXSourceBlock
    from bf_epic_blocks.io.tbx import write_tbx
    from bf_epic_blocks.station.offline import configure_offline
    configure_offline()
    rng = np.random.default_rng(5)
    data = rng.integers(0, 256, (300, 24, 256, 2), dtype=np.uint8)
    order = np.arange(600)
    for a in (0, 130, 300, 430):                                # irregular gulps between regular ones
        order[[a, a + 1]] = order[[a + 1, a]]
    p = tmp_path / f"x.{fmt}"
    if fmt == "tbf":
        from bf_epic_blocks.io.tbf import write_tbf
        write_tbf(p, data, 1200, 10**15, frame_id=1, order=order)
        cls, station = TBFSourceBlock, None
    else:
        write_tbx(p, data, 10**15 + 8192 * np.arange(300), 1200, order=order)
        cls, station = TBXSourceBlock, "lwasv"
    got = {}
    for space in ("system", "cuda"):
        with bfp.Pipeline() as pl:
            src = cls(str(p), 32, station=station, space=space)
            sink = ArraySinkBlock(src)
            pl.run()
        got[space] = sink.result(0).view(np.uint8).reshape(data.shape)
        assert src.tbf_stats["frames_read"] == 600 and src.tbf_stats["samples"] == 300
    np.testing.assert_array_equal(got["cuda"], data)
    np.testing.assert_array_equal(got["system"], data)


def test_a_short_read_names_the_byte(tmp_path):
    """The reader threads' reads of a file that ends before the gulp does (truncated after the scan):
    a clear error naming where, never a half-filled buffer passed on."""
    import os
    from concurrent.futures import ThreadPoolExecutor
    from bf_epic_blocks.blocks.sources import pread_start, pread_wait

    def pread_into(fd, buf, offset, piece):
        with ThreadPoolExecutor(2) as pool:
            pread_wait(pread_start(fd, buf, offset, pool, piece=piece))
    p = tmp_path / "short.bin"
    p.write_bytes(bytes(range(256)) * 10)
    buf = np.zeros(3000, np.uint8)
    fd = os.open(p, os.O_RDONLY)
    try:
        pread_into(fd, buf[:2000], 100, piece=512)
        np.testing.assert_array_equal(buf[:2000], np.frombuffer(p.read_bytes()[100:2100], np.uint8))
        with pytest.raises(OSError, match="short read at byte 2560 of the capture"):
            pread_into(fd, buf, 0, piece=512)
    finally:
        os.close(fd)


@pytest.mark.skipif(not __import__("os").path.exists("/proc/self/clear_refs"), reason="needs Linux /proc")
def test_reading_a_file_does_not_keep_its_pages_resident(tmp_path):
    """The header pass and the gathering reads map the file, and every page they touch would stay in
    the process's resident set: a run's peak memory grew with the file's length (a 30-s, 9.3-GB
    recording: 9.3 GB). Pages are handed back as each chunk is done, so the peak growth stays near a
    chunk's, whatever the file's length."""
    import gc
    import os
    from bf_epic_blocks.io.tbf import write_tbf
    ntime = 40000                                 # LWA-NA, 12 channels: 1,560-byte frames, 62 MB
    path = tmp_path / "long.tbf"
    write_tbf(path, np.random.default_rng(0).integers(0, 256, (ntime, 12, 64, 2), dtype=np.uint8), 1200, 0)
    size = os.path.getsize(path)
    gc.collect()

    def status(key):
        return int(open("/proc/self/status").read().split(key + ":")[1].split()[0]) * 1024

    for step in ("scan", "read"):
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")                          # VmHWM := VmRSS
        base = status("VmRSS")
        if step == "scan":
            info = scan_tbf(path)
        else:
            for _ in iter_tbf_gulps(path, 4096, info=info):
                pass
        grew = status("VmHWM") - base
        assert grew < size / 2, (step, grew, size)

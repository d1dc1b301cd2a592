"""TBX reader: LSL's real LWA-NA TBX capture, files written here, corrupted copies; LSL's reader is the truth."""
import struct
import warnings
from pathlib import Path

import numpy as np
import pytest

from bf_epic_blocks.io.formats import FrameFormatError, detect_format
from bf_epic_blocks.io.tbf import TBFError, read_tbf, unpack_ci4
from bf_epic_blocks.io.tbx import (LWANA_FRAME_BYTES, TBXError, TBXWarning, iter_tbx_gulps, pack_tbx_frame,
                                   parse_tbx_frame, parse_tbx_header, read_tbx, scan_tbx, tbx_frame_bytes, write_tbx)

from test_tbf import NA, needs_na

TBX = Path(__file__).resolve().parent / "data" / "lwana-ndp-tbx.dat"
FB = LWANA_FRAME_BYTES  # 1564

# nearly every test here reads the real capture in tests/data (or LSL's reading of it)
pytestmark = pytest.mark.real_data


@pytest.fixture(scope="module")
def lsl_tbx():
    from bf_epic_blocks.station.offline import configure_offline
    configure_offline()  # before lsl is imported
    pytest.importorskip("lsl")
    from lsl.reader import tbx
    return tbx


def lsl_frames(tbx, path):
    """Every frame LSL's reader returns, in file order: [(header, time tag, complex64 (nchan, nstand, 2))]."""
    from lsl.reader.errors import EOFError as LSLEOF
    out = []
    with open(path, "rb") as fh:
        while True:
            try:
                f = tbx.read_frame(fh)
            except LSLEOF:
                return out
            out.append((f.header, int(f.payload.timetag), np.array(f.payload.data)))


def lsl_grid(tbx, path):
    """The (time, channel) grid built from LSL's frames alone: sorted tags and channels, zeros where
    no frame, the first copy of a repeated frame."""
    frames = lsl_frames(tbx, path)
    tags = sorted({t for _, t, _ in frames})
    nchan = frames[0][0].nchan
    blocks = sorted({h.first_chan for h, _, _ in frames})
    out = np.zeros((len(tags), len(blocks) * nchan) + frames[0][2].shape[1:], np.complex64)
    seen = set()
    for h, t, x in frames:
        key = (t, h.first_chan)
        if key in seen:
            continue
        seen.add(key)
        b = blocks.index(h.first_chan)
        out[tags.index(t), b * nchan:(b + 1) * nchan] = x
    return np.array(tags), (np.array(blocks)[:, None] + np.arange(nchan)).ravel(), out


def read_quiet(path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", TBXWarning)
        return read_tbx(path)


# ------------------------------------------------------------------------------------- the real file
def test_real_tbx_layout_time_and_truncation():
    with pytest.warns(TBXWarning, match="296 trailing bytes"):
        d = read_tbx(TBX)
    assert d.data.dtype == np.uint8 and d.data.shape == (1, 312, 64, 2)
    np.testing.assert_array_equal(d.channels, np.arange(2176, 2488))
    assert d.chan_bw_hz == 196e6 / 8192 and d.sample_ticks == 8192
    assert d.freq_hz[0] == pytest.approx(2176 * 23925.78125)
    assert d.station_hint == "lwana" and d.frame_id == 8 and d.nstand == 64
    assert d.stats == dict(frames_read=26, frames_expected=26, frames_missing=0, frames_duplicate=0,
                           time_gaps=0, truncated_bytes=40960 - 26 * FB)
    assert d.times[0].isot == "2024-06-27T17:32:27.000"


def test_real_tbx_equals_lsl(lsl_tbx):
    tags, chans, ref = lsl_grid(lsl_tbx, TBX)
    d = read_quiet(TBX)
    np.testing.assert_array_equal(d.time_tags, tags)
    np.testing.assert_array_equal(d.channels, chans)
    np.testing.assert_array_equal(d.unpack(np.complex64), ref)
    assert np.count_nonzero(ref) > 0.5 * ref.size   # real voltages, not an empty grid


def test_parse_tbx_frame_equals_lsl_frame_by_frame(lsl_tbx):
    raw = TBX.read_bytes()
    frames = lsl_frames(lsl_tbx, TBX)
    assert len(frames) == 26
    for i, (h, tag, x) in enumerate(frames):
        f = parse_tbx_frame(raw, i * FB)
        assert (f.time_tag, f.first_chan) == (tag, h.first_chan)
        assert f.payload.shape == (12, 64, 2) and f.payload.dtype == np.uint8
        np.testing.assert_array_equal(unpack_ci4(f.payload, np.complex64), x)
        hh = parse_tbx_header(raw[i * FB:(i + 1) * FB])
        assert (hh.frame_id, hh.frame_count, hh.second_count, hh.nstand, hh.nchan) == (
            h.frame_id, h.frame_count, h.second_count, h.nstand, h.nchan)
    # the same through every buffer type; a view unless copy=True
    one = raw[:FB]
    for buf in (one, bytearray(one), memoryview(one), np.frombuffer(one, np.uint8)):
        f = parse_tbx_frame(buf)
        assert f.time_tag == frames[0][1] and f.first_chan == 2176
    arr = np.frombuffer(bytearray(one), np.uint8)
    assert np.shares_memory(parse_tbx_frame(arr).payload, arr)
    assert not np.shares_memory(parse_tbx_frame(arr, copy=True).payload, arr)


def test_parse_tbx_frame_rejects_bad_frames():
    raw = TBX.read_bytes()
    with pytest.raises(TBXError, match="truncated TBX frame: 1000 bytes, the header announces 1564"):
        parse_tbx_frame(raw[:1000])
    with pytest.raises(TBXError, match="shorter than a TBX header"):
        parse_tbx_frame(raw[:20])
    with pytest.raises(TBXError, match=r"at byte offset 1: bad sync word") as e:
        parse_tbx_frame(raw, 1)
    assert e.value.offset == 1
    tbf_like = raw[:4] + bytes([5]) + raw[5:FB]
    with pytest.raises(TBXError, match="frame id 5 is not the TBX frame id 8 .it is a TBF frame id"):
        parse_tbx_frame(tbf_like)


@needs_na
def test_detect_format_by_frame_id(tmp_path):
    assert detect_format(TBX) == "tbx" and detect_format(str(TBX)) == "tbx"
    assert detect_format(NA) == "tbf"
    assert detect_format(TBX.read_bytes()[:FB]) == "tbx"
    assert detect_format(np.frombuffer(NA.read_bytes()[:64], np.uint8)) == "tbf"
    raw = TBX.read_bytes()
    with pytest.raises(FrameFormatError, match="frame id 3 is neither"):
        detect_format(raw[:4] + b"\x03" + raw[5:10])
    with pytest.raises(FrameFormatError, match="bad sync word 0x00000000"):
        detect_format(bytes(16))
    with pytest.raises(FrameFormatError, match="too short"):
        detect_format(b"\xde\xc0")
    with pytest.raises(FileNotFoundError):
        detect_format(tmp_path / "absent.dat")
    # and the TBF reader, given a TBX file, says what it is
    with pytest.raises(TBFError, match="frame id 8 is not a TBF frame id.*TBX frame id"):
        read_tbf(TBX)


# ------------------------------------------------------------------------------------- writer round trip
@pytest.mark.parametrize("nstand,nchan_frame", [(64, 12), (256, 16), (128, 4)])
def test_writer_round_trip_through_lsl(tmp_path, lsl_tbx, nstand, nchan_frame):
    rng = np.random.default_rng(nstand)
    # 4 x 2 frames: LSL first reads as many bytes as the previous file's frame size (8,220 for
    # 256 x 16) and calls a shorter file empty, so every file here is longer than that.
    ntime, nblock = 4, 2
    data = rng.integers(0, 256, size=(ntime, nblock * nchan_frame, nstand, 2), dtype=np.uint8)
    tags = 337023871211995136 + 8192 * np.arange(ntime)
    p = tmp_path / "w.tbx"
    assert write_tbx(p, data, tags, 1000, nchan_frame=nchan_frame) == ntime * nblock
    assert p.stat().st_size == ntime * nblock * tbx_frame_bytes(nchan_frame, nstand)
    frames = lsl_frames(lsl_tbx, p)
    assert len(frames) == ntime * nblock
    for i, (h, tag, x) in enumerate(frames):
        t, b = divmod(i, nblock)
        assert h.is_tbx and (h.nstand, h.nchan) == (nstand, nchan_frame)
        assert tag == tags[t] and h.first_chan == 1000 + b * nchan_frame and h.frame_count == t
        np.testing.assert_array_equal(x, unpack_ci4(data[t, b * nchan_frame:(b + 1) * nchan_frame], np.complex64))
    d = read_tbx(p)
    np.testing.assert_array_equal(d.data, data)
    np.testing.assert_array_equal(d.time_tags, tags)
    np.testing.assert_array_equal(d.channels, 1000 + np.arange(nblock * nchan_frame))
    tags_l, chans_l, ref = lsl_grid(lsl_tbx, p)
    np.testing.assert_array_equal(d.unpack(), ref)
    # one frame through pack/parse
    f = parse_tbx_frame(pack_tbx_frame(int(tags[1]), 1000, data[1, :nchan_frame], frame_count=7))
    assert f.time_tag == tags[1] and f.first_chan == 1000
    np.testing.assert_array_equal(f.payload, data[1, :nchan_frame])


def test_writer_rejects_bad_input(tmp_path):
    with pytest.raises(ValueError, match="multiple of nchan_frame"):
        write_tbx(tmp_path / "x", np.zeros((1, 13, 64, 2), np.uint8), [0], 0)
    with pytest.raises(ValueError, match="uint8"):
        write_tbx(tmp_path / "x", np.zeros((1, 12, 64, 2), np.int8), [0], 0)
    with pytest.raises(ValueError, match="time_tags"):
        write_tbx(tmp_path / "x", np.zeros((2, 12, 64, 2), np.uint8), [0], 0)


# ------------------------------------------------------------------------------------- corrupted copies
def _frames(raw=None):
    raw = TBX.read_bytes() if raw is None else raw
    return [raw[i:i + FB] for i in range(0, len(raw) - len(raw) % FB, FB)]


def _with_time(frame, dt_ticks):
    tt = struct.unpack(">q", frame[20:28])[0] + dt_ticks
    return frame[:20] + struct.pack(">q", tt) + frame[28:]


def _patch(frame, offset, fmt, value):
    n = struct.calcsize(fmt)
    return frame[:offset] + struct.pack(fmt, value) + frame[offset + n:]


def _three_times(dropped=(), shuffle=False, seed=0):
    """The real frames at 3 consecutive time tags (8192 ticks apart), some optionally dropped or shuffled."""
    base = _frames()
    frames = [_with_time(f, t * 8192) for t in range(3) for f in base]
    keep = [f for i, f in enumerate(frames) if i not in dropped]
    if shuffle:
        keep = [keep[i] for i in np.random.default_rng(seed).permutation(len(keep))]
    return keep


def test_bad_sync_word_names_byte_offset(tmp_path, lsl_tbx):
    frames = _frames()
    frames[3] = b"\x00\x11\x22\x33" + frames[3][4:]
    p = tmp_path / "badsync.tbx"
    p.write_bytes(b"".join(frames))
    with pytest.raises(TBXError, match=rf"byte offset {3 * FB} \(frame 3\): bad sync word 0x00112233") as e:
        read_tbx(p)
    assert e.value.offset == 3 * FB and isinstance(e.value, ValueError)
    # LSL agrees: three frames, then a sync error
    from lsl.reader.errors import SyncError
    with open(p, "rb") as fh:
        for _ in range(3):
            lsl_tbx.read_frame(fh)
        with pytest.raises(SyncError):
            lsl_tbx.read_frame(fh)


@pytest.mark.parametrize("field,fmt,value,what", [
    (16, ">H", 32, "stand count 32 differs"),
    (18, ">H", 8, "channel count 8 differs"),
    (4, ">B", 5, "frame id 5 is not the TBX frame id"),
    (12, ">I", 2177, "first channel 2177 is not aligned"),
])
def test_inconsistent_frame_raises_with_offset(tmp_path, field, fmt, value, what):
    frames = _frames()
    frames[5] = _patch(frames[5], field, fmt, value)
    p = tmp_path / "bad.tbx"
    p.write_bytes(b"".join(frames))
    with pytest.raises(TBXError, match=rf"byte offset {5 * FB} \(frame 5\): {what}") as e:
        read_tbx(p)
    assert e.value.offset == 5 * FB


def test_not_a_tbx_file(tmp_path):
    p = tmp_path / "junk.dat"
    p.write_bytes(b"\x01" * 100)
    with pytest.raises(TBXError, match=r"byte offset 0: bad sync word 0x01010101 \(expected 0xDEC0DE5C\) \(frame 0\)"):
        read_tbx(p)
    p.write_bytes(TBX.read_bytes()[:FB - 1])
    with pytest.raises(TBXError, match="no complete frame"):
        read_tbx(p)
    with pytest.raises(FileNotFoundError):
        read_tbx(tmp_path / "absent.dat")


def test_dropped_frame_zero_filled_counted_and_equal_to_lsl(tmp_path, lsl_tbx):
    ref = read_quiet(TBX)
    p = tmp_path / "drop.tbx"
    p.write_bytes(b"".join(_three_times(dropped=(26 + 2,))))   # time 1, third block (first chan 2200)
    d = read_tbx(p)
    assert d.data.shape == (3, 312, 64, 2)
    assert d.stats["frames_missing"] == 1 and d.stats["frames_read"] == 77
    k = int(np.flatnonzero(d.channels == 2200)[0])
    assert not d.data[1, k:k + 12].any()
    mask = np.ones(312, bool)
    mask[k:k + 12] = False
    np.testing.assert_array_equal(d.data[1, mask], ref.data[0, mask])
    np.testing.assert_array_equal(d.data[[0, 2]], np.concatenate([ref.data, ref.data]))
    tags, chans, grid = lsl_grid(lsl_tbx, p)
    np.testing.assert_array_equal(d.unpack(), grid)
    np.testing.assert_array_equal(d.time_tags, tags)


def test_shuffled_order_and_gulps_equal_ordered_and_lsl(tmp_path, lsl_tbx):
    p1, p2 = tmp_path / "ordered.tbx", tmp_path / "shuffled.tbx"
    p1.write_bytes(b"".join(_three_times()))
    p2.write_bytes(b"".join(_three_times(shuffle=True)))
    a, b = read_tbx(p1), read_tbx(p2)
    np.testing.assert_array_equal(a.data, b.data)
    np.testing.assert_array_equal(a.time_tags, b.time_tags)
    np.testing.assert_array_equal(np.diff(a.time_tags), [8192, 8192])
    np.testing.assert_array_equal(b.unpack(), lsl_grid(lsl_tbx, p2)[2])
    gulps = list(iter_tbx_gulps(p2, 2))
    assert [g.ntime for g in gulps] == [2, 1]
    np.testing.assert_array_equal(np.concatenate([g.data for g in gulps]), a.data)
    for key in a.stats:
        assert sum(g.stats[key] for g in gulps) == a.stats[key]
    with pytest.raises(ValueError, match="gulp_ntime"):
        next(iter_tbx_gulps(p1, 0))


def test_missing_time_tag_is_a_gap_and_duplicates_are_counted(tmp_path):
    frames = _three_times(dropped=tuple(range(26, 52)))   # time 1 absent altogether
    frames.append(frames[0])
    p = tmp_path / "gap.tbx"
    p.write_bytes(b"".join(frames))
    d = read_tbx(p)
    assert d.ntime == 2 and d.stats["time_gaps"] == 1 and d.stats["frames_duplicate"] == 1
    assert d.stats["frames_missing"] == 0
    assert sum(g.stats["time_gaps"] for g in iter_tbx_gulps(p, 1)) == 1


def test_truncated_file_stops_cleanly(tmp_path):
    raw = TBX.read_bytes()
    p = tmp_path / "trunc.tbx"
    p.write_bytes(raw[:10 * FB + 700])
    with pytest.warns(TBXWarning, match="700 trailing bytes"):
        d = read_tbx(p)
    assert d.stats["truncated_bytes"] == 700 and d.stats["frames_read"] == 10
    np.testing.assert_array_equal(d.channels, np.arange(2176, 2176 + 120))
    np.testing.assert_array_equal(d.data[0], read_quiet(TBX).data[0, :120])


def test_scan_matches_read():
    with pytest.warns(TBXWarning):
        info = scan_tbx(TBX)
    assert info.nframe == 26 and info.frame_bytes == FB and info.nstand == 64 and info.nchan_frame == 12
    assert info.station_hint == "lwana" and info.engine == "NDP" and info.nchan == 312
    np.testing.assert_array_equal(info.channels, np.arange(2176, 2488))

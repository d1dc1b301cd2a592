"""Live capture over UDP, on loopback only (127.0.0.1, ephemeral ports), every test bounded in time.

Truth: the file reader. A capture replayed as packets must give exactly the samples (and images) that
reading the file gives; with packets dropped, exactly what reading the file without those frames
gives (the reader zero-fills missing frames), with the missing count equal to the number dropped.
"""
import socket
import struct
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("astropy")
from bf_epic_blocks.station.offline import configure_offline  # noqa: E402

configure_offline()

from bf_epic_blocks.io.tbf import FS_HZ, read_tbf, write_tbf  # noqa: E402
from bf_epic_blocks.io.udp import UDPCapture, choose_drops, packet_format, replay  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
PIPES = REPO / "pipelines"
DATA = REPO.parent / "shared" / "data" / "lwa"
need_data = pytest.mark.skipif(not (DATA / "lwasv-adp-tbf.dat").exists(), reason=f"real LWA data not found at {DATA}")
LOOPBACK = "127.0.0.1"
NDP_TICKS = 8192


def gen_capture(path, ntime, nstand=8, nchan=36, first=600, seed=0, shuffle_within=0, frame_id=5):
    """A random ci4 capture written with write_tbf; frames optionally shuffled within groups of samples."""
    rng = np.random.default_rng(seed)
    data = rng.integers(0, 256, (ntime, nchan, nstand, 2), dtype=np.uint8)
    nblock = nchan // 12
    order = None
    if shuffle_within:
        order = np.arange(ntime * nblock)
        g = shuffle_within * nblock
        for a in range(0, len(order), g):
            rng.shuffle(order[a:a + g])
    write_tbf(path, data, first, 1_700_000_000 * FS_HZ, frame_id=frame_id, order=order)
    return data, order


def drain(cap, timeout=10.0):
    """Collect a capture's events until its sequence ends: (list of SequenceInfo, data (ntime, ...))."""
    infos, chunks, t_next = [], [], 0
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        ev = cap.next_event(0.2)
        if ev is None:
            continue
        if ev[0] == "start":
            infos.append(ev[1])
        elif ev[0] == "data":
            assert ev[1] == t_next
            chunks.append(ev[2].copy())
            t_next += ev[2].shape[0]
        elif ev[0] == "gap":
            raise AssertionError(f"consumer overflow: {ev}")
        elif ev[0] in ("end", "closed"):
            return infos, (np.concatenate(chunks) if chunks else None), ev
    raise AssertionError("capture did not end in time")


def file_frame_cells(order, nblock, nframe):
    """(time index, block index) of each file frame (file order)."""
    idx = np.arange(nframe) if order is None else np.asarray(order)
    return idx // nblock, idx % nblock


# ------------------------------------------------------------------------------------------------
def test_write_tbf_roundtrip_and_order(tmp_path):
    data, order = gen_capture(tmp_path / "a.tbf", 20, shuffle_within=5, seed=3)
    d = read_tbf(tmp_path / "a.tbf")
    assert np.array_equal(d.data, data) and d.stats["frames_missing"] == 0 and d.frame_id == 5
    assert np.array_equal(np.diff(d.time_tags), np.full(19, NDP_TICKS)) and d.channels[0] == 600
    raw = (tmp_path / "a.tbf").read_bytes()
    fb = 24 + 12 * 8 * 2
    tt = [struct.unpack(">q", raw[i * fb + 16:i * fb + 24])[0] for i in range(60)]
    assert tt != sorted(tt), "frames really are out of order in the file"


def test_choose_drops_exact_and_reproducible():
    a, b = choose_drops(10_000, 0.01, 7), choose_drops(10_000, 0.01, 7)
    assert len(a) == 100 and np.array_equal(a, b) and len(set(a.tolist())) == 100
    assert not np.array_equal(a, choose_drops(10_000, 0.01, 8))
    assert len(choose_drops(5, 0.01, 1)) == 0
    with pytest.raises(ValueError, match="drop"):
        choose_drops(10, 1.5, 1)


def test_capture_reorders_and_counts_exactly_the_dropped_frames(tmp_path):
    """3000 samples x 3 blocks, shuffled within 8 samples, 1% dropped: data = file minus those frames."""
    path = tmp_path / "gen.tbf"
    ntime, nblock = 3000, 3
    data, order = gen_capture(path, ntime, shuffle_within=8, seed=1)
    with UDPCapture(LOOPBACK, 0, "tbf", gulp_nframe=512, buffer_s=0.002, idle_timeout_s=0.3,
                    start_timeout_s=5) as cap:
        cap.start()
        res = {}
        th = threading.Thread(target=lambda: res.update(r=replay(path, LOOPBACK, cap.port, rate=1.0, drop=0.01,
                                                                 seed=11)))
        th.start()
        infos, got, end = drain(cap)
        th.join()
    r = res["r"]
    assert r.sent == ntime * nblock - 90 and len(r.dropped) == 90
    t_idx, b_idx = file_frame_cells(order, nblock, ntime * nblock)
    dt, db = t_idx[r.dropped], b_idx[r.dropped]
    assert 0 not in dt and ntime - 1 not in dt  # first/last sample intact: the time axis is the file's
    expected = data.copy().reshape(ntime, nblock, -1)
    expected[dt, db] = 0
    assert end[0] == "end" and "no packet" in end[1]
    assert len(infos) == 1 and infos[0].nchan == 36 and infos[0].layout.nstand == 8
    assert infos[0].time_tag0 == 1_700_000_000 * FS_HZ
    assert np.array_equal(got, expected.reshape(data.shape))
    s = cap.stats
    assert s["packets"] == r.sent and s["frames_used"] == r.sent
    assert s["frames_missing"] == len(r.dropped) == 90
    assert s["samples"] == ntime and s["frames_late"] == s["frames_duplicate"] == 0 and not s["garbage"]
    # and the file reader agrees: the same file without the dropped frames
    raw = path.read_bytes()
    fb = 24 + 12 * 8 * 2
    keep = np.ones(ntime * nblock, bool)
    keep[r.dropped] = False
    (tmp_path / "kept.tbf").write_bytes(b"".join(raw[i * fb:(i + 1) * fb] for i in np.flatnonzero(keep)))
    d = read_tbf(tmp_path / "kept.tbf")
    assert np.array_equal(d.data, got) and d.stats["frames_missing"] == 90


def test_garbage_is_counted_by_reason_and_ignored(tmp_path):
    path = tmp_path / "gen.tbf"
    data, _ = gen_capture(path, 400, seed=2)
    fmt = packet_format("tbf")
    frames, _ = fmt.file_frames(path)
    good = bytes(frames[0])
    rng = np.random.default_rng(5)
    before = [rng.integers(0, 256, int(n), dtype=np.uint8).tobytes() for n in rng.integers(1, 3000, 40)]
    before += [b"\x00" * len(good)] * 5                                   # right size, bad sync
    before += [good[:100]] * 5                                            # truncated frame
    during = [good[:4] + bytes([1]) + good[5:]] * 6                       # frame id 1 (ADP) in an NDP stream
    during += [good[:12] + struct.pack(">h", 601) + good[14:]] * 4        # channel off the 12-channel blocks
    during += [good[:16] + struct.pack(">q", struct.unpack(">q", good[16:24])[0] + 1) + good[24:]] * 3  # off grid
    during += [good + b"\x00"] * 2                                        # one byte too many
    with UDPCapture(LOOPBACK, 0, "tbf", gulp_nframe=128, buffer_s=0.002, idle_timeout_s=0.3,
                    start_timeout_s=5) as cap:
        tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        for g in before:
            tx.sendto(g, (LOOPBACK, cap.port))
        cap.start()
        res = {}
        th = threading.Thread(target=lambda: res.update(r=replay(path, LOOPBACK, cap.port, rate=1.0)))
        th.start()
        time.sleep(0.005)
        for g in during:
            tx.sendto(g, (LOOPBACK, cap.port))
        tx.close()
        infos, got, _ = drain(cap)
        th.join()
    assert np.array_equal(got, data)
    s = cap.stats
    assert sum(s["garbage"].values()) == len(before) + len(during)
    assert s["garbage"]["frame_id"] == 6 and s["garbage"]["channel"] == 4 and s["garbage"]["time_grid"] == 3
    assert s["packets"] == len(before) + len(during) + res["r"].sent and s["frames_missing"] == 0


def test_idle_timeout_ends_the_sequence_and_a_new_stream_starts_another(tmp_path):
    """A replay stopped half-way ends the sequence after the idle timeout; the next replay is sequence 2."""
    path = tmp_path / "gen.tbf"
    data, _ = gen_capture(path, 2000, seed=4)
    with UDPCapture(LOOPBACK, 0, "tbf", gulp_nframe=256, buffer_s=0.002, idle_timeout_s=0.25,
                    start_timeout_s=5, max_sequences=2) as cap:
        cap.start()
        stop = threading.Event()
        res = {}
        th = threading.Thread(target=lambda: res.update(r=replay(path, LOOPBACK, cap.port, rate=0.25, stop=stop)))
        th.start()
        time.sleep(0.15)  # ~900 samples of the 2000 at 0.25x
        stop.set()
        th.join()
        t_stop = time.monotonic()
        infos, got, end = drain(cap)
        t_end = time.monotonic() - t_stop
        assert end[0] == "end" and 0.2 < t_end < 1.5
        sent = res["r"].sent
        n = -(-sent // 3)  # the last sample may be partial: its missing blocks are zero-filled, counted
        assert 0 < sent < 6000 and got.shape[0] == n
        want = data[:n].copy().reshape(n, 3, -1)
        want[n - 1, sent - 3 * (n - 1):] = 0
        assert np.array_equal(got, want.reshape(got.shape))
        assert cap.stats["frames_missing"] == 3 * n - sent
        replay(path, LOOPBACK, cap.port, rate=5.0)
        infos2, got2, end2 = drain(cap)
        assert [i.index for i in infos2] == [1] and np.array_equal(got2, data)
        ev = cap.next_event(2.0)
        assert ev[0] == "closed" and "all sequences" in ev[1]
    assert cap.stats["sequences"] == 2


def test_replay_refuses_non_loopback_and_tbx_hook_is_clear(tmp_path):
    path = tmp_path / "gen.tbf"
    gen_capture(path, 4)
    with pytest.raises(ValueError, match="loopback"):
        replay(path, "192.0.2.1", 4015)  # TEST-NET-1: never reached, refused before any packet
    try:
        packet_format("tbx")
    except ValueError as e:
        assert "tbx" in str(e).lower()
    with pytest.raises(ValueError, match="unknown packet format"):
        packet_format("drx")


# ------------------------------------------------------------------------------------------------
# Through the pipeline (CLI config -> blocks), compared with reading the file
# ------------------------------------------------------------------------------------------------
pytest.importorskip("lsl")
from bf_epic_blocks.pipeline import cli  # noqa: E402
from bf_epic_blocks.pipeline.config import load_config  # noqa: E402
from bf_epic_blocks.pipeline.runner import build_graph  # noqa: E402
from bf_epic_blocks.pipeline.runner import run as run_pipeline  # noqa: E402


def fits_data(files):
    from astropy.io import fits
    out = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for f in sorted(x for x in files if x.endswith(".fits")):
            with fits.open(f) as h:
                out.append(h[0].data.copy())
    return out


def common_sets(outdir, gulp, acc, size=16):
    return ["--set", f"output.dir={outdir}", "--set", "output.png=false", "--set", f"imager.grid.size={size}",
            "--set", f"source.gulp_nframe={gulp}", "--set", f"imager.accumulate_frames={acc}"]


def run_live(tmp_path, station, capture, rate, gulp, acc, drop=0.0, seed=None, garbage=(), tag="udp"):
    """Build the live pipeline on an ephemeral port, replay ``capture`` into it, run it to the end."""
    sets = ["--set", f"station.name={station}", "--set", "source.port=0", "--set", "source.idle_timeout_s=0.3",
            "--set", "source.start_timeout_s=10", "--set", "source.buffer_s=0.002",
            *common_sets(tmp_path / tag, gulp, acc)]
    cfg = load_config(PIPES / "lwasv_udp_live.yaml", sets[1::2])
    g = build_graph(cfg)
    res = {}

    def send():
        tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        for x in garbage:
            tx.sendto(x, (LOOPBACK, g.source.port))
        tx.close()
        res["r"] = replay(capture, LOOPBACK, g.source.port, rate=rate, drop=drop, seed=seed)

    th = threading.Thread(target=send)
    th.start()
    t0 = time.monotonic()
    g.pipeline.run()
    th.join()
    return g, res["r"], time.monotonic() - t0


def run_file(tmp_path, station, capture, gulp, acc, tag="file"):
    sets = ["--set", f"station.name={station}", "--set", f"source.path={capture}", *common_sets(tmp_path / tag, gulp, acc)]
    cfg = load_config(PIPES / "lwasv_tbf_allsky.yaml", sets[1::2])
    return run_pipeline(cfg, show_progress=False)


@need_data
@pytest.mark.parametrize("rate", [1.0, 5.0])
@pytest.mark.parametrize("fname,station", [("lwasv-adp-tbf.dat", "lwasv"), ("lwana-ndp-tbf.dat", "lwana")])
def test_real_file_replayed_gives_the_images_of_reading_it(tmp_path, fname, station, rate):
    capture = DATA / fname
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the LWA-SV file's truncated last frame
        ref = run_file(tmp_path, station, capture, 1, 1)
    g, r, wall = run_live(tmp_path, station, capture, rate, 1, 1)
    live, want = fits_data(g.writer.written), fits_data(ref["files"])
    assert len(live) == len(want) >= 1
    for a, b in zip(live, want):
        assert np.array_equal(a, b, equal_nan=True)
    s = g.source.udp_stats
    assert s["packets"] == r.sent == r.nframe and s["frames_missing"] == 0 and s["samples"] == 1
    assert g.calfold.stats["nframe_skipped"] == 0 and wall < 10


def test_generated_capture_with_drops_and_garbage_through_the_pipeline(tmp_path):
    """LWA-NA layout (64 stands), 1200 samples: 1% dropped + a garbage burst; images = the file reader's
    images of the same file without the dropped frames; missing count = dropped count; garbage counted."""
    path = tmp_path / "na.tbf"
    ntime, nblock = 1200, 2
    data, _ = gen_capture(path, ntime, nstand=64, nchan=24, first=2176, seed=6, shuffle_within=4)
    garbage = [b"\x12" * n for n in (10, 1560, 3000)] * 7
    g, r, wall = run_live(tmp_path, "lwana", path, 2.0, ntime, 300, drop=0.01, seed=5, garbage=garbage)
    assert len(r.dropped) == 24 and r.sent == ntime * nblock - 24
    raw, fb = path.read_bytes(), 24 + 12 * 64 * 2
    keep = np.ones(ntime * nblock, bool)
    keep[r.dropped] = False
    kept = tmp_path / "kept.tbf"
    kept.write_bytes(b"".join(raw[i * fb:(i + 1) * fb] for i in np.flatnonzero(keep)))
    ref = run_file(tmp_path, "lwana", kept, ntime, 300)
    assert ref["tbf"]["frames_missing"] == 24
    live, want = fits_data(g.writer.written), fits_data(ref["files"])
    assert len(live) == len(want) == ntime // 300  # one FITS per image
    for a, b in zip(live, want):
        assert np.array_equal(a, b, equal_nan=True)
    full = fits_data(run_file(tmp_path, "lwana", path, ntime, 300, tag="full")["files"])
    assert not all(np.array_equal(a, b, equal_nan=True) for a, b in zip(live, full)), "the drops must show"
    s = g.source.udp_stats
    assert s["frames_missing"] == 24 and s["packets"] == r.sent + len(garbage)
    assert sum(s["garbage"].values()) == len(garbage) and s["samples"] == ntime


def test_slow_imager_never_stalls_the_socket(tmp_path):
    """A reader that cannot keep up skips (counted) while the capture keeps receiving every packet."""
    from bf_epic_blocks.blocks import bfp
    from bf_epic_blocks.blocks.udp_source import UDPSourceBlock

    class Slow(bfp.SinkBlock):
        def __init__(self, iring, *args, **kwargs):
            super().__init__(iring, *args, **kwargs)
            self.read = 0

        def on_sequence(self, iseq):
            pass

        def on_data(self, ispan):
            self.read += ispan.data.shape[0]
            time.sleep(0.05)  # a slow imager: 50 ms per 64-sample gulp (64 samples of data = 2.7 ms)

        def on_skip(self, islices, ospans):
            pass

    path = tmp_path / "gen.tbf"
    data, _ = gen_capture(path, 3000, nstand=64, nchan=24, first=2176, seed=8)
    with bfp.Pipeline() as p:
        src = UDPSourceBlock(LOOPBACK, 0, 64, station="lwana", buffer_s=0.002, idle_timeout_s=0.3,
                             start_timeout_s=10)
        sink = Slow(src, guarantee=False)
    res = {}
    th = threading.Thread(target=lambda: res.update(r=replay(path, LOOPBACK, src.port, rate=1.0)))
    th.start()
    p.run()
    th.join()
    s = src.udp_stats
    assert s["packets"] == res["r"].sent == 6000 and s["frames_missing"] == 0 and s["samples"] == 3000
    assert src.stats["nframe_written"] == 3000
    skipped = sink.stats["nframe_skipped"]
    assert skipped > 0 and sink.read + skipped == 3000


def test_cli_replay_prints_what_it_dropped(tmp_path, capsys):
    path = tmp_path / "gen.tbf"
    data, _ = gen_capture(path, 500, seed=9)
    with UDPCapture(LOOPBACK, 0, "tbf", gulp_nframe=500, buffer_s=0.002, idle_timeout_s=0.3,
                    start_timeout_s=5) as cap:
        cap.start()
        assert cli.main(["replay", str(path), "--to", f"127.0.0.1:{cap.port}", "--rate", "5", "--drop", "0.01",
                         "--seed", "3", "-q"]) == 0
        _, got, _ = drain(cap)
    out = capsys.readouterr().out
    want = choose_drops(1500, 0.01, 3)
    assert f"sent {1500 - 15}, dropped 15 (seed 3)" in out
    assert "dropped frame indices (file order): " + " ".join(map(str, want)) in out
    assert cap.stats["frames_missing"] == 15
    assert cli.main(["replay", str(path), "--to", "192.0.2.1:4015"]) == 2
    assert "loopback" in capsys.readouterr().err


def test_udp_config_keys_are_checked():
    from bf_epic_blocks.pipeline.config import ConfigError
    cfg = load_config("source: {kind: udp, port: 4015}\n")
    assert cfg["source"]["format"] == "tbf" and cfg["source"]["buffer_s"] == 0.05 and cfg["source"]["sequences"] == 1
    with pytest.raises(ConfigError) as e:
        load_config("source: {kind: udp, port: 4015, path: x.dat, format: drx}\n")
    msg = str(e.value)
    assert "source.path: only used when source.kind is 'tbf'" in msg and "source.format" in msg
    with pytest.raises(ConfigError, match="source.port: missing required key"):
        load_config("source: {kind: udp}\n")

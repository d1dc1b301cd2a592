"""The pixel split (several GPUs, each imaging and searching its own part of the grid): the parts
cover the sky once; PixelMergeBlock joins parts into the grid and names parts that do not fit; and
through `bf-epic run` a split of two parts (on the CPU here; two H100s in the GPU check) gives the
images and the candidate table one graph gives, with the burst where it was injected."""
from pathlib import Path

import numpy as np
import pytest

from bf_epic_blocks import imaging
from bf_epic_blocks.blocks import (ArraySinkBlock, ArraySourceBlock, ImageIntegratorBlock, PixelMergeBlock, bfp,
                                   image_layout)
from bf_epic_blocks.blocks.headers import grid_pixels_header
from test_transient import DT, image_header

YAML = Path(__file__).resolve().parent.parent / "pipelines" / "lwasv_sim_wholeband.yaml"


@pytest.mark.parametrize("n", [1, 2, 3, 7])
def test_grid_parts_cover_the_sky_once(n):
    grid = imaging.lm_grid(16)
    parts = [grid.part(k, n) for k in range(n)]
    masks = np.stack([p.mask for p in parts])
    assert np.array_equal(masks.sum(axis=0), grid.mask.astype(int))          # every pixel in one part
    assert max(p.npix for p in parts) - min(p.npix for p in parts) <= 1
    assert np.array_equal(np.concatenate([p.lm for p in parts]), grid.lm)     # in the grid's own order
    for p in parts:
        assert np.array_equal(p.lm, grid.lm[np.isin(np.flatnonzero(grid.mask), np.flatnonzero(p.mask))])
    with pytest.raises(ValueError, match="k must be"):
        grid.part(n, n)
    with pytest.raises(ValueError, match="cannot share"):
        grid.part(0, grid.npix + 1)


def _part_images(grid, part, x):
    """``x`` with only ``part``'s pixels kept (NaN elsewhere), as that part's imager leaves them."""
    y = x.copy()
    y[..., ~part.mask] = np.nan
    return y


def test_merge_block_joins_the_parts_and_names_what_does_not_fit():
    rng = np.random.default_rng(5)
    grid = imaging.lm_grid(16)
    freq = 74e6 + 25e3 * np.arange(4)
    x = rng.normal(5.0, 1.0, (96, 4, 1, 16, 16)).astype(np.float32)
    x[..., ~grid.mask] = np.nan
    parts = [grid.part(k, 3) for k in range(3)]
    with bfp.Pipeline() as p:
        srcs = []
        for part in parts:
            hdr = image_header(grid, freq, 16 * DT)
            hdr["pixels"] = grid_pixels_header(part.size, part.cell, part.mask)
            srcs.append(ArraySourceBlock(_part_images(grid, part, x), hdr, gulp_nframe=32))
        host = [ImageIntegratorBlock(s, nimage=1, average_channels=True, space="system") for s in srcs]
        sink = ArraySinkBlock(PixelMergeBlock(host))
        p.run()
    got = sink.result(0)
    want = x.astype(np.float64).mean(axis=1, keepdims=True)
    assert got.shape == want.shape
    assert np.array_equal(np.isfinite(got), np.isfinite(want))
    ok = np.isfinite(want)
    assert np.allclose(got[ok], want[ok], rtol=1e-6)
    lay = image_layout(sink.headers[0])
    assert "index" not in sink.headers[0]["pixels"] and lay["lm"].shape == grid.lm.shape   # the whole sky again

    # two parts holding the same pixels: named, not merged
    with pytest.raises(Exception, match="overlap"):
        with bfp.Pipeline() as p:
            hdr = image_header(grid, freq, 16 * DT)
            hdr["pixels"] = grid_pixels_header(parts[0].size, parts[0].cell, parts[0].mask)
            a = ArraySourceBlock(_part_images(grid, parts[0], x), hdr, gulp_nframe=32)
            b = ArraySourceBlock(_part_images(grid, parts[0], x), dict(hdr), gulp_nframe=32)
            ArraySinkBlock(PixelMergeBlock([a, b]))
            p.run()


def _gpus():
    try:
        import cupy
        return cupy.cuda.runtime.getDeviceCount()
    except Exception:       # no CuPy, no driver
        return 0


@pytest.mark.slow
@pytest.mark.parametrize("device", ["cpu", "cpu3", pytest.param("gpu", marks=[
    pytest.mark.gpu, pytest.mark.skipif(_gpus() < 2, reason="needs two CUDA GPUs")])])
def test_pixel_split_through_run_equals_one_graph(tmp_path, device):
    """The whole-band pipeline made small (16 channels, 16x16 grid, a burst at DM 0.6), run as one graph
    and as a split of two parts (on the CPU; or device gpu:0 against gpu:all, the split over the GPUs
    present): the burst is found where it was injected, and the split gives the same candidate table
    (the burst's beam sidelobe in the other part, S/N 8, folded into it as one graph folds it),
    band-averaged FITS and cube."""
    from astropy.io import fits
    from bf_epic_blocks.io.candidates import read_candidates
    from bf_epic_blocks.io.cube import read_image_cube
    from bf_epic_blocks.pipeline.config import load_config
    from bf_epic_blocks.pipeline.runner import run
    got = {}
    nparts = 3 if device == "cpu3" else 2          # (any number of parts: three on the CPU)
    runs = (("one", None, "cpu"), ("split", [None] * nparts, "cpu")) if device.startswith("cpu") else \
        (("one", None, "gpu:0"), ("split", None, "gpu:all"))
    for tag, parts, dev in runs:
        out = tmp_path / tag
        cfg = load_config(YAML, [f"output.dir={out}", f"device={dev}", "source.duration_s=0.42", "source.channels.count=16",
                                 "imager.grid.size=16", "imager.search.window_s=0.06", "imager.search.dms=[1.0]",
                                 "imager.search.threshold=7", "output.integrate.seconds=0.1",
                                 "output.cube.dtype=float32", "output.png=false",
                                 "source.transients=[{ra_deg: 310.0, dec_deg: 20.0, start_s: 0.3, "
                                 "duration_s: 0.0015, flux_jy: 2000.0, dm: 0.6}]"])
        summary = run(cfg, show_progress=False, parts=parts)
        tab = read_candidates(out / "lwasv_sim_wholeband_candidates.ecsv")
        cube = read_image_cube(next(out.glob("*_cube_*.h5")))["images"]
        files = [fits.getdata(f) for f in sorted(out.glob("*_s00_i*.fits"))]
        got[tag] = (summary, tab, cube, files)
    (s1, t1, c1, f1), (s2, t2, c2, f2) = got["one"], got["split"]
    assert s2["search"]["parts"] == (nparts if device.startswith("cpu") else _gpus())
    best = t2[int(np.argmax(t2["snr"]))]
    assert abs(best["image"] - 0.3 / (16 * DT)) <= 1 and abs(best["dm"] - 0.6) < 0.1 and best["snr"] > 10
    assert len(t1) == len(t2) >= 1
    for col in ("image", "pixel", "grid_x", "grid_y", "width", "nmembers", "nsidelobes", "kind"):
        assert list(t1[col]) == list(t2[col]), col
    for col in ("snr", "dm", "ra_deg", "dec_deg", "l", "m"):
        assert np.allclose(t1[col], t2[col], rtol=1e-6), col
    assert s1["search"]["trials_per_width"] == s2["search"]["trials_per_width"]
    assert c1.shape == c2.shape and np.allclose(c1, c2, rtol=2e-6, equal_nan=True)
    assert len(f1) == len(f2) == 4
    for a, b in zip(f1, f2):
        assert np.allclose(a, b, rtol=2e-6, equal_nan=True)


def test_split_is_checked():
    from bf_epic_blocks.pipeline.config import ConfigError, load_config, resolved_split
    cfg = load_config(YAML, ["device=gpu:all"])
    assert resolved_split(cfg) == "pixels"                       # a search on a grid: auto splits pixels
    assert resolved_split(load_config(YAML, ["imager.search=null"])) == "channels"
    with pytest.raises(ConfigError, match="imager.split.*tracked|imager.track follows"):
        load_config(YAML, ["imager.split=pixels", "imager.grid=null",
                           "imager.track={source: CygA, size: 8, fov_deg: 5}"])
    # live packets: one receiver, so a search on several GPUs shares the channels; pixels is refused
    live = YAML.parent / "lwasv_udp_live.yaml"
    assert resolved_split(load_config(live, ["device=gpu:all", "imager.search={dms: [0.0]}"])) == "channels"
    with pytest.raises(ConfigError, match="source is live"):
        load_config(live, ["device=gpu:all", "imager.split=pixels"])


def test_pixel_split_of_a_capture_file_equals_one_graph(tmp_path):
    """A TBX capture (LSL's LWA-NA test file, 312 channels) split over two parts: each reads the file
    itself, images its half of the grid with the cable terms folded into its operator, and the parts'
    per-channel images (no band mean here: the writer keeps every channel) meet on one grid; the FITS
    equal one graph's (CalFoldBlock on the voltages, then the imager) to float32 rounding."""
    from astropy.io import fits
    from bf_epic_blocks.pipeline.config import load_config
    from bf_epic_blocks.pipeline.runner import run
    yaml = YAML.parent / "lwana_tbx_allsky.yaml"
    data = {}
    for tag, parts in (("one", None), ("split", [None, None])):
        out = tmp_path / tag
        cfg = load_config(yaml, [f"output.dir={out}", "output.png=false", "imager.grid.size=32"])
        summary = run(cfg, show_progress=False, parts=parts)
        data[tag] = [fits.getdata(f) for f in sorted(out.glob("*.fits"))]
        assert summary["frames_imaged"] == 1
    assert len(data["one"]) == len(data["split"]) >= 1
    for a, b in zip(data["one"], data["split"]):
        assert a.shape == b.shape and np.array_equal(np.isfinite(a), np.isfinite(b))
        ok = np.isfinite(a)
        assert np.abs(a[ok] - b[ok]).max() <= 1e-5 * np.abs(a[ok]).max()


def _row(part, gx, gy, image, snr, dm=1.0, kind="point", width=2, sky_fraction=0.0):
    """A candidate row as a part's search writes it: ``pixel`` its index among ``part``'s pixels."""
    from astropy.time import Time
    part_pixel = int(np.flatnonzero(np.flatnonzero(part.mask) == gy * part.size + gx)[0])
    return {"time_utc": Time("2024-06-01T10:00:00", scale="utc"), "sequence": "s", "image": image,
            "pixel": part_pixel, "grid_x": gx, "grid_y": gy, "l": (gx - 8) / 8, "m": (gy - 8) / 8, "ra_deg": 0.0,
            "dec_deg": 0.0, "snr": snr, "dm": dm, "dm_trial": dm, "channel": -1, "width": width, "width_ms": 1.28, "nmembers": 2,
            "nsidelobes": 0, "kind": kind, "sky_fraction": sky_fraction, "lightcurve": np.zeros(3), "_sigma": 1.0}


def _part_block(grid, part, rows, freq):
    """What SearchParts reads of a part's TransientSearchBlock (no beam: only the DM and sky-wide rules)."""
    import types
    lay = {"pixel_index": np.flatnonzero(part.mask), "lm": part.lm, "grid": part, "freq_hz": freq, "dt_s": 16 * DT,
           "products": ["I"]}
    stats = {"images": 100, "images_searched": 90, "crossings": len(rows), "candidates": len(rows), "resets": 0,
             "images_lost": 0, "trials_per_width": [10, 10], "sequences": 1,
             "sky_wide": sum(r["kind"] == "sky-wide" for r in rows), "sidelobes_folded": 0,
             "crossings_dropped": 0}
    return types.SimpleNamespace(
        name="TransientSearchBlock", lay=lay, rows=rows, search_stats=stats, sidelobe_factor=2.0, _tlink=8,
        _space=2.0, search=types.SimpleNamespace(wmax=8, shift=40, average=True, dms=[0.0, 0.5, 1.0, 1.5]),
        beam_on=lambda lm: None, lc_before=1, lc_after=1, threshold=6.0, _prod=0, _sky=np.zeros(part.npix),
        meta=lambda: {"threshold": 6.0, "trials_per_width": [10, 10]})


def test_search_parts_fold_what_another_part_explains(tmp_path):
    """SearchParts' rules across parts: a sky-wide event both halves saw is one row (the larger sky
    fraction); a fainter candidate in the other half beside a burst, at another DM, within what the
    burst's DM sidelobe puts there, is folded into it; one the sidelobe cannot explain (too bright, or
    far in time) stays a row; pixels are renumbered over the whole sky."""
    from bf_epic_blocks.blocks.search_parts import SearchParts
    from bf_epic_blocks.search import dm_sidelobe_snr
    grid = imaging.lm_grid(16)
    a, b = grid.part(0, 2), grid.part(1, 2)
    freq = 74e6 + 25e3 * np.arange(64)
    # the last pixel of part a and the first of part b: neighbours on the grid (same row or the next)
    qa, qb = np.flatnonzero(a.mask)[-1], np.flatnonzero(b.mask)[0]
    ax, ay, bx, by = qa % 16, qa // 16, qb % 16, qb // 16
    assert np.hypot(ax - bx, ay - by) <= 2.0
    bright = (500, 1.0, 2, 300.0)

    def sidelobe(dm):
        """(image, S/N) where the burst's sweep puts most into the trial of ``dm``: its DM sidelobe."""
        e = max(range(500, 560), key=lambda e: dm_sidelobe_snr(freq, 16 * DT, bright, (e, dm, 2)))
        return e, dm_sidelobe_snr(freq, 16 * DT, bright, (e, dm, 2))
    (e5, s5), (e25, s25) = sidelobe(0.5), sidelobe(0.25)
    assert s5 > 3 and s25 > 3                          # real sidelobes
    rows_a = [_row(a, ax, ay, image=500, snr=300.0, dm=1.0),
              _row(a, 3, 3, image=2000, snr=40.0, kind="sky-wide", sky_fraction=0.3)]
    rows_b = [_row(b, bx, by, image=e5, snr=0.9 * 2 * s5, dm=0.5),              # folded: within 2x the sidelobe
              _row(b, bx, by, image=e25, snr=3.0 * s25, dm=0.25),               # 3x: a source of its own
              _row(b, 12, 12, image=900, snr=8.0, dm=0.5),                       # far in time: its own row
              _row(b, 9, 9, image=2001, snr=35.0, kind="sky-wide", sky_fraction=0.5)]
    sp = SearchParts([_part_block(grid, a, rows_a, freq), _part_block(grid, b, rows_b, freq)], tmp_path, "t",
                     "ecsv", png=False)
    tab = sp.finish()
    assert len(tab) == 4                         # the burst, the bright other-DM row, the far one, one sky-wide
    burst_row = tab[tab["snr"] == 300.0][0]
    assert burst_row["nsidelobes"] == 1 and burst_row["nmembers"] == 4
    sky = tab[tab["kind"] == "sky-wide"]
    assert len(sky) == 1 and sky["snr"][0] == 40.0 and sky["sky_fraction"][0] == 0.5
    whole = np.flatnonzero(grid.mask)
    assert set(tab["pixel"]) == {int(np.searchsorted(whole, q)) for q in (qa, qb, 12 * 16 + 12, 3 * 16 + 3)}
    assert sp.search_stats["sidelobes_folded"] == 2 and sp.search_stats["candidates"] == 4
    assert sp.search_stats["sky_wide"] == 1
    assert sp.search_stats["trials_per_width"] == [20, 20] and sp.search_stats["images"] == 100
    assert (tmp_path / "t_candidates.ecsv").exists()


def test_plan_of_a_split_is_per_gpu():
    """`bf-epic plan` of a pixel split plans each GPU's part (half the pixels, the one-GPU modes: i8x2 for
    4-bit voltages at 1e-4) and needs no GPU to do it."""
    from bf_epic_blocks.pipeline.config import load_config
    from bf_epic_blocks.pipeline.runner import plan
    one, _ = plan(load_config(YAML, ["device=gpu"]))
    two, text = plan(load_config(YAML, ["device=gpu:0,1"]))
    assert one["pixels"] == 3205 and two["pixels"] == 1603 and "split over 2 GPUs" in text
    assert two["tolerance_pick"]["precision"] == one["tolerance_pick"]["precision"] == "i8x2"
    assert two["search"]["memory_bytes"]["history"] < 0.51 * one["search"]["memory_bytes"]["history"]
    chans, _ = plan(load_config(YAML, ["device=gpu:0,1", "imager.split=channels", "imager.tolerance=1e-3"]))
    assert chans["pixels"] == 3205 and chans["tolerance_pick"]["precision"] not in ("i8x2", "i8x3")

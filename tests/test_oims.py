"""The station's OIMS image database format (bf_epic_blocks.io.oims), against its published layout: byte
offsets and sizes worked out by hand from the format's description, files of older versions built field by
field with struct (not by the writer), and the pixel directions against the WCS that OIMS2fits gives the
images (built here with astropy exactly as Orville's wcs.py builds it)."""
import json
import struct

import numpy as np
import pytest

from bf_epic_blocks.io.oims import OimsFormatError, OimsWriter, from_lm_image, oims_lm, read_oims


def _write(path, n=2, ext=None, starts=(60000.5, 60000.5 + 5 / 86400)):
    rng = np.random.default_rng(1)
    data = rng.normal(size=(len(starts), 2, 4, n, n)).astype(np.float32)
    with OimsWriter(path, "LWASV", ("I", "Q", "U", "V"), ngrid=n, nchan=2, imager_version="test 1") as w:
        for i, t in enumerate(starts):
            w.add(data[i], start_mjd=t, int_len_s=5.0, freq_hz=[40e6, 40.1e6], lst_turns=0.25,
                  mask=[False, True], center_ra_deg=90.0, center_dec_deg=34.0,
                  extended=ext if i == 1 else None)
    return data


def test_the_bytes_are_where_the_format_puts_them(tmp_path):
    """nchan 2, 4 Stokes, ngrid 4: the file header ends at 156, a plain record is 140 + 512 + 2 = 654 bytes,
    one with the 8-byte JSON {"a": 1} 662: 1,472 bytes in all."""
    p = tmp_path / "a.oims"
    data = _write(p, n=4, ext={"a": 1})
    raw = p.read_bytes()
    assert len(raw) == 156 + 654 + 662
    assert raw[:24] == b"OrvilleImageDBv006" + b"\0" * 6
    assert raw[48:53] == b"LWASV" and raw[72:79] == b"I,Q,U,V"
    assert struct.unpack_from("<i", raw, 96)[0] == 4                       # ngrid
    assert struct.unpack_from("<d", raw, 100)[0] == 130.0 / 4              # pixel size, degrees
    assert struct.unpack_from("<iI", raw, 108) == (2, 1)                   # nchan, flags: time-ordered
    start, stop = struct.unpack_from("<dd", raw, 116)
    assert start == 60000.5 and stop == pytest.approx(60000.5 + 10 / 86400, abs=1e-12)
    assert raw[132:136] == b"none"
    for rec, ext in ((156, -1), (156 + 654, 8)):
        assert raw[rec:rec + 4] == bytes.fromhex("FECADEC0")               # 0xC0DECAFE, little-endian
        assert struct.unpack_from("<d", raw, rec + 12)[0] == pytest.approx(5 / 86400, rel=1e-15)  # days
        assert struct.unpack_from("<ddd", raw, rec + 36) == (40e6, 40.1e6, pytest.approx(0.1e6))
        assert raw[rec + 60:rec + 67] == b"natural"
        assert struct.unpack_from("<iiiiii", raw, rec + 116) == (-1, -1, -1, -1, -1, ext)
        img = np.frombuffer(raw, "<f4", 2 * 4 * 16, rec + 140).reshape(2, 4, 4, 4)
        np.testing.assert_array_equal(img, data[0 if ext < 0 else 1])
        assert raw[rec + 140 + 512:rec + 140 + 514] == b"\x00\x01"           # channel 1 flagged
    assert raw[-8:] == json.dumps({"a": 1}).encode()


def test_what_is_written_reads_back(tmp_path):
    p = tmp_path / "b.oims"
    data = _write(p, ext={"oarfish": {"good": 0.9}})
    got = read_oims(p)
    h = got["header"]
    assert (h["version"], h["station"], h["stokes"], h["ngrid"], h["nchan"]) == (6, "LWASV", ["I", "Q", "U", "V"], 2, 2)
    np.testing.assert_array_equal(got["data"], data)
    np.testing.assert_array_equal(got["mask"], [[False, True], [False, True]])
    assert "extended_attributes" not in got["entries"][0]
    assert got["entries"][1]["extended_attributes"] == {"oarfish": {"good": 0.9}}
    assert got["entries"][0]["lst"] == 0.25 and got["entries"][0]["center_dec"] == 34.0


def test_appending_keeps_the_records_and_an_earlier_image_clears_the_time_order(tmp_path):
    p = tmp_path / "c.oims"
    _write(p, starts=(60000.5,))
    with OimsWriter(p, "LWASV", ("I", "Q", "U", "V"), ngrid=2, nchan=2, append=True) as w:
        assert w.nint == 1
        w.add(np.ones((2, 4, 2, 2)), start_mjd=60000.4, int_len_s=5.0, freq_hz=[40e6, 40.1e6])
    h = read_oims(p)["header"]
    assert len(read_oims(p)["entries"]) == 2
    assert h["flags"] == 0 and h["start_time"] == 60000.4
    with pytest.raises(OimsFormatError, match="ngrid 2 in the file, 4 here"):
        OimsWriter(p, "LWASV", ("I", "Q", "U", "V"), ngrid=4, nchan=2, append=True)


def test_every_version_s_headers_have_the_format_s_sizes():
    from bf_epic_blocks.io import oims
    assert {v: e[0].size for v, e in oims._ENTRY.items()} == oims.ENTRY_BYTES == \
        {1: 68, 2: 92, 3: 92, 4: 108, 5: 132, 6: 140}
    assert all(len(names) == len(st.unpack(bytes(st.size))) for st, names in oims._ENTRY.values())
    assert (oims._FILE_HDR_V6.size, oims._FILE_HDR_V1.size) == (132, 108)


def test_older_versions_are_read(tmp_path):
    """A version-2 file (no mask, 92-byte entries) and a version-5 file (108-byte header, 132-byte entries
    with the weighting), built field by field from the format's description."""
    assert struct.calcsize("<I11d") == 92 and struct.calcsize("<I7d24s4d4i") == 132
    rng = np.random.default_rng(2)
    img = rng.normal(size=(2, 3, 1, 1, 2, 2)).astype("<f4")         # 3 integrations, 1 channel, I only
    hdr = struct.pack("<24s24s24sidiIdd", b"orville", b"LWA1", b"I", 2, 65.0, 1, 1, 60000.0, 60000.1)
    v2 = struct.pack("<24s", b"OrvilleImageDBv002") + hdr
    v5 = struct.pack("<24s", b"OrvilleImageDBv005") + hdr
    for i in range(3):
        v2 += struct.pack("<I11d", 0xC0DECAFE, 60000.0 + i, 0.001, 0.5, 0.3, 38e6, 38e6, 1e5,
                          10.0, 20.0, 0.0, 90.0) + img[0, i].tobytes()
        v5 += struct.pack("<I7d24s4d4i", 0xC0DECAFE, 60000.0 + i, 0.001, 0.5, 0.3, 74e6, 74e6, 1e5,
                          b"uniform", 10.0, 20.0, 0.0, 90.0, 1, 2, 3, 4) + img[1, i].tobytes() + bytes([i % 2])
    for name, blob, k in (("v2", v2, 0), ("v5", v5, 1)):
        (tmp_path / name).write_bytes(blob)
        got = read_oims(tmp_path / name)
        assert got["header"]["version"] == (2 if k == 0 else 5)
        assert [e["start_time"] for e in got["entries"]] == [60000.0, 60001.0, 60002.0]
        np.testing.assert_array_equal(got["data"], img[k])
    assert read_oims(tmp_path / "v5")["mask"][:, 0].tolist() == [False, True, False]
    assert read_oims(tmp_path / "v5")["entries"][0]["weighting"] == "uniform"
    assert read_oims(tmp_path / "v5")["entries"][0]["asp_atten_3"] == 4


def test_bad_files_are_named(tmp_path):
    p = tmp_path / "x.oims"
    _write(p)
    raw = p.read_bytes()
    (tmp_path / "short").write_bytes(raw[:-5])
    with pytest.raises(OimsFormatError, match="truncated"):
        read_oims(tmp_path / "short")
    bad = bytearray(raw)
    bad[156:160] = b"\0\0\0\0"
    (tmp_path / "sync").write_bytes(bytes(bad))
    with pytest.raises(OimsFormatError, match="sync word 0x00000000"):
        read_oims(tmp_path / "sync")
    (tmp_path / "other").write_bytes(b"SIMPLE  =                    T" + b" " * 50)
    with pytest.raises(OimsFormatError, match="not an OIMS file"):
        read_oims(tmp_path / "other")
    comp = bytearray(raw)
    comp[132:156] = b"fpzip".ljust(24, b"\0")
    (tmp_path / "comp").write_bytes(bytes(comp))
    with pytest.raises(OimsFormatError, match="compressed with 'fpzip'"):
        read_oims(tmp_path / "comp")
    with pytest.raises(OimsFormatError, match=r"\(nchan, nstokes, ngrid, ngrid\)"):
        with OimsWriter(tmp_path / "y.oims", "LWASV", ("I",), ngrid=4, nchan=1) as w:
            w.add(np.zeros((1, 1, 4, 5)), start_mjd=6e4, int_len_s=1.0, freq_hz=[5e7])
    with pytest.raises(OimsFormatError, match="longer than the 24 bytes"):
        OimsWriter(tmp_path / "z.oims", "A" * 25, ("I",), ngrid=4, nchan=1)


@pytest.mark.parametrize("n", [64, 128])
def test_each_pixel_is_the_direction_oims2fits_wcs_gives_it(n):
    """OIMS2fits' WCS (Orville's wcs.py: CRPIX ngrid/2 + 0.5, CDELT (-130/ngrid, 130/ngrid) degrees, SIN,
    CRVAL the phase centre): with the centre at RA 0, Dec 0, a pixel's world direction has l = cos(dec)
    sin(ra) (East) and m = sin(dec) (North), which must be oims_lm's for that pixel."""
    from astropy.wcs import WCS
    w = WCS(naxis=2)
    w.wcs.crpix = [n / 2 + 0.5 * ((n + 1) % 2)] * 2
    w.wcs.cdelt = [-130.0 / n, 130.0 / n]
    w.wcs.crval = [0.0, 0.0]
    w.wcs.ctype = ["RA---SIN", "DEC--SIN"]
    lm = oims_lm(n)
    rows, cols = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    keep = (lm ** 2).sum(axis=-1) < 0.95
    ra, dec = w.wcs_pix2world(cols[keep], rows[keep], 0)          # numpy's last axis is FITS axis 1
    ra, dec = np.radians(ra), np.radians(dec)
    np.testing.assert_allclose(np.cos(dec) * np.sin(ra), lm[keep][:, 0], atol=1e-12)
    np.testing.assert_allclose(np.sin(dec), lm[keep][:, 1], atol=1e-12)


def test_a_point_source_lands_on_its_pixel_in_oims_orientation():
    """A source East of the zenith imaged (float64 DFT, from the definition) on oims_lm's pixels, held
    [m, l] as this package's grids are, then turned by from_lm_image: its peak is left of the centre
    column (East on the left, as OIMS2fits and LWATV show the sky) and above the centre row."""
    rng = np.random.default_rng(3)
    n, lam = 32, 4.0
    xyz = rng.uniform(-40, 40, (64, 3)) * [1, 1, 0.02]
    lm = oims_lm(n)
    src = lm[20, 9]                                                   # row 20 (North), column 9 (East)
    phase = lambda l, m: np.exp(2j * np.pi / lam * (xyz[:, 0] * l + xyz[:, 1] * m))  # noqa: E731
    v = phase(*src)
    above = (lm ** 2).sum(axis=-1) < 1
    img_ml = np.zeros((n, n))
    # held as [m, l] with l increasing: column j of the OIMS image is l-index n - 1 - j
    for r in range(n):
        for c in range(n):
            if above[r, c]:
                img_ml[r, n - 1 - c] = abs(np.vdot(phase(*lm[r, c]), v)) ** 2
    oims = from_lm_image(img_ml)
    assert np.unravel_index(np.argmax(oims), oims.shape) == (20, 9)
    assert src[0] > 0 and 9 < (n - 1) / 2 and 20 > (n - 1) / 2


def test_a_pipeline_writes_the_sky_into_the_station_s_oims_file(tmp_path):
    """`output.oims` on the simulated sky (Cyg A alone, 80 deg up): one hourly file named as Orville names
    its own, two 0.5-s integrations of I, Q, U, V, the header's times, station and phase centre (the
    zenith: Dec within a degree of the station's latitude), and Cyg A's peak on the OIMS pixel that its
    direction, from astropy, falls in."""
    import astropy.units as u
    from astropy.coordinates import AltAz, SkyCoord
    from astropy.time import Time

    from bf_epic_blocks.pipeline import runner
    from bf_epic_blocks.pipeline.config import load_config
    from bf_epic_blocks.sky.catalogue import KNOWN_SOURCES

    n = 32
    cfg = load_config("pipelines/lwasv_sim_allsky.yaml", [
        "source.duration_s=1.0", "source.channels.count=4", "source.sources=[CygA]", "source.diffuse=null",
        "imager.grid.size=8", "output.png=false", "output.fits=false", f"output.dir={tmp_path}",
        f"output.oims={{ngrid: {n}, seconds: 0.5}}"])
    summary = runner.run(cfg, show_progress=False)
    files = sorted(tmp_path.glob("*.oims"))
    assert [f.name for f in files] == ["60462_100000_74.000MHz_74.075MHz.oims"]
    assert summary["oims"]["integrations"] == 2 and str(files[0]) in summary["files"]
    got = read_oims(files[0])
    h, e = got["header"], got["entries"]
    assert (h["version"], h["ngrid"], h["nchan"], h["stokes"], h["flags"]) == (6, n, 4, ["I", "Q", "U", "V"], 1)
    assert h["pixel_size"] == 130.0 / n and h["station"]
    t0 = Time("2024-06-01T10:00:00", scale="utc").mjd
    assert [x["start_time"] for x in e] == pytest.approx([t0, t0 + 0.5 / 86400], abs=1e-9)
    assert e[0]["int_len"] == pytest.approx(0.5 / 86400, rel=1e-9)
    assert (e[0]["start_freq"], e[0]["stop_freq"], e[0]["bandwidth"]) == (74e6, 74.075e6, 25e3)
    loc = runner.load_station_for(cfg, None, per_channel=False).location
    assert abs(e[0]["center_dec"] - loc.lat.deg) < 1.0 and e[0]["center_alt"] == 90.0
    mid = Time(t0 + 0.25 / 86400, format="mjd", scale="utc")
    cyg = KNOWN_SOURCES["CygA"]
    aa = SkyCoord(ra=cyg.ra_deg * u.deg, dec=cyg.dec_deg * u.deg).transform_to(AltAz(obstime=mid, location=loc))
    l, m = np.cos(aa.alt.rad) * np.sin(aa.az.rad), np.cos(aa.alt.rad) * np.cos(aa.az.rad)
    cell = np.radians(130.0 / n)
    want = (round(m / cell + (n - 1) / 2), round(-l / cell + (n - 1) / 2))
    img = got["data"][0, :, 0].sum(axis=0)                              # Stokes I, summed over the channels
    peak = np.unravel_index(np.argmax(img), img.shape)
    assert abs(peak[0] - want[0]) <= 1 and abs(peak[1] - want[1]) <= 1, (peak, want)
    # the LWATV view under Orville's names (1-s names: the second 0.5-s integration redraws the first),
    # of the band's middle channel, and the timestamp file
    png = tmp_path / "lwatv" / "60462" / "60462_100000_74.050MHz.png"
    assert str(png) in summary["files"]
    assert (tmp_path / "lwatv" / "lwatv_timestamp").read_text() == "60462:10:00:00"
    from matplotlib.image import imread
    pix = imread(png)
    assert pix.shape[1] > pix.shape[0] > 300 and pix[..., :3].std() > 0.05       # I and |V| side by side, drawn
    assert sorted(p.name for p in (tmp_path / "lwatv").rglob("*")) == ["60462", "60462_100000_74.050MHz.png",
                                                                         "lwatv_timestamp"]


def test_a_bad_oims_section_is_a_clear_error():
    from bf_epic_blocks.pipeline.config import load_config
    with pytest.raises(ValueError, match="output.oims.ngrid"):
        load_config("pipelines/lwasv_sim_allsky.yaml", ["output.oims={ngrid: 1}"])
    with pytest.raises(ValueError, match="output.oims.seconds"):
        load_config("pipelines/lwasv_sim_allsky.yaml", ["output.oims={seconds: 0}"])


def test_a_day_of_lwatv_views_becomes_one_movie(tmp_path):
    """`bf-epic movie FOLDER`: the folder's LWATV PNGs in time order, 'nomovie+' views left out, as an H.264
    MP4 that ffmpeg (imageio-ffmpeg's) reads back frame for frame; bad folders are clear errors."""
    pytest.importorskip("imageio_ffmpeg")
    import imageio_ffmpeg

    from bf_epic_blocks.io.quicklook import lwatv_png
    from bf_epic_blocks.pipeline.cli import main
    day = tmp_path / "lwatv" / "60462"
    # a spot that moves East to West (column 10, 16, 22) at 10:00:00, :05, :10, written out of order
    for hhmmss, col in (("100010", 22), ("100000", 10), ("100005", 16)):
        img = np.zeros((32, 32))
        img[14:18, col - 2:col + 2] = 1.0
        lwatv_png(day / f"60462_{hhmmss}_74.050MHz.png", img, None, 130 / 32, when=hhmmss)
    lwatv_png(day / "nomovie+60462_100000_38.100MHz.png", np.ones((32, 32)), None, 130 / 32)
    assert main(["movie", str(day), "--fps", "5"]) == 0
    out = tmp_path / "lwatv" / "60462.mp4"
    reader = imageio_ffmpeg.read_frames(str(out))
    meta = reader.__next__()
    frames = [np.frombuffer(f, np.uint8).reshape(meta["size"][1], meta["size"][0], 3).astype(int) for f in reader]
    assert len(frames) == 3 and meta["fps"] == 5
    # the spot (jet's red, R - B large) in the frames' order: columns rising, so the views went in by time
    cols = [int(np.argmax((f[..., 0] - f[..., 2]).clip(0).sum(axis=0))) for f in frames]
    assert cols[0] < cols[1] < cols[2], cols
    assert main(["movie", str(tmp_path / "none")]) == 2
    (tmp_path / "empty").mkdir()
    assert main(["movie", str(tmp_path / "empty")]) == 2

"""Chosen corruptions of the simulated voltages (sky.corrupt) and SimSkySourceBlock's pattern, diffuse
and corrupt options, against truth written here: the gains' statistics and drift, the block's sample
covariance against g_a g_b* (point sources x dipole pattern + the diffuse modes) x cables + noise
computed from positions, cable tables and the true gains, deaf and noisy inputs' powers, seeds, and
the path without options bit for bit as the simulator made it before them."""
import numpy as np
import pytest

from bf_epic_blocks.blocks import ArraySinkBlock, bfp
from bf_epic_blocks.blocks.sources import SimSkySourceBlock
from bf_epic_blocks.sky import fastsim
from bf_epic_blocks.sky.corrupt import GainCorruption
from bf_epic_blocks.station.tables import StationTable

C = 299792458.0
START = "2024-06-01T08:15:00"


def small_station(nstand=24, seed=5):
    """A synthetic LWA-SV-sited station: stands within ~25 m, cable delays and gains per input and
    channel (a table, as a header carries), two flagged inputs."""
    rng = np.random.default_rng(seed)
    xyz = np.c_[rng.uniform(-25, 25, (nstand, 2)), rng.uniform(-0.5, 0.5, nstand)]
    flags = np.zeros((nstand, 2), bool)
    flags[3, 0] = flags[10, 1] = True
    freq = 74e6 + 25e3 * np.arange(4)
    table = {"freq_hz": freq, "delay_s": rng.uniform(100e-9, 400e-9, (nstand, 2, 1)) * np.ones(freq.size),
             "gain": rng.uniform(0.05, 0.2, (nstand, 2, 1)) * np.ones(freq.size)}
    return StationTable("lwasv", 34.348358, -106.885783, 1477.8, np.arange(1, nstand + 1), xyz, flags,
                        np.full((nstand, 2), 33), None, table)


def run_block(station, freq, duration_s, sources, gulp=512, **kw):
    with bfp.Pipeline() as p:
        sim = SimSkySourceBlock(station, freq, START, duration_s, sources, gulp, **kw)
        sink = ArraySinkBlock(sim)
        p.run()
    run_block.header = sink.headers[0]
    return sim, sink.result(as_complex=not kw.get("quantize", True))


# ------------------------------------------------------------------ GainCorruption alone
def test_gains_statistics_delays_and_drift():
    c = GainCorruption(amplitude_rms=0.25, delay_ns_rms=30.0, drift_amplitude_frac=0.1, drift_phase_deg=20.0,
                       drift_over_s=100.0, seed=11)
    f = np.array([70e6, 71e6])
    g0 = c.gains(4000, 2, f, 0.0)
    amp = np.abs(g0[0])
    assert g0.shape == (2, 4000, 2) and g0.dtype == np.complex128
    assert abs(amp.mean() - 1) < 0.01 and abs(amp.std() / amp.mean() - 0.25) < 0.01 and amp.min() > 0
    tau = -np.angle(g0[1] / g0[0]) / (2 * np.pi * 1e6)               # |2 pi 1 MHz tau| < pi for |tau| < 500 ns
    assert abs(tau.std() - 30e-9) < 1.5e-9 and abs(tau.mean()) < 1.5e-9
    ph = np.angle(g0[0] * np.exp(2j * np.pi * f[0] * tau))             # the uniform phase per input
    assert abs(np.mean(np.exp(1j * ph))) < 0.05
    g1 = c.gains(4000, 2, f, 100.0)
    ratio = g1 / g0
    assert np.allclose(np.abs(ratio), 1 + 0.1 * np.sign(np.abs(ratio) - 1)[0], atol=1e-12)
    assert np.allclose(np.abs(np.angle(ratio)), np.radians(20), atol=1e-12)   # the same at every frequency
    assert 0.45 < np.mean(np.abs(ratio[0]) > 1) < 0.55                     # random signs
    flat = GainCorruption(amplitude_rms=0, delay_ns_rms=0, random_phase=False).gains(5, 2, f)
    assert np.array_equal(flat, np.ones((2, 5, 2)))


def test_seeds_deaf_and_noisy_inputs():
    c = GainCorruption(deaf=5, noisy=3, seed=2)
    usable = np.ones((40, 2), bool)
    usable[:10] = False
    d, n = c.deaf_mask(40, 2, usable=usable), c.noisy_mask(40, 2, usable=usable)
    assert d.sum() == 5 and n.sum() == 3 and not (d & n).any() and not ((d | n) & ~usable).any()
    f = np.array([74e6])
    assert np.array_equal(c.gains(40, 2, f, usable=usable), GainCorruption(deaf=5, noisy=3, seed=2).gains(
        40, 2, f, usable=usable))                                          # deterministic from the seed
    assert np.all(c.gains(40, 2, f, usable=usable)[0][d] == 0)
    assert not np.allclose(c.gains(40, 2, f), GainCorruption(seed=3).gains(40, 2, f))
    # asking for deaf inputs leaves the other inputs' gains as they were
    assert np.array_equal(c.gains(40, 2, f, usable=usable)[0][~d], GainCorruption(seed=2).gains(40, 2, f)[0][~d])
    e = GainCorruption(deaf=[(1, 0), (7, 1)], noisy=[(2, 1)], noisy_power=4.0)
    assert np.argwhere(e.deaf_mask(8, 2)).tolist() == [[1, 0], [7, 1]]
    w = e.noisy_weights(8, 2, 3, np.array([10.0, 20.0, 30.0]))
    assert w.shape == (3, 1, 8, 2) and np.count_nonzero(w) == 3
    assert np.allclose(2 * np.abs(w[:, 0, 2, 1]) ** 2, [40.0, 80.0, 120.0])   # noisy_power x median, both parts
    with pytest.raises(ValueError, match="usable"):
        GainCorruption(deaf=100).deaf_mask(40, 2, usable=usable)
    with pytest.raises(ValueError, match="outside"):
        GainCorruption(deaf=[(9, 0)]).deaf_mask(8, 2)
    with pytest.raises(ValueError):
        GainCorruption(amplitude_rms=-1)


def test_from_config_is_the_yaml_mapping():
    from bf_epic_blocks.pipeline.config import load_config
    cfg = load_config("source: {kind: simulated, seed: 9, corrupt: {delay_ns_rms: 5, drift: {phase_deg: 3}, "
                      "deaf: [[1, 0]], noisy: 2}}")
    c = GainCorruption.from_config(cfg["source"]["corrupt"], seed=cfg["source"]["seed"])
    assert c == GainCorruption(delay_ns_rms=5.0, drift_phase_deg=3.0, deaf=((1, 0),), noisy=2, seed=9)
    assert GainCorruption(**c.to_dict()) == c
    assert GainCorruption.from_config({}).seed == 0


# ------------------------------------------------------------------ the block
def test_no_option_path_is_the_simulator_as_before():
    """Without pattern, diffuse and corrupt the block's bytes are those of the generator driven as it
    always was: sky_weights of the sources with the cable factor, the scale from their expected rms,
    make_gulp over the whole run (every sample a function of its place, so one call equals the gulps)."""
    from bf_epic_blocks.sky import source_directions
    from bf_epic_blocks.sky.efield import cable_factor
    st = small_station()
    freq = 74e6 + 25e3 * np.arange(4)
    srcs = ["CygA", {"name": "A", "flux_jy": 3000.0, "l": 0.3, "m": -0.2}]
    for quantize in (True, False):
        sim, got = run_block(st, freq, 0.08, srcs, quantize=quantize, seed=4, refresh_s=10.0)
        d = source_directions(srcs, sim.start, st.location)
        cab = cable_factor(np.moveaxis(st.cable_delay_s(freq), -1, 0), np.moveaxis(st.cable_gain(freq), -1, 0), freq,
                           freq.size, st.nstand, 2)
        w = fastsim.sky_weights(st.xyz_m, freq, d.l, d.m, d.n, np.stack([s.flux_at(freq) for s in d.sources], 1), cab)
        on0, on1 = fastsim.burst_windows(len(d.sources), [], freq, sim.dt_s)
        want = np.empty((sim.nframe, freq.size, st.nstand, 2), np.uint8 if quantize else np.complex64)
        scale = 2.0 / fastsim.expected_rms(w, 1000.0) if quantize else None
        fastsim.make_gulp(want, 0, w, on0, on1, fastsim.stream_keys(4), 1000.0, scale)
        raw = np.ascontiguousarray(got).view(np.uint8).reshape(want.shape) if quantize else got
        assert np.array_equal(raw, want)
        assert sim.truth()["deaf"].sum() == 0 and np.array_equal(sim.true_gains(0.05), np.ones((4, st.nstand, 2)))


def test_refreshes_take_their_directions_from_one_batched_call(monkeypatch):
    """The sources' and a burst's directions at every refresh come from one astropy call each for the run
    (source_directions_at), and the bytes are those of the generator driven refresh by refresh with
    source_directions at each refresh's own time (the truth), the burst's window from its DM."""
    from astropy.time import TimeDelta

    from bf_epic_blocks.sky import catalogue, source_directions
    from bf_epic_blocks.sky.efield import cable_factor
    calls = []
    real = catalogue.source_directions_at
    monkeypatch.setattr(catalogue, "source_directions_at", lambda *a, **k: calls.append(1) or real(*a, **k))
    st = small_station()
    freq = 74e6 + 25e3 * np.arange(4)
    srcs = ["CygA", "CasA", {"name": "A", "flux_jy": 3000.0, "l": 0.3, "m": -0.2}]
    burst = {"name": "B", "ra_deg": 310.0, "dec_deg": 20.0, "flux_jy": 5000.0, "start_s": 0.02, "duration_s": 0.01,
             "dm": 0.3}
    gulp = 512
    sim, got = run_block(st, freq, 4 * gulp * 40e-6, srcs, gulp=gulp, quantize=True, seed=4, refresh_s=gulp * 40e-6,
                         transients=[burst])
    assert [p for p, _ in sim.truth()["refreshes"]] == [0, 512, 1024, 1536]
    assert len(calls) == 2                          # the sources, the burst: once each for the run
    cab = cable_factor(np.moveaxis(st.cable_delay_s(freq), -1, 0), np.moveaxis(st.cable_gain(freq), -1, 0), freq,
                       freq.size, st.nstand, 2)
    want = np.empty((sim.nframe, freq.size, st.nstand, 2), np.uint8)
    scale = None
    for p in (0, 512, 1024, 1536):
        t = sim.start + TimeDelta(p * sim.dt_s, format="sec")
        d = source_directions(srcs, t, st.location)
        b = source_directions([{k: burst[k] for k in ("name", "ra_deg", "dec_deg", "flux_jy")}], t, st.location)
        flux = np.stack([s.flux_at(freq) for s in d.sources + b.sources], 1)
        w = fastsim.sky_weights(st.xyz_m, freq, np.r_[d.l, b.l], np.r_[d.m, b.m], np.r_[d.n, b.n], flux, cab)
        on0, on1 = fastsim.burst_windows(len(d.sources), [burst], freq, sim.dt_s)
        if scale is None:
            scale = 2.0 / fastsim.expected_rms(w[:, :len(d.sources)], 1000.0)
        fastsim.make_gulp(want[p:p + gulp], p, w, on0, on1, fastsim.stream_keys(4), 1000.0, scale)
    assert np.array_equal(np.ascontiguousarray(got).view(np.uint8).reshape(want.shape), want)


def test_source_directions_at_is_source_directions_at_each_time():
    """Bit for bit, for ICRS sources, a body, alt-az and (l, m) sources, and sources that set in between."""
    from astropy.time import Time, TimeDelta

    from bf_epic_blocks.sky.catalogue import SUN, source_directions, source_directions_at
    st = small_station()
    srcs = ["CygA", "TauA", "VirA", SUN, {"name": "Z", "flux_jy": 1.0, "az_deg": 10.0, "alt_deg": 30.0},
            {"name": "L", "flux_jy": 1.0, "l": 0.1, "m": 0.2}]
    times = Time(START, scale="utc") + TimeDelta(np.arange(0, 12 * 3600, 1800.0), format="sec")
    many = source_directions_at(srcs, times, st.location)
    dropped = set()
    for t, got in zip(times, many):
        want = source_directions(srcs, t, st.location)
        assert got.names == want.names and got.dropped == want.dropped
        for a, b in zip((*got, got.az, got.n), (*want, want.az, want.n)):
            assert np.array_equal(a, b)
        dropped |= set(got.dropped)
    assert {"TauA", "VirA", "Sun"} & dropped        # some set or rise within the twelve hours


def dipole(l, m):
    """(nsrc, 2) the short dipole's voltage pattern: X (N-S) sqrt(1 - m^2), Y (E-W) sqrt(1 - l^2)."""
    return np.stack([np.sqrt(1 - m ** 2), np.sqrt(1 - l ** 2)], axis=-1)


@pytest.fixture(scope="module")
def corrupted_run():
    st = small_station()
    freq = 74e6 + 25e3 * np.arange(2)
    srcs = [{"name": "A", "flux_jy": 60000.0, "l": 0.3, "m": -0.2}, {"name": "B", "flux_jy": 25000.0, "l": -0.5,
                                                                     "m": 0.6}]
    corrupt = GainCorruption(amplitude_rms=0.3, delay_ns_rms=40.0, drift_amplitude_frac=0.2, drift_phase_deg=60.0,
                             drift_over_s=0.16384, deaf=2, noisy=2, noisy_power=3.0, seed=7)
    # 8192 samples, a refresh at sample 4096: two stretches with different (drifted) gains
    sim, x = run_block(st, freq, 8192 * 40e-6, srcs, quantize=False, seed=8, refresh_s=4096 * 40e-6,
                       pattern="dipole", diffuse={"nmode": 6, "scale": 0.02}, corrupt=corrupt, noise_power=2000.0)
    return st, freq, srcs, sim, x.astype(np.complex128)


def model_covariance(st, freq, srcs, sim, gains, with_noise=True):
    """The expected covariance (nchan, npol, nstand, nstand) from the data model written here."""
    tr = sim.truth()
    l = np.array([s["l"] for s in srcs])
    m = np.array([s["m"] for s in srcs])
    n = np.sqrt(1 - l ** 2 - m ** 2)
    b2 = dipole(l, m) ** 2                                                           # (nsrc, 2)
    cab_tau = st.cable_delay_s(freq)                                                 # (nstand, 2, nchan)
    cab_g = st.cable_gain(freq)
    wd = tr["diffuse_weights"]                                                       # (nchan, nmode, nstand, 2)
    out = np.zeros((freq.size, 2, st.nstand, st.nstand), np.complex128)
    for c, nu in enumerate(freq):
        ph = np.exp(2j * np.pi * nu / C * (st.xyz_m @ np.stack([l, m, n])))           # (nstand, nsrc)
        for p in range(2):
            sky = (ph * (np.array([s["flux_jy"] for s in srcs]) / 2 * b2[:, p])) @ ph.conj().T
            sky += 2 * wd[c, :, :, p].T @ wd[c, :, :, p].conj()
            v = np.sqrt(cab_g[:, p, c]) * np.exp(-2j * np.pi * nu * cab_tau[:, p, c]) * gains[c, :, p]
            out[c, p] = v[:, None] * sky * v.conj()[None, :]
            if with_noise:
                out[c, p] += np.diag(sim.noise_power + tr["noisy"][:, p] * tr["noisy_power"] * tr["median_power"][c])
    return out


def whitened(x, model):
    """sqrt(T) (L^-1 R_hat L^-H - 1) per (chan, pol), with model = L L^H: for complex Gaussian data of
    that covariance, entries of unit rms, independent of each other (strongly correlated antennas
    make the raw differences R_hat - R move together; whitening takes that out)."""
    T = x.shape[0]
    rhat = np.einsum("tcap,tcbp->cpab", x, x.conj()) / T
    out = np.empty_like(rhat)
    for c in range(rhat.shape[0]):
        for p in range(rhat.shape[1]):
            li = np.linalg.inv(np.linalg.cholesky(model[c, p]))
            out[c, p] = np.sqrt(T) * (li @ rhat[c, p] @ li.conj().T - np.eye(len(li)))
    return out, rhat


def test_sample_covariance_is_gains_times_model_plus_noise(corrupted_run):
    """Each stretch's sample covariance equals g_a g_b* (sources x dipole + diffuse modes) x cables +
    noise within the sampling noise (whitened, unit-rms differences), with the gains true_gains reports for it;
    the other stretch's gains (the drift) or no gains at all do not fit."""
    st, freq, srcs, sim, x = corrupted_run
    tr = sim.truth()
    assert [p for p, _ in tr["refreshes"]] == [0, 4096]
    good = ~tr["flags"]
    stretches = [(0, 4096, sim.true_gains(0.0)), (4096, 8192, sim.true_gains(0.2))]
    assert not np.allclose(stretches[0][2], stretches[1][2])
    for a, b, g in stretches:
        z, rhat = whitened(x[a:b], model_covariance(st, freq, srcs, sim, g))
        rms = np.sqrt(np.mean(np.abs(z) ** 2, axis=(0, 2, 3)))
        assert np.all((0.95 < rms) & (rms < 1.05)) and np.abs(z).max() < 6, (a, rms, np.abs(z).max())
        cross = np.einsum("tca,tcb->cab", x[a:b, :, :, 0], x[a:b, :, :, 1].conj()) / (b - a)
        dx, dy = np.real(np.einsum("caa->ca", rhat[:, 0])), np.real(np.einsum("caa->ca", rhat[:, 1]))
        zc = cross / np.sqrt(dx[:, :, None] * dy[:, None, :] / (b - a))
        assert np.sqrt(np.mean(np.abs(zc) ** 2)) < 1.1                                 # X and Y independent
    # the wrong gains are seen: the other stretch's (the drift) and none
    z, _ = whitened(x[4096:], model_covariance(st, freq, srcs, sim, stretches[0][2]))
    assert np.sqrt(np.mean(np.abs(z) ** 2)) > 3
    z, _ = whitened(x[:4096], model_covariance(st, freq, srcs, sim, np.ones_like(stretches[0][2])))
    assert np.sqrt(np.mean(np.abs(z) ** 2)) > 3


def test_deaf_and_noisy_inputs_and_the_median_power(corrupted_run):
    """Deaf inputs carry the receiver noise alone (and correlate with nothing); a noisy input's power
    exceeds its sky + noise by noisy_power x the median input's power, that median being the model's
    over the unflagged inputs that are neither deaf nor noisy."""
    st, freq, srcs, sim, x = corrupted_run
    tr = sim.truth()
    deaf, noisy, good = tr["deaf"], tr["noisy"], ~tr["flags"]
    assert deaf.sum() == 2 and noisy.sum() == 2 and not ((deaf | noisy) & tr["flags"]).any()
    T = 4096
    xs = x[:T]
    power = np.mean(np.abs(xs) ** 2, axis=0)                                          # (nchan, nstand, 2)
    tol = 5 * np.sqrt(1.0 / T)
    assert np.all(np.abs(power[:, deaf] / sim.noise_power - 1) < tol)
    g0 = sim.true_gains(0.0)
    assert np.all(g0[:, deaf] == 0)
    sky_noise = model_covariance(st, freq, srcs, sim, g0, with_noise=False)
    sky_noise = np.real(np.einsum("cpaa->cap", sky_noise)) + sim.noise_power         # (nchan, nstand, 2)
    median = np.median(sky_noise[:, good & ~deaf & ~noisy], axis=1)
    assert np.allclose(tr["median_power"], median, rtol=1e-5)
    extra = power[:, noisy] - sky_noise[:, noisy]
    want = tr["noisy_power"] * median[:, None]
    assert np.all(np.abs(extra / want - 1) < tol * power[:, noisy] / want)
    # deaf inputs correlate with nothing: |R_ab| at the noise floor
    for c in range(freq.size):
        for s, p in np.argwhere(deaf):
            r = xs[:, c, :, p].conj().T @ xs[:, c, s, p] / T
            rr = np.sqrt(power[c, :, p] * power[c, s, p] / T)
            others = np.arange(st.nstand) != s
            assert np.all(np.abs(r[others]) < 5 * rr[others])


def test_seeds_repeat_and_the_header_records_the_options():
    st = small_station()
    freq = 74e6 + 25e3 * np.arange(2)
    kw = dict(quantize=True, seed=3, pattern="dipole", corrupt={"deaf": 1, "noisy": 1, "seed": 5},
              diffuse={"nmode": 4, "scale": 0.02})
    sim1, a = run_block(st, freq, 0.02, ["CygA"], **kw)
    sim2, b = run_block(st, freq, 0.02, ["CygA"], **kw)
    assert np.array_equal(np.asarray(a).view(np.uint8), np.asarray(b).view(np.uint8))
    kw["corrupt"] = {"deaf": 1, "noisy": 1, "seed": 6}
    sim3, c = run_block(st, freq, 0.02, ["CygA"], **kw)
    assert not np.array_equal(np.asarray(a).view(np.uint8), np.asarray(c).view(np.uint8))
    assert not np.array_equal(sim1.truth()["deaf"], sim3.truth()["deaf"]) or \
        not np.allclose(sim1.true_gains(0), sim3.true_gains(0))
    simh = run_block.header["simulation"]
    assert simh["pattern"] == "dipole" and simh["diffuse"] == {"scale": 0.02, "nmode": 4, "refresh_s": 60.0}
    assert simh["corrupt"]["seed"] == 6 and simh["corrupt"]["amplitude_rms"] == 0.25 and simh["corrupt"]["deaf"] == 1
    # the 4-bit scale comes from every column: the quantised parts' rms is ~2 units
    from bf_epic_blocks.io.tbf import unpack_ci4
    q = unpack_ci4(np.asarray(a).view(np.uint8))
    rms = np.sqrt(np.mean(np.concatenate([q.real.ravel(), q.imag.ravel()]) ** 2))
    assert 1.6 < rms < 2.4

"""The gain solver (imaging.skycal) against truth the tests choose: gains, deaf and noisy inputs,
covariances sampled with the statistics of T samples, and the model from its definition."""
import math

import numpy as np
import pytest

from bf_epic_blocks.imaging import skycal
from bf_epic_blocks.imaging._xp import to_numpy

C = 299792458.0


def lwasv():
    from bf_epic_blocks.station.tables import load_station
    return load_station("lwasv")


def two_sources(nchan, npol=2):
    lmn = np.array([[0.10, 0.15, math.sqrt(1 - 0.01 - 0.0225)], [-0.30, 0.50, math.sqrt(1 - 0.09 - 0.25)]])
    flux = np.broadcast_to(np.array([17000.0, 17000.0])[None, :, None] / 2, (nchan, 2, npol)).copy()
    return lmn, flux


def sample_covariance(Rt, T, rng):
    """R_hat = (1/T) sum_t x x^H for T independent x ~ CN(0, Rt), drawn through Bartlett's
    decomposition of the complex Wishart (O(n^3), whatever T): the sampling noise of T samples."""
    out = np.empty_like(Rt)
    n = Rt.shape[-1]
    for idx in np.ndindex(Rt.shape[:-2]):
        L = np.linalg.cholesky(Rt[idx])
        A = np.tril((rng.standard_normal((n, n)) + 1j * rng.standard_normal((n, n))) / math.sqrt(2), -1)
        A[np.arange(n), np.arange(n)] = np.sqrt(rng.chisquare(2 * (T - np.arange(n))) / 2)
        LA = L @ A
        out[idx] = LA @ LA.conj().T / T
    return out


def corrupted(xyz, f, rng, *, deaf=(), noisy=(), noise=1000.0, noisy_power=2e5, delay_rms=30e-9):
    """(true gains (c, a, p), true covariance (c, p, a, a), model M) for two sources."""
    nant = len(xyz)
    lmn, flux = two_sources(f.size)
    M = skycal.model_covariance(xyz, f, lmn, flux)
    amp = np.exp(0.25 * rng.standard_normal((nant, 2)))
    tau = delay_rms * rng.standard_normal((nant, 2))
    ph = rng.uniform(0, 2 * np.pi, (nant, 2))
    g = amp[None] * np.exp(1j * (ph[None] - 2 * np.pi * f[:, None, None] * tau[None]))
    for a, p in deaf:
        g[:, a, p] = 0
    G = g.transpose(0, 2, 1)
    Rt = G[..., :, None] * np.conj(G[..., None, :]) * M
    i = np.arange(nant)
    Rt[..., i, i] += noise
    for a, p in noisy:
        Rt[:, p, a, a] += noisy_power
    return g, Rt, M


def test_model_covariance_is_the_definition():
    rng = np.random.default_rng(3)
    xyz = rng.uniform(-50, 50, (6, 3))
    f = np.array([60e6, 74e6])
    lmn, flux = two_sources(2)
    flux[:, 1, 1] *= 0.5                                   # pols differ
    M = skycal.model_covariance(xyz, f, lmn, flux)
    for c in range(2):
        for p in range(2):
            for a in range(6):
                for b in range(6):
                    want = sum(flux[c, s, p] * np.exp(2j * np.pi * f[c] / C * lmn[s] @ (xyz[a] - xyz[b]))
                               for s in range(2))
                    assert abs(M[c, p, a, b] - want) < 1e-9 * abs(flux).max()


@pytest.mark.parametrize("dtype,tol", [(np.complex128, 1e-6), (np.complex64, 1e-4)])
def test_noiseless_gains_recovered_exactly(xp, dtype, tol):
    st = lwasv()
    f = 74e6 + 25e3 * np.arange(3)
    rng = np.random.default_rng(1)
    g, Rt, M = corrupted(st.xyz_m, f, rng, noise=0.0)
    sol = skycal.solve_gains(xp.asarray(Rt.astype(dtype)), xp.asarray(M.astype(dtype)), st.xyz_m, f, st.flags,
                             skycal.SolveSettings(smooth_channels=1, tol=tol / 100, max_iter=500))
    good = ~sol.flags
    assert good.sum() == (~st.flags).sum()
    err, per = skycal.gain_error(sol.corrections, g, good)
    assert err < tol
    # the amplitude scale is observable: |c g| = 1 (calibrated data on the model's flux scale)
    e = sol.corrections * g
    assert np.allclose(np.abs(e[:, good]), 1, atol=tol)


@pytest.mark.parametrize("T", [50000])
def test_sampled_covariance_with_deaf_and_noisy_inputs(T):
    st = lwasv()
    f = 74e6 + 25e3 * np.arange(12)
    rng = np.random.default_rng(7)
    good0 = ~st.flags
    cand = np.argwhere(good0)
    pick = cand[rng.choice(len(cand), 6, replace=False)]
    deaf, noisy = [tuple(x) for x in pick[:3]], [tuple(x) for x in pick[3:]]
    g, Rt, M = corrupted(st.xyz_m, f, rng, deaf=deaf, noisy=noisy)
    R = sample_covariance(Rt, T, rng)
    sol = skycal.solve_gains(R, M, st.xyz_m, f, st.flags)
    for a, p in deaf:
        assert sol.reasons[a, p] == "deaf"
    for a, p in noisy:
        assert sol.reasons[a, p] == "noisy"
    wrongly = sol.flags & good0
    for a, p in deaf + noisy:
        wrongly[a, p] = False
    assert wrongly.sum() <= 0.01 * good0.sum()
    err, _ = skycal.gain_error(sol.corrections, g, ~sol.flags)
    # 2 x 8,500 Jy per pol against 1,000 of noise, 50,000 samples, ~230 inputs: ~0.1% per channel
    assert err < 0.005, err
    assert (sol.corrections[:, sol.flags] == 0).all()
    # a live solver's next solve starts from this one's gains and health flags: the same flags and
    # accuracy from fewer iterations (one round instead of two)
    g0 = sol.gains.transpose(0, 2, 1)
    warm = skycal.solve_gains(R, M, st.xyz_m, f, st.flags, g0=g0)
    nxt = skycal.solve_gains(R, M, st.xyz_m, f, st.flags, g0=g0, flags0=sol.reasons)
    assert (nxt.reasons == sol.reasons).all()
    assert skycal.gain_error(nxt.corrections, g, ~nxt.flags)[0] < 0.005
    assert nxt.info["iterations"] < warm.info["iterations"] < sol.info["iterations"]


def test_smoothing_recovers_cable_delays():
    st = lwasv()
    f = 50e6 + 300e3 * np.arange(64)                       # 19.2 MHz: delays of tens of ns are visible
    rng = np.random.default_rng(11)
    g, Rt, M = corrupted(st.xyz_m, f, rng, noise=2e5, delay_rms=40e-9)
    R = sample_covariance(Rt, 2000, rng)
    raw = skycal.solve_gains(R, M, st.xyz_m, f, st.flags, skycal.SolveSettings(smooth_channels=1))
    sm = skycal.solve_gains(R, M, st.xyz_m, f, st.flags, skycal.SolveSettings(smooth_channels=64))
    good = ~raw.flags & ~sm.flags
    e_raw, _ = skycal.gain_error(raw.corrections, g, good)
    e_sm, _ = skycal.gain_error(sm.corrections, g, good)
    assert e_sm < 0.5 * e_raw, (e_sm, e_raw)
    # the fitted delays are the chosen ones relative to the reference input's
    tau_true = -np.angle(g[1] / g[0]) / (2 * np.pi * (f[1] - f[0]))      # from the truth, per input
    for p in range(2):
        ref = sm.info["reference"][p]
        d_fit = sm.quality["delay_s"][:, p] - sm.quality["delay_s"][ref, p]
        d_true = tau_true[:, p] - tau_true[ref, p]
        sel = good[:, p]
        assert np.sqrt(np.mean((d_fit[sel] - d_true[sel]) ** 2)) < 2e-9


def test_covariance_sums_ci4_and_complex_match_the_definition(xp):
    from bf_epic_blocks.io.tbf import pack_ci4
    rng = np.random.default_rng(5)
    q = rng.integers(-8, 8, (300, 3, 7, 2)) + 1j * rng.integers(-8, 8, (300, 3, 7, 2))
    want = np.einsum("tcap,tcbp->cpab", q, q.conj())
    s_int = skycal.CovarianceSums(3, 7, 2, xp, chunk=2)          # two chunks of channels
    rows = set()
    for t0 in (0, 100, 200):
        s_int.add(xp.asarray(pack_ci4(q[t0:t0 + 100])), ci4=True)
        if xp is not np:
            rows.add(s_int._rows._slots[0][0].data.ptr)
    # on a GPU every chunk of every gulp lays its int8 rows into one kept array (a new one each chunk
    # split the pool's blocks under the station's pool limit)
    assert len(rows) == (1 if xp is not np else 0)
    s_cpx = skycal.CovarianceSums(3, 7, 2, xp)
    s_cpx.add(xp.asarray(q.astype(np.complex64)))
    assert np.array_equal(to_numpy(s_int.sum), want)
    assert np.allclose(to_numpy(s_cpx.sum), want, rtol=1e-6, atol=1e-3)
    assert np.allclose(to_numpy(s_int.mean()), want / 300)


def test_fitted_scale_is_the_chosen_one_and_the_least_squares_definition(xp):
    """fit_scale against truth: R made exactly of g g* (M + s E) gives back the chosen s per channel and
    pol; with noise added, the result is the least-squares minimiser written out elementwise in float64
    here (the residual's derivative in s is zero there), and a negative optimum is clipped to 0."""
    rng = np.random.default_rng(21)
    c, p, n = 3, 2, 24
    cplx = lambda *sh: rng.standard_normal(sh) + 1j * rng.standard_normal(sh)
    M, E = cplx(c, p, n, n), cplx(c, p, n, n)
    g = cplx(c, p, n)
    W = (rng.uniform(size=(c, 1, n, n)) > 0.3).astype(float)
    s_true = rng.uniform(0.2, 3.0, (c, p))
    GG = g[..., :, None] * np.conj(g[..., None, :])
    R = GG * (M + s_true[..., None, None] * E)
    cdt = np.complex128 if xp is np else xp.complex64
    got = to_numpy(skycal.fit_scale(*(xp.asarray(a.astype(cdt)) for a in (R, M, E, g)), xp.asarray(W)))
    assert np.allclose(got, s_true, rtol=1e-10 if xp is np else 2e-4)
    Rn = R + 5.0 * cplx(c, p, n, n)
    A = GG * E
    want = (W * np.conj(A) * (Rn - GG * M)).real.sum((-1, -2)) / (W * np.abs(A) ** 2).sum((-1, -2))
    got = to_numpy(skycal.fit_scale(*(xp.asarray(a.astype(cdt)) for a in (Rn, M, E, g)), xp.asarray(W)))
    assert np.allclose(got, np.clip(want, 0, None), rtol=1e-9 if xp is np else 1e-3, atol=1e-6)
    resid = lambda s: (W * np.abs(Rn - GG * (M + s[..., None, None] * E)) ** 2).sum((-1, -2))
    assert np.all(resid(want) <= resid(want * 1.01)) and np.all(resid(want) <= resid(want * 0.99))
    neg = to_numpy(skycal.fit_scale(*(xp.asarray(a.astype(cdt)) for a in (GG * (M - E), M, E, g)), xp.asarray(W)))
    assert np.all(neg == 0)


def test_input_health_figures_are_their_definitions(xp):
    """input_health's residual, power and baseline count against the sums written out here, with one
    input left out of the solve (its baselines do not count for the others)."""
    rng = np.random.default_rng(22)
    c, p, n = 5, 2, 12
    cplx = lambda *sh: rng.standard_normal(sh) + 1j * rng.standard_normal(sh)
    R, M, g = cplx(c, p, n, n), cplx(c, p, n, n), cplx(c, p, n)
    R = R + np.conj(R.swapaxes(-1, -2)) + 10 * np.eye(n)
    W = (rng.uniform(size=(c, n, n)) > 0.2).astype(float)
    live = np.ones((p, n), bool)
    live[1, 4] = False
    h = skycal.input_health(*(xp.asarray(a) for a in (R, M, W, g)), live)
    Wl = W[:, None] * live[None, :, :, None] * live[None, :, None, :]
    fit = g[..., :, None] * np.conj(g[..., None, :]) * M
    ref = (Wl * np.abs(fit) ** 2).sum(-1)
    res = np.where(ref > 0, (Wl * np.abs(R - fit) ** 2).sum(-1) / np.where(ref > 0, ref, 1), np.inf)
    assert np.allclose(h["residual"], np.median(res, axis=0).T, rtol=1e-10)
    assert np.allclose(h["power"], np.median(np.einsum("cpaa->cpa", R).real, axis=0).T)
    assert np.allclose(h["gain_amp"], np.median(np.abs(g), axis=0).T)
    assert np.array_equal(h["baselines"], np.median((Wl > 0).sum(-1), axis=0).T)


def test_bad_input_is_a_clear_error():
    st = lwasv()
    f = np.array([74e6])
    lmn, flux = two_sources(1)
    M = skycal.model_covariance(st.xyz_m, f, lmn, flux)
    R = M.copy()
    with pytest.raises(ValueError, match="model is empty"):
        skycal.solve_gains(R, np.zeros_like(M), st.xyz_m, f, st.flags)
    with pytest.raises(ValueError, match="no baseline is longer"):
        skycal.solve_gains(R, M, st.xyz_m, f, st.flags, skycal.SolveSettings(min_baseline_lambda=1e6))
    flags = np.ones_like(st.flags)
    flags[:5] = False
    with pytest.raises(ValueError, match="inputs of pol 0 are good"):
        skycal.solve_gains(R, M, st.xyz_m, f, flags)
    with pytest.raises(ValueError, match="out of range"):
        skycal.SolveSettings(noisy_above=0.5)


def test_sky_model_places_the_sun_and_applies_the_pattern():
    from astropy.time import Time

    from bf_epic_blocks.sky.model import sky_model
    st = lwasv()
    # solar noon at LWA-SV (longitude -106.9 deg) near the June solstice: the Sun due South, at
    # 90 - (latitude - declination) = 90 - (34.35 - 23.44) ~ 79.1 deg
    t = Time("2024-06-21T19:09:00", scale="utc")
    m = sky_model(["Sun", "CygA"], t, st.location, [74e6], pattern="dipole", min_alt_deg=0)
    i = m.names.index("Sun")
    assert abs(m.alt_deg[i] - 79.1) < 0.5
    l, mm, n = m.lmn[i]
    assert abs(l) < 0.02 and mm < 0                        # South: m < 0
    # the short dipole's power pattern: X (N-S) 1 - m^2, Y (E-W) 1 - l^2
    assert np.isclose(m.flux_pol[0, i, 0], 8000 * (1 - mm ** 2))
    assert np.isclose(m.flux_pol[0, i, 1], 8000 * (1 - l ** 2))
    low = sky_model(["CygA"], Time("2024-06-01T20:00:00"), st.location, [74e6], min_alt_deg=89.9)
    assert low.names == [] and low.dropped == ["CygA"]


def test_the_galactic_sky_biases_a_point_model_and_its_fitted_term_removes_the_bias():
    """LWA-SV at 74 MHz under the analytic Galactic sky (~1e6 Jy per antenna) plus two sources the
    model lacks: a point-source model with a 4-wavelength cut is biased by >10%; the model with the
    diffuse term (scale fitted) recovers the gains to ~1%, and finds the brightness it was given."""
    from astropy.time import Time

    from bf_epic_blocks.sky.diffuse import diffuse_covariance
    from bf_epic_blocks.sky.model import diffuse_model, sky_model
    st = lwasv()
    f = 74e6 + 25e3 * np.arange(4)
    t = Time("2024-06-01T10:00:00")
    sky = diffuse_covariance(st.xyz_m, f, t, st.location, pattern="dipole", scale=0.8)   # 20% fainter than the model
    E = diffuse_model(st.xyz_m, f, t, st.location, pattern="dipole")
    m = sky_model(["CygA", "CasA", "TauA", "VirA"], t, st.location, f, pattern="dipole")
    Mp = skycal.model_covariance(st.xyz_m, f, m.lmn, m.flux_pol)
    un = sky_model([{"name": "X1", "flux_jy": 1500.0, "l": 0.3, "m": -0.2},
                    {"name": "X2", "flux_jy": 1000.0, "l": -0.5, "m": -0.4}], t, st.location, f, pattern="dipole")
    Mu = skycal.model_covariance(st.xyz_m, f, un.lmn, un.flux_pol)
    rng = np.random.default_rng(2)
    amp = np.exp(0.25 * rng.standard_normal((256, 2)))
    g = amp[None] * np.exp(1j * (rng.uniform(0, 2 * np.pi, (256, 2))[None]
                                 - 2 * np.pi * f[:, None, None] * 30e-9 * rng.standard_normal((256, 2))[None]))
    G = g.transpose(0, 2, 1)
    Rt = G[..., :, None] * np.conj(G[..., None, :]) * (Mp + Mu + sky)
    i = np.arange(256)
    Rt[..., i, i] += 1000.0
    R = sample_covariance(Rt, 50000, rng)
    point = skycal.solve_gains(R, Mp, st.xyz_m, f, st.flags)
    both = skycal.solve_gains(R, Mp, st.xyz_m, f, st.flags, extra=E)
    e_point, _ = skycal.gain_error(point.corrections, g, ~point.flags)
    e_both, _ = skycal.gain_error(both.corrections, g, ~both.flags)
    assert e_point > 0.10, e_point
    assert e_both < 0.03, e_both          # 4 channels to smooth over; 12 give ~1% (bench_calibration)
    s = np.asarray(both.info["extra_scale"])       # a nuisance parameter, found to ~15% here
    assert (s > 0.7).all() and (s < 1.0).all(), s


def test_saturated_inputs_are_flagged_with_their_reason():
    st = lwasv()
    f = np.array([74e6, 74.025e6])
    rng = np.random.default_rng(4)
    g, Rt, M = corrupted(st.xyz_m, f, rng, noise=1000.0)
    sat = np.zeros_like(st.flags)
    sat[[3, 40], [0, 1]] = True
    sol = skycal.solve_gains(Rt, M, st.xyz_m, f, st.flags, saturated=sat)
    assert sol.reasons[3, 0] == sol.reasons[40, 1] == "saturated"
    assert (sol.corrections[:, 3, 0] == 0).all()
    # 4-bit levels -8..7: a Gaussian of rms 2 per part clips ~1e-4 of its samples, of rms 3.2 ~1.4%
    assert skycal.clip_fraction(8.0) < 2e-4 and 0.01 < skycal.clip_fraction(2 * 3.2 ** 2) < 0.02


def test_the_diffuse_model_on_a_gpu_is_the_cpus(xp):
    """diffuse_model's own GEMMs (CuPy) against sky.diffuse's covariance (NumPy, scipy's cherk)."""
    from astropy.time import Time

    from bf_epic_blocks.sky.diffuse import diffuse_covariance
    from bf_epic_blocks.sky.model import diffuse_model
    st = lwasv()
    f = np.array([60e6, 74e6])
    t = Time("2024-06-01T10:00:00")
    want = diffuse_covariance(st.xyz_m, f, t, st.location, pattern="dipole")
    got = to_numpy(diffuse_model(st.xyz_m, f, t, st.location, pattern="dipole", xp=xp))
    assert np.abs(got - want).max() < 2e-5 * np.abs(want).max()


def test_the_diffuse_model_s_gpu_form_in_small_chunks_is_the_cpus(monkeypatch):
    """The GPU form's arithmetic (phases a channel at a time from the float64 path, GEMMs over the pixels),
    run here with NumPy behind another namespace, against sky.diffuse's covariance, complex64 and
    complex128."""
    import types

    from astropy.time import Time

    from bf_epic_blocks.sky import model
    from bf_epic_blocks.sky.diffuse import diffuse_covariance
    st = lwasv()
    f = np.array([38e6, 60e6, 74e6])
    t = Time("2024-06-01T10:00:00")
    want = diffuse_covariance(st.xyz_m, f, t, st.location, pattern="dipole")
    ns = types.ModuleType("numpy_as_another_namespace")
    ns.__dict__.update(np.__dict__)
    monkeypatch.setattr(model, "DIFFUSE_CHUNK_BYTES", 1)          # one channel at a time
    for dtype in (np.complex64, np.complex128):
        got = model.diffuse_model(st.xyz_m, f, t, st.location, pattern="dipole", xp=ns, dtype=dtype)
        assert got.dtype == dtype and got.shape == want.shape
        assert np.abs(got - want).max() < 2e-6 * np.abs(want).max()


@pytest.mark.gpu
def test_gpu_the_diffuse_model_needs_its_output_and_its_chunks_only():
    """A live solver's first diffuse model (64 channels of LWA-SV here, 784 on a station) adds at most its
    output, the path and one chunk of phases to the GPU memory in use: it once formed float64 and complex128
    copies of every 64 channels' phases (~8 GB), the station's highest peak."""
    cp = pytest.importorskip("cupy")
    if not cp.cuda.is_available():
        pytest.skip("no GPU")
    from astropy.time import Time

    from bf_epic_blocks.sky import model
    st = lwasv()
    f = 74e6 + 25e3 * np.arange(64)
    t = Time("2024-06-01T10:00:00")
    pool = cp.get_default_memory_pool()
    peak = [0]

    def alloc(size):
        p = pool.malloc(size)
        peak[0] = max(peak[0], pool.used_bytes())
        return p
    base = pool.used_bytes()
    cp.cuda.set_allocator(alloc)
    try:
        out = model.diffuse_model(st.xyz_m, f, t, st.location, pattern="dipole", xp=cp)
    finally:
        cp.cuda.set_allocator(pool.malloc)
    extra = peak[0] - base - out.nbytes
    assert extra <= model.DIFFUSE_CHUNK_BYTES + 64 * 2**20, extra / 2**20     # (+ the path, 34 MB)


def test_covariance_sums_of_flagged_data_are_means_over_the_kept_samples(xp):
    """After interference flagging (whole short blocks of a stand zeroed), each baseline's mean is over
    the samples both its stands kept: the definition, summed here in float64 with the masks."""
    from bf_epic_blocks.runtime.dtypes import pack_ci4
    rng = np.random.default_rng(4)
    T, C, A, P, g = 512, 3, 6, 2, 16
    v = rng.integers(-7, 8, (T, C, A, P)) + 1j * rng.integers(-7, 8, (T, C, A, P))
    keep = np.ones((T // g, C, A), bool)
    keep[4:12, :, 2] = False                 # stand 2 flagged for 128 samples in every channel
    keep[20:24, 1, :] = False                # channel 1 flagged for every stand for 64 samples
    keep[rng.random(keep.shape) < 0.05] = False
    m = np.repeat(keep, g, axis=0)[..., None]                                         # (T, C, A, 1)
    v = np.where(m, v, 0)
    want = np.zeros((C, P, A, A), complex)
    for c in range(C):
        for p in range(P):
            x, k = v[:, c, :, p], m[:, c, :, 0].astype(float)
            want[c, p] = (x.T @ x.conj()) / np.maximum(k.T @ k, 1)
    s = skycal.CovarianceSums(C, A, P, xp)
    b = xp.asarray(pack_ci4(v))
    for t0 in (0, 256):                                                                # two gulps
        part = b[t0:t0 + 256]
        nz = (part != 0).any(axis=3).reshape(256 // g, g, C, A).any(axis=1).astype(xp.float32)
        s.add(part, ci4=True, used=nz, block=g)
    got = s.mean()
    got = got.get() if hasattr(got, "get") else got
    assert np.allclose(got, want, rtol=1e-5, atol=1e-5)
    plain = skycal.CovarianceSums(C, A, P, xp)
    plain.add(b, ci4=True)
    p_ = plain.mean()
    p_ = p_.get() if hasattr(p_, "get") else p_
    assert not np.allclose(p_, want, rtol=1e-2)          # without the counts, the flagged baselines are low


def test_the_solver_after_the_flagger_solves_from_the_unflagged_data_only():
    """Interference the test chose, on a sky whose gains it chose: a 2-ms broadband spark from one direction
    in every stand, and one stand's own 0.6-ms spike. The flagger zeroes them (the spike on its stand
    only); the covariances the gain
    solver sums from the flagger's output (its masks read from the zeros, as GainSolverBlock does) are means
    over the kept samples, and the gains come out within 1% of the truth, where the same data unflagged
    give gains wrong by several per cent."""
    from types import SimpleNamespace

    from bf_epic_blocks.blocks import ArraySinkBlock, ArraySourceBlock, bfp, efield_header
    from bf_epic_blocks.blocks.gain_solver import GainSolverBlock
    from bf_epic_blocks.blocks.rfi_flag import RFIFlagBlock
    st = lwasv()
    f = 74e6 + 25e3 * np.arange(4)
    rng = np.random.default_rng(9)
    g, Rt, M = corrupted(st.xyz_m, f, rng)
    T, A = 8192, st.nstand
    x = np.empty((T, f.size, A, 2), np.complex64)
    for c in range(f.size):
        for p in range(2):
            L = np.linalg.cholesky(Rt[c, p])
            z = (rng.standard_normal((A, T)) + 1j * rng.standard_normal((A, T))) / math.sqrt(2)
            x[:, c, :, p] = (L @ z).T
    spark = _steer(st.xyz_m, f, 0.6, -0.7)                              # a spark near the horizon, all stands
    w = 40 * math.sqrt(1000.0) * (rng.standard_normal((50, f.size)) + 1j * rng.standard_normal((50, f.size)))
    x[3000:3050] += (w[:, :, None] * spark[None])[..., None]
    own = int(np.flatnonzero(~st.flags.any(axis=1))[17])               # a stand in use
    x[6000:6016, :, own, :] += 60 * math.sqrt(1000.0) * rng.standard_normal((16, f.size, 2))  # its own spike
    hdr = efield_header("cal+rfi", 0, f, 40e-6, {"name": "lwasv", "xyz_m": st.xyz_m, "flags": st.flags},
                        dtype="cf32")
    with bfp.Pipeline() as pipe:
        src = ArraySourceBlock(x, hdr, gulp_nframe=2048)
        fb = RFIFlagBlock(src, far=1e-3, block_frames=1024, impulse_frames=16)
        sink = ArraySinkBlock(fb)
        pipe.run()
    y = np.asarray(sink.result(0)).reshape(x.shape)
    assert (y[3000:3050] == 0).all() and (y[6000:6016, :, own] == 0).all()
    # one stand's spike is that stand's: the others keep those samples
    others = np.flatnonzero(~st.flags.any(axis=1) & (np.arange(A) != own))
    assert (y[6000:6016][:, :, others] != 0).mean() > 0.99
    me = SimpleNamespace(_flag_block=16, _xp=np, _lay={"dtype": "cf32"})

    def solved(data, flagged):
        s = skycal.CovarianceSums(f.size, A, 2, np)
        for t0 in range(0, T, 2048):
            part = data[t0:t0 + 2048]
            used, block = GainSolverBlock._used(me, part) if flagged else (None, 1)
            s.add(part, used=used, block=block)
        return skycal.solve_gains(s.mean(), M, st.xyz_m, f, st.flags)
    good = ~st.flags
    sol = solved(y, True)
    err, _ = skycal.gain_error(sol.corrections, g, good & ~sol.flags)
    bad = solved(x, False)
    err_bad, _ = skycal.gain_error(bad.corrections, g, good & ~bad.flags)
    print(f"gain error: flagged {err:.4f}, unflagged {err_bad:.4f}")
    assert (sol.flags & good).sum() <= 0.01 * good.sum()
    assert err < 0.01, err
    assert err_bad > 3 * err and err_bad > 0.02, (err_bad, err)


def _steer(xyz, f, l, m):
    n = math.sqrt(1 - l * l - m * m)
    return np.exp(2j * np.pi * f[:, None] / C * (xyz @ np.array([l, m, n]))[None, :])


@pytest.mark.parametrize("diffuse,one_channel_chunks", [(True, False), (False, False), (True, True)])
def test_the_plan_s_solver_memory_bounds_what_the_solver_allocates(diffuse, one_channel_chunks, monkeypatch):
    """`bf-epic plan` counts a live solver's arrays (:func:`~bf_epic_blocks.imaging.cost.solver_bytes`):
    what it holds (the covariance sums, the baseline weights, the diffuse model) and the most it adds while
    summing an integration of 4-bit voltages (the integer Gram sums) or forming a solution (the sums' mean,
    the model, the solver's own peak). On the CPU (complex128, float64 Gram sums), numpy's allocations as
    tracemalloc sees them: each within 12% of the count (its chunk factor is the GPU's, 2.9 covariances of a
    chunk, where the CPU's complex128 takes 2.66), none above it. With chunks of one channel (a whole
    band's case: 784 channels in chunks of 64) the model with its diffuse term is a chunk's, not a whole
    covariance more."""
    import tracemalloc

    from bf_epic_blocks.imaging.cost import solver_bytes
    if one_channel_chunks:
        monkeypatch.setattr(skycal, "SOLVE_CHUNK_BYTES", 2 * 64 * 64 * 16)
    from bf_epic_blocks.runtime.dtypes import pack_ci4
    rng = np.random.default_rng(4)
    nchan, nant, T = 16, 64, 64
    xyz = rng.normal(0, 30, (nant, 3)) * [1, 1, 0.05]
    f = 74e6 + 25e3 * np.arange(nchan)
    g, Rt, M0 = corrupted(xyz, f, rng)
    lmn, flux = two_sources(nchan)
    want = solver_bytes(nchan, nant, 2, gpu=False, diffuse=diffuse)
    q = rng.integers(-7, 8, (T, nchan, nant, 2)) + 1j * rng.integers(-7, 8, (T, nchan, nant, 2))
    # (a first solve's one-off allocations, its imports' caches, are not the solver's arrays)
    skycal.solve_gains(Rt.copy(), M0, xyz, f, extra=0.1 * M0 if diffuse else None)
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        sums = skycal.CovarianceSums(nchan, nant, 2)
        W = skycal.baseline_weights(xyz, f, 4.0)
        E = 0.1 * M0 if diffuse else None
        held = tracemalloc.get_traced_memory()[0] - base
        tracemalloc.reset_peak()
        sums.add(pack_ci4(q), ci4=True)
        summing = tracemalloc.get_traced_memory()[1] - base - held
        sums.reset()
        tracemalloc.reset_peak()
        M = skycal.model_covariance(xyz, f, lmn, flux)
        R = Rt.copy()                                           # (the sums' mean: an array of the solve's own)
        skycal.solve_gains(R, M, xyz, f, weights=W, extra=E)
        solving = tracemalloc.get_traced_memory()[1] - base - held
    finally:
        tracemalloc.stop()
    assert 0.9 * want["held"] <= held <= want["held"] * 1.001, (held, want)
    if one_channel_chunks:
        assert 0.88 * want["solving"] <= solving <= want["solving"], (solving, want)
    else:
        assert 0.88 * want["working"] <= max(summing, solving) <= want["working"], (summing, solving, want)

"""The simulated sky made where the imager runs: F-engine voltages from counters, one pass per gulp.

Same data model as :func:`bf_epic_blocks.sky.simulate_efield` (module :mod:`.efield`: unpolarised
point sources of power S/2 per pol, geometric phase sigma = +1, cable delay and power gain applied
to the sky signal, receiver noise of power ``noise_power`` added after them, dispersed bursts),
made differently so that a GPU can make it at many times real time and a CPU twin gives the same
samples (to the last bit on the CPU; to the GPU's fast functions' rounding there, see below):

* Every random number is a function of where it goes, not of a generator's state: a complex
  normal (variance 1 per real part) is Box-Muller of a 64-bit hash (splitmix64's finaliser) of a
  counter, with the counter for source s, pol p, channel c at absolute sample T
  ``((T nchan + c) nsrc + s) 2 + p`` and for the noise of antenna a ``((T nchan + c) nant + a) 2 + p``,
  each stream with its own key from the seed. So a sample does not depend on the gulp size and a
  gulp can be made anywhere. The NumPy twin does Box-Muller in float32 from IEEE operations only
  (+, -, *, sqrt and integer bit work: Cephes' polynomials for log and sin/cos, relative error
  ~1e-7), so any machine gives its samples bit for bit. The CUDA kernel takes the same counters,
  hash and 24-bit uniforms and the hardware's own log, sqrt and sin/cos with fused multiply-add:
  its voltages are the twin's to 4e-5 of their rms (1.5e-4 for noise alone), its 4-bit samples the
  twin's except ~2 in 10^6 that sit on a rounding edge and land one step over (tested on every GPU
  run). The twin's IEEE-only polynomials would make the two agree bit for bit, at a large cost in
  the kernel's speed.
* The sky signal is X = sum_s e_s,p(T, c) W[c, s, a, p] + noise, with
  W = sqrt(S_s(nu_c) / 4) exp(sigma 2 pi i nu_c (s_hat . r_a) / c0) sqrt(G) exp(-2 pi i nu_c tau)
  (:func:`sky_weights`); a burst is a source whose e is zero outside its dispersed window of samples.
* 4-bit output (``ci4``, high nibble real) is ``clip(rint(X * scale), -8, 7)``; the scale is set
  from the model's expected power (rms 2 units, as :func:`quantize_ci4` does from the data).
* The source directions are recomputed when the sky has turned for ``refresh_s`` (the
  block's choice), not per sample: 1 s of Earth rotation moves a source by 0.004 deg.

On a GPU one CUDA kernel (``fastsim.cu`` beside this module) writes the packed bytes (or complex64)
straight into the output array: nothing but the weights crosses the bus. A CUDA block makes a tile
of 32 samples of one channel, so an antenna's weights are read once per tile, not once per sample.
Up to ``MAX_REG_SRC`` sources (every shipped pipeline) the kernel is compiled for the source count:
an antenna's weights stay in registers and the sample loop steps its counters (the same bits as the
generic kernel, several times faster for many sources). It is bound by instruction issue, most of
it the noise's Box-Muller.
"""
from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..conventions import SPEED_OF_LIGHT_M_S
from ..conventions import dispersion_delay_s
from ..cuda import get_kernel, register

__all__ = ["stream_keys", "sky_weights", "burst_windows", "expected_rms", "make_gulp", "complex_normals"]

_M64 = (1 << 64) - 1
_NEVER = np.iinfo(np.int64).min, np.iinfo(np.int64).max


def _mix64_int(z: int) -> int:
    z = (z + 0x9E3779B97F4A7C15) & _M64
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & _M64
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & _M64
    return z ^ (z >> 31)


def stream_keys(seed: int) -> tuple[int, int]:
    """(sky key, noise key): 64-bit keys of the two counter streams for ``seed`` (any int)."""
    base = _mix64_int(int(seed) & _M64)
    return _mix64_int(base ^ 1), _mix64_int(base ^ 2)


def _mix64(z):
    """splitmix64's finaliser on a uint64 NumPy array (wrapping arithmetic)."""
    z = z + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


# Box-Muller in float32 from IEEE operations only (+, -, *, sqrt, integer bit work): no library
# log/sin/cos, whose results differ between libraries and machines, so every CPU gives the same
# bits. The polynomials are Cephes' logf and sinf/cosf (relative error ~1e-7 on their ranges).
_LOG_P = (7.0376836292e-2, -1.1514610310e-1, 1.1676998740e-1, -1.2420140846e-1, 1.4249322787e-1,
          -1.6668057665e-1, 2.0000714765e-1, -2.4999993993e-1, 3.3333331174e-1)
_F = np.float32


def _log_u1(k1):
    """log(k1 / 2^24) for integer k1 in [1, 2^24], float32, as the kernel computes it."""
    u = k1.astype(_F) * _F(1.0 / 16777216.0)                            # exact
    bits = u.view(np.int32)
    e = ((bits >> 23) & 0xFF) - 127
    m = ((bits & 0x7FFFFF) | 0x3F800000).view(_F)                       # u = m 2^e, m in [1, 2)
    big = m > _F(1.4142135)
    m = m * (_F(1.0) - _F(0.5) * big)                                   # x 1/2 or x 1, both exact: [sqrt(1/2), sqrt(2)]
    ef = (e + big).astype(_F)
    x = m - _F(1.0)
    z = x * x
    p = np.full_like(x, _F(_LOG_P[0]))
    for c in _LOG_P[1:]:
        p = p * x + _F(c)
    y = x * z * p + ef * _F(-2.12194440e-4) - _F(0.5) * z
    return (x + y) + ef * _F(0.693359375)


def _sincos_2pi(k2):
    """(cos, sin) of 2 pi k2 / 2^24 for integer k2 (int32) in [0, 2^24), float32: octant from the top 3
    bits, the angle within it from the other 21 (reflected in odd octants), Cephes' polynomials on
    [0, pi/4]. The octant's swaps and signs are bit operations (np.where on a mask that changes
    every element is slow in NumPy)."""
    o = k2 >> 21
    j = k2 & 0x1FFFFF
    odd = o & 1
    j = j + odd * ((1 << 21) - 2 * j)                                   # 2^21 - j in odd octants
    t = j.astype(_F) * _F(np.pi / 4 / (1 << 21))
    z = t * t
    sn = ((_F(-1.9515295891e-4) * z + _F(8.3321608736e-3)) * z - _F(1.6666654611e-1)) * z * t + t
    cs = ((_F(2.443315711809948e-5) * z - _F(1.388731625493765e-3)) * z + _F(4.166664568298827e-2)) * z * z \
        - _F(0.5) * z + _F(1.0)
    swap = -(((o + 1) >> 1) & 1)                                        # all ones in octants 1, 2, 5, 6
    sb, cb = sn.view(np.int32), cs.view(np.int32)
    c = (sb & swap) | (cb & ~swap)
    s = (cb & swap) | (sb & ~swap)
    c ^= (((o + 2) >> 2) & 1) << 31                                     # octants 2-5: cos < 0
    s ^= ((o >> 2) & 1) << 31                                           # octants 4-7: sin < 0
    return c.view(_F), s.view(_F)


def complex_normals(counter, key):
    """(re, im) float32 arrays: a standard normal pair for each uint64 counter: Box-Muller of its
    hash, u1 = (top 24 bits + 1) / 2^24 in (0, 1], u2 = the next 24 bits / 2^24, in IEEE float32
    operations only (the CUDA kernel: the same u1 and u2, its hardware functions). Whole arrays,
    not cache-sized pieces: the host twin runs on a thread per core, and a NumPy call lets the
    others run only while it works (pieces of 8,192 cost 4.6x on 16 cores, waiting for the GIL)."""
    h = _mix64(np.asarray(counter, np.uint64) ^ np.uint64(key))
    k1 = ((h >> np.uint64(40)) + np.uint64(1)).astype(np.int32)         # <= 2^24: 32 bits do
    k2 = ((h >> np.uint64(16)) & np.uint64(0xFFFFFF)).astype(np.int32)
    r = np.sqrt(_F(-2.0) * _log_u1(k1))
    c, s = _sincos_2pi(k2)
    return r * c, r * s


def sky_weights(xyz_m, freq_hz, l, m, n, flux, cable=None, sigma=+1, pattern=None):
    """W (nchan, nsrc, nant, 2) complex64: amplitude x geometric phase x cable term (module docstring).

    l, m, n : (nsrc,) direction cosines; flux : (nchan, nsrc) flux density per source; cable : None
    or complex (nchan, nant, 2) sqrt(G) exp(-2 pi i nu tau) (times any true gains); pattern : None or
    the antennas' voltage pattern B_p in each source's direction, broadcastable to (nchan, nsrc, 2).
    """
    f = np.asarray(freq_hz, np.float64)
    s_dot_r = np.stack([l, m, n], axis=1) @ np.asarray(xyz_m, np.float64).T                  # (nsrc, nant)
    phase = np.exp(sigma * 2j * np.pi * (f[:, None, None] / SPEED_OF_LIGHT_M_S) * s_dot_r[None])   # (c, s, a)
    w = np.sqrt(np.asarray(flux, np.float64) / 4.0)[:, :, None, None] * phase[..., None] * np.ones(2)
    if pattern is not None:
        w = w * np.broadcast_to(np.asarray(pattern), (f.size, s_dot_r.shape[0], 2))[:, :, None, :]
    if cable is not None:
        w = w * np.asarray(cable)[:, None, :, :]
    return w.astype(np.complex64)


def burst_windows(nsteady, bursts, freq_hz, dt_s):
    """(on0, on1) int64 (nsrc, nchan): the samples [on0, on1) (counted from the run's first sample)
    in which each source shines: always for the ``nsteady`` steady ones, then for each burst
    ``{start_s, duration_s, dm}`` from ``start_s + delay_c`` for ``duration_s`` (delay to the
    band's highest channel, as :func:`~.efield.simulate_efield` does)."""
    f = np.asarray(freq_hz, np.float64)
    on0 = np.full((nsteady + len(bursts), len(f)), _NEVER[0], np.int64)
    on1 = np.full_like(on0, _NEVER[1])
    for j, b in enumerate(bursts):
        start = float(b["start_s"]) + dispersion_delay_s(float(b.get("dm", 0.0)), f, f.max())
        on0[nsteady + j] = np.ceil(start / dt_s - 1e-9)
        on1[nsteady + j] = np.ceil((start + float(b["duration_s"])) / dt_s - 1e-9)
    return on0, on1


def expected_rms(w_steady, noise_power):
    """rms of the real and imaginary parts of the voltages the model expects (bursts left out)."""
    var = noise_power / 2.0 + np.sum(np.abs(np.asarray(w_steady, np.complex128)) ** 2, axis=1)   # (c, a, p)
    return math.sqrt(float(np.mean(var)))


# ------------------------------------------------------------------ the gulp
_TILE = 32          # samples per CUDA block (TILE in fastsim.cu)
MAX_REG_SRC = 16    # up to this many sources, sim_gulp_few (weights in registers: 4 per source)
MAX_GPU_COLUMNS = 48 * 1024 // (_TILE * 16)   # sim_gulp's shared memory: a tile's signals, 2 float2 per column
_OPTIONS = ("--use_fast_math",)


def _gpu_kernel(nsrc):
    """(kernel, few): ``sim_gulp_few`` compiled for ``nsrc`` sources when nsrc <= MAX_REG_SRC, else the
    generic ``sim_gulp``; both with the hardware's fast functions (module docstring)."""
    few = nsrc <= MAX_REG_SRC
    return get_kernel("sky/fastsim.cu", "sim_gulp_few" if few else "sim_gulp",
                      defines={"NSRC": nsrc} if few else None, options=_OPTIONS), few


# every source count a sky may have: the generic kernel, and the few-source one for 0 .. MAX_REG_SRC
register("sky/fastsim.cu", ({}, None, _OPTIONS), *[({"NSRC": n}, None, _OPTIONS) for n in range(MAX_REG_SRC + 1)])


def make_gulp(out, t0, w, on0, on1, keys, noise_power, scale=None):
    """Samples t0 .. t0 + len(out) - 1 of the run into ``out`` (NumPy or CuPy, where it lives).

    out : (n, nchan, nant, 2) uint8 for ci4 (packed, high nibble real; needs ``scale``) or complex64
    (the voltages themselves). w : (nchan, nsrc, nant, 2) complex64 (:func:`sky_weights`, in out's
    namespace on a GPU); on0, on1 : (nsrc, nchan) int64 (:func:`burst_windows`); keys :
    :func:`stream_keys`. Returns ``out``.
    """
    n, nchan, nant, npol = out.shape
    ci4 = out.dtype == np.uint8
    if npol != 2 or not (ci4 or out.dtype == np.complex64):
        raise ValueError(f"make_gulp: out must be (n, nchan, nant, 2) uint8 (ci4) or complex64, got "
                         f"{out.shape} {out.dtype}")
    if ci4 and not (scale and scale > 0):
        raise ValueError("make_gulp: ci4 output needs a positive scale")
    nsrc = int(w.shape[1])
    noise_amp = np.float32(math.sqrt(noise_power / 2.0))
    if type(out).__module__.startswith("cupy"):
        import cupy
        if not out.flags.c_contiguous:
            raise ValueError("make_gulp: the output array must be C-contiguous")
        if nsrc > MAX_GPU_COLUMNS:
            raise ValueError(f"make_gulp: {nsrc} sky columns; the GPU kernel holds at most {MAX_GPU_COLUMNS} "
                             "(a tile's signals, 16 bytes per column and sample, in 48 KiB of shared memory): "
                             "fewer diffuse modes or sources")
        k, few = _gpu_kernel(nsrc)
        threads = 256 if nant > 128 else 64
        head = (out, np.int32(ci4), cupy.ascontiguousarray(w, cupy.complex64), cupy.asarray(on0, cupy.int64),
                cupy.asarray(on1, cupy.int64), np.int64(t0), np.int32(n), np.int32(nchan))
        tail = (np.int32(nant), np.uint64(keys[0]), np.uint64(keys[1]), noise_amp, np.float32(scale or 1.0))
        if n * nchan:
            if few:     # its shared memory is static
                k((-(-n // _TILE) * nchan,), (threads,), head + tail)
            else:
                k((-(-n // _TILE) * nchan,), (threads,), head + (np.int32(nsrc),) + tail,
                  shared_mem=max(8, _TILE * 16 * nsrc))
        return out
    _numpy_gulp(out, int(t0), np.asarray(w, np.complex64), np.asarray(on0), np.asarray(on1), keys, noise_amp,
                np.float32(scale or 1.0), ci4)
    return out


def _numpy_gulp(out, t0, w, on0, on1, keys, noise_amp, scale, ci4, chunk=16):
    """The CPU twin: chunks of ``chunk`` samples on a thread each (NumPy lets go of the interpreter
    lock in its loops), one per core."""
    n = out.shape[0]
    starts = range(0, n, chunk)
    if n <= chunk or (os.cpu_count() or 1) == 1:
        for a0 in starts:
            _numpy_chunk(out, a0, min(n, a0 + chunk), t0, w, on0, on1, keys, noise_amp, scale, ci4)
        return
    with ThreadPoolExecutor(max_workers=min(os.cpu_count() or 1, 16)) as pool:
        list(pool.map(lambda a0: _numpy_chunk(out, a0, min(n, a0 + chunk), t0, w, on0, on1, keys, noise_amp,
                                              scale, ci4), starts))


def _numpy_chunk(out, a0, a1, t0, w, on0, on1, keys, noise_amp, scale, ci4):
    # the kernel's float32 operations, element for element; worked in (t, c, p, a) order so that the
    # antenna axis is the long contiguous one, and turned to (t, c, a, p) at the end
    n, nchan, nant, _ = out.shape
    nsrc = w.shape[1]
    wt = np.ascontiguousarray(np.transpose(w, (0, 1, 3, 2)))                                # (c, s, p, a)
    wr, wi = np.ascontiguousarray(wt.real), np.ascontiguousarray(wt.imag)
    c = np.arange(nchan, dtype=np.uint64)
    a_p = (np.arange(nant, dtype=np.uint64)[None, :] * np.uint64(2) + np.arange(2, dtype=np.uint64)[:, None])  # (p, a)
    s_p = np.arange(nsrc, dtype=np.uint64)[:, None] * np.uint64(2) + np.arange(2, dtype=np.uint64)[None, :]   # (s, p)
    T = np.arange(t0 + a0, t0 + a1, dtype=np.int64)
    base = T.astype(np.uint64)[:, None] * np.uint64(nchan) + c[None, :]                  # (t, c)
    vr = np.zeros((len(T), nchan, 2, nant), np.float32)
    vi = np.zeros_like(vr)
    if nsrc:
        er, ei = complex_normals(base[:, :, None, None] * np.uint64(2 * nsrc) + s_p, keys[0])   # (t, c, s, p)
        on = (T[:, None, None] >= on0.T[None]) & (T[:, None, None] < on1.T[None])       # (t, c, s)
        er, ei = er * on[..., None], ei * on[..., None]
        t1, t2 = np.empty_like(vr), np.empty_like(vr)
        for s in range(nsrc):
            # vr += zr wr - zi wi, vi += zr wi + zi wr: the same float32 operations in the same order
            # as the expressions written out, in place (no arrays made per source)
            zr, zi = er[:, :, s, :, None], ei[:, :, s, :, None]
            np.multiply(zr, wr[None, :, s], out=t1)
            np.multiply(zi, wi[None, :, s], out=t2)
            t1 -= t2
            vr += t1
            np.multiply(zr, wi[None, :, s], out=t1)
            np.multiply(zi, wr[None, :, s], out=t2)
            t1 += t2
            vi += t1
    nr, ni = complex_normals(base[:, :, None, None] * np.uint64(2 * nant) + a_p, keys[1])  # (t, c, p, a)
    vr = np.transpose(vr + noise_amp * nr, (0, 1, 3, 2))
    vi = np.transpose(vi + noise_amp * ni, (0, 1, 3, 2))
    dst = out[a0:a0 + len(T)]
    if ci4:
        qr = np.clip(np.rint(vr * scale), -8, 7).astype(np.int8).view(np.uint8)
        qi = np.clip(np.rint(vi * scale), -8, 7).astype(np.int8).view(np.uint8)
        dst[...] = ((qr & np.uint8(0xF)) << np.uint8(4)) | (qi & np.uint8(0xF))
    else:
        dst.real, dst.imag = vr, vi

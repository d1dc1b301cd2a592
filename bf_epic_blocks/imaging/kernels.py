"""Gridding kernels: the "exponential of semicircle" (ES) kernel and its Fourier transform.

The ES kernel (Barnett, Magland & af Klinteberg 2019, the kernel of FINUFFT and ducc0) in grid-cell
units z, support W cells:

    phi(z) = exp(beta * (sqrt(1 - (2 z / W)^2) - 1))   for |z| < W/2,   0 outside.

Parameters from the requested accuracy ``epsilon`` and the oversampling factor ``sigma`` (the FFT
grid is ``sigma`` times finer than the image needs), the FINUFFT formulas:

    sigma == 2:  W = ceil(log10(1/epsilon)) + 1,        beta = b(W) * W, b = 2.20 (W=2),
                                                         2.26 (W=3), 2.38 (W=4), 2.30 (W>=5)
    otherwise:   W = ceil(ln(1/epsilon) / (pi sqrt(1 - 1/sigma))),
                 beta = 0.97 * pi * (1 - 1/(2 sigma)) * W
    W is at least 2 and at most :data:`MAX_SUPPORT`.

Gridding a point at fractional cell coordinate x spreads it onto the W integer cells p with
|p - x| < W/2 (``p0 = ceil(x - W/2)``, cells ``p0 .. p0 + W - 1``), weights ``phi(p - x)``. After the
FFT the output at frequency f (cycles per cell, |f| <= 1/(2 sigma) for the kept pixels) carries the
factor ``phihat(f) = integral phi(z) exp(-2 pi i z f) dz`` (real, phi is even), which the caller
divides out; :func:`es_fourier` evaluates it by Gauss-Legendre quadrature (exact to ~1e-15).
The aliased images phihat(f + k), k != 0, are the error; their size relative to phihat(f) is about
epsilon per dimension.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

MAX_SUPPORT = 16


@dataclass(frozen=True)
class ESKernel:
    """An ES kernel: support ``W`` cells, shape ``beta``, for oversampling ``sigma``."""

    W: int
    beta: float
    sigma: float
    epsilon: float

    def __call__(self, z):
        return es_kernel(z, self.W, self.beta)

    def fourier(self, f):
        return es_fourier(f, self.W, self.beta)


def es_params(epsilon: float, sigma: float = 2.0) -> ESKernel:
    """Kernel support and shape for accuracy ``epsilon`` (1e-1 .. 1e-14) at oversampling ``sigma``.

    Formulas in the module docstring. Raises ValueError for epsilon outside (0, 0.5) or sigma
    outside [1.2, 4].
    """
    epsilon = float(epsilon)
    sigma = float(sigma)
    if not (1e-14 <= epsilon < 0.5):
        raise ValueError(f"epsilon must lie in [1e-14, 0.5), got {epsilon!r}")
    if not (1.2 <= sigma <= 4.0):
        raise ValueError(f"oversampling sigma must lie in [1.2, 4], got {sigma!r}")
    if sigma == 2.0:
        W = int(math.ceil(-math.log10(epsilon / 10.0)))
    else:
        W = int(math.ceil(-math.log(epsilon) / (math.pi * math.sqrt(1.0 - 1.0 / sigma))))
    W = max(2, W)
    if W > MAX_SUPPORT:
        raise ValueError(f"epsilon={epsilon:g} at sigma={sigma:g} needs a kernel support of {W} cells, "
                         f"more than the maximum {MAX_SUPPORT}; raise sigma or epsilon")
    if sigma == 2.0:
        b = {2: 2.20, 3: 2.26, 4: 2.38}.get(W, 2.30)
    else:
        b = 0.97 * math.pi * (1.0 - 1.0 / (2.0 * sigma))
    return ESKernel(W=W, beta=b * W, sigma=sigma, epsilon=epsilon)


def es_kernel(z, W: int, beta: float):
    """phi(z) for z in grid cells (NumPy float64 array in, float64 out); 0 for |z| >= W/2."""
    z = np.asarray(z, dtype=np.float64)
    t = 2.0 * z / W
    inside = np.abs(t) < 1.0
    out = np.zeros_like(t)
    out[inside] = np.exp(beta * (np.sqrt(1.0 - t[inside] ** 2) - 1.0))
    return out


_GL_CACHE: dict[int, tuple[np.ndarray, np.ndarray]] = {}


def es_fourier(f, W: int, beta: float, nquad: int | None = None):
    """phihat(f) = integral_{-W/2}^{W/2} phi(z) cos(2 pi z f) dz, f in cycles per cell (float64).

    Gauss-Legendre quadrature on [0, W/2] (phi is even). The kernel has a square-root edge, so the
    rule uses many nodes (default 4 W + 60); checked against a dense trapezoid rule in the tests.
    """
    f = np.asarray(f, dtype=np.float64)
    q = nquad or (4 * W + 60)
    if q not in _GL_CACHE:
        _GL_CACHE[q] = np.polynomial.legendre.leggauss(q)
    x, wq = _GL_CACHE[q]
    z = (x + 1.0) * (W / 4.0)           # nodes on [0, W/2]
    wz = wq * (W / 4.0)
    phi = es_kernel(z, W, beta)
    flat = f.reshape(-1)
    out = np.empty_like(flat)
    # chunk to bound the (len(f), nquad) temporary
    step = max(1, 2_000_000 // q)
    for i in range(0, flat.size, step):
        out[i:i + step] = 2.0 * (np.cos(2.0 * np.pi * np.outer(flat[i:i + step], z)) @ (wz * phi))
    return out.reshape(f.shape)


def spread_weights(x, kern: ESKernel):
    """Cells and weights for spreading points at fractional cell coordinates ``x`` (float64).

    Returns ``(p0, w)``: p0 int64 shaped like x (first cell, ``ceil(x - W/2)``), w float64
    shaped ``x.shape + (W,)`` with ``w[..., j] = phi(p0 + j - x)``.
    """
    x = np.asarray(x, dtype=np.float64)
    p0 = np.ceil(x - kern.W / 2.0).astype(np.int64)
    d = p0[..., None] + np.arange(kern.W) - x[..., None]
    return p0, es_kernel(d, kern.W, kern.beta)


def good_fft_size(n: int) -> int:
    """Smallest even integer >= n whose prime factors are 2, 3, 5 (fast for pocketfft and cuFFT)."""
    n = max(2, int(math.ceil(n)))
    while True:
        m = n
        for p in (2, 3, 5):
            while m % p == 0:
                m //= p
        if m == 1 and n % 2 == 0:
            return n
        n += 1

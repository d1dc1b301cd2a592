"""Pixel sets: where the imager looks.

Every pixel is a direction (l, m) with l East and m North (direction cosines); n = sqrt(1-l^2-m^2)
is computed in float64 by :func:`n_from_lm` in a form that stays accurate at the horizon.

Regular grids (:class:`LMGrid`): an N x N grid with cell ``2 / N * fov_scale`` in l and m,
centres ``l_i = (i - N//2) * cell`` (so index N//2 is the zenith, as an FFT grid), images indexed
``[m_index, l_index]`` (rows North, columns East, both increasing). Only the pixels strictly above
the horizon (l^2 + m^2 < 1) are imaged; :meth:`LMGrid.to_image` puts values back on the 2-D grid
with NaN outside.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field

import numpy as np

from ..cuda import get_kernel, register
from ._xp import get_xp, host_all, host_any


def n_from_lm(l, m):
    """n = sqrt(1 - l^2 - m^2) in float64, accurate near the horizon.

    ``1 - l^2 - m^2`` loses everything near n ~ 0 when formed naively in float32; in float64 we
    use ``(1 - r)(1 + r)`` with r = sqrt(l^2 + m^2), which keeps the relative accuracy of the small
    factor (1 - r).
    """
    xp = get_xp(l, m)
    l = xp.asarray(l, dtype=xp.float64)
    m = xp.asarray(m, dtype=xp.float64)
    r = xp.hypot(l, m)
    return xp.sqrt(xp.clip((1.0 - r) * (1.0 + r), 0.0, None))


def check_lm(pixels_lm):
    """Validate a (npix, 2) l, m array (host or device); returns it as float64.

    Raises ValueError naming the first pixel with l^2 + m^2 > 1 (below the horizon).
    """
    xp = get_xp(pixels_lm)
    lm = xp.asarray(pixels_lm, dtype=xp.float64)
    if lm.ndim != 2 or lm.shape[1] != 2:
        raise ValueError(f"pixels_lm must be shaped (npix, 2) [l East, m North]; got shape {tuple(lm.shape)}")
    if lm.shape[0] == 0:
        raise ValueError("pixels_lm is empty: at least one pixel is needed")
    r2 = lm[:, 0] ** 2 + lm[:, 1] ** 2
    bad = r2 > 1.0
    if host_any(bad) or not host_all(xp.isfinite(r2)):
        idx = int(xp.argmax(bad | ~xp.isfinite(r2)))
        l, m = float(lm[idx, 0]), float(lm[idx, 1])
        raise ValueError(
            f"pixel {idx} at (l, m) = ({l:.6g}, {m:.6g}) is below the horizon or not finite "
            f"(l^2 + m^2 = {l * l + m * m:.6g} > 1); direction cosines must satisfy l^2 + m^2 <= 1")
    return lm


@dataclass(frozen=True)
class LMGrid:
    """A regular N x N (l, m) grid of which only the pixels above the horizon are imaged.

    Attributes
    ----------
    size : int            N, pixels per side.
    cell : float          grid step in l and m (direction cosine units).
    lm : (npix, 2) float64 array of the kept pixels, in row-major [m_index, l_index] order.
    mask : (N, N) bool    True where a pixel is kept (indexed [m_index, l_index]).
    """

    size: int
    cell: float
    lm: np.ndarray = field(repr=False)
    mask: np.ndarray = field(repr=False)

    @property
    def npix(self) -> int:
        return int(self.lm.shape[0])

    @property
    def axis(self) -> np.ndarray:
        """Pixel-centre coordinates along l (columns) and m (rows): (i - N//2) * cell."""
        return (np.arange(self.size) - self.size // 2) * self.cell

    def part(self, k: int, n: int) -> "LMGrid":
        """The k-th of ``n`` parts of this grid's kept pixels: contiguous runs in their row-major
        order, sizes differing by at most one, on the same N x N grid (the others not kept). Several
        GPUs image and search one part each (the pipeline's pixel split)."""
        if int(n) != n or n < 1 or int(k) != k or not 0 <= k < n:
            raise ValueError(f"LMGrid.part: k must be in 0..n-1 with n >= 1, got k={k!r}, n={n!r}")
        if n > self.npix:
            raise ValueError(f"LMGrid.part: cannot share {self.npix} pixel(s) among {n} parts")
        edges = np.linspace(0, self.npix, int(n) + 1).round().astype(int)
        keep = np.flatnonzero(self.mask)[edges[k]:edges[k + 1]]
        mask = np.zeros_like(self.mask)
        mask.flat[keep] = True
        return LMGrid(size=self.size, cell=self.cell, lm=self.lm[edges[k]:edges[k + 1]].copy(), mask=mask)

    def to_image(self, values):
        """Scatter (..., npix) values back onto (..., N, N) [m, l] images, NaN outside the kept set."""
        xp = get_xp(values)
        values = xp.asarray(values)
        if values.dtype.kind not in "fc":
            values = values.astype(xp.float64)
        out = GridPlacement(np.flatnonzero(self.mask), self.size * self.size, xp)(values)
        return out.reshape(values.shape[:-1] + (self.size, self.size))


class GridPlacement:
    """Puts (..., npix) pixel values on (..., n) cells, NaN in the other cells.

    index : (npix,) distinct flat cell indices in 0..n-1 (e.g. ``np.flatnonzero(LMGrid.mask)``).
    xp : the array namespace of the values (NumPy or CuPy).

    On the GPU one kernel writes every cell (a gather through the inverse index): no NaN fill pass
    and none of CuPy's fancy-index set-up, which costs more host time than the copy itself.

    extra : directions imaged beside the grid's pixels (a watchlist's): the values' last ``extra``
        pixels, npix = index.size + extra. They go to :attr:`xout` (..., extra), given for each call by
        :meth:`beside`; kernels that write each pixel's cell (:attr:`cells`) find them at cells n + j.
    """

    def __init__(self, index, n, xp=np, extra=0):
        index = np.asarray(index).ravel()
        n = int(n)
        if index.dtype.kind not in "iu" or (index.size and (index.min() < 0 or index.max() >= n)) \
                or np.unique(index).size != index.size:
            raise ValueError(f"GridPlacement: index must be distinct integers in 0..{n - 1}, got {index.size} "
                             f"values of dtype {index.dtype}")
        self.extra = int(extra)
        self.n, self.ngrid, self.npix, self.xp = n, int(index.size), int(index.size) + self.extra, xp
        self.xout = None
        self.index = xp.asarray(index)
        self._gather = self._cells = self._empty = None          # (_empty: clear()'s row)
        if xp.__name__ == "cupy":
            # every form the kernels read is made here, from the host index: a copy for one call
            # (:meth:`beside`) shares them, and no call reads the index back from the device (a wait for
            # the images queued before it)
            gather = np.full(n, -1, np.int32)
            gather[index] = np.arange(index.size, dtype=np.int32)
            self._gather = xp.asarray(gather)
            self._cells = xp.asarray(np.concatenate([index, n + np.arange(self.extra)]).astype(np.int32))
            row = np.full(n, np.nan, np.float32)
            row[index] = 0.0
            self._empty = xp.asarray(row)

    @property
    def gather(self):
        """On the GPU, the int32 (n,) pixel of each cell (-1: none), for kernels that place as they
        write (:func:`.reduce.products_from_blocks`); None on the CPU."""
        return self._gather

    @property
    def cells(self):
        """On the GPU, the int32 (npix,) cell of each pixel (kernels that write each pixel's cell); None on
        the CPU."""
        return self._cells

    def beside(self, xout):
        """This placement with the destination of the pixels beside the grid for one call: ``xout``
        (..., extra), the same leading axes as the grid's ``out`` (a shallow copy; ``self`` is unchanged)."""
        if int(xout.shape[-1]) != self.extra:
            raise ValueError(f"beside: xout has {xout.shape[-1]} pixels, the placement {self.extra} beside the grid")
        bound = copy.copy(self)
        bound.xout = xout
        return bound

    def clear(self, out):
        """GPU: every image of ``out`` (..., n) float32 contiguous set to 0 in the pixels' cells and NaN in
        the others (one pass of 16-byte stores: what kernels that add each pixel's terms start from)."""
        rows = out.size // self.n
        if not (out.dtype == np.float32 and out.flags.c_contiguous and out.shape[-1] == self.n):
            raise ValueError(f"clear: out must be float32 (..., {self.n}) contiguous, got {out.dtype} {tuple(out.shape)}")
        if rows:
            vec = 4 if self.n % 4 == 0 else 1
            _raw(f"bf_clear_rows<{'float4' if vec == 4 else 'float'}>")(
                ((self.n // vec + 127) // 128, min(rows, 65535)), (128,),
                (out, self._empty, np.int64(rows), np.int32(self.n // vec)))
        return out

    def __call__(self, values, out=None):
        """(..., npix) real or complex -> ``out`` (..., n) (a new array of the values' dtype if None;
        values are cast to a given ``out``'s dtype)."""
        xp = self.xp
        if values.shape[-1] != self.npix:
            raise ValueError(f"expected a last axis of {self.npix} pixels, got shape {tuple(values.shape)}")
        if out is None:
            out = xp.empty(values.shape[:-1] + (self.n,), values.dtype)
        elif out.shape != values.shape[:-1] + (self.n,):
            raise ValueError(f"out must be shaped {values.shape[:-1] + (self.n,)}, got {tuple(out.shape)}")
        if self._gather is None:
            out[...] = np.nan
            out[..., self.index] = values[..., :self.ngrid]
        else:
            v = xp.ascontiguousarray(values, dtype=out.dtype)
            _place_kernel(xp)(v, self._gather, self.n, self.npix, out.dtype.type(np.nan), out)
        if self.extra:                                     # the pixels beside the grid
            if self.xout is None:
                raise ValueError("GridPlacement: pixels beside the grid need their destination (beside(xout))")
            self.xout[...] = values[..., self.ngrid:]
        return out


def take_pixels(values, index):
    """(A, B, ncell) float32 -> (A, B, npix) the cells ``index`` (int32 device array on the GPU), a new
    contiguous array: the inverse of :class:`GridPlacement`. ``values`` may be a strided view whose
    last axis is contiguous (a product of a ring span). On the GPU one kernel with 32-bit indexing
    (CuPy's ``take``, with its generic index arithmetic, runs well below the memory's speed);
    elsewhere ``take``."""
    from ._xp import get_xp
    xp = get_xp(values)
    if xp is np or values.ndim != 3 or values.dtype != np.float32 or values.strides[-1] != 4:
        return xp.take(values, index, axis=-1)
    A, B, ncell = (int(v) for v in values.shape)
    npix = int(index.shape[0])
    out = xp.empty((A, B, npix), xp.float32)
    if out.size == 0:
        return out
    sa, sb = (int(v) // 4 for v in values.strides[:2])
    rows = A * B
    # a block per (pixel run, row): fewer blocks, each walking many rows, are slower
    _raw("bf_take_pixels")(((npix + 255) // 256, min(rows, 65535)), (256,),
                           (values, xp.asarray(index, dtype=xp.int32), out, np.int32(A), np.int32(B), np.int32(npix),
                            np.int64(sa), np.int64(sb)))
    return out


_PLACE = None


def _place_kernel(cp):
    """An ElementwiseKernel (CuPy's, not a .cu file: one snippet for every dtype ``values`` come in, on
    CuPy's indexing of any output shape): i enumerates the output's cells in C order, row i // n of the
    values, cell i % n."""
    global _PLACE
    if _PLACE is None:
        _PLACE = cp.ElementwiseKernel(
            "raw T v, raw int32 gather, int64 n, int64 npix, T fill", "T out",
            "const int k = gather[i % n]; out = k >= 0 ? v[(i / n) * npix + k] : fill;",
            "bf_epic_place_on_grid")
    return _PLACE


_NAMES = ("bf_clear_rows<float>", "bf_clear_rows<float4>")


def _raw(name):
    """A kernel of pixels.cu (``bf_take_pixels``, ``bf_clear_rows<float|float4>``)."""
    return get_kernel("imaging/pixels.cu", name, name_expressions=_NAMES)


register("imaging/pixels.cu")


def lm_grid(size: int, *, cell: float | None = None, horizon_margin: float = 0.0,
            min_elevation_deg: float = 0.0) -> LMGrid:
    """A regular all-sky (or narrower) grid.

    Parameters
    ----------
    size : int   N pixels per side (>= 2).
    cell : float step in l and m; default 2 / N, i.e. the grid spans the whole sky l, m in [-1, 1).
    horizon_margin : float  keep only pixels with sqrt(l^2+m^2) < 1 - horizon_margin.
    min_elevation_deg : float  keep only pixels at or above this elevation (n >= sin(el)): a dipole
        has almost no gain near the horizon, so those pixels are not worth imaging.
    """
    if not (0.0 <= float(min_elevation_deg) < 90.0):
        raise ValueError(f"min_elevation_deg must be in [0, 90) degrees, got {min_elevation_deg!r}")
    if int(size) != size or size < 2:
        raise ValueError(f"grid size must be an integer >= 2, got {size!r}")
    size = int(size)
    cell = 2.0 / size if cell is None else float(cell)
    if not (cell > 0):
        raise ValueError(f"grid cell must be positive, got {cell!r}")
    ax = (np.arange(size) - size // 2) * cell
    mm, ll = np.meshgrid(ax, ax, indexing="ij")
    rho = np.hypot(ll, mm)
    mask = rho < 1.0 - horizon_margin
    if min_elevation_deg > 0:
        mask &= rho <= np.cos(np.radians(float(min_elevation_deg)))   # rho = cos(elevation)
    lm = np.stack([ll[mask], mm[mask]], axis=-1)
    if lm.shape[0] == 0:
        raise ValueError("the grid has no pixel above the horizon")
    return LMGrid(size=size, cell=cell, lm=lm, mask=mask)


def lm_list(pixels_lm) -> np.ndarray:
    """An arbitrary list of (l, m) directions, validated; returns (npix, 2) float64."""
    return check_lm(np.atleast_2d(np.asarray(pixels_lm, dtype=np.float64)))


def lm_from_azalt(az_deg, alt_deg) -> np.ndarray:
    """(npix, 2) direction cosines from azimuth (deg, North through East) and altitude (deg).

    l = cos(alt) sin(az), m = cos(alt) cos(az). Altitude must be in [0, 90] degrees.
    """
    az = np.deg2rad(np.atleast_1d(np.asarray(az_deg, dtype=np.float64)))
    alt_d = np.atleast_1d(np.asarray(alt_deg, dtype=np.float64))
    if az.shape != alt_d.shape:
        raise ValueError(f"azimuth and altitude must have the same shape, got {az.shape} and {alt_d.shape}")
    bad = (alt_d < 0) | (alt_d > 90) | ~np.isfinite(alt_d)
    if np.any(bad):
        i = int(np.argmax(bad))
        raise ValueError(f"altitude {alt_d[i]!r} deg at index {i} is outside [0, 90]: the pixel is below the horizon")
    alt = np.deg2rad(alt_d)
    return np.stack([np.cos(alt) * np.sin(az), np.cos(alt) * np.cos(az)], axis=-1)


def azalt_from_lm(pixels_lm):
    """Inverse of :func:`lm_from_azalt`: (az_deg, alt_deg) arrays for (npix, 2) l, m."""
    lm = np.asarray(pixels_lm, dtype=np.float64)
    n = n_from_lm(lm[:, 0], lm[:, 1])
    az = np.rad2deg(np.arctan2(lm[:, 0], lm[:, 1])) % 360.0
    alt = np.rad2deg(np.arctan2(n, np.hypot(lm[:, 0], lm[:, 1])))
    return az, alt

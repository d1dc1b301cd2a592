"""PNG quicklooks of all-sky images, drawn as seen lying on the ground looking up.

The sky is shown North up and East LEFT (the l axis reversed), as a sky map or a photograph of the
sky taken looking up; axes are labelled 'l (East)' and 'm (North)' and the cardinal points N, E, S, W
are marked just outside the horizon circle (l^2 + m^2 = 1). Pixels below the horizon (NaN) are
drawn dark grey. Colour limits default to the (1, 99.5) percentiles of the finite pixels, so one
very bright source does not wash out the rest.

Matplotlib is used through its object API with the Agg canvas (no pyplot, no display, no global
backend change), so these functions are safe in headless pipelines and threads.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..imaging._xp import to_numpy

__all__ = ["quicklook_png", "quicklook_grid_png", "lwatv_png", "save_figure"]

_MARKER_COLOUR = "cyan"  # far from every colour of the sequential maps used for the sky


def _extent(grid):
    """imshow extent [l_left, l_right, m_bottom, m_top] of pixel edges (before the l reversal)."""
    ax = grid.axis
    h = 0.5 * float(grid.cell)
    return [ax[0] - h, ax[-1] + h, ax[0] - h, ax[-1] + h]


def _limits(images, vmin, vmax, pct):
    vals = np.concatenate([np.asarray(a, dtype=np.float64).ravel() for a in images])
    vals = vals[np.isfinite(vals)]
    if vals.size == 0:
        lo, hi = 0.0, 1.0
    else:
        lo, hi = np.percentile(vals, pct)
    lo = float(lo) if vmin is None else float(vmin)
    hi = float(hi) if vmax is None else float(vmax)
    if not hi > lo:  # a constant image: open the range so the colour map is defined
        hi = lo + (abs(lo) if lo else 1.0)
    return lo, hi


def _check_image(image, grid, what="image"):
    a = np.asarray(to_numpy(image))
    if a.ndim != 2 or a.shape != (grid.size, grid.size):
        raise ValueError(f"{what} must be shaped (N, N) = ({grid.size}, {grid.size}) [m, l]; got {a.shape}")
    if not np.isrealobj(a):
        raise TypeError(f"{what} must be real, got dtype {a.dtype}")
    return a


def _draw_sky(ax, image, grid, *, cmap, lo, hi, sources, horizon, label_sources=True, cardinal=True,
              axis_labels=True):
    from matplotlib import colormaps
    from matplotlib.patches import Circle
    cm = colormaps[cmap].with_extremes(bad="0.2")
    ext = _extent(grid)
    im = ax.imshow(np.ma.masked_invalid(image), origin="lower", extent=ext, cmap=cm, vmin=lo, vmax=hi,
                   interpolation="nearest")
    r = max(1.08, max(abs(e) for e in ext))
    ax.set_xlim(r, -r)  # l reversed: East on the LEFT, as the sky looks from below
    ax.set_ylim(-r, r)
    ax.set_aspect("equal")
    if horizon:
        ax.add_patch(Circle((0.0, 0.0), 1.0, fill=False, color="white", lw=0.8, alpha=0.8))
    if cardinal:
        for txt, x, y in (("N", 0.0, 1.04), ("S", 0.0, -1.04), ("E", 1.04, 0.0), ("W", -1.04, 0.0)):
            ax.text(x, y, txt, color="black", ha="center", va="center", fontsize=9, fontweight="bold",
                    bbox=dict(boxstyle="round,pad=0.15", fc="white", ec="none", alpha=0.8))
    if axis_labels:
        ax.set_xlabel("l (East)  \u2190 East is left")
        ax.set_ylabel("m (North)")
    for label, l, m in sources or ():
        if not (np.isfinite(l) and np.isfinite(m)):
            continue
        ax.plot([l], [m], marker="o", ms=11, mfc="none", mec=_MARKER_COLOUR, mew=1.2)
        if label_sources:
            ax.annotate(str(label), (l, m), xytext=(7, 7), textcoords="offset points", color=_MARKER_COLOUR,
                        fontsize=8, fontweight="bold")
    return im


def save_figure(fig, path, **kwargs) -> str:
    """``fig.savefig`` to ``path`` as a whole: drawn into a hidden file beside it, then renamed over it
    (``os.replace``), so that a reader (the service's page, a person's browser) never gets a file that is
    half written, and the last complete one stays until the next is. Returns the path."""
    import os
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        fig.savefig(tmp, format=kwargs.pop("format", path.suffix.lstrip(".") or "png"), **kwargs)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return str(path)


def _save(fig, path, dpi):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    FigureCanvasAgg(fig)
    return save_figure(fig, path, dpi=dpi, format="png")


def quicklook_png(path, image, grid, *, title=None, sources=None, horizon=True, cmap="inferno", vmin=None,
                  vmax=None, pct=(1.0, 99.5), colorbar=True, units="power (uncalibrated)", dpi=110,
                  size_in=6.0) -> str:
    """Write one all-sky image as a PNG; returns the path.

    image : (N, N) [m, l] real array (NumPy or CuPy), NaN below the horizon; grid : its LMGrid.
    sources : [(label, l, m), ...] drawn as labelled open circles (NaN l/m skipped: below horizon).
    vmin, vmax : colour limits; each defaults to the ``pct`` percentile of the finite pixels.
    colorbar : draw a colour bar labelled ``units``. Orientation: North up, East left.
    """
    from matplotlib.figure import Figure
    img = _check_image(image, grid)
    lo, hi = _limits([img], vmin, vmax, pct)
    fig = Figure(figsize=(size_in + (1.2 if colorbar else 0.0), size_in))
    ax = fig.add_subplot(1, 1, 1)
    im = _draw_sky(ax, img, grid, cmap=cmap, lo=lo, hi=hi, sources=sources, horizon=horizon)
    if title:
        ax.set_title(title, fontsize=10)
    if colorbar:
        fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04, label=units)
    fig.tight_layout()  # (constrained layout clips the m label of an equal-aspect axes here)
    return _save(fig, path, dpi)


def quicklook_grid_png(path, cube, grid, freq_hz, *, title=None, sources=None, horizon=True, cmap="inferno",
                       vmin=None, vmax=None, pct=(1.0, 99.5), shared_scale=True, max_panels=16, ncols=None,
                       units="power (uncalibrated)", dpi=90, panel_in=2.6) -> str:
    """Write a grid of per-channel all-sky images as one PNG; returns the path.

    cube : (nchan, N, N) [chan, m, l] real array; freq_hz : (nchan,) channel centres (Hz), used as
    panel titles. At most ``max_panels`` channels are drawn, evenly spaced over the band (first and
    last included). shared_scale : one colour scale (and bar) for all panels, else one per panel.
    sources : [(label, l, m), ...] marked in every panel (labels on the first panel only).
    """
    from matplotlib.figure import Figure
    c = np.asarray(to_numpy(cube))
    if c.ndim != 3 or c.shape[1:] != (grid.size, grid.size):
        raise ValueError(f"cube must be shaped (nchan, N, N) = (nchan, {grid.size}, {grid.size}) [chan, m, l]; "
                         f"got {c.shape}")
    f = np.atleast_1d(np.asarray(freq_hz, dtype=np.float64))
    if f.size != c.shape[0]:
        raise ValueError(f"cube has {c.shape[0]} channels but freq_hz has {f.size}")
    if int(max_panels) < 1:
        raise ValueError(f"max_panels must be >= 1, got {max_panels!r}")
    nchan = c.shape[0]
    sel = np.unique(np.round(np.linspace(0, nchan - 1, min(nchan, int(max_panels)))).astype(int))
    n = sel.size
    ncols = int(ncols) if ncols else int(np.ceil(np.sqrt(n)))
    nrows = int(np.ceil(n / ncols))
    fig = Figure(figsize=(panel_in * ncols + (1.0 if shared_scale else 0.0), panel_in * nrows + (0.4 if title else 0.0)),
                 layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False)
    shared = _limits([c[k] for k in sel], vmin, vmax, pct) if shared_scale else None
    im = None
    for j, ax in enumerate(axes.ravel()):
        if j >= n:
            ax.set_axis_off()
            continue
        k = int(sel[j])
        lo, hi = shared if shared_scale else _limits([c[k]], vmin, vmax, pct)
        im = _draw_sky(ax, c[k], grid, cmap=cmap, lo=lo, hi=hi, sources=sources, horizon=horizon,
                       label_sources=(j == 0), cardinal=True, axis_labels=False)
        ax.set_title(f"ch {k}: {f[k] / 1e6:.3f} MHz", fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
        if not shared_scale:
            fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02)
    if title:
        fig.suptitle(f"{title}   (North up, East left)", fontsize=10)
    if shared_scale and im is not None:
        fig.colorbar(im, ax=axes.ravel().tolist(), fraction=0.03, pad=0.02, label=units)
    return _save(fig, path, dpi)


def lwatv_png(path, stokes_i, abs_v, pixel_deg, *, when="", freq_hz=None, labels=(), spectrum=None,
              spectrum_freq_hz=None, spectrum_label="") -> str:
    """The station's LWATV view of one channel: Stokes I and |V| side by side on black, each clipped at the
    horizon, with the sources labelled, the time and frequency written in, and the band's spectrum below
    with the shown channel marked (as Orville draws its ``lwatv`` PNGs).

    stokes_i, abs_v : (ngrid, ngrid) images in OIMS orientation (row North, column West; the zenith at
        ((ngrid - 1) / 2, (ngrid - 1) / 2)); abs_v None: I alone. pixel_deg : degrees a pixel (sine
        projection). labels : [(name, l, m)] above the horizon. spectrum : (nchan,) values against
        spectrum_freq_hz (drawn on a log scale where all are positive), the shown channel freq_hz marked.
    """
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    img_i = np.nan_to_num(np.asarray(stokes_i, np.float64))
    n = img_i.shape[0]
    c = (n - 1) / 2.0
    r = np.degrees(1.0) / float(pixel_deg)                       # the horizon's radius in pixels
    panels = [("I", img_i)] + ([("|V|", np.abs(np.nan_to_num(np.asarray(abs_v, np.float64))))] if abs_v is not None else [])
    fig = Figure(figsize=(5 * len(panels), 6.2), facecolor="black")
    FigureCanvasAgg(fig)
    top = 0.22
    inside = (np.hypot(*np.meshgrid(np.arange(n) - c, np.arange(n) - c, indexing="ij")) < r)
    vmax = max(1e-6, float(np.percentile(img_i[inside], 99.75))) if inside.any() else 1.0
    for k, (name, img) in enumerate(panels):
        ax = fig.add_axes([k / len(panels), top, 1.0 / len(panels), 1 - top - 0.06])
        ax.set_facecolor("black")
        im = ax.imshow(img, origin="lower", vmin=0, vmax=vmax, interpolation="bilinear", cmap="jet")
        clip = Circle((c, c), 1.03 * r, facecolor="none", edgecolor="none")
        ax.add_patch(clip)
        im.set_clip_path(clip)
        ax.set_xticks([])
        ax.set_yticks([])
        for lab, l, m in labels:
            ax.text(c - l * r, c + m * r, str(lab), color="white", fontsize=12)
        ax.text(0.02 if k == 0 else 0.98, 0.98, name, color="white", fontsize=13, va="top",
                ha="left" if k == 0 else "right", transform=ax.transAxes)
    fig.text(0.01, 0.995, when, color="white", fontsize=12, va="top")
    if freq_hz is not None:
        fig.text(0.99, 0.995, f"{float(freq_hz) / 1e6:.3f} MHz", color="white", fontsize=12, va="top", ha="right")
    if spectrum is not None and spectrum_freq_hz is not None:
        sp = np.asarray(spectrum, np.float64)
        f = np.asarray(spectrum_freq_hz, np.float64) / 1e6
        sax = fig.add_axes([0.06, 0.03, 0.88, top - 0.06], facecolor="black")
        (sax.semilogy if np.all(sp > 0) else sax.plot)(f, sp, color="white")
        if freq_hz is not None:
            j = int(np.argmin(np.abs(f - float(freq_hz) / 1e6)))
            sax.scatter([f[j]], [sp[j]], color="red", zorder=3)
        sax.tick_params(colors="white", labelsize=8)
        sax.set_xlabel("MHz", color="white", fontsize=8)
        sax.set_title(spectrum_label, color="white", fontsize=8, loc="left")
        for sp_ in sax.spines.values():
            sp_.set_color("white")
    return save_figure(fig, path, dpi=78, format="png", facecolor="black")

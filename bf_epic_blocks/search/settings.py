"""The transient search's settings: one frozen object, checked when it is made.

:class:`SearchSettings` is what :class:`~bf_epic_blocks.blocks.transient_search.TransientSearchBlock`
is configured by (the pipeline builds it from the YAML's ``imager.search`` section) and what ``bf-epic
plan`` sizes the search with; :meth:`SearchSettings.search_keywords` turns it, for images at given
frequencies and cadence, into the :class:`~.statistics.TransientSearch` keywords.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .statistics import REFINE_SLACK, REFINE_SPAN, TREE_CHANNELS

__all__ = ["SearchSettings"]


@dataclass(frozen=True)
class SearchSettings:
    """How to search image sequences for transients.

    threshold : S/N above which a trial is a crossing (default 6).
    window_s : sliding statistics window, seconds (> 0; at least 3 images are used).
    dms : trial DMs, pc cm^-3 (finite, >= 0; default (0,)); with ``dedisperse='tree'`` the trials are
        every sweep up to max(dms)'s, and each candidate's DM is its sweep's.
    widths : boxcar widths in images (distinct integers >= 1; default (1, 2, 4, 8)).
    average_channels : dedisperse and average the channels (default), or search each channel.
    product : which image product to search (name, e.g. 'I'; None: the first).
    dedisperse : 'shifts', 'tree' or 'auto' (see :class:`~.statistics.TransientSearch`).
    tree_precision : 'fp32' or 'fp16', what the tree stores (see :class:`~.tree.StreamingFDMT`).
    max_pixels : crossings kept per trial image, the brightest (integer >= 1).
    sky_fraction : a trial image with more than this fraction of its pixels over the threshold is one
        sky-wide crossing (in (0, 1]).
    space_link : clustering distance in grid pixels (grids) or in l/m (pixel lists); None: 2 grid
        pixels, or twice the median nearest-neighbour distance of a pixel list.
    time_link : clustering distance in images (None: the widest boxcar).
    lc_before, lc_after : light-curve images before and after the event start (integers >= 0).
    sidelobe_factor : a point candidate whose S/N is at most this many times what a brighter one puts
        at its pixel (through the array's beam, or its DM sidelobe) is folded into it (>= 0; 0 keeps
        every candidate a row of its own).
    """

    threshold: float = 6.0
    window_s: float = 1.0
    dms: tuple = (0.0,)
    widths: tuple = (1, 2, 4, 8)
    average_channels: bool = True
    product: str | None = None
    dedisperse: str = "shifts"
    tree_precision: str = "fp32"
    max_pixels: int = 32
    sky_fraction: float = 0.1
    space_link: float | None = None
    time_link: int | None = None
    lc_before: int = 32
    lc_after: int = 32
    sidelobe_factor: float = 2.0

    def __post_init__(self):
        def fix(name, value):
            object.__setattr__(self, name, value)

        def whole(name, low):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer, float)) or int(v) != v or v < low:
                raise ValueError(f"SearchSettings: {name} must be an integer >= {low}, got {v!r}")
            fix(name, int(v))

        if not _real(self.threshold) or not math.isfinite(self.threshold):
            raise ValueError(f"SearchSettings: threshold must be a finite S/N, got {self.threshold!r}")
        fix("threshold", float(self.threshold))
        if not _real(self.window_s) or not self.window_s > 0 or not math.isfinite(self.window_s):
            raise ValueError(f"SearchSettings: window_s must be > 0 seconds, got {self.window_s!r}")
        fix("window_s", float(self.window_s))
        dms = np.atleast_1d(np.asarray(self.dms, dtype=object))
        if not dms.size or not all(_real(d) and math.isfinite(d) and d >= 0 for d in dms):
            raise ValueError(f"SearchSettings: dms must be finite DMs >= 0 (pc cm^-3), at least one, got {self.dms!r}")
        fix("dms", tuple(float(d) for d in dms))
        widths = np.atleast_1d(np.asarray(self.widths, dtype=object))
        if (not widths.size or not all(_real(w) and int(w) == w and w >= 1 for w in widths)
                or len(set(int(w) for w in widths)) != widths.size):
            raise ValueError(f"SearchSettings: widths must be distinct integers >= 1 (images), got {self.widths!r}")
        fix("widths", tuple(int(w) for w in widths))
        if not isinstance(self.average_channels, (bool, np.bool_)):
            raise ValueError(f"SearchSettings: average_channels must be true or false, got {self.average_channels!r}")
        fix("average_channels", bool(self.average_channels))
        if self.product is not None and not isinstance(self.product, str):
            raise ValueError(f"SearchSettings: product must be a product name (e.g. 'I') or None, got {self.product!r}")
        if self.dedisperse not in ("shifts", "tree", "auto"):
            raise ValueError(f"SearchSettings: dedisperse must be 'shifts', 'tree' or 'auto', got {self.dedisperse!r}")
        if self.tree_precision not in ("fp32", "fp16"):
            raise ValueError(f"SearchSettings: tree_precision must be 'fp32' or 'fp16', got {self.tree_precision!r}")
        whole("max_pixels", 1)
        if not _real(self.sky_fraction) or not 0 < self.sky_fraction <= 1:
            raise ValueError(f"SearchSettings: sky_fraction must be a fraction in (0, 1], got {self.sky_fraction!r}")
        fix("sky_fraction", float(self.sky_fraction))
        if self.space_link is not None:
            if not _real(self.space_link) or not self.space_link > 0:
                raise ValueError(f"SearchSettings: space_link must be > 0 (grid pixels or l/m) or None, "
                                 f"got {self.space_link!r}")
            fix("space_link", float(self.space_link))
        if self.time_link is not None:
            whole("time_link", 0)
        whole("lc_before", 0)
        whole("lc_after", 0)
        if not _real(self.sidelobe_factor) or not self.sidelobe_factor >= 0:
            raise ValueError(f"SearchSettings: sidelobe_factor must be >= 0, got {self.sidelobe_factor!r}")
        fix("sidelobe_factor", float(self.sidelobe_factor))

    def search_keywords(self, freq_hz, dt_s):
        """``(keywords, time_link)``: the :class:`~.statistics.TransientSearch` keywords for images at
        ``freq_hz`` (Hz) every ``dt_s`` seconds (``window``, ``dms``, ``widths``, ``average_channels``,
        ``hold``, ``dedisperse`` resolved, ``tree_precision``, and ``max_batch`` for the tree), and the
        clustering's time link in images."""
        widths = list(self.widths)
        window = max(3, int(round(self.window_s / dt_s)))
        tlink = max(widths) if self.time_link is None else self.time_link
        dedisperse = self.dedisperse
        if dedisperse == "auto":
            dedisperse = "tree" if self.average_channels and len(np.atleast_1d(freq_hz)) >= TREE_CHANNELS else "shifts"
        # a candidate's row looks back at its crossing (the light curve, its window, its boxcar on every
        # pixel, its S/N in the trials around it) once the values after it are there, a batch at a time,
        # not when its cluster closes (up to the largest sweep later: tens of GB of history for a whole
        # band): values reach this far after the event's first, and back beyond the window
        hold = look_ahead(self.lc_after, max(widths), self.average_channels) + _reach(self.average_channels)
        kw = dict(window=window, dms=list(self.dms), widths=widths, average_channels=self.average_channels,
                  hold=hold, dedisperse=dedisperse, tree_precision=self.tree_precision)
        if dedisperse == "tree":
            kw["max_batch"] = 64            # the tree's many trials: a history of one gulp's batch, not 256
        return kw, tlink


def _reach(average_channels):
    """Values either side of an event that its DM between the trials reads (``refine_dm``'s first view)."""
    return REFINE_SPAN + REFINE_SLACK if average_channels else 0


def look_ahead(lc_after, wmax, average_channels):
    """Values after an event's first (value index ``n``) that its candidate row reads: the light curve's
    ``lc_after``, the widest boxcar, and the S/N in the trials around it (``refine_dm``'s first view reads
    up to ``n + reach + wmax - 1``). The row is formed once value ``n + look_ahead`` has been searched."""
    return max(int(lc_after), int(wmax), _reach(average_channels) + int(wmax) - 1)


def _real(v):
    """A real number (not a bool, not a string)."""
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))

"""Triggered saves: the last seconds of band-averaged images kept in a ring where the images are (the
GPU's memory on a GPU), written to an HDF5 snippet with the seconds after it when something triggers.

Triggers come from the transient search (each candidate), a watch target's light curve crossing its
threshold (:class:`~.watch.WatchWriterBlock`), or outside: a file dropped in ``trigger_dir`` (its first
line is the reason; the file is moved to ``trigger_dir/done``). All go through a :class:`TriggerBus`;
:class:`SnippetBlock` reads the main imager's images, keeps the ring and writes the snippets. A trigger
within ``hold_off_s`` of the last one saved is counted, not saved, so that a flash that fires hundreds of
triggers writes one snippet.

Snippet file ``<prefix>_snippet_<UTC>_<reason>.h5`` (h5py): ``images`` (ntime, ...) float32, the band
mean of the imager's first product at each image (the grid (N, N), NaN below the horizon, or the pixel
list); ``time_unix`` (ntime,) float64 image centres; attributes ``reason``, ``trigger_unix``, ``product``,
``pixels`` (the imager header's pixel description, JSON), ``held`` (triggers held off while it was open),
``complete`` (True when it holds its whole after-window; False when the data ended first or the next save
cut it short). A trigger that reaches the bus after the last images (a search lags its images) is saved from
the ring when the run ends.
"""
from __future__ import annotations

import collections
import json
import math
import logging
import os
import re
import threading
from pathlib import Path

import numpy as np

from . import _compat
from ._compat import bfp, span_array, to_numpy

__all__ = ["SnippetBlock", "TriggerBus"]

log = logging.getLogger(__name__)



class TriggerBus:
    """Triggers posted from any thread, taken by the snippet block: (time_unix of the data, reason).
    ``listeners``: callables told of each trigger as a dict (``time_utc`` ISO, ``reason``, and what the
    poster knows: ``ra_deg``, ``dec_deg``, ``snr``, ``dm``, ``width_ms``), e.g. an
    :class:`~bf_epic_blocks.io.alerts.AlertSender`'s ``send``."""

    def __init__(self):
        self._q = collections.deque()
        self._requests = collections.deque()
        self._lock = threading.Lock()
        self.posted = 0
        self.listeners = []

    def request(self, reason):
        """A trigger from outside the data (the service's POST /trigger): the snippet block posts it at the
        time of its newest images, as it does a trigger file."""
        with self._lock:
            self._requests.append(str(reason))

    def take_requests(self):
        with self._lock:
            out = list(self._requests)
            self._requests.clear()
        return out

    def post(self, time_unix, reason, info=None):
        with self._lock:
            self._q.append((float(time_unix), str(reason)))
            self.posted += 1
            n = self.posted
        if self.listeners:
            from astropy.time import Time
            stamp = Time(float(time_unix), format="unix").isot.replace("-", "").replace(":", "")
            alert = {"id": f"{stamp}_{n}",
                     "time_utc": Time(float(time_unix), format="unix").isot, "reason": str(reason), **(info or {})}
            for fn in self.listeners:
                try:
                    fn(alert)
                except Exception as e:  # noqa: BLE001 - a listener must not stop the poster
                    log.warning("TriggerBus: a listener failed: %s", e)

    def take(self):
        with self._lock:
            out = list(self._q)
            self._q.clear()
        return out


def _slug(text):
    return re.sub(r"[^A-Za-z0-9_.-]+", "-", text).strip("-")[:40] or "trigger"


class SnippetBlock(bfp.SinkBlock):
    """Keep the last ``ring_s`` of band-averaged images; on a trigger write them and the next
    ``after_s`` to a snippet (module docstring).

    Parameters
    ----------
    iring : the imager's images (time, freq, pol, pixels...).
    outdir, prefix : where the snippets go, ``<prefix>_snippet_...h5``.
    bus : the :class:`TriggerBus` the triggers come through.
    ring_s, after_s, hold_off_s : seconds of images before and after a trigger, and between saves.
    late_s : seconds a trigger may reach the bus after its own time (a search's latency: its window and
        the dispersion sweep) and still find all ``ring_s`` before it; the ring holds ring_s + late_s.
        A snippet holds the images from ``trigger - ring_s`` to ``trigger + after_s`` whenever it arrives
        within that, so that it does not depend on how far the search lagged.
    trigger_dir : a folder whose new files are triggers (None: none).
    ``stats``: triggers seen, saved, held off, and from files; ``written`` the snippets closed.
    """

    def __init__(self, iring, outdir, prefix, bus, ring_s=2.0, after_s=1.0, hold_off_s=10.0, trigger_dir=None,
                 late_s=2.0, **kwargs):
        super().__init__(iring, **kwargs)
        self.outdir, self.prefix, self.bus = Path(outdir), prefix, bus
        self.ring_s, self.after_s, self.hold_off_s = float(ring_s), float(after_s), float(hold_off_s)
        self.late_s = float(late_s)
        self.trigger_dir = None if trigger_dir is None else Path(trigger_dir)
        self.trig_stats = {"triggers": 0, "saved": 0, "held": 0, "from_files": 0, "from_requests": 0}
        self.written = []
        self._ring = None            # (keep, pixels...) float32 band means, where the images are (CuPy or NumPy)
        self._ring_t = None          # (keep,) float64 their times on the host; NaN: an empty slot
        self._open = None            # (h5py File, end time, nrows)
        self._last_saved = -np.inf

    def define_valid_input_spaces(self):
        return "any"

    def on_sequence(self, iseq):
        hdr = iseq.header
        tens = hdr["_tensor"]
        self._t0, self._dt = float(tens["scales"][0][0]), float(tens["scales"][0][1])
        self._pixels = json.dumps(hdr.get("pixels", {}), default=lambda o: np.asarray(o).tolist())
        self._product = (hdr.get("pol_products") or ["?"])[0]
        self._image = 0
        self._ring = None
        self._keep = max(1, int(math.ceil((self.ring_s + self.late_s) / self._dt)))

    def on_data(self, ispan):
        x = span_array(ispan)
        n = int(x.shape[0])
        if n == 0:
            return
        first = getattr(ispan, "frame_offset", self._image)
        t = self._t0 + (first + np.arange(n) + 0.5) * self._dt
        self._image = first + n
        with _compat.stream_context():
            band = x[:, :, 0].mean(axis=1)                     # (n, pixels...): the band mean, first product
            self._remember(t, band)
            if self._open is not None:                         # only an open snippet brings images to the host
                self._append_open(t, to_numpy(band))
        for when, reason in self._triggers(t[-1]):
            self._trigger(when, reason)

    def _remember(self, t, band):
        """Write the gulp's band means into the ring (a device copy; the host sees them only on a trigger)."""
        if self._ring is None:
            xp = _compat.input_xp(self)
            self._ring = xp.zeros((self._keep,) + tuple(band.shape[1:]), np.float32)
            self._ring_t = np.full(self._keep, np.nan)
        if t.size > self._keep:
            t, band = t[-self._keep:], band[-self._keep:]
        slots = (np.arange(t.size) + self._image - t.size) % self._keep
        lo = int(slots[0])
        k = min(t.size, self._keep - lo)                       # at most two contiguous pieces
        self._ring[lo:lo + k] = band[:k]
        self._ring[:t.size - k] = band[k:]
        self._ring_t[slots] = t

    def _image_time(self):
        """The time of the newest image seen."""
        return self._t0 + (self._image - 0.5) * self._dt

    def _ring_rows(self):
        """(times, images) of the ring on the host, oldest first."""
        if self._ring is None:
            return np.empty(0), None
        order = np.argsort(self._ring_t)                       # NaN (empty) last
        order = order[~np.isnan(self._ring_t[order])]
        with _compat.stream_context():
            return self._ring_t[order], to_numpy(self._ring)[order]

    def _triggers(self, now):
        """The bus's triggers, with each new file of ``trigger_dir`` posted to it first (at the data's time
        ``now``, so that its listeners hear of it as of any other)."""
        if self.trigger_dir is not None and self.trigger_dir.is_dir():
            done = self.trigger_dir / "done"
            for e in sorted(os.scandir(self.trigger_dir), key=lambda e: e.name):
                if not e.is_file():
                    continue
                try:
                    reason = Path(e.path).read_text(errors="replace").strip().splitlines()
                    reason = reason[0][:200] if reason and reason[0] else e.name
                    done.mkdir(exist_ok=True)
                    os.replace(e.path, done / e.name)
                except OSError as err:
                    log.warning("SnippetBlock: trigger file %s not read: %s", e.path, err)
                    continue
                self.trig_stats["from_files"] += 1
                self.bus.post(now, f"file: {reason}")
        for reason in self.bus.take_requests():
            self.trig_stats["from_requests"] += 1
            self.bus.post(now, reason)
        return self.bus.take()

    def _trigger(self, when, reason):
        self.trig_stats["triggers"] += 1
        if when - self._last_saved < self.hold_off_s:
            self.trig_stats["held"] += 1
            if self._open is not None:
                self._open[0].attrs["held"] = int(self._open[0].attrs["held"]) + 1
            return
        self._last_saved = when
        self._close(complete=False)      # the previous one, cut short by this one
        import h5py
        from astropy.time import Time
        stamp = Time(when, format="unix", scale="utc").isot.replace("-", "").replace(":", "")    # ...T100000.329
        path = self.outdir / f"{self.prefix}_snippet_{stamp}_{_slug(reason)}.h5"
        self.outdir.mkdir(parents=True, exist_ok=True)
        f = h5py.File(path, "w")
        t_ring, imgs = self._ring_rows()
        shape = imgs.shape[1:] if imgs is not None else ()
        if t_ring.size:
            filled = t_ring.size >= self._keep      # not: the sequence began less than the ring's span ago
            keep = t_ring >= when - self.ring_s
            t_ring, imgs = t_ring[keep], imgs[keep]
            if t_ring.size and t_ring[0] > when - self.ring_s + self._dt and not filled:
                log.info("SnippetBlock: the trigger (%s) came %.2f s after the sequence's first image: its snippet "
                         "starts there, not %.2f s before it", reason, when - t_ring[0], self.ring_s)
            elif t_ring.size and t_ring[0] > when - self.ring_s + self._dt:
                log.warning("SnippetBlock: the trigger (%s) came %.2f s after its time, more than late_s = %.2f s: "
                            "its snippet starts %.2f s before it, not %.2f s", reason, self._image_time() - when,
                            self.late_s, when - t_ring[0], self.ring_s)
        f.create_dataset("images", (0,) + shape, "f4", maxshape=(None,) + shape, chunks=(16,) + shape)
        f.create_dataset("time_unix", (0,), "f8", maxshape=(None,), chunks=(256,))
        f.attrs.update({"reason": reason, "trigger_unix": when, "product": self._product, "pixels": self._pixels,
                        "held": 0, "complete": False, "band_averaged": True})
        self._open = [f, when + self.after_s, 0]
        self.trig_stats["saved"] += 1
        if t_ring.size and self._rows(t_ring, imgs):
            self._close()                      # the trigger came late (a search's latency): all is in the ring
        log.info("triggered save (%s) at %s UTC -> %s", reason, Time(when, format="unix").isot, path.name)

    def _rows(self, t, imgs):
        f, end, nrow = self._open
        keep = t <= end
        t, imgs = t[keep], imgs[keep]
        if t.size:
            for k, v in (("images", imgs), ("time_unix", t)):
                f[k].resize(nrow + t.size, axis=0)
                f[k][nrow:] = v
            self._open[2] = nrow + t.size
        return not keep.all()

    def _append_open(self, t, band):
        if self._open is not None and self._rows(t, band):
            self._close()

    def _close(self, complete=True):
        """Close the open snippet; ``complete``: its after-window was covered (False: the data ended first)."""
        if self._open is not None:
            f = self._open[0]
            f.attrs["complete"] = bool(complete)
            self.written.append(f.filename)
            f.close()
            self._open = None

    def on_sequence_end(self, iseq):
        self._close(complete=False)

    def finish(self):
        """Save the triggers that reached the bus after the last images (a search lags its images),
        from the ring; the runner calls this once every block is done."""
        if self._ring is None:
            return
        for when, reason in self._triggers(float(np.nanmax(self._ring_t))):
            self._trigger(when, reason)
        self._close(complete=False)

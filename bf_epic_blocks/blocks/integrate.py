"""ImageIntegratorBlock: longer images from an imager's short ones -- the mean of every ``nimage``
images, and optionally of all channels (a band-averaged image).

Why a block: at 0.64-ms cadence over a whole tuning the imager makes ~1.2 million channel images a
second, which no disk takes; a station keeps their band mean at a cadence it chooses (1 s: one
FITS + PNG a second), and the image writer downstream writes those as it writes any imager's.

Output header (docs/HEADERS.md, "Written by DFTImagerBlock"), from the input's: the time scale's
step and ``imager.integration_ticks`` times ``nimage``; with ``average_channels`` one channel at the
band's mean frequency, ``freq_hz`` [mean] and the frequency scale's step the band's width
(nchan x the channel spacing); ``integrated = {images, average_channels, nchan_in}``. Pixels, products
and the pixel layout are unchanged; a pixel NaN in any input (below the horizon) stays NaN.

Images at the end of a sequence that do not fill an integration are counted
(``int_stats['images_dropped_partial']``) and logged, as the imagers do with frames.
"""
from __future__ import annotations

import logging
import math

import numpy as np

from ..imaging._xp import get_xp
from ..imaging.reduce import channel_mean, rows_nonzero
from . import _compat
from ._compat import bfp, span_array
from .headers import derived_header, image_layout

log = logging.getLogger(__name__)


class ImageIntegratorBlock(bfp.TransformBlock):
    """Mean of every ``nimage`` consecutive images (and of the channels, with ``average_channels``).

    iring : an imager's output ring (grid or pixel list; any space: sums stay where the ring lives,
    float64 per output pixel).  nimage : images per output; or seconds : the output's length, made
    ``max(1, round(seconds / image length))`` images of each sequence (its header's time scale).
    space : the output ring's space (default the input's): 'system' brings the (small) results to
    the host, as a pixel split's parts do before :class:`~.pixel_merge.PixelMergeBlock` joins them.
    """

    def __init__(self, iring, nimage=None, average_channels=True, *args, seconds=None, space=None, **kwargs):
        if (nimage is None) == (seconds is None):
            raise ValueError("ImageIntegratorBlock: give nimage (images) or seconds, one of them")
        if nimage is not None and (isinstance(nimage, bool) or int(nimage) != nimage or nimage < 1):
            raise ValueError(f"ImageIntegratorBlock: nimage must be a positive integer, got {nimage!r}")
        if seconds is not None and not seconds > 0:
            raise ValueError(f"ImageIntegratorBlock: seconds must be > 0, got {seconds!r}")
        super().__init__(iring, *args, **kwargs)
        self.nimage = None if nimage is None else int(nimage)
        self.seconds, self.average_channels = seconds, bool(average_channels)
        self._int_stats = {"images_in": 0, "images_out": 0, "images_dropped_partial": 0, "channel_images_flagged": 0}
        self._flagged_dev = None          # on a GPU: channel images flagged, summed there until int_stats is read
        if space is not None:
            self.orings = [self.create_ring(space=space)]

    @property
    def int_stats(self):
        """Counts: images in and out, images dropped at a sequence's end, channel images left out of a band
        mean as wholly flagged (on a GPU summed there each gulp and brought to the host when read here:
        a copy each gulp would wait for the imager's queued images)."""
        if self._flagged_dev is not None:
            pending, self._flagged_dev = self._flagged_dev, None
            self._int_stats["channel_images_flagged"] += int(_compat.to_numpy(pending))
        return self._int_stats

    def define_valid_input_spaces(self):
        return "any"

    def define_output_nframes(self, input_nframe):
        """At most this many integrations end in a gulp of ``input_nframe`` images (all of them, while
        the length in images is not yet known)."""
        return max(1, math.ceil(input_nframe / self.nimage)) if self.nimage else max(1, input_nframe)

    def on_sequence(self, iseq):
        ihdr = iseq.header
        lay = image_layout(ihdr, "ImageIntegratorBlock")
        if self.seconds is not None:
            self.nimage = max(1, int(round(self.seconds / lay["dt_s"])))
        self._n = 0
        self._sum = self._w = None
        self._flagging = bool(ihdr.get("flagging"))
        ohdr = derived_header(ihdr)
        t = ohdr["_tensor"]
        t["scales"] = list(t.get("scales") or [None] * len(t["shape"]))
        t["scales"][0] = [lay["t0_s"], lay["dt_s"] * self.nimage]
        f = np.asarray(lay["freq_hz"], np.float64)
        if self.average_channels and len(f) > 1:
            step = float(f[1] - f[0])
            t["shape"] = [t["shape"][0], 1] + list(t["shape"][2:])
            t["scales"][1] = [float(f.mean()), step * len(f)]
            ohdr["freq_hz"] = [float(f.mean())]
        imager = dict(ohdr.get("imager") or {})
        if "integration_ticks" in imager:
            imager["integration_ticks"] = int(imager["integration_ticks"]) * self.nimage
        ohdr["imager"] = imager
        # an integration of an integration (the band mean of each image, then its mean over a second):
        # what both did, against the imager's images
        prev = ihdr.get("integrated") or {}
        ohdr["integrated"] = {"images": self.nimage * int(prev.get("images", 1)),
                              "average_channels": self.average_channels or bool(prev.get("average_channels")),
                              "nchan_in": int(prev.get("nchan_in", lay["nchan"]))}
        log.info("ImageIntegratorBlock %s: the mean of every %d images (%.3f s)%s", ihdr.get("name"), self.nimage,
                 self.nimage * lay["dt_s"], f", {len(f)} channels averaged" if self.average_channels else "")
        return ohdr

    def on_data(self, ispan, ospan):
        x = span_array(ispan)
        out = span_array(ospan)
        xp = get_xp(x)
        n = x.shape[0]
        nout = 0
        pos = 0
        if self.nimage == 1:
            # each image its own output (the band mean of each, a pixel split's parts): all at once
            part = self._band_mean(x) if self.average_channels else x
            out[:n] = _to_space(part.astype(out.dtype), out)
            pos = nout = n
        while pos < n:
            take = min(self.nimage - self._n, n - pos)
            part = x[pos:pos + take]
            live = None
            if self._flagging:
                # images (or channel images) wholly flagged are left out of the time mean
                live = rows_nonzero(part)                                                      # (take, C)
                w = live.any(axis=1, keepdims=True) if self.average_channels else live
                w = w.sum(axis=0).astype(xp.float64)
                self._w = w if self._w is None else self._w + w
            if self.average_channels:
                part = self._band_mean(part, live)
            s = part.sum(axis=0, dtype=xp.float64)
            self._sum = s if self._sum is None else self._sum + s
            self._n += take
            pos += take
            if self._n == self.nimage:
                if self._w is None:
                    mean = self._sum / self.nimage
                else:
                    w = self._w.reshape((-1,) + (1,) * (self._sum.ndim - 1))
                    mean = xp.where(w > 0, self._sum / xp.maximum(w, 1), 0.0)
                out[nout] = _to_space(mean.astype(out.dtype), out)
                nout += 1
                self._sum, self._n, self._w = None, 0, None
        self._int_stats["images_in"] += n
        self._int_stats["images_out"] += nout
        return nout

    def _band_mean(self, x, live=None):
        """The channel mean of x (n, C, ...); after interference flagging (the header's ``flagging``) the mean
        of the channels that imaged anything (``live``: :func:`~..imaging.reduce.rows_nonzero`; a channel whose
        voltages were all flagged images as zeros), since a wholly flagged channel's
        zeros would pull the mean down. An image with every channel flagged is 0."""
        m = channel_mean(x)
        if not self._flagging:
            return m
        xp = get_xp(x)
        n, C = x.shape[0], x.shape[1]
        live = rows_nonzero(x) if live is None else live
        used = live.sum(axis=1)
        if xp is np:
            self._int_stats["channel_images_flagged"] += int(n * C - int(used.sum()))
        else:
            flagged = n * C - used.sum()
            self._flagged_dev = flagged if self._flagged_dev is None else self._flagged_dev + flagged
        scale = xp.where(used > 0, C / xp.maximum(used, 1), 0.0).astype(xp.float64)
        return m * scale.reshape((n, 1) + (1,) * (m.ndim - 2))

    def on_sequence_end(self, iseq):
        if self._n:
            self._int_stats["images_dropped_partial"] += self._n
            log.warning("ImageIntegratorBlock: %d images at the end of sequence %s did not fill an integration of %d "
                        "and were not written", self._n, iseq.header.get("name"), self.nimage)
            self._sum, self._n, self._w = None, 0, None


def _to_space(a, out):
    """``a`` where ``out`` lives (a GPU result for a host output ring is copied to the host)."""
    return _compat.to_numpy(a) if isinstance(out, np.ndarray) else a


def image_integrator(iring, nimage=None, *args, **kwargs):
    """Functional form of :class:`ImageIntegratorBlock`."""
    return ImageIntegratorBlock(iring, nimage, *args, **kwargs)

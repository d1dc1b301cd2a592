"""ImageCubeWriterBlock: an imager's output stream into HDF5 image cubes with a time axis.

A thin sink over :class:`bf_epic_blocks.io.cube.ImageCubeWriter` (why HDF5, and the file layout,
are in that module). Guaranteed reader by default: the imager waits rather than lose an image
(Bifrost's back-pressure); with ``guarantee=False`` lost images are counted, logged and recorded in
the file (``images_lost``; the ``time_tag`` of later images jumps over them).
"""
from __future__ import annotations

import logging
import os

import numpy as np

from ._compat import bfp, frames_lost_at_end, frames_lost_before, frames_overwritten, span_array, to_numpy
from .headers import image_layout, station_location

log = logging.getLogger(__name__)


class ImageCubeWriterBlock(bfp.SinkBlock):
    """Write every image of ``iring`` to ``<outdir>/<prefix>_s<seq>_p<part>.h5``.

    dtype : 'float32' or 'float16'; average_channels : store the channel mean only;
    images_per_file : start a new file every so many images (None: one file per sequence);
    location : astropy EarthLocation for the WCS (default: the header's station).
    ``written`` lists the files; ``cube_stats`` counts images written and lost.
    """

    def __init__(self, iring, outdir, prefix="cube", dtype="float32", average_channels=False, images_per_file=None,
                 location=None, *args, **kwargs):
        super().__init__(iring, *args, **kwargs)
        if dtype not in ("float32", "float16"):
            raise ValueError(f"ImageCubeWriterBlock: dtype must be 'float32' or 'float16', got {dtype!r}")
        if images_per_file is not None and (int(images_per_file) != images_per_file or images_per_file < 1):
            raise ValueError(f"ImageCubeWriterBlock: images_per_file must be a positive integer or None, "
                             f"got {images_per_file!r}")
        self.outdir, self.prefix, self.dtype = str(outdir), prefix, dtype
        self.average_channels, self.images_per_file, self.location = average_channels, images_per_file, location
        self.written = []
        self.cube_stats = {"images": 0, "images_lost": 0, "files": 0}
        self._seq = -1
        self._w = None

    def on_sequence(self, iseq):
        self.hdr = iseq.header
        self.lay = image_layout(self.hdr, "ImageCubeWriterBlock")
        self.loc = self.location if self.location is not None else station_location(self.hdr)
        self._seq += 1
        self._part = 0
        self._j = 0                 # sequence index of the next image
        self._in_file = 0
        os.makedirs(self.outdir, exist_ok=True)
        self._open()

    def _open(self):
        lay = self.lay
        path = os.path.join(self.outdir, f"{self.prefix}_s{self._seq:02d}_p{self._part:03d}.h5")
        from ..io.cube import ImageCubeWriter
        imager = self.hdr.get("imager") or {}
        self._w = ImageCubeWriter(path, lay["freq_hz"], lay["products"], lm=lay["lm"],
                                  time_tag0=lay["time_tag"] + self._j * lay["integration_ticks"],
                                  integration_ticks=lay["integration_ticks"],
                                  pixel_index=lay["pixel_index"] if lay["grid"] is not None else None,
                                  grid=lay["grid"], location=self.loc, dtype=self.dtype,
                                  average_channels=self.average_channels,
                                  telescope=(self.hdr.get("station") or {}).get("name"),
                                  attrs={"sequence": str(self.hdr.get("name", "")), "first_image": self._j,
                                         "imager": str(imager.get("kind", "")), "method": str(imager.get("method", ""))})
        self.written.append(path)
        self.cube_stats["files"] += 1
        self._in_file = 0

    def _close(self):
        if self._w is not None:
            self._w.close()
            self._w = None

    def _lose(self, lost, why):
        """``lost`` images that will not be written: later images' time tags jump over them."""
        self._w.skip(lost)
        self._j += lost
        self.cube_stats["images_lost"] += lost
        log.warning("ImageCubeWriterBlock: %d images lost (%s, guarantee=False)", lost, why)

    def on_data(self, ispan):
        # images are placed by their index in the sequence, not by the order of calls (see _compat)
        gap = frames_lost_before(ispan, self._j)
        if gap:
            self._lose(gap, "reader overrun")
        data = span_array(ispan)
        n = data.shape[0]
        lay = self.lay
        x = data.reshape(n, lay["nchan"], lay["nprod"], -1)
        if self.average_channels and lay["nchan"] > 1:
            # the channel mean where the images live: a whole band's images (0.6 GB a gulp at 784
            # channels) never cross to the host, only their mean does
            x = x.mean(axis=1, keepdims=True, dtype=np.float32)
        x = to_numpy(x)
        if lay["grid"] is not None:   # take, not fancy indexing: ~6x faster on NumPy for this gather
            x = np.take(x, lay["pixel_index"], axis=-1)
        elif not getattr(self, "guarantee", True):
            x = np.array(x, copy=True)   # ring memory an overrun may reuse (real Bifrost reads in place)
        bad = frames_overwritten(ispan, n)   # after the copy just made
        if bad:
            self._lose(bad, "overwritten while read")
            x, n = x[bad:], n - bad
        pos = 0
        while pos < n:
            if self.images_per_file and self._in_file == self.images_per_file:
                self._close()
                self._part += 1
                self._open()
            take = n - pos if not self.images_per_file else min(n - pos, self.images_per_file - self._in_file)
            self._w.append(x[pos:pos + take])
            pos += take
            self._in_file += take
            self._j += take
        self.cube_stats["images"] += n

    def on_skip(self, islices, ospans):
        lost = frames_lost_at_end(islices, self._j)   # those before a later span: counted in on_data
        if lost:
            self._lose(lost, "reader overrun")

    def on_sequence_end(self, iseq):
        self._close()


def image_cube_writer(iring, outdir, *args, **kwargs):
    """Factory for :class:`ImageCubeWriterBlock`."""
    return ImageCubeWriterBlock(iring, outdir, *args, **kwargs)

"""PixelMergeBlock: the parts of a pixel split joined into whole images.

When several GPUs split a grid's pixels (``device: gpu:all``, ``imager.split: pixels``), each GPU
images every channel for its own part of the sky (:meth:`~bf_epic_blocks.imaging.pixels.LMGrid.part`)
and searches it; what a person keeps (band-averaged images, the cube) needs the whole sky again. Each
part's images reach the host small (:class:`~.integrate.ImageIntegratorBlock` with ``nimage=1``,
``space='system'``: the band mean of every image, or each channel), and this block writes, frame by
frame, every part's pixels into one grid.

Inputs: two or more grid image rings (docs/HEADERS.md, "Written by DFTImagerBlock") in host memory,
read in lock step: the same frame shape, products, channels, time axis and time tag, and disjoint
pixel sets (header ``pixels.index``). Anything else is named in a ValueError at the sequence's start.
Output: one host ring, the first input's header with ``pixels.index`` the union (dropped when that is
every pixel above the horizon), each frame NaN where no part imaged.
"""
from __future__ import annotations

import logging

import numpy as np

from ._compat import bfp, span_array
from .headers import derived_header, grid_pixels_header, image_layout

log = logging.getLogger(__name__)


class PixelMergeBlock(bfp.MultiTransformBlock):
    """Join the grid images of a pixel split's parts (see the module docstring).

    irings : the parts' image rings (host memory), each a grid of the same size with its own pixels.
    ``merge_stats`` counts the frames merged.
    """

    def __init__(self, irings, *args, **kwargs):
        irings = list(irings)
        if len(irings) < 2:
            raise ValueError(f"PixelMergeBlock: needs two or more parts' rings, got {len(irings)}")
        super().__init__(irings, *args, **kwargs)
        self.orings = [self.create_ring(space="system")]
        self.merge_stats = {"frames": 0, "parts": len(irings)}

    def define_valid_input_spaces(self):
        return [("system", "cuda_host")] * len(self.irings)

    def define_output_nframes(self, input_nframes):
        return [input_nframes[0]]

    def on_sequence(self, iseqs):
        lays = [image_layout(s.header, f"PixelMergeBlock input {k}") for k, s in enumerate(iseqs)]
        first = lays[0]
        if first["grid"] is None:
            raise ValueError("PixelMergeBlock: the parts must be grid images (labels time, freq, pol, m, l)")
        for k, lay in enumerate(lays[1:], 1):
            same = (lay["grid"] is not None and lay["frame_shape"] == first["frame_shape"]
                    and lay["products"] == first["products"] and np.array_equal(lay["freq_hz"], first["freq_hz"])
                    and lay["t0_s"] == first["t0_s"] and lay["dt_s"] == first["dt_s"]
                    and lay["time_tag"] == first["time_tag"] and lay["grid"].cell == first["grid"].cell)
            if not same:
                raise ValueError(f"PixelMergeBlock: part {k} does not describe the same images as part 0 (frame "
                                 f"shape {lay['frame_shape']} vs {first['frame_shape']}, products, channels, time "
                                 "axis, time tag and grid must agree)")
        index = np.concatenate([lay["pixel_index"] for lay in lays])
        if np.unique(index).size != index.size:
            raise ValueError("PixelMergeBlock: the parts' pixels overlap (header pixels.index); each pixel must "
                             "be imaged by one part")
        self._index = [lay["pixel_index"] for lay in lays]
        self._npix = first["grid"].size ** 2
        mask = np.zeros(self._npix, bool)
        mask[index] = True
        g = first["grid"]
        ohdr = derived_header(iseqs[0].header)
        ohdr["pixels"] = grid_pixels_header(g.size, g.cell, mask.reshape(g.size, g.size))
        log.info("PixelMergeBlock %s: %d parts, %d pixels", ohdr.get("name"), len(lays), int(mask.sum()))
        return [ohdr]

    def on_data(self, ispans, ospans):
        n = ispans[0].nframe
        if any(sp.nframe != n for sp in ispans):
            raise ValueError(f"PixelMergeBlock: the parts' spans differ in length ({[sp.nframe for sp in ispans]} "
                             "frames): the parts must be cut into the same gulps")
        out = span_array(ospans[0])
        flat = out.reshape(out.shape[:3] + (self._npix,))
        flat[...] = np.nan
        for sp, idx in zip(ispans, self._index):
            x = span_array(sp)
            flat[..., idx] = x.reshape(x.shape[:3] + (self._npix,))[..., idx]
        self.merge_stats["frames"] += n
        return [n]


def pixel_merge(irings, *args, **kwargs):
    """Factory for :class:`PixelMergeBlock`."""
    return PixelMergeBlock(irings, *args, **kwargs)

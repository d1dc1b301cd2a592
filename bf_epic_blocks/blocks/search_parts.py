"""SearchParts: the transient searches of a pixel split's parts, made one candidate table.

With ``device: gpu:all`` and ``imager.split: pixels`` each GPU images and searches its own part of
the sky (:meth:`~bf_epic_blocks.imaging.pixels.LMGrid.part`), so that the per-channel images never
leave the GPU that made them. Each part's :class:`~.transient_search.TransientSearchBlock` clusters
its crossings and folds the sidelobes it can see; what it cannot see is the other parts. A bright
burst in part 0 has beam sidelobes over the whole sky (at S/N 370, tens in places), and a burst at a
part's edge shows on both sides of it; neither may become a row of its own.

After the pipeline has run, :meth:`SearchParts.finish` takes every part's rows, brightest first, and
folds a row into a brighter one of another part (same sequence) when the brighter explains it by the
rules the block applies within a part (its ``sidelobe_factor``):

* beam sidelobe: both point candidates within a boxcar and the time link of each other, the fainter's
  S/N at most ``sidelobe_factor`` times what the brighter puts at its pixel through the array's beam
  (the beam from the brighter's pixel centre, scaled by the two pixels' window sigmas: the rule the
  block uses once a row's images are no longer held);
* DM sidelobe: within the grid link of the brighter's pixel and a sweep of it in time, at another
  DM, its S/N at most ``sidelobe_factor`` times
  :func:`~bf_epic_blocks.search.dm_sidelobe_snr`;
* a sky-wide event seen by several parts is one row, the brightest (its ``sky_fraction`` that of the
  part with the largest).

Then it writes the one table and PNG the single-GPU block would write (pixel numbers over the whole
sky). ``search_stats`` adds the parts' trial and crossing counts; counts of the stream (images,
resets, images lost, sequences) are the largest any part saw (they see the same images); candidates
and sky-wide events are those of the merged table.
"""
from __future__ import annotations

import logging

import numpy as np

from ..search import dm_sidelobe_snr

log = logging.getLogger(__name__)

#: counts of the image stream: every part sees the same images, so the merged count is their largest
_STREAM_COUNTS = ("images", "images_searched", "resets", "images_lost", "sequences")


class SearchParts:
    """The searches of a pixel split as one (see the module docstring).

    blocks : the parts' TransientSearchBlocks (run with ``outdir=None``), in part order.
    outdir, prefix, table_format, png : where the merged table and PNG go
    (:class:`~bf_epic_blocks.io.candidates.CandidateWriter`'s; outdir None: none written). After
    :meth:`finish`: ``candidates`` (astropy Table), ``search_stats``, ``written``.
    """

    def __init__(self, blocks, outdir=None, prefix="transients", table_format="ecsv", png=True):
        if len(blocks) < 2:
            raise ValueError(f"SearchParts: a pixel split has two or more parts, got {len(blocks)}")
        self.blocks = list(blocks)
        for b in self.blocks:
            b.fit_every_row = True
        from ..io.candidates import CandidateWriter
        self.writer = None if outdir is None else CandidateWriter(outdir, prefix, table_format, png)
        self.candidates, self.written = None, []
        self.search_stats = self._stats(folded=0, ncand=0)

    @property
    def name(self):
        return "SearchParts(" + ", ".join(b.name for b in self.blocks) + ")"

    def _stats(self, folded, ncand, nsky=None):
        out = {}
        for key in self.blocks[0].search_stats:
            vals = [b.search_stats[key] for b in self.blocks]
            if key == "trials_per_width":
                out[key] = [int(sum(v)) for v in zip(*vals)]
            elif key in _STREAM_COUNTS:
                out[key] = max(vals)
            else:
                out[key] = sum(vals)
        out["sidelobes_folded"] += folded
        out["candidates"] = ncand
        if nsky is not None:            # a sky-wide event both halves saw is one row, counted once
            out["sky_wide"] = nsky
        out["parts"] = len(self.blocks)
        return out

    def finish(self):
        """Merge the parts' rows (folding what another part's brighter row explains), write the files;
        returns the candidate table."""
        from ..io import candidates as cio
        from ..imaging.pixels import LMGrid
        b0 = self.blocks[0]
        seen = [getattr(b, "lay", None) is not None for b in self.blocks]
        if not any(seen):
            return None                       # no sequence reached the searches: nothing to write, as one search
        if not all(seen):
            raise RuntimeError("SearchParts.finish: some parts' searches saw a sequence and some did not: the "
                               "parts must be fed the same source")
        lays = [b.lay for b in self.blocks]
        index = np.concatenate([lay["pixel_index"] for lay in lays])
        order = np.argsort(index, kind="stable")
        union = index[order]
        lm = np.concatenate([lay["lm"] for lay in lays])[order]
        rows = []
        for k, b in enumerate(self.blocks):
            for r in b.rows:
                r = dict(r, _part=k)
                r["pixel"] = int(np.searchsorted(union, b.lay["pixel_index"][r["pixel"]]))
                rows.append(r)
        rows.sort(key=lambda r: -r["snr"])
        kept, folded = self._fold(rows, lm)
        meta = b0.meta()
        meta["trials_per_width"] = self._stats(0, 0)["trials_per_width"]
        meta["pixel_split_parts"] = len(self.blocks)
        self.candidates = cio.candidate_table(kept, meta, lc_length=b0.lc_before + b0.lc_after + 1)
        self.search_stats = self._stats(folded, len(kept), sum(r["kind"] == "sky-wide" for r in kept))
        if folded:
            log.info("pixel split: %d candidate(s) of one part folded into another part's brighter one", folded)
        if self.writer is not None:
            g = lays[0]["grid"]
            mask = np.zeros(g.size * g.size, bool)
            mask[union] = True
            whole = LMGrid(size=g.size, cell=g.cell, lm=lm, mask=mask.reshape(g.size, g.size))
            sky = np.concatenate([np.asarray(b._sky, np.float64) for b in self.blocks])[order]
            self.written = self.writer.write(self.candidates, sky, grid=whole, lm=lm)
        return self.candidates

    def _fold(self, rows, lm):
        """(kept rows, number folded): ``rows`` brightest first; each folded into the first kept row of
        another part that explains it."""
        b0 = self.blocks[0]
        factor = b0.sidelobe_factor
        kept, folded = [], 0
        if not rows:
            return kept, folded
        s = b0.search
        tlink, wmax, shift = b0._tlink, s.wmax, s.shift
        beam = at = None
        if factor:
            lm_rows = np.array([[r["l"], r["m"]] for r in rows])
            beam = b0.beam_on(lm_rows)
            at = beam.at(lm_rows) if beam is not None else None       # (from row, at row)
        pos = {id(r): i for i, r in enumerate(rows)}
        xy = np.column_stack([np.asarray([r["grid_x"] for r in rows], float),
                              np.asarray([r["grid_y"] for r in rows], float)])
        for r in rows:
            host = None
            for p in kept if factor else ():
                if p["_part"] == r["_part"] or p["sequence"] != r["sequence"] or p["snr"] < r["snr"]:
                    continue
                dt = abs(p["image"] - r["image"])
                if r["kind"] == "sky-wide" or p["kind"] == "sky-wide":
                    if r["kind"] == p["kind"] and dt <= shift + wmax + tlink:
                        host = p
                        break
                    continue
                ip, iq = pos[id(p)], pos[id(r)]
                if beam is not None and dt <= tlink + wmax and r["_sigma"] > 0:
                    if p.get("_fit") is not None:
                        # its fitted point source (position, flux) through the beam, in r's pixel's noise
                        lf, mf, amp = p["_fit"]
                        expect = amp * float(beam.at(np.array([[lf, mf]]))[0, iq]) / r["_sigma"]
                    else:
                        # the beam from its pixel centre, scaled by the two pixels' window sigmas
                        expect = p["snr"] * at[ip, iq] / at[ip, ip] * p["_sigma"] / r["_sigma"] \
                            if at[ip, ip] > 0 else 0.0
                    if r["snr"] <= factor * expect:
                        host = p
                        break
                if s.average and len(s.dms) > 1 and p["dm_trial"] != r["dm_trial"] and dt <= shift + tlink + wmax \
                        and np.hypot(*(xy[ip] - xy[iq])) <= b0._space:
                    expect = dm_sidelobe_snr(b0.lay["freq_hz"], b0.lay["dt_s"],
                                             (p["image"], p["dm_trial"], p["width"], p["snr"]),
                                             (r["image"], r["dm_trial"], r["width"]))
                    if r["snr"] <= factor * expect:
                        host = p
                        break
            if host is None:
                kept.append(r)
                continue
            folded += 1
            host["nmembers"] += r["nmembers"]
            if r["kind"] == "sky-wide":
                host["sky_fraction"] = max(host["sky_fraction"], r["sky_fraction"])
            else:
                host["nsidelobes"] += 1
            log.debug("part %d's candidate at image %d, pixel %d, S/N %.1f folded into part %d's S/N %.1f one",
                      r["_part"], r["image"], r["pixel"], r["snr"], host["_part"], host["snr"])
        return kept, folded

"""The stall watchdog of `bf-epic run`: a block stuck in host work is named, with where it is."""
import logging
import time

import numpy as np
import pytest

from bf_epic_blocks.blocks import ArraySinkBlock, ArraySourceBlock, bfp, efield_header
from bf_epic_blocks.blocks import _compat
from bf_epic_blocks.pipeline import runner
from bf_epic_blocks.pipeline.watchdog import StallWatchdog

pytestmark = pytest.mark.skipif(_compat.RUNTIME == "bifrost",
                                reason="real Bifrost's blocks keep a perf proclog, not the stats the watchdog reads")


class _StuckSink(ArraySinkBlock):
    def on_data(self, ispan):
        super().on_data(ispan)
        if len(self._chunks[-1]) == 2:
            _busy_in_host_work(1.2)


def _busy_in_host_work(seconds):
    t = time.perf_counter()
    while time.perf_counter() - t < seconds:
        pass


def _pipeline(sink_cls):
    x = np.zeros((40, 2, 3, 2), np.complex64)
    hdr = efield_header("w", 0, [60e6, 60.025e6], 4e-5, {"xyz_m": np.zeros((3, 3))}, dtype="cf32")
    p = bfp.Pipeline()
    with p:
        src = ArraySourceBlock(x, hdr, gulp_nframe=10)
        sink = sink_cls(src)
    return p, sink


def test_a_stalled_block_is_named_with_where_it_is(caplog):
    p, sink = _pipeline(_StuckSink)
    with caplog.at_level(logging.WARNING, logger="bf_epic_blocks"):
        with StallWatchdog(p.blocks, stall_s=0.4, poll_s=0.05) as wd:
            p.run()
    assert wd.warnings >= 1
    text = "\n".join(r.getMessage() for r in caplog.records)
    assert "no block has finished a gulp" in text
    line = [ln for ln in text.splitlines() if sink.name in ln][0]
    assert "_busy_in_host_work" in line and "1 gulp done" in line
    assert sink.result(0).shape[0] == 40                 # the watchdog only watches


def test_a_moving_pipeline_is_not_warned_about_and_the_runner_watches(caplog):
    p, _ = _pipeline(ArraySinkBlock)
    with caplog.at_level(logging.WARNING, logger="bf_epic_blocks"):
        with StallWatchdog(p.blocks, stall_s=0.4, poll_s=0.05) as wd:
            p.run()
    assert wd.warnings == 0 and not any("no block has finished" in r.getMessage() for r in caplog.records)
    assert runner.STALL_WARN_S > 0
    assert StallWatchdog([], 1.0).blocks == []           # blocks without runtime stats: not watched

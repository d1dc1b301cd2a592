"""Our blocks inside real Bifrost on a GPU, between Bifrost's own blocks (tools/bifrost_mixed.py).

Bifrost copies ci4 / cf32 voltages to its 'cuda' ring (and transposes station-major cf32 on the
GPU), CalFoldBlock and DFTImagerBlock run on that ring, Bifrost copies the images back. The images
must equal our runtime's for the same data (run in a subprocess with BF_EPIC_RUNTIME=builtin) to
1e-6 of the peak, NaN below the horizon in the same places, and a float64 sum by the definition
to 1e-5. The block tests themselves (tests/test_blocks.py, `-m gpu`) run on Bifrost's 'cuda'
rings wherever Bifrost is the runtime.
"""
import pytest

from bf_epic_blocks.blocks import _compat
from bf_epic_blocks.imaging._xp import gpu_available

pytestmark = [pytest.mark.bifrost, pytest.mark.gpu,
              pytest.mark.skipif(not (_compat.HAVE_BIFROST and gpu_available()),
                                 reason="needs real Bifrost built with CUDA (tools/build_bifrost_gpu.sh) and a GPU")]


def test_mixed_bifrost_pipeline_on_the_gpu_equals_our_runtime(tmp_path):
    import json
    import bifrost_mixed
    out = tmp_path / "mixed.json"
    rc = bifrost_mixed.main(["--compare", "--nstand", "64", "--nchan", "4", "--ntime", "2048", "--gulp", "256",
                             "--accumulate", "512", "--grid", "24", "--json", str(out)])
    rows = json.loads(out.read_text())["rows"]
    assert [r["dtype"] for r in rows] == ["ci4", "cf32"]
    for r in rows:
        assert r["images"] == 4
        assert r["nan_masks_equal"] and r["rel_diff_vs_ours"] <= 1e-6 and r["err_vs_float64"] <= 1e-5, r
    assert rc == 0

"""What a block's thread would import for the first time is imported while the pipeline is built.

Two block threads importing SciPy's subpackages for the first time at once can deadlock: Python's import
raises ``_DeadlockError`` in one thread and hands the other a partly made module. This happened on a
16-core machine, running the whole station on the CPU: the gain solver's worker imported
``scipy.linalg.blas`` while an image writer's thread imported a module that imports it too, and the run
failed. The blocks whose threads use SciPy import it in their constructors, on the thread that builds
the pipeline. Each test runs in a fresh interpreter, the only place where "imported yet?" means anything.
"""
import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent

CASES = {
    "solver": ("pipelines/lwasv_sim_calibrate.yaml", ["scipy.linalg", "scipy.linalg.blas", "scipy.special"]),
    "search": ("pipelines/lwasv_sim_transient.yaml", ["scipy.sparse.csgraph", "scipy.spatial", "scipy.stats"]),
}


def _modules_after_build(yaml, outdir):
    code = textwrap.dedent(f"""
        import json, sys
        from bf_epic_blocks.pipeline.config import load_config
        from bf_epic_blocks.pipeline.runner import build_graph
        before = set(sys.modules)
        cfg = load_config({yaml!r}, ["device=cpu", "source.duration_s=1.0", "source.channels.count=2",
                                     "output.dir={outdir}"])
        build_graph(cfg)
        print(json.dumps({{"before": sorted(m for m in before if m.startswith("scipy")),
                          "after": sorted(m for m in sys.modules if m.startswith("scipy"))}}))
    """)
    r = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("case", sorted(CASES))
def test_the_scipy_a_block_thread_uses_is_imported_when_the_pipeline_is_built(case, tmp_path):
    yaml, wanted = CASES[case]
    got = _modules_after_build(yaml, tmp_path)
    missing = [m for m in wanted if m not in got["after"]]
    assert not missing, f"{yaml}: not imported while building: {missing}"
    # the check means something only if building is what imported them
    assert not set(wanted) & set(got["before"])

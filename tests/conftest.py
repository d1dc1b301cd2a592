"""Shared fixtures. The tests' helper modules (truth.py, lwa_data.py) and the scripts under tools/
are importable by name through setup.cfg's pytest ``pythonpath``."""
import pytest

from bf_epic_blocks.imaging._xp import cupy_or_none, gpu_available

HAVE_GPU = gpu_available()


def _xp_params():
    import numpy
    params = [pytest.param(numpy, id="numpy")]
    params.append(pytest.param(cupy_or_none(), id="cupy",
                               marks=[pytest.mark.gpu,
                                      pytest.mark.skipif(not HAVE_GPU, reason="needs CuPy and a CUDA device")]))
    return params


@pytest.fixture(params=_xp_params())
def xp(request):
    """The array namespace under test: numpy always, cupy on a GPU machine."""
    return request.param

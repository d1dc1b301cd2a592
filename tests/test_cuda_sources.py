"""Every ``.cu`` file of the package is registered with the loader and compiles with NVRTC.

The CPU part checks the bookkeeping (each shipped ``.cu`` file has its configurations listed, each
listed file exists, the loader pastes the package's own includes); the GPU part compiles every listed
configuration with NVRTC through the loader, Hopper-only ones where the device is a Hopper GPU.
"""
import importlib
import pkgutil

import pytest

import bf_epic_blocks
from bf_epic_blocks import cuda


def _import_every_module():
    """Import the package's modules so each launcher registers its .cu configurations."""
    for info in pkgutil.walk_packages(bf_epic_blocks.__path__, "bf_epic_blocks."):
        if ".pipeline" in info.name or ".blocks" in info.name:
            continue                     # the launchers live below the blocks
        importlib.import_module(info.name)


def _configs():
    _import_every_module()
    return [(path, defines, arch, options) for path, cfgs in sorted(cuda.COMPILE_CHECKS.items())
            for defines, arch, options in cfgs]


def test_every_cu_file_is_registered():
    _import_every_module()
    files = cuda.cu_files()
    assert files, "no .cu files found in the package"
    missing = [f for f in files if not cuda.COMPILE_CHECKS.get(f)]
    assert not missing, f".cu files no launcher registers (the compile test would miss them): {missing}"
    stale = [p for p in cuda.COMPILE_CHECKS if p not in files]
    assert not stale, f"registered .cu files that do not exist: {stale}"


def test_loader_pastes_package_includes(tmp_path, monkeypatch):
    (tmp_path / "a.cuh").write_text("#define FROM_HEADER 1\n")
    (tmp_path / "k.cu").write_text('#include <cuda_fp16.h>\n#include "a.cuh"\n#include "a.cuh"\nkernel\n')
    monkeypatch.setattr(cuda, "PACKAGE_DIR", tmp_path)
    src = cuda.source("k.cu")
    assert src.count("#define FROM_HEADER 1") == 1 and "#include <cuda_fp16.h>" in src and '"a.cuh"' not in src
    with pytest.raises(FileNotFoundError, match="missing.cu"):
        cuda.source("missing.cu")


@pytest.mark.gpu
@pytest.mark.parametrize("path, defines, arch, options", _configs())
def test_cu_file_compiles_with_nvrtc(path, defines, arch, options):
    cp = pytest.importorskip("cupy")
    try:
        if cp.cuda.runtime.getDeviceCount() < 1:
            pytest.skip("no CUDA device")
    except Exception:
        pytest.skip("no CUDA device")
    if arch == "sm_90a" and int(cp.cuda.Device().compute_capability) != 90:
        pytest.skip("Hopper-only (sm_90a) kernel on a device that is not Hopper")
    mod = cuda.get_module(path, defines=defines, options=options, arch=arch)
    mod.compile()

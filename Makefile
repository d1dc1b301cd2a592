# Two commands do all set-up on a fresh machine (Debian/Ubuntu, Python >= 3.10):
#   make demo   -- install system packages and a virtualenv, run the default pipeline end to end
#   make test   -- the same set-up, then the whole test suite (what CI runs)
#   make test-quick -- the suite without the tests marked slow or real_data (a developer's quick run)
# On a machine with an NVIDIA GPU:
#   make gpu-check  -- CuPy too, then the GPU tests, every shipped pipeline by bf-epic run on the GPU
#                      and the CPU with their outputs compared, and the planner's GPU picks (a table)
#   make kernels    -- CuPy too, then every shipped GPU pipeline's kernels compiled once into the kernel
#                      store (a few minutes), so that every later run starts within seconds
#   make docs       -- the documentation site into output/site (mkdocs, warnings are errors)
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin

.PHONY: setup test test-quick demo bench gpu-check kernels docs clean
# CuPy for the GPU check: gpu (CUDA 12 wheels), gpu-cuda12 or gpu-cuda13 (the machine's own toolkit)
GPU_EXTRA ?= gpu

setup: $(VENV)/.installed

$(VENV)/.installed: setup.cfg pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	PYTHON=$(BIN)/python bash tools/install_system_deps.sh
	$(BIN)/python -m pip install -q -e '.[test]'
	touch $@

test: setup
	PYTHON=$(BIN)/python bash tools/install_system_deps.sh --browser
	$(BIN)/python -m pytest -q -ra --durations=15

test-quick: setup
	$(BIN)/python -m pytest -q -ra -m "not slow and not real_data"

demo: setup
	$(BIN)/bf-epic run pipelines/lwasv_sim_allsky.yaml

# The site's tools come from the docs extra; the mkdocs 2 notices printed by its plugins are not the build's.
docs: setup
	$(BIN)/python -m pip install -q -e '.[docs]'
	NO_MKDOCS_2_WARNING=1 DISABLE_MKDOCS_2_WARNING=true $(BIN)/mkdocs build --strict -d output/site

gpu-check: setup
	$(BIN)/python -m pip install -q -e '.[$(GPU_EXTRA)]'
	$(BIN)/python tools/gpu_check.py --json output/gpu_check.json

# the simulated pipelines whose shapes the shipped GPU pipelines share (the live and capture ones included)
KERNEL_PIPELINES ?= pipelines/lwasv_sim_station.yaml pipelines/lwasv_sim_wholeband.yaml \
	pipelines/lwasv_sim_transient.yaml pipelines/lwasv_sim_allsky.yaml pipelines/lwasv_sim_calibrate.yaml

kernels: setup
	$(BIN)/python -m pip install -q -e '.[$(GPU_EXTRA)]'
	$(BIN)/bf-epic compile $(KERNEL_PIPELINES)

# one benchmark on the CPU; tools/bench/README.md lists them all
bench: setup
	$(BIN)/python tools/bench/bench_dft.py --device cpu --json output/bench_dft_cpu.json

clean:
	rm -rf $(VENV) output

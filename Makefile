# Two commands do all set-up on a fresh machine (Debian/Ubuntu, Python >= 3.10):
#   make demo   -- install system packages and a virtualenv, run the default pipeline end to end
#   make test   -- the same set-up, then the test suite (what CI runs)
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin

.PHONY: setup test demo bench clean

setup: $(VENV)/.installed

$(VENV)/.installed: setup.cfg pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	PYTHON=$(BIN)/python bash tools/install_system_deps.sh
	$(BIN)/python -m pip install -q -e '.[test]'
	touch $@

test: setup
	$(BIN)/python -m pytest -q -ra

demo: setup
	$(BIN)/bf-epic run pipelines/lwasv_sim_allsky.yaml

bench: setup
	$(BIN)/python tools/bench_dft.py --device cpu --json bench_dft_cpu.json

clean:
	rm -rf $(VENV) output

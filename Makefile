# liver_p2p_reg developer commands. Each target sets up .venv on first use.
# CPU torch is installed first, from its pin, so no CUDA wheels are ever pulled.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp
TORCH_PIN := torch==2.13.0
export OMP_NUM_THREADS ?= 2

.PHONY: help setup demo test lint format bench clean

help: ## list the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  make %-8s %s\n", $$1, $$2}'

$(STAMP): setup.py package.xml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet $(TORCH_PIN)
	$(PY) -m pip install --quiet -e '.[cpu,dev,ros,slicer]'
	touch $(STAMP)

setup: $(STAMP) ## create .venv and install the package (CPU torch, headless Open3D, rclpy wheels)

demo: $(STAMP) ## run the main job: every bundled bag through the live ROS 2 graph, per-bag table
	$(PY) -m liver_p2p_reg demo

test: $(STAMP) ## lint, format check and the whole test suite
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(PY) -m pytest -q test

lint: $(STAMP) ## ruff lint only
	$(VENV)/bin/ruff check .

bench: $(STAMP) ## smoke benchmark: 24 cases of insilico-test-v1 (builds 3 of its 12 livers on first use) -> out/bench
	$(PY) -m liver_p2p_reg benchmark --dataset insilico-test-v1 --preset smoke --methods procrustes,fpfh-ransac-icp,learned-p2p-icp --out out/bench

format: $(STAMP) ## reformat the code with ruff
	$(VENV)/bin/ruff format .

clean: ## remove build outputs (keeps .venv)
	rm -rf build install log *.egg-info .pytest_cache .ruff_cache

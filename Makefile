# RenderWorld: two commands from a fresh clone.
#   make test   set up .venv (torch pinned first) and run the default test suite
#   make demo   set up .venv and run the most complete job the package can do
#   make dev    simulate the development fixture (mini preset, seed 1001) into data/sim_dev
#               and convert it (infos under data/sim_dev/renderworld_infos/v1.0-mini)
#   make dev-interactions  the interaction behaviours' development fixture (32 scenes, seed
#               1002, occupancy only) into data/sim_dev_inter (v1.0-interactions)
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
TORCH_SPEC ?= torch==2.13.0
PY := $(VENV)/bin/python
# Test worker processes (pytest-xdist); a test file's tests share one worker and its fixtures.
TEST_WORKERS ?= 2
PYTEST := $(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile
STAMP := $(VENV)/.renderworld-installed

.PHONY: setup test test-all lint demo dev dev-interactions bench clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	@set -e; \
	if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo "[setup] installing Debian libusb-1.0-0 (needed by open3d)"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null; \
	  else \
	    echo "[setup] WARNING: libusb-1.0-0 is missing and cannot be installed here (not root or no apt-get)."; \
	    echo "[setup]          open3d (simulator only) will fail to import; install it with: sudo apt-get install libusb-1.0-0"; \
	  fi; \
	fi
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q "$(TORCH_SPEC)"
	$(PY) -m pip install -q -e '.[test]'
	@touch $(STAMP)

test: $(STAMP)
	$(PYTEST)

test-all: $(STAMP)
	$(PYTEST) -m ''

lint: $(STAMP)
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .

demo: $(STAMP)
	$(PY) tools/run_pipeline.py

dev: $(STAMP)
	$(PY) tools/make_fixtures.py preset=mini seed=1001 out=data/sim_dev overwrite=true
	$(PY) tools/create_data.py data_root=data/sim_dev version=v1.0-mini

dev-interactions: $(STAMP)
	$(PY) tools/make_fixtures.py preset=interactions seed=1002 num_scenes=32 mode=occupancy \
	  out=data/sim_dev_inter overwrite=true
	$(PY) tools/create_data.py data_root=data/sim_dev_inter version=v1.0-interactions labels=false

# The accuracy-vs-time sweep after `make demo` (PRESET=quick|standard|full).
PRESET ?= quick
bench: $(STAMP)
	$(PY) tools/bench.py bench=$(PRESET)

clean:
	rm -rf $(VENV) .cache .pytest_cache

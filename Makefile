# The two commands: `make demo` and `make test`. Both create .venv first when it is missing or stale.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
DEMO_SCENE := bags/demo_scene
DEMO_BAG := bags/demo_scene_bag
BAG ?= $(DEMO_BAG)
CONFIG ?= synthetic

.PHONY: venv test demo build clean-build bench

venv: $(STAMP)

# Re-run only when the pinned requirements, the core's packaging, its C++ kernels or the interface
# packages change (fast no-op otherwise): installing builds the kernels and the interfaces the wheels lack.
$(STAMP): requirements.txt src/neb_slam_core/setup.cfg src/neb_slam_core/setup.py \
		$(wildcard src/neb_slam_core/neb_slam_core/scene/csrc/*) src/neb_slam_core/neb_slam_core/scene/_ext.py \
		$(wildcard interfaces/*/*.* interfaces/*/msg/*) tools/build_interfaces.py
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade "pip>=24"
	$(PY) -m pip install --quiet -r requirements.txt
	$(PY) -m pip install --quiet --no-build-isolation --no-deps -e src/neb_slam_core
	$(PY) tools/build_interfaces.py
	@touch $(STAMP)

test: venv
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(PY) -m pytest -q tests

build: venv
	source $(VENV)/bin/activate && colcon build --base-paths src

clean-build:
	rm -rf build install log

demo: venv
	@$(PY) tools/demo.py --scene $(DEMO_SCENE) --bag $(BAG) --config $(CONFIG)

bench: venv
	$(PY) benchmarks/encoding.py

# IBVS window-and-landing stack: the two commands of the README, plus helpers.
#   make run   - fly the reference scenario, write results/<run>/summary.json
#   make test  - lint + the whole test suite (unit, node, integration)
# Both create .venv on first use from requirements*.txt and install the workspace into it.
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
PKGS := ibvs_common ibvs_control ibvs_perception ibvs_sim ibvs_bringup ibvs_harness
PKG_DIRS := $(addprefix ros2_ws/src/,$(PKGS))
# A sourced ROS 2 Jazzy (/opt/ros/jazzy) provides rclpy and the messages: use it, skip the wheels.
ifeq ($(ROS_DISTRO),jazzy)
VENV_FLAGS := --system-site-packages
ROS_REQS :=
else
VENV_FLAGS :=
ROS_REQS := -r requirements-ros.txt
endif
# Installed package data (config, launch, ament index markers) that needs a reinstall on change.
PKG_DATA := $(shell find $(PKG_DIRS) -name setup.py -o -name setup.cfg -o -name package.xml \
	-o -name '*.yaml' -o -name '*.launch.py' -o -path '*/resource/*' 2>/dev/null)
export AMENT_PREFIX_PATH := $(CURDIR)/$(VENV):$(AMENT_PREFIX_PATH)
export PYTHONDONTWRITEBYTECODE := 1
RUN_ARGS ?=
# Second environment: Ubuntu 24.04's OpenCV 4.6 and numpy 1.26 (requirements-cv46.txt).
VENV46 ?= .venv-cv46
PY46 := $(VENV46)/bin/python
# make test: pytest workers (pytest-xdist). The whole-graph runs and the SITL flights are two
# groups (xdist_group marks) that run beside each other, each on one worker.
PYTEST_WORKERS ?= 2

.PHONY: run test lint unit unit-cv46 integration bench venv install clean

$(VENV)/.deps: requirements.txt requirements-ros.txt
	$(PYTHON) -m venv $(VENV_FLAGS) $(VENV)
	$(PY) -m pip install --quiet --upgrade pip setuptools wheel
	$(PY) -m pip install --quiet -r requirements.txt $(ROS_REQS)
	touch $@

# Like `colcon build --symlink-install`: editable Python, then the layout the ros2 CLI reads
# (scripts/ament_layout.py: ament index markers, share/<pkg> files as per-file symlinks,
# lib/<pkg>/<executable>) under the venv prefix, which is on AMENT_PREFIX_PATH.
$(VENV)/.workspace: $(VENV)/.deps $(PKG_DATA) Makefile scripts/ament_layout.py
	$(PY) -m pip install --quiet --no-deps --no-build-isolation $(addprefix -e ,$(PKG_DIRS))
	$(PY) scripts/ament_layout.py --prefix $(VENV) $(PKG_DIRS)
	touch $@

venv: $(VENV)/.deps
install: $(VENV)/.workspace

# The same packages (editable) on OpenCV 4.6 / numpy 1.26, every other pin from requirements.txt.
$(VENV46)/.deps: requirements.txt requirements-ros.txt requirements-cv46.txt
	$(PYTHON) -m venv $(VENV_FLAGS) $(VENV46)
	$(PY46) -m pip install --quiet --upgrade pip setuptools wheel
	grep -v -E '^(numpy|opencv-python-headless)==' requirements.txt > $(VENV46)/requirements-shared.txt
	$(PY46) -m pip install --quiet -r $(VENV46)/requirements-shared.txt -r requirements-cv46.txt \
		$(ROS_REQS)
	touch $@

$(VENV46)/.workspace: $(VENV46)/.deps $(PKG_DATA) Makefile scripts/ament_layout.py
	$(PY46) -m pip install --quiet --no-deps --no-build-isolation $(addprefix -e ,$(PKG_DIRS))
	$(PY46) scripts/ament_layout.py --prefix $(VENV46) $(PKG_DIRS)
	touch $@

run: install
	$(PY) -m ibvs_harness.run_scenario $(RUN_ARGS)

lint: install
	$(PY) -m flake8 --max-line-length 99 ros2_ws/src tests scripts benchmarks
	$(PY) -m pydocstyle --convention=pep257 --add-ignore=D100,D101,D102,D103,D104,D105,D107 \
		ros2_ws/src tests scripts benchmarks

# Each package's own tests (unit and node tests with real rclpy; what `colcon test` runs on a
# Jazzy install) and the repository-wide ones (layering, docker, docs, scripts, benchmarks).
PKG_TESTS := $(addsuffix /test,$(PKG_DIRS)) tests/repo
unit: install
	$(PY) -m pytest -q -n $(PYTEST_WORKERS) -m 'not slow' $(PKG_TESTS)

# The package tests on OpenCV 4.6 / numpy 1.26, with .venv-cv46 as the only install prefix. Not
# the `slow` ones (e.g. the fifty random starts of the feature-level loop, a statistic of
# the control law that the main run checks; 2 minutes of CI on a slow machine): the feature
# loop itself runs here in its other tests.
unit-cv46: $(VENV46)/.workspace
	$(PY46) -c 'import cv2, numpy; print("OpenCV", cv2.__version__, "numpy", numpy.__version__)'
	AMENT_PREFIX_PATH=$(CURDIR)/$(VENV46) $(PY46) -m pytest -q -n $(PYTEST_WORKERS) \
		-m 'not slow' $(PKG_TESTS)

integration: install
	$(PY) -m pytest -q tests/integration

# The two venvs' dependencies first, side by side: pip mostly waits on downloads and unpacking
# (from scratch 65 s together against 52 + 58 s one after the other, 2026-11-26). The editable
# installs of the workspace stay one at a time: they write into the source tree.
test:
	$(MAKE) -j2 $(VENV)/.deps $(VENV46)/.deps
	$(MAKE) lint
	$(PY) -m pytest -q -n $(PYTEST_WORKERS) --dist loadgroup --durations=20 tests/integration \
		$(PKG_TESTS)
	$(MAKE) unit-cv46

bench: install
	for b in benchmarks/bench_*.py; do $(PY) $$b || exit 1; done

# Monte Carlo campaign under wind at feature level (issue 14; docs/performance.md "Campaign"):
# results/campaign/<name>/ (resumable), e.g. make mc MC_ARGS='--name feature --runs 500'.
MC_ARGS ?=
.PHONY: mc
mc: install
	$(PY) -m ibvs_harness.campaign $(MC_ARGS)

clean:
	rm -rf $(VENV) $(VENV46) build install log

# One-command workflow. Every target runs `setup`, which is idempotent and near-instant when
# nothing changed (a stamp file tracks requirements.txt and every package's build files).
SHELL := /bin/bash
PYTHON ?= python3
VIZ ?= 0
VENV := $(CURDIR)/.venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.setup-stamp
PKGS := $(wildcard ros2_ws/src/*/package.xml)
PKG_DIRS := $(patsubst %/package.xml,%,$(PKGS))
PKG_BUILD_FILES := $(PKGS) $(wildcard ros2_ws/src/*/setup.py ros2_ws/src/*/setup.cfg ros2_ws/src/*/config/* ros2_ws/src/*/launch/*)

# ament_index_python finds packages through AMENT_PREFIX_PATH; the venv is our install prefix.
export AMENT_PREFIX_PATH := $(VENV)$(if $(AMENT_PREFIX_PATH),:$(AMENT_PREFIX_PATH),)
export PATH := $(VENV)/bin:$(PATH)
export PYTHONDONTWRITEBYTECODE := 1

.PHONY: setup test demo docs bench experiment experiment-paper experiment-quick experiment-ablation paper-tuning clean

setup: $(STAMP)

$(STAMP): requirements.txt $(PKG_BUILD_FILES) scripts/setup.sh scripts/install_data_files.py
	@bash scripts/setup.sh "$(PYTHON)" "$(VENV)" $(PKG_DIRS)
	@touch $(STAMP)

test: setup
	$(PY) -m pytest

demo: setup   # `make demo VIZ=1`: with the live 3D view in the browser
	@VIZ=$(VIZ) bash scripts/demo.sh

# The documentation site, strict: a broken link or anchor, a page outside the nav or an unresolved
# API reference fails the build. `make docs SITE=/tmp/site` builds elsewhere.
SITE ?= site
docs: setup
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict --site-dir $(SITE)

bench: setup
	$(PY) -m tools.bench

# The comparison on a local Ray runtime (EXPERIMENT_ARGS='--address HEAD:6379 --jobs 16' for a cluster: README).
experiment: setup
	$(PY) -m calibration_bringup.experiment --system ours $(EXPERIMENT_ARGS)

experiment-paper: setup
	$(PY) -m calibration_bringup.experiment --system paper $(EXPERIMENT_ARGS)

experiment-quick: setup
	$(PY) -m calibration_bringup.experiment --system ours --quick $(EXPERIMENT_ARGS)

# From the paper's system to ours one change at a time (R and AL, 50 x 50 per row); rows 0 and
# last share their runs with experiment-paper and experiment.
experiment-ablation: setup
	$(PY) -m calibration_bringup.ablation $(EXPERIMENT_ARGS)

# The paper system's silent constants, chosen on tuning seeds (seed base 1000) no report uses.
paper-tuning: setup
	$(PY) -m calibration_bringup.paper_tuning $(EXPERIMENT_ARGS)

clean:
	rm -rf $(VENV) build install log .pytest_cache site

# linear_slam_ros: set-up, main job, tests, benchmark. Every target sets up what it needs and is
# idempotent: a second run only redoes what changed.
SHELL := /bin/bash
.SHELLFLAGS := -eu -o pipefail -c
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
DATASETS ?= ../shared/datasets
# DDS stays on this machine, in its own domain.
export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST
export ROS_DOMAIN_ID ?= 61
export LINEAR_SLAM_CACHE := $(CURDIR)/.cache/datasets
SOURCES := $(shell find linear_slam_ros msg_adapters config resource -type f \( -name '*.py' -o -name '*.yaml' -o -name 'linear_slam_ros' \)) setup.py setup.cfg package.xml
ACTIVATE := set +u && source install/setup.bash && set -u

.PHONY: run test test-slow benchmark setup bags clean

## Command one: set up, then replay the VicPark200 bag through the joiner node into out/.
run: setup bags/vicpark200/metadata.yaml
	$(ACTIVATE) && $(PY) -m linear_slam_ros.ros.demo --dataset $(DATASETS)/VicPark_200_local_maps.tar.xz --bag bags/vicpark200 --out out

## Command two: set up, then run the test suite (slow dataset runs excluded: make test-slow).
test: setup
	$(ACTIVATE) && $(PY) -m pytest -q

test-slow: setup
	$(ACTIVATE) && $(PY) -m pytest -q -m slow

## Figures: every dataset with every method, to out/benchmark/benchmark.{md,json} (not a test).
benchmark: setup
	$(PY) -m linear_slam_ros benchmark --datasets-dir $(DATASETS) --out out/benchmark
	$(ACTIVATE) && $(PY) -m linear_slam_ros.ros.bench_persistence --datasets-dir $(DATASETS) --out out/benchmark

setup: $(VENV)/.installed install/.built .cache/datasets/.unpacked

# CHOLMOD (scikit-sparse) builds against Debian's SuiteSparse and runs on its OpenBLAS.
SUITESPARSE_H := /usr/include/suitesparse/cholmod.h
$(SUITESPARSE_H):
	@if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libsuitesparse-dev libopenblas-dev >/dev/null; \
	else echo "SuiteSparse headers missing: run 'sudo apt-get install libsuitesparse-dev libopenblas-dev' (rosdep key: suitesparse)" >&2; exit 1; fi

$(VENV)/.installed: requirements.txt $(SUITESPARSE_H)
	$(PYTHON) -m venv $(VENV)
	SUITESPARSE_INCLUDE_DIR=/usr/include/suitesparse $(VENV)/bin/pip install --disable-pip-version-check -q -r requirements.txt
	touch $(VENV)/COLCON_IGNORE
	touch $@

install/.built: $(VENV)/.installed $(SOURCES)
	mkdir -p .cache out bags && touch .cache/COLCON_IGNORE out/COLCON_IGNORE bags/COLCON_IGNORE
	PATH=$(CURDIR)/$(VENV)/bin:$$PATH $(VENV)/bin/colcon --log-base log build --base-paths . --build-base build --install-base install --event-handlers console_cohesion- summary-
	touch $@

.cache/datasets/.unpacked: $(VENV)/.installed
	$(PY) -m linear_slam_ros unpack $(DATASETS)
	touch $@

bags: bags/vicpark200/metadata.yaml

bags/vicpark200/metadata.yaml: install/.built
	$(ACTIVATE) && $(PY) -m linear_slam_ros.ros.bag_from_dataset $(DATASETS)/VicPark_200_local_maps.tar.xz --out bags/vicpark200 --rate 10

clean:
	rm -rf build install log out .cache bags/*/ $(VENV)

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
SOURCES := $(shell find linear_slam_ros msg_adapters config resource launch rviz -type f \( -name '*.py' -o -name '*.yaml' -o -name '*.xml' -o -name '*.rviz' -o -name 'linear_slam_ros' \)) setup.py setup.cfg package.xml \
  $(wildcard bags/vicpark200/vicpark200.mcap)
ACTIVATE := set +u && source install/setup.bash && set -u

.PHONY: run run-sim test test-slow benchmark setup bags clean

## Command one: set up, then replay the VicPark200 bag through the joiner node into out/ (the committed
## bags/vicpark200, remade from the dataset archive when $(DATASETS) is there).
run: setup $(if $(wildcard $(DATASETS)/VicPark_200_local_maps.tar.xz),bags/vicpark200/metadata.yaml)
	$(ACTIVATE) && $(PY) -m linear_slam_ros.ros.demo --bag bags/vicpark200 --out out \
	  $(if $(wildcard $(DATASETS)/VicPark_200_local_maps.tar.xz),--dataset $(DATASETS)/VicPark_200_local_maps.tar.xz)

## The live front-end example instead of the bag: sim_frontend publishes 200 local maps of its seeded
## park world into the joiner (20 a second); the same files, in out/sim/.
run-sim: setup
	$(ACTIVATE) && $(PY) -m linear_slam_ros.ros.demo --sim --out out/sim

## Command two: set up, then run the test suite (slow dataset runs excluded: make test-slow), on two workers:
## the tests that start ROS nodes one at a time on one of them, the others on the second (test/ros/conftest.py).
test: setup
	$(ACTIVATE) && $(PY) -m pytest -q -n 2 --dist loadgroup

test-slow: setup
	$(ACTIVATE) && $(PY) -m pytest -q -m slow

## Figures (not a test): every dataset with every method offline, beside the reference program when it is there
## (benchmark.{md,json}); every stream through the node (node.{md,json}, node/<stream>/timing.png); persistence.
benchmark: setup bags $(VENV)/.bench-installed
	$(PY) -m linear_slam_ros benchmark --datasets-dir $(DATASETS) --out out/benchmark
	$(PY) -m linear_slam_ros.refinement.race --datasets-dir $(DATASETS) --out out/benchmark
	$(ACTIVATE) && $(PY) -m linear_slam_ros.ros.bench_node --datasets-dir $(DATASETS) --out out/benchmark
	$(ACTIVATE) && $(PY) -m linear_slam_ros.ros.bench_persistence --datasets-dir $(DATASETS) --out out/benchmark
	$(PY) -m linear_slam_ros.evaluation.islands --datasets-dir $(DATASETS) --out out/benchmark

setup: $(VENV)/.installed install/.built .cache/datasets/.unpacked

# gtsam for the race against iSAM2 (make benchmark only; never a dependency of the node).
$(VENV)/.bench-installed: requirements-bench.txt $(VENV)/.installed
	$(VENV)/bin/pip install --disable-pip-version-check -q -r requirements-bench.txt
	touch $@

# CHOLMOD (scikit-sparse) builds against Debian's SuiteSparse and runs on its OpenBLAS.
SUITESPARSE_H := /usr/include/suitesparse/cholmod.h
$(SUITESPARSE_H):
	@if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libsuitesparse-dev libopenblas-dev >/dev/null; \
	else echo "SuiteSparse headers missing: run 'sudo apt-get install libsuitesparse-dev libopenblas-dev' (rosdep key: suitesparse)" >&2; exit 1; fi

# requirements.txt: what the package needs beyond ROS; requirements-ros-pypi.txt: ROS 2 Jazzy and colcon
# from PyPI (this machine has no ROS install); requirements-dev.txt: tests, lint, type check.
REQUIREMENTS := requirements.txt requirements-ros-pypi.txt requirements-dev.txt
$(VENV)/.installed: $(REQUIREMENTS) $(SUITESPARSE_H)
	$(PYTHON) -m venv $(VENV)
	SUITESPARSE_INCLUDE_DIR=/usr/include/suitesparse $(VENV)/bin/pip install --disable-pip-version-check -q $(foreach r,$(REQUIREMENTS),-r $(r))
	touch $(VENV)/COLCON_IGNORE
	touch $@

install/.built: $(VENV)/.installed $(SOURCES)
	mkdir -p .cache out bags && touch .cache/COLCON_IGNORE out/COLCON_IGNORE bags/COLCON_IGNORE
	PATH=$(CURDIR)/$(VENV)/bin:$$PATH $(VENV)/bin/colcon --log-base log build --base-paths . --build-base build --install-base install --event-handlers console_cohesion- summary-
	touch $@

# Without $(DATASETS) (a fresh clone on its own) nothing is unpacked: the committed bags/ stand in.
.cache/datasets/.unpacked: $(VENV)/.installed
	if [ -d $(DATASETS) ]; then $(PY) -m linear_slam_ros unpack $(DATASETS) && touch $@; \
	else echo "no $(DATASETS): nothing to unpack; the committed bags/ (bags/README.md) stand in for the datasets"; fi

# City-sized synthetic streams (linear_slam_ros/evaluation/city.py, seed 0): pose graphs as pose_graph chunks.
SYNTHETIC_GRAPH_BAGS := city2d-20000 garage3d-5000
SYNTHETIC_MAP_BAGS := features2d-5000

# The benchmark datasets as committed bags (bags/README.md), named as their archives (VicPark_200: vicpark200).
# With $(DATASETS) there they are remade when the archive or the package changes (byte-identical output
# when neither did); without it they are used as committed.
DATASET_BAGS := DLR_200_local_maps Intel 8240_data_50_local_maps Simu_3D_870_Loop manhattanOlson3500 sphere2500
BAG_INPUTS = $(if $(wildcard $(DATASETS)/$(1).tar.xz),$(DATASETS)/$(1).tar.xz install/.built)

bags: bags/vicpark200/metadata.yaml $(foreach b,$(DATASET_BAGS) $(SYNTHETIC_GRAPH_BAGS) $(SYNTHETIC_MAP_BAGS),bags/$(b)/metadata.yaml)

bags/vicpark200/metadata.yaml: $(call BAG_INPUTS,VicPark_200_local_maps) | install/.built
	$(ACTIVATE) && $(PY) -m linear_slam_ros.ros.bag_from_dataset $(DATASETS)/VicPark_200_local_maps.tar.xz --out bags/vicpark200 --rate 10

.SECONDEXPANSION:
$(foreach b,$(DATASET_BAGS),bags/$(b)/metadata.yaml): bags/%/metadata.yaml: $$(call BAG_INPUTS,$$*) | install/.built
	$(ACTIVATE) && $(PY) -m linear_slam_ros.ros.bag_from_dataset $(DATASETS)/$*.tar.xz --out bags/$* --rate 10

$(foreach b,$(SYNTHETIC_GRAPH_BAGS),bags/$(b)/metadata.yaml): bags/%/metadata.yaml: install/.built
	$(ACTIVATE) && $(PY) -m linear_slam_ros.ros.bag_from_dataset --synthetic $* --out bags/$* --rate 10 --as-pose-graph

$(foreach b,$(SYNTHETIC_MAP_BAGS),bags/$(b)/metadata.yaml): bags/%/metadata.yaml: install/.built
	$(ACTIVATE) && $(PY) -m linear_slam_ros.ros.bag_from_dataset --synthetic $* --out bags/$* --rate 10

clean:  # generated bags go; the committed ones (vicpark200 and DATASET_BAGS) stay
	rm -rf build install log out .cache $(VENV) $(filter-out bags/vicpark200/ $(foreach b,$(DATASET_BAGS),bags/$(b)/),$(wildcard bags/*/))

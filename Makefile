# deepprompt_ros — every target does the set-up it needs first and is idempotent.
SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python
export ROS_AUTOMATIC_DISCOVERY_RANGE ?= LOCALHOST
export AMENT_PREFIX_PATH := $(abspath $(VENV))$(if $(AMENT_PREFIX_PATH),:$(AMENT_PREFIX_PATH))

.PHONY: setup run run-dual test bench experiments experiments-quick models train-sine train-reach train-shake clean

setup:
	bash tools/setup.sh $(VENV)

test: setup
	$(PY) -m pytest -q test

bench: setup
	$(PY) bench/run_all.py

# The paper's experiments (EXPERIMENTS.md): --medium writes docs/experiments/ (resumable: see EXPERIMENTS.md).
experiments: setup
	$(PY) experiments/run.py --medium

experiments-quick: setup
	$(PY) experiments/run.py --quick

run: setup
	$(PY) -m deepprompt_ros.run_main

# Two simulated arms, each with its server under its own namespace (/left_arm: Gen3 lite, /right_arm: WAM).
run-dual: setup
	$(PY) -m deepprompt_ros.run_main --launch dual_arm

# Train the shipped primitives in models/ (seeded: the same command gives the same weights and choices;
# the metadata's creation time and wall time differ): train-sine, train-reach and train-shake give
# models/bimodal_sine, models/gen3_lite_reach and models/wam_shake.
TRAIN := $(PY) -m deepprompt_ros.training.cli
models: train-sine train-reach train-shake
train-sine: setup
	$(TRAIN) --builtin bimodal_sine --config config/train_bimodal_sine.yaml --out models/bimodal_sine.safetensors
train-reach: setup
	$(TRAIN) --builtin gen3_lite_reach --config config/train_gen3_lite_reach.yaml --out models/gen3_lite_reach.safetensors
train-shake: setup
	$(TRAIN) --builtin wam_shake --config config/train_wam_shake.yaml --out models/wam_shake.safetensors

clean:
	rm -rf build install log $(VENV)

# deepprompt_ros — every target does the set-up it needs first and is idempotent.
SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python
export ROS_AUTOMATIC_DISCOVERY_RANGE ?= LOCALHOST
export AMENT_PREFIX_PATH := $(abspath $(VENV))$(if $(AMENT_PREFIX_PATH),:$(AMENT_PREFIX_PATH))

.PHONY: setup run test bench train-sine clean

setup:
	bash tools/setup.sh $(VENV)

test: setup
	$(PY) -m pytest -q test

bench: setup
	$(PY) bench/run_all.py

run: setup
	$(PY) -m deepprompt_ros.run_main

# Reproduces models/bimodal_sine.safetensors (the shipped primitive).
train-sine: setup
	$(PY) -m deepprompt_ros.core.train --builtin bimodal_sine --config config/train_bimodal_sine.yaml --out models/bimodal_sine.safetensors

clean:
	rm -rf build install log $(VENV)

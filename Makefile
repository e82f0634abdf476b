# packml_ros2 — the two commands of the README, and the habits behind them.
#   make demo   set up (first run: a few minutes), then run the demo cell
#   make test   set up, then linters, type check and the whole test suite
SHELL := /bin/bash
VENV ?= .venv
BIN := $(VENV)/bin
CELL ?= config/demo_cell.yaml

# DDS traffic stays on this machine, its sockets on loopback; discovery is quick (config/fastdds_loopback.xml).
export ROS_AUTOMATIC_DISCOVERY_RANGE ?= LOCALHOST
export FASTDDS_DEFAULT_PROFILES_FILE ?= $(CURDIR)/config/fastdds_loopback.xml
export AMENT_PREFIX_PATH := $(CURDIR)/$(VENV)$(if $(AMENT_PREFIX_PATH),:$(AMENT_PREFIX_PATH))

.PHONY: setup setup-test demo test lint format typecheck pytest bench clean

setup:
	@tools/setup.sh

demo: setup
	$(BIN)/packml launch $(CELL)

test: setup-test lint typecheck pytest

setup-test:
	@tools/setup.sh --test

lint:
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

format:
	$(BIN)/ruff check --fix .
	$(BIN)/ruff format .

typecheck:
	$(BIN)/mypy

pytest:
	$(BIN)/pytest $(PYTEST_ARGS)

bench: setup
	$(BIN)/python bench/engine.py
	$(BIN)/python bench/ros_latency.py
	$(BIN)/python bench/replay.py
	$(BIN)/python bench/cli.py
	$(BIN)/python bench/scale.py
	$(BIN)/python bench/hmi.py

clean:
	rm -rf $(VENV) .cache msg_defs/build build *.egg-info .pytest_cache .mypy_cache .ruff_cache

# The HMI's main screens (overview, unit with state diagram, alarms, line) as PNGs for the README,
# written by the browser test against a running demo-like cell.
.PHONY: screenshots
screenshots:
	PACKML_SCREENSHOTS_DIR=$(CURDIR)/docs/screenshots $(BIN)/pytest test/hmi/test_browser.py test/line/test_line_demo.py -q -rs

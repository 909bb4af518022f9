# lanefree_sumo — everything runs inside .venv, bootstrapped on first use.
# Main jobs:  make test  ·  make train DENSITY=90  ·  make simulate DENSITY=90  ·  make bench
# Checks:     make lint  ·  make test-fast (no SUMO, < 30 s)

PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

DENSITY ?= 90
SEED    ?= 0
ALGO    ?= ddpg
REWARD  ?= fields_zones_overtake_collision
EPISODES ?= 625
ENVS    ?= 1
OBS     ?= vector
RUN     ?=
RUNS    ?= runs/*/
EPISODE ?= 1
SECONDS ?= 200
LENGTH  ?= 500
WIDTH   ?= 10.2
STAMP_NOW := $(shell date +%Y%m%d-%H%M%S)

.PHONY: venv test test-fast lint train evaluate replay report simulate nets bench traffic clean-venv

# Re-installs only when pyproject.toml changes. torch must be exactly 2.13.0 (the local CPU
# build) BEFORE anything depends on it; any other spec pulls a multi-GB CUDA build.
$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q torch==2.13.0
	$(BIN)/python -m pip install -q -e ".[rl,test]"
	touch $(STAMP)

venv: $(STAMP)

test: $(STAMP)
	$(BIN)/python -m pytest -q

# Pure-numpy and small-torch tests only (no SUMO, no GUI, no training): < 30 s.
test-fast: $(STAMP)
	$(BIN)/python -m pytest -q -m "not sumo and not gui and not slow"

lint: $(STAMP)
	$(BIN)/ruff check lanefree_sumo tests
	$(BIN)/mypy

train: $(STAMP)
	$(BIN)/lanefree train --algo $(ALGO) --reward $(REWARD) --density $(DENSITY) --episodes $(EPISODES) \
		--seed $(SEED) --envs $(ENVS) --obs $(OBS)

evaluate: $(STAMP)
	@test -n "$(RUN)" || { echo "usage: make evaluate RUN=runs/<run folder>"; exit 2; }
	$(BIN)/lanefree evaluate $(RUN) --record

replay: $(STAMP)
	@test -n "$(RUN)" || { echo "usage: make replay RUN=runs/<run folder> [EPISODE=1]"; exit 2; }
	$(BIN)/lanefree replay $(RUN) --episode $(EPISODE)

report: $(STAMP)
	$(BIN)/lanefree report $(RUNS) --out runs/report

simulate: $(STAMP)
	$(BIN)/lanefree simulate --density $(DENSITY) --seconds $(SECONDS) --seed $(SEED) \
		--out runs/sim-d$(DENSITY)-s$(SEED)-$(STAMP_NOW)

nets: $(STAMP)
	$(BIN)/lanefree net --length $(LENGTH) --width $(WIDTH)

bench: $(STAMP)
	$(BIN)/python -m lanefree_sumo.tools.bench

clean-venv:
	rm -rf $(VENV)

traffic: $(STAMP)
	$(BIN)/python -m lanefree_sumo.tools.traffic_check

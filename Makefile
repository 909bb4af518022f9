# lanefree_sumo — everything runs inside .venv, bootstrapped on first use.
# Main jobs:  make test  ·  make simulate DENSITY=90  ·  make bench

PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

DENSITY ?= 90
SEED    ?= 0
SECONDS ?= 200
LENGTH  ?= 500
WIDTH   ?= 10.2
STAMP_NOW := $(shell date +%Y%m%d-%H%M%S)

.PHONY: venv test simulate nets bench traffic clean-venv

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

simulate: $(STAMP)
	$(BIN)/lanefree simulate --density $(DENSITY) --seconds $(SECONDS) --seed $(SEED) \
		--out runs/sim-d$(DENSITY)-s$(SEED)-$(STAMP_NOW)

nets: $(STAMP)
	$(BIN)/lanefree net --length $(LENGTH) --width $(WIDTH)

bench: $(STAMP)
	$(BIN)/python -m lanefree_sumo.bench

clean-venv:
	rm -rf $(VENV)

traffic: $(STAMP)
	$(BIN)/python -m lanefree_sumo.traffic_check

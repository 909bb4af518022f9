# lanefree_sumo — everything runs inside .venv, bootstrapped on first use.
# Main jobs:  make test  ·  make train DENSITY=90  ·  make simulate DENSITY=90  ·  make bench  ·  make docs
# Checks:     make lint  ·  make test-fast (no SUMO, no training)  ·  make mutate (before a release; not in CI)

PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
BENCH_STAMP := $(VENV)/.installed-bench
DOCS_STAMP := $(VENV)/.installed-docs
MUTATE_STAMP := $(VENV)/.installed-mutate

# Options are passed only when set, so every default is the one in lanefree_sumo/config.py
# (`lanefree COMMAND --help` shows them): make train DENSITY=90 ALGO=per SEED=3 SHIELD=1 ...
RUN     ?=
RUNS    ?= runs/*/
opt = $(if $($(1)),$(2) $($(1)))
TRAIN_OPTS = $(call opt,ALGO,--algo) $(call opt,REWARD,--reward) $(call opt,DENSITY,--density) \
	$(call opt,EPISODES,--episodes) $(call opt,SEED,--seed) $(call opt,ENVS,--envs) $(call opt,OBS,--obs) \
	$(call opt,ENCODER,--encoder) $(if $(SHIELD),--shield)
SIM_OPTS = $(call opt,DENSITY,--density) $(call opt,SECONDS,--seconds) $(call opt,SEED,--seed)
STAMP_NOW := $(shell date +%Y%m%d-%H%M%S)

.PHONY: venv system-deps test test-fast lint mutate docs train sweep evaluate replay report simulate nets bench bench-gpu traffic onramp-flows results clean-venv

# Re-installs only when pyproject.toml changes. torch must be exactly 2.13.0 (the local CPU
# build) BEFORE anything depends on it; any other spec pulls a multi-GB CUDA build.
$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q torch==2.13.0
	$(BIN)/python -m pip install -q -e ".[rl,test]"
	touch $(STAMP)

venv: $(STAMP)

# `make bench` only: the HighwayEnv peer of the training-speed section (the `bench` extra).
$(BENCH_STAMP): $(STAMP)
	$(BIN)/python -m pip install -q -e ".[bench]"
	touch $(BENCH_STAMP)

# Xvfb and the system libraries SUMO's wheels need (scripts/system-deps.sh): installed with apt-get
# when missing. Every target that runs SUMO (libsumo, sumo, sumo-gui, netconvert) depends on it.
system-deps:
	@bash scripts/system-deps.sh

# One pytest worker per core, at most 4 (TEST_WORKERS=; each worker holds torch, SUMO and at times a Ray
# of its own): pytest-xdist, `worksteal` hands a worker that ran out the queued tests of another, so the few
# minute-long sweep tests do not leave a core idle at the end. Tests share nothing but the machine: each
# has its own tmp dirs, Ray instance, ports and Xvfb display.
TEST_WORKERS ?= $(shell n=$$(nproc); echo $$(( n < 4 ? n : 4 )))
test: system-deps $(STAMP)
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist worksteal

# Pure-numpy and small-torch tests only (no SUMO, no GUI, no training; timings in README.md).
test-fast: $(STAMP)
	$(BIN)/python -m pytest -q -m "not sumo and not gui and not slow"

lint: $(STAMP)
	$(BIN)/ruff check lanefree_sumo tests scripts
	$(BIN)/mypy

# `make mutate [MODULES="lanefree_sumo.rl.rewards ..."]`: mutation testing (mutmut, the `mutate` extra) of the
# modules that decide results, each mutant against the fast tests that reach it; prints the score per module
# (docs/development.md). Without MODULES every module of pyproject.toml's [tool.mutmut], only what has no result
# in mutants/ yet. Hours on 2 cores when nothing is cached: run before a release, not in CI.
$(MUTATE_STAMP): $(STAMP)
	$(BIN)/python -m pip install -q -e ".[mutate]"
	touch $(MUTATE_STAMP)

mutate: $(STAMP) $(MUTATE_STAMP)
	nice -n 19 $(BIN)/python scripts/mutate.py $(MODULES)

train: system-deps $(STAMP)
	$(BIN)/lanefree train $(TRAIN_OPTS)

evaluate: system-deps $(STAMP)
	@test -n "$(RUN)" || { echo "usage: make evaluate RUN=runs/<run folder> [OVERWRITE=1]"; exit 2; }
	$(BIN)/lanefree evaluate $(RUN) --record $(if $(OVERWRITE),--overwrite)

replay: system-deps $(STAMP)
	@test -n "$(RUN)" || { echo "usage: make replay RUN=runs/<run folder> [EPISODE=1] (under xvfb-run without a DISPLAY)"; exit 2; }
	$(if $(DISPLAY),,xvfb-run -a) $(BIN)/lanefree replay $(RUN) $(call opt,EPISODE,--episode)

report: $(STAMP)
	$(BIN)/lanefree report $(RUNS) $(call opt,OUT,--out)

simulate: system-deps $(STAMP)
	$(BIN)/lanefree simulate $(SIM_OPTS) --out runs/sim-$(STAMP_NOW)

nets: system-deps $(STAMP)
	$(BIN)/lanefree net $(call opt,LENGTH,--length) $(call opt,WIDTH,--width)

# `make docs`: the Sphinx site (docs/) into build/docs/, warnings as errors.
$(DOCS_STAMP): $(STAMP)
	$(BIN)/python -m pip install -q -e ".[docs]"
	touch $(DOCS_STAMP)

docs: $(STAMP) $(DOCS_STAMP)
	rm -rf build/docs
	$(BIN)/sphinx-build -W --keep-going -q -b html docs build/docs
	@echo "docs -> build/docs/index.html"

bench: system-deps $(STAMP) $(BENCH_STAMP)
	$(BIN)/python -m lanefree_sumo.tools.bench

# The batched path on a CUDA GPU (env rates, training iterations/s, the projected 150-run grid; < 8 min).
bench-gpu: $(STAMP)
	$(BIN)/python -m lanefree_sumo.tools.bench --gpu

# make sweep GRID=table7 [OUT=runs/sweep_table7] [SEEDS=3] [EPISODES=625] [WORKERS=2] [ADDRESS=host:6379]
sweep: system-deps $(STAMP)
	@test -n "$(GRID)" || { echo "usage: make sweep GRID=table5|table6|table7|table8|paper|varobs|FILE.yaml [OUT=DIR] [SEEDS=N] [EPISODES=N] [WORKERS=N] [ADDRESS=HOST:PORT]"; exit 2; }
	$(BIN)/lanefree sweep $(GRID) $(call opt,OUT,--out) $(call opt,SEEDS,--seeds) $(call opt,EPISODES,--episodes) \
		$(call opt,WORKERS,--workers) $(call opt,ADDRESS,--address)

# Evaluate finished runs and rewrite every committed result table (results/paper, results/varobs).
results: system-deps $(STAMP)
	scripts/update-results.sh

clean-venv:
	rm -rf $(VENV)

traffic: system-deps $(STAMP)
	$(BIN)/python -m lanefree_sumo.tools.traffic_check

# The on-ramp's inflow-outflow curve into results/onramp/ (RAMP=veh/h, default 300).
onramp-flows: $(STAMP)
	$(BIN)/python -m lanefree_sumo.tools.onramp_flows $(if $(RAMP),--ramp-flow $(RAMP) --out results/onramp/ramp$(RAMP),)

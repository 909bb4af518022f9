#!/usr/bin/env bash
# The GPU path's device checks in one call, on a machine with a CUDA GPU and its own python3 with torch
# (docs/performance.md, "On a GPU"). Writes into $OUT (default runs/gpu_check):
#   quick: nvidia-smi, `make bench-gpu` with a shorter budget, and a 2-seed × 2-episode batch trained on CUDA
#          whose model.zip files load on the CPU;
#   grid:  the paper grid at 10 seeds (lanefree sweep paper --no-ray --batch 110 on CUDA), resumable across calls
#          on one warm machine; finished runs packed as grid.tar.gz;
#   remedies: the set encoder's DDPG collapse and its remedies (results/varobs_remedies/ddpg.yaml: DDPG and DDPG
#          with the pre-tanh penalty, 3 seeds each, one batch of 6 in the lockstep loop; then td3.yaml, 3 runs, the
#          exact loop) on CUDA, resumable across calls on one warm machine; finished runs packed as remedies.tar.gz;
#   full:  the whole bench, a profile of a DDPG iteration at K = 110, then the learning check's runs: three
#          settings × 10 seeds × $EPISODES episodes trained on CUDA (the three batches at once, stopped with a
#          checkpoint after $LEARN_LIMIT_S s), packed as learn.tar.gz; compare them with the CPU runs of
#          results/paper by scripts/analysis/learning_check.py.
# Packages the machine lacks (gymnasium, stable-baselines3) are installed from wheels in .whl/ when present.
set -uo pipefail
mode=${1:-quick}
began=$(date +%s)
OUT=${OUT:-runs/gpu_check}
PY=${PYTHON:-python3}
EPISODES=${EPISODES:-100}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
if ! $PY -c "import gymnasium, stable_baselines3" 2>/dev/null && ls .whl/*.whl >/dev/null 2>&1; then
  $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    && export PYTHONPATH="$PYTHONPATH:/tmp/site"
fi
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv | tee "$OUT/gpu.txt"
lanefree() { $PY -m lanefree_sumo.cli "$@"; }

if [ "$mode" = grid ]; then
  # the paper grid at 10 seeds on the GPU, without Ray: DDPG's 110 runs as one batch, dqn+ddqn as one, dueling
  # and per as one each. Stopped with a checkpoint after $GRID_LIMIT_S s; run it again on the same warm machine to
  # continue (the sweep folder, runs/gpu_grid, stays between calls). The finished runs' small files, the summary
  # and the logs come back as grid.tar.gz. On a fresh machine (a batch checkpoint does not travel): unpack
  # grid.tar.gz in the repository (it holds runs/gpu_grid) and carry runs/gpu_grid; its finished runs count as
  # complete (their last session says so), the others start again.
  GRID=runs/gpu_grid
  if [ -f "$GRID/sweep.yaml" ]; then set -- --resume "$GRID"; else set -- paper --out "$GRID" --set train.device=cuda; fi
  timeout -s TERM "${GRID_LIMIT_S:-480}" $PY -m lanefree_sumo.cli sweep "$@" --batch 110 --no-ray --no-progress \
    2>&1 | grep -v "Warning\|check(" | tail -n 40 | tee "$OUT/grid.log"
  tar czf "$OUT/grid.tar.gz" --exclude='*.zip' --exclude='*.pt' --exclude='tb' --exclude='checkpoints' \
    --exclude='batch_checkpoints' "$GRID"
  exit 0
fi

if [ "$mode" = remedies ]; then
  # Stopped with a checkpoint after $REMEDIES_LIMIT_S s in all; run it again on the same warm machine to continue.
  # The set encoder's iteration on a GPU was never measured: the log's episode counts say how far it got.
  for grid in ddpg td3; do
    dir=runs/gpu_remedies_$grid
    if [ -f "$dir/sweep.yaml" ]; then set -- --resume "$dir"; else
      set -- "results/varobs_remedies/$grid.yaml" --out "$dir" --set train.device=cuda; fi
    left=$(( ${REMEDIES_LIMIT_S:-480} - ($(date +%s) - began) ))
    [ "$left" -gt 60 ] || break
    timeout -s TERM "$left" $PY -m lanefree_sumo.cli sweep "$@" --batch 6 --no-ray --no-progress \
      2>&1 | grep -v "Warning\|check(" | tail -n 20 | tee -a "$OUT/remedies.log"
  done
  tar czf "$OUT/remedies.tar.gz" --exclude='*.zip' --exclude='*.pt' --exclude='tb' --exclude='checkpoints' \
    --exclude='batch_checkpoints' runs/gpu_remedies_*
  exit 0
fi

if [ "$mode" = quick ]; then
  $PY -m lanefree_sumo.tools.bench --gpu --budget-s "${BUDGET_S:-150}" --train-sizes 1,110 --dqn-sizes 1,10 \
    2>&1 | tee "$OUT/bench_gpu.md"
  lanefree train --seeds 0-1 --device cuda --episodes 2 --episode-steps 100 --out "$OUT/smoke" 2>&1 | tail -5
  $PY - "$OUT/smoke" <<'EOF' 2>&1 | tee "$OUT/smoke.txt"
import sys
from pathlib import Path
from stable_baselines3 import DDPG
for run in sorted(Path(sys.argv[1]).glob("ddpg_*")):
    model = DDPG.load(run / "model.zip", device="cpu")
    rows = (run / "episodes.csv").read_text().splitlines()
    print(run.name, "model.zip loads on the CPU;", len(rows) - 1, "episode rows;", rows[-1][:60])
EOF
  exit 0
fi

# BENCH_ARGS: other rows than the bench's defaults (each K compiles the step and the update anew)
$PY -m lanefree_sumo.tools.bench --gpu --budget-s "${BUDGET_S:-300}" ${BENCH_ARGS:-} 2>&1 | tee "$OUT/bench_gpu.md"
# where an iteration's GPU time goes: DDPG, K = 110, no graph (every kernel seen; compiled as the loop runs), 5
# iterations
[ "${PROFILE:-1}" = 1 ] && $PY - > "$OUT/profile_ddpg_k110.txt" 2>&1 <<'PROFILE'
import torch
from torch.profiler import ProfilerActivity, profile
from lanefree_sumo.tools.bench_gpu import _loop
loop = _loop(110, "cuda", 0, "ddpg", graphs=False)
for _ in range(70):
    loop.iterate()
torch.cuda.synchronize()
with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
    for _ in range(5):
        loop.iterate()
    torch.cuda.synchronize()
events = [e for e in prof.events() if e.device_type == torch.autograd.DeviceType.CUDA]
print(f"kernels per iteration: {len(events) / 5:.0f}; GPU busy per iteration: "
      f"{sum(e.device_time for e in events) / 5 / 1000:.3f} ms")
print(prof.key_averages().table(sort_by="cuda_time_total", row_limit=25))
PROFILE
LEARN=${LEARN:-/tmp/learn}  # outside $OUT: only 8 files come back from a device call
LIMIT=${LEARN_LIMIT_S:-330}  # the batches get SIGTERM (a checkpoint, then they stop) after this many seconds
if [ -n "${DEADLINE_S:-}" ]; then  # or: what is left until DEADLINE_S seconds after the script began, less 25 s
  LIMIT=$(( DEADLINE_S - ($(date +%s) - began) - 25 ))
fi
echo "learning check: $LIMIT s"
start=$(date +%s)
learn() {  # NAME, then train's options
  local name=$1; shift
  timeout -s TERM "$LIMIT" $PY -m lanefree_sumo.cli train --seeds 0-9 --device cuda --episodes "$EPISODES" \
    --out "$LEARN/$name" "$@" > "$OUT/learn_$name.log" 2>&1
}
learn ddpg_fzoc70 --algo ddpg --reward fields_zones_overtake_collision --density 70 &
learn ddpg_collision70 --algo ddpg --reward collision --density 70 &
learn dqn_fzoc70 --algo dqn --reward fields_zones_overtake_collision --density 70 &
wait
echo "learning-check runs: $(( $(date +%s) - start )) s for 3 batches of 10 runs × $EPISODES episodes, at once"
tar czf "$OUT/learn.tar.gz" --exclude='*.zip' --exclude='*.pt' --exclude='tb' --exclude='checkpoints' \
  -C "$(dirname "$LEARN")" "$(basename "$LEARN")"
tail -n 3 "$OUT"/learn_*.log

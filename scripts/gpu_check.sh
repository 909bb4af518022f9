#!/usr/bin/env bash
# The GPU path's device checks in one call, on a machine with a CUDA GPU and its own python3 with torch
# (docs/performance.md, "On a GPU"). Writes into $OUT (default runs/gpu_check):
#   quick: nvidia-smi, `make bench-gpu` with a shorter budget, and a 2-seed × 2-episode batch trained on CUDA
#          whose model.zip files load on the CPU;
#   full:  the whole bench, then the learning check's runs: three settings × 10 seeds × $EPISODES episodes
#          trained on CUDA (the three batches at once), packed as learn.tar.gz; compare them with the CPU runs
#          of results/paper by scripts/learning_check.py.
# Packages the machine lacks (gymnasium, stable-baselines3) are installed from wheels in .whl/ when present.
set -uo pipefail
mode=${1:-quick}
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

$PY -m lanefree_sumo.tools.bench --gpu --budget-s "${BUDGET_S:-300}" 2>&1 | tee "$OUT/bench_gpu.md"
start=$(date +%s)
lanefree train --seeds 0-9 --device cuda --algo ddpg --reward fields_zones_overtake_collision --density 70 \
  --episodes "$EPISODES" --out "$OUT/learn/ddpg_fzoc70" > "$OUT/learn_ddpg_fzoc70.log" 2>&1 &
lanefree train --seeds 0-9 --device cuda --algo ddpg --reward collision --density 70 \
  --episodes "$EPISODES" --out "$OUT/learn/ddpg_collision70" > "$OUT/learn_ddpg_collision70.log" 2>&1 &
lanefree train --seeds 0-9 --device cuda --algo dqn --reward fields_zones_overtake_collision --density 70 \
  --episodes "$EPISODES" --out "$OUT/learn/dqn_fzoc70" > "$OUT/learn_dqn_fzoc70.log" 2>&1 &
wait
echo "learning-check runs: $(( $(date +%s) - start )) s for 3 batches of 10 runs × $EPISODES episodes, at once"
tar czf "$OUT/learn.tar.gz" --exclude='*.zip' --exclude='*.pt' --exclude='tb' --exclude='checkpoints' \
  -C "$OUT" learn
tail -n 3 "$OUT"/learn_*.log

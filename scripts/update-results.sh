#!/usr/bin/env bash
# Bring the committed result files up to date after runs finish. Evaluates every finished run of
# the paper sweep that still has its model and lacks an evaluation (`lanefree evaluate SWEEP`, deterministic and
# shielded, 50 episodes each), rewrites the
# sweep's summary, claims and curves (of the seeds complete in every setting), both evaluation tables, the
# collisions-against-overtakes figure and README.md's results table (scripts/collisions_vs_overtakes.py,
# readme_results.py) from the committed episodes.csv files, then runs the variable-dimension evaluations and
# reports (scripts/varobs-transfer.sh). Resumable: it only evaluates what is missing.
# Usage: scripts/update-results.sh [EPISODES]   (make results; EPISODES per evaluation, default 50)
set -euo pipefail
cd "$(dirname "$0")/.."  # relative paths: the tables name runs as results/..., on any machine
exec 9>results/.lock  # one update at a time (the watcher of scripts/reproduce.sh runs this too)
flock -n 9 || { echo "another update of the results is running; waiting for it"; flock 9; }
bin=.venv/bin/lanefree
paper=results/paper
episodes=${1:-50}
[[ $episodes =~ ^[1-9][0-9]*$ ]] || { echo "update-results: EPISODES must be a whole number >= 1, got '$episodes'" >&2; exit 2; }
"$bin" evaluate "$paper" --episodes "$episodes"  # every finished run lacking a complete evaluation
"$bin" evaluate "$paper" --episodes "$episodes" --shield
# the tables' seeds 0 … seeds−1: those complete in every setting (while the sweep is extended to more seeds,
# its tables stay those of the seeds it has everywhere; every seed once it is complete); before any seed is
# complete everywhere, every complete run
seeds=$(.venv/bin/python -c "import sys; from lanefree_sumo.experiments.sweep.summary import complete_seeds; from pathlib import Path; print(complete_seeds(Path(sys.argv[1])))" "$paper")
if ((seeds > 0)); then
    "$bin" sweep --summary "$paper" --seeds "$seeds" >/dev/null
else
    "$bin" report "$paper" >/dev/null
fi
for eval in eval eval_shield; do
    finished=()  # runs with a model (trained here) or this evaluation (committed): not those still training
    for run in "$paper"/runs/*/; do
        run=${run%/}
        ((seeds == 0 || ${run##*_s} < seeds)) || continue
        if [ -e "$run/model.zip" ] || [ -d "$run/$eval" ]; then finished+=("$run"); fi
    done
    if ((${#finished[@]})); then
        "$bin" report "${finished[@]}" --eval "$eval" --out "$paper/${eval}_report" >/dev/null
    fi
done
.venv/bin/python scripts/collisions_vs_overtakes.py "$paper" >/dev/null
if [ -f README.md ] && [ -f "$paper/summary.csv" ]; then .venv/bin/python scripts/readme_results.py >/dev/null; fi
scripts/varobs-transfer.sh "$episodes" >/dev/null
echo "results updated: $paper (summary.md, runs.csv, claims.md, eval_report/, eval_shield_report/, collisions_vs_overtakes.png), README.md's table, results/varobs/report*/, results/varobs/verdict/"

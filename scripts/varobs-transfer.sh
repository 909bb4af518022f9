#!/usr/bin/env bash
# Issue 17, part 3: evaluate every finished run of the variable-dimension experiment — the fixed-vector
# baseline is the paper sweep's own DDPG fields_zones_overtake_collision 70 veh/km runs (seeds 0-2, the
# default vector observation), the set-encoder runs are results/varobs/set/runs/* — deterministically at
# its training density (eval/), zero-shot at 90 and 120 veh/km (eval_d90/, eval_d120/) and on the
# on-ramp's main road at its training density (eval_onramp/), then write the training report (curves of
# both observations overlaid) into results/varobs/report/ and the four evaluations side by side (table,
# bar charts) into results/varobs/report_transfer/. A run is evaluated where its model.zip is (the
# machine that trained it) and reported wherever its evaluations are committed.
# Resumable: rerun it and it evaluates only what is missing. Usage: scripts/varobs-transfer.sh [EPISODES]
set -euo pipefail
cd "$(dirname "$0")/.."  # relative paths: the tables name runs as results/..., on any machine
bin=.venv/bin/lanefree
episodes=${1:-50}
base=results/varobs
runs=()
source scripts/evaluation-helper.sh
for run in results/paper/runs/ddpg_fields_zones_overtake_collision_d70_s{0,1,2} "$base"/set/runs/*; do
    if [ -e "$run/model.zip" ]; then
        evaluate "$run" eval
        for density in 90 120; do
            evaluate "$run" "eval_d$density" --density "$density"
        done
        evaluate "$run" eval_onramp --scenario onramp
    fi
    if [ -s "$run/eval/episodes.csv" ]; then runs+=("$run"); fi
done
[ ${#runs[@]} -gt 0 ] || { echo "no finished, evaluated run of the variable-dimension experiment"; exit 0; }
"$bin" report "${runs[@]}" --out "$base/report"
"$bin" report "${runs[@]}" --eval eval eval_d90 eval_d120 eval_onramp --out "$base/report_transfer"

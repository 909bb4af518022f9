#!/usr/bin/env bash
# Issue 17, part 3: evaluate every finished run of the variable-dimension experiment (folders with
# model.zip under results/varobs/{vector,set}/runs) deterministically at its training density (eval/),
# zero-shot at 90 and 120 veh/km (eval_d90/, eval_d120/) and on the on-ramp's main road at its training
# density (eval_onramp/), then write the training report (curves of both observations overlaid) into
# results/varobs/report/ and the four evaluations side by side (table, bar charts) into results/varobs/report_transfer/.
# Resumable: rerun it and it evaluates only what is missing. Usage: scripts/varobs-transfer.sh [EPISODES]
set -euo pipefail
cd "$(dirname "$0")/.."  # relative paths: the tables name runs as results/..., on any machine
bin=.venv/bin/lanefree
episodes=${1:-50}
base=results/varobs
runs=()
# evaluate RUN into RUN/FOLDER unless it already holds EPISODES complete episodes (a partial one is replaced)
evaluate() {
    local run=$1 folder=$2
    shift 2
    local log=$run/$folder/episodes.csv
    if [ -s "$log" ] && [ $(($(wc -l <"$log") - 1)) -ge "$episodes" ]; then return 0; fi
    "$bin" evaluate "$run" --episodes "$episodes" --out "$run/$folder" --overwrite "$@"
}
for model in "$base"/vector/runs/*/model.zip "$base"/set/runs/*/model.zip; do
    [ -e "$model" ] || continue
    run=$(dirname "$model")
    runs+=("$run")
    evaluate "$run" eval
    for density in 90 120; do
        evaluate "$run" "eval_d$density" --density "$density"
    done
    evaluate "$run" eval_onramp --scenario onramp
done
[ ${#runs[@]} -gt 0 ] || { echo "no finished run with a model under $base"; exit 0; }
"$bin" report "${runs[@]}" --out "$base/report"
"$bin" report "${runs[@]}" --eval eval eval_d90 eval_d120 eval_onramp --out "$base/report_transfer"

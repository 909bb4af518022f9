#!/usr/bin/env bash
# Evaluate every finished run (a folder with model.zip) under DIR that lacks an evaluation:
# 50 deterministic episodes (RUN/eval/) and 50 with the safety shield (RUN/eval_shield/).
# Resumable: rerun it and it does only what is missing. Usage: scripts/evaluate-runs.sh DIR [EPISODES]
set -euo pipefail
dir=${1:?usage: scripts/evaluate-runs.sh DIR [EPISODES]}
episodes=${2:-50}
bin=$(dirname "$0")/../.venv/bin/lanefree
for model in "$dir"/runs/*/model.zip; do
    [ -e "$model" ] || continue
    run=$(dirname "$model")
    [ -s "$run/eval/episodes.csv" ] || "$bin" evaluate "$run" --episodes "$episodes"
    [ -s "$run/eval_shield/episodes.csv" ] || "$bin" evaluate "$run" --episodes "$episodes" --shield
done

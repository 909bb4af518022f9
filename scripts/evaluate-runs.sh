#!/usr/bin/env bash
# Evaluate every finished run (a folder with model.zip) under DIR that lacks an evaluation:
# 50 deterministic episodes (RUN/eval/) and 50 with the safety shield (RUN/eval_shield/). An evaluation
# with fewer episodes (one stopped part-way keeps what it finished) is run again whole.
# Resumable: rerun it and it does only what is missing. Usage: scripts/evaluate-runs.sh DIR [EPISODES]
set -euo pipefail
dir=${1:?usage: scripts/evaluate-runs.sh DIR [EPISODES]}
episodes=${2:-50}
bin=$(dirname "$0")/../.venv/bin/lanefree
source "$(dirname "$0")/evaluation-helper.sh"
for model in "$dir"/runs/*/model.zip; do
    [ -e "$model" ] || continue
    run=$(dirname "$model")
    evaluate "$run" eval
    evaluate "$run" eval_shield --shield
done

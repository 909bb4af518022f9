#!/usr/bin/env bash
# Evaluate every finished run of the variable-dimension experiment deterministically at its
# training density (eval/), zero-shot at 90 and 120 veh/km (eval_d90/, eval_d120/) and on the on-ramp's main
# road at its training density (eval_onramp/), and report each comparison of the fixed vector against the set
# encoder at fields_zones_overtake_collision / 70 veh/km:
#   DDPG (the experiment's design): the paper sweep's own DDPG runs (seeds 0-2, the default vector observation) against
#     results/varobs/set/runs/*; training report (curves of both observations overlaid) in
#     results/varobs/report/, the four evaluations side by side (table, bar charts) in results/varobs/report_transfer/;
#   DQN (Liu et al.'s own setting, a Q-network): the paper sweep's DQN runs against results/varobs/set_dqn/runs/*;
#     results/varobs/report_dqn/ and results/varobs/report_dqn_transfer/;
# then both comparisons' verdicts on Liu et al.'s claim, set - vector with bootstrap CIs, in
# results/varobs/verdict/verdict.md (`lanefree report ... --compare` of every finished run of both).
# A run is evaluated where its model.zip is (the machine that trained it) and reported wherever its evaluations
# are committed. Resumable: rerun it and it evaluates only what is missing. Usage: scripts/varobs-transfer.sh [EPISODES]
set -euo pipefail
cd "$(dirname "$0")/.."  # relative paths: the tables name runs as results/..., on any machine
bin=.venv/bin/lanefree
episodes=${1:-50}
base=results/varobs
finished=()  # every evaluated run of both comparisons, for the verdict
source scripts/evaluation-helper.sh

# compare ALGO SET_SWEEP REPORT: evaluate the vector runs of ALGO and the set runs of SET_SWEEP, report them
compare() {
    local algo=$1 sets=$2 report=$3 run runs=()
    for run in results/paper/runs/"$algo"_fields_zones_overtake_collision_d70_s{0,1,2} "$sets"/runs/*; do
        if [ -e "$run/model.zip" ]; then
            evaluate "$run" eval
            for density in 90 120; do
                evaluate "$run" "eval_d$density" --density "$density"
            done
            evaluate "$run" eval_onramp --scenario onramp
        fi
        if [ -s "$run/eval/episodes.csv" ]; then runs+=("$run"); finished+=("$run"); fi
    done
    # the set sweep's own summary and runs.csv, with the evaluations made since its driver wrote them
    if [ -f "$sets/sweep.yaml" ]; then "$bin" report "$sets" >/dev/null; fi
    [ ${#runs[@]} -gt 0 ] || { echo "$algo: no finished, evaluated run of the variable-dimension experiment"; return 0; }
    "$bin" report "${runs[@]}" --out "$report"
    "$bin" report "${runs[@]}" --eval eval eval_d90 eval_d120 eval_onramp --out "${report}_transfer"
}

compare ddpg "$base/set" "$base/report"
compare dqn "$base/set_dqn" "$base/report_dqn"
# the verdict once both observations have a finished run (a set run's config.yaml says `kind: set`)
if [ ${#finished[@]} -gt 0 ]; then
    sets=$( (grep -lx "  kind: set" "${finished[@]/%//config.yaml}" || true) | wc -l)
    if [ "$sets" -gt 0 ] && [ "$sets" -lt ${#finished[@]} ]; then
        "$bin" report "${finished[@]}" --out "$base/verdict" --compare >/dev/null
    fi
fi

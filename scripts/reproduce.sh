#!/usr/bin/env bash
# Issue 17's long runs, started and stopped the same way every session:
#
#   scripts/reproduce.sh start [PAPER_WORKERS]   the paper sweep (results/paper, 1 worker by default), the
#                                                set-encoder sweep of the variable-dimension experiment
#                                                (results/varobs/set) on another core, and a watcher that runs
#                                                scripts/update-results.sh whenever a run finishes
#   scripts/reproduce.sh stop                    SIGTERM to both sweep drivers (every run saves a checkpoint) and
#                                                the watcher; waits until they are gone
#   scripts/reproduce.sh status                  lanefree sweep --status of each sweep (with the time left)
#
# The sweeps run the code of a git worktree pinned at HEAD (.worktrees/<commit>), so editing, committing or
# switching branches in this checkout never changes the code of runs in flight; they write into this checkout's
# results/. Never `git stash` or `git checkout` files under results/ while they run, and stop before editing
# scripts/update-results.sh or scripts/varobs-transfer.sh (the watcher runs them from this checkout). Logs and process ids go to
# .worktrees/logs/. Resumable: `start` after a stop (or a reboot) continues every partial run from its checkpoint.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
cd "$root"
state=$root/.worktrees
logs=$state/logs
python=$root/.venv/bin/python
mkdir -p "$logs"

alive() { [ -s "$1" ] && kill -0 "$(cat "$1")" 2>/dev/null; }

start() {
    local workers=${1:-1}
    for name in paper varobs watcher; do
        if alive "$logs/$name.pid"; then echo "already running: $name (pid $(cat "$logs/$name.pid")); stop first"; exit 2; fi
    done
    local commit tree
    commit=$(git rev-parse --short HEAD)
    tree=$state/$commit
    for old in "$state"/*/; do  # nothing runs: earlier pinned trees can go
        [ "${old%/}" = "$tree" ] || [ "${old%/}" = "$logs" ] || git worktree remove --force "${old%/}" 2>/dev/null || true
    done
    [ -d "$tree" ] || git worktree add --detach "$tree" HEAD >/dev/null
    local cli=(env PYTHONPATH="$tree" "$python" -c "import sys; from lanefree_sumo.cli import main; sys.exit(main())")
    cd "$tree"
    # the paper sweep, every setting of Tables 5-8 with 3 seeds; its pid is the sweep driver's
    if [ -f "$root/results/paper/sweep.yaml" ]; then
        nohup "${cli[@]}" sweep --resume "$root/results/paper" --workers "$workers" --no-progress >>"$logs/paper.log" 2>&1 &
    else
        nohup "${cli[@]}" sweep paper --seeds 3 --out "$root/results/paper" --workers "$workers" --no-progress \
            >>"$logs/paper.log" 2>&1 &
    fi
    echo $! >"$logs/paper.pid"
    # part 3 on the other core: the set-encoder runs (the vector baseline is the paper sweep's fzoc/70 cells)
    if [ -f "$root/results/varobs/set/sweep.yaml" ]; then
        nohup "${cli[@]}" sweep --resume "$root/results/varobs/set" --workers 1 --no-progress >>"$logs/varobs.log" 2>&1 &
    else
        nohup "${cli[@]}" sweep "$root/results/varobs/set_paper.yaml" --out "$root/results/varobs/set" --workers 1 \
            --no-progress >>"$logs/varobs.log" 2>&1 &
    fi
    echo $! >"$logs/varobs.pid"
    cd "$root"
    # the watcher (its own process group): evaluations and tables whenever the set of finished models changes
    setsid nohup bash -c '
        set -o pipefail
        last=""
        while true; do
            now=$(ls results/paper/runs/*/model.zip results/varobs/*/runs/*/model.zip 2>/dev/null | md5sum)
            if [ "$now" != "$last" ]; then
                echo "$(date -Is) update-results"
                scripts/update-results.sh 2>&1 | grep -v "^not in the summary\|^skipped\|^evaluate:" && last=$now
            fi
            sleep 300
        done' >>"$logs/watcher.log" 2>&1 &
    echo $! >"$logs/watcher.pid"
    echo "started at $commit (code in $tree): paper sweep ($workers worker(s)), set-encoder sweep, watcher; logs in $logs"
}

stop() {
    # a sweep driver stops its runs with a checkpoint on SIGTERM: signal the drivers only, never their workers
    if alive "$logs/paper.pid"; then kill -TERM "$(cat "$logs/paper.pid")" || true; fi
    if alive "$logs/varobs.pid"; then kill -TERM "$(cat "$logs/varobs.pid")" || true; fi
    # the watcher's whole group: an evaluation in flight leaves nothing behind (evaluate writes its folder at the end)
    if alive "$logs/watcher.pid"; then kill -TERM -- "-$(cat "$logs/watcher.pid")" || true; fi
    for name in paper varobs watcher; do
        while alive "$logs/$name.pid"; do sleep 2; done
        rm -f "$logs/$name.pid"
    done
    echo "stopped; every run saved a checkpoint (continue with: scripts/reproduce.sh start)"
}

status() {
    for folder in results/paper results/varobs/set; do
        [ -f "$folder/sweep.yaml" ] && .venv/bin/lanefree sweep --status "$folder" | sed -n '1,5p'
        echo
    done
    for name in paper varobs watcher; do
        alive "$logs/$name.pid" && echo "$name: running (pid $(cat "$logs/$name.pid"))" || echo "$name: not running"
    done
}

case ${1:-} in
    start) start "${2:-1}" ;;
    stop) stop ;;
    status) status ;;
    *) echo "usage: scripts/reproduce.sh start [PAPER_WORKERS] | stop | status"; exit 2 ;;
esac

#!/usr/bin/env bash
# Issue 17's long runs, started and stopped the same way every session:
#
#   scripts/reproduce.sh start [PAPER_WORKERS]   the paper sweep (results/paper) on PAPER_WORKERS cores (1 by
#                                                default; 0 leaves it stopped), the set-encoder sweep of the
#                                                variable-dimension experiment (results/varobs/set) on the
#                                                cores left (none left: not started; a later `start` with
#                                                fewer paper workers resumes it), and a watcher that runs
#                                                scripts/update-results.sh whenever a run finishes
#   scripts/reproduce.sh stop                    SIGTERM to both sweep drivers (every run saves a checkpoint) and
#                                                the watcher; waits until they are gone
#   scripts/reproduce.sh status                  lanefree sweep --status of each sweep (with the time left)
#
# The sweeps run the code of a git worktree pinned at HEAD (.worktrees/<commit>), so editing, committing or
# switching branches in this checkout never changes the code of runs in flight; they write into this checkout's
# results/; the watcher's evaluations use the pinned code too, but its scripts are this checkout's: stop before
# editing scripts/*.sh. Never `git stash` or `git checkout` files under results/ while they run. Logs and process ids go to
# .worktrees/logs/. Resumable: `start` after a stop (or a reboot) continues every partial run from its checkpoint.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
cd "$root"
state=$root/.worktrees
logs=$state/logs
python=$root/.venv/bin/python
marker="lanefree-reproduce $state"  # in the command line of every process started here
cores=$(env -u OMP_NUM_THREADS -u OMP_THREAD_LIMIT nproc)  # the cores this process may use (nproc obeys OMP_*)
mkdir -p "$logs"

# alive NAME: the process in $logs/NAME.pid runs and is ours (its command line names this checkout's pinned
# trees), not another that got the pid of one gone since (after a reboot)
alive() {
    local file=$logs/$1.pid pid
    [ -s "$file" ] || return 1
    pid=$(cat "$file")
    kill -0 "$pid" 2>/dev/null && tr '\0' ' ' <"/proc/$pid/cmdline" 2>/dev/null | grep -q -- "$marker"
}

start() {
    local workers=${1:-1}
    if ! [[ $workers =~ ^(0|[1-9][0-9]{0,3})$ ]] || [ "$workers" -gt "$cores" ]; then  # no leading 0: octal in $((…))
        echo "reproduce.sh: PAPER_WORKERS must be a whole number from 0 to $cores (the cores), got '$workers'" >&2
        exit 2
    fi
    for name in paper varobs watcher; do
        if alive "$name"; then echo "already running: $name (pid $(cat "$logs/$name.pid")); stop first"; exit 2; fi
        rm -f "$logs/$name.pid" "$logs/stopping"
    done
    local commit tree
    commit=$(git rev-parse --short HEAD)
    tree=$state/$commit
    for old in "$state"/*/; do  # nothing runs: earlier pinned trees can go
        [ "${old%/}" = "$tree" ] || [ "${old%/}" = "$logs" ] || git worktree remove --force "${old%/}" 2>/dev/null || true
    done
    git worktree prune
    [ -d "$tree" ] || git worktree add --detach "$tree" HEAD >/dev/null
    # the marker rides along as an ignored argument of python -c, so `alive` can recognise the process
    local cli=(env PYTHONPATH="$tree" "$python" -c "import sys; del sys.argv[1]; from lanefree_sumo.cli import main; \
sys.exit(main())" "$marker")
    cd "$tree"
    # the paper sweep, every setting of Tables 5-8 with 3 seeds; its pid is the sweep driver's
    local paper="paper sweep ($workers worker(s))"
    if [ "$workers" -eq 0 ]; then
        paper="no paper sweep (0 workers asked for)"
    elif [ -f "$root/results/paper/sweep.yaml" ]; then
        nohup "${cli[@]}" sweep --resume "$root/results/paper" --workers "$workers" --no-progress >>"$logs/paper.log" 2>&1 &
        echo $! >"$logs/paper.pid"
    else
        nohup "${cli[@]}" sweep paper --seeds 3 --out "$root/results/paper" --workers "$workers" --no-progress \
            >>"$logs/paper.log" 2>&1 &
        echo $! >"$logs/paper.pid"
    fi
    # part 3 on the cores left: the set-encoder runs (the vector baseline is the paper sweep's fzoc/70 cells);
    # never more runs than cores
    local set_workers=$((cores - workers)) varobs
    if [ "$set_workers" -eq 0 ]; then
        varobs="no set-encoder sweep (no core left)"
    else
        varobs="set-encoder sweep ($set_workers worker(s))"
        if [ -f "$root/results/varobs/set/sweep.yaml" ]; then
            nohup "${cli[@]}" sweep --resume "$root/results/varobs/set" --workers "$set_workers" --no-progress \
                >>"$logs/varobs.log" 2>&1 &
        else
            nohup "${cli[@]}" sweep "$root/results/varobs/set_paper.yaml" --out "$root/results/varobs/set" \
                --workers "$set_workers" --no-progress >>"$logs/varobs.log" 2>&1 &
        fi
        echo $! >"$logs/varobs.pid"
    fi
    cd "$root"
    # the watcher (its own process group, the pinned code too): evaluations and tables whenever the set of
    # finished models changes
    PYTHONPATH=$tree setsid nohup bash -c '
        set -o pipefail
        last=""
        while true; do
            now=$(ls results/paper/runs/*/model.zip results/varobs/*/runs/*/model.zip 2>/dev/null | md5sum)
            if [ "$now" != "$last" ]; then
                echo "$(date -Is) update-results"
                scripts/update-results.sh 2>&1 | grep -v "^not in the summary\|^skipped\|^evaluate:" && last=$now
            fi
            sleep 300
        done' "$marker" >>"$logs/watcher.log" 2>&1 &
    echo $! >"$logs/watcher.pid"
    echo "started at $commit (code in $tree): $paper, $varobs, watcher; logs in $logs"
}

stop() {
    # a sweep driver stops its runs with a checkpoint on the first SIGTERM and kills them on a second one:
    # signal each driver once (a second `stop` only waits), never their workers
    if [ ! -e "$logs/stopping" ]; then
        touch "$logs/stopping"
        if alive paper; then kill -TERM "$(cat "$logs/paper.pid")" || true; fi
        if alive varobs; then kill -TERM "$(cat "$logs/varobs.pid")" || true; fi
        # the watcher's whole group; an evaluation stopped part-way is run again whole next time
        if alive watcher; then kill -TERM -- "-$(cat "$logs/watcher.pid")" || true; fi
    fi
    for name in paper varobs watcher; do
        if alive "$name"; then echo "waiting for $name (pid $(cat "$logs/$name.pid")) to save its checkpoints and stop"; fi
        while alive "$name"; do sleep 2; done
        rm -f "$logs/$name.pid"
    done
    rm -f "$logs/stopping"
    echo "stopped; every run saved a checkpoint (continue with: scripts/reproduce.sh start)"
}

status() {
    for folder in results/paper results/varobs/set; do
        if [ -f "$folder/sweep.yaml" ]; then .venv/bin/lanefree sweep --status "$folder" | sed -n '1,5p' || true; fi
        echo
    done
    for name in paper varobs watcher; do
        if alive "$name"; then echo "$name: running (pid $(cat "$logs/$name.pid"))"; else echo "$name: not running"; fi
    done
}

case ${1:-} in
    start) start "${2:-1}" ;;
    stop) stop ;;
    status) status ;;
    *) echo "usage: scripts/reproduce.sh start [PAPER_WORKERS] | stop | status"; exit 2 ;;
esac

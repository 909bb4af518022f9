#!/usr/bin/env bash
# The long result runs, started and stopped the same way every time:
#
#   scripts/reproduce.sh start [PAPER_WORKERS]   the paper sweep (results/paper) on PAPER_WORKERS cores (1 by
#                                                default; 0 leaves it stopped), the set-encoder sweeps of the
#                                                variable-dimension experiment at the same time on the cores
#                                                left, in order of priority, each on as many as it has runs to
#                                                train: DDPG (results/varobs/set), then DQN (results/varobs/set_dqn,
#                                                Liu et al.'s own Q-network) (no core left: not started; a later
#                                                `start` resumes it), and a watcher that runs
#                                                scripts/update-results.sh whenever a run finishes
#   scripts/reproduce.sh stop                    SIGTERM to every sweep driver (every run saves a checkpoint) and
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
drivers="paper varobs varobs_dqn"  # the sweep drivers' names in $logs/NAME.pid, NAME.log
processes="$drivers watcher"
usage="usage: scripts/reproduce.sh start [PAPER_WORKERS] | stop | status"
case ${1:-} in  # before anything is written
    start | stop | status) ;;
    "") echo "reproduce.sh: no command given; $usage" >&2; exit 2 ;;
    *) echo "reproduce.sh: unknown command '$1'; $usage" >&2; exit 2 ;;
esac
mkdir -p "$logs"

# alive NAME: the process in $logs/NAME.pid runs and is ours (its command line names this checkout's pinned
# trees), not another that got the pid of one gone since (after a reboot)
alive() {
    local file=$logs/$1.pid pid
    [ -s "$file" ] || return 1
    pid=$(cat "$file")
    kill -0 "$pid" 2>/dev/null && tr '\0' ' ' <"/proc/$pid/cmdline" 2>/dev/null | grep -q -- "$marker"
}

# runs_to_do FOLDER GRID: the runs of the sweep in FOLDER that a resume would train (running, partial, stale,
# pending or failed; not complete, busy elsewhere or damaged), from its status; before it begins, every run of
# GRID. Fails when neither can be read. Needs $cli and $python (the pinned code).
runs_to_do() {
    if [ -f "$1/sweep.yaml" ]; then
        "${cli[@]}" sweep --status "$1" | awk '/^runs: [0-9]+ complete/ { seen = 1
            for (i = 2; i < NF; i += 2) if ($(i + 1) ~ /^(running|partial|stale|pending|failed),?$/) todo += $i }
            END { if (!seen) exit 1; print todo + 0 }'
    else
        PYTHONPATH=$tree "$python" -c "import sys; from lanefree_sumo.experiments.sweep.grid import load_grid; \
print(len(load_grid(sys.argv[1]).cells()))" "$2" 2>/dev/null  # unreadable: the caller says so in one line
    fi
}

start() {
    local workers=${1:-1}
    if ! [[ $workers =~ ^(0|[1-9][0-9]{0,3})$ ]] || [ "$workers" -gt "$cores" ]; then  # no leading 0: octal in $((…))
        echo "reproduce.sh: PAPER_WORKERS must be a whole number from 0 to $cores (the cores), got '$workers'" >&2
        exit 2
    fi
    for name in $processes; do
        if alive "$name"; then echo "reproduce.sh: already running: $name (pid $(cat "$logs/$name.pid")); stop first" >&2; exit 2; fi
        rm -f "$logs/$name.pid" "$logs/stopping"
    done
    local commit tree old
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
    # the paper sweep, every setting of Tables 5-8 with the paper's 10 seeds; its pid is the sweep driver's
    local paper="paper sweep ($workers worker(s))"
    if [ "$workers" -eq 0 ]; then
        paper="no paper sweep (0 workers asked for)"
    elif [ -f "$root/results/paper/sweep.yaml" ]; then
        nohup "${cli[@]}" sweep --resume "$root/results/paper" --workers "$workers" --no-progress >>"$logs/paper.log" 2>&1 &
        echo $! >"$logs/paper.pid"
    else
        nohup "${cli[@]}" sweep paper --out "$root/results/paper" --workers "$workers" --no-progress \
            >>"$logs/paper.log" 2>&1 &
        echo $! >"$logs/paper.pid"
    fi
    # part 3 on the cores left, never more runs than cores: the set-encoder sweeps in order of priority, at the
    # same time, each on as many of the cores left as it has runs to do (their vector baselines are the paper
    # sweep's own fzoc/70 cells)
    local left=$((cores - workers)) varobs="" sweep name folder grid label todo n
    for sweep in "varobs results/varobs/set set_paper.yaml set-encoder sweep" \
                 "varobs_dqn results/varobs/set_dqn set_dqn_paper.yaml DQN set-encoder sweep"; do
        read -r name folder grid label <<<"$sweep"
        if ! todo=$(runs_to_do "$root/$folder" "$root/results/varobs/$grid"); then
            echo "reproduce.sh: cannot count the runs left in $folder; giving it every core left" >&2
            todo=$cores
        fi
        n=$((todo < left ? todo : left))
        if [ "$n" -eq 0 ]; then
            if [ "$todo" -eq 0 ]; then varobs+="no $label (no run left to train), "; else varobs+="no $label (no core left), "; fi
            continue
        fi
        varobs+="$label ($n worker(s)), "
        left=$((left - n))
        if [ -f "$root/$folder/sweep.yaml" ]; then
            nohup "${cli[@]}" sweep --resume "$root/$folder" --workers "$n" --no-progress >>"$logs/$name.log" 2>&1 &
        else
            nohup "${cli[@]}" sweep "$root/results/varobs/$grid" --out "$root/$folder" --workers "$n" --no-progress \
                >>"$logs/$name.log" 2>&1 &
        fi
        echo $! >"$logs/$name.pid"
    done
    varobs=${varobs%, }
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
    local running="" name
    for name in $processes; do
        if alive "$name"; then running+="$name "; fi
    done
    if [ -z "$running" ]; then
        rm -f "$logs/stopping"
        echo "nothing to stop: no sweep driver and no watcher of this checkout is running"
        return 0
    fi
    # a sweep driver stops its runs with a checkpoint on the first SIGTERM and kills them on a second one:
    # signal each driver once (a second `stop` only waits), never their workers
    if [ ! -e "$logs/stopping" ]; then
        touch "$logs/stopping"
        for name in $drivers; do
            if alive "$name"; then kill -TERM "$(cat "$logs/$name.pid")" || true; fi
        done
        # the watcher's whole group; an evaluation stopped part-way is run again whole next time
        if alive watcher; then kill -TERM -- "-$(cat "$logs/watcher.pid")" || true; fi
    fi
    for name in $processes; do
        if alive "$name"; then echo "waiting for $name (pid $(cat "$logs/$name.pid")) to save its checkpoints and stop"; fi
        while alive "$name"; do sleep 2; done
        rm -f "$logs/$name.pid"
    done
    rm -f "$logs/stopping"
    echo "stopped; every run saved a checkpoint (continue with: scripts/reproduce.sh start)"
}

status() {
    for folder in results/paper results/varobs/set results/varobs/set_dqn; do
        if [ -f "$folder/sweep.yaml" ]; then .venv/bin/lanefree sweep --status "$folder" | sed -n '1,5p' || true; fi
        echo
    done
    for name in $processes; do
        if alive "$name"; then echo "$name: running (pid $(cat "$logs/$name.pid"))"; else echo "$name: not running"; fi
    done
}

case ${1:-} in
    start) start "${2:-1}" ;;
    stop) stop ;;
    status) status ;;
esac

"""The body of one Ray task: train (or resume, or extend) ONE run of a sweep in this process.

Ray starts a fresh worker process for every task (``max_calls=1``: libsumo runs one simulation
per process) and retries the task when that process dies; a retry finds the run folder as the
dead worker left it and continues from its newest checkpoint (``train(resume=True)`` cuts
``episodes.csv`` back to the checkpoint, so no episode is duplicated). A run folder without a
checkpoint restarts from scratch, as ``lanefree train`` itself does. ``ray.cancel`` (the driver's
Ctrl-C) raises SIGINT's handler in the task: ``train()`` then saves a checkpoint and returns.

Everything the task prints goes to ``DIR/logs/<run>.log``. The task returns a plain dict (see
:func:`run_cell`); it raises only when something outside the run is broken.
"""

from __future__ import annotations

import os
import shutil
import socket
import sys
import time
import traceback
from pathlib import Path
from typing import Any

from lanefree_sumo.errors import LaneFreeError, RunError
from lanefree_sumo.experiments.sweep.manifest import SweepDir
from lanefree_sumo.experiments.sweep.state import (
    COMPLETE,
    DAMAGED,
    PENDING,
    STALE,
    Heartbeat,
    clear_failure,
    inspect_run,
    record_failure,
    run_lock,
    writers_elsewhere,
)


def config_difference(existing: Any, expected: Any) -> str | None:
    """First key (dotted) where two configs differ, ignoring ``train.episodes`` (a run may be
    extended), the keys that do not change results (:data:`~lanefree_sumo.config.SAME_RESULTS`:
    a run trained on libsumo is a run of the same setting as one on numpy) and the hyperparameters
    the algorithm never reads (:func:`~lanefree_sumo.rl.algorithms.unused_config`: a DDPG run
    never reads ``train.dqn`` nor ``train.actor_critic.ppo_n_steps``); ``key = saved vs expected``, or
    None."""
    from lanefree_sumo.config import SAME_RESULTS, config_to_dict
    from lanefree_sumo.rl.algorithms import unused_config

    unused = unused_config(expected.train.algo)

    def walk(a: Any, b: Any, path: str) -> str | None:
        if isinstance(a, dict) and isinstance(b, dict):
            for key in list(b) + [k for k in a if k not in b]:
                where = f"{path}.{key}" if path else key
                if where == "train.episodes" or where in SAME_RESULTS or where in unused:
                    continue
                found = walk(a.get(key, "<missing>"), b.get(key, "<missing>"), where)
                if found:
                    return found
            return None
        return None if a == b else f"{path} = {a!r} in the folder vs {b!r} in the grid"

    return walk(config_to_dict(existing), config_to_dict(expected), "")


def check_adoptable(folder: Path, expected: Any) -> None:
    """RunError unless existing run folder ``folder`` is a run of ``expected`` (the same config;
    at most as many episodes): a sweep adopts such folders, started by it or by hand."""
    from lanefree_sumo.experiments.storage.rundir import read_config

    if not (folder / "config.yaml").is_file():
        raise RunError(f"{folder} exists but is not a run folder (no config.yaml); move it away or choose "
                       "another --out")
    existing = read_config(folder)
    diff = config_difference(existing, expected)
    if diff is not None:
        raise RunError(f"{folder} holds a run of another config ({diff}); move it away or choose another --out")
    if existing.train.episodes > expected.train.episodes:
        raise RunError(f"{folder} is a run of {existing.train.episodes} episodes but the grid asks for "
                       f"{expected.train.episodes}; use the same --episodes or another --out")


def _finish_from_checkpoint(folder: Path, target: int) -> bool:
    """A run killed between its final checkpoint and writing model.zip: finish it from that
    checkpoint (its model IS the final model). True when done."""
    from lanefree_sumo.experiments.storage.episodes import EpisodeLog
    from lanefree_sumo.experiments.storage.rundir import RunDir

    run = RunDir(folder)
    try:
        ckpt = run.newest_checkpoint()
    except RunError:
        return False
    if ckpt.episodes < target or run.load_config().train.episodes != target:
        return False
    EpisodeLog.truncate(run.episodes, target)
    tmp = run.model.with_name(f".{run.model.name}.tmp")
    shutil.copyfile(ckpt.model, tmp)
    os.replace(tmp, run.model)
    print(f"finished from checkpoint {ckpt.path.name} (the process died before writing model.zip)", flush=True)
    return True


def train_cell(folder: Path, config: dict[str, Any], target: int, command: str) -> None:
    """Bring run ``folder`` to ``target`` episodes: start, resume, extend or finish it."""
    from lanefree_sumo.config import LaneFreeConfig, merge_config
    from lanefree_sumo.experiments.runners.train import train
    from lanefree_sumo.experiments.storage.rundir import read_config

    expected = merge_config(LaneFreeConfig(), config)
    info = inspect_run(folder, target)
    if info.state == COMPLETE:
        return
    if info.state == DAMAGED:
        raise RunError(f"{folder}: {info.detail}")
    if info.state != PENDING:
        check_adoptable(folder, expected)
    if info.state == STALE:
        print(f"{folder.name}: no checkpoint ({info.episodes} episode rows); starting from scratch", flush=True)
        shutil.rmtree(folder)
    elif info.state != PENDING:
        if _finish_from_checkpoint(folder, target):
            return
        saved = read_config(folder).train.episodes
        print(f"{folder.name}: {info.detail}", flush=True)
        train(LaneFreeConfig(), run=folder, resume=True, progress=False, command=command,
              episodes=target if saved != target else None)
        return
    train(expected, run=folder, progress=False, command=command)


def run_cell(out: str, name: str, config: dict[str, Any], target: int, command: str) -> dict[str, Any]:
    """Ray task: train run ``name`` of sweep folder ``out``. Returns ``{"name", "status", "episodes",
    "detail", "host", "pid", "wall_s"}`` with status ``complete``, ``interrupted`` (stopped by
    Ctrl-C/SIGTERM with a checkpoint), ``failed`` (reason in detail, also on file) or ``busy``
    (another process has the run)."""
    sweep = SweepDir(Path(out))
    folder = sweep.run(name)
    t0 = time.monotonic()
    result: dict[str, Any] = {"name": name, "status": "failed", "episodes": 0, "detail": "",
                              "host": socket.gethostname(), "pid": os.getpid(), "wall_s": 0.0}
    _redirect_output(sweep.log(name))
    node = _node_id()
    print(f"\n=== {time.strftime('%Y-%m-%d %H:%M:%S')} run {name} on host {result['host']} pid {os.getpid()} "
          f"node {node}", flush=True)
    with run_lock(sweep, name) as held:
        holders = writers_elsewhere(folder / "episodes.csv")
        if not held or holders:
            who = f"process {holders[0]}" if holders else "another sweep worker"
            result.update(status="busy", detail=f"{folder} is being trained by {who}")
            print(result["detail"], flush=True)
            return result
        beat = Heartbeat(sweep, name, {"node": node})
        try:
            clear_failure(sweep, name)
            train_cell(folder, config, target, f"{command}  # sweep worker on {result['host']} pid {os.getpid()}")
            info = inspect_run(folder, target)
            result["episodes"] = info.episodes
            if info.state == COMPLETE:
                result["status"] = "complete"
            elif info.state == DAMAGED:
                result["detail"] = info.detail
            else:
                result.update(status="interrupted", detail=f"stopped at {info.episodes}/{target} episodes")
        except KeyboardInterrupt:
            result.update(status="interrupted", detail="stopped before training began")
        except LaneFreeError as exc:
            result["detail"] = " ".join(str(exc).split())
        except Exception as exc:  # a bug or a broken environment: the traceback goes to the log
            traceback.print_exc()
            result["detail"] = f"{type(exc).__name__}: {' '.join(str(exc).split())[:300]} (see {sweep.log(name)})"
        finally:
            beat.stop()
        if result["status"] == "failed":
            record_failure(sweep, name, result["detail"])
        result["wall_s"] = round(time.monotonic() - t0, 1)
        print(f"=== {result['status']}: {result['detail'] or name} ({result['wall_s']} s)", flush=True)
        return result


def _redirect_output(path: Path) -> None:
    """Send this process's stdout and stderr (file descriptors too: SUMO writes there) to ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    sys.stdout.flush()
    sys.stderr.flush()
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    os.close(fd)


def _node_id() -> str:
    """The Ray node this task runs on; ``-`` outside Ray (``sweep --no-ray``, tests calling run_cell directly).
    Ray is asked only when it is running: its runtime context starts a local Ray where none is."""
    ray = sys.modules.get("ray")
    if ray is None or not ray.is_initialized():
        return "-"
    return str(ray.get_runtime_context().get_node_id())[:12]


def probe(out: str, token: str) -> dict[str, Any]:
    """Ray task run once on every node before a cluster sweep: can this node import lanefree_sumo,
    see the driver's sweep folder (the token file the driver wrote) and write into it?"""
    from importlib.metadata import version

    host = socket.gethostname()
    sweep = SweepDir(Path(out))
    answer: dict[str, Any] = {"host": host, "node": _node_id(), "ok": False, "version": version("lanefree_sumo")}
    try:
        seen = (sweep.state / f"probe-{token}").read_text().strip()
    except OSError as exc:
        answer["detail"] = f"does not see {out} ({exc.strerror or exc}); --out must be storage every node mounts"
        return answer
    if seen != token:
        answer["detail"] = f"sees another {out} than the driver; --out must be storage every node mounts"
        return answer
    probe_file = sweep.runs / f".probe-{token}-{answer['node']}"
    try:
        sweep.runs.mkdir(parents=True, exist_ok=True)
        probe_file.write_text("ok\n")
        probe_file.unlink()
    except OSError as exc:
        answer["detail"] = f"cannot write {sweep.runs} ({exc.strerror or exc})"
        return answer
    answer["ok"] = True
    return answer

"""The Ray driver of a sweep: one task per run, one progress bar, a clean Ctrl-C.

* **Embedded** (default): ``ray.init`` starts a private local Ray with ``workers`` CPUs, every
  process bound to 127.0.0.1, token authentication with a fresh random token, no dashboard, no
  usage statistics. It stops with the command.
* **Cluster** (``--address HOST:PORT`` or ``RAY_ADDRESS``): the driver joins an existing cluster;
  before any run starts, a probe task on every node checks that it can import lanefree_sumo,
  sees the driver's sweep folder and can write into it (``--out`` must be shared storage).

Each run is one task with ``num_cpus`` = its environments (1 by default; torch uses one thread,
``train.torch_threads``), ``max_calls=1`` (a fresh process per run: libsumo runs one simulation
per process) and ``max_retries`` (a worker that dies is retried; the retry resumes from the
run's newest checkpoint, :mod:`.worker`); a batch of runs (:mod:`.batches`) is one such task with one CPU,
whose retry resumes from the batch's newest checkpoint. Ctrl-C or SIGTERM on the driver cancels the tasks
without force: Ray raises SIGINT's handler in each running task, ``train()`` saves a checkpoint
and returns; a second Ctrl-C (or :data:`STOP_TIMEOUT_S`) kills what is left, which then resumes
from its latest periodic checkpoint next time.
"""

from __future__ import annotations

import contextlib
import logging
import os
import secrets
import signal
import socket
import sys
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

from lanefree_sumo.config import config_to_dict
from lanefree_sumo.errors import RunError, UsageError
from lanefree_sumo.experiments.storage.rundir import write_atomic
from lanefree_sumo.experiments.sweep.batches import Batch
from lanefree_sumo.experiments.sweep.grid import Cell, Grid
from lanefree_sumo.experiments.sweep.manifest import SweepDir
from lanefree_sumo.experiments.sweep.state import STALE_S, count_rows, heartbeat_age, record_failure

POLL_S = 2.0
"""Progress refresh interval (s)."""
STOP_TIMEOUT_S = 180.0
"""How long Ctrl-C waits for running runs to save their checkpoint (s)."""
PROBE_TIMEOUT_S = 300.0
"""How long the cluster check waits for every node to answer (s)."""
OBJECT_STORE_BYTES = 256 * 1024**2
"""Object store of the embedded Ray: tasks exchange only small dicts."""
LOOPBACK = ("127.0.0.1", "localhost", "::1")


@dataclass
class SweepOutcome:
    """What a driver session did."""

    results: dict[str, dict[str, Any]] = field(default_factory=dict)
    """Per run name: the task's result dict (status complete / interrupted / failed / busy / cancelled)."""
    interrupted: bool = False


def parse_address(address: str) -> tuple[str, int]:
    """``HOST:PORT`` → (host, port); UsageError otherwise."""
    host, sep, port = address.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise UsageError(f"--address must be HOST:PORT of a Ray head node (e.g. 10.0.0.5:6379), got {address!r}")
    return host.strip("[]"), int(port)


def check_address(address: str) -> None:
    """UsageError unless something listens at ``HOST:PORT`` (before anything is written)."""
    host, port = parse_address(address)
    try:
        socket.create_connection((host, port), timeout=10).close()
    except OSError as exc:
        raise UsageError(f"no Ray head node answers at {address} ({exc.strerror or exc}); start one with "
                         f"'ray start --head --port {port}' or check --address / RAY_ADDRESS") from None


def _prepare_environment(address: str | None) -> None:
    """Environment variables Ray reads when it is imported and passes to every process it starts."""
    os.environ["RAY_USAGE_STATS_ENABLED"] = "0"  # never report usage to anyone
    if address is None or parse_address(address)[0] in LOOPBACK:
        # Ray turns 127.0.0.1 into the host's outward address unless clusters are "disabled"; this
        # keeps every server, and the driver's own, on the loopback interface.
        os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"
    if address is None and not any(k in os.environ for k in ("RAY_AUTH_MODE", "RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH")):
        os.environ["RAY_AUTH_MODE"] = "token"  # a private cluster: a fresh token, not written to disk
        os.environ["RAY_AUTH_TOKEN"] = secrets.token_hex(16)


def start_ray(workers: int | None, address: str | None, gpus: int = 0) -> Any:
    """``ray`` connected to a new embedded Ray (``address`` None; ``gpus``: the GPUs it may hand out) or to the
    cluster at ``address``."""
    _prepare_environment(address)
    try:
        import ray
    except ImportError as exc:
        raise UsageError(f"'lanefree sweep' needs Ray ({exc}); pip install -e '.[rl]'") from None
    common: dict[str, Any] = {"log_to_driver": False, "logging_level": logging.WARNING}
    if address is None:
        try:
            ray.init(address="local", num_cpus=workers, num_gpus=gpus, include_dashboard=False,
                     object_store_memory=OBJECT_STORE_BYTES, **common)
        except Exception as exc:  # a node that timed out starting (an overloaded machine), no room for its files
            reason = " ".join(str(exc).split())[:300]
            raise RunError(f"the embedded Ray did not start ({type(exc).__name__}: {reason}); nothing was trained: "
                           "rerun the same command (it resumes) once that is mended (a timeout: when the machine "
                           "is less loaded)") from None
        return ray
    check_address(address)
    try:
        ray.init(address=address, **common)
    except Exception as exc:  # ConnectionError, AuthenticationError, version mismatch, ...
        reason = " ".join(str(exc).split())[:300]
        raise UsageError(f"cannot join the Ray cluster at {address} ({type(exc).__name__}: {reason})") from None
    return ray


def cluster_cpus(ray: Any) -> int:
    return int(ray.cluster_resources().get("CPU", 0))


def cluster_size(address: str) -> int:
    """The CPUs of the Ray cluster at ``address``, read over a short connection (the default batch size keeps
    them all busy)."""
    ray = start_ray(None, address)
    try:
        return cluster_cpus(ray)
    finally:
        ray.shutdown()


def check_nodes(ray: Any, sweep: SweepDir) -> list[dict[str, Any]]:
    """Run :func:`.worker.probe` on every alive node with CPUs; UsageError naming the first node
    that cannot import lanefree_sumo, see the sweep folder or write into it."""
    from importlib.metadata import version

    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    from lanefree_sumo.experiments.sweep.worker import probe

    token = uuid.uuid4().hex
    token_file = sweep.state / f"probe-{token}"
    write_atomic(token_file, token + "\n")
    remote = ray.remote(num_cpus=0, max_calls=1, max_retries=0)(probe)
    nodes = [n for n in ray.nodes() if n.get("Alive") and n.get("Resources", {}).get("CPU", 0) > 0]
    if not nodes:
        raise UsageError("the Ray cluster has no alive node with CPUs")
    refs = {remote.options(scheduling_strategy=NodeAffinitySchedulingStrategy(n["NodeID"], soft=False))
            .remote(str(sweep.path), token): n for n in nodes}
    answers = []
    try:
        for ref, node in refs.items():
            where = f"{node.get('NodeManagerAddress', '?')} (node {node['NodeID'][:12]})"
            try:
                answer = ray.get(ref, timeout=PROBE_TIMEOUT_S)
            except Exception as exc:
                reason = " ".join(str(exc).split()[-30:])[:300]
                raise UsageError(f"worker node {where} cannot run lanefree_sumo tasks ({type(exc).__name__}: "
                                 f"{reason}); install the same lanefree_sumo on every node") from None
            if not answer["ok"]:
                raise UsageError(f"worker node {where} {answer['detail']}")
            mine = version("lanefree_sumo")
            if answer["version"] != mine:
                raise UsageError(f"worker node {where} has lanefree_sumo {answer['version']}, the driver {mine}; "
                                 "install the same version everywhere")
            answers.append(answer)
    finally:
        token_file.unlink(missing_ok=True)
    return answers


class Tracker:
    """Episodes done over all runs, polled from their episodes.csv (re-read only when changed)."""

    def __init__(self, sweep: SweepDir, names: list[str], target: int) -> None:
        self.sweep, self.names, self.target = sweep, names, target
        self._cache: dict[str, tuple[tuple[int, int], int]] = {}

    def episodes(self, names: list[str] | tuple[str, ...] | None = None) -> int:
        """Episodes done by ``names`` (default: every run)."""
        return sum(self.done(name) for name in (self.names if names is None else names))

    def done(self, name: str) -> int:
        """Episodes done by run ``name`` (at most the target)."""
        path = self.sweep.run(name) / "episodes.csv"
        try:
            st = path.stat()
        except OSError:
            return 0
        key = (st.st_size, st.st_mtime_ns)
        cached = self._cache.get(name)
        if cached is None or cached[0] != key:
            cached = (key, count_rows(path))
            self._cache[name] = cached
        return min(cached[1], self.target)

    def running(self, names: list[str]) -> int:
        return sum(1 for n in names if (age := heartbeat_age(self.sweep, n)) is not None and age < STALE_S)


def _one_line(exc: BaseException) -> str:
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    text = lines[-1] if lines else type(exc).__name__
    return f"{type(exc).__name__}: {text}"[:400]


def _collect(ray: Any, sweep: SweepDir, ref: Any, names: tuple[str, ...]) -> list[dict[str, Any]]:
    """The results of the task ``ref`` of runs ``names`` (one run, or a batch's runs)."""
    from ray.exceptions import RayError, TaskCancelledError

    try:
        answer = ray.get(ref)
        return [dict(r) for r in answer] if isinstance(answer, list) else [dict(answer)]
    except TaskCancelledError:
        return [{"name": name, "status": "cancelled", "detail": "cancelled before it started"} for name in names]
    except RayError as exc:  # the worker died more often than --retries allows, OOM, a node lost
        detail = f"{_one_line(exc)} (after all retries)"
        for name in names:
            record_failure(sweep, name, detail)
        return [{"name": name, "status": "failed", "detail": detail} for name in names]


def _batch_text(tracker: Tracker, batch: Batch) -> str:
    """A batch bar's postfix: each run's episodes, by its seed (``s3:120``) or its name where seeds repeat."""
    tails = [name.rsplit("_", 1)[-1] for name in batch.runs]
    labels = tails if len(set(tails)) == len(tails) else list(batch.runs)
    return " ".join(f"{label}:{tracker.done(name)}" for label, name in zip(labels, batch.runs))


def _raise_interrupt(_signum: int, _frame: Any) -> None:
    raise KeyboardInterrupt


def _batch_configs(grid: Grid, by_name: dict[str, Cell], batch: Batch) -> list[dict[str, Any]]:
    """The configs of ``batch``'s runs, as a batch task takes them."""
    return [config_to_dict(grid.config(by_name[name])) for name in batch.runs]


def run_tasks(ray: Any, sweep: SweepDir, grid: Grid, todo: list[Cell], retries: int, command: str,
              progress: bool, batches: list[Batch] | None = None) -> SweepOutcome:
    """Submit one task per cell of ``todo`` and one per batch of ``batches`` and wait for all of them with a
    progress bar over the episodes of the whole grid and one per batch (each run's episodes);
    Ctrl-C/SIGTERM stop the runs cleanly (module docstring)."""
    from tqdm import tqdm

    from lanefree_sumo.experiments.sweep.batches import run_batch
    from lanefree_sumo.experiments.sweep.worker import run_cell

    cells = grid.cells()
    by_name = {c.name: c for c in cells}
    target = grid.episodes
    batches = batches or []
    tracker = Tracker(sweep, [c.name for c in cells], target)
    task = ray.remote(max_calls=1, max_retries=retries, retry_exceptions=False)(run_cell)
    batch_task = ray.remote(max_calls=1, max_retries=retries, retry_exceptions=False)(run_batch)
    refs: dict[Any, tuple[str, ...]] = {}
    for cell in todo:
        cfg = grid.config(cell)
        refs[task.options(num_cpus=max(1, cfg.train.envs), name=f"lanefree-sweep:{cell.name}").remote(
            str(sweep.path), cell.name, config_to_dict(cfg), target, command)] = (cell.name,)
    for batch in batches:
        configs = _batch_configs(grid, by_name, batch)
        on_gpu = grid.config(by_name[batch.runs[0]]).train.device == "cuda"  # one batch per GPU at a time
        refs[batch_task.options(num_cpus=1, num_gpus=1 if on_gpu else 0, name=f"lanefree-sweep:{batch.name}").remote(
            str(sweep.path), batch.name, list(batch.runs), configs, target, command)] = batch.runs
    outcome = SweepOutcome()
    complete_before = len(cells) - len(todo) - sum(len(b.runs) for b in batches)
    tty = sys.stderr.isatty()
    common: dict[str, Any] = {"unit": "ep", "disable": not progress, "dynamic_ncols": True,
                              "mininterval": 1.0 if tty else 60.0, "smoothing": 0.05}
    bar = tqdm(total=len(cells) * target, initial=tracker.episodes(), desc="sweep", **common)
    batch_bars = [tqdm(total=len(b.runs) * target, initial=tracker.episodes(b.runs), desc=b.name, position=i + 1,
                       leave=False, **common) for i, b in enumerate(batches)]

    def refresh() -> None:
        done = complete_before + sum(1 for r in outcome.results.values() if r["status"] == "complete")
        failed = sum(1 for r in outcome.results.values() if r["status"] == "failed")
        waiting = [name for names in refs.values() for name in names]
        running = tracker.running(waiting)
        bar.update(tracker.episodes() - bar.n)
        bar.set_postfix_str(f"runs {done}/{len(cells)} done, {running} running, "
                            f"{len(waiting) - running} queued, {failed} failed", refresh=False)
        for batch, batch_bar in zip(batches, batch_bars):
            batch_bar.update(tracker.episodes(batch.runs) - batch_bar.n)
            batch_bar.set_postfix_str(_batch_text(tracker, batch), refresh=False)

    # Ctrl-C and SIGTERM stop the sweep, also when it was started with SIGINT ignored (a background job)
    previous = {sig: signal.signal(sig, _raise_interrupt) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        while refs:
            ready, _ = ray.wait(list(refs), num_returns=len(refs), timeout=POLL_S)
            for ref in ready:
                for result in _collect(ray, sweep, ref, refs.pop(ref)):
                    outcome.results[result["name"]] = result
                    if result["status"] != "complete":
                        bar.write(f"{result['name']}: {result['status']}: {result.get('detail', '')}")
            refresh()
    except KeyboardInterrupt:
        outcome.interrupted = True
        _stop(ray, sweep, refs, outcome, bar)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        refresh()
        for batch_bar in batch_bars:
            batch_bar.close()
        bar.close()
    return outcome


def stop_text(tasks: list[tuple[str, ...]]) -> str:
    """What a stop does to the unfinished ``tasks`` (each a run's name, or a batch's runs): counted in runs, and in
    tasks where a batch holds several."""
    runs = sum(len(names) for names in tasks)
    within = f" in {len(tasks)} task(s)" if runs != len(tasks) else ""
    return f"{runs} run(s){within}: those training save a checkpoint and stop, those queued do not start"


def _stop(ray: Any, sweep: SweepDir, refs: dict[Any, tuple[str, ...]], outcome: SweepOutcome, bar: Any) -> None:
    """Cancel every task (running ones save a checkpoint and return); force after a second Ctrl-C
    or :data:`STOP_TIMEOUT_S`."""
    bar.write(f"stopping: {stop_text(list(refs.values()))} (Ctrl-C again to kill them at once; they then resume "
              "from their previous checkpoint)")
    for ref in refs:
        try:
            ray.cancel(ref, force=False, recursive=False)
        except Exception:  # finished meanwhile
            pass
    deadline = time.monotonic() + STOP_TIMEOUT_S
    try:
        while refs and time.monotonic() < deadline:
            ready, _ = ray.wait(list(refs), num_returns=len(refs), timeout=1.0)
            for ref in ready:
                for result in _collect(ray, sweep, ref, refs.pop(ref)):
                    outcome.results[result["name"]] = result
    except KeyboardInterrupt:
        pass
    for ref, names in list(refs.items()):
        try:
            ray.cancel(ref, force=True, recursive=False)
        except Exception:
            pass
        for name in names:
            outcome.results[name] = {"name": name, "status": "interrupted", "detail": "killed while stopping"}
        refs.pop(ref)


@contextlib.contextmanager
def _own_output() -> Iterator[None]:
    """Within the block a task may send this process's stdout and stderr to its log; after it they are the
    driver's again."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    try:
        yield
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        os.close(saved[0])
        os.close(saved[1])


def run_in_process(sweep: SweepDir, grid: Grid, todo: list[Cell], command: str,
                   batches: list[Batch] | None = None) -> SweepOutcome:
    """``lanefree sweep --no-ray``: the batches, then the runs of ``todo``, one after another in this process, each
    as a Ray task would train it (:func:`~.batches.run_batch`, :func:`~.worker.run_cell`, their logs in
    ``DIR/logs``); one line per task as it ends. Ctrl-C/SIGTERM stop the task at hand with a checkpoint and
    start no other."""
    from lanefree_sumo.experiments.sweep.batches import run_batch
    from lanefree_sumo.experiments.sweep.worker import run_cell

    sweep = SweepDir(sweep.path.resolve())
    by_name = {c.name: c for c in grid.cells()}
    tasks: list[tuple[str, Any]] = [
        (batch.name, lambda b=batch: run_batch(str(sweep.path), b.name, list(b.runs),
                                               _batch_configs(grid, by_name, b),
                                               grid.episodes, command)) for batch in batches or []]
    tasks += [(cell.name, lambda c=cell: [run_cell(str(sweep.path), c.name, config_to_dict(grid.config(c)),
                                                   grid.episodes, command)]) for cell in todo]
    outcome = SweepOutcome()
    previous = {sig: signal.signal(sig, _raise_interrupt) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        for i, (name, task) in enumerate(tasks, 1):
            t0 = time.monotonic()
            with _own_output():
                results = task()
            for result in results:
                outcome.results[result["name"]] = result
            done = sum(1 for r in results if r["status"] == "complete")
            print(f"  [{i}/{len(tasks)}] {name}: {done}/{len(results)} run(s) complete "
                  f"({time.monotonic() - t0:.0f} s)" + "".join(
                      f"; {r['name']}: {r['status']}" + (f" ({r['detail']})" if r.get("detail") else "")
                      for r in results if r["status"] != "complete"),
                  flush=True)
            if any(r["status"] == "interrupted" for r in results):
                outcome.interrupted = True
                break
    except KeyboardInterrupt:
        outcome.interrupted = True
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return outcome


def run_sweep(sweep: SweepDir, grid: Grid, todo: list[Cell], workers: int | None, address: str | None,
              retries: int, command: str, progress: bool, batches: list[Batch] | None = None) -> SweepOutcome:
    """Start or join Ray, check the nodes (cluster), run ``todo`` one run per task and ``batches`` one batch
    per task, and always shut Ray down."""
    sweep = SweepDir(sweep.path.resolve())  # workers run elsewhere: they get an absolute path
    on_gpu = bool(batches) and grid.on_cuda()
    gpus = 0
    if on_gpu and address is None:
        import torch  # the embedded Ray hands this machine's GPUs to the batches, one batch per GPU

        gpus = torch.cuda.device_count()
    ray = start_ray(workers, address, gpus)
    try:
        if address is not None:
            check_nodes(ray, sweep)
            if cluster_cpus(ray) < 1:
                raise RunError(f"the Ray cluster at {address} has no CPUs")
            if on_gpu and ray.cluster_resources().get("GPU", 0) < 1:
                raise RunError(f"the batches train on a GPU (train.device = cuda), but the Ray cluster at {address} "
                               "has none; start its nodes on GPU machines or train on the CPU")
        return run_tasks(ray, sweep, grid, todo, retries, command, progress, batches)
    finally:
        ray.shutdown()

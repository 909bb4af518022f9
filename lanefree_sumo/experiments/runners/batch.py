"""K training runs in one process (the batched environment and learners), written into K ordinary run folders.

Run k of a batch is ``lanefree train`` of its own config: the loop below keeps SB3's order for every run (the
action, the environment step, the finished episodes' rows, the transition stored with the terminal observation,
the step's schedules, one update), so run k's ``episodes.csv`` equals the sequential run's in every column but
``wall_s`` (on CPU; ``tests/experiments/test_batch.py``), under every open modelling choice (the overtake bonus,
the agent's limits, the discrete action sizes, the learner profile). Runs may differ in seed, density, reward
preset and overtake bonus (:class:`~lanefree_sumo.rl.batched_env.BatchedRingEnv`,
:func:`~lanefree_sumo.rl.models.build_batched`).

Layout: the batch folder holds ``batch.json`` (the run folders, relative) and ``batch_checkpoints/`` (the whole
batch — learners, replay, random streams, the environment — one file per checkpoint, the two newest kept). Each
run folder is an ordinary one (config.yaml, command.txt, versions.json, episodes.csv, sessions.jsonl,
last_session.json, model.zip when finished); its ``checkpoints/ep_N/`` holds the run's own ``model.zip`` and a
``state.json`` naming the batch file it belongs to. A batch checkpoint is taken after a whole step (after the
update), so ``lanefree train --resume BATCH`` continues with exactly the episodes of an uninterrupted batch.

A run whose action is not finite (a diverged policy) is stopped alone: its folder's session says why and it gets
no ``model.zip``; the other runs go on.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import os
import pickle
import shlex
import shutil
import signal
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from lanefree_sumo.config import LaneFreeConfig, merge_config
from lanefree_sumo.errors import ConfigError, OperatingSystemError, RunError, os_error_message
from lanefree_sumo.experiments.runners.session import Stop, check_episode_rows, new_run_folder, versions
from lanefree_sumo.experiments.storage.episodes import TENSORBOARD_SCALARS, EpisodeLog, episode_columns
from lanefree_sumo.experiments.storage.rundir import (
    BATCH_CHECKPOINTS,
    BATCH_FILE,
    RunDir,
    append_command,
    claim,
    record_session,
    write_config,
)
from lanefree_sumo.sim.road import road_kind
from lanefree_sumo.sim.xp import on_cpu

KEEP_BATCH_CHECKPOINTS = 2


def batch_refusal(cfg: LaneFreeConfig, alone: bool = False) -> str | None:
    """What of ``cfg`` the batched path cannot train (one phrase, e.g. ``the ppo algorithm (--algo)``), or None
    when it trains it: the one list behind :func:`check_batchable` and the single run's choice of trainer (SB3's
    loop for SAC and PPO; a batchable algorithm's run it cannot train is refused). ``alone``: the run is a batch of
    one (``lanefree train --seed``), which may run inside SUMO. What no run trains (several environments inside
    SUMO, a learner choice its algorithm lacks) is :func:`~lanefree_sumo.rl.models.check_trainable`'s."""
    from lanefree_sumo.rl.algorithms import BATCHED
    if cfg.train.algo not in BATCHED:
        return f"the {cfg.train.algo} algorithm (--algo)"
    cpu = cpu_only(cfg)
    for wrong, what in ((cpu is not None, f"{cpu} on {cfg.train.device} (it trains on train.device = cpu)"),
                        (cfg.train.backend != "numpy" and not alone,
                         f"the {cfg.train.backend} backend (--backend)")):
        if wrong:
            return what
    return None


def _several(cfg: LaneFreeConfig) -> str | None:
    """``several agents (--agents)`` or ``several environments (--envs)`` for a run of several slots (SB3's
    ``n_envs``: :class:`~lanefree_sumo.rl.env_batch.SlotBatch`), else None."""
    if cfg.scenario.agents != 1:
        return "several agents (--agents)"
    return "several environments (--envs)" if cfg.train.envs != 1 else None


def needs_env_batch(cfg: LaneFreeConfig) -> bool:
    """Whether a batch of ``cfg``'s runs steps LaneFree-v0 environments (:class:`~lanefree_sumo.rl.env_batch.
    EnvBatch`: the shield, a road other than the ring, a run inside SUMO; :class:`~lanefree_sumo.rl.env_batch.
    SlotBatch`: several agents or environments per run) rather than the ring's batched world."""
    return (cfg.shield.enabled or not road_kind(cfg).batched_world or cfg.train.backend != "numpy"
            or _several(cfg) is not None)


def cpu_only(cfg: LaneFreeConfig) -> str | None:
    """What of ``cfg`` trains on ``train.device = cpu`` only while ``train.device`` names another device
    (``the safety shield (--shield)``, ``the onramp road (--scenario)``, ``the libsumo backend (--backend)``), else
    None."""
    if not needs_env_batch(cfg) or cfg.train.device == "cpu":
        return None
    if cfg.shield.enabled:
        return "the safety shield (--shield)"
    several = _several(cfg)
    if several is not None:
        return several
    if cfg.train.backend != "numpy":
        return f"the {cfg.train.backend} backend (--backend)"
    return f"the {cfg.road.kind} road (--scenario)"


def check_batchable(cfg: LaneFreeConfig, alone: bool = False) -> None:
    """ConfigError (one line) for a run the batched path cannot train (``alone``: as a batch of one,
    :func:`batch_refusal`)."""
    from lanefree_sumo.rl.algorithms import BATCHED

    if cfg.train.algo not in BATCHED:
        raise ConfigError(f"batched training covers {', '.join(BATCHED)}, not {cfg.train.algo}; "
                          "train it with --seed (one run)")
    cpu = cpu_only(cfg)
    if cpu is not None:
        raise ConfigError(f"runs with {cpu} train on the CPU (train.device = cpu), not on train.device = "
                          f"{cfg.train.device}; leave --device out")
    from lanefree_sumo.rl.models import check_trainable

    check_trainable(cfg)  # the single run's check: what one run refuses, a batch refuses
    why = batch_refusal(cfg, alone)
    if why is not None:
        raise ConfigError(f"batched training does not support {why}; train such runs with --seed (one run)")
    check_device(cfg.train.device)


def check_device(device: str) -> None:
    """ConfigError (one line) when ``device`` (``train.device``) is not on this machine."""
    if device == "cuda":
        import torch

        if torch.version.cuda is None:  # `make venv` installs torch's CPU build
            raise ConfigError(f"train.device = cuda, but this torch ({torch.__version__}) is a CPU-only build; "
                              "install a CUDA build of torch to train on a GPU, or train on the CPU with --device cpu")
        if not torch.cuda.is_available():
            raise ConfigError("train.device = cuda, but torch finds no CUDA GPU on this machine; "
                              "train on the CPU with --device cpu")


def replay_bytes(cfg: LaneFreeConfig) -> int:
    """Bytes of one run's replay buffer in a batch (:class:`~lanefree_sumo.rl.algorithms.batched.replay.
    BatchedReplay`: observations and next observations, actions, rewards, dones, timeouts; float32, DQN's actions
    int64), from the config's buffer size and the run's spaces."""
    from lanefree_sumo.rl.algorithms import get_algorithm
    from lanefree_sumo.rl.env import action_space, observation_space

    section = get_algorithm(cfg.train.algo).config_section
    capacity = cfg.train.actor_critic.buffer_size if section == "actor_critic" else cfg.train.dqn.buffer_size
    obs, act = observation_space(cfg), action_space(cfg)
    obs_values = sum(int(np.prod(s.shape or ())) for s in getattr(obs, "spaces", {"": obs}).values())
    action_bytes = 8 if act.shape == () else 4 * int(np.prod(act.shape or ()))
    return capacity * (2 * 4 * obs_values + action_bytes + 3 * 4)


def available_memory(device: str) -> int:
    """Bytes the replay buffers of a batch can take: the CPU's available memory (``MemAvailable``), or the free
    memory of the CUDA device."""
    if not on_cpu(device):
        import torch

        return int(torch.cuda.mem_get_info(torch.device(device))[0])
    try:
        with open("/proc/meminfo", encoding="ascii") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_AVPHYS_PAGES"))


def check_memory(cfgs: Sequence[LaneFreeConfig], device: str) -> None:
    """ConfigError (one line) when the batch's replay buffers would not fit into this machine's available memory
    (or the device's): how much they need, how much there is, how many such runs fit."""
    each = [replay_bytes(cfg) for cfg in cfgs]
    need, have = sum(each), available_memory(device)
    if need <= have:
        return
    per_run = max(each)
    where = "this machine" if on_cpu(device) else f"the {device} device"
    raise ConfigError(f"{len(cfgs)} runs need ≈ {need / 2**30:.1f} GiB of replay memory ({per_run / 2**20:,.0f} MiB "
                      f"each) and {where} has {have / 2**30:.1f} GiB available: at most {have // per_run} such runs "
                      "fit here; train fewer seeds per batch (or a smaller buffer_size)")


@dataclass
class _Books:
    """What the batch loop keeps per run besides the learners and the environment (saved in its checkpoints)."""

    done: list[int]
    target: list[int]
    finished: list[bool]
    stopped: dict[int, str] = field(default_factory=dict)
    steps: int = 0

    def active(self, k: int) -> bool:
        return not self.finished[k] and k not in self.stopped


def _load_books(saved: dict[str, Any] | bytes) -> _Books:
    """A checkpoint's books: a dict (:func:`dataclasses.asdict`), or the pickled :class:`_Books` of a checkpoint
    written while this module was ``lanefree_sumo.experiments.batch`` (still resumable)."""
    if isinstance(saved, dict):
        return _Books(**{**saved, "stopped": {int(k): v for k, v in saved["stopped"].items()}})

    class Moved(pickle.Unpickler):
        def find_class(self, module: str, name: str) -> Any:
            return super().find_class(__name__ if module == "lanefree_sumo.experiments.batch" else module, name)

    books = Moved(io.BytesIO(saved)).load()
    if not isinstance(books, _Books):
        raise TypeError(f"the books are a {type(books).__name__}")
    return books


def _bar_text(books: _Books, names: list[str]) -> str:
    return " ".join(f"{n}:{'x' if k in books.stopped else books.done[k]}" for k, n in enumerate(names))


def _seed_name(folder: Path) -> str:
    return folder.name.rsplit("_", 1)[-1] if "_" in folder.name else folder.name


class _Batch:
    """One session of a batch: its folders, environment, learner and books."""

    def __init__(self, batch_dir: Path, cfgs: list[LaneFreeConfig], folders: list[RunDir],
                 lockstep: bool | None = None) -> None:
        self.batch_dir, self.cfgs, self.folders = batch_dir, cfgs, folders
        self.device = cfgs[0].train.device
        """Where the simulation and the learners live (``train.device``: ``cpu`` the numpy simulation)."""
        self.lockstep = lockstep
        """Run the lockstep loop (:mod:`~lanefree_sumo.rl.lockstep`: device streams, CUDA graphs on a GPU);
        None: on CUDA where the batch allows it."""
        self.runs = len(cfgs)
        self._ended = np.zeros(self.runs, dtype=bool)
        self._boards: list[_Board] = []
        """Each run's TensorBoard log (:class:`_Board`), for the length of :meth:`run`."""
        self.interrupted = False
        """Whether :meth:`run` ended on Ctrl-C or SIGTERM."""

    # -- checkpoints ------------------------------------------------------------------------------------
    def save(self, env: Any, learner: Any, obs: Any, books: _Books, loop: Any = None) -> Path:
        """The whole batch after a complete step, and each unfinished run's ``checkpoints/ep_N`` naming it."""
        import torch

        folder = self.batch_dir / BATCH_CHECKPOINTS
        folder.mkdir(exist_ok=True)
        path = folder / f"step_{books.steps:010d}.pt"
        tmp = path.with_name(path.name + ".tmp")
        try:
            torch.save({"learner": learner.state_dict(), "env": pickle.dumps(env), "obs": obs,
                        "books": dataclasses.asdict(books),
                        "lockstep": None if loop is None else loop.state_dict()}, tmp)
            os.replace(tmp, path)
        except (OSError, RuntimeError) as exc:  # torch.save reports a full disk as a RuntimeError of its own
            tmp.unlink(missing_ok=True)
            said = os_error_message(exc) if isinstance(exc, OSError) else " ".join(str(exc).split())[:160]
            kept = sorted(folder.glob("step_*.pt"))
            raise OperatingSystemError(
                f"could not write the batch checkpoint {path} ({said}); "
                + (f"the previous one ({kept[-1].name}) is kept: free some space and resume with --resume "
                   f"{self.batch_dir}" if kept else "free some space and start the batch again")) from None
        saved = datetime.now().isoformat(timespec="seconds")
        for k, run in enumerate(self.folders):
            if books.finished[k] or books.done[k] == 0:
                continue
            ckpt = run.checkpoint(books.done[k])
            ckpt.mkdir(parents=True, exist_ok=True)
            learner.export(k, ckpt / "model.zip")
            run.write_checkpoint_state(ckpt, {
                "episodes": books.done[k], "timesteps": books.steps, "algo": self.cfgs[k].train.algo,
                "saved": saved, "batch": os.path.relpath(path, run.path), "batch_run": k})
        for old in sorted(folder.glob("step_*.pt"))[:-KEEP_BATCH_CHECKPOINTS]:
            old.unlink(missing_ok=True)
        return path

    def _save_final(self, env: Any, learner: Any, obs: Any, books: _Books, loop: Any) -> None:
        """The finished single run's last batch checkpoint, from which ``--episodes N`` extends it. The run is
        complete without it: a failure to write it is said in one line, and the run stands."""
        try:
            self.save(env, learner, obs, books, loop)
        except OperatingSystemError as exc:
            reason = str(exc).split("; ", 1)[0]
            print(f"{self.batch_dir}: finished (model.zip), but {reason}; extending it with --episodes N needs that "
                  "checkpoint", file=sys.stderr)

    def _unusable_advice(self, path: Path) -> str:
        """What to do when the newest batch checkpoint ``path`` cannot be loaded: resume from the older one, or —
        the batch's only one — start afresh with the command that made it (a batch's runs finish together: none of
        them has finished)."""
        if len(list(path.parent.glob("step_*.pt"))) > 1:
            return "delete it to resume from the older one"
        if self.folders == [RunDir(self.batch_dir)]:
            if self.folders[0].model.is_file():
                return ("it was the run's only one: the run is complete (model.zip) but cannot be extended; train "
                        "a new run")
            return (f"it was the run's only one: start it afresh with 'lanefree train … --out {self.batch_dir}' "
                    "(no --resume)")
        return ("it was the batch's only one: start the batch afresh with the command that made it (its --out "
                f"{self.batch_dir}, no --resume)")

    def newest(self) -> Path:
        found = sorted((self.batch_dir / BATCH_CHECKPOINTS).glob("step_*.pt"))
        if not found and self.folders == [RunDir(self.batch_dir)]:
            raise RunError(f"{self.batch_dir} has no usable checkpoint under {BATCH_CHECKPOINTS}/ (it never reached "
                           f"its first); start it afresh with 'lanefree train … --out {self.batch_dir}' (no --resume)")
        if not found:
            raise RunError(f"{self.batch_dir} has no batch checkpoint under {BATCH_CHECKPOINTS}/ (it never reached "
                           "its first); start the batch afresh")
        return found[-1]

    # -- the loop ---------------------------------------------------------------------------------------
    def run(self, resume: bool, progress: bool, command: str, extend: int | None = None) -> list[tuple[Path, int]]:
        """Train (``resume``: from the newest batch checkpoint) until every run has its episodes or a stop;
        ``extend``: first raise the single run's target to that many episodes (:meth:`_extend`)."""
        import torch
        from tqdm import tqdm

        from lanefree_sumo.rl.env import action_space, observation_space
        from lanefree_sumo.rl.models import build_batched

        cfgs = self.cfgs
        torch.set_num_threads(cfgs[0].train.torch_threads)
        started, session_versions = datetime.now(timezone.utc).isoformat(timespec="seconds"), versions()
        learner = build_batched(cfgs, [c.seed for c in cfgs], observation_space(cfgs[0]), action_space(cfgs[0]),
                                device=self.device)
        state: dict[str, Any] = {}
        if resume:
            env, obs, books, state = self._resume(learner, extend)
        else:
            env, obs, books = self._start()
        loop = self._lockstep(env, learner, state.get("lockstep"))
        first = list(books.done)
        steps0 = books.steps
        logs = [EpisodeLog(run.episodes, episode_columns(c)) for run, c in zip(self.folders, cfgs)]
        self._boards = [_Board(run.tensorboard / "batch") for run in self.folders]
        for run in self.folders:
            append_command(run.path, command)
        names = [_seed_name(r.path) for r in self.folders]
        desc = cfgs[0].train.algo if self.runs == 1 else f"{cfgs[0].train.algo} x{self.runs}"
        several = _several(cfgs[0])  # as SB3's loop said it: "ddpg, 4 agents"
        if several is not None:
            desc += f", {cfgs[0].scenario.agents * cfgs[0].train.envs} {several.split()[1]}"
        bar = tqdm(total=sum(books.target), initial=sum(books.done), unit="ep", disable=not progress, desc=desc,
                   dynamic_ncols=True, postfix=_bar_text(books, names))
        stop = Stop()
        previous = {sig: signal.signal(sig, stop) for sig in (signal.SIGINT, signal.SIGTERM)}
        t0 = time.perf_counter()
        try:
            if loop is not None:
                self._run_lockstep(loop, env, learner, obs, books, logs, bar, stop, names)
            while loop is None and any(books.active(k) for k in range(self.runs)) and not stop.requested:
                checkpoint = self._step(env, learner, obs, books, logs, bar)
                obs = env.reset([k for k in range(self.runs) if self._ended[k] and books.active(k)])
                if self._ended.any():
                    bar.set_postfix_str(_bar_text(books, names))
                if checkpoint and not stop.requested:
                    self.save(env, learner, obs, books)
            # a stop is saved here, whenever in the step it came (a check inside the loop could miss one arriving
            # between that check and the loop's); a run inside SUMO resumes from its newest checkpoint, taken
            # between episodes (EnvBatch.saves_mid_episode)
            if loop is None and stop.requested and any(books.active(k) for k in range(self.runs)):
                if env.saves_mid_episode:
                    self.save(env, learner, obs, books)
                else:
                    kept = books.done[0] - books.done[0] % self.cfgs[0].train.checkpoint_every_episodes
                    print(f"stopped inside an episode: a run inside SUMO resumes from its newest checkpoint "
                          f"({kept} episodes) and trains the episodes after it again, the same ones",
                          file=sys.stderr)
            if self.runs == 1 and books.finished[0] and not books.stopped:
                self._save_final(env, learner, obs if loop is None else loop.obs, books, loop)
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
            for log in logs:
                log.close()
            for board in self._boards:
                board.close()
            bar.close()
            env.close()
        wall = time.perf_counter() - t0
        self.interrupted = stop.requested
        ended = datetime.now(timezone.utc).isoformat(timespec="seconds")
        for k, run in enumerate(self.folders):
            record_session(run.path, {
                "episodes_done": books.done[k], "timesteps": books.steps, "wall_s": wall,
                "steps_per_s": (books.steps - steps0) / wall if wall > 0 else None,
                "stopped_by": books.stopped.get(k) or (stop.signal_name or None if not books.finished[k] else None),
                "first_episode": first[k] + 1, "started": started, "ended": ended, "versions": session_versions,
                "batch": {"folder": os.path.relpath(self.batch_dir, run.path), "run": k, "runs": self.runs}})
        return [(run.path, books.done[k]) for k, run in enumerate(self.folders)]

    def _resume(self, learner: Any, extend: int | None) -> tuple[Any, Any, _Books, dict[str, Any]]:
        """The newest batch checkpoint loaded into ``learner``: (environment, observation, books, the checkpoint);
        each run's episodes.csv checked and cut back to it; ``extend``: :meth:`_extend` first."""
        import torch

        path = self.newest()
        try:
            state = torch.load(path, weights_only=False)
            learner.load_state_dict(state["learner"])
            env, obs, books = pickle.loads(state["env"]), state["obs"], _load_books(state["books"])
        except Exception as exc:
            raise RunError(f"batch checkpoint {path} is unusable ({type(exc).__name__}: {exc}); "
                           + self._unusable_advice(path)) from None
        for k, run in enumerate(self.folders):
            cfg = self.cfgs[k]
            check_episode_rows(run, books.done[k], cfg.scenario.agents)  # a damaged file is said, not hidden
            EpisodeLog.truncate(run.episodes, books.done[k], episode_columns(cfg))
        if extend is not None:
            obs = self._extend(extend, env, obs, books)
        return env, obs, books, state

    def _start(self) -> tuple[Any, Any, _Books]:
        """A new batch's environment (every run reset), its first observation and its books."""
        from lanefree_sumo.rl.batched_env import BatchedRingEnv
        from lanefree_sumo.rl.env_batch import EnvBatch, SlotBatch

        kind = (SlotBatch if any(_several(c) is not None for c in self.cfgs) else
                EnvBatch if any(needs_env_batch(c) for c in self.cfgs) else BatchedRingEnv)
        env = kind(self.cfgs, device=self.device)
        obs = env.reset()
        return env, obs, _Books([0] * self.runs, [c.train.episodes for c in self.cfgs], [False] * self.runs)

    def _extend(self, target: int, env: Any, obs: Any, books: _Books) -> Any:
        """Raise the single run's target to ``target`` episodes (its config says so from now on); a finished run
        starts its next episode. Returns the observation to go on from. RunError for a target it has reached, or
        for a finished run whose final batch checkpoint is missing (extending would retrain episodes)."""
        run, done = self.folders[0], books.done[0]
        if target <= done:
            raise RunError(f"{run.path} already has {done} episodes; --episodes must exceed that")
        if run.model.is_file() and not books.finished[0]:
            raise RunError(f"{run.path} finished without a final checkpoint (newest: {done} episodes); extending it "
                           "would retrain episodes: start a new run")
        books.target[0] = target
        self.cfgs[0] = merge_config(self.cfgs[0], {"train": {"episodes": target}})
        write_config(run.path, self.cfgs[0])
        if books.finished[0]:
            books.finished[0] = False
            env.stopped[0] = False
            obs = env.reset([0])
        return obs

    def _lockstep(self, env: Any, learner: Any, state: dict[str, Any] | None) -> Any:
        """The lockstep loop of this batch, or None (the exact loop)."""
        from lanefree_sumo.rl.lockstep import Lockstep, lockstep_refusal

        wanted = self.lockstep if self.lockstep is not None else self.device == "cuda"
        if not wanted:
            return None
        why = lockstep_refusal(env, learner)
        if why is not None:
            if self.lockstep:
                raise ConfigError(f"this batch cannot run the lockstep loop: {why}")
            return None
        seed = int(np.random.SeedSequence([c.seed for c in self.cfgs]).generate_state(1)[0])
        loop = Lockstep(env, learner, seed)
        if state is not None:
            loop.load_state_dict(state)
        if loop.compiled is not None:  # the first iterations wait for it, with no episode to show
            print(f"compiling the ring step and the update for {self.device} ({loop.compiled}; a minute or more "
                  "on a machine that has not compiled them before)", file=sys.stderr, flush=True)
        return loop

    def _run_lockstep(self, loop: Any, env: Any, learner: Any, obs: Any, books: _Books, logs: list[EpisodeLog],
                      bar: Any, stop: Any, names: list[str]) -> None:
        """The loop of :meth:`run` with the lockstep loop: whole iterations on the device; episode rows, resets and
        checkpoints between episodes (a stop checkpoints after the current iteration)."""
        loop.start(obs)
        episode_steps = self.cfgs[0].sim.episode_steps
        while any(books.active(k) for k in range(self.runs)) and not stop.requested:
            live = [k for k in range(self.runs) if books.active(k)]
            # the step that ends every live run's last episode takes no update: SB3 stops before it (the final
            # models are those of the sequential runs)
            last = all(books.done[k] + 1 >= books.target[k] for k in live) and \
                int(env.steps[live].max()) + 1 >= episode_steps
            loop.iterate(update=not last)
            books.steps += 1
            if not loop.episode_over():
                continue
            flagged = loop.take_flagged()
            host = env.host_books()
            ended = np.zeros(self.runs, dtype=bool)
            checkpoint = False
            for k in range(self.runs):
                if not books.active(k):
                    continue
                if flagged[k]:
                    books.stopped[k] = (f"run {k}: an action was not finite in episode {int(env.episode[k])}; a "
                                        "diverged policy must not drive the car")
                    env.stopped[k] = True
                    print(f"{self.folders[k].path}: stopped: {books.stopped[k]}", file=sys.stderr)
                    continue
                ended[k] = True
                checkpoint |= self._episode_done(k, [env.episode_metrics(k, host)], learner.num_timesteps, learner,
                                                 env, books, logs, bar)
            learner.episodes_ended(ended)
            loop.start(env.reset([k for k in range(self.runs) if books.active(k)]))
            bar.set_postfix_str(_bar_text(books, names))
            if checkpoint:
                self.save(env, learner, loop.obs, books, loop)
        if stop.requested and any(books.active(k) for k in range(self.runs)):
            self.save(env, learner, loop.obs, books, loop)

    def _episode_done(self, k: int, group: list[dict[str, Any]], timesteps: int, learner: Any, env: Any,
                      books: _Books, logs: list[EpisodeLog], bar: Any) -> bool:
        """Run k ended an episode: its rows (``group``: one, or one per agent), and its final model when it is
        done; returns whether it reached a checkpoint episode."""
        books.done[k] += 1
        cfg = self.cfgs[k]
        for metrics in group:
            logs[k].append({**metrics, "episode": books.done[k], "algorithm": cfg.train.algo,
                            "timesteps": timesteps})
        self._boards[k].episode(group, timesteps)
        bar.update(1)
        if books.done[k] >= books.target[k]:
            books.finished[k] = True  # the sequential run stops here: its final model is this one
            run = self.folders[k]
            ckpt = run.checkpoint(books.done[k])
            ckpt.mkdir(parents=True, exist_ok=True)
            learner.export(k, ckpt / "model.zip")
            run.write_checkpoint_state(ckpt, {
                "episodes": books.done[k], "timesteps": timesteps, "algo": cfg.train.algo,
                "saved": datetime.now().isoformat(timespec="seconds"), "batch": None, "batch_run": k})
            learner.export(k, run.model)
            env.stopped[k] = True  # finished: never reset nor scored again
            return False
        return books.done[k] % cfg.train.checkpoint_every_episodes == 0

    def _step(self, env: Any, learner: Any, obs: Any, books: _Books, logs: list[EpisodeLog], bar: Any) -> bool:
        """One step of every run in SB3's order; returns whether a run reached a checkpoint episode."""
        actions = learner.act(obs, explore=True)
        new_obs, reward, terminated, truncated, info = env.step(actions)
        m = learner.slots
        timesteps = learner.num_timesteps + m  # SB3 counts the step before the callback sees it
        checkpoint = False
        for k, reason in info["stopped"].items():
            if books.active(k):
                books.stopped[k] = reason
                print(f"{self.folders[k].path}: stopped: {reason}", file=sys.stderr)
        self._ended = np.zeros(self.runs, dtype=bool)
        grouped = getattr(env, "grouped", False)
        for k in range(self.runs):
            ended = [metrics for metrics in info["episode_metrics"][k * m:(k + 1) * m] if metrics is not None]
            if not ended or not books.active(k):
                continue
            self._ended[k] = True
            # SB3's callback: the agents' rows of one episode form that episode; several environments' ends are
            # episodes one after another, those past the run's last one dropped
            for group in [ended] if grouped else [[metrics] for metrics in ended]:
                if not books.active(k):
                    break
                checkpoint |= self._episode_done(k, group, timesteps, learner, env, books, logs, bar)
        done = terminated | truncated
        learner.store(obs, actions, reward, new_obs, done, truncated & ~terminated)
        learner.update()
        books.steps += 1
        return checkpoint


def batch_name(cfg: LaneFreeConfig) -> str:
    """A run's folder name in a batch, as a sweep names its cells: ``<algo>_<preset>_d<density>_s<seed>``."""
    return f"{cfg.train.algo}_{cfg.reward.preset}_d{cfg.scenario.density_veh_per_km:g}_s{cfg.seed}"


def train_batch(cfgs: list[LaneFreeConfig], batch_dir: Path, folders: list[Path] | None = None,
                progress: bool = True, command: str | None = None,
                lockstep: bool | None = None) -> list[tuple[Path, int]]:
    """Train the runs ``cfgs`` as one batch into ``folders`` (default ``batch_dir/<batch_name>``); return each
    run's (folder, episodes done). Ctrl-C/SIGTERM checkpoint the batch and return early. The batch simulates and
    learns on its runs' ``train.device``. ``lockstep``: run the lockstep loop (:mod:`~lanefree_sumo.rl.lockstep`;
    None: on CUDA where the batch allows it)."""
    from lanefree_sumo.rl.models import training_config
    from lanefree_sumo.sim.spawn import check_fits

    cfgs = [training_config(c) for c in cfgs]
    for cfg in cfgs:
        check_batchable(cfg, alone=len(cfgs) == 1)
        check_fits(cfg)  # the density fits, before anything is written
    if len({c.train.device for c in cfgs}) > 1:
        raise ConfigError("the runs of one batch train on one device; give them the same train.device")
    check_memory(cfgs, cfgs[0].train.device)
    paths = folders or [batch_dir / batch_name(c) for c in cfgs]
    if len(set(paths)) != len(paths):
        raise ConfigError("two runs of the batch would share a run folder; give each run its own seed or folder")
    with contextlib.ExitStack() as stack:
        stack.enter_context(claim(batch_dir, "train"))  # one batch writes a batch folder at a time
        restart = check_batch_folder(batch_dir, paths)
        batch_dir.mkdir(parents=True, exist_ok=True)
        runs: list[RunDir] = []
        for cfg, path in zip(cfgs, paths):
            run = RunDir(new_run_folder(cfg, path, restart=restart))
            stack.enter_context(run.writer_lock())
            if restart or run.never_checkpointed():
                run.clear()
            runs.append(run)
        if restart:  # none of them loads: the batch starts afresh
            for old in (batch_dir / BATCH_CHECKPOINTS).glob("step_*.pt"):
                old.unlink()
        single = paths == [batch_dir]  # a single run, its own batch: nothing of it stays unless it learned
        try:
            for cfg, run in zip(cfgs, runs):
                write_config(run.path, cfg)
                run.versions.write_text(json.dumps(versions(), indent=2) + "\n")
            (batch_dir / BATCH_FILE).write_text(json.dumps(
                {"runs": [os.path.relpath(r.path, batch_dir) for r in runs]}, indent=2) + "\n")
            batch = _Batch(batch_dir, cfgs, runs, lockstep)
            result = batch.run(False, progress, command or shlex.join(["lanefree", *sys.argv[1:]]))
        except BaseException:
            if single and not runs[0].has_checkpoint():
                shutil.rmtree(batch_dir, ignore_errors=True)
            raise
        if single and batch.interrupted and not runs[0].has_checkpoint():
            shutil.rmtree(batch_dir, ignore_errors=True)
            raise KeyboardInterrupt  # stopped before its first checkpoint: nothing to resume
        return result
    raise AssertionError("unreachable")


class _Board:
    """One run's TensorBoard log of a batch (``RUN/tb/batch``), opened at its first episode end."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self._writer: Any = None

    def episode(self, group: list[dict[str, Any]], timesteps: int) -> None:
        """The episode's :data:`TENSORBOARD_SCALARS` (the mean over its agents' rows ``group``) at the batch's step
        ``timesteps``."""
        if self._writer is None:
            from torch.utils.tensorboard import SummaryWriter

            self._writer = SummaryWriter(log_dir=str(self.folder))
        for key in TENSORBOARD_SCALARS:
            self._writer.add_scalar(f"episode/{key}", float(np.mean([m[key] for m in group])), timesteps)
        self._writer.flush()

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()


def usable_checkpoint(batch_dir: Path) -> bool:
    """Whether one of ``batch_dir``'s batch checkpoints loads (newest first)."""
    import torch

    for path in sorted((batch_dir / BATCH_CHECKPOINTS).glob("step_*.pt"), reverse=True):
        try:
            state = torch.load(path, weights_only=False)
            pickle.loads(state["env"])
            _load_books(state["books"])
            return True
        except Exception:  # noqa: BLE001 - any failure to load makes it unusable, as resume finds it
            continue
    return False


def dead_single_run(folder: Path) -> bool:
    """A single run (its own batch, :func:`is_single_run`) that cannot go on: not finished, and none of its batch
    checkpoints loads (its only one was damaged). The same command starts it afresh."""
    return is_single_run(folder) and not RunDir(folder).model.is_file() and not usable_checkpoint(folder)


def check_batch_folder(batch_dir: Path, paths: list[Path]) -> bool:
    """Refuse, before anything is written, a batch folder that holds anything but this batch killed before its
    first checkpoint (the same run folders in its ``batch.json``, no batch checkpoint) or this batch with no batch
    checkpoint that loads: a user's folder, a run's, a sweep's, another batch's — RunError saying what it holds and
    what to do. Returns True for the latter, where the batch starts afresh over its runs (which finish together:
    none has)."""
    if not batch_dir.exists():
        return False
    if not batch_dir.is_dir():
        raise RunError(f"{batch_dir} exists and is not a folder; choose another --out")
    entries = sorted(p.name for p in batch_dir.iterdir())
    if not entries or (paths == [batch_dir] and RunDir(batch_dir).never_checkpointed()):
        return False  # new, or a single run (its own batch) killed before its first checkpoint: it starts afresh
    if paths == [batch_dir] and dead_single_run(batch_dir):
        return True
    listed = None
    if is_batch(batch_dir):
        try:
            listed = json.loads((batch_dir / BATCH_FILE).read_text())["runs"]
        except (OSError, ValueError, KeyError, TypeError):
            listed = None
    mine = [os.path.relpath(p, batch_dir) for p in paths]
    if listed is not None and listed and all(RunDir(batch_dir / p).model.is_file() for p in listed):
        raise RunError(f"{batch_dir} holds a finished batch (every run has its model.zip); choose another --out")
    if listed is not None and any((batch_dir / BATCH_CHECKPOINTS).glob("step_*.pt")):
        if listed == mine and not usable_checkpoint(batch_dir):
            return True  # this batch, whose only checkpoint was damaged: it starts afresh
        raise RunError(f"{batch_dir} holds a batch already; resume it with --resume {batch_dir} or choose another "
                       "--out")
    if listed is not None and listed == mine:
        return False  # this batch, killed before its first checkpoint: it starts afresh
    what = ("another batch" if listed is not None else "a run" if (batch_dir / "config.yaml").is_file()
            else f"{len(entries)} file(s) or folder(s), e.g. {entries[0]}")
    raise RunError(f"{batch_dir} exists and holds {what}; a batch writes into a new or empty folder: choose "
                   "another --out")


def batch_runs(paths: list[Path]) -> list[Path]:
    """``paths`` with every batch folder (``lanefree train --seeds``) replaced by its run folders, in its order;
    RunError for a batch folder whose ``batch.json`` is unusable."""
    out: list[Path] = []
    for path in paths:
        if not is_batch(path):
            out.append(path)
            continue
        try:
            listed = json.loads((path / BATCH_FILE).read_text())["runs"]
            out += [path / str(p) for p in listed]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise RunError(f"{path / BATCH_FILE} is unusable ({exc}); pass the batch's run folders instead") from None
    return out


def is_batch(folder: Path) -> bool:
    """Whether ``folder`` is a batch folder of several runs (``lanefree train --seeds``: its ``batch.json`` lists
    run folders below it); a single run trained as a batch of one (:func:`is_single_run`) is a run folder."""
    return (folder / BATCH_FILE).is_file() and not is_single_run(folder)


def is_single_run(folder: Path) -> bool:
    """Whether ``folder`` is a run trained as a batch of one in its own folder (``lanefree train --seed``): its
    ``batch.json`` lists the folder itself."""
    try:
        return json.loads((folder / BATCH_FILE).read_text()).get("runs") == ["."]
    except (OSError, ValueError, AttributeError):
        return False


def resume_batch(batch_dir: Path, progress: bool = True, command: str | None = None,
                 lockstep: bool | None = None, episodes: int | None = None) -> list[tuple[Path, int]]:
    """Continue the batch in ``batch_dir`` from its newest batch checkpoint (the same episodes as uninterrupted).
    ``episodes``: extend a single run (:func:`is_single_run`), finished or not, to that many episodes."""
    try:
        listed = json.loads((batch_dir / BATCH_FILE).read_text())["runs"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise RunError(f"{batch_dir / BATCH_FILE} is unusable ({exc}); it is not a batch folder") from None
    runs = [RunDir(batch_dir / p) for p in listed]
    if episodes is not None and listed != ["."]:
        raise RunError(f"{batch_dir} is a batch of {len(runs)} runs; a batch is not extended: train more episodes "
                       "as a new batch")
    if episodes is None and all(run.model.is_file() for run in runs):
        if listed == ["."]:
            have = runs[0].load_config().train.episodes
            raise RunError(f"{batch_dir} is finished ({have} episodes); nothing to resume. To train it further pass "
                           f"--episodes N with N > {have}")
        raise RunError(f"{batch_dir} is finished (every run has its model.zip); nothing to resume")
    with contextlib.ExitStack() as stack:
        stack.enter_context(claim(batch_dir, "train"))
        cfgs = [run.load_config(note_retired=True) for run in runs]
        check_device(cfgs[0].train.device)
        for run in runs:
            stack.enter_context(run.writer_lock())
        return _Batch(batch_dir, cfgs, runs, lockstep).run(
            True, progress, command or shlex.join(["lanefree", *sys.argv[1:]]), extend=episodes)
    raise AssertionError("unreachable")

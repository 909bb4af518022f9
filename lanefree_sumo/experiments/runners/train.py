"""Training and evaluation runs: run folders, algorithms with the paper's hyperparameters,
per-episode CSV, checkpoints, interruption and resume.

The run folder layout is defined in :mod:`lanefree_sumo.experiments.storage.rundir`.

One trainer: a run the batched path trains (DDPG, TD3 and the DQN family; on numpy, or inside SUMO with one
environment: :func:`~lanefree_sumo.experiments.runners.batch.batch_refusal`) is a batch of one in its own
folder (:func:`~lanefree_sumo.experiments.runners.batch.train_batch`); its resume continues the whole state (learner,
replay, random streams, environment) and gives the uninterrupted run's episodes bit for bit, and ``--episodes N``
extends it the same way. SAC and PPO train in SB3's loop below: ``resume`` continues from the newest checkpoint
(model and replay buffer restored, ``episodes.csv`` cut back to the checkpoint's episode count, episode numbers
continued).
Episode k's traffic seed depends only on the run's seed and k (:func:`~lanefree_sumo.rl.models.episode_seed`;
with several environments, on the environment too), so a resumed one-environment run sees the traffic an
uninterrupted one sees; SB3's exploration noise state and the torch/numpy random streams are not checkpointed:
there, a resumed run is a valid continuation, not a bit-identical replay of an uninterrupted one.
"""

from __future__ import annotations

import contextlib
import json
import shlex
import shutil
import signal
import sys
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from lanefree_sumo.config import LaneFreeConfig, merge_config
from lanefree_sumo.errors import ConfigError, RunError
from lanefree_sumo.experiments.runners.session import Stop, check_episode_rows, new_run_folder, versions
from lanefree_sumo.experiments.storage.episodes import TENSORBOARD_SCALARS, EpisodeLog, episode_columns
from lanefree_sumo.experiments.storage.rundir import Checkpoint, RunDir, append_command, record_session, write_config
from lanefree_sumo.rl.algorithms import BATCHED, get_algorithm
from lanefree_sumo.rl.env import resolve_config
from lanefree_sumo.rl.models import build_model, check_trainable, load_saved_model, make_vec_env, training_config
from lanefree_sumo.sim.spawn import check_fits

# -- episode log and checkpoints ------------------------------------------------------------------

KEEP_REPLAY_BUFFERS = 2
"""Checkpoints whose replay buffer is kept (the newest ones; older checkpoints keep their model):
a buffer of 100 000 transitions is ~20 MB, 25 of them per run would be half a gigabyte."""


def save_checkpoint(model: Any, run: RunDir, episodes: int, algo: str) -> Path:
    """Model, replay buffer (off-policy) and counters in ``run.checkpoint(episodes)``."""
    folder = run.checkpoint(episodes)
    folder.mkdir(parents=True, exist_ok=True)
    model.save(folder / "model.zip")
    if get_algorithm(algo).off_policy:
        model.save_replay_buffer(Checkpoint(folder, episodes, 0).replay_buffer)
    run.write_checkpoint_state(folder, {"episodes": episodes, "timesteps": int(model.num_timesteps), "algo": algo,
                                        "saved": datetime.now().isoformat(timespec="seconds")})
    run.prune_replay_buffers(keep=KEEP_REPLAY_BUFFERS)
    return folder


# -- the training loop ----------------------------------------------------------------------------

def _make_callback(run: RunDir, cfg: LaneFreeConfig, log: EpisodeLog, done: int, stop: Stop, progress: bool) -> Any:
    from stable_baselines3.common.callbacks import BaseCallback
    from tqdm import tqdm

    target = cfg.train.episodes
    algo = cfg.train.algo
    shared = cfg.scenario.agents > 1

    class EpisodeCallback(BaseCallback):
        """Writes a CSV row per finished episode (per agent with several: TensorBoard gets their means),
        logs to TensorBoard, checkpoints every K episodes, and stops at the target episode count or on a
        signal."""

        def __init__(self) -> None:
            super().__init__()
            self.episodes = done
            desc = f"{algo}, {cfg.scenario.agents} agents" if shared else algo
            self.bar = tqdm(total=target, initial=done, unit="ep", desc=desc, disable=not progress,
                            dynamic_ncols=True)

        def _on_step(self) -> bool:
            ended = [info["episode_metrics"] for info in self.locals["infos"] if "episode_metrics" in info]
            # several agents: their rows of one simulation episode arrive together and form one episode
            for group in ([ended] if shared and ended else [[metrics] for metrics in ended]):
                if self.episodes >= target:
                    break
                self.episodes += 1
                for metrics in group:
                    log.append({**metrics, "episode": self.episodes, "algorithm": algo,
                                "timesteps": self.num_timesteps})
                for key in TENSORBOARD_SCALARS:
                    self.logger.record(f"episode/{key}", float(np.mean([m[key] for m in group])))
                self.logger.dump(self.num_timesteps)
                self.bar.update(1)
                # several agents: collisions summed over them, speed deviation and return their means
                summed, mean = (" (sum)", " (mean)") if shared else ("", "")
                self.bar.set_postfix({f"collisions{summed}": sum(m["collisions"] for m in group),
                                      f"speed_dev{mean}": f"{np.mean([m['speed_dev_mps'] for m in group]):.2f}",
                                      f"ret{mean}": f"{np.mean([m['return'] for m in group]):.1f}"})
                if self.episodes % cfg.train.checkpoint_every_episodes == 0 and self.episodes < target:
                    save_checkpoint(self.model, run, self.episodes, algo)
            return not stop.requested and self.episodes < target

        def _on_training_end(self) -> None:
            self.bar.close()

    return EpisodeCallback()


def _resume_point(folder: RunDir, cfg: LaneFreeConfig, episodes: int | None) -> tuple[Checkpoint, int]:
    """The checkpoint to continue from and the episode target; refuses what would lose episodes."""
    have = cfg.train.episodes
    if folder.model.is_file():
        if episodes is None:
            raise RunError(f"{folder.path} is finished ({have} episodes); nothing to resume. "
                           f"To train it further pass --episodes N with N > {have}")
        ckpt = folder.newest_checkpoint()
        if ckpt.episodes < have:
            raise RunError(f"{folder.path} finished without a final checkpoint (newest: {ckpt.episodes} episodes); "
                           "extending it would retrain episodes: start a new run")
    else:
        ckpt = folder.newest_checkpoint()
    target = have if episodes is None else episodes
    if target <= ckpt.episodes:
        raise RunError(f"{folder.path} already has {ckpt.episodes} episodes; --episodes must exceed that")
    return ckpt, target


def _unbatched_resume(folder: RunDir, algo: str) -> str:
    """Why a run of a batchable ``algo`` that is no batch of one is not resumed (nothing is written): a run of a
    batch of several (its batch continues it), a batch of one that lost its ``batch.json``, or a run an earlier
    version trained in SB3's loop (its checkpoints keep SB3's replay buffer); RunError when it has no checkpoint."""
    run = folder.path
    try:
        batch = json.loads((run / "last_session.json").read_text()).get("batch")
    except (OSError, ValueError, AttributeError):
        batch = None
    if isinstance(batch, dict) and batch.get("folder") not in (None, "."):
        where = (run / str(batch["folder"])).resolve()
        return (f"{run} is a run of the batch {where}; continue the whole batch: lanefree sweep --resume SWEEP for a "
                f"sweep's, lanefree train --resume {where} for one of --seeds")
    if isinstance(batch, dict):
        return (f"{run} was trained as a batch of one but has no batch.json, so its batch checkpoint cannot be "
                "found; its model still evaluates (lanefree evaluate): start a new run to train it further")
    if folder.newest_checkpoint().replay_buffer.is_file():
        return (f"{run} was trained in SB3's loop by an earlier version, where {algo} no longer trains; its model "
                "still evaluates (lanefree evaluate): start a new run to train it further")
    return f"{run} has checkpoints of no batch; its model still evaluates (lanefree evaluate): start a new run"


def _load_checkpoint(spec: Any, ckpt: Checkpoint, env: Any, folder: RunDir) -> Any:
    """The model (and replay buffer) of a checkpoint of ``folder``; RunError naming it when unusable. Its
    TensorBoard folder is ``folder``'s, never the path the checkpoint saved: a moved, renamed or copied run, or
    one resumed from another directory, writes into itself."""
    try:
        model = load_saved_model(spec.name, ckpt.model, env=env, tensorboard_log=str(folder.tensorboard))
        if spec.off_policy:
            if not ckpt.replay_buffer.is_file():
                raise RunError(f"checkpoint {ckpt.path} lacks {ckpt.replay_buffer.name}; it is incomplete")
            model.load_replay_buffer(ckpt.replay_buffer)
    except RunError:
        raise
    except Exception as exc:
        raise RunError(f"checkpoint {ckpt.path} is corrupt ({type(exc).__name__}: {exc}); "
                       "delete that folder to resume from an older one") from None
    return model


def train(
    cfg: LaneFreeConfig,
    run: Path | None = None,
    resume: bool = False,
    progress: bool = True,
    command: str | None = None,
    episodes: int | None = None,
) -> tuple[Path, int]:
    """Train (or resume) a run; return (run folder, episodes done): as a batch of one when the batched path
    trains it (module docstring), else in SB3's loop.  Ctrl-C/SIGTERM save a
    checkpoint and return early.  ``resume`` with ``episodes`` extends a run (finished or not)
    to that many episodes; a finished run is never resumed without it.  A new run that fails
    before its first checkpoint (an error such as a full disk, Ctrl-C or SIGTERM) leaves no folder behind, and one
    killed outright there is started afresh by the next start into its folder, so the same command can simply be run
    again.  The process holds the run's writer lock
    (:meth:`RunDir.writer_lock`) throughout: a second training of the same folder is refused."""
    from lanefree_sumo.experiments.runners.batch import (
        batch_refusal,
        check_batchable,
        dead_single_run,
        is_single_run,
        resume_batch,
        train_batch,
    )

    command = command or shlex.join(["lanefree", *sys.argv[1:]])
    if resume and run is not None and is_single_run(run):
        return resume_batch(run, progress, command, episodes=episodes)[0]
    if not resume:
        cfg = training_config(cfg)
        why = batch_refusal(cfg, alone=True)
        if why is None:  # one trainer: a single run is a batch of one, in its own folder
            check_batchable(cfg, alone=True)
            check_fits(cfg)  # before the folder is made
            path = new_run_folder(cfg, run, restart=run is not None and dead_single_run(run))
            return train_batch([cfg], path, [path], progress, command)[0]
        check_trainable(cfg)
        if cfg.train.algo in BATCHED:  # every run of a batchable algorithm trains in the one trainer
            check_batchable(cfg, alone=True)  # its one-line refusal, with what to do
            raise ConfigError(f"{cfg.train.algo} does not train {why}")
        if cfg.train.device != "cpu":
            raise ConfigError(f"train.device = {cfg.train.device} trains on the batched path, which does not "
                              f"support {why}; leave --device out to train this run on the CPU")
    with contextlib.ExitStack() as stack:
        created = False
        if resume:
            if run is None:
                raise RunError("resuming needs the run folder")
            folder = RunDir(run)
            # a run folder at all, before anything is written
            cfg = resolve_config(folder.load_config(note_retired=True))
            if cfg.train.algo in BATCHED:  # neither a batch of one (above) nor a --seeds batch's run (the CLI's)
                raise RunError(_unbatched_resume(folder, cfg.train.algo))
            stack.enter_context(folder.writer_lock())  # one writer: a second resume is refused here
            ckpt, target = _resume_point(folder, cfg, episodes)
            timesteps = ckpt.timesteps
        else:
            check_fits(cfg)  # the density fits, before anything is written
            run = new_run_folder(cfg, run)
            folder = RunDir(run)
            stack.enter_context(folder.writer_lock())  # another start of the same --out: refused, nothing removed
            if folder.never_checkpointed():
                folder.clear()  # what a start killed before its first checkpoint left: nothing to resume
            created = True  # ours from here: removed again if nothing is learned
            timesteps, target = 0, cfg.train.episodes
        try:
            if created:
                write_config(run, cfg)
                folder.versions.write_text(json.dumps(versions(), indent=2) + "\n")
            return _train_session(cfg, folder, ckpt if resume else None, timesteps, target, progress, command)
        except BaseException:
            if created and not folder.has_checkpoint():  # nothing to resume (also a first checkpoint that failed)
                shutil.rmtree(run, ignore_errors=True)
            raise
    raise AssertionError("unreachable")


def _train_session(cfg: LaneFreeConfig, folder: RunDir, ckpt: Checkpoint | None, timesteps: int, target: int,
                   progress: bool, command: str) -> tuple[Path, int]:
    """One training session of a run: from scratch (``ckpt`` None) or from ``ckpt``."""
    import torch

    resume = ckpt is not None
    done = ckpt.episodes if ckpt is not None else 0
    first_episode = done + 1
    started, session_versions = datetime.now(timezone.utc).isoformat(timespec="seconds"), versions()
    torch.set_num_threads(cfg.train.torch_threads)
    algo = cfg.train.algo
    spec = get_algorithm(algo)
    env = make_vec_env(cfg, done)
    stop = Stop()
    previous = {sig: signal.signal(sig, stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    log: EpisodeLog | None = None
    try:
        if ckpt is not None:
            model = _load_checkpoint(spec, ckpt, env, folder)  # validated before anything changes
            check_episode_rows(folder, done, cfg.scenario.agents)
            EpisodeLog.truncate(folder.episodes, done, episode_columns(cfg))
            if target != cfg.train.episodes:
                cfg = merge_config(cfg, {"train": {"episodes": target}})
                write_config(folder.path, cfg)
        else:
            model = build_model(cfg, env, cfg.seed, str(folder.tensorboard))
        append_command(folder.path, command)
        log = EpisodeLog(folder.episodes, episode_columns(cfg))
        callback = _make_callback(folder, cfg, log, done, stop, progress)
        # the budget from episodes, not from the checkpoint's timesteps: a checkpoint taken mid-episode
        # counts steps of an episode the resumed run starts again
        remaining = (target - done + cfg.train.envs) * cfg.sim.episode_steps * cfg.scenario.agents
        t0 = time.perf_counter()
        model.learn(total_timesteps=remaining, callback=callback, reset_num_timesteps=not resume,
                    tb_log_name="tb", progress_bar=False)
        done = callback.episodes
        wall = time.perf_counter() - t0
        if stop.requested and done == 0 and not resume:
            raise KeyboardInterrupt  # stopped before its first episode: train() removes the new run folder
        save_checkpoint(model, folder, done, algo)  # also at the end: a finished run can be extended
        if not stop.requested and done >= cfg.train.episodes:
            model.save(folder.model)
        record_session(folder.path, {
            "episodes_done": done, "timesteps": int(model.num_timesteps), "wall_s": wall,
            "steps_per_s": (model.num_timesteps - timesteps) / wall if wall > 0 else None,
            "stopped_by": stop.signal_name or None, "first_episode": first_episode, "started": started,
            "ended": datetime.now(timezone.utc).isoformat(timespec="seconds"), "versions": session_versions})
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if log is not None:
            log.close()
        env.close()
    return folder.path, done

"""``lanefree train``: train an agent (or a batch of seeds) into a run folder; ``--resume`` continues one."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from lanefree_sumo import argtypes
from lanefree_sumo.config import LaneFreeConfig, merge_config
from lanefree_sumo.errors import EXIT_INTERRUPTED, UsageError
from lanefree_sumo.options import DENSITY, SEED, Option, add_options, add_retired_flags, command_line, verb_config
from lanefree_sumo.rl.algorithms import help_text as algorithms_help

DEFAULTS = LaneFreeConfig()
EPISODE_S = DEFAULTS.sim.episode_steps * DEFAULTS.sim.step_s

OPTIONS: tuple[Option, ...] = (
    Option("--algo", "train.algo", note=algorithms_help()),
    Option("--reward", "reward.preset"),
    DENSITY,
    Option("--episodes", "train.episodes", unit="episodes",
           note=f"{DEFAULTS.sim.episode_steps} steps = {EPISODE_S:g} s by default"),
    SEED,
    Option("--seeds", type=argtypes.seeds, default=None, extra={"metavar": "A-B"},
           note="train these seeds (a range A-B or a list A,B,C) as one batch in one process, one run folder each "
           "under --out (ddpg, td3 and the DQN family: the vector or the set observation, the ring, the on-ramp, the "
           "shield, several agents or environments; on the numpy backend)"),
    Option("--obs", "observation.kind"),
    Option("--encoder", "observation.encoder"),
    Option("--envs", "train.envs", unit="environments"),
    Option("--scenario", "road.kind",
           note="on the on-ramp the learning vehicle starts on the ramp (road.onramp.agent_start) with 4 more ego "
           "features (its boundaries, on the ramp, room to the ramp's end)"),
    Option("--agents", "scenario.agents", unit="vehicles",
           note="all driven and trained by one shared policy; episodes.csv gets a row per agent and episode "
           "(1: LaneFree-v0)"),
    Option("--episode-steps", "sim.episode_steps", unit="steps", note=f"of {DEFAULTS.sim.step_s:g} s each"),
    Option("--checkpoint-every", "train.checkpoint_every_episodes", unit="episodes"),
    Option("--out", type=Path, note="run folder (default runs/<date-time>_...)"),
    Option("--resume", type=Path, default=None, extra={"metavar": "RUN"},
           note="continue RUN from its newest checkpoint with the options in RUN/config.yaml; with --episodes N, "
           "extend RUN (finished or not) to N episodes; other options are refused. A batch folder (made by "
           "--seeds) continues the whole batch"),
    Option("--backend", "train.backend"),
    Option("--device", "train.device"),
    Option("--shield", "shield.enabled", note="run folder ..._shield"),
)


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """The ``train`` sub-command's parser."""
    p = subparsers.add_parser(
        "train",
        help="train an agent; writes a run folder under runs/",
        description="Train an agent on LaneFree-v0 with the paper's hyperparameters (docs/specification.md "
        "§9) and write a run folder runs/<date-time>_<algo>_<reward>_d<density>_s<seed>/ (config.yaml, "
        "command.txt, versions.json, episodes.csv, TensorBoard logs in tb/, checkpoints/, model.zip). Ctrl-C or "
        "SIGTERM saves a checkpoint; --resume RUN continues from the newest one.",
    )
    add_options(p, OPTIONS)
    add_retired_flags(p, "train.overlap")
    argtypes.add_config_options(p)
    return p


def run(args: argparse.Namespace) -> int:
    """``lanefree train``: train (or resume) and say how many episodes; EXIT_INTERRUPTED when stopped early."""
    from lanefree_sumo.experiments.runners.batch import is_batch
    from lanefree_sumo.experiments.runners.train import train

    if args.resume is not None and is_batch(args.resume):
        extra = ", ".join(sorted(args.given - {"--resume"}))
        if extra:
            raise UsageError(f"--resume {args.resume} continues a batch with its saved options; {extra} cannot be "
                             "given (a batch is not extended)")
        return report_batch(_resume_batch(args.resume))
    if args.resume is not None and is_batch(args.resume.parent):
        if (args.resume / "model.zip").is_file():  # finished: the batch cannot go on, and its runs are not extended
            raise UsageError(f"{args.resume} is a finished run of the batch {args.resume.parent}; a batch's runs are "
                             "not extended: train more episodes as a new batch (lanefree train --seeds … --episodes N "
                             "--out NEW), or evaluate and report it as it is")
        raise UsageError(f"{args.resume} is a run of the batch {args.resume.parent}; resume the whole batch with: "
                         f"lanefree train --resume {args.resume.parent}")
    if args.resume is not None:
        ignored = sorted(args.given - {"--resume", "--episodes"})
        if ignored:
            raise UsageError(f"--resume continues RUN with the options saved in RUN/config.yaml; {', '.join(ignored)} "
                             "cannot be changed (only --episodes N, to extend the run to N episodes)")
        run, done = train(LaneFreeConfig(), run=args.resume, resume=True,
                          episodes=args.episodes if "--episodes" in args.given else None)
    else:
        cfg = verb_config(args, OPTIONS)
        if args.seeds is not None:
            return report_batch(_train_batch(args, cfg))
        run, done = train(cfg, run=args.out)
    target = _episodes_target(run)
    if done < target:
        print(f"stopped after {done}/{target} episodes; checkpoint saved. Resume with: lanefree train --resume {run}",
              file=sys.stderr)
        return EXIT_INTERRUPTED
    from lanefree_sumo.experiments.analysis.markdown import count
    from lanefree_sumo.experiments.storage.rundir import read_sessions

    sessions = read_sessions(run)  # this session's first episode: a resume trains the rest only
    now = done - int(sessions[-1].get("first_episode", 1)) + 1 if sessions else done
    print(f"trained {count(now, 'episode')}" + (f" ({done} of {target} in all)" if now != done else "") + f" -> {run}")
    return 0


def _train_batch(args: argparse.Namespace, cfg: LaneFreeConfig) -> list[tuple[Path, int]]:
    """``lanefree train --seeds``: the seeds as one batch under ``--out``."""
    from datetime import datetime

    from lanefree_sumo.experiments.runners.batch import check_batchable, train_batch

    if "--seed" in args.given or any(key == "seed" for key, _ in args.settings):
        given = "--seed" if "--seed" in args.given else "--set seed=…"
        raise UsageError(f"{given} and --seeds exclude each other; give the batch's seeds with --seeds only")
    check_batchable(cfg)
    seeds = args.seeds
    out = args.out or Path("runs") / (f"{datetime.now():%Y%m%d-%H%M%S}_{cfg.train.algo}_{cfg.reward.preset}"
                                      f"_d{cfg.scenario.density_veh_per_km:g}_s{seeds[0]}-{seeds[-1]}")
    return train_batch([merge_config(cfg, {"seed": s}) for s in seeds], out, command=command_line())


def _resume_batch(folder: Path) -> list[tuple[Path, int]]:
    from lanefree_sumo.experiments.runners.batch import resume_batch

    return resume_batch(folder, command=command_line())


def report_batch(results: list[tuple[Path, int]]) -> int:
    """Print each run's outcome; EXIT_INTERRUPTED when a run is short of its episodes by an interruption (a run
    stopped for a non-finite action is named with its reason: resuming would not continue it)."""
    from lanefree_sumo.experiments.analysis.markdown import count
    from lanefree_sumo.experiments.storage.rundir import read_sessions

    short = False
    for run, done in results:
        target = _episodes_target(run)
        reason = (read_sessions(run) or [{}])[-1].get("stopped_by") or ""
        diverged = "not finite" in reason  # stopped for good: resuming does not continue it
        short |= done < target and not diverged
        what = f"trained {count(done, 'episode')}" if done >= target else f"stopped after {done}/{target} episodes"
        print(f"{what} -> {run}" + (f" ({reason})" if diverged else ""))
    if short:
        print(f"resume the batch with: lanefree train --resume {results[0][0].parent}", file=sys.stderr)
    return EXIT_INTERRUPTED if short else (1 if any(done < _episodes_target(r) for r, done in results) else 0)


def _episodes_target(run: Path) -> int:
    from lanefree_sumo.experiments.storage.rundir import read_config

    return read_config(run).train.episodes

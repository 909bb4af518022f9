"""``lanefree`` command line: ``simulate`` (background traffic), ``train``, ``evaluate``,
``rollout`` (built-in or trained policy, optionally shielded), ``replay`` (sumo-gui), ``export``
(CSV + FCD XML), ``report`` (figures, tables) and ``net``.

This module parses and dispatches only; the work is in :mod:`lanefree_sumo.experiments`.
Every default shown in ``--help`` comes from :mod:`lanefree_sumo.config`. Every
:class:`~lanefree_sumo.errors.LaneFreeError` ends in ONE line on stderr saying what was wrong and
what to do, with its exit code (2 for bad input, 1 when SUMO fails); 130 on Ctrl-C.
"""

from __future__ import annotations

import argparse
import json
import shlex
import shutil
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from lanefree_sumo import argtypes
from lanefree_sumo.config import (
    BACKENDS,
    DEVICES,
    OBSERVATION_KINDS,
    ROAD_KINDS,
    EvaluationConfig,
    LaneFreeConfig,
    ReplayConfig,
    ReportConfig,
    layered_config,
    merge_config,
    nested_overrides,
)
from lanefree_sumo.errors import EXIT_INTERRUPTED, LaneFreeError, OperatingSystemError, UsageError, os_error_message
from lanefree_sumo.experiments import mixed_autonomy, rollout
from lanefree_sumo.experiments.signals import sigterm_as_interrupt
from lanefree_sumo.experiments.sweep import command as sweep_command
from lanefree_sumo.rl.algorithms import ALGORITHM_NAMES
from lanefree_sumo.rl.algorithms import help_text as algorithms_help
from lanefree_sumo.rl.rewards import PRESETS

EXIT_BAD_INPUT = 2
EXIT_BUG = 3
DEFAULTS = LaneFreeConfig()
EVAL = EvaluationConfig()
REPLAY = ReplayConfig()
REPORT = ReportConfig()


class _Parser(argparse.ArgumentParser):
    """argparse that reports errors as one line instead of usage + error, and takes no
    abbreviated options (``--dens`` is an error, not ``--density``)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> None:  # type: ignore[override]
        raise UsageError(f"{self.prog}: {message} (see '{self.prog} --help')")


def _build_config(args: argparse.Namespace, options: Sequence[tuple[str, tuple[str, ...], Any]],
                  extra: Mapping[str, Any] | None = None) -> LaneFreeConfig:
    """The config of a verb: the defaults, then ``--config FILE``, then the verb's ``options`` ((dotted key,
    option names, value): all of them without a file, only those given on the command line with one), then
    ``extra`` (overrides the verb derives), then every ``--set``; validated whole."""
    chosen = [(key, value) for key, names, value in options if args.config is None or args.given & set(names)]
    return layered_config(LaneFreeConfig(), args.config, [nested_overrides(chosen), extra or {}], args.settings)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="lanefree", description="Deep RL in lane-free traffic on Eclipse SUMO.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)

    sim = sub.add_parser(
        "simulate",
        help="run background traffic only and write trajectories and a summary",
        description="Run the force-based background traffic on the ring road (or the on-ramp) and write a "
        "per-step trajectory CSV (t, id, x, y, vx, vy, ax, ay) plus summary.json, config.yaml and command.txt "
        "into --out.",
    )
    density = DEFAULTS.scenario.density_veh_per_km
    episode_s = DEFAULTS.sim.episode_steps * DEFAULTS.sim.step_s
    onramp = DEFAULTS.road.onramp
    sim.add_argument("--scenario", choices=ROAD_KINDS, default=DEFAULTS.road.kind,
                     help="ring: the paper's 500 m ring; onramp: an open road with an on-ramp (its sizes and demands: "
                     f"road.onramp in 'lanefree config') (default {DEFAULTS.road.kind})")
    sim.add_argument("--main-flow", type=argtypes.nonnegative(float, "veh/h"), default=None,
                     help=f"on-ramp: demand at the main road's upstream end in veh/h (default "
                     f"{onramp.main_flow_veh_per_h:g})")
    sim.add_argument("--ramp-flow", type=argtypes.nonnegative(float, "veh/h"), default=None,
                     help=f"on-ramp: demand at the ramp in veh/h (default {onramp.ramp_flow_veh_per_h:g})")
    sim.add_argument("--density", type=argtypes.density, default=density,
                     help=f"background density in veh/km (default {density:g}; on the on-ramp: of the main road "
                     "at the start)")
    sim.add_argument("--seconds", type=argtypes.positive(float, "s"), default=episode_s,
                     help=f"simulated time in s (default {episode_s:g} = {DEFAULTS.sim.episode_steps} steps of "
                     f"{DEFAULTS.sim.step_s:g} s)")
    sim.add_argument("--seed", type=int, default=DEFAULTS.seed,
                     help=f"random seed of the initial traffic (default {DEFAULTS.seed})")
    sim.add_argument("--out", type=Path, default=None,
                     help="output folder (default runs/sim-d<density>-s<seed>, on the on-ramp "
                     "runs/sim-onramp-d<density>-s<seed>); refused if it exists")
    sim.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    sim.add_argument("--backend", choices=BACKENDS, default=DEFAULTS.backend,
                     help=f"libsumo (SUMO in-process), traci (SUMO over a socket) or numpy (no SUMO); "
                     f"default {DEFAULTS.backend}")
    sim.add_argument("--gui", action="store_true", help="show the run in sumo-gui (uses the TraCI backend)")
    sim.add_argument("--nudging", action="store_true", help="switch on nudging by vehicles behind (off in the paper)")
    sim.add_argument("--net", type=Path, default=None,
                     help="SUMO network file (default: the committed 500 m × 10.2 m ring)")
    sim.add_argument("--length", type=argtypes.positive(float, "m"), default=None,
                     help=f"ring length in m (default {DEFAULTS.road.length_m:g})")
    sim.add_argument("--width", type=argtypes.positive(float, "m"), default=None,
                     help=f"road width in m (default {DEFAULTS.road.width_m:g})")
    sim.add_argument("--json", action="store_true", help="print the summary as one JSON object on stdout's last line")
    argtypes.add_config_options(sim)
    sim.add_argument("--no-trajectory", action="store_true", help="skip the per-step trajectory CSV")

    tr = sub.add_parser(
        "train",
        help="train an agent; writes a run folder under runs/",
        description="Train an agent on LaneFree-v0 with the paper's hyperparameters (docs/specification.md "
        "§9) and write a run folder runs/<date-time>_<algo>_<reward>_d<density>_s<seed>/ (config.yaml, "
        "command.txt, versions.json, episodes.csv, TensorBoard logs in tb/, checkpoints/, model.zip). Ctrl-C or "
        "SIGTERM saves a checkpoint; --resume RUN continues from the newest one.",
    )
    t = DEFAULTS.train
    tr.add_argument("--algo", choices=ALGORITHM_NAMES, default=t.algo,
                    help=f"algorithm (default {t.algo}): {algorithms_help()}")
    tr.add_argument("--reward", choices=tuple(PRESETS), default=DEFAULTS.reward.preset,
                    help=f"reward preset of docs/specification.md §7 (default {DEFAULTS.reward.preset})")
    tr.add_argument("--density", type=argtypes.density, default=density,
                    help=f"background density in veh/km (default {density:g})")
    tr.add_argument("--episodes", type=argtypes.positive(int, "episodes"), default=t.episodes,
                    help=f"training episodes of {DEFAULTS.sim.episode_steps} steps = {episode_s:g} s each "
                    f"(default {t.episodes})")
    tr.add_argument("--seed", type=int, default=DEFAULTS.seed,
                    help=f"random seed of networks and traffic (default {DEFAULTS.seed})")
    tr.add_argument("--seeds", type=argtypes.seeds, default=None, metavar="A-B",
                    help="train these seeds (a range A-B or a list A,B,C) as one batch in one process, one run "
                    "folder each under --out (ddpg and the DQN family, one agent on the ring, vector observation)")
    tr.add_argument("--obs", choices=OBSERVATION_KINDS, default=DEFAULTS.observation.kind,
                    help="vector = the paper's 5 nearest; set = every vehicle in range through the set encoder "
                    f"(default {DEFAULTS.observation.kind})")
    tr.add_argument("--encoder", choices=("small", "paper"), default=DEFAULTS.observation.encoder,
                    help="set encoder, only with --obs set: small = the project's d1 = d2 = 8 (64 features); "
                    "paper = Liu et al. Table 1 (f1, f2 5x256 ReLU, mean over one axis, 256x256 ReLU feature "
                    f"layer) (default {DEFAULTS.observation.encoder})")
    tr.add_argument("--envs", type=argtypes.positive(int, "processes"), default=t.envs,
                    help=f"parallel environments, one process each (default {t.envs})")
    tr.add_argument("--scenario", choices=ROAD_KINDS, default=DEFAULTS.road.kind,
                    help="ring: the paper's ring; onramp: the open road with an on-ramp, the learning vehicle starting "
                    "on the ramp (road.onramp.agent_start) with 4 more ego features (its boundaries, on the ramp, "
                    f"room to the ramp's end) (default {DEFAULTS.road.kind})")
    tr.add_argument("--agents", type=argtypes.positive(int, "vehicles"), default=DEFAULTS.scenario.agents,
                    help="learning vehicles on the ring, on top of the background traffic, all driven and trained "
                    "by one shared policy; episodes.csv gets a row per agent and episode "
                    f"(default {DEFAULTS.scenario.agents}: LaneFree-v0)")
    tr.add_argument("--episode-steps", type=argtypes.positive(int, "steps"), default=DEFAULTS.sim.episode_steps,
                    help=f"steps of {DEFAULTS.sim.step_s:g} s per episode (default {DEFAULTS.sim.episode_steps} = "
                    f"{episode_s:g} s, the paper's)")
    tr.add_argument("--checkpoint-every", type=argtypes.positive(int, "episodes"), default=t.checkpoint_every_episodes,
                    help=f"save a checkpoint every K episodes (default {t.checkpoint_every_episodes})")
    tr.add_argument("--out", type=Path, default=None, help="run folder (default runs/<date-time>_...)")
    tr.add_argument("--resume", type=Path, default=None, metavar="RUN",
                    help="continue RUN from its newest checkpoint with the options in RUN/config.yaml; with "
                    "--episodes N, extend RUN (finished or not) to N episodes; other options are refused. A batch "
                    "folder (made by --seeds) continues the whole batch")
    tr.add_argument("--backend", choices=BACKENDS, default=t.backend,
                    help=f"simulation backend (default {t.backend}: the same episodes as libsumo bit for bit, "
                    "without SUMO; libsumo/traci train inside SUMO)")
    tr.add_argument("--device", choices=DEVICES, default=t.device,
                    help=f"where a batch (--seeds) simulates and learns: cpu (numpy, bit for bit the single runs) "
                    f"or cuda (torch on the GPU) (default {t.device})")
    argtypes.add_config_options(tr)
    tr.add_argument("--shield", action="store_true",
                    help="learn with the safety shield on every action (run folder ..._shield)")
    tr.add_argument("--overlap", action=argparse.BooleanOptionalAction, default=t.overlap,
                    help="DDPG: step the environment on a second core while the learner updates; the acting policy "
                    f"then lags the learner by one update (default {'on' if t.overlap else 'off'}: SB3's order, "
                    "bit for bit)")

    ev = sub.add_parser(
        "evaluate",
        help="run a trained policy deterministically on fresh seeds",
        description="Evaluate RUN's final model (or newest checkpoint) deterministically; writes RUN/eval/episodes.csv "
        "(RUN/eval_d<density>/ at another density, RUN/eval_onramp/ on the on-ramp) and, with --record, one "
        "trajectory CSV of all vehicles per episode.",
    )
    ev.add_argument("run", type=Path, metavar="RUN", help="run folder made by 'lanefree train'")
    ev.add_argument("--episodes", type=argtypes.positive(int, "episodes"), default=EVAL.episodes,
                    help=f"episodes (default {EVAL.episodes})")
    ev.add_argument("--density", type=argtypes.density, default=None, help="veh/km (default: the training density)")
    ev.add_argument("--seed", type=argtypes.seed, default=None,
                    help=f"base seed; episode k uses seed+{EVAL.seed_offset}+k (default: the training seed)")
    ev.add_argument("--record", action="store_true", help="write trajectories/episode_NNNN.csv of every vehicle")
    ev.add_argument("--out", type=Path, default=None,
                    help="output folder (default RUN/eval, RUN/eval_d<density>, RUN/eval_onramp[_d<density>], "
                    "with _shield or _noshield appended when --shield changes the run's setting)")
    ev.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    ev.add_argument("--shield", action=argparse.BooleanOptionalAction, default=None,
                    help="switch the safety shield on (or off) for this evaluation, e.g. an unshielded policy "
                    "shielded (default: as trained; output eval_shield/ or eval_noshield/)")
    ev.add_argument("--scenario", choices=("ring", "onramp"), default=None,
                    help="the road to evaluate on (default: the run's own); onramp drives a ring-trained policy "
                    "on the on-ramp's main road with the ring's observation, output eval_onramp/")

    rollout.add_parser(sub)

    rp = sub.add_parser(
        "replay",
        help="replay a recorded evaluation episode in sumo-gui",
        description="Replay episode K recorded by 'lanefree evaluate RUN --record' in sumo-gui, exactly, step by step: "
        "the agent green and tracked, background vehicles coloured by desired speed (blue slow, orange fast), "
        "overlapping vehicles red. Prints the largest deviation between SUMO and the recording.",
    )
    rp.add_argument("run", type=Path, metavar="RUN", help="run folder (or its eval folder) with a recording")
    rp.add_argument("--episode", type=argtypes.positive(int, "episodes"), default=1,
                    help="recorded episode number (default 1)")
    rp.add_argument("--delay", type=argtypes.nonnegative(float, "s"), default=REPLAY.delay_s,
                    help=f"wall-clock delay per step in s (default {REPLAY.delay_s:g})")
    rp.add_argument("--screenshot", type=Path, default=None, help="save a PNG of the view at --screenshot-step")
    rp.add_argument("--screenshot-step", type=argtypes.positive(int, "steps"), default=None,
                    help="step of the screenshot (default: the last)")
    rp.add_argument("--frames", type=Path, default=None, help="folder for one PNG per --every steps")
    rp.add_argument("--every", type=argtypes.positive(int, "steps"), default=1,
                    help="frame interval in steps (default 1)")
    rp.add_argument("--gif", type=Path, default=None, help="write an animated GIF of the frames")
    size = "x".join(map(str, REPLAY.size_px))
    rp.add_argument("--size", type=argtypes.size, default=REPLAY.size_px,
                    help=f"view size WIDTHxHEIGHT in pixels (default {size})")
    rp.add_argument("--zoom", type=argtypes.positive(float, "%"), default=None,
                    help=f"view zoom in %% (default {REPLAY.zoom_percent:g} on the ring, "
                         f"{REPLAY.onramp_zoom_percent:g} on the on-ramp)")
    rp.add_argument("--no-gui", action="store_true", help="replay without a window (with --fcd: export only)")
    rp.add_argument("--fcd", type=Path, default=None, help="also write SUMO FCD XML (with posLat) of the replay")

    ex = sub.add_parser(
        "export",
        help="export a recorded episode as CSV and SUMO FCD XML",
        description="Write episode K of RUN's recording as trajectory CSV and as SUMO's own FCD XML (x, y, angle, "
        "type, speed, pos, lane, posLat) into --out, by replaying it headless in SUMO.",
    )
    ex.add_argument("run", type=Path, metavar="RUN", help="run folder (or its eval folder) with a recording")
    ex.add_argument("--episode", type=argtypes.positive(int, "episodes"), default=1,
                    help="recorded episode (default 1)")
    ex.add_argument("--out", type=Path, default=None, help="output folder (default RUN/eval/export)")
    ex.add_argument("--overwrite", action="store_true", help="replace existing export files")

    rep = sub.add_parser(
        "report",
        help="learning curves and paper-style tables from run folders",
        description="Group run folders by (algorithm, reward preset, density, variant: every other setting in "
        "which a run's config differs from the defaults, e.g. shield.enabled=True), average the seeds, and write "
        "learning curves (return, collisions, speed deviation per episode; mean ± std over seeds, smoothed) as PNG "
        "and a table of last-50-episode means ± std with the paper's numbers (docs/specification.md §10) as "
        "summary.csv and summary.md. Unusable runs are named and skipped. Given a sweep folder (one with "
        "sweep.yaml), writes the sweep's summary into it instead: last-50 means with 95 % bootstrap CIs over "
        "seeds, as 'lanefree sweep'.",
    )
    rep.add_argument("runs", type=Path, nargs="*", metavar="RUN",
                     help="run folders made by 'lanefree train', or ONE sweep folder made by 'lanefree sweep' "
                     "(at least one)")
    rep.add_argument("--out", type=Path, default=Path("report"),
                     help="output folder (default report/: outside runs/, which holds run folders only)")
    rep.add_argument("--last", type=argtypes.positive(int, "episodes"), default=REPORT.last_episodes,
                     help=f"episodes at the end of each run averaged in the table (default {REPORT.last_episodes}, "
                     "as the paper)")
    rep.add_argument("--smooth", type=argtypes.positive(int, "episodes"), default=REPORT.smooth_episodes,
                     help="trailing moving-average window of the curves in episodes "
                     f"(default {REPORT.smooth_episodes})")
    rep.add_argument("--eval", nargs="*", default=None, metavar="NAME",
                     help="tabulate each run's evaluation RUN/NAME/episodes.csv (default NAME eval; e.g. "
                     "eval_d120, eval_shield) instead of its training episodes, at the evaluated density; several "
                     "NAMEs: the evaluations side by side in one table and two bar charts "
                     "(evaluations_collisions.png, evaluations_speed_dev.png), no learning curves. Put the RUN "
                     "folders before --eval")

    sweep_command.add_parser(sub)
    mixed_autonomy.add_parser(sub)

    conf = sub.add_parser(
        "config",
        help="print the resolved config as YAML, each key with its unit and meaning",
        description="Print the configuration that 'lanefree train' / 'simulate' would start from (the defaults, "
        "then --config FILE, then every --set) as YAML, with each key's unit, allowed values and meaning as a "
        "comment. Save it, edit it, and pass it back with --config FILE.",
    )
    argtypes.add_config_options(conf)

    net = sub.add_parser(
        "net",
        help="build a ring network with netconvert",
        description="Write plain node/edge files of a one-lane ring and build the SUMO network with netconvert.",
    )
    net.add_argument("--length", type=argtypes.positive(float, "m"), default=DEFAULTS.road.length_m,
                     help=f"centre-line length in m (default {DEFAULTS.road.length_m:g})")
    net.add_argument("--width", type=argtypes.positive(float, "m"), default=DEFAULTS.road.width_m,
                     help=f"road (lane) width in m (default {DEFAULTS.road.width_m:g})")
    net.add_argument("--out-dir", type=Path, default=None, help="folder for the files (default sumo_nets/)")
    return parser


ROAD_OPTIONS: dict[str, tuple[str, ...]] = {"ring": ("--length",), "onramp": ("--main-flow", "--ramp-flow")}
"""``simulate``'s options that size or feed one road only."""


def _check_road_options(args: argparse.Namespace, cfg: LaneFreeConfig) -> None:
    """Refuse an option of another road than ``cfg``'s: it would be ignored."""
    for road, names in ROAD_OPTIONS.items():
        given = sorted(args.given & set(names))
        if road != cfg.road.kind and given:
            lengths = ("; the on-ramp's lengths are road.onramp.upstream_m, ramp_m, merge_m and downstream_m "
                       "(--set)") if road == "ring" else ""
            raise UsageError(f"{given[0]} applies to --scenario {road} only, not to the {cfg.road.kind}{lengths}")


def _simulate(args: argparse.Namespace) -> int:
    options: list[tuple[str, tuple[str, ...], Any]] = [
        ("seed", ("--seed",), args.seed),
        ("road.kind", ("--scenario",), args.scenario),
        ("backend", ("--backend",), args.backend),
        ("scenario.density_veh_per_km", ("--density",), args.density),
        ("scenario.driver.nudging", ("--nudging",), args.nudging),
    ]
    options += [(key, (option,), value) for key, option, value in (
        ("road.length_m", "--length", args.length), ("road.width_m", "--width", args.width),
        ("net_file", "--net", None if args.net is None else str(args.net)),
        ("road.onramp.main_flow_veh_per_h", "--main-flow", args.main_flow),
        ("road.onramp.ramp_flow_veh_per_h", "--ramp-flow", args.ramp_flow)) if value is not None]
    cfg = _build_config(args, options, {"gui": True, "backend": "traci"} if args.gui else None)
    _check_road_options(args, cfg)
    from lanefree_sumo.experiments.simulate import simulate

    road = "" if cfg.road.kind == "ring" else f"{cfg.road.kind}-"  # a ring and an on-ramp run do not collide
    out = args.out or Path("runs") / f"sim-{road}d{cfg.scenario.density_veh_per_km:g}-s{cfg.seed}"
    summary = simulate(cfg, args.seconds, out, _command(), overwrite=args.overwrite,
                       write_trajectory=not args.no_trajectory, progress=not args.json)
    if args.json:
        print(json.dumps(summary))
    else:
        print(
            f"{summary['steps']} steps, {summary['vehicles']} vehicles, "
            f"{summary['background_collisions']} collisions, mean speed {summary['mean_speed_mps']:.2f} m/s "
            f"(desired {summary['mean_desired_speed_mps']:.2f}), min margin {summary['min_lateral_margin_m']:.3f} m, "
            f"{summary['wall_s']:.1f} s -> {out}"
        )
        if "onramp" in summary:
            o = summary["onramp"]
            print(f"on-ramp: {o['entered_main']} entered the main road, {o['entered_ramp']} the ramp, "
                  f"{o['left']} left, "
                  f"{o['on_road']} on the road at the end; {o['merged']} merged, {o['ramp_end_reached_unmerged']} "
                  f"reached the ramp's end unmerged; outflow {o['outflow_veh_per_h']:.0f} veh/h")
    return 0 if not summary["interrupted"] else EXIT_INTERRUPTED


def _train(args: argparse.Namespace) -> int:
    from lanefree_sumo.experiments.batch import is_batch
    from lanefree_sumo.experiments.train import train

    if args.resume is not None and is_batch(args.resume):
        extra = ", ".join(sorted(args.given - {"--resume"}))
        if extra:
            raise UsageError(f"--resume {args.resume} continues a batch with its saved options; {extra} cannot be "
                             "given (a batch is not extended)")
        return _report_batch(_resume_batch(args.resume))
    if args.resume is not None and is_batch(args.resume.parent):
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
        cfg = _build_config(args, [
            ("seed", ("--seed",), args.seed),
            ("scenario.density_veh_per_km", ("--density",), args.density),
            ("reward.preset", ("--reward",), args.reward),
            ("observation.kind", ("--obs",), args.obs),
            ("observation.encoder", ("--encoder",), args.encoder),
            ("shield.enabled", ("--shield",), args.shield),
            ("sim.episode_steps", ("--episode-steps",), args.episode_steps),
            ("train.algo", ("--algo",), args.algo),
            ("train.episodes", ("--episodes",), args.episodes),
            ("train.envs", ("--envs",), args.envs),
            ("scenario.agents", ("--agents",), args.agents),
            ("road.kind", ("--scenario",), args.scenario),
            ("train.backend", ("--backend",), args.backend),
            ("train.device", ("--device",), args.device),
            ("train.overlap", ("--overlap", "--no-overlap"), args.overlap),
            ("train.checkpoint_every_episodes", ("--checkpoint-every",), args.checkpoint_every),
        ])
        if args.seeds is not None:
            return _report_batch(_train_batch(args, cfg))
        run, done = train(cfg, run=args.out)
    target = _episodes_target(run)
    if done < target:
        print(f"stopped after {done}/{target} episodes; checkpoint saved. Resume with: lanefree train --resume {run}",
              file=sys.stderr)
        return EXIT_INTERRUPTED
    from lanefree_sumo.experiments.markdown import count
    from lanefree_sumo.experiments.rundir import read_sessions

    sessions = read_sessions(run)  # this session's first episode: a resume trains the rest only
    now = done - int(sessions[-1].get("first_episode", 1)) + 1 if sessions else done
    print(f"trained {count(now, 'episode')}" + (f" ({done} of {target} in all)" if now != done else "") + f" -> {run}")
    return 0


def _train_batch(args: argparse.Namespace, cfg: LaneFreeConfig) -> list[tuple[Path, int]]:
    """``lanefree train --seeds``: the seeds as one batch under ``--out``."""
    from datetime import datetime

    from lanefree_sumo.config import merge_config
    from lanefree_sumo.experiments.batch import check_batchable, train_batch

    if "--seed" in args.given:
        raise UsageError("--seed and --seeds exclude each other; give the batch's seeds with --seeds only")
    check_batchable(cfg)
    seeds = args.seeds
    out = args.out or Path("runs") / (f"{datetime.now():%Y%m%d-%H%M%S}_{cfg.train.algo}_{cfg.reward.preset}"
                                      f"_d{cfg.scenario.density_veh_per_km:g}_s{seeds[0]}-{seeds[-1]}")
    return train_batch([merge_config(cfg, {"seed": s}) for s in seeds], out, command=_command())


def _resume_batch(folder: Path) -> list[tuple[Path, int]]:
    from lanefree_sumo.experiments.batch import resume_batch

    return resume_batch(folder, command=_command())


def _report_batch(results: list[tuple[Path, int]]) -> int:
    """Print each run's outcome; EXIT_INTERRUPTED when a run is short of its episodes by an interruption (a run
    stopped for a non-finite action is named with its reason: resuming would not continue it)."""
    from lanefree_sumo.experiments.markdown import count
    from lanefree_sumo.experiments.rundir import read_sessions

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
    from lanefree_sumo.experiments.rundir import read_config

    return read_config(run).train.episodes


def _command() -> str:
    """The command line as typed, for command.txt."""
    return shlex.join(["lanefree", *sys.argv[1:]])


def _evaluate(args: argparse.Namespace) -> int:
    from lanefree_sumo.experiments.evaluate import evaluate, summary_line

    result = evaluate(args.run, episodes=args.episodes, density=args.density, seed=args.seed, record=args.record,
                      out=args.out, overwrite=args.overwrite, shield=args.shield,
                      scenario=args.scenario)
    if result.kept_earlier:
        print(f"lanefree: interrupted; the earlier evaluation in {result.out} is kept (the new one was not complete)",
              file=sys.stderr)
        return EXIT_INTERRUPTED
    if result.interrupted:
        print(f"lanefree: interrupted; kept {result.episodes} complete episode(s) in {result.out}", file=sys.stderr)
        return EXIT_INTERRUPTED
    print(summary_line(result))
    return 0


def _replay(args: argparse.Namespace) -> int:
    from lanefree_sumo.experiments.replay import replay

    result = replay(args.run, episode=args.episode, gui=not args.no_gui, delay_s=args.delay,
                    screenshot=args.screenshot, screenshot_step=args.screenshot_step, frames=args.frames,
                    every=args.every, gif=args.gif, fcd=args.fcd, size=args.size, zoom=args.zoom)
    print(f"replayed {result.steps} steps; largest deviation from the recording: "
          f"x {result.max_dx_m:.2e} m, y {result.max_dy_m:.2e} m")
    return 0


def _export(args: argparse.Namespace) -> int:
    from lanefree_sumo.experiments.replay import replay
    from lanefree_sumo.experiments.rundir import OUTPUT_MARKER, check_new_file, find_eval_dir, new_file, trajectory_path

    source = trajectory_path(find_eval_dir(args.run), args.episode)
    out = args.out or find_eval_dir(args.run) / "export"
    csv_out = out / f"episode_{args.episode:04d}.csv"
    fcd_out = out / f"episode_{args.episode:04d}.fcd.xml"
    for target in (csv_out, fcd_out):  # before any work: never a run's file, never a folder not export's own
        check_new_file(target, args.overwrite, "export", marker_folder=True)
    if not (out / OUTPUT_MARKER).exists() and not any(out.iterdir()):
        (out / OUTPUT_MARKER).write_text("export\n")
    result = replay(args.run, episode=args.episode, gui=False, fcd=fcd_out, overwrite=args.overwrite,
                    verb="export")
    with new_file(csv_out, "export") as tmp:
        shutil.copyfile(source, tmp)
    print(f"exported {result.steps} steps -> {csv_out} and {fcd_out}")
    return 0


def _report(args: argparse.Namespace) -> int:
    from lanefree_sumo.experiments.report import report
    from lanefree_sumo.experiments.sweep.manifest import MANIFEST

    sources = _evaluation_names(args.eval)
    if not args.runs:
        raise UsageError("lanefree report needs at least one RUN folder (or one sweep folder), before --eval")
    sweeps = [path for path in args.runs if (path / MANIFEST).is_file()]
    if sweeps:
        return _report_sweep(args, sweeps)
    result = report(args.runs, args.out, last=args.last, smooth=args.smooth, source=sources)
    for path, reason in result.skipped:
        print(f"skipped {path}: {reason}", file=sys.stderr)
    for note in result.notes:
        print(f"note: {note}", file=sys.stderr)
    rows = "group(s)" if isinstance(sources, str) or len(sources) == 1 else "row(s), one per evaluation and group"
    print(f"{len(result.table)} {rows} -> {args.out}")
    print((args.out / "summary.md").read_text())
    return 0


def _evaluation_names(names: list[str] | None) -> list[str] | str:
    """``report --eval``'s names: "" without the option (training episodes), ["eval"] for a bare ``--eval``;
    a path among them is refused (the run folders were put after ``--eval``)."""
    if names is None:
        return ""
    names = [name.rstrip("/") for name in names]
    for name in names:
        if not name or "/" in name or name in (".", ".."):
            raise UsageError(f"--eval takes evaluation folder names inside each run (eval, eval_d120, …), got "
                             f"{name!r}: put the RUN folders before --eval")
    return names or ["eval"]


def _report_sweep(args: argparse.Namespace, sweeps: list[Path]) -> int:
    """``lanefree report SWEEP_DIR``: the sweep's summary with bootstrap CIs, written into it."""
    from lanefree_sumo.experiments.sweep.summary import summarize

    if len(args.runs) > 1:
        raise UsageError(f"{sweeps[0]} is a sweep folder: report it alone (lanefree report {sweeps[0]})")
    if "--out" in args.given or args.eval is not None:
        bad = "--out" if "--out" in args.given else "--eval"
        raise UsageError(f"a sweep's summary is written into the sweep folder {sweeps[0]} from its training runs; "
                         f"drop {bad}")
    result = summarize(sweeps[0], last=args.last, smooth=args.smooth)
    for name, reason in result.incomplete:
        print(f"not in the summary: {name} ({reason})", file=sys.stderr)
    for note in result.notes:
        print(f"note: {note}", file=sys.stderr)
    print(f"{len(result.table)} setting(s) -> {sweeps[0]}")
    print((sweeps[0] / "summary.md").read_text())
    return 0


def _config(args: argparse.Namespace) -> int:
    from lanefree_sumo.config.describe import describe_config

    print(describe_config(_build_config(args, [])), end="")
    return 0


def _net(args: argparse.Namespace) -> int:
    from lanefree_sumo.sim.backends.sumo import build_ring_net
    from lanefree_sumo.sim.network import NETS_DIR

    cfg = merge_config(LaneFreeConfig(), {"road": {"length_m": args.length, "width_m": args.width}})
    net = build_ring_net(cfg, args.out_dir or NETS_DIR)
    print(net)
    return 0


def _end_progress_bars() -> None:
    """Close every progress bar a failed verb left open: each ends its line now (not later, when it is
    collected), so that the error line that follows comes last on stderr, on a line of its own."""
    tqdm_module = sys.modules.get("tqdm")
    if tqdm_module is not None:
        for bar in list(getattr(tqdm_module.tqdm, "_instances", ())):
            bar.close()


def _error(line: str) -> None:
    """Print ``lanefree: LINE`` as the last line of stderr (after any progress bar), whitespace folded."""
    _end_progress_bars()
    print(f"lanefree: {' '.join(line.split())}", file=sys.stderr, flush=True)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``lanefree`` console script."""
    parser = build_parser()
    try:
        argv = list(sys.argv[1:] if argv is None else argv)
        args = parser.parse_args(argv)
        args.given = {token.split("=", 1)[0] for token in argv if token.startswith("--")}
        if args.command is None:
            parser.print_help()
            return EXIT_BAD_INPUT
        handler = {"simulate": _simulate, "train": _train, "evaluate": _evaluate, "rollout": rollout.run,
                   "replay": _replay, "export": _export, "report": _report, "net": _net,
                   "config": _config, "mixed-autonomy": mixed_autonomy.run, "sweep": sweep_command.run}[args.command]
        with sigterm_as_interrupt():  # `kill PID` stops every verb as Ctrl-C does
            return handler(args)
    except LaneFreeError as exc:  # the user's to fix: one line, no traceback
        _error(f"error: {exc}")
        return exc.exit_code
    except KeyboardInterrupt:
        _error("interrupted")
        return EXIT_INTERRUPTED
    except MemoryError:
        _error("error: out of memory; use fewer processes (--envs, --workers) or a smaller buffer")
        return OperatingSystemError.exit_code
    except OSError as exc:  # the operating system's limit, not a bug: one line, named
        _error(f"error: {os_error_message(exc)}")
        return OperatingSystemError.exit_code
    except Exception as exc:  # a bug in lanefree_sumo, not a user mistake
        _error(f"internal error {type(exc).__name__}: {exc} (a bug; please report it with the command line)")
        return EXIT_BUG


if __name__ == "__main__":
    sys.exit(main())

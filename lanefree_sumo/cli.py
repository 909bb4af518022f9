"""``lanefree`` command line: ``simulate`` (background traffic), ``train``, ``evaluate``,
``replay`` (sumo-gui), ``export`` (CSV + FCD XML), ``report`` (figures, tables) and ``net``.

Every bad input ends in ONE line on stderr saying what was wrong and what to do, and a
non-zero exit code (2 for bad input, 1 when SUMO fails, 130 on Ctrl-C); never a traceback.
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import shutil
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import yaml

from lanefree_sumo.config import ConfigError, LaneFreeConfig, config_to_dict, merge_config, validate_density
from lanefree_sumo.experiments.train import RunError

EXIT_BAD_INPUT = 2
EXIT_SUMO = 1
EXIT_INTERRUPTED = 130


class UsageError(Exception):
    """Bad command-line input; the message is the one line shown to the user."""


class _Parser(argparse.ArgumentParser):
    """argparse that reports errors as one line instead of usage + error."""

    def error(self, message: str) -> None:  # type: ignore[override]
        raise UsageError(f"{self.prog}: {message} (see '{self.prog} --help')")


def _density(text: str) -> float:
    try:
        return validate_density(text)
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _positive(kind: type, unit: str):
    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number in {unit}, got {text!r}") from None
        if not (isinstance(value, int) or math.isfinite(value)) or value <= 0:
            raise argparse.ArgumentTypeError(f"expected a positive number in {unit}, got {text!r}")
        return value

    return parse


def _nonnegative(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number in s, got {text!r}") from None
    if not math.isfinite(value) or value < 0:
        raise argparse.ArgumentTypeError(f"expected a non-negative number in s, got {text!r}")
    return value


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT in pixels, e.g. 1024x768, got {text!r}") from None
    if w < 16 or h < 16:
        raise argparse.ArgumentTypeError(f"size must be at least 16x16 pixels, got {text!r}")
    return w, h


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="lanefree", description="Deep RL in lane-free traffic on Eclipse SUMO.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)

    sim = sub.add_parser(
        "simulate",
        help="run background traffic only and write trajectories and a summary",
        description="Run the force-based background traffic on the ring road and write a per-step "
        "trajectory CSV (t, id, x, y, vx, vy, ax, ay) plus summary.json, config.yaml and command.txt "
        "into --out.",
    )
    sim.add_argument("--density", type=_density, default=70.0, help="background density in veh/km (default 70)")
    sim.add_argument("--seconds", type=_positive(float, "s"), default=200.0,
                     help="simulated time in s (default 200 = 800 steps of 0.25 s)")
    sim.add_argument("--seed", type=int, default=0, help="random seed of the initial traffic (default 0)")
    sim.add_argument("--out", type=Path, default=None,
                     help="output folder (default runs/sim-d<density>-s<seed>); refused if it exists")
    sim.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    sim.add_argument("--backend", choices=("libsumo", "traci", "numpy"), default="libsumo",
                     help="libsumo (SUMO in-process, default), traci (SUMO over a socket) or numpy (no SUMO)")
    sim.add_argument("--gui", action="store_true", help="show the run in sumo-gui (uses the TraCI backend)")
    sim.add_argument("--nudging", action="store_true", help="switch on nudging by vehicles behind (off in the paper)")
    sim.add_argument("--net", type=Path, default=None,
                     help="SUMO network file (default: the committed 500 m × 10.2 m ring)")
    sim.add_argument("--length", type=_positive(float, "m"), default=None, help="ring length in m (default 500)")
    sim.add_argument("--width", type=_positive(float, "m"), default=None, help="road width in m (default 10.2)")
    sim.add_argument("--json", action="store_true", help="print the summary as one JSON object on stdout's last line")
    sim.add_argument("--no-trajectory", action="store_true", help="skip the per-step trajectory CSV")

    tr = sub.add_parser(
        "train",
        help="train an agent; writes a run folder under runs/",
        description="Train an agent on LaneFree-v0 with the paper's hyperparameters (SPEC §9) and write a run "
        "folder runs/<date-time>_<algo>_<reward>_d<density>_s<seed>/ (config.yaml, command.txt, versions.json, "
        "episodes.csv, TensorBoard logs in tb/, checkpoints/, model.zip). Ctrl-C or SIGTERM saves a checkpoint; "
        "--resume RUN continues from the newest one.",
    )
    from lanefree_sumo.rl.rewards import PRESETS  # noqa: PLC0415
    from lanefree_sumo.experiments.train import ALGOS  # noqa: PLC0415

    tr.add_argument("--algo", choices=ALGOS, default="ddpg",
                    help="ddpg (default; Ornstein-Uhlenbeck noise), td3, sac, ppo on continuous actions; "
                    "dqn, ddqn (double), dueling (dueling double), per (double + prioritised replay) on the 9 discrete actions")
    tr.add_argument("--reward", choices=tuple(PRESETS), default="fields_zones_overtake_collision",
                    help="reward preset of SPEC §7 (default fields_zones_overtake_collision)")
    tr.add_argument("--density", type=_density, default=70.0, help="background density in veh/km (default 70)")
    tr.add_argument("--episodes", type=_positive(int, "episodes"), default=625,
                    help="training episodes of 800 steps = 200 s each (default 625)")
    tr.add_argument("--seed", type=int, default=0, help="random seed of networks and traffic (default 0)")
    tr.add_argument("--obs", choices=("vector", "set"), default="vector",
                    help="vector = the paper's 5 nearest; set = every vehicle in range through the set encoder")
    tr.add_argument("--envs", type=_positive(int, "processes"), default=1,
                    help="parallel environments, one process each (default 1)")
    tr.add_argument("--episode-steps", type=_positive(int, "steps"), default=800,
                    help="steps of 0.25 s per episode (default 800 = 200 s, the paper's)")
    tr.add_argument("--checkpoint-every", type=_positive(int, "episodes"), default=25,
                    help="save a checkpoint every K episodes (default 25)")
    tr.add_argument("--out", type=Path, default=None, help="run folder (default runs/<date-time>_...)")
    tr.add_argument("--resume", type=Path, default=None, metavar="RUN",
                    help="continue RUN from its newest checkpoint (other options are taken from RUN/config.yaml)")
    tr.add_argument("--backend", choices=("libsumo", "traci", "numpy"), default="libsumo",
                    help="simulation backend (default libsumo; numpy = the same physics without SUMO)")

    ev = sub.add_parser(
        "evaluate",
        help="run a trained policy deterministically on fresh seeds",
        description="Evaluate RUN's final model (or newest checkpoint) deterministically; writes RUN/eval/episodes.csv "
        "(RUN/eval_d<density>/ at another density) and, with --record, one trajectory CSV of all vehicles per episode.",
    )
    ev.add_argument("run", type=Path, metavar="RUN", help="run folder made by 'lanefree train'")
    ev.add_argument("--episodes", type=_positive(int, "episodes"), default=20, help="episodes (default 20)")
    ev.add_argument("--density", type=_density, default=None, help="veh/km (default: the training density)")
    ev.add_argument("--seed", type=int, default=None,
                    help="base seed; episode k uses seed+100000+k (default: the training seed)")
    ev.add_argument("--record", action="store_true", help="write trajectories/episode_NNNN.csv of every vehicle")
    ev.add_argument("--out", type=Path, default=None, help="output folder (default RUN/eval or RUN/eval_d<density>)")
    ev.add_argument("--overwrite", action="store_true", help="replace an existing output folder")

    rp = sub.add_parser(
        "replay",
        help="replay a recorded evaluation episode in sumo-gui",
        description="Replay episode K recorded by 'lanefree evaluate RUN --record' in sumo-gui, exactly, step by step: "
        "the agent green and tracked, background vehicles coloured by desired speed (blue slow, orange fast), "
        "overlapping vehicles red. Prints the largest deviation between SUMO and the recording.",
    )
    rp.add_argument("run", type=Path, metavar="RUN", help="run folder (or its eval folder) with a recording")
    rp.add_argument("--episode", type=_positive(int, "episodes"), default=1, help="recorded episode number (default 1)")
    rp.add_argument("--delay", type=_nonnegative, default=0.05, help="wall-clock delay per step in s (default 0.05)")
    rp.add_argument("--screenshot", type=Path, default=None, help="save a PNG of the view at --screenshot-step")
    rp.add_argument("--screenshot-step", type=_positive(int, "steps"), default=None,
                    help="step of the screenshot (default: the last)")
    rp.add_argument("--frames", type=Path, default=None, help="folder for one PNG per --every steps")
    rp.add_argument("--every", type=_positive(int, "steps"), default=1, help="frame interval in steps (default 1)")
    rp.add_argument("--gif", type=Path, default=None, help="write an animated GIF of the frames")
    rp.add_argument("--size", type=_size, default=(1024, 768), help="view size WIDTHxHEIGHT in pixels (default 1024x768)")
    rp.add_argument("--zoom", type=_positive(float, "%"), default=400.0, help="view zoom in %% (default 400)")
    rp.add_argument("--no-gui", action="store_true", help="replay without a window (with --fcd: export only)")
    rp.add_argument("--fcd", type=Path, default=None, help="also write SUMO FCD XML (with posLat) of the replay")

    ex = sub.add_parser(
        "export",
        help="export a recorded episode as CSV and SUMO FCD XML",
        description="Write episode K of RUN's recording as trajectory CSV and as SUMO's own FCD XML (x, y, angle, "
        "type, speed, pos, lane, posLat) into --out, by replaying it headless in SUMO.",
    )
    ex.add_argument("run", type=Path, metavar="RUN", help="run folder (or its eval folder) with a recording")
    ex.add_argument("--episode", type=_positive(int, "episodes"), default=1, help="recorded episode (default 1)")
    ex.add_argument("--out", type=Path, default=None, help="output folder (default RUN/eval/export)")
    ex.add_argument("--overwrite", action="store_true", help="replace existing export files")

    rep = sub.add_parser(
        "report",
        help="learning curves and paper-style tables from run folders",
        description="Group run folders by (algorithm, reward preset, density), average the seeds, and write "
        "learning curves (return, collisions, speed deviation per episode; mean ± std over seeds, smoothed) as PNG "
        "and a table of last-50-episode means ± std with the paper's numbers (SPEC §10) as summary.csv and "
        "summary.md. Unusable runs are named and skipped.",
    )
    rep.add_argument("runs", type=Path, nargs="+", metavar="RUN", help="run folders made by 'lanefree train'")
    rep.add_argument("--out", type=Path, default=Path("runs/report"), help="output folder (default runs/report)")
    rep.add_argument("--last", type=_positive(int, "episodes"), default=50,
                     help="episodes at the end of each run averaged in the table (default 50, as the paper)")
    rep.add_argument("--smooth", type=_positive(int, "episodes"), default=20,
                     help="trailing moving-average window of the curves in episodes (default 20)")

    net = sub.add_parser(
        "net",
        help="build a ring network with netconvert",
        description="Write plain node/edge files of a one-lane ring and build the SUMO network with netconvert.",
    )
    net.add_argument("--length", type=_positive(float, "m"), default=500.0, help="centre-line length in m (default 500)")
    net.add_argument("--width", type=_positive(float, "m"), default=10.2, help="road (lane) width in m (default 10.2)")
    net.add_argument("--out-dir", type=Path, default=None, help="folder for the files (default sumo_nets/)")
    return parser


def _prepare_out(out: Path, overwrite: bool) -> None:
    if out.exists():
        if not overwrite:
            raise UsageError(f"output folder {out} exists; choose another --out or pass --overwrite")
        if out.is_dir():
            shutil.rmtree(out)
        else:
            out.unlink()
    out.mkdir(parents=True)


def _simulate(args: argparse.Namespace) -> int:
    overrides: dict[str, Any] = {
        "seed": args.seed,
        "backend": "traci" if args.gui else args.backend,
        "gui": args.gui,
        "scenario": {"density_veh_per_km": args.density, "driver": {"nudging": args.nudging}},
    }
    road: dict[str, float] = {}
    if args.length is not None:
        road["length_m"] = args.length
    if args.width is not None:
        road["width_m"] = args.width
    if road:
        overrides["road"] = road
    if args.net is not None:
        overrides["net_file"] = str(args.net)
    cfg = merge_config(LaneFreeConfig(), overrides)
    steps = int(round(args.seconds / cfg.sim.step_s))

    from lanefree_sumo.sim.spawn import spawn  # noqa: PLC0415

    spawn(cfg, np.random.default_rng(cfg.seed))  # density check before anything is written
    out = args.out or Path("runs") / f"sim-d{args.density:g}-s{args.seed}"
    _prepare_out(out, args.overwrite)
    (out / "command.txt").write_text(shlex.join(["lanefree", *sys.argv[1:]]) + "\n")
    (out / "config.yaml").write_text(yaml.safe_dump(config_to_dict(cfg), sort_keys=False))

    summary = run_simulation(cfg, steps, out, write_trajectory=not args.no_trajectory, progress=not args.json)
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    if args.json:
        print(json.dumps(summary))
    else:
        print(
            f"{summary['steps']} steps, {summary['vehicles']} vehicles, "
            f"{summary['background_collisions']} collisions, mean speed {summary['mean_speed_mps']:.2f} m/s "
            f"(desired {summary['mean_desired_speed_mps']:.2f}), min margin {summary['min_lateral_margin_m']:.3f} m, "
            f"{summary['wall_s']:.1f} s -> {out}"
        )
    return 0 if not summary["interrupted"] else EXIT_INTERRUPTED


def run_simulation(
    cfg: LaneFreeConfig, steps: int, out: Path | None, write_trajectory: bool = True, progress: bool = False
) -> dict[str, Any]:
    """Run background traffic for ``steps``; write ``out/trajectory.csv`` (flushed every simulated
    second) and return the summary.  Ctrl-C stops early and returns what was simulated."""
    from tqdm import tqdm  # noqa: PLC0415

    from lanefree_sumo.sim.simulation import Simulation  # noqa: PLC0415
    from lanefree_sumo.experiments.trajectory import TrajectoryWriter  # noqa: PLC0415

    sim = Simulation(cfg)
    t0 = time.perf_counter()
    state = sim.reset(cfg.seed)
    n = state.n
    width = cfg.road.width_m
    collisions = boundary_contacts = done = 0
    speed_sum = 0.0
    min_margin = float(np.min(np.minimum(state.y - 0.5 * state.width, width - state.y - 0.5 * state.width)))
    writer = (
        TrajectoryWriter(out / "trajectory.csv", cfg.sim.step_s) if (out is not None and write_trajectory) else None
    )
    interrupted = False
    try:
        for k in tqdm(range(steps), disable=not progress or not sys.stderr.isatty(), unit="step", desc="simulate"):
            result = sim.step()
            done = k + 1
            collisions += len(result.new_collisions)
            boundary_contacts += int(result.boundary_contact.sum())
            speed_sum += float(state.vx.mean())
            margin = np.minimum(state.y - 0.5 * state.width, width - state.y - 0.5 * state.width)
            min_margin = min(min_margin, float(margin.min()))
            if writer:
                writer.write(done, state, result)
    except KeyboardInterrupt:
        interrupted = True
    finally:
        if writer:
            writer.close()
        sim.close()
    wall = time.perf_counter() - t0
    return {
        "steps": done,
        "vehicles": n,
        "density_veh_per_km": cfg.scenario.density_veh_per_km,
        "seed": cfg.seed,
        "backend": cfg.backend,
        "nudging": cfg.scenario.driver.nudging,
        "background_collisions": collisions,
        "boundary_contacts": boundary_contacts,
        "mean_speed_mps": speed_sum / done if done else float("nan"),
        "mean_desired_speed_mps": float(state.v_desired.mean()),
        "min_lateral_margin_m": min_margin,
        "wall_s": wall,
        "steps_per_s": done / wall if wall > 0 else float("nan"),
        "interrupted": interrupted,
    }


def _train(args: argparse.Namespace) -> int:
    from lanefree_sumo.experiments.train import train  # noqa: PLC0415

    if args.resume is not None:
        run, done = train(LaneFreeConfig(), run=args.resume, resume=True)
    else:
        cfg = merge_config(LaneFreeConfig(), {
            "seed": args.seed,
            "backend": args.backend,
            "scenario": {"density_veh_per_km": args.density},
            "reward": {"preset": args.reward},
            "observation": {"kind": args.obs},
            "sim": {"episode_steps": args.episode_steps},
            "train": {"algo": args.algo, "episodes": args.episodes, "envs": args.envs,
                      "checkpoint_every_episodes": args.checkpoint_every},
        })
        run, done = train(cfg, run=args.out)
    target = _episodes_target(run)
    if done < target:
        print(f"stopped after {done}/{target} episodes; checkpoint saved. Resume with: lanefree train --resume {run}",
              file=sys.stderr)
        return EXIT_INTERRUPTED
    print(f"trained {done} episodes -> {run}")
    return 0


def _episodes_target(run: Path) -> int:
    from lanefree_sumo.experiments.train import load_run_config  # noqa: PLC0415

    return load_run_config(run).train.episodes


def _evaluate(args: argparse.Namespace) -> int:
    from lanefree_sumo.experiments.evaluate import evaluate  # noqa: PLC0415

    out = evaluate(args.run, episodes=args.episodes, density=args.density, seed=args.seed, record=args.record,
                   out=args.out, overwrite=args.overwrite)
    print(f"evaluated {args.episodes} episodes -> {out / 'episodes.csv'}")
    return 0


def _replay(args: argparse.Namespace) -> int:
    from lanefree_sumo.experiments.replay import replay  # noqa: PLC0415

    result = replay(args.run, episode=args.episode, gui=not args.no_gui, delay_s=args.delay,
                    screenshot=args.screenshot, screenshot_step=args.screenshot_step, frames=args.frames,
                    every=args.every, gif=args.gif, fcd=args.fcd, size=args.size, zoom=args.zoom)
    print(f"replayed {result.steps} steps; largest deviation from the recording: "
          f"x {result.max_dx_m:.2e} m, y {result.max_dy_m:.2e} m")
    return 0


def _export(args: argparse.Namespace) -> int:
    from lanefree_sumo.experiments.replay import find_eval_dir, replay  # noqa: PLC0415

    source = find_eval_dir(args.run) / "trajectories" / f"episode_{args.episode:04d}.csv"
    out = args.out or find_eval_dir(args.run) / "export"
    csv_out = out / f"episode_{args.episode:04d}.csv"
    fcd_out = out / f"episode_{args.episode:04d}.fcd.xml"
    if (csv_out.exists() or fcd_out.exists()) and not args.overwrite:
        raise UsageError(f"{csv_out.parent} already holds episode {args.episode}; pass --overwrite to replace it")
    result = replay(args.run, episode=args.episode, gui=False, fcd=fcd_out)
    shutil.copyfile(source, csv_out)
    print(f"exported {result.steps} steps -> {csv_out} and {fcd_out}")
    return 0


def _report(args: argparse.Namespace) -> int:
    from lanefree_sumo.experiments.report import ReportError, report  # noqa: PLC0415

    try:
        result = report(args.runs, args.out, last=args.last, smooth=args.smooth)
    except ReportError as exc:
        raise UsageError(str(exc)) from None
    for path, reason in result.skipped:
        print(f"skipped {path}: {reason}", file=sys.stderr)
    for note in result.notes:
        print(f"note: {note}", file=sys.stderr)
    print(f"{len(result.table)} group(s) -> {args.out}")
    print((args.out / "summary.md").read_text())
    return 0


def _net(args: argparse.Namespace) -> int:
    from lanefree_sumo.sim.network import NETS_DIR  # noqa: PLC0415
    from lanefree_sumo.sim.backends.sumo import build_ring_net  # noqa: PLC0415

    cfg = merge_config(LaneFreeConfig(), {"road": {"length_m": args.length, "width_m": args.width}})
    net = build_ring_net(cfg, args.out_dir or NETS_DIR)
    print(net)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``lanefree`` console script."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
        if args.command is None:
            parser.print_help()
            return EXIT_BAD_INPUT
        handler = {"simulate": _simulate, "train": _train, "evaluate": _evaluate, "replay": _replay,
                   "export": _export, "report": _report, "net": _net}[args.command]
        return handler(args)
    except (UsageError, ConfigError, RunError) as exc:
        print(f"lanefree: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("lanefree: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as exc:  # SUMO errors and anything unexpected: one line, no traceback
        from lanefree_sumo.sim.backends.sumo import SumoError  # noqa: PLC0415

        if isinstance(exc, SumoError):
            print(f"lanefree: SUMO error: {exc}", file=sys.stderr)
            return EXIT_SUMO
        print(f"lanefree: unexpected {type(exc).__name__}: {exc} (please report this)", file=sys.stderr)
        return EXIT_SUMO


if __name__ == "__main__":
    sys.exit(main())

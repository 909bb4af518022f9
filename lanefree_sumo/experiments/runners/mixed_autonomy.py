"""``lanefree mixed-autonomy RUN``: the whole ring when some of its vehicles drive by a trained shared policy.

The ring holds ``--vehicles`` N vehicles (default: RUN's density × the ring length: 45 at 90 veh/km); for each
k of ``--agents`` (default 0, 2, 5, 10), k of them are replaced by agents driven by RUN's policy
(deterministic; one shared policy, so a run trained with any number of agents drives any k) and N − k stay
background vehicles of the force model. A collision does not end an episode here (``terminate_on_collision``
is switched off for the measurement). k = 0 is the background traffic alone. Every k runs the same
``--episodes`` traffic seeds (RUN's seed + the evaluation offset + episode).

Per episode, of the whole ring: ``ring_collisions`` (collision events between any two vehicles),
``agent_collisions`` (those with at least one agent in them), ``mean_speed_mps`` (mean over steps and
vehicles), ``agent_speed_mps`` / ``background_speed_mps`` (the same over each kind; NaN where there is none),
and ``throughput_veh_per_h`` (vehicles crossing the ring's x = 0 line per hour). Written into
``RUN/mixed_autonomy/`` (``--out``): ``episodes.csv``, ``summary.csv`` and ``summary.md`` (mean ± sample std
over episodes per k) and ``mixed_autonomy.png``.
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from lanefree_sumo import argtypes
from lanefree_sumo.config import EvaluationConfig, LaneFreeConfig, merge_config
from lanefree_sumo.errors import EXIT_INTERRUPTED, RunError
from lanefree_sumo.experiments.runners.signals import StopRequest, stop_requested
from lanefree_sumo.experiments.storage.rundir import MIXED_AUTONOMY, RunDir, fresh_output, write_config
from lanefree_sumo.options import Option, add_options

EVALUATION = EvaluationConfig()
DEFAULT_AGENTS = (0, 2, 5, 10)
DEFAULT_EPISODES = 10
COLUMNS = ("agents", "episode", "seed", "vehicles", "ring_collisions", "agent_collisions", "mean_speed_mps",
           "agent_speed_mps", "background_speed_mps", "throughput_veh_per_h")
SUMMARY_METRICS = (
    ("ring_collisions", "collisions on the ring / episode"),
    ("agent_collisions", "… with an agent in them"),
    ("mean_speed_mps", "mean speed, all vehicles (m/s)"),
    ("throughput_veh_per_h", "throughput (veh/h)"),
)


def _counts(text: str) -> tuple[int, ...]:
    """``0,2,5,10`` → (0, 2, 5, 10): distinct whole numbers ≥ 0."""
    try:
        counts = tuple(int(part) for part in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected whole numbers separated by commas, got {text!r}") from None
    if any(k < 0 for k in counts) or len(set(counts)) != len(counts):
        raise argparse.ArgumentTypeError(f"expected distinct numbers >= 0, got {text!r}")
    return counts


OPTIONS: tuple[Option, ...] = (
    Option("run", type=Path, extra={"metavar": "RUN"}, note="run folder made by 'lanefree train' (any --agents)"),
    Option("--agents", type=_counts, default=DEFAULT_AGENTS, extra={"metavar": "K,K,…"},
           note=f"numbers of vehicles driven by the policy (default {','.join(map(str, DEFAULT_AGENTS))})"),
    Option("--vehicles", type=argtypes.positive(int, "vehicles"),
           note="vehicles on the ring, agents included (default: RUN's density × ring length, 45 at 90 veh/km)"),
    Option("--episodes", type=argtypes.positive(int, "episodes"), default=DEFAULT_EPISODES,
           note=f"episodes per k, the same traffic seeds for every k (default {DEFAULT_EPISODES})"),
    Option("--out", type=Path, note="output folder (default RUN/mixed_autonomy)"),
    Option("--overwrite", extra={"action": "store_true"}, note="replace an earlier mixed-autonomy output"),
)


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """The ``mixed-autonomy`` sub-command's parser."""
    p = subparsers.add_parser(
        "mixed-autonomy",
        help="replace k background vehicles by a trained run's agents: collisions, speed, throughput of the ring",
        description="Drive k of the ring's vehicles by RUN's trained (shared) policy and the others by the force "
        "model, for each k of --agents, and measure the whole ring: collisions, mean speed, throughput. Writes "
        "RUN/mixed_autonomy/ (episodes.csv, summary.csv, summary.md, mixed_autonomy.png).",
    )
    add_options(p, OPTIONS)
    return p


class _InterruptedError(Exception):
    """Leaves :func:`fresh_output`'s block: the new output is discarded, an earlier one kept."""


def run(args: argparse.Namespace) -> int:
    """``lanefree mixed-autonomy``: measure, write, print the summary table."""
    result = measure(args.run, args.agents, args.vehicles, args.episodes, args.out, args.overwrite)
    if result is None:
        print("lanefree: interrupted; nothing written (an earlier output is kept)", file=sys.stderr)
        return EXIT_INTERRUPTED
    print((result / "summary.md").read_text())
    print(f"-> {result}")
    return 0


def setting(cfg: LaneFreeConfig, vehicles: int, agents: int) -> LaneFreeConfig:
    """``cfg`` with ``agents`` agents and ``vehicles − agents`` background vehicles on its ring."""
    if agents > vehicles:
        raise RunError(f"cannot replace {agents} of {vehicles} vehicles; use --agents up to {vehicles}")
    density = (vehicles - agents) * 1000.0 / cfg.road.length_m
    if agents == vehicles:
        raise RunError("at least one background vehicle stays on the ring; use fewer --agents or more --vehicles")
    # a measurement of the whole ring over a fixed time: a collision does not end it
    return merge_config(cfg, {"scenario": {"density_veh_per_km": density, "with_agent": agents > 0,
                                           "agents": max(agents, 1)},
                              "episode": {"terminate_on_collision": False}})


def measure(run_path: Path, counts: Sequence[int], vehicles: int | None, episodes: int, out: Path | None,
            overwrite: bool) -> Path | None:
    """Run the measurement of the module docstring; returns the output folder (None when Ctrl-C/SIGTERM
    stopped it: then nothing is written)."""
    from lanefree_sumo.experiments.runners.evaluate import load_model

    folder = RunDir(run_path)
    cfg = folder.load_config()
    if cfg.road.kind != "ring":
        raise RunError(f"{run_path} was trained on the {cfg.road.kind}; the mixed-autonomy measurement runs on "
                       "the ring")
    n = vehicles if vehicles is not None else cfg.background_vehicles
    settings = [setting(cfg, n, k) for k in counts]  # every k checked before anything runs
    out = out or folder.path / MIXED_AUTONOMY
    model = load_model(folder, cfg) if any(counts) else None
    base_seed = cfg.seed + EVALUATION.seed_offset
    rows: list[dict[str, Any]] = []
    try:
        with fresh_output(out, overwrite, "mixed-autonomy") as tmp, stop_requested() as stop:
            write_config(tmp, cfg)
            for k, setting_cfg in zip(counts, settings):
                for episode in range(1, episodes + 1):
                    row = _episode(setting_cfg, k, model, base_seed + episode, stop)
                    if row is None:
                        raise _InterruptedError
                    rows.append({"agents": k, "episode": episode, "seed": base_seed + episode, "vehicles": n, **row})
                    print(f"k = {k:>3}, episode {episode}/{episodes}: {row['ring_collisions']} collisions, "
                          f"{row['mean_speed_mps']:.2f} m/s", file=sys.stderr, flush=True)
            _write(tmp, rows, counts)
    except _InterruptedError:
        return None
    return out


def _episode(cfg: LaneFreeConfig, agents: int, model: Any, seed: int, stop: StopRequest) -> dict[str, Any] | None:
    """One episode's ring metrics (None when stopped)."""
    from lanefree_sumo.rl.multi_agent import PolicyDriver
    from lanefree_sumo.sim.simulation import Simulation

    driver = PolicyDriver(cfg) if agents else None
    sim = driver.sim if driver is not None else Simulation(cfg)
    books = {"collisions": 0, "agent_collisions": 0, "speed": 0.0, "agent_speed": 0.0, "background_speed": 0.0,
             "crossings": 0}
    try:
        obs = driver.reset(seed) if driver is not None else None
        if driver is None:
            sim.reset(seed)
        state = sim.current()[0]
        is_agent = ~state.controlled
        for _ in range(cfg.sim.episode_steps):
            if stop.requested:
                return None
            x_before = sim.current()[0].x.copy()
            if driver is not None:
                action, _ = model.predict(obs, deterministic=True)
                obs, _, _, _ = driver.step(action)
            else:
                sim.step()
            state, result = sim.current()[0], sim.last_result
            assert result is not None
            pairs = result.new_collisions
            books["collisions"] += len(pairs)
            books["agent_collisions"] += int(np.count_nonzero(is_agent[pairs].any(axis=1))) if len(pairs) else 0
            books["speed"] += float(state.vx.mean())
            books["agent_speed"] += float(state.vx[is_agent].mean()) if is_agent.any() else math.nan
            books["background_speed"] += float(state.vx[~is_agent].mean())
            books["crossings"] += int(np.count_nonzero(state.x < x_before - 0.5 * cfg.road.length_m))
    finally:
        (driver or sim).close()
    steps = cfg.sim.episode_steps
    return {"ring_collisions": books["collisions"], "agent_collisions": books["agent_collisions"],
            "mean_speed_mps": books["speed"] / steps, "agent_speed_mps": books["agent_speed"] / steps,
            "background_speed_mps": books["background_speed"] / steps,
            "throughput_veh_per_h": books["crossings"] * 3600.0 / (steps * cfg.sim.step_s)}


def _write(folder: Path, rows: list[dict[str, Any]], counts: Sequence[int]) -> None:
    """episodes.csv, summary.csv, summary.md and the figure."""
    with open(folder / "episodes.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    summary = []
    for k in counts:
        mine = [r for r in rows if r["agents"] == k]
        entry: dict[str, Any] = {"agents": k, "episodes": len(mine)}
        for key in COLUMNS[4:]:
            values = np.array([r[key] for r in mine], dtype=float)
            entry[key] = float(values.mean())
            entry[f"{key}_std"] = float(values.std(ddof=1)) if len(values) > 1 else math.nan
        summary.append(entry)
    with open(folder / "summary.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(summary[0]))
        writer.writeheader()
        writer.writerows(summary)
    header = "| agents | episodes | " + " | ".join(label for _, label in SUMMARY_METRICS) + " |"
    lines = ["# Mixed autonomy: the ring with k agents", "",
             f"{rows[0]['vehicles']} vehicles on the ring; mean ± sample std over episodes (the same traffic seeds "
             "for every k).", "", header, "|" + "---|" * (2 + len(SUMMARY_METRICS))]
    for entry in summary:
        cells = [f"{entry[key]:.2f} ± {entry[f'{key}_std']:.2f}" for key, _ in SUMMARY_METRICS]
        lines.append(f"| {entry['agents']} | {entry['episodes']} | " + " | ".join(cells) + " |")
    (folder / "summary.md").write_text("\n".join(lines) + "\n")
    _plot(folder / "mixed_autonomy.png", summary)


def _plot(path: Path, summary: list[dict[str, Any]]) -> None:
    """One panel per summary metric against k, with ± std bars."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(4.0 * len(SUMMARY_METRICS), 3.6), dpi=100)
    FigureCanvasAgg(fig)
    ks = [entry["agents"] for entry in summary]
    for i, (key, label) in enumerate(SUMMARY_METRICS):
        ax = fig.add_subplot(1, len(SUMMARY_METRICS), i + 1)
        ax.errorbar(ks, [e[key] for e in summary], yerr=[0.0 if math.isnan(e[f"{key}_std"]) else e[f"{key}_std"]
                                                          for e in summary], marker="o", capsize=3)
        ax.set_xlabel("vehicles driven by the policy (k)")
        ax.set_title(label, fontsize=10)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)

"""``lanefree rollout``: LaneFree-v0 driven by a built-in policy or a trained run, with or
without the safety shield; per-episode rows and a summary, nothing written to disk.

Policies: ``random`` (uniform actions from the action space, seeded with ``--seed``: the same
action stream with and without ``--shield``), ``idle`` (the zero action: ax = ay = 0) or
``--run RUN`` (RUN's final model or newest checkpoint, deterministic, with RUN's config; the
density defaults to RUN's). Episode k (1-based) uses traffic seed ``seed + k − 1``; the seed
defaults to the config's for a built-in policy and to RUN's seed + the evaluation offset + 1
(the seed of ``lanefree evaluate``'s first episode) for a run.

With ``--json`` stdout's last line is ONE JSON object: ``episodes``, ``agents``, ``collisions`` (agent
collision events summed over episodes and agents), ``collisions_per_episode`` (per agent), ``collision_steps``,
``background_collisions``, ``shield_interventions``, ``shield_interventions_per_episode``,
``shield_fallbacks_per_episode``, ``speed_dev_mps`` and ``mean_speed_mps`` (means over episodes and agents),
``boundary_contacts``, ``mean_return``, plus the settings (policy, density, seed, shield, backend).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from lanefree_sumo import argtypes
from lanefree_sumo.config import EvaluationConfig, LaneFreeConfig
from lanefree_sumo.errors import EXIT_INTERRUPTED
from lanefree_sumo.experiments.analysis.markdown import count
from lanefree_sumo.experiments.runners.signals import StopRequest, stop_requested
from lanefree_sumo.options import DENSITY, Option, add_options, verb_config
from lanefree_sumo.sim.road import road_kind

POLICIES = ("random", "idle")
EVALUATION = EvaluationConfig()
DEFAULTS = LaneFreeConfig()
ROW = ("episode", "agent", "seed", "collisions", "background_collisions", "shield_interventions", "shield_fallbacks",
       "speed_dev_mps", "mean_speed_mps", "return")
"""Columns of the per-episode rows."""


OPTIONS: tuple[Option, ...] = (
    Option("--policy", extra={"choices": POLICIES}, group="who",
           note="built-in policy: random (uniform actions, seeded) or idle (ax = ay = 0); default random"),
    Option("--run", type=Path, extra={"metavar": "RUN"}, group="who",
           note="a run folder made by 'lanefree train': its model, deterministic, with its config"),
    replace(DENSITY, default=None, note=f"default {DEFAULTS.scenario.density_veh_per_km:g}, or RUN's"),
    Option("--episodes", "episodes", schema=EvaluationConfig, unit="episodes",
           note=f"of {DEFAULTS.sim.episode_steps} steps"),
    Option("--seed", type=argtypes.seed, default=None,
           note=f"episode k uses traffic seed SEED+k-1 (default {DEFAULTS.seed}; with --run, RUN's seed+"
           f"{EVALUATION.seed_offset}+1 as 'lanefree evaluate')"),
    Option("--agents", "scenario.agents", unit="vehicles", default=None,
           note=f"on top of the background traffic (default {DEFAULTS.scenario.agents}, or RUN's); rows per agent "
           "and episode"),
    Option("--shield", "shield.enabled", negatable=True, default=None, note="default off; with --run, as RUN was "
           "trained"),
    Option("--backend", "backend"),
    Option("--json", note="print ONE JSON summary object on stdout's last line", extra={"action": "store_true"}),
)


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """The ``rollout`` sub-command's parser."""
    p = subparsers.add_parser(
        "rollout",
        help="drive LaneFree-v0 with a built-in policy (random, idle) or a trained run, optionally shielded",
        description="Run LaneFree-v0 episodes with --policy random|idle or a trained --run RUN, with or without the "
        "safety shield, and print one row per episode; --json adds ONE JSON summary on stdout's last line. "
        "Nothing is written to disk.",
    )
    add_options(p, OPTIONS)
    argtypes.add_config_options(p)
    return p


def run(args: argparse.Namespace) -> int:
    """``lanefree rollout``: print the rows (and the JSON summary); exit code 0."""
    cfg, model = _setup(args)
    policy = "run" if model is not None else (args.policy or "random")
    if args.seed is not None:
        seed = args.seed
    elif model is not None:
        seed = cfg.seed + EVALUATION.seed_offset + 1
    else:
        seed = DEFAULTS.seed
    widths = [max(len(c), 8) for c in ROW]
    print("  ".join(f"{c:>{w}}" for c, w in zip(ROW, widths)), flush=True)

    def show(row: dict[str, Any]) -> None:
        print("  ".join(f"{row[c]:>{w}.3f}" if isinstance(row[c], float) else f"{row[c]:>{w}}"
                        for c, w in zip(ROW, widths)), flush=True)

    summary = rollout(cfg, policy, args.episodes, seed, model=model, on_episode=show)
    summary["run"] = str(args.run) if args.run is not None else None
    if summary["interrupted"]:
        print(f"lanefree: interrupted; the summary covers the {summary['episodes']} complete episode(s)",
              file=sys.stderr)
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"{count(summary['episodes'], 'episode')} at {summary['density']:g} veh/km, policy {policy}, shield "
              f"{'on' if summary['shield'] else 'off'}: {summary['collisions_per_episode']:.2f} agent collisions, "
              f"{summary['background_collisions']} background collisions, "
              f"{summary['shield_interventions_per_episode']:.1f} interventions per episode, speed deviation "
              f"{summary['speed_dev_mps']:.2f} m/s, mean speed {summary['mean_speed_mps']:.2f} m/s")
    return EXIT_INTERRUPTED if summary["interrupted"] else 0


def _setup(args: argparse.Namespace) -> tuple[LaneFreeConfig, Any]:
    """The config (and the model with --run) of a rollout: the defaults or RUN's config, then ``--config FILE``,
    then the options, then every ``--set``."""
    folder = None
    if args.run is not None:
        from lanefree_sumo.experiments.storage.rundir import RunDir

        folder = RunDir(args.run)
    base = LaneFreeConfig() if folder is None else folder.load_config()
    # the backend is always the option's (a run's training backend is not the rollout's)
    cfg = verb_config(args, OPTIONS, {"backend": args.backend}, base=base)
    if folder is None:
        return cfg, None
    from lanefree_sumo.experiments.runners.evaluate import load_model

    return cfg, load_model(folder, cfg)


def rollout(cfg: LaneFreeConfig, policy: str, episodes: int, seed: int, model: Any = None,
            on_episode: Any = None) -> dict[str, Any]:
    """Run ``episodes`` episodes of ``policy`` (``random``, ``idle`` or ``run`` with ``model``);
    call ``on_episode(row)`` after each; return the summary of the module docstring."""
    from lanefree_sumo.rl.multi_agent import PolicyDriver

    driver = PolicyDriver(cfg)
    driver.seed_actions(seed)
    rows: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    interrupted = False
    try:
        with stop_requested() as stop:
            interrupted = _episodes(driver, policy, episodes, seed, model, rows, on_episode, stop)
    finally:
        driver.close()
    return {**_summary(rows, cfg, policy, seed, time.perf_counter() - t0), "interrupted": interrupted}


def _episodes(driver: Any, policy: str, episodes: int, seed: int, model: Any, rows: list[dict[str, Any]],
              on_episode: Any, stop: StopRequest) -> bool:
    """Episodes 1 … ``episodes`` into ``rows`` (one per agent and episode); True when Ctrl-C/SIGTERM stopped
    them (the episode in progress is dropped: the summary holds complete episodes only)."""
    zero = driver.idle()
    for k in range(1, episodes + 1):
        obs = driver.reset(seed + k - 1)
        ended: list[dict[str, Any]] = []
        done = False
        while not done:
            if stop.requested:
                return True
            if policy == "random":
                action = driver.sample()
            elif policy == "idle":
                action = zero
            else:
                action, _ = model.predict(obs, deterministic=True)
            obs, done, _, ended = driver.step(action)
        for metrics in ended:
            row = {"agent": "agent", **metrics, "episode": k}
            rows.append(row)
            if on_episode is not None:
                on_episode(row)
    return False


def _summary(rows: list[dict[str, Any]], cfg: LaneFreeConfig, policy: str, seed: int, wall: float) -> dict[str, Any]:
    n = len(rows)  # agent-episodes: with several agents each episode counts once per agent

    def total(key: str) -> int:
        return int(sum(r[key] for r in rows))

    def mean(key: str) -> float:
        return float(np.mean([r[key] for r in rows])) if rows else float("nan")

    return {
        "episodes": n // cfg.scenario.agents,
        "agents": cfg.scenario.agents,
        "policy": policy,
        "density": cfg.scenario.density_veh_per_km,
        "seed": seed,
        "shield": cfg.shield.enabled,
        "backend": cfg.backend,
        "collisions": total("collisions"),
        "collisions_per_episode": total("collisions") / n if n else float("nan"),
        "collision_steps": total("collision_steps"),
        "background_collisions": total("background_collisions") // cfg.scenario.agents,  # every agent's row has it
        "shield_interventions": total("shield_interventions"),
        "shield_interventions_per_episode": total("shield_interventions") / n if n else float("nan"),
        "shield_fallbacks_per_episode": total("shield_fallbacks") / n if n else float("nan"),
        "speed_dev_mps": mean("speed_dev_mps"),
        "mean_speed_mps": mean("mean_speed_mps"),
        "boundary_contacts": total("boundary_contacts"),
        "mean_return": mean("return"),
        **{f"{name}_share": mean(name) for name in ("merged", "left_road") if name in road_kind(cfg).metrics},
        "wall_s": wall,
    }

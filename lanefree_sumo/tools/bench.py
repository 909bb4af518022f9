"""``make bench``: step rates measured side by side in one run, printed as a table and written
to ``runs/bench/``.

For 70, 90 and 120 veh/km, 800 steps each:
(a) bare SUMO — the same ring and vehicles, SUMO's own models drive, no Python per step;
(b) the libsumo backend with the force model (read state, forces, commands, collisions);
(c) the TraCI backend (same, over a socket);
(d) the numpy-only physics (no SUMO).
(a) and (b) are measured alternately ``REPEATS`` times and the median is reported, so that
machine noise hits both alike.  Timings are not tests: the numbers are for reading.
"""

from __future__ import annotations

import argparse
import statistics
import time
from datetime import datetime
from pathlib import Path

import numpy as np

from lanefree_sumo.config import LaneFreeConfig, merge_config
from lanefree_sumo.sim.simulation import Simulation
from lanefree_sumo.sim.spawn import spawn
from lanefree_sumo.sim.backends.sumo import bare_step_rate, sumo_version

DENSITIES = (70, 90, 120)
REPEATS = 3


def _rate(cfg: LaneFreeConfig, steps: int, seed: int) -> tuple[float, float, dict[str, float]]:
    """(steps per second, reset time in ms, ms per step split into SUMO's own step, the
    per-vehicle commands and reads, and the Python physics) on ``cfg.backend``."""
    sim = Simulation(cfg)
    try:
        sim.reset(seed)
        t0 = time.perf_counter()
        sim.reset(seed + 1)
        reset_ms = 1000.0 * (time.perf_counter() - t0)
        sim.backend_seconds = 0.0
        sumo_step = getattr(sim.backend, "sumo_step_seconds", 0.0)
        t0 = time.perf_counter()
        for _ in range(steps):
            sim.step()
        total = time.perf_counter() - t0
        sumo_step = getattr(sim.backend, "sumo_step_seconds", 0.0) - sumo_step
        split = {
            "sumo_step": 1000.0 * sumo_step / steps,
            "api_calls": 1000.0 * (sim.backend_seconds - sumo_step) / steps,
            "physics": 1000.0 * (total - sim.backend_seconds) / steps,
        }
        return steps / total, reset_ms, split
    finally:
        sim.close()


def env_overhead(steps: int, seed: int, density: float = 120.0) -> list[tuple[str, float, float]]:
    """(observation kind, env work ms per step, core step ms) of LaneFree-v0 on libsumo: the
    env's own work (observation, reward, bookkeeping) against the simulation core's step."""
    from lanefree_sumo.rl.env import LaneFreeEnv

    out = []
    for kind in ("vector", "set"):
        env = LaneFreeEnv({"scenario": {"density_veh_per_km": density}, "observation": {"kind": kind}})
        try:
            env.reset(seed=seed)
            env.env_seconds = 0.0
            action = np.array([0.3, 0.0])
            t0 = time.perf_counter()
            for _ in range(steps):
                env.step(action)
            total = time.perf_counter() - t0
        finally:
            env.close()
        out.append((kind, 1000.0 * env.env_seconds / steps, 1000.0 * (total - env.env_seconds) / steps))
    return out


def training_rate(algo: str, seed: int, density: float = 90.0, steps: int = 1600,
                  encoder: str | None = None) -> float:
    """Env steps per second of a training run of ``algo`` including its learning updates,
    measured over ``steps`` steps after learning has started (SPEC §9 settings); with
    ``encoder`` (``small`` or ``paper``), on the set observation through that set encoder."""
    from stable_baselines3.common.callbacks import BaseCallback

    from lanefree_sumo.experiments.train import build_model, make_vec_env, training_config

    cfg = training_config(merge_config(LaneFreeConfig(), {
        "scenario": {"density_veh_per_km": density}, "train": {"algo": algo},
        **({"observation": {"kind": "set", "encoder": encoder}} if encoder else {})}))
    starts = cfg.train.dqn.learning_starts_steps if algo in ("dqn", "ddqn", "dueling", "per") \
        else cfg.train.actor_critic.learning_starts_steps
    import torch

    torch.set_num_threads(cfg.train.torch_threads)

    class Clock(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.t_start = self.t_end = 0.0

        def _on_step(self) -> bool:
            if self.num_timesteps == starts:
                self.t_start = time.perf_counter()
            if self.num_timesteps == starts + steps:
                self.t_end = time.perf_counter()
                return False
            return True

    env = make_vec_env(cfg, seed, 1)
    try:
        model = build_model(cfg, env, seed, None)
        clock = Clock()
        model.learn(total_timesteps=starts + steps + 1, callback=clock)
    finally:
        env.close()
    return steps / (clock.t_end - clock.t_start)


def run(steps: int, seed: int, out_dir: Path) -> str:
    rows = []
    profile = []
    for density in DENSITIES:
        base = merge_config(LaneFreeConfig(), {"scenario": {"density_veh_per_km": density}})
        state = spawn(base, np.random.default_rng(seed))
        bare, lib, resets, splits = [], [], [], []
        for _ in range(REPEATS):
            bare.append(bare_step_rate(base, state, steps))
            rate, reset_ms, split = _rate(merge_config(base, {"backend": "libsumo"}), steps, seed)
            lib.append(rate)
            resets.append(reset_ms)
            splits.append(split)
        traci_rate, _, _ = _rate(merge_config(base, {"backend": "traci"}), steps, seed)
        numpy_rate, _, _ = _rate(merge_config(base, {"backend": "numpy"}), steps, seed)
        a, b = statistics.median(bare), statistics.median(lib)
        rows.append((density, state.n, a, b, traci_rate, numpy_rate, b / a, statistics.median(resets)))
        split = {k: statistics.median(s[k] for s in splits) for k in splits[0]}
        ceiling = (1000.0 / a) / (split["sumo_step"] + split["api_calls"])
        profile.append((density, 1000.0 / a, split["sumo_step"], split["api_calls"], split["physics"], ceiling))
        print(f"  {density} veh/km done", flush=True)
    header = (
        "| density (veh/km) | vehicles | (a) bare SUMO | (b) libsumo + forces | (c) TraCI + forces "
        "| (d) numpy only | (b)/(a) | reset (ms) |\n|---|---|---|---|---|---|---|---|"
    )
    lines = [header] + [
        f"| {d} | {n} | {a:.0f} | {b:.0f} | {c:.0f} | {e:.0f} | {r:.2f} | {ms:.1f} |"
        for d, n, a, b, c, e, r, ms in rows
    ]
    lines += [
        "",
        "Where (b)'s time goes, ms per step (median of the repeats):",
        "",
        "| density (veh/km) | bare SUMO step (a) | SUMO step under control | setSpeed/changeSublane + read "
        "| Python physics | (b)/(a) ceiling with zero physics |\n|---|---|---|---|---|---|",
    ] + [
        f"| {d} | {bare_ms:.3f} | {st:.3f} | {api:.3f} | {phys:.3f} | {ceil:.2f} |"
        for d, bare_ms, st, api, phys, ceil in profile
    ]
    lines += [
        "",
        "LaneFree-v0 at 120 veh/km on libsumo: the env's own work per step against the core step:",
        "",
        "| observation | env work (ms/step) | core step (ms/step) | share |\n|---|---|---|---|",
    ] + [f"| {kind} | {work:.3f} | {core:.3f} | {work / core:.1%} |" for kind, work, core in env_overhead(steps, seed)]
    lines += [
        "",
        "Training throughput at 90 veh/km (libsumo, one env, learning updates every step, SPEC §9 settings):",
        "",
        "| algorithm | env steps/s incl. learning | projected 625-episode run |\n|---|---|---|",
    ]
    for algo in ("ddpg", "dqn"):
        rate = training_rate(algo, seed)
        hours = 625 * 800 / rate / 3600.0
        lines.append(f"| {algo} | {rate:.0f} | {hours:.2f} h ({625 * 800 / rate / 625:.1f} s/episode) |")
    table = "\n".join(lines)
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    out_dir.mkdir(parents=True, exist_ok=True)
    text = (
        f"Step rates in steps/s ({steps} steps, median of {REPEATS} for (a) and (b)), "
        f"SUMO {sumo_version()}, {stamp}\n\n{table}\n"
    )
    (out_dir / f"bench-{stamp}.md").write_text(text)
    (out_dir / "latest.md").write_text(text)
    return text


def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m lanefree_sumo.tools.bench", description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=800, help="steps per measurement (default 800)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the traffic (default 0)")
    parser.add_argument("--out", type=Path, default=Path("runs/bench"), help="folder for the table")
    args = parser.parse_args()
    print(run(args.steps, args.seed, args.out))


if __name__ == "__main__":
    main()

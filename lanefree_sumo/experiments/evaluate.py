"""``lanefree evaluate RUN``: the deterministic policy of a run on fresh seeds.

Writes ``<RUN>/eval/episodes.csv`` (``eval_d<density>/`` when evaluated at another density than
trained), one row per episode with the SPEC §8 columns, and with ``record`` one trajectory file
per episode, ``trajectories/episode_NNNN.csv`` — every vehicle at every step including the
initial state, in the format of :mod:`lanefree_sumo.experiments.trajectory` with the ``overlap`` column;
the agent's id is ``agent`` — and ``episode_NNNN.vehicles.csv`` with each vehicle's length,
width and desired speed.  ``recording.json`` beside them names the network and the config
so that a replay can rebuild the scene.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from lanefree_sumo.config import merge_config, validate_density
from lanefree_sumo.errors import RunError
from lanefree_sumo.experiments.rundir import (
    EPISODES,
    RECORDING,
    TRAJECTORIES,
    RunDir,
    prepare_output,
    trajectory_path,
    vehicles_path,
    write_config,
)
from lanefree_sumo.experiments.train import EpisodeLog
from lanefree_sumo.rl.algorithms import get_algorithm

EVAL_SEED_OFFSET = 100_000
"""Evaluation episode k of a run with training seed s uses seed s + 100000 + k (never a
training seed)."""


def evaluate(
    run: Path,
    episodes: int = 20,
    density: float | None = None,
    seed: int | None = None,
    record: bool = False,
    out: Path | None = None,
    overwrite: bool = False,
    progress: bool = True,
) -> Path:
    """Run the deterministic policy for ``episodes`` episodes; return the eval folder."""
    from tqdm import tqdm

    from lanefree_sumo.experiments.trajectory import TrajectoryWriter, write_vehicles
    from lanefree_sumo.rl.env import LaneFreeEnv

    folder = RunDir(run)
    cfg = folder.load_config()
    trained_density = cfg.scenario.density_veh_per_km
    if density is not None:
        cfg = merge_config(cfg, {"scenario": {"density_veh_per_km": validate_density(density)}})
    d = cfg.scenario.density_veh_per_km
    out = out or folder.eval_dir(None if d == trained_density else d)
    if out.exists() and not overwrite:
        raise RunError(f"{out} exists; pass --overwrite to replace it or --out for another folder")
    model_path = folder.find_model()
    try:
        model = get_algorithm(cfg.train.algo).cls.load(model_path, device="cpu")
    except Exception as exc:
        raise RunError(f"{model_path} cannot be loaded ({type(exc).__name__}: {exc})") from None
    prepare_output(out, overwrite)
    base_seed = (cfg.seed if seed is None else seed) + EVAL_SEED_OFFSET
    write_config(out, cfg)
    if record:
        (out / TRAJECTORIES).mkdir()
        (out / RECORDING).write_text(json.dumps({
            "model": str(model_path), "net_file": cfg.net_file, "road_length_m": cfg.road.length_m,
            "road_width_m": cfg.road.width_m, "step_s": cfg.sim.step_s, "density_veh_per_km": d,
            "agent_id": "agent", "format": "lanefree_sumo.experiments.trajectory (t,id,x,y,vx,vy,ax,ay,overlap)",
        }, indent=2) + "\n")
    log = EpisodeLog(out / EPISODES)
    env = LaneFreeEnv(cfg)
    try:
        for k in tqdm(range(1, episodes + 1), desc="evaluate", unit="ep", disable=not progress):
            obs, _ = env.reset(seed=base_seed + k)
            writer = TrajectoryWriter(trajectory_path(out, k), cfg.sim.step_s, overlap=True) if record else None
            if writer:
                writer.write(0, env.sim.current()[0], None)
                write_vehicles(vehicles_path(out, k), env.sim.current()[0])
            info: dict[str, Any] = {}
            done = False
            while not done:
                action, _ = model.predict(obs, deterministic=True)
                obs, _, terminated, truncated, info = env.step(action)
                if writer:
                    writer.write(env.sim.steps, env.sim.current()[0], env.sim.last_result)
                done = terminated or truncated
            if writer:
                writer.close()
            log.append({**info["episode_metrics"], "episode": k, "algorithm": cfg.train.algo,
                        "timesteps": int(model.num_timesteps)})
    finally:
        log.close()
        env.close()
    return out



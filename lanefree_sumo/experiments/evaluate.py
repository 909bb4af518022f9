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
import shutil
from pathlib import Path
from typing import Any

import yaml

from lanefree_sumo.config import config_to_dict, merge_config, validate_density
from lanefree_sumo.experiments.train import EPISODE_COLUMNS, EpisodeLog, RunError, algorithm_class, load_run_config

EVAL_SEED_OFFSET = 100_000
"""Evaluation episode k of a run with training seed s uses seed s + 100000 + k (never a
training seed)."""


def find_model(run: Path) -> Path:
    """The final ``model.zip`` of a run, else its newest checkpoint's."""
    final = run / "model.zip"
    if final.is_file():
        return final
    from lanefree_sumo.experiments.train import newest_checkpoint  # noqa: PLC0415

    try:
        return newest_checkpoint(run).path / "model.zip"
    except RunError:
        raise RunError(f"{run} has no model.zip and no checkpoint; train it first with 'lanefree train'") from None


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
    from tqdm import tqdm  # noqa: PLC0415

    from lanefree_sumo.rl.env import LaneFreeEnv  # noqa: PLC0415
    from lanefree_sumo.experiments.trajectory import TrajectoryWriter, write_vehicles  # noqa: PLC0415

    cfg = load_run_config(run)
    trained_density = cfg.scenario.density_veh_per_km
    if density is not None:
        cfg = merge_config(cfg, {"scenario": {"density_veh_per_km": validate_density(density)}})
    d = cfg.scenario.density_veh_per_km
    out = out or run / ("eval" if d == trained_density else f"eval_d{d:g}")
    if out.exists():
        if not overwrite:
            raise RunError(f"{out} exists; pass --overwrite to replace it or --out for another folder")
        shutil.rmtree(out)
    model_path = find_model(run)
    try:
        model = algorithm_class(cfg.train.algo).load(model_path, device="cpu")
    except Exception as exc:
        raise RunError(f"{model_path} cannot be loaded ({type(exc).__name__}: {exc})") from None
    out.mkdir(parents=True)
    base_seed = (cfg.seed if seed is None else seed) + EVAL_SEED_OFFSET
    (out / "config.yaml").write_text(yaml.safe_dump(config_to_dict(cfg), sort_keys=False))
    if record:
        (out / "trajectories").mkdir()
        (out / "recording.json").write_text(json.dumps({
            "model": str(model_path), "net_file": cfg.net_file, "road_length_m": cfg.road.length_m,
            "road_width_m": cfg.road.width_m, "step_s": cfg.sim.step_s, "density_veh_per_km": d,
            "agent_id": "agent", "format": "lanefree_sumo.experiments.trajectory (t,id,x,y,vx,vy,ax,ay,overlap)",
        }, indent=2) + "\n")
    log = EpisodeLog(out / "episodes.csv")
    env = LaneFreeEnv(cfg)
    try:
        for k in tqdm(range(1, episodes + 1), desc="evaluate", unit="ep", disable=not progress):
            obs, _ = env.reset(seed=base_seed + k)
            writer = TrajectoryWriter(out / "trajectories" / f"episode_{k:04d}.csv", cfg.sim.step_s,
                                      overlap=True) if record else None
            if writer:
                writer.write(0, env.sim.state, None)
                write_vehicles(out / "trajectories" / f"episode_{k:04d}.vehicles.csv", env.sim.state)
            info: dict[str, Any] = {}
            done = False
            while not done:
                action, _ = model.predict(obs, deterministic=True)
                obs, _, terminated, truncated, info = env.step(action)
                if writer:
                    writer.write(env.sim.steps, env.sim.state, env.sim.last_result)
                done = terminated or truncated
            if writer:
                writer.close()
            log.append({**info["episode_metrics"], "episode": k, "algorithm": cfg.train.algo,
                        "timesteps": int(model.num_timesteps)})
    finally:
        log.close()
        env.close()
    return out


__all__ = ["evaluate", "find_model", "EPISODE_COLUMNS"]

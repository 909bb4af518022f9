"""``lanefree evaluate RUN``: the deterministic policy of a run on fresh seeds.

Writes ``<RUN>/eval/episodes.csv`` (``eval_d<density>/`` when evaluated at another density than
trained; ``eval_shield/`` or ``eval_noshield/``, after the density, when the safety shield is
switched on or off against the run's config; ``eval_onramp…`` first for a ring-trained policy on the
on-ramp, :func:`on_another_road`), one row per episode with the specification §8 columns, and
with ``record`` one trajectory file per episode, ``trajectories/episode_NNNN.csv`` — every
vehicle on the road at every step including the initial state (on the on-ramp vehicles come and
go: see :mod:`lanefree_sumo.experiments.storage.trajectory`), in the format of
:mod:`lanefree_sumo.experiments.storage.trajectory` with the ``overlap`` column; the agents' ids are
``agent`` (``agent1``, … in a run of several agents, with one ``episodes.csv`` row per agent) — and
``episode_NNNN.vehicles.csv`` with the length, width and desired speed of every vehicle seen.  ``recording.json``
beside them names the network and the config so that a replay can rebuild the scene.  A shielded
recording has a ``shielded`` column (1 in an agent's row on the steps the shield changed its action).
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lanefree_sumo.config import EvaluationConfig, LaneFreeConfig, merge_config, validate_density
from lanefree_sumo.errors import RunError
from lanefree_sumo.experiments.analysis.markdown import count
from lanefree_sumo.experiments.runners.signals import StopRequest, stop_requested
from lanefree_sumo.experiments.storage.episodes import EpisodeLog, episode_columns
from lanefree_sumo.experiments.storage.rundir import (
    EPISODES,
    RECORDING,
    TRAJECTORIES,
    RunDir,
    check_replaceable,
    fresh_output,
    trajectory_path,
    vehicles_path,
    write_config,
)
from lanefree_sumo.rl.models import load_saved_model
from lanefree_sumo.sim.road import road_of
from lanefree_sumo.sim.spawn import agent_id

EVALUATION = EvaluationConfig()


@dataclass
class EvaluationResult:
    """Where an evaluation went and how far it got."""

    out: Path
    episodes: int
    """Complete episodes written."""
    interrupted: bool
    kept_earlier: bool = False
    """Interrupted while replacing an earlier evaluation (``overwrite``): the earlier one is kept whole and
    the new, incomplete one discarded."""


def summary_line(result: EvaluationResult) -> str:
    """One line on what an evaluation measured: its episodes, the means over its rows (one per episode, or
    per agent and episode with several agents) of collisions, speed deviation (m/s), mean speed (m/s) and
    return, and where they are."""
    path = result.out / EPISODES
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    if not rows:
        return f"evaluated 0 episodes -> {path}"

    def mean(key: str) -> float:
        return sum(float(row[key]) for row in rows) / len(rows)

    per = "per agent and episode" if len(rows) > result.episodes else "per episode"
    return (f"evaluated {count(result.episodes, 'episode')}: {mean('collisions'):.2f} agent collisions {per}, "
            f"speed deviation {mean('speed_dev_mps'):.2f} m/s, mean speed {mean('mean_speed_mps'):.2f} m/s, "
            f"return {mean('return'):.1f} -> {path}")


class _IncompleteError(Exception):
    """Leaves :func:`fresh_output`'s block so that the new output is discarded and the earlier one kept."""


def evaluate(
    run: Path,
    episodes: int = EVALUATION.episodes,
    density: float | None = None,
    seed: int | None = None,
    record: bool = False,
    out: Path | None = None,
    overwrite: bool = False,
    progress: bool = True,
    shield: bool | None = None,
    scenario: str | None = None,
) -> EvaluationResult:
    """Run the deterministic policy for ``episodes`` episodes into the eval folder.

    The output is written beside ``out`` and replaces it only at the end (an old evaluation is
    never lost to a failed or interrupted one). Ctrl-C or SIGTERM keep the complete episodes and
    drop the one in progress, so no partial recording looks complete; when they interrupt the
    replacement of an earlier evaluation (``overwrite``), the earlier one is kept whole instead.
    ``shield`` True/False switches the safety
    shield on/off for the evaluation only (None: as the run's config). ``scenario`` ``"onramp"`` drives a
    ring-trained policy on the on-ramp (:func:`on_another_road`)."""
    folder = RunDir(run)
    cfg, default = evaluation_config(folder, density, shield, scenario)
    out = out or default
    check_replaceable(out, overwrite, "evaluate")
    model_path = folder.find_model()
    model = load_model(folder, cfg)
    base_seed = (cfg.seed if seed is None else seed) + EVALUATION.seed_offset
    try:
        return _evaluate_into(out, overwrite, cfg, model, model_path, base_seed, episodes, record, progress)
    except _IncompleteError:
        return EvaluationResult(out, 0, True, kept_earlier=True)


def evaluation_config(folder: RunDir, density: float | None = None, shield: bool | None = None,
                      scenario: str | None = None) -> tuple[LaneFreeConfig, Path]:
    """The config an evaluation of ``folder``'s run drives (its own, with another density, shield or road) and
    its default output folder (``RUN/eval``, ``RUN/eval_d<density>``, …: :meth:`RunDir.eval_dir`)."""
    cfg = folder.load_config()
    trained_density, trained_shield, trained_road = cfg.scenario.density_veh_per_km, cfg.shield.enabled, cfg.road.kind
    if scenario is not None and scenario != trained_road:
        cfg = on_another_road(cfg, scenario)
    if density is not None:
        cfg = merge_config(cfg, {"scenario": {"density_veh_per_km": validate_density(density)}})
    if shield is not None:
        cfg = merge_config(cfg, {"shield": {"enabled": shield}})
    d = cfg.scenario.density_veh_per_km
    return cfg, folder.eval_dir(None if d == trained_density else d,
                                None if cfg.shield.enabled == trained_shield else cfg.shield.enabled,
                                None if cfg.road.kind == trained_road else cfg.road.kind)


@dataclass
class ManyResult:
    """What :func:`evaluate_many` did: the runs evaluated (their results), those whose evaluation was complete
    already, those without a final model (still training or unfinished), and whether it was interrupted."""

    evaluated: list[EvaluationResult]
    complete: list[Path]
    unfinished: list[Path]
    interrupted: bool


def evaluate_many(runs: list[Path], episodes: int = EVALUATION.episodes, density: float | None = None,
                  seed: int | None = None, record: bool = False, overwrite: bool = False, progress: bool = True,
                  shield: bool | None = None, scenario: str | None = None,
                  report: Any = None) -> ManyResult:
    """Evaluate every finished run of ``runs`` (one with its ``model.zip``) into its default output folder, unless
    that folder already holds ``episodes`` episodes (``overwrite``: every one again); an evaluation stopped
    part-way is run again whole. ``report(result)`` is called after each. Stops at the first interrupted one."""
    out = ManyResult([], [], [], False)
    for run in runs:
        folder = RunDir(run)
        if not folder.model.is_file():
            out.unfinished.append(run)
            continue
        _, target = evaluation_config(folder, density, shield, scenario)
        if not overwrite and _episodes_in(target) >= episodes:
            out.complete.append(run)
            continue
        result = evaluate(run, episodes=episodes, density=density, seed=seed, record=record, out=target,
                          overwrite=True, progress=progress, shield=shield, scenario=scenario)
        out.evaluated.append(result)
        if report is not None:
            report(result)
        if result.interrupted or result.kept_earlier:
            out.interrupted = True
            break
    return out


def _episodes_in(out: Path) -> int:
    """Complete episode rows of an evaluation folder's ``episodes.csv`` (0 when there is none)."""
    path = out / "episodes.csv"
    if not path.is_file():
        return 0
    with open(path, newline="") as fh:
        return max(sum(1 for _ in fh) - 1, 0)


def _evaluate_into(out: Path, overwrite: bool, cfg: LaneFreeConfig, model: Any, model_path: Path, base_seed: int,
                   episodes: int, record: bool, progress: bool) -> EvaluationResult:
    """The episodes into a new output folder swapped in at the end; an interrupted replacement of an
    earlier output raises :class:`_IncompleteError` (the new folder is dropped, the earlier one stays)."""
    d = cfg.scenario.density_veh_per_km
    with fresh_output(out, overwrite, "evaluate") as tmp, stop_requested() as stop:
        replacing = out.is_dir() and any(out.iterdir())  # under the claim: no other writer changes it now
        write_config(tmp, cfg)
        if record:
            (tmp / TRAJECTORIES).mkdir()
            (tmp / RECORDING).write_text(json.dumps({
                "model": str(model_path), "net_file": cfg.net_file, "road_length_m": road_of(cfg).length_m,
                "road_width_m": cfg.road.width_m, "step_s": cfg.sim.step_s, "density_veh_per_km": d,
                "agent_ids": [agent_id(i) for i in range(cfg.scenario.agents)],
                "format": "lanefree_sumo.experiments.storage.trajectory (t,id,x,y,vx,vy,ax,ay,overlap"
                + (",shielded)" if cfg.shield.enabled else ")"),
            }, indent=2) + "\n")
        done = _run_episodes(model, cfg, tmp, base_seed, episodes, record, progress, stop)
        if done < episodes and replacing:
            raise _IncompleteError
    return EvaluationResult(out, done, done < episodes)


def on_another_road(cfg: LaneFreeConfig, scenario: str) -> LaneFreeConfig:
    """``cfg`` of a ring-trained run moved to the on-ramp for a zero-shot evaluation: the agent starts on
    the main road upstream of the ramp (it never learned to merge) and sees the ring's observation (no
    road features); traffic, density and everything else as configured. RunError for a road the policy
    cannot drive (an on-ramp policy needs its road features)."""
    if scenario != "onramp" or cfg.road.kind != "ring":
        raise RunError(f"--scenario {scenario} cannot evaluate a policy trained on the {cfg.road.kind}: "
                       "only ring-trained policies move to another road (--scenario onramp)")
    return merge_config(cfg, {"road": {"kind": "onramp", "onramp": {"agent_start": "main"}}, "net_file": "",
                              "observation": {"road_features": False}})


def load_model(folder: RunDir, cfg: LaneFreeConfig) -> Any:
    """RUN's final model (or newest checkpoint's), on the CPU; RunError naming it when unusable.

    torch runs on the run's ``train.torch_threads``, as in training. Its default, a thread per core, gives the
    same episodes bit for bit but only contends with SUMO and with runs beside it (3 set-encoder episodes with
    two trainings on both cores: 8.3 s, against 5.3 s on one thread)."""
    import torch

    torch.set_num_threads(cfg.train.torch_threads)
    model_path = folder.find_model()
    try:
        return load_saved_model(cfg.train.algo, model_path)
    except Exception as exc:
        raise RunError(f"{model_path} cannot be loaded ({type(exc).__name__}: {exc})") from None


def _run_episodes(model: Any, cfg: LaneFreeConfig, out: Path, base_seed: int, episodes: int, record: bool,
                  progress: bool, stop: StopRequest) -> int:
    """Episodes 1..``episodes`` into ``out``; returns how many completed (fewer once ``stop`` is
    requested: the episode in progress is dropped with its recording)."""
    from tqdm import tqdm

    from lanefree_sumo.experiments.storage.trajectory import TrajectoryWriter
    from lanefree_sumo.rl.multi_agent import PolicyDriver

    log = EpisodeLog(out / EPISODES, episode_columns(cfg))
    driver = PolicyDriver(cfg)
    sim = driver.sim
    done = 0
    try:
        for k in tqdm(range(1, episodes + 1), desc="evaluate", unit="ep", disable=not progress):
            if stop.requested:
                break
            obs = driver.reset(base_seed + k)
            writer = (TrajectoryWriter(trajectory_path(out, k), cfg.sim.step_s, overlap=True, shield=cfg.shield.enabled,
                                       vehicles=vehicles_path(out, k)) if record else None)
            if writer:
                writer.write(0, sim.current()[0], None)
            rows: list[dict[str, Any]] = []
            finished = False
            while not finished and not stop.requested:
                action, _ = model.predict(obs, deterministic=True)
                obs, finished, shielded, rows = driver.step(action)
                if writer:
                    writer.write(sim.steps, sim.current()[0], sim.last_result, shielded=shielded)
            if not finished:  # stopped mid-episode: no partial recording may look complete
                if writer:
                    writer.close()
                trajectory_path(out, k).unlink(missing_ok=True)
                vehicles_path(out, k).unlink(missing_ok=True)
                break
            if writer:
                writer.close()
            for row in rows:
                log.append({**row, "episode": k, "algorithm": cfg.train.algo, "timesteps": int(model.num_timesteps)})
            done = k
    finally:
        log.close()
        driver.close()
    return done

"""One run's data as the report, the learning curves, the sweep summary and the claims check read it
(its own module, so that those import it and not each other): :class:`RunData`, and :func:`read_run`,
which reads it from a run folder (its config and its ``episodes.csv``, or an evaluation's)."""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from lanefree_sumo.config import SAME_RESULTS, LaneFreeConfig, config_differences
from lanefree_sumo.errors import RunError
from lanefree_sumo.experiments.storage.rundir import EPISODES, read_config
from lanefree_sumo.rl.algorithms import unused_config

RunKey = tuple[str, str, float, str]
"""(algorithm, reward preset, density veh/km, variant): the group of a run."""


@dataclass
class RunData:
    """One usable run: its group key, seed and per-episode metrics."""

    path: Path
    algorithm: str
    preset: str
    density: float
    """Background density (veh/km)."""
    seed: int
    episodes: pd.DataFrame
    """Index ``episode`` (ascending, unique), float columns ``REQUIRED_COLUMNS[1:]``."""
    variant: str = ""
    """How the run's config differs from the defaults beyond the group key (``""`` for none)."""
    road: str = "ring"
    """The road its episodes were driven on (``road.kind``; the paper's values are the ring's)."""

    @property
    def key(self) -> RunKey:
        return (self.algorithm, self.preset, self.density, self.variant)


REQUIRED_COLUMNS: tuple[str, ...] = ("episode", "return", "collisions", "speed_dev_mps", "overtakes")
"""Columns of ``episodes.csv`` the report needs; the others of :data:`.episodes.EPISODE_COLUMNS` are ignored but for
:data:`OPTIONAL_COLUMNS`."""
OPTIONAL_COLUMNS: tuple[str, ...] = ("mean_speed_mps", "speed_dev_episode_mps", "speed_error_mps",
                                     "return_reciprocal", "return_bonus", "return_collision")
"""Columns read where a file has them (older runs lack the last five; :func:`read_run` derives the two speed
readings from ``mean_speed_mps``); a value that is not a number reads as NaN."""

NOT_VARIANT: tuple[str, ...] = ("seed", "train.algo", "reward.preset", "scenario.density_veh_per_km",
                                 "scenario.with_agent", "action.kind", *SAME_RESULTS)
"""Config keys that are part of the group key already or follow from it (training sets ``action.kind``
from the algorithm), the same in every training run (the agent), or do not change what a run learns
(:data:`~lanefree_sumo.config.SAME_RESULTS`). A run's planned
``train.episodes`` is part of the variant: last-50 means of 150- and 625-episode runs do not average."""

_DEFAULT_CONFIG = LaneFreeConfig()
"""What a run's variant is measured against (built once, not per run)."""


class UnusableRunError(Exception):
    """A run folder that must be skipped; the message is the reason."""


def _one_line(text: object) -> str:
    return " ".join(str(text).split())


def variant_of(cfg: LaneFreeConfig, planned: bool = True) -> str:
    """``key=value, …`` of the settings where ``cfg`` differs from the defaults (beyond
    :data:`NOT_VARIANT` and the hyperparameters the run never read,
    :func:`~lanefree_sumo.rl.algorithms.unused_config`); ``""`` for a default run. ``planned=False`` leaves out
    ``train.episodes`` (runs read over the same first episodes, whatever their length)."""
    ignore = NOT_VARIANT + unused_config(cfg.train.algo) + (() if planned else ("train.episodes",))
    return ", ".join(f"{k}={v}" for k, v in config_differences(cfg, _DEFAULT_CONFIG, ignore).items())


def _run_config(run: Path) -> LaneFreeConfig:
    """``run/config.yaml``; raises ``UnusableRunError`` with the reason when it is missing or malformed."""
    try:
        return read_config(run)
    except RunError as exc:
        raise UnusableRunError(str(exc)) from None


def read_episodes(path: Path) -> pd.DataFrame:
    """The required metrics of an ``episodes.csv``, indexed by episode (ascending); a run of several agents
    (an ``agent`` column, one row per agent and episode) gives each episode the mean over its agents.

    Strict: every non-blank row must have as many fields as the header (a last line cut in the
    middle fails here), required values must be finite numbers, episode numbers integral and
    unique (per agent). Raises ``UnusableRunError`` with the reason, naming the line.
    """
    if not path.is_file():
        raise UnusableRunError("no episodes.csv")
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            reader = csv.reader(fh)
            header = next(reader, None)
            if header is None:
                raise UnusableRunError("episodes.csv is empty")
            header = [h.strip() for h in header]
            missing = [c for c in REQUIRED_COLUMNS if c not in header]
            if missing:
                raise UnusableRunError(f"episodes.csv lacks column(s) {', '.join(missing)}")
            columns = [*REQUIRED_COLUMNS, *(c for c in OPTIONAL_COLUMNS if c in header)]
            index = {c: header.index(c) for c in columns}
            agent_at = header.index("agent") if "agent" in header else None
            agents: list[str] = []
            rows: list[list[float]] = []
            for fields in reader:
                if not fields or all(not f.strip() for f in fields):
                    continue
                line = reader.line_num
                if len(fields) != len(header):
                    cut = " (file cut mid-row?)" if len(fields) < len(header) else ""
                    raise UnusableRunError(
                        f"episodes.csv line {line} has {len(fields)} fields, header has {len(header)}{cut}")
                row = []
                for col in columns:
                    text = fields[index[col]].strip()
                    try:
                        value = float(text)
                    except ValueError:
                        value = math.nan
                    if not math.isfinite(value) and col in REQUIRED_COLUMNS:
                        raise UnusableRunError(f"episodes.csv line {line}: {col} = {text!r} is not a finite number")
                    row.append(value)
                rows.append(row)
                if agent_at is not None:
                    agents.append(fields[agent_at].strip())
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise UnusableRunError(f"episodes.csv unreadable ({_one_line(exc)})") from None
    return _episode_frame(rows, agents, columns)


def _episode_frame(rows: list[list[float]], agents: list[str], columns: list[str]) -> pd.DataFrame:
    """:func:`read_episodes`' frame of the rows read (``agents``: each row's agent, or empty)."""
    if not rows:
        raise UnusableRunError("episodes.csv has no episodes")
    frame = pd.DataFrame(rows, columns=columns)
    if not np.all(frame["episode"] == np.round(frame["episode"])):
        raise UnusableRunError("episodes.csv has a non-integer episode number")
    frame["episode"] = frame["episode"].astype(int)
    keys = frame[["episode"]].assign(agent=agents) if agents else frame[["episode"]]
    repeated = frame["episode"][keys.duplicated()]
    if len(repeated):
        who = " for one agent" if agents else ""
        raise UnusableRunError(f"episodes.csv has episode {int(repeated.iloc[0])} more than once{who}")
    if agents:
        return frame.groupby("episode").mean().sort_index()
    return frame.set_index("episode").sort_index()


def _evaluated_density(path: Path, trained: float) -> float:
    """The density (veh/km) an evaluation ran at: its CSV's ``density`` column when that holds one
    value (``lanefree evaluate --density``), else the training density."""
    try:
        values = pd.read_csv(path, usecols=["density"])["density"].unique()
    except (OSError, ValueError, KeyError):
        return trained
    return round(float(values[0]), 6) if len(values) == 1 and math.isfinite(values[0]) else trained


def read_run(run: Path, source: str = "", first: int | None = None) -> RunData:
    """Read one run folder — its training ``episodes.csv``, or with ``source`` the one of its
    evaluation folder ``run/<source>/`` (e.g. ``eval``, ``eval_d120_shield``); raises
    ``UnusableRunError`` with the reason to skip it. ``first``: only the training episodes 1 … ``first``,
    the planned number of episodes then not part of the variant (a run with fewer episodes is unusable)."""
    if not run.is_dir():
        raise UnusableRunError("not a folder" if run.exists() else "folder does not exist")
    cfg = _run_config(run)
    algo, preset, seed = cfg.train.algo, cfg.reward.preset, cfg.seed
    density = round(float(cfg.scenario.density_veh_per_km), 6)
    variant = variant_of(cfg, planned=first is None)
    desired = cfg.scenario.agent
    v_d = desired.desired_speed_min_mps if desired.desired_speed_min_mps == desired.desired_speed_max_mps else None
    if not source:
        episodes = read_episodes(run / EPISODES)
        if first is not None:
            if episodes.index.max() < first:
                raise UnusableRunError(f"has {int(episodes.index.max())} episode(s), fewer than the first {first} "
                                       "asked for")
            episodes = episodes.loc[:first]
        return RunData(run, algo, preset, density, seed, with_speed_readings(episodes, v_d), variant, cfg.road.kind)
    if first is not None:
        raise ValueError("first applies to the training episodes, not to an evaluation")
    path = run / source / EPISODES
    if not path.is_file():
        raise UnusableRunError(f"no {source}/{EPISODES} (run 'lanefree evaluate' first)")
    return RunData(run, algo, preset, _evaluated_density(path, density), seed,
                   with_speed_readings(read_episodes(path), v_d), variant, _road(run / source, cfg.road.kind))


def with_speed_readings(episodes: pd.DataFrame, v_d: float | None) -> pd.DataFrame:
    """``episodes`` with the per-episode speed readings (``speed_error_mps`` = mean vx − v_d, signed, and
    ``speed_dev_episode_mps`` = its absolute value, m/s) derived from ``mean_speed_mps`` where a file written
    before they were recorded lacks them (the agent's desired speed ``v_d`` is one number; None: not
    derivable)."""
    if "speed_error_mps" in episodes or "mean_speed_mps" not in episodes or v_d is None:
        return episodes
    error = episodes["mean_speed_mps"] - v_d
    return episodes.assign(speed_error_mps=error, speed_dev_episode_mps=error.abs())


def _road(folder: Path, default: str) -> str:
    """The road (``road.kind``) of the evaluation ``folder`` by its config.yaml; ``default`` without a readable
    one."""
    try:
        return read_config(folder).road.kind
    except RunError:
        return default

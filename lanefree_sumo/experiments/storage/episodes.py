"""A run's ``episodes.csv`` (and an evaluation's): its columns and its writer, one row per finished episode
(and agent), appended and flushed at once. Training and evaluation both write it; the report reads it
(:mod:`.rundata`)."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

from lanefree_sumo.config import LaneFreeConfig
from lanefree_sumo.rl.problem import METRIC_TERMS
from lanefree_sumo.sim.road import road_kind

__all__ = ["EPISODE_COLUMNS", "MULTI_AGENT_COLUMNS", "EpisodeLog", "episode_columns"]

_COLUMNS = (
    "episode", "steps", "return", "collisions", "collision_steps", "background_collisions", "speed_dev_mps",
    "mean_speed_mps", "overtakes", "boundary_contacts", "mean_c_x", "mean_c_y", "mean_c_f", "mean_reward",
    "density", "seed", "algorithm", "reward_preset", "timesteps", "wall_s", "shield_interventions",
    "speed_dev_episode_mps", "speed_error_mps", "return_reciprocal", "return_bonus", "return_collision",
)
EPISODE_COLUMNS = _COLUMNS + tuple(f"mean_{t}" for t in METRIC_TERMS if f"mean_{t}" not in _COLUMNS)
"""The columns of every run's ``episodes.csv``: a reward term beyond the paper's adds its per-step mean
(``mean_<term>``) at the end."""
MULTI_AGENT_COLUMNS = ("agent", "agent_collisions")
"""Added to ``EPISODE_COLUMNS`` in runs of several agents (one row per agent and episode)."""


def episode_columns(cfg: LaneFreeConfig) -> tuple[str, ...]:
    """The columns of a run's ``episodes.csv``."""
    return (EPISODE_COLUMNS + (MULTI_AGENT_COLUMNS if cfg.scenario.agents > 1 else ())
            + road_kind(cfg).metrics)


TENSORBOARD_SCALARS = ("return", "collisions", "speed_dev_mps", "overtakes", "mean_speed_mps", "shield_interventions")
"""The episode metrics a run's TensorBoard log gets at each episode's end, as ``episode/<name>`` (a single run's
logger and a batch's run alike)."""


class EpisodeLog:
    """``episodes.csv``: one row per finished episode (and agent), appended and flushed at once."""

    def __init__(self, path: Path, columns: tuple[str, ...] = EPISODE_COLUMNS) -> None:
        self.path = path
        new = not path.exists() or path.stat().st_size == 0
        if not new:  # a resumed run keeps its file's columns (one written before columns were added has fewer)
            with open(path, newline="") as fh:
                header = next(csv.reader(fh), None)
            columns = tuple(header) if header else columns
        self._fh = open(path, "a", newline="")
        self._writer = csv.DictWriter(self._fh, fieldnames=columns, extrasaction="ignore")
        if new:
            self._writer.writeheader()
            self._fh.flush()

    def append(self, row: dict[str, Any]) -> None:
        self._writer.writerow(row)
        self._fh.flush()

    def close(self) -> None:
        self._fh.close()

    @staticmethod
    def missing(path: Path, episodes: int, rows_per_episode: int = 1) -> list[int]:
        """Episodes among 1..``episodes`` that ``path`` lacks, holds a wrong number of times (each has
        ``rows_per_episode`` rows: one per agent) or holds in a half-written row (fewer fields than the header)."""
        counts: dict[int, int] = {}
        if path.exists():
            with open(path, newline="") as fh:
                for row in csv.DictReader(fh):
                    text = (row.get("episode") or "").strip()
                    whole = None not in row.values() and None not in row
                    if text.isdigit() and whole:
                        counts[int(text)] = counts.get(int(text), 0) + 1
        return [k for k in range(1, episodes + 1) if counts.get(k, 0) != rows_per_episode]

    @staticmethod
    def truncate(path: Path, episodes: int, columns: tuple[str, ...] = EPISODE_COLUMNS) -> None:
        """Keep the header and the rows of episodes 1..``episodes`` (drops rows a crash left
        beyond the checkpoint, so a resumed run has no duplicates)."""
        if not path.exists():
            return
        with open(path, newline="") as fh:
            rows = list(csv.DictReader(fh))
        kept = [r for r in rows if r.get("episode", "").isdigit() and int(r["episode"]) <= episodes]
        with open(path, "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=columns, extrasaction="ignore")
            writer.writeheader()
            writer.writerows(kept)

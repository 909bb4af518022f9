"""One run's data as the report, the learning curves, the sweep summary and the claims check read it
(its own module, so that those import it and not each other)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pandas as pd

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

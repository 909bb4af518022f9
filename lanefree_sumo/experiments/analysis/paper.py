"""The paper's reference results (specification §10, Karalakou et al. 2023 Tables 5–8).

Last-50-episode means over 10 runs: agent collisions per episode and speed deviation (m/s),
keyed by (algorithm, reward preset, density veh/km). :data:`PAPER_ROWS` keeps the table each
number comes from, so grids of experiments can be built per table.
"""

from __future__ import annotations

from typing import NamedTuple

DEFAULT_DENSITY = 70.0
"""Density (veh/km) of the paper's tables that do not vary it (Tables 5, 6, 8)."""

GroupKey = tuple[str, str, float]
"""(algorithm, reward preset, density in veh/km)."""


class PaperReference(NamedTuple):
    """One reference result of the paper (specification §10): last-50-episode means over 10 runs."""

    collisions: float
    """Agent collisions per episode."""
    speed_dev_mps: float
    """Speed deviation mean |vx − v_d| (m/s)."""
    source: str
    """Paper table(s) reporting it, e.g. ``"Tables 6, 7, 8"``."""


# (table, algorithm, preset, density veh/km, collisions / episode, speed deviation m/s) — specification §10.
PAPER_ROWS: tuple[tuple[int, str, str, float, float, float], ...] = (
    # Table 5: DDPG, reward presets, 70 veh/km
    (5, "ddpg", "collision", DEFAULT_DENSITY, 2.256, 0.135),
    (5, "ddpg", "fields", DEFAULT_DENSITY, 1.761, 0.323),
    (5, "ddpg", "fields_collision", DEFAULT_DENSITY, 0.726, 0.698),
    (5, "ddpg", "overtake_collision", DEFAULT_DENSITY, 2.293, 0.058),
    (5, "ddpg", "fields_overtake_collision", DEFAULT_DENSITY, 0.649, 0.613),
    # Table 6: DDPG, zones vs fields, 70 veh/km
    (6, "ddpg", "fields_zones_overtake_collision", DEFAULT_DENSITY, 0.449, 0.723),
    (6, "ddpg", "fields_overtake_collision", DEFAULT_DENSITY, 0.649, 0.613),
    (6, "ddpg", "zones_overtake_collision", DEFAULT_DENSITY, 1.282, 0.403),
    # Table 7: DDPG, densities
    (7, "ddpg", "fields_zones_overtake_collision", 70.0, 0.449, 0.723),
    (7, "ddpg", "fields_zones_overtake_collision", 90.0, 0.508, 0.998),
    (7, "ddpg", "fields_zones_overtake_collision", 120.0, 0.591, 1.718),
    (7, "ddpg", "fields_overtake_collision", 70.0, 0.649, 0.613),
    (7, "ddpg", "fields_overtake_collision", 90.0, 0.771, 0.956),
    (7, "ddpg", "fields_overtake_collision", 120.0, 1.066, 1.715),
    # Table 8: algorithms, fields_zones_overtake_collision, 70 veh/km
    (8, "ddpg", "fields_zones_overtake_collision", DEFAULT_DENSITY, 0.449, 0.723),
    (8, "dqn", "fields_zones_overtake_collision", DEFAULT_DENSITY, 0.952, 0.471),
    (8, "ddqn", "fields_zones_overtake_collision", DEFAULT_DENSITY, 1.094, 0.483),
    (8, "dueling", "fields_zones_overtake_collision", DEFAULT_DENSITY, 1.04, 0.496),
    (8, "per", "fields_zones_overtake_collision", DEFAULT_DENSITY, 0.792, 0.617),
)


def _build_paper_reference() -> dict[GroupKey, PaperReference]:
    """Merge the per-table rows; a setting in several tables must have the same numbers there."""
    values: dict[GroupKey, tuple[float, float]] = {}
    tables: dict[GroupKey, list[int]] = {}
    for table, algo, preset, density, collisions, speed_dev in PAPER_ROWS:
        key = (algo, preset, float(density))
        if key in values and values[key] != (collisions, speed_dev):
            raise AssertionError(f"paper tables disagree for {key}: {values[key]} vs {(collisions, speed_dev)}")
        values[key] = (collisions, speed_dev)
        tables.setdefault(key, []).append(table)
    out: dict[GroupKey, PaperReference] = {}
    for key, (collisions, speed_dev) in values.items():
        nums = sorted(set(tables[key]))
        source = ("Table " if len(nums) == 1 else "Tables ") + ", ".join(str(n) for n in nums)
        out[key] = PaperReference(collisions, speed_dev, source)
    return out


PAPER_REFERENCE: dict[GroupKey, PaperReference] = _build_paper_reference()
"""specification §10 reference numbers keyed by (algorithm, reward preset, density veh/km)."""


def paper_reference(algorithm: str, preset: str, density: float, road: str = "ring") -> PaperReference | None:
    """The paper's result for a setting driven on ``road`` (``road.kind``), or None if the paper has none: a
    setting it did not run, or another road than its ring (density in veh/km)."""
    if road != "ring":
        return None
    return PAPER_REFERENCE.get((algorithm, preset, round(float(density), 6)))

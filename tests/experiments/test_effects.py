"""The open-choices effect table: each variant against the default per cell, with the verdicts' rules
(decides racing / moves the numbers / no effect detected / too few runs) at their boundaries."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest

from lanefree_sumo.experiments.analysis.effects import COLUMNS, effect_table, effects_markdown, overview, verdict
from lanefree_sumo.experiments.storage.rundata import RunData

CELL = ("dqn", "fields_zones_overtake_collision", 70.0)


def _runs(variant: str, speeds: list[float], collisions: list[float], cell: tuple = CELL) -> list[RunData]:
    """One run per seed whose every episode has this mean speed (m/s) and collisions; 60 episodes, so the last
    50 are read."""
    out = []
    for seed, (v, c) in enumerate(zip(speeds, collisions)):
        frame = pd.DataFrame({"mean_speed_mps": [0.0] * 10 + [v] * 50, "collisions": [99.0] * 10 + [c] * 50,
                              "speed_dev_mps": abs(v - 20.0), "speed_dev_episode_mps": abs(v - 20.0),
                              "overtakes": 0.0, "return": 100.0, "return_reciprocal": 100.0, "return_bonus": 0.0,
                              "return_collision": 0.0}, index=pd.RangeIndex(1, 61, name="episode"))
        out.append(RunData(Path(f"{variant}_s{seed}"), *cell, seed, frame, variant))
    return out


def test_verdicts_at_their_rules() -> None:
    groups = {
        (*CELL, "default"): _runs("default", [28.0, 28.5, 27.9, 29.0], [20.0, 19.0, 21.0, 20.5]),
        (*CELL, "calm"): _runs("calm", [20.0, 20.1, 19.9, 20.2], [1.0, 1.5, 0.5, 1.2]),          # 4/4 → 0/4 racing
        (*CELL, "fewer"): _runs("fewer", [28.0, 28.5, 27.9, 29.0], [10.0, 9.0, 11.0, 10.5]),     # collisions halved
        (*CELL, "same"): _runs("same", [28.1, 28.4, 28.0, 28.9], [20.1, 19.2, 20.8, 20.4]),      # interleaved
        (*CELL, "two"): _runs("two", [20.0, 20.1], [1.0, 1.5]),                                 # 2 runs
        (*CELL, "half"): _runs("half", [28.0, 28.5, 20.0, 20.1], [20.0, 19.0, 1.0, 1.5]),        # 2/4 racing
    }
    table = effect_table(groups, last=50)
    assert tuple(table.columns) == COLUMNS
    verdicts = {v: verdict(rows) for v, rows in table.groupby("variant")}
    assert verdicts == {"calm": "decides racing", "fewer": "moves the numbers", "same": "no effect detected",
                        "two": "too few runs", "half": "no effect detected"}
    # half: racing −0.5 meets the fraction rule, but the speeds' rank test (4 vs 4: 2 of 4 lower) has p > 0.05
    calm = table[(table["variant"] == "calm")].set_index("metric")
    assert calm.loc["racing_fraction", "difference"] == -1.0
    assert calm.loc["collisions", "difference"] == pytest.approx((1.0 + 1.5 + 0.5 + 1.2) / 4 - 20.125)
    assert calm.loc["mean_speed_mps", "rank_p"] == pytest.approx(2 / 70)  # every calm run below every default one
    assert calm.loc["collisions", "ci95_high"] < 0
    md = effects_markdown(table, 50)
    assert "| calm | 4, 4 | decides racing | 100% → 0% |" in md
    assert "## dqn / fields_zones_overtake_collision / 70 veh/km" in md


def test_no_default_no_rows() -> None:
    assert effect_table({(*CELL, "calm"): _runs("calm", [20.0] * 3, [1.0] * 3)}).empty
    assert "No cell has both" in effects_markdown(effect_table({}), 50)


def test_a_choices_verdict_over_cells_is_its_strongest_with_enough_runs() -> None:
    """The overview: per choice its verdict in each cell and the strongest of them; a cell with too few runs
    does not weaken it, and decides it only where no cell has enough."""
    calm = ("ddpg", "collision", 70.0)
    racing, calm_speeds = [28.0, 28.5, 27.9, 29.0], [20.0, 20.1, 19.9, 20.2]
    groups = {
        (*CELL, "default"): _runs("default", racing, [20.0] * 4),
        (*CELL, "once"): _runs("once", calm_speeds, [2.0] * 4),             # decides racing here
        (*CELL, "short"): _runs("short", calm_speeds[:2], [2.0] * 2),        # too few here …
        (*calm, "default"): _runs("default", calm_speeds, [2.0] * 4, calm),
        (*calm, "once"): _runs("once", [20.1, 20.0, 20.2, 19.9], [2.0] * 4, calm),   # no effect here
        (*calm, "short"): _runs("short", calm_speeds, [1.0] * 4, calm),      # … moves the numbers here
        (*calm, "only"): _runs("only", calm_speeds[:2], [1.0] * 2, calm),   # too few in its only cell
    }
    headers, rows = overview(effect_table(groups, last=50))
    assert headers[2:] == ["dqn / fields_zones_overtake_collision / 70 veh/km", "ddpg / collision / 70 veh/km"]
    assert [row[:2] for row in rows] == [["once", "decides racing"], ["short", "moves the numbers"],
                                         ["only", "too few runs"]]
    assert rows[0][2:] == ["decides racing (racing 100% → 0%; runs 4, 4)",
                           "no effect detected (racing 0% → 0%; runs 4, 4)"]
    assert rows[1][2] == "too few runs (racing 100% → 0%; runs 4, 2)" and rows[2][2] == "–"

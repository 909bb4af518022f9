"""The open-choices effect table: each variant against the default per cell, with the verdicts' rules
(decides racing / moves the numbers / no effect detected / too few runs) at their boundaries."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest

from lanefree_sumo.experiments.analysis.effects import (
    COLUMNS,
    effect_table,
    effects_markdown,
    overview,
    study_markdown,
    verdict,
)
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


CALM = ("ddpg", "collision", 90.0)


def _flat(variant: str, collisions: float, runs: int = 3, cell: tuple = CALM, **columns: float) -> list[RunData]:
    """``runs`` calm runs (20 m/s) of 60 episodes, every episode with these collisions and ``columns``."""
    values = {"mean_speed_mps": 20.0, "collisions": collisions, "speed_dev_mps": 1.0, "speed_dev_episode_mps": 0.5,
              "overtakes": 0.0, "return": 50.0, "return_reciprocal": 50.0, "return_bonus": 0.0,
              "return_collision": 0.0, **columns}
    frame = pd.DataFrame({k: [v] * 60 for k, v in values.items()}, index=pd.RangeIndex(1, 61, name="episode"))
    return [RunData(Path(f"{variant}_s{seed}"), *cell, seed, frame, variant) for seed in range(runs)]


def test_a_sweeps_effects_page_is_exactly_its_figures_computed_by_hand() -> None:
    """Three runs a side, each constant over its episodes: the variant's collisions 1 against 2 give −1.00 with the
    bootstrap CI [−1.00, −1.00] and the rank test's p 2/20 (every variant run below every default run, two-sided);
    an unchanged metric +0.00 [+0.00, +0.00] (p 1.000); p 0.100 > 0.05: no effect detected."""
    table = effect_table({(*CALM, "default"): _flat("default", 2.0), (*CALM, "fewer"): _flat("fewer", 1.0)})
    same = "+0.00 [+0.00, +0.00] (p 1.000)"
    assert effects_markdown(table, 50).split("\n") == [
        "# Each open choice against the defaults", "",
        "Per run: the mean over its last 50 episodes. Racing: a run whose mean speed is above 24 m/s. Each figure: "
        "the variant's mean over runs minus the default's, [95 % percentile-bootstrap CI] (exact two-sided "
        "rank-test p). Verdicts: *decides racing* (the racing fractions differ by half or more and the mean speeds "
        "with p ≤ 0.05), *moves the numbers* (a CI excludes 0 with p ≤ 0.05), *no effect detected* (with few runs: "
        "low power), *too few runs* (below 3 a side).", "",
        "## ddpg / collision / 90 veh/km", "",
        "<!-- effects-ddpg-collision-90 -->", "",
        "| variant | runs (default, variant) | verdict | racing runs (default → variant) | collisions / episode | "
        "speed deviation per step (m/s) | speed deviation per episode (m/s) | overtakes / episode | return | "
        "return: overtake bonus |",
        "|---|---|---|---|---|---|---|---|---|---|",
        f"| fewer | 3, 3 | no effect detected | 0% → 0% | -1.00 [-1.00, -1.00] (p 0.100) | {same} | {same} | "
        f"{same} | {same} | {same} |",
        "", "<!-- /effects-ddpg-collision-90 -->", ""]


def test_the_study_page_is_the_overview_then_each_cells_section() -> None:
    """Two sweeps' effects: the overview table with the cells and the choices in the order they come (not sorted),
    then each cell's section as a sweep's page has it, in the same order; an empty study says so."""
    dqn, d70 = ("dqn", "collision", 90.0), ("ddpg", "collision", 70.0)
    table = effect_table({(*CALM, "default"): _flat("default", 2.0), (*CALM, "zeta"): _flat("zeta", 1.0),
                          (*CALM, "alpha"): _flat("alpha", 2.0),
                          (*dqn, "default"): _flat("default", 2.0, cell=dqn),
                          (*dqn, "zeta"): _flat("zeta", 2.0, cell=dqn),
                          (*d70, "default"): _flat("default", 2.0, cell=d70),
                          (*d70, "zeta"): _flat("zeta", 1.0, cell=d70)})
    page = study_markdown(table, 50, ["runs/a", "runs/b"]).split("\n")
    sweep_page = effects_markdown(table, 50).split("\n")
    assert page[:4] == ["# Each open choice against the defaults, every cell", "",
                        "From the sweeps `runs/a`, `runs/b`. " + sweep_page[2], ""]
    entry = "no effect detected (racing 0% → 0%; runs 3, 3)"
    assert page[4:11] == [
        "<!-- effects-overview -->", "",
        "| choice | verdict (strongest over the cells) | ddpg / collision / 90 veh/km | dqn / collision / 90 veh/km | "
        "ddpg / collision / 70 veh/km |",
        "|---|---|---|---|---|",
        f"| zeta | no effect detected | {entry} | {entry} | {entry} |",
        f"| alpha | no effect detected | {entry} | – | – |",
        ""]
    assert page[11:15] == ["<!-- /effects-overview -->", "",
                           "Runs: the default's and the choice's complete runs in the cell. –: no complete runs of the "
                           "choice in that cell (not in its grid, or not finished).", ""]
    assert page[15:] == sweep_page[4:]
    assert [line for line in sweep_page if line.startswith("## ")] == [
        "## ddpg / collision / 90 veh/km", "## dqn / collision / 90 veh/km", "## ddpg / collision / 70 veh/km"]
    assert [line.split(" | ")[0] for line in sweep_page if line.startswith(("| zeta", "| alpha"))] == [
        "| zeta", "| alpha", "| zeta", "| zeta"]
    empty = study_markdown(effect_table({}), 50, ["runs/a"]).split("\n")
    assert empty[4:] == ["No cell has both a `default` and another variant with complete runs yet.", ""]
    assert effects_markdown(effect_table({}), 50).split("\n")[4:] == empty[4:]


def _rows(racing: float = 0.0, speed_p: float = 1.0, p: float = 1.0, low: float = -1.0, high: float = 1.0,
          n: int = 3) -> pd.DataFrame:
    """One cell and variant's rows for :func:`verdict`: the racing fraction's difference, the mean speed's p and
    collisions' p and CI, ``n`` runs a side."""
    base = {"n_default": n, "n_variant": n, "ci95_low": -1.0, "ci95_high": 1.0, "rank_p": 1.0, "difference": 0.0}
    return pd.DataFrame([{**base, "metric": "racing_fraction", "difference": racing},
                         {**base, "metric": "mean_speed_mps", "rank_p": speed_p},
                         {**base, "metric": "collisions", "rank_p": p, "ci95_low": low, "ci95_high": high}])


def test_verdicts_exactly_at_their_boundaries() -> None:
    """Three runs a side is enough; half the runs racing with the speeds at p = 0.05 decides racing (less than half
    does not); a CI that touches 0, or excludes it at p just above 0.05, moves nothing; one that excludes 0 by less
    than 1 at p = 0.05 does."""
    assert verdict(_rows(n=3)) == "no effect detected" and verdict(_rows(n=2)) == "too few runs"
    assert verdict(_rows(racing=-0.5, speed_p=0.05)) == "decides racing"
    assert verdict(_rows(racing=0.49, speed_p=0.05)) == "no effect detected"
    assert verdict(_rows(racing=-0.5, speed_p=0.051)) == "no effect detected"
    assert verdict(_rows(p=0.05, low=0.5, high=2.0)) == "moves the numbers"
    assert verdict(_rows(p=0.05, low=-2.0, high=-0.5)) == "moves the numbers"
    assert verdict(_rows(p=0.05, low=0.0, high=2.0)) == "no effect detected"
    assert verdict(_rows(p=0.05, low=-2.0, high=0.0)) == "no effect detected"
    assert verdict(_rows(p=0.05, low=-0.5, high=0.5)) == "no effect detected"
    assert verdict(_rows(p=0.051, low=0.5, high=2.0)) == "no effect detected"


def test_the_last_episodes_the_racing_threshold_and_a_side_without_the_metric() -> None:
    """Each run's mean over its last 50 episodes by default (episodes 11–60 of 1, 2, …, 60: 35.5); a run at exactly
    24 m/s does not race; a side whose runs lack a column has no mean (and the table keeps its columns when
    empty)."""
    ramp = pd.DataFrame({"mean_speed_mps": [24.0] * 60, "collisions": [float(e) for e in range(1, 61)]},
                        index=pd.RangeIndex(1, 61, name="episode"))
    groups = {(*CALM, "default"): _flat("default", 2.0),
              (*CALM, "ramp"): [RunData(Path(f"ramp_s{s}"), *CALM, s, ramp, "ramp") for s in range(3)]}
    table = effect_table(groups).set_index("metric")
    assert table.loc["collisions", "variant_mean"] == 35.5 and table.loc["collisions", "difference"] == 33.5
    assert table.loc["collisions", "ci95_low"] == table.loc["collisions", "ci95_high"] == 33.5
    assert table.loc["racing_fraction", "variant_mean"] == 0.0
    assert table.loc["return", "n_variant"] == 0 and pd.isna(table.loc["return", "variant_mean"])
    assert table.loc["return", "default_mean"] == 50.0
    flipped = effect_table({(*CALM, "default"): groups[(*CALM, "ramp")], (*CALM, "flat"): _flat("flat", 2.0)})
    assert pd.isna(flipped.set_index("metric").loc["return", "default_mean"])
    assert tuple(effect_table({}).columns) == COLUMNS
    assert effect_table(groups, last=10).set_index("metric").loc["collisions", "variant_mean"] == 55.5


def test_a_row_with_too_few_runs_or_without_a_metric_shows_what_it_has() -> None:
    """Two runs: the difference alone (no CI, no p below three runs a side); runs without the speed column: no
    racing share and no figure (–)."""
    blind = [RunData(r.path, *CALM, r.seed, r.episodes.drop(columns=["mean_speed_mps", "overtakes"]), "blind")
             for r in _flat("blind", 1.0)]
    table = effect_table({(*CALM, "default"): _flat("default", 2.0), (*CALM, "two"): _flat("two", 1.0, runs=2),
                          (*CALM, "blind"): blind})
    rows = [line for line in effects_markdown(table, 50).split("\n") if line.startswith(("| two", "| blind"))]
    assert rows == ["| two | 3, 2 | too few runs | 0% → 0% | -1.00 | +0.00 | +0.00 | +0.00 | +0.00 | +0.00 |",
                    "| blind | 3, 0 | too few runs | – | -1.00 [-1.00, -1.00] (p 0.100) "
                    "| +0.00 [+0.00, +0.00] (p 1.000) | +0.00 [+0.00, +0.00] (p 1.000) | – "
                    "| +0.00 [+0.00, +0.00] (p 1.000) "
                    "| +0.00 [+0.00, +0.00] (p 1.000) |"]

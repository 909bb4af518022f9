"""The interpretation study's score and pick (results/interpretations/protocol.md) on hand-made run tables."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import pandas as pd
import pytest

from lanefree_sumo.config import LaneFreeConfig, merge_config
from lanefree_sumo.experiments.analysis.claims import AGAINST
from lanefree_sumo.experiments.analysis.interpretations import (
    BONUS_CELLS,
    CELLS,
    SEEDS,
    VARIANTS,
    cell_values,
    claims_by_variant,
    claims_markdown,
    distance,
    phase1_markdown,
    pick,
    run_folder,
    scores,
)
from lanefree_sumo.experiments.analysis.paper import paper_reference
from lanefree_sumo.experiments.storage.episodes import EpisodeLog, episode_columns
from lanefree_sumo.experiments.storage.rundir import write_config


def table(variant: str, presets, collisions_factor: float, speed_factor: float) -> list[dict]:
    rows = []
    for preset in presets:
        ref = paper_reference("ddpg", preset, 70.0)
        for seed in SEEDS:
            rows.append({"variant": variant, "reward_preset": preset, "density": 70.0, "seed": seed,
                         "collisions": ref.collisions * collisions_factor, "speed_dev_mps": ref.speed_dev_mps
                         * speed_factor})
    return rows


def runs() -> pd.DataFrame:
    return pd.DataFrame(table("", CELLS, 2.0, 1.0)  # the default: collisions twice the paper's everywhere
                        + table("once_per_vehicle", BONUS_CELLS, 1.0, 1.0)  # the paper's values where it applies
                        + table("cap25", CELLS, 1.0, math.e)
                        + table("both", BONUS_CELLS, 1.0, 1.0 / math.e))


def test_the_distance_is_the_mean_absolute_log_ratio_over_fourteen_figures():
    values = cell_values(runs(), "default")
    d, ratios = distance(values)
    assert d == pytest.approx(7 * math.log(2) / 14)
    assert all(r == (pytest.approx(math.log(2)), pytest.approx(0.0)) for r in ratios.values())
    cap = distance(cell_values(runs(), "cap25"))[0]
    assert cap == pytest.approx(0.5)  # speed off by e in every cell: |ln e| = 1 in 7 of 14 figures


def test_bonus_variants_take_the_other_runs_where_no_bonus_is_paid():
    once = distance(cell_values(runs(), "once_per_vehicle"))[0]
    assert once == pytest.approx(3 * math.log(2) / 14)  # the three cells without a bonus are the default's
    both = distance(cell_values(runs(), "both"))[0]
    assert both == pytest.approx((4 * 1 + 3 * 1) / 14)  # speed /e in the bonus cells, cap25's e in the others


def test_the_pick_is_the_smallest_distance_with_ties_to_the_earlier_variant():
    results = scores(runs(), resamples=200)
    assert [s.variant for s in results] == ["default", "once_per_vehicle", "cap25", "both"]
    assert pick(results).variant == "once_per_vehicle"
    tied = [results[2], replace(results[0], distance=results[2].distance)]
    assert pick(tied).variant == "default"
    page = phase1_markdown(results)
    assert "| **once_per_vehicle** |" in page and "Picked: **once_per_vehicle**" in page


def _score(variant: str, distance: float, difference: float = math.nan, low: float = math.nan,
           high: float = math.nan) -> Any:
    from lanefree_sumo.experiments.analysis.interpretations import Score

    ratios = {preset: (0.1 * k, -0.05 * k) for k, preset in enumerate(CELLS)}
    return Score(variant, distance, ratios, difference, low, high)


def test_the_phase1_table_in_full_and_a_pick_the_ci_cannot_tell_from_the_defaults():
    results = [_score("default", 1.0), _score("once_per_vehicle", 0.8, -0.2, -0.35, -0.05),
               _score("cap25", 0.5, -0.5, -0.9, 0.0), _score("both", 0.7, -0.3, -0.6, 0.1)]
    rows = "".join(f"| {preset} | " + " | ".join([f"{0.1 * k:+.2f} / {-0.05 * k:+.2f}"] * 4) + " |\n"
                   for k, preset in enumerate(CELLS))
    assert phase1_markdown(results) == (
        "| variant | D (mean abs log ratio) | D − D(default) [95 % CI] |\n|---|---|---|\n"
        "| default | 1.000 | – |\n"
        "| once_per_vehicle | 0.800 | -0.200 [-0.350, -0.050] |\n"
        "| **cap25** | 0.500 | -0.500 [-0.900, +0.000] |\n"
        "| both | 0.700 | -0.300 [-0.600, +0.100] |\n\n"
        "Picked: **cap25** (not distinguishable from the defaults: the CI of D − D(default) contains 0)\n\n"
        "ln(ours / paper) per cell, collisions / speed deviation:\n\n"
        "| cell | default | once_per_vehicle | cap25 | both |\n|---|---|---|---|---|\n" + rows)
    at_its_low = [results[0], _score("cap25", 0.5, 0.2, 0.0, 0.4)]  # a CI starting at exactly 0 contains it
    assert "Picked: **cap25** (not distinguishable from the defaults" in phase1_markdown(at_its_low)
    told_apart = [results[0], _score("cap25", 0.5, -0.5, -0.9, -1e-9)]
    assert "Picked: **cap25**\n\n" in phase1_markdown(told_apart)
    assert "Picked: **default**\n\n" in phase1_markdown([results[0]])  # no difference, no CI
    # a variant outside the protocol's list ranks after all of them on a tie
    assert pick([_score("other", 0.5), _score("both", 0.5)]).variant == "both"


def test_the_bootstrap_is_paired_by_seed_and_constant_runs_give_a_point_interval():
    once = scores(runs(), resamples=200)[1]
    assert once.low == pytest.approx(once.difference) and once.high == pytest.approx(once.difference)


def test_a_missing_run_is_named():
    partial = runs()
    partial = partial.drop(partial[(partial["variant"] == "cap25") & (partial["seed"] == 3)
                                   & (partial["reward_preset"] == "fields")].index)
    with pytest.raises(ValueError, match=r"variant cap25: the fields cell \(cap25's runs\) has seeds \[0, 1, 2, 4\]"):
        cell_values(partial, "cap25")
    with pytest.raises(ValueError, match="variant both: the fields cell"):
        cell_values(partial, "both")


def make_cells(results: Path, episodes: int = 60) -> None:
    """Every run folder phase 1 reads, made here (config.yaml, episodes.csv of ``episodes`` rows): seed s of a
    preset collides 10 × (the preset's place in CELLS) + s times per episode in every variant, so each variant
    holds the same numbers."""
    for variant in VARIANTS:
        for p, preset in enumerate(CELLS):
            for seed in SEEDS:
                to = run_folder(results, variant, preset, seed)
                if to.exists():
                    continue
                to.mkdir(parents=True)
                cfg = merge_config(LaneFreeConfig(), {"seed": seed, "reward": {"preset": preset}})
                write_config(to, cfg)
                log = EpisodeLog(to / "episodes.csv", episode_columns(cfg))
                for e in range(1, episodes + 1):
                    log.append({"episode": e, "steps": 800, "collisions": 10 * p + seed,
                                "speed_dev_mps": 1.0 + 0.1 * seed, "speed_dev_episode_mps": 0.5,
                                "speed_error_mps": -0.5, "mean_speed_mps": 19.5,
                                "return": 100.0, "overtakes": 3, "algorithm": "ddpg", "reward_preset": preset,
                                "density": 70.0, "seed": seed})
                log.close()


def test_the_claims_of_tables_5_and_6_under_each_variant(tmp_path):
    make_cells(tmp_path)
    table = claims_by_variant(tmp_path)
    assert list(dict.fromkeys(table["variant"])) == list(VARIANTS)
    blocks = [table[table["variant"] == v].reset_index(drop=True) for v in VARIANTS]
    assert len(blocks[0]) == 5 and set(blocks[0]["n_a"]) == {5}  # the claims of Tables 5-6 among the 7 cells
    # collision (place 0) − fields_collision (place 2): 20 fewer collisions, every pair of runs one way
    first = blocks[0].iloc[0]
    assert first["difference"] == -20.0 and first["verdict"] == AGAINST
    for block in blocks[1:]:  # the same runs under every name: the same verdicts
        assert list(block["verdict"]) == list(blocks[0]["verdict"])
    page = claims_markdown(table)
    assert page.count("\n") == 2 + 5 and "| claim | default | once_per_vehicle | cap25 | both |" in page
    assert run_folder(tmp_path, "both", "collision", 3).parent.parent.name == "phase1_cap25"  # no bonus: cap25's


def test_each_cell_under_the_three_readings_and_its_racing_runs(tmp_path):
    """The readings table: each run's last 50 episodes averaged (not its first), then the cell's runs; a run races
    above 24 m/s; a variant that does not change a cell shows the runs it stands for."""
    from lanefree_sumo.experiments.analysis.interpretations import readings_by_variant, readings_markdown

    make_cells(tmp_path)
    racer = run_folder(tmp_path, "cap25", "fields", 2)  # cap25's fields cell, seed 2: the last 50 differ
    cfg = merge_config(LaneFreeConfig(), {"seed": 2, "reward": {"preset": "fields"}})
    (racer / "episodes.csv").unlink()
    log = EpisodeLog(racer / "episodes.csv", episode_columns(cfg))
    for e in range(1, 61):
        late = e > 10
        log.append({"episode": e, "steps": 800, "collisions": 7.0 if late else 99.0,
                    "speed_dev_mps": 5.0 if late else 0.0, "speed_dev_episode_mps": 4.0 if late else 0.0,
                    "speed_error_mps": 4.5 if late else -9.0, "mean_speed_mps": 24.5 if late else 19.0,
                    "return": 1.0, "overtakes": 3, "algorithm": "ddpg", "reward_preset": "fields", "density": 70.0,
                    "seed": 2})
    log.close()
    table = readings_by_variant(tmp_path)
    assert list(table["variant"]) == [v for v in VARIANTS for _ in range(7)]
    assert list(table["cell"])[:7] == list(CELLS)
    fields = table[table["cell"] == "fields"].set_index("variant")
    # fields is place 1 of CELLS: seed s collides 10 + s times; seed 2 now 7 (its last 50)
    assert fields.loc["default", "collisions"] == pytest.approx(12.0)
    assert fields.loc["cap25", "collisions"] == pytest.approx((10 + 11 + 7 + 13 + 14) / 5)
    assert fields.loc["cap25", "speed_dev_mps"] == pytest.approx((1.0 + 1.1 + 5.0 + 1.3 + 1.4) / 5)
    assert fields.loc["cap25", "speed_dev_episode_mps"] == pytest.approx((0.5 * 4 + 4.0) / 5)
    assert fields.loc["cap25", "speed_error_mps"] == pytest.approx((-0.5 * 4 + 4.5) / 5)
    assert fields.loc["cap25", "racing"] == 1 and fields.loc["both", "racing"] == 1  # both stands for cap25 here
    assert fields.loc["default", "racing"] == 0 and fields.loc["once_per_vehicle", "racing"] == 0
    ref = paper_reference("ddpg", "fields", 70.0)
    assert fields.loc["both", "paper_collisions"] == ref.collisions
    assert fields.loc["both", "paper_speed_dev_mps"] == ref.speed_dev_mps
    page = readings_markdown(table)
    assert page.count("\n") == 2 + 28
    assert (f"| fields | cap25 | 11.00 | 1.96 | 1.20 | 0.50 | {ref.collisions:g} / {ref.speed_dev_mps:g} | 1 of 5 |"
            in page)
    assert "| collision | default | 2.00 | 1.20 | 0.50 | -0.50 |" in page


def test_the_figure_puts_each_cells_mean_against_the_papers_on_log_axes(tmp_path):
    """ours_vs_paper: two log-log panels (collisions, per-step speed deviation), one series per variant whose points
    are (the paper's value, the cell's mean), the diagonal over the points' span widened 1.5× either way, a legend
    of the variants; a PNG of 1100 × 495 pixels."""
    import matplotlib.image

    from lanefree_sumo.experiments.analysis.interpretations import FIGURE_METRICS, figure_points, ours_vs_paper

    found = scores(runs(), resamples=20)
    points = figure_points(found)
    assert len(points) == 2 and [list(panel) for panel in points] == [list(VARIANTS)] * 2
    refs = [paper_reference("ddpg", preset, 70.0) for preset in CELLS]
    for s in found:
        paper, ours = points[0][s.variant]
        assert paper == [r.collisions for r in refs]
        assert ours == pytest.approx([r.collisions * math.exp(s.log_ratios[c][0]) for r, c in zip(refs, CELLS)])
        paper, ours = points[1][s.variant]
        assert paper == [r.speed_dev_mps for r in refs]
        assert ours == pytest.approx([r.speed_dev_mps * math.exp(s.log_ratios[c][1]) for r, c in zip(refs, CELLS)])
    values = cell_values(runs(), "cap25")  # ours is the cell's mean, back from its log ratio
    assert points[0]["cap25"][1] == pytest.approx([max(values[c][:, 0].mean(), 0.01) for c in CELLS])
    path = tmp_path / "f.png"
    fig = ours_vs_paper(found, path)
    assert matplotlib.image.imread(path).shape[:2] == (495, 1100)
    assert len(fig.axes) == 2
    for ax, label, panel in zip(fig.axes, FIGURE_METRICS, points):
        assert (ax.get_xscale(), ax.get_yscale()) == ("log", "log")
        assert (ax.get_xlabel(), ax.get_ylabel()) == (f"paper: {label}", f"ours: {label}")
        drawn = [c.get_offsets() for c in ax.collections]
        assert [[tuple(xy) for xy in d] for d in drawn] == [list(zip(*panel[v])) for v in VARIANTS]
        everything = [v for paper, ours in panel.values() for v in paper + ours]
        [diagonal] = ax.lines
        assert list(diagonal.get_xdata()) == list(diagonal.get_ydata()) == pytest.approx(
            [min(everything) / 1.5, max(everything) * 1.5])
    assert [t.get_text() for t in fig.axes[0].get_legend().get_texts()] == list(VARIANTS)
    assert fig.axes[0].get_legend().get_title().get_text() == "variant" and fig.axes[1].get_legend() is None
    assert fig._suptitle.get_text().startswith("Tables 5–6, DDPG, 70 veh/km")


def test_the_phase1_page_and_figure_from_run_tables(tmp_path):
    from lanefree_sumo.experiments.analysis.interpretations import (
        phase1_page,
        phase1_runs,
        readings_by_variant,
        readings_markdown,
        write_phase1,
    )

    all_runs = runs()
    for folder, variants in (("paper", [""]), ("interpretations/phase1_bonus", ["once_per_vehicle", "both"]),
                             ("interpretations/phase1_cap25", ["cap25"])):
        (tmp_path / folder).mkdir(parents=True)
        part = all_runs[all_runs["variant"].isin(variants)].assign(algorithm="ddpg")
        part.to_csv(tmp_path / folder / "runs.csv", index=False)
    make_cells(tmp_path)
    page = write_phase1(tmp_path)
    text = page.read_text()
    found = scores(phase1_runs(tmp_path))
    assert text == (
        "# Interpretation study, phase 1: the distance to the paper\n\n"
        "Computed by `python -m lanefree_sumo.experiments.analysis.interpretations` from the `runs.csv` of "
        "`results/paper`, `results/interpretations/phase1_bonus`, `results/interpretations/phase1_cap25` as "
        "`protocol.md` defines it: 7 DDPG cells of Tables 5–6 at 70 veh/km, seeds 0–4, each run's last 50 training "
        "episodes.\n\n" + phase1_markdown(found) + "\n![ours against the paper](ours_vs_paper.png)\n\n"
        "## Every cell under the three readings of the speed deviation\n\nMeans over the cell's 5 runs of each run's "
        "last 50 training episodes (the score reads the collisions and the per-step reading); a run races when its "
        "last-50 mean speed is above 24 m/s (the desired speed is 20). Where a variant does not change a cell, its "
        "runs are those of the variant it stands for (`protocol.md`).\n\n"
        + readings_markdown(readings_by_variant(tmp_path)) + "\n"
        "## The paper's claims of Tables 5–6 under each variant\n\nEach cell: the verdict of the claim alone / as "
        "one family of this variant's claims (Holm; `lanefree_sumo/experiments/analysis/claims.py`), 5 runs a "
        "side.\n\n" + claims_markdown(claims_by_variant(tmp_path)))
    assert phase1_page(tmp_path, found) == text == phase1_page(tmp_path)
    assert "Picked: **once_per_vehicle**" in text and "## The paper's claims of Tables 5–6 under each variant" in text
    assert "## Every cell under the three readings of the speed deviation" in text and "| racing runs |" in text
    assert (tmp_path / "interpretations" / "ours_vs_paper.png").stat().st_size > 10_000

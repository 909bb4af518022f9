"""The claims check: per-run statistics, the bootstrap difference and the verdicts (pure logic)."""

from __future__ import annotations

import itertools
import math
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from lanefree_sumo.experiments.analysis.claims import (
    AGAINST,
    COLUMNS,
    COMPARISONS,
    CONSISTENT,
    EQUIVALENT,
    NO_DATA,
    NO_DIFFERENCE,
    NOT_SHOWN_EQUIVALENT,
    UNDECIDED,
    Comparison,
    check_claims,
    claims_markdown,
    decidable,
    difference_ci,
    family_verdict,
    holm,
    per_run,
    rank_test,
    reading_comparisons,
    readings_markdown,
    verdict,
)
from lanefree_sumo.experiments.analysis.markdown import TABLE_BEGIN
from lanefree_sumo.experiments.analysis.report import RunData
from lanefree_sumo.experiments.analysis.statistics import bootstrap_ci, bootstrap_difference_ci

from conftest import fenced_rows


def run(algo: str, preset: str, density: float, seed: int, collisions: list[float], speed_dev: float = 1.0) -> RunData:
    episodes = pd.DataFrame({"collisions": collisions, "speed_dev_mps": [speed_dev] * len(collisions)},
                            index=pd.Index(range(1, len(collisions) + 1), name="episode"))
    return RunData(Path(f"{preset}_{seed}"), algo, preset, density, seed, episodes)


def test_difference_ci_and_verdicts():
    diff, low, high = difference_ci([3.0, 3.2, 2.9], [1.0, 1.1, 0.9])
    assert np.isclose(diff, 2.0333, atol=1e-3) and 0 < low < diff < high
    assert verdict(1, low, high, 0.05, 1.0) == CONSISTENT == "consistent with the paper"
    assert verdict(-1, low, high, 1.0, 0.05) == AGAINST == "against the paper"
    assert verdict(1, -0.5, 0.4, 0.3, 0.8) == UNDECIDED == "undecided"
    assert verdict(0, -0.5, 0.4, 0.6, 0.6) == NO_DIFFERENCE == "consistent with the paper (no difference detected)"
    assert verdict(0, low, high, 0.05, 0.05) == AGAINST and verdict(0, low, high, 0.10, 0.10) == UNDECIDED
    assert np.isnan(difference_ci([1.0, 2.0], [2.0, 3.0, 4.0])[1])  # below MIN_RUNS
    assert verdict(1, float("nan"), float("nan"), float("nan"), float("nan")) == "no data"


def test_a_ci_off_zero_needs_the_rank_test_in_its_direction_too():
    """The bootstrap CI alone decides nothing: the one-sided rank test in the CI's direction must reach
    ALPHA (0.05), exactly 0.05 included, or the verdict is undecided."""
    assert verdict(1, 0.2, 1.0, 0.05, 1.0) == CONSISTENT and verdict(1, 0.2, 1.0, 0.0501, 1.0) == UNDECIDED
    assert verdict(-1, 0.2, 1.0, 1.0, 0.05) == AGAINST and verdict(-1, 0.2, 1.0, 1.0, 0.10) == UNDECIDED
    assert verdict(-1, -1.0, -0.2, 0.01, 0.99) == CONSISTENT and verdict(1, -1.0, -0.2, 0.99, 0.01) == AGAINST
    # a rank test in the paper's direction does not count for a CI on the other side, nor the reverse
    assert verdict(1, -1.0, -0.2, 0.01, 0.99) == UNDECIDED and verdict(1, 0.2, 1.0, 0.99, 0.01) == UNDECIDED
    # 3 runs a side, every a above every b: the bootstrap excludes 0 and the rank test reaches 1/20
    a, b = [3.0, 3.2, 2.9], [1.0, 1.1, 0.9]
    row = check_claims({COMPARISONS[0].a: [run(*COMPARISONS[0].a, s, [v] * 2) for s, v in enumerate(a)],
                        COMPARISONS[0].b: [run(*COMPARISONS[0].b, s, [v] * 2) for s, v in enumerate(b)]},
                       last=2, comparisons=COMPARISONS[:1]).iloc[0]
    assert (row["pairs_a_above_b"], row["rank_p"], row["rank_p_against"]) == (9.0, pytest.approx(0.05), 1.0)
    assert row["verdict"] == CONSISTENT
    # one pair out of order: the CI still excludes 0, but p = 2/20 leaves it undecided
    row = check_claims({COMPARISONS[0].a: [run(*COMPARISONS[0].a, s, [v] * 2) for s, v in enumerate([3.0, 3.2, 1.05])],
                        COMPARISONS[0].b: [run(*COMPARISONS[0].b, s, [v] * 2) for s, v in enumerate(b)]},
                       last=2, comparisons=COMPARISONS[:1]).iloc[0]
    assert row["pairs_a_above_b"] == 8.0 and row["rank_p"] == pytest.approx(0.10) and row["verdict"] == UNDECIDED
    assert row["ci95_low"] > 0
    # the paper's 10 runs a side, every a above every b: p = 1 / C(20, 10), written with two significant digits
    ten = {COMPARISONS[0].a: [run(*COMPARISONS[0].a, s, [2.0 + 0.01 * s] * 2) for s in range(10)],
           COMPARISONS[0].b: [run(*COMPARISONS[0].b, s, [1.0 + 0.01 * s] * 2) for s in range(10)]}
    table = check_claims(ten, last=2, comparisons=COMPARISONS[:1])
    assert table.iloc[0]["rank_p"] == pytest.approx(1 / 184_756) and table.iloc[0]["verdict"] == CONSISTENT
    assert f"| 100/100, p = 5.4e-06 (other way 1.00) | {CONSISTENT} |" in claims_markdown(table)


def test_rank_test_counts_pairs_and_gives_the_exact_permutation_p():
    high, low = [3.0, 3.2, 2.9], [1.0, 1.1, 0.9]
    above, p = rank_test(high, low, 1)
    assert above == 9.0 and np.isclose(p, 1 / 20)  # every a above every b: 1 of the 20 splits of 6 runs
    assert np.isclose(rank_test(high, low, 0)[1], 2 / 20)  # two-sided: either extreme split
    assert np.isclose(rank_test(high, low, -1)[1], 1.0)
    above, p = rank_test([1.0, 2.0, 3.0], [1.5, 2.5, 3.5], 1)  # pairs above: 2 > 1.5, 3 > 1.5, 3 > 2.5
    assert above == 3.0 and np.isclose(p, 16 / 20)  # 16 of the 20 splits have U >= 3
    assert np.isclose(rank_test([1.0, 2.0, 3.0], [1.5, 2.5, 3.5], -1)[1], 7 / 20)  # U <= 3: 1 + 1 + 2 + 3 splits
    # ties: [1, 1, 2] vs [0, 1, 1] has U = 3 (2 > 0, 2 > 1 twice) + 2 × ½ × 2 (the 1s) + 1 (1s > 0) = 7
    above, p = rank_test([1.0, 1.0, 2.0], [0.0, 1.0, 1.0], 1)
    assert above == 7.0 and np.isclose(p, 6 / 20)  # counted over the 20 splits of the tied values (not 0.20)
    assert rank_test([0.0] * 3, [0.0] * 3, 1) == (4.5, 1.0)  # all tied: nothing to tell them apart
    assert all(np.isnan(rank_test([1.0, 2.0], [1.0, 2.0, 3.0], 1)))  # below MIN_RUNS


def test_rank_test_p_values_against_brute_force():
    rng = np.random.default_rng(3)
    for _ in range(20):
        values = rng.integers(0, 4, size=7).astype(float)  # many ties
        a, b = list(values[:3]), list(values[3:])

        def u(x: list[float], y: list[float]) -> float:
            return sum(float(i > j) + 0.5 * float(i == j) for i in x for j in y)

        splits = [(list(values[list(c)]), [values[k] for k in range(7) if k not in c])
                  for c in itertools.combinations(range(7), 3)]
        us = np.array([u(x, y) for x, y in splits])
        observed = u(a, b)
        assert rank_test(a, b, 1) == (observed, float((us >= observed).mean()))
        assert rank_test(a, b, -1)[1] == float((us <= observed).mean())
        assert rank_test(a, b, 0)[1] == float((np.abs(us - 6) >= abs(observed - 6)).mean())
    many = list(np.linspace(0, 1, 11)), list(np.linspace(0.5, 1.5, 11))  # C(22, 11) splits: sampled
    above, p = rank_test(*many, -1)
    assert above == 121 - rank_test(many[1], many[0], 1)[0] and 0 < p < 0.05


def test_claims_from_runs_last_episodes_and_windows():
    last = 10
    groups = {
        ("ddpg", "collision", 70.0): [run("ddpg", "collision", 70.0, s, [9.0] * 20 + [3.0 + 0.1 * s] * 10)
                                      for s in range(3)],
        ("ddpg", "fields_collision", 70.0): [run("ddpg", "fields_collision", 70.0, s, [1.0 + 0.1 * s] * 30)
                                             for s in range(3)],
        # PER worse than DDQN only in episodes 50–150, equal at the end
        ("per", "fields_zones_overtake_collision", 70.0): [
            run("per", "fields_zones_overtake_collision", 70.0, s, [1.0] * 49 + [5.0 + s] * 101 + [1.0] * 50)
            for s in range(3)],
        ("ddqn", "fields_zones_overtake_collision", 70.0): [
            run("ddqn", "fields_zones_overtake_collision", 70.0, s, [1.0 + 0.01 * s] * 200) for s in range(3)],
    }
    table = check_claims(groups, last=last)
    assert len(table) == len(COMPARISONS)
    fields = table.iloc[0]
    assert fields["verdict"] == CONSISTENT and np.isclose(fields["difference"], 2.0)  # the last 10 episodes only
    assert fields["pairs_a_above_b"] == 9.0 and np.isclose(fields["rank_p"], 0.05)
    assert np.isclose(fields["paper_difference"], 2.256 - 0.726)
    per = table[table["claim"].str.contains("temporarily")].iloc[0]
    assert per["verdict"] == CONSISTENT and per["difference"] > 4 and np.isnan(per["paper_difference"])
    assert (table[table["claim"].str.contains("density")]["verdict"] == "no data").all()
    # a run that ends before the window's last episode gives no value for it
    short = {**groups, ("ddqn", "fields_zones_overtake_collision", 70.0): [
        run("ddqn", "fields_zones_overtake_collision", 70.0, s, [1.0] * 120) for s in range(3)]}
    per_short = check_claims(short, last=last)
    row = per_short[per_short["claim"].str.contains("temporarily")].iloc[0]
    assert row["n_b"] == 0 and row["verdict"] == "no data"
    text = claims_markdown(table)
    assert text.count("\n| ") == len(COMPARISONS) + 1 and CONSISTENT in text
    assert "| +2.000 [" in text and f"| 9/9, p = 0.05 (other way 1.00) | {CONSISTENT} |" in text
    assert len(fenced_rows(text)) == len(COMPARISONS) + 2  # header, rule, one row per claim


def test_a_grid_decides_only_the_claims_that_compare_two_of_its_settings():
    table5 = [("ddpg", preset, 70) for preset in ("collision", "fields_collision", "overtake_collision",
                                                 "fields_overtake_collision")]
    claims = [c.claim for c in decidable(table5)]
    assert len(claims) == 4 and all("(Table 5)" in c for c in claims)
    assert decidable([("ddpg", "fields_zones_overtake_collision", 70.0)]) == ()  # one setting: nothing to compare
    assert len(decidable([("ddpg", "fields_zones_overtake_collision", 70), ("ddpg", "fields_overtake_collision", 70),
                          ("dqn", "fields_zones_overtake_collision", 70)])) == 3  # zones at 70, DQN vs DDPG twice
    table = check_claims({}, comparisons=decidable(table5))
    assert list(table["claim"]) == claims and (table["verdict"] == "no data").all()


# -- exact boundaries: a CI bound of exactly 0, the run counts, the episode window --------------------

def test_a_ci_bound_of_exactly_zero_is_undecided_on_either_side():
    """A bound of exactly 0 does not exclude 0, whatever the rank test says."""
    assert verdict(1, 0.0, 0.5, 0.0, 1.0) == UNDECIDED and verdict(-1, 0.0, 0.5, 1.0, 0.0) == UNDECIDED
    assert verdict(-1, -0.5, 0.0, 0.0, 1.0) == UNDECIDED and verdict(1, -0.5, 0.0, 1.0, 0.0) == UNDECIDED
    assert verdict(0, 0.0, 0.5, 0.0, 0.0) == verdict(0, -0.5, 0.0, 0.0, 0.0) == NO_DIFFERENCE
    assert verdict(1, 1e-12, 0.5, 0.01, 1.0) == CONSISTENT and verdict(-1, 1e-12, 0.5, 1.0, 0.01) == AGAINST
    assert verdict(-1, -0.5, -1e-12, 0.01, 1.0) == CONSISTENT and verdict(1, -0.5, -1e-12, 1.0, 0.01) == AGAINST
    assert verdict(0, 1e-12, 0.5, 0.01, 0.01) == verdict(0, -0.5, -1e-12, 0.01, 0.01) == AGAINST
    assert verdict(1, 0.0, 0.0, 0.0, 0.0) == UNDECIDED


def test_a_bootstrap_whose_low_bound_is_exactly_zero():
    # a = [1, 1, 1] always averages 1; b = [0, 0, 1] resampled averages 0, 1/3, 2/3 or 1. The difference
    # is 0 only when all three draws of b are the 1: probability (1/3)^3 = 1/27 ≈ 3.7 % > 2.5 %, so the
    # 2.5 % quantile is exactly 0; the difference is 1 with probability (2/3)^3 ≈ 30 % > 2.5 %: high = 1
    diff, low, high = difference_ci([1.0, 1.0, 1.0], [0.0, 0.0, 1.0])
    assert (diff, low, high) == (pytest.approx(2 / 3), 0.0, 1.0)
    assert verdict(1, low, high, 0.0, 1.0) == UNDECIDED
    diff, low, high = difference_ci([0.0, 0.0, 1.0], [1.0, 1.0, 1.0])  # mirrored: high is exactly 0
    assert (diff, low, high) == (pytest.approx(-2 / 3), -1.0, 0.0)
    assert verdict(-1, low, high, 0.0, 1.0) == UNDECIDED
    # the claims table reads the same CI: three runs each, one value per run
    groups = {("ddpg", "collision", 70.0): [run("ddpg", "collision", 70.0, s, [1.0] * 4) for s in range(3)],
              ("ddpg", "fields_collision", 70.0): [run("ddpg", "fields_collision", 70.0, s, [c] * 4)
                                                   for s, c in enumerate([0.0, 0.0, 1.0])]}
    row = check_claims(groups, last=2, comparisons=COMPARISONS[:1]).iloc[0]
    assert (row["n_a"], row["n_b"], row["ci95_low"], row["ci95_high"]) == (3, 3, 0.0, 1.0)
    assert row["verdict"] == UNDECIDED and row["difference"] == pytest.approx(2 / 3)


def test_the_bootstrap_intervals_at_their_boundaries():
    # two values: the resampled mean is 0, 0.5 or 1 with probabilities 1/4, 1/2, 1/4 (10 000 draws:
    # about 2 500 ± 45 zeros and ones): the 95 % interval is [0, 1], the 20 % one (quantiles 0.4, 0.6) [0.5, 0.5]
    assert bootstrap_ci([0.0, 1.0]) == (0.0, 1.0)
    assert bootstrap_ci([0.0, 1.0], level=0.2) == (0.5, 0.5)
    assert all(np.isnan(bootstrap_ci([1.0])))  # fewer than 2 values
    assert bootstrap_ci([3.0, 3.0]) == (3.0, 3.0)
    # one resample is one mean: both bounds are that mean, one of 0, 0.5, 1
    low, high = bootstrap_ci([0.0, 1.0], resamples=1)
    assert low == high and low in (0.0, 0.5, 1.0)
    # the difference: one value per group is enough (its CI is the point), an empty group is not
    assert bootstrap_difference_ci([2.0], [0.5]) == (1.5, 1.5)
    assert all(np.isnan(bootstrap_difference_ci([], [1.0]))) and all(np.isnan(bootstrap_difference_ci([1.0], [])))
    assert bootstrap_difference_ci([0.0, 1.0], [0.0]) == (0.0, 1.0)
    assert bootstrap_difference_ci([0.0], [0.0, 1.0]) == (-1.0, 0.0)  # b subtracted, not a
    assert bootstrap_difference_ci([0.0, 1.0], [0.0], level=0.2) == (0.5, 0.5)
    # the seed is used: two seeds give different intervals of a spread sample, the same seed the same one
    values = list(np.linspace(0.0, 1.0, 7))
    assert bootstrap_ci(values, seed=1) == bootstrap_ci(values, seed=1) != bootstrap_ci(values, seed=2)
    assert bootstrap_difference_ci(values, values, seed=1) != bootstrap_difference_ci(values, values, seed=2)


def test_difference_needs_three_runs_in_each_group():
    diff, low, high = difference_ci([1.0, 2.0, 3.0], [0.0, 0.0, 0.0])
    assert diff == 2.0 and not np.isnan(low) and not np.isnan(high)
    for a, b in (([1.0, 2.0], [1.0, 1.0, 4.0]), ([1.0, 2.0, 3.0], [0.5, 1.5])):
        diff, low, high = difference_ci(a, b)
        assert np.isnan(low) and np.isnan(high) and diff == pytest.approx(np.mean(a) - np.mean(b))
    assert all(np.isnan(difference_ci([], [1.0, 2.0, 3.0])))
    assert all(np.isnan(difference_ci([1.0, 2.0, 3.0], [])))


def test_per_run_statistic_over_the_last_episodes_or_a_closed_window():
    r = run("ddpg", "collision", 70.0, 0, [1.0, 2.0, 4.0, 8.0])  # episodes 1..4
    assert per_run([r], "collisions", 2, None) == [6.0]  # (4 + 8) / 2
    assert per_run([r], "collisions", 1, None) == [8.0]
    assert per_run([r], "collisions", 9, None) == [3.75]  # all four
    assert per_run([r], "collisions", 2, (2, 4)) == [pytest.approx(14 / 3)]  # episodes 2, 3, 4: both ends in
    assert per_run([r], "collisions", 2, (1, 2)) == [1.5]
    assert per_run([r], "collisions", 2, (2, 5)) == []  # the run ends before episode 5
    assert per_run([r, r], "speed_dev_mps", 2, None) == [1.0, 1.0]


def test_the_bootstrap_quantiles_are_the_two_tails_of_the_level():
    # [0, 1, 1]: the resampled mean is 0 with probability (1/3)^3 = 1/27 ≈ 3.7 %, 1/3 with 6/27 ≈ 22 %. A level of
    # 0.91 puts the low bound at the 4.5 % quantile: above the 3.7 % of zeros (by about 8 draws' standard errors
    # in 10 000), so 1/3; a 3 % quantile would fall among the zeros
    assert bootstrap_ci([0.0, 1.0, 1.0], level=0.91) == (pytest.approx(1 / 3), 1.0)
    # mirrored, [0, 0, 1]: the high bound at the 95.5 % quantile is 2/3 (1 has 3.7 %)
    assert bootstrap_ci([0.0, 0.0, 1.0], level=0.91) == (0.0, pytest.approx(2 / 3))
    assert bootstrap_difference_ci([1.0, 1.0, 1.0], [0.0, 0.0, 1.0], level=0.91) == (pytest.approx(1 / 3), 1.0)


def test_the_default_seed_is_zero_and_a_seed_fixes_the_draws():
    # the committed tables were computed with seed 0: the same values give the same CIs, another seed others
    values = [0.0, 0.3, 1.1, 2.9, 7.0, 20.5]
    assert bootstrap_ci(values) == bootstrap_ci(values, seed=0) == bootstrap_ci(values, seed=0)
    assert bootstrap_ci(values, seed=0) != bootstrap_ci(values, seed=1)
    other = [1.0, 4.2, 0.7]
    assert bootstrap_difference_ci(values, other) == bootstrap_difference_ci(values, other, seed=0) \
        == bootstrap_difference_ci(values, other, seed=0)
    assert bootstrap_difference_ci(values, other, seed=0) != bootstrap_difference_ci(values, other, seed=1)
    assert difference_ci(values, other)[1:] == bootstrap_difference_ci(values, other)
    assert difference_ci(values, other, seed=1)[1:] == bootstrap_difference_ci(values, other, seed=1)


def test_an_empty_group_gives_nan_without_a_numpy_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert all(np.isnan(bootstrap_difference_ci([], [1.0, 2.0])))
        assert all(np.isnan(bootstrap_difference_ci([1.0, 2.0], [])))
        assert all(np.isnan(difference_ci([], [1.0, 2.0, 3.0]))) and all(np.isnan(difference_ci([1.0, 2.0], [])))


def test_a_run_short_of_the_window_is_skipped_and_the_next_one_counted():
    short = run("ddpg", "collision", 70.0, 0, [1.0, 2.0])
    full = run("ddpg", "collision", 70.0, 1, [1.0, 2.0, 4.0, 8.0])
    assert per_run([short, full, short, full], "collisions", 2, (2, 4)) == [pytest.approx(14 / 3)] * 2


def test_sampled_rank_p_values_are_reproducible():
    many = list(np.linspace(0, 1, 11)), list(np.linspace(0.5, 1.5, 11))  # C(22, 11) = 705 432 splits: sampled
    assert rank_test(*many, -1) == rank_test(*many, -1)


FZOC_KEY = ("ddpg", "fields_zones_overtake_collision")


def test_claims_rows_name_their_groups_metric_and_the_papers_difference():
    speed = Comparison("speed", (*FZOC_KEY, 120.0), (*FZOC_KEY, 70.0), metric="speed_dev_mps")
    windowed = Comparison("window", (*FZOC_KEY, 120.0), (*FZOC_KEY, 70.0), window=(2, 3))
    unknown = Comparison("no paper value", (*FZOC_KEY, 120.0), ("ddpg", "collision", 55.0))
    table = check_claims({}, comparisons=(speed, windowed, unknown))
    assert list(table.columns) == list(COLUMNS)
    assert list(table["metric"]) == ["speed_dev_mps (last 50)", "collisions (episodes 2–3)", "collisions (last 50)"]
    assert list(table["a"]) == ["ddpg/fields_zones_overtake_collision/120"] * 3
    assert list(table["b"]) == ["ddpg/fields_zones_overtake_collision/70", "ddpg/fields_zones_overtake_collision/70",
                                "ddpg/collision/55"]
    # Table 7 (FZOC, DDPG): speed deviation 1.718 m/s at 120 veh/km, 0.723 at 70; no paper value for a window
    # or for a setting the paper does not have
    assert table["paper_difference"].iloc[0] == pytest.approx(1.718 - 0.723)
    assert np.isnan(table["paper_difference"].iloc[1]) and np.isnan(table["paper_difference"].iloc[2])
    assert list(check_claims({}, comparisons=()).columns) == list(COLUMNS)  # no rows, the same columns


def test_claims_use_the_last_fifty_episodes_by_default():
    # 60 episodes: the first 10 differ, so the last 50 (not 51) give exactly 2.0 and 1.0
    groups = {("ddpg", "collision", 70.0): [run("ddpg", "collision", 70.0, s, [9.0] * 10 + [2.0] * 50)
                                            for s in range(3)],
              ("ddpg", "fields_collision", 70.0): [run("ddpg", "fields_collision", 70.0, s, [0.0] * 10 + [1.0] * 50)
                                                   for s in range(3)]}
    row = check_claims(groups, comparisons=COMPARISONS[:1]).iloc[0]
    assert row["difference"] == 1.0 and row["metric"] == "collisions (last 50)"


def test_claims_markdown_rows_with_and_without_data():
    groups = {("ddpg", "collision", 70.0): [run("ddpg", "collision", 70.0, s, [3.0 + s] * 4) for s in range(3)],
              ("ddpg", "fields_collision", 70.0): [run("ddpg", "fields_collision", 70.0, s, [1.0] * 4)
                                                   for s in range(3)]}
    comparisons = (COMPARISONS[0], Comparison("unknown", ("ddpg", "collision", 55.0), ("ddpg", "collision", 70.0)))
    text = claims_markdown(check_claims(groups, last=2, comparisons=comparisons))
    assert text.startswith("# The paper's claims, checked\n\nDifference of per-run means")
    assert text.endswith("\n") and "not independent facts).\n\n" + TABLE_BEGIN + "\n" in text
    rows = fenced_rows(text)
    assert rows[0] == ("| # | claim | metric | n (a, b) | paper | ours [95 % CI] | rank: a > b, p in the paper's "
                       "direction | verdict | Holm p | paper in CI | shares a group with | verdict, as a family |")
    assert rows[1] == "|---|---|---|---|---|---|---|---|---|---|---|---|"
    # a − b = mean(3, 4, 5) − 1 = 3; every a above every b: 9 of 9 pairs, p = 1/20; paper 2.256 − 0.726; the
    # family holds one claim with data, so Holm leaves p alone; the paper's +1.53 lies below our CI
    low, high = check_claims(groups, last=2, comparisons=comparisons[:1]).iloc[0][["ci95_low", "ci95_high"]]
    assert rows[2] == (f"| 1 | {COMPARISONS[0].claim} | collisions (last 2) | 3, 3 | +1.530 | +3.000 [{low:+.3f}, "
                       f"{high:+.3f}] | 9/9, p = 0.05 (other way 1.00) | {CONSISTENT} | 0.05 | no | 2 | "
                       f"{CONSISTENT} |")
    # no runs at 55 veh/km and no paper value: dashes, no CI, no rank; the two share the collision group
    assert rows[3] == "| 2 | unknown | collisions (last 2) | 0, 3 | – | – | – | no data | – | – | 1 | no data |"
    assert len(rows) == 4


def test_holm_adjusts_step_down_and_leaves_nans_out_of_the_family():
    assert holm([0.01, 0.04, 0.03, math.nan, 0.2]) == [0.04, 0.09, 0.09, pytest.approx(math.nan, nan_ok=True), 0.2]
    assert holm([0.5, 0.6]) == [1.0, 1.0] and holm([]) == []
    out = holm([0.01, math.nan])
    assert out[0] == 0.01 and math.isnan(out[1])


def test_the_family_verdict_needs_the_adjusted_p_and_equivalence():
    assert family_verdict(1, 0.5, 2.0, 0.04, False) == CONSISTENT
    assert family_verdict(1, 0.5, 2.0, 0.06, False) == UNDECIDED  # the same CI, its p adjusted past 0.05
    assert family_verdict(1, -2.0, -0.5, 0.01, False) == AGAINST
    assert family_verdict(0, -0.1, 0.1, 0.9, True) == EQUIVALENT
    assert family_verdict(0, -1.0, 0.1, 0.9, False) == NOT_SHOWN_EQUIVALENT  # contains 0, too wide to be equivalent
    assert family_verdict(0, 0.2, 1.0, 0.01, False) == AGAINST
    assert family_verdict(1, math.nan, math.nan, math.nan, False) == NO_DATA


def test_a_claim_of_no_difference_is_equivalent_only_within_the_margin():
    claim = COMPARISONS[2]  # collision − overtake_collision ≈ 0; margin 0.2 × the paper's 2.293
    assert claim.expect == 0

    def groups(shift: float, spread: float) -> dict:
        return {claim.a: [run(*claim.a, s, [2.0 + spread * (s - 1)] * 4) for s in range(3)],
                claim.b: [run(*claim.b, s, [2.0 + shift + spread * (s - 1)] * 4) for s in range(3)]}

    tight = check_claims(groups(0.05, 0.01), last=2, comparisons=(claim,)).iloc[0]
    assert tight["equivalence_margin"] == pytest.approx(0.2 * 2.293) and tight["equivalent"]
    assert tight["verdict_holm"] == EQUIVALENT
    wide = check_claims(groups(0.05, 0.8), last=2, comparisons=(claim,)).iloc[0]
    assert not wide["equivalent"] and wide["verdict"] == NO_DIFFERENCE
    assert wide["verdict_holm"] == NOT_SHOWN_EQUIVALENT


def test_claims_that_share_a_group_are_marked():
    table = check_claims({}, comparisons=COMPARISONS)
    speed = [i for i, c in enumerate(COMPARISONS) if "smaller speed deviation than DDPG" in c.claim]
    assert len(speed) == 4  # DQN, DDQN, dueling, PER, each against the same DDPG runs
    for i in speed:
        shared = set(table["shares_group_with"].iloc[i].split(", "))
        assert {str(j + 1) for j in speed if j != i} <= shared and str(i + 1) not in shared


def test_the_speed_claims_under_the_other_readings():
    speed = [c for c in COMPARISONS if c.metric == "speed_dev_mps"]
    others = reading_comparisons(COMPARISONS)
    assert len(others) == 2 * len(speed) and {c.metric for c in others} == {"speed_dev_episode_mps",
                                                                            "speed_error_mps"}
    # the signed reading by the magnitude of each run's mean: −2 and +2 are the same size of deviation
    runs = [run("ddpg", "fields_zones_overtake_collision", 70.0, s, [0.0] * 4) for s in range(3)]
    for r, sign in zip(runs, (-1, 1, -1)):
        r.episodes["speed_error_mps"] = sign * 2.0
    assert per_run(runs, "speed_error_mps", 2, None) == [2.0, 2.0, 2.0]
    text = claims_markdown(check_claims({}, comparisons=COMPARISONS[:1]),
                           check_claims({}, comparisons=others[:1]))
    assert "## The speed claims under the other two readings" in text and "<!-- readings -->" in text
    line = next(line for line in text.splitlines() if line.startswith("| Speed deviation grows"))
    assert "per episode, \\|mean (v_x − v_d)\\|" in line and line.count(" | ") == 8  # nine cells, pipes escaped


def test_the_family_columns_at_their_boundaries():
    """Each claim's p in the family is the one of the side its CI lies on; the equivalence test is at 90 %."""
    fields, plain = ("ddpg", "fields_collision", 70.0), ("ddpg", "collision", 70.0)
    claim = COMPARISONS[0]  # collision − fields_collision > 0
    against = {plain: [run(*plain, s, [1.0 + 0.1 * s] * 4) for s in range(3)],
               fields: [run(*fields, s, [3.0 + 0.1 * s] * 4) for s in range(3)]}
    row = check_claims(against, last=2, comparisons=(claim,)).iloc[0]
    assert row["verdict"] == AGAINST and row["test_p"] == row["rank_p_against"] != row["rank_p"]
    assert not row["equivalent"] and not row["paper_in_ci"]
    assert row["holm_p"] == row["test_p"]  # a family of one
    same = COMPARISONS[2]  # collision − overtake_collision ≈ 0: two-sided, both p the same
    assert same.expect == 0
    spread = 0.53  # a 95 % CI beyond the margin of 0.2 × 2.293 whose 90 % CI lies within it
    a = [2.0 - spread, 2.0, 2.0 + spread, 2.0 + 0.5 * spread]
    b = [2.0 - 0.5 * spread, 2.0, 2.0 + 0.8 * spread, 2.1]
    groups = {same.a: [run(*same.a, s, [v] * 4) for s, v in enumerate(a)],
              same.b: [run(*same.b, s, [v] * 4) for s, v in enumerate(b)]}
    row = check_claims(groups, last=2, comparisons=(same,)).iloc[0]
    margin = 0.2 * 2.293
    assert row["ci95_low"] < -margin or row["ci95_high"] > margin
    assert row["equivalent"] and row["verdict_holm"] == EQUIVALENT
    assert row["rank_p_against"] == row["rank_p"] == row["test_p"]
    empty = check_claims({}, comparisons=(same, claim))
    assert empty["test_p"].isna().all() and empty["holm_p"].isna().all() and set(empty["verdict_holm"]) == {NO_DATA}


def test_the_readings_table_rows():
    speed = next(c for c in COMPARISONS if c.metric == "speed_dev_mps" and c.a[2] == 120.0)
    (episode, signed) = [c for c in reading_comparisons(COMPARISONS) if c.a == speed.a and c.b == speed.b]
    groups = {}
    for key, level in ((speed.a, 3.0), (speed.b, 1.0)):
        groups[key] = [run(*key, s, [0.0] * 4) for s in range(3)]
        for s, r in enumerate(groups[key]):
            r.episodes["speed_dev_episode_mps"] = level + 0.1 * s
            r.episodes["speed_error_mps"] = -(level + 0.1 * s)  # slower than desired: its size is the reading
    table = check_claims(groups, last=2, comparisons=(episode, signed))
    assert list(table["difference"].round(9)) == [2.0, 2.0]
    lines = [line for line in readings_markdown(table) if line.startswith("| Speed")]
    low, high = table.iloc[0][["ci95_low", "ci95_high"]]
    assert lines[0] == (f"| {speed.claim} | per episode, \\|mean (v_x − v_d)\\| | 3, 3 | +0.995 | +2.000 "
                        f"[{low:+.3f}, {high:+.3f}] | 9/9, p = 0.05 | {CONSISTENT} | 0.10 | {UNDECIDED} |")
    assert "| signed, \\|mean (v_x − v_d)\\| of the run |" in lines[1]
    assert readings_markdown(table.iloc[0:0]) == []


def test_family_verdicts_and_holm_at_their_edges():
    assert family_verdict(0, 0.2, 1.0, 0.06, False) == UNDECIDED  # a difference the family does not decide
    assert family_verdict(1, 0.0, 1.0, 0.01, False) == UNDECIDED  # a CI bound of exactly 0 decides nothing
    assert family_verdict(-1, -1.0, 0.0, 0.01, False) == UNDECIDED
    assert family_verdict(1, 0.2, 1.0, 0.05, False) == CONSISTENT  # p at exactly the level decides
    assert holm([0.6, 0.7]) == [1.0, 1.0]  # capped at 1

"""The claims check: per-run statistics, the bootstrap difference and the verdicts (pure logic)."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from lanefree_sumo.experiments.claims import (
    COMPARISONS,
    check_claims,
    claims_markdown,
    decidable,
    difference_ci,
    per_run,
    rank_test,
    verdict,
)
from lanefree_sumo.experiments.report import RunData
from lanefree_sumo.experiments.statistics import bootstrap_ci, bootstrap_difference_ci

from conftest import fenced_rows


def run(algo: str, preset: str, density: float, seed: int, collisions: list[float], speed_dev: float = 1.0) -> RunData:
    episodes = pd.DataFrame({"collisions": collisions, "speed_dev_mps": [speed_dev] * len(collisions)},
                            index=pd.Index(range(1, len(collisions) + 1), name="episode"))
    return RunData(Path(f"{preset}_{seed}"), algo, preset, density, seed, episodes)


def test_difference_ci_and_verdicts():
    diff, low, high = difference_ci([3.0, 3.2, 2.9], [1.0, 1.1, 0.9])
    assert np.isclose(diff, 2.0333, atol=1e-3) and 0 < low < diff < high
    assert verdict(1, low, high) == "reproduced" and verdict(-1, low, high) == "opposite"
    assert verdict(1, -0.5, 0.4) == "inconclusive" and verdict(0, -0.5, 0.4) == "no difference detected (low power)"
    assert verdict(0, low, high) == "not reproduced (a difference)"
    assert np.isnan(difference_ci([1.0, 2.0], [2.0, 3.0, 4.0])[1])  # below MIN_RUNS
    assert verdict(1, float("nan"), float("nan")) == "no data"


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
    assert fields["verdict"] == "reproduced" and np.isclose(fields["difference"], 2.0)  # the last 10 episodes only
    assert fields["pairs_a_above_b"] == 9.0 and np.isclose(fields["rank_p"], 0.05)
    assert np.isclose(fields["paper_difference"], 2.256 - 0.726)
    per = table[table["claim"].str.contains("temporarily")].iloc[0]
    assert per["verdict"] == "reproduced" and per["difference"] > 4 and np.isnan(per["paper_difference"])
    assert (table[table["claim"].str.contains("density")]["verdict"] == "no data").all()
    # a run that ends before the window's last episode gives no value for it
    short = {**groups, ("ddqn", "fields_zones_overtake_collision", 70.0): [
        run("ddqn", "fields_zones_overtake_collision", 70.0, s, [1.0] * 120) for s in range(3)]}
    per_short = check_claims(short, last=last)
    row = per_short[per_short["claim"].str.contains("temporarily")].iloc[0]
    assert row["n_b"] == 0 and row["verdict"] == "no data"
    text = claims_markdown(table)
    assert text.count("\n| ") == len(COMPARISONS) + 1 and "reproduced" in text
    assert "| +2.000 [" in text and "| 9/9, p = 0.05 | reproduced |" in text
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

def test_a_ci_bound_of_exactly_zero_is_inconclusive_on_either_side():
    assert verdict(1, 0.0, 0.5) == "inconclusive" and verdict(-1, 0.0, 0.5) == "inconclusive"
    assert verdict(-1, -0.5, 0.0) == "inconclusive" and verdict(1, -0.5, 0.0) == "inconclusive"
    assert verdict(0, 0.0, 0.5) == verdict(0, -0.5, 0.0) == "no difference detected (low power)"
    assert verdict(1, 1e-12, 0.5) == "reproduced" and verdict(-1, 1e-12, 0.5) == "opposite"
    assert verdict(-1, -0.5, -1e-12) == "reproduced" and verdict(1, -0.5, -1e-12) == "opposite"
    assert verdict(0, 1e-12, 0.5) == verdict(0, -0.5, -1e-12) == "not reproduced (a difference)"
    assert verdict(1, 0.0, 0.0) == "inconclusive"


def test_a_bootstrap_whose_low_bound_is_exactly_zero():
    # a = [1, 1, 1] always averages 1; b = [0, 0, 1] resampled averages 0, 1/3, 2/3 or 1. The difference
    # is 0 only when all three draws of b are the 1: probability (1/3)^3 = 1/27 ≈ 3.7 % > 2.5 %, so the
    # 2.5 % quantile is exactly 0; the difference is 1 with probability (2/3)^3 ≈ 30 % > 2.5 %: high = 1
    diff, low, high = difference_ci([1.0, 1.0, 1.0], [0.0, 0.0, 1.0])
    assert (diff, low, high) == (pytest.approx(2 / 3), 0.0, 1.0)
    assert verdict(1, low, high) == "inconclusive"
    diff, low, high = difference_ci([0.0, 0.0, 1.0], [1.0, 1.0, 1.0])  # mirrored: high is exactly 0
    assert (diff, low, high) == (pytest.approx(-2 / 3), -1.0, 0.0)
    assert verdict(-1, low, high) == "inconclusive"
    # the claims table reads the same CI: three runs each, one value per run
    groups = {("ddpg", "collision", 70.0): [run("ddpg", "collision", 70.0, s, [1.0] * 4) for s in range(3)],
              ("ddpg", "fields_collision", 70.0): [run("ddpg", "fields_collision", 70.0, s, [c] * 4)
                                                   for s, c in enumerate([0.0, 0.0, 1.0])]}
    row = check_claims(groups, last=2, comparisons=COMPARISONS[:1]).iloc[0]
    assert (row["n_a"], row["n_b"], row["ci95_low"], row["ci95_high"]) == (3, 3, 0.0, 1.0)
    assert row["verdict"] == "inconclusive" and row["difference"] == pytest.approx(2 / 3)


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
    for a, b in (([1.0, 2.0], [0.0, 0.0, 0.0]), ([1.0, 2.0, 3.0], [0.0, 0.0])):
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

"""The claims check: per-run statistics, the bootstrap difference and the verdicts (pure logic)."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pandas as pd

from lanefree_sumo.experiments.claims import (
    COMPARISONS,
    check_claims,
    claims_markdown,
    decidable,
    difference_ci,
    rank_test,
    verdict,
)
from lanefree_sumo.experiments.report import RunData

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

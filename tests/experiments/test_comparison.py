"""The comparison page (``verdict.md``: a variant against a baseline over every source), from run folders made
here, its figures computed by hand: the windows of the training episodes, the evaluations a run has, the
claims' one rule at its boundaries and the grouping of ``report --compare``."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import pytest

from lanefree_sumo.experiments.analysis import comparison
from lanefree_sumo.experiments.analysis.comparison import (
    TOO_FEW,
    Sides,
    against_defaults,
    readable,
    reading,
    rows,
    sources,
    verdict_markdown,
)
from lanefree_sumo.experiments.storage.rundata import read_run
from tests.experiments.test_report import make_run

EPISODES = 80


def _returns(early: float, middle: float, late: float) -> list[float]:
    """Episodes 1–12 at ``early``, 13–30 at ``middle``, 31–80 (the last 50) at ``late``."""
    return [early] * 12 + [middle] * 18 + [late] * 50


def _sides(root: Path, variants: int = 4, baselines: int = 4, evaluated: int = 2) -> Sides:
    """``variants`` runs whose return is 1 over episodes 1–12, 2 over 13–30 and 3 over the last 50, collisions
    1 and speed deviation 0.5 m/s, against ``baselines`` runs at return 4, 6 and 8 in the same windows, collisions 1
    and 0.2 m/s; the first
    ``evaluated`` variant runs and every baseline run have a zero-shot evaluation at 90 veh/km (return 7 against
    4)."""
    variant = [make_run(root / "set", f"v{k}", seed=k, returns=_returns(1.0, 2.0, 3.0), speed_dev=[0.5] * EPISODES,
                        episodes=EPISODES) for k in range(variants)]
    baseline = [make_run(root / "vector", f"b{k}", seed=k, returns=_returns(4.0, 6.0, 8.0), speed_dev=[0.2] * EPISODES,
                         episodes=EPISODES) for k in range(baselines)]
    for k, run in enumerate(variant[:evaluated]):
        make_run(run, "eval_d90", seed=k, density=90.0, returns=[7.0] * 50, episodes=50)
    for k, run in enumerate(baseline):
        make_run(run, "eval_d90", seed=k, density=90.0, returns=[4.0] * 50, episodes=50)
    return Sides("ddpg / fzoc / d70", variant, baseline)


def test_every_source_and_metric_is_one_row_with_its_figures(tmp_path: Path) -> None:
    """Four runs a side, each constant within a window: the return 1 − 4 over episodes 1–12, (12·1 + 18·2 + 50·3)/80
    − (12·4 + 18·6 + 50·8)/80 over all 80, 3 − 8 over the last 50, each with a point CI and the rank test's 0 of 16
    pairs above, two-sided p = 2/70 = 0.03: decided; equal collisions: 8 of 16 pairs (ties ½), p 1, no
    difference; the larger speed deviation is worse; the evaluation two variant runs have: too few runs."""
    got = rows([_sides(tmp_path)], EPISODES)
    head = ["ddpg / fzoc / d70"]
    early, every, last = ("training, episodes 1–12 (Liu et al.'s 10 000 steps)", "training, all 80 episodes",
                          "training, last 50 episodes")
    decided, same = "0/16, p = 0.03", "8/16, p = 1.00"
    whole = (12 * 1 + 18 * 2 + 50 * 3) / 80 - (12 * 4 + 18 * 6 + 50 * 8) / 80
    assert got == [
        [*head, early, "return", "4, 4", "1.00", "4.00", "-3.00 [-3.00, -3.00]", decided, "set worse"],
        [*head, early, "collisions / episode", "4, 4", "1.00", "1.00", "+0.00 [+0.00, +0.00]", same,
         "no difference detected"],
        [*head, early, "speed deviation (m/s)", "4, 4", "0.50", "0.20", "+0.30 [+0.30, +0.30]", "16/16, p = 0.03",
         "set worse"],
        [*head, every, "return", "4, 4", "2.48", "6.95", f"{whole:+.2f} [{whole:+.2f}, {whole:+.2f}]", decided,
         "set worse"],
        [*head, every, "collisions / episode", "4, 4", "1.00", "1.00", "+0.00 [+0.00, +0.00]", same,
         "no difference detected"],
        [*head, every, "speed deviation (m/s)", "4, 4", "0.50", "0.20", "+0.30 [+0.30, +0.30]", "16/16, p = 0.03",
         "set worse"],
        [*head, last, "return", "4, 4", "3.00", "8.00", "-5.00 [-5.00, -5.00]", decided, "set worse"],
        [*head, last, "collisions / episode", "4, 4", "1.00", "1.00", "+0.00 [+0.00, +0.00]", same,
         "no difference detected"],
        [*head, last, "speed deviation (m/s)", "4, 4", "0.50", "0.20", "+0.30 [+0.30, +0.30]", "16/16, p = 0.03",
         "set worse"],
        [*head, "zero-shot, 90 veh/km", "return", "2, 4", "7.00", "4.00", "+3.00", "–", TOO_FEW],
        [*head, "zero-shot, 90 veh/km", "collisions / episode", "2, 4", "1.00", "1.00", "+0.00", "–", TOO_FEW],
        [*head, "zero-shot, 90 veh/km", "speed deviation (m/s)", "2, 4", "0.50", "0.50", "+0.00", "–", TOO_FEW],
    ]
    assert (12 * 1 + 18 * 2 + 50 * 3) / 80 == 2.475


def test_the_first_episodes_only_and_a_side_without_runs(tmp_path: Path) -> None:
    """``first``: every run over its first 30 episodes, both sides (its last 50 are then 1–30; no evaluation); a
    side with no readable run shows no mean and no difference."""
    sides = _sides(tmp_path)
    got = rows([sides], 30, variant="cap25", first=30)
    assert [row[1] for row in got[::3]] == ["training, episodes 1–12 (Liu et al.'s 10 000 steps)",
                                            "training, all 30 episodes", "training, last 50 episodes"]
    assert got[3][4] == f"{(12 * 1 + 18 * 2) / 30:.2f}" == got[6][4]  # every window within the first 30
    assert got[3][5] == f"{(12 * 4 + 18 * 6) / 30:.2f}" == got[6][5] and got[0][5] == "4.00"
    assert got[0][-1] == "cap25 worse"
    empty = rows([Sides("none", [tmp_path / "missing"], sides.baseline)], EPISODES)
    assert empty[0][3:7] == ["0, 4", "–", "4.00", "–"] and empty[0][-1] == TOO_FEW


def test_the_rule_at_its_boundaries() -> None:
    """A CI touching 0 at either end contains it; p exactly 0.05 decides and just above it does not; higher is
    better for the return, lower for collisions; no CI (too few runs) says so; the variant is named."""
    assert reading(1, 0.0, 2.0, 0.01) == reading(1, -2.0, 0.0, 0.01) == "no difference detected"
    assert reading(1, 0.5, 2.0, 0.05) == "set better" and reading(-1, 0.5, 2.0, 0.05) == "set worse"
    assert reading(1, -2.0, -0.5, 0.05, "cap25") == "cap25 worse" and reading(-1, -2.0, -0.5, 0.05) == "set better"
    assert reading(1, 0.5, 2.0, 0.0501) == comparison.UNDECIDED == "undecided"
    assert reading(1, 0.5, 2.0, math.nan) == "undecided"
    assert reading(1, math.nan, math.nan, math.nan) == TOO_FEW == "too few runs (< 3 a side)"


def test_sources_are_the_training_windows_then_the_evaluations_some_run_has(tmp_path: Path) -> None:
    sides = _sides(tmp_path, evaluated=0)
    assert sources([sides], 625) == [
        ("", "training, episodes 1–12 (Liu et al.'s 10 000 steps)", (1, 12)),
        ("", "training, all 625 episodes", (1, 625)),
        ("", "training, last 50 episodes", None),
        ("eval_d90", "zero-shot, 90 veh/km", None)]
    make_run(sides.variant[0], "eval", returns=[1.0] * 50, episodes=50)
    make_run(sides.variant[1], "eval_onramp", returns=[1.0] * 50, episodes=50)
    assert [s[0] for s in sources([sides], 625)] == ["", "", "", "eval", "eval_d90", "eval_onramp"]
    assert [s[0] for s in sources([sides], 625, evaluations=False)] == ["", "", ""]
    assert [s[0] for s in sources([Sides("x", sides.variant[2:], [])], 625)] == ["", "", ""]


def test_readable_keeps_the_runs_that_have_the_source(tmp_path: Path) -> None:
    sides = _sides(tmp_path, evaluated=1)
    missing = tmp_path / "gone"
    assert [r.path for r in readable([*sides.variant, missing], "eval_d90")] == [sides.variant[0]]
    assert [r.path for r in readable([missing, *sides.variant[:2]], "")] == sides.variant[:2]
    first = readable(sides.variant[:1], "", first=12)[0]
    assert list(first.episodes.index) == list(range(1, 13))
    assert readable(sides.variant[:1], "", first=81) == []  # fewer episodes than asked for: left out


def test_each_variant_is_compared_with_the_defaults_of_its_own_setting(tmp_path: Path) -> None:
    """Per variant one comparison per setting where the defaults have runs too; a variant whose settings have no
    default runs is left out; the defaults are never a variant."""
    def run(name: str, density: float, variant: str):
        return replace(read_run(make_run(tmp_path, name, density=density, episodes=10)), variant=variant)

    groups = {("ddpg", "fzoc", 70.0, ""): [run("d70", 70.0, "")],
              ("ddpg", "fzoc", 90.0, ""): [run("d90", 90.0, "")],
              ("ddpg", "fzoc", 70.0, "cap"): [run("c70a", 70.0, "cap"), run("c70b", 70.0, "cap")],
              ("ddpg", "fzoc", 90.0, "cap"): [run("c90", 90.0, "cap")],
              ("ddpg", "fzoc", 120.0, "cap"): [run("c120", 120.0, "cap")],
              ("ddpg", "fzoc", 120.0, "lonely"): [run("l120", 120.0, "lonely")]}
    got = against_defaults(groups)
    assert list(got) == ["cap"]
    assert got["cap"] == [Sides("ddpg / fzoc / d70", [tmp_path / "c70a", tmp_path / "c70b"], [tmp_path / "d70"]),
                          Sides("ddpg / fzoc / d90", [tmp_path / "c90"], [tmp_path / "d90"])]


def test_the_page_says_how_to_read_it_then_holds_the_table(tmp_path: Path) -> None:
    sides = _sides(tmp_path, evaluated=0)
    page = verdict_markdown([sides], EPISODES, "Set against vector", "Every run: DDPG", "a test",
                            variant="set", baseline="vector", label="setting").split("\n")
    assert page[:2] == ["# Set against vector", ""]
    intro = page[2]
    assert intro.startswith("Every run: DDPG; per-run means over the last 50 episodes of each source (training also "
                            "over its first 12 episodes, about the 10 000 steps over which Liu et al. compare "
                            "training rewards, and over all 80), then set − vector with a 95 % percentile-bootstrap "
                            "CI over runs and the two-sided rank test (pairs of runs with set above vector, ties ½; "
                            "exact permutation p). Verdict, the rule of the paper's claims: *set worse* or *set "
                            "better* when the CI excludes 0 and the rank test has p ≤ 0.05 (worse: lower return, "
                            "more collisions, larger speed deviation), *undecided* when the CI excludes 0 but the "
                            "rank test does not reach it, *no difference detected* when the CI contains 0 (few runs a "
                            "side: low power, not equivalence), *too few runs* below 3 runs on a side.")
    assert intro.endswith("(every set run on one side of every vector run), so no difference is decided there: "
                          "more runs a side decide. Written by a test from the run folders.")
    header = "| setting | source | metric | n (set, vector) | set | vector | set − vector [95 % CI] | " \
             "rank: set > vector, p | verdict |"
    assert page[3:8] == ["", "<!-- table -->", "", header, "|---|---|---|---|---|---|---|---|---|"]
    assert page[-3:] == ["", "<!-- /table -->", ""]
    body = [line for line in page if line.startswith("| ddpg")]
    assert body == ["| " + " | ".join(row) + " |" for row in rows([sides], EPISODES)]
    cut = verdict_markdown([sides], 30, "T", "S", "w", first=30)
    assert "S; every run read over its first 30 training episodes only (longer runs cut there; no evaluation, " \
           "those are of the final models); per-run means" in cut and cut.endswith("\n")
    assert [line for line in cut.split("\n") if line.startswith("| ddpg")] == [
        "| " + " | ".join(row) + " |" for row in rows([sides], 30, first=30)]
    assert "| algorithm | source | metric | n (set, vector) | set | vector | set − vector [95 % CI] | rank: set > " \
           "vector, p | verdict |" in cut  # the defaults: the set encoder against the vector observation


@pytest.mark.parametrize("values, text", [([], "–"), ([1.0, 2.0], "1.50"), ([1.004], "1.00")])
def test_a_sides_mean_is_two_decimals_or_a_dash(values: list[float], text: str) -> None:
    assert comparison._mean_text(values) == text

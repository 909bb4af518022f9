"""The claims the first paper draws from its Tables 5–8, checked one by one on a set of runs.

Each claim compares settings (algorithm, reward preset, density in veh/km) by a per-run statistic —
the mean of a metric over a run's last ``last`` episodes (or over an episode window) — through a
**difference of means between two groups of runs** with its 95 % percentile-bootstrap confidence interval
(each group resampled with replacement, 10 000 times, fixed seed), and a **rank** statistic that does not
lean on the bootstrap's asymptotics (:func:`rank_test`): in how many of the n_a · n_b pairs of runs a's value
is above b's (the Mann–Whitney U; ties count ½), with its exact permutation p-value. Verdicts
(:func:`verdict`), both tests agreeing at :data:`ALPHA`:

* *consistent with the paper*: the CI excludes 0 on the side the paper's numbers are on and the one-sided
  rank test in that direction has p ≤ :data:`ALPHA`; for a claim of *no* difference: the CI contains 0
  ("no difference detected", which with few runs is a lack of power, not evidence of equivalence);
* *against the paper*: the CI excludes 0 on the other side and the one-sided rank test in that direction
  has p ≤ :data:`ALPHA` (for a claim of no difference: either side, the two-sided test);
* *undecided*: anything else;
* *no data*: a group has fewer than :data:`MIN_RUNS` complete runs (a percentile bootstrap of 2 values
  is meaningless), or a run does not cover the episode window.

With 3 runs per group the smallest p possible is 1/20 = 0.05 one-sided (every a above every b) and 0.10
two-sided; with the paper's 10 per group, 1/184 756.

The paper's own difference (Karalakou et al. 2023, specification §10) is printed beside ours.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import pandas as pd

from lanefree_sumo.experiments.analysis import markdown
from lanefree_sumo.experiments.analysis.paper import paper_reference
from lanefree_sumo.experiments.analysis.statistics import bootstrap_difference_ci
from lanefree_sumo.experiments.storage.rundata import RunData

FZOC, FOC = "fields_zones_overtake_collision", "fields_overtake_collision"
Key = tuple[str, str, float]
"""(algorithm, reward preset, density veh/km)."""


@dataclass(frozen=True)
class Comparison:
    """One test of a claim: mean(metric | ``a``) − mean(metric | ``b``), expected ``expect`` (+1: a > b,
    −1: a < b, 0: no difference)."""

    claim: str
    a: Key
    b: Key
    metric: str = "collisions"
    expect: int = 1
    window: tuple[int, int] | None = None
    """Episodes (first, last) averaged per run instead of the last ``last``; the paper value is then
    not in its tables (None)."""


def _k(preset: str, density: float = 70.0, algo: str = "ddpg") -> Key:
    return (algo, preset, float(density))


COMPARISONS: tuple[Comparison, ...] = (
    Comparison("Fields cut collisions (Table 5): collision − fields_collision > 0", _k("collision"),
               _k("fields_collision")),
    Comparison("Fields cut collisions (Table 5): overtake_collision − fields_overtake_collision > 0",
               _k("overtake_collision"), _k(FOC)),
    Comparison("The overtake term alone does not help (Table 5): collision − overtake_collision ≈ 0",
               _k("collision"), _k("overtake_collision"), expect=0),
    Comparison("The overtake term helps combined with fields (Table 5): fields_collision − "
               "fields_overtake_collision > 0", _k("fields_collision"), _k(FOC)),
    Comparison("Zones cut collisions, marginally at 70 veh/km (Table 6): FOC − FZOC > 0", _k(FOC), _k(FZOC)),
    Comparison("Zones cut collisions clearly at 90 veh/km (Table 7): FOC − FZOC > 0", _k(FOC, 90), _k(FZOC, 90)),
    Comparison("Zones cut collisions clearly at 120 veh/km (Table 7): FOC − FZOC > 0", _k(FOC, 120),
               _k(FZOC, 120)),
    Comparison("Collisions grow with density (Table 7, FZOC): 120 − 70 > 0", _k(FZOC, 120), _k(FZOC)),
    Comparison("Speed deviation grows with density (Table 7, FZOC): 120 − 70 > 0", _k(FZOC, 120), _k(FZOC),
               metric="speed_dev_mps"),
    Comparison("Collisions grow with density (Table 7, FOC): 120 − 70 > 0", _k(FOC, 120), _k(FOC)),
    Comparison("Speed deviation grows with density (Table 7, FOC): 120 − 70 > 0", _k(FOC, 120), _k(FOC),
               metric="speed_dev_mps"),
    *(Comparison(f"DDPG has fewer collisions than {algo.upper()} (Table 8): {algo} − ddpg > 0",
                 _k(FZOC, algo=algo), _k(FZOC)) for algo in ("dqn", "ddqn", "dueling", "per")),
    *(Comparison(f"{algo.upper()} has a smaller speed deviation than DDPG (Table 8): ddpg − {algo} > 0",
                 _k(FZOC), _k(FZOC, algo=algo), metric="speed_dev_mps") for algo in ("dqn", "ddqn", "dueling", "per")),
    Comparison("PER is temporarily worse, episodes 50–150 (Table 8's text): per − ddqn > 0", _k(FZOC, algo="per"),
               _k(FZOC, algo="ddqn"), window=(50, 150)),
)
"""Every claim checked, in the paper's order."""

MIN_RUNS = 3
"""Complete runs per group below which no verdict is given."""
ALPHA = 0.05
"""The rank test's p at or below which a verdict leaves *undecided*."""

EQUIVALENCE_SHARE = 0.2
"""The equivalence margin of a claim of no difference: ± this share of the paper's value of group b. The paper
treats a 22 % difference as an effect ("slight improvement in collision occurrences": Fields RF 1.761 against
Collision Avoidance RF 2.256, Table 5) and speaks of no difference where its cells differ by 2 % (Collision 2.256
against Overtake and Avoid Collision 2.293): a fifth of the value lies between the two."""

COLUMNS = ("claim", "metric", "a", "b", "n_a", "n_b", "paper_difference", "difference", "ci95_low", "ci95_high",
           "pairs_a_above_b", "rank_p", "rank_p_against", "verdict", "test_p", "holm_p", "paper_in_ci",
           "equivalence_margin", "equivalent", "shares_group_with", "verdict_holm")
"""The claims table's columns: the verdict of each claim alone (``verdict``), then the family's: ``test_p`` the
rank test's p of the direction the CI lies on (two-sided for a claim of no difference), ``holm_p`` it adjusted by
Holm's step-down over every claim of the table with data, ``paper_in_ci`` whether the paper's own difference lies
in our CI (magnitude, not only sign), ``equivalent`` for a claim of no difference whether the 90 % CI lies within
± ``equivalence_margin`` (two one-sided tests at 0.05, :data:`EQUIVALENCE_SHARE`), ``shares_group_with`` the rows
(1-based) of the same metric that use one of this claim's groups (their verdicts are not independent), and
``verdict_holm`` the verdict read with ``holm_p`` and, for a claim of no difference, equivalence instead of a CI
that contains 0."""


OTHER_READINGS: tuple[tuple[str, str], ...] = (
    ("speed_dev_episode_mps", "per episode, |mean (v_x − v_d)|"),
    ("speed_error_mps", "signed, |mean (v_x − v_d)| of the run"))
"""The speed metric's other two readings (docs/interpretation.md), under which the speed claims are decided too
(:func:`reading_comparisons`); the signed one by the magnitude of the run's mean (a deviation's size)."""
MAGNITUDE_OF_MEAN = frozenset({"speed_error_mps"})
"""Metrics whose per-run statistic is the magnitude of the run's mean (a signed deviation read by its size)."""


def per_run(runs: Sequence[RunData], metric: str, last: int, window: tuple[int, int] | None) -> list[float]:
    """The statistic of each run: mean of ``metric`` over its last ``last`` episodes or over ``window`` (its
    magnitude for :data:`MAGNITUDE_OF_MEAN`)."""
    values = []
    for run in runs:
        column = run.episodes[metric]
        if window and column.index.max() < window[1]:
            continue  # does not cover the window: not a value of this statistic
        part = column.loc[window[0]:window[1]] if window else column.iloc[-last:]
        mean = float(part.mean())
        values.append(abs(mean) if metric in MAGNITUDE_OF_MEAN else mean)
    return values


def reading_comparisons(comparisons: Sequence[Comparison]) -> tuple[Comparison, ...]:
    """The speed claims of ``comparisons`` once more under each of :data:`OTHER_READINGS`."""
    return tuple(replace(c, metric=metric) for metric, _ in OTHER_READINGS for c in comparisons
                 if c.metric == "speed_dev_mps")


def difference_ci(a: Sequence[float], b: Sequence[float], resamples: int = 10_000, seed: int = 0,
                  level: float = 0.95) -> tuple[float, float, float]:
    """(mean(a) − mean(b), CI low, CI high): percentile bootstrap, each group resampled on its own;
    NaNs when a group has fewer than :data:`MIN_RUNS` values."""
    x, y = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    if x.size < MIN_RUNS or y.size < MIN_RUNS:
        return (float(x.mean() - y.mean()) if x.size and y.size else math.nan), math.nan, math.nan
    low, high = bootstrap_difference_ci(list(x), list(y), level, resamples, seed)
    return float(x.mean() - y.mean()), low, high


EXACT_SPLITS = 200_000
"""Up to this many ways of splitting the runs into the two groups (C(n_a + n_b, n_a): 20 for 3 + 3, 184 756
for 10 + 10) the rank test's p-value enumerates them all; beyond, it samples as many at random."""


def rank_test(a: Sequence[float], b: Sequence[float], expect: int) -> tuple[float, float]:
    """(U: pairs of runs with a's value above b's, a tie counting ½; its permutation p-value): the share of all
    the ways to split the pooled runs into groups of a's and b's sizes whose U is at least as extreme — ≥ for
    ``expect`` +1 (a > b), ≤ for −1, as far from n_a · n_b / 2 for 0. Exact (ties included, where the usual
    tables are not) up to :data:`EXACT_SPLITS` splits; NaNs when a group has fewer than :data:`MIN_RUNS`
    values."""
    if len(a) < MIN_RUNS or len(b) < MIN_RUNS:
        return math.nan, math.nan
    pooled = np.asarray([*a, *b], dtype=float)
    n, n_a = pooled.size, len(a)
    # U of a group = the sum of its mid-ranks − n_a (n_a + 1) / 2 (mid-ranks: tied values share their mean rank)
    ranks = (pooled[:, None] > pooled).sum(axis=1) + 0.5 * ((pooled[:, None] == pooled).sum(axis=1) + 1)
    offset = n_a * (n_a + 1) / 2
    observed = float(ranks[:n_a].sum() - offset)
    if math.comb(n, n_a) <= EXACT_SPLITS:
        groups = np.array(list(itertools.combinations(range(n), n_a)))
    else:
        groups = np.argsort(np.random.default_rng(0).random((EXACT_SPLITS, n)), axis=1)[:, :n_a]
    u = ranks[groups].sum(axis=1) - offset  # sums of halves: exact in floating point
    if expect > 0:
        extreme = u >= observed
    elif expect < 0:
        extreme = u <= observed
    else:
        centre = len(a) * len(b) / 2
        extreme = np.abs(u - centre) >= abs(observed - centre)
    return observed, float(extreme.mean())


CONSISTENT, AGAINST, UNDECIDED, NO_DATA = ("consistent with the paper", "against the paper", "undecided",
                                          "no data")
NO_DIFFERENCE = f"{CONSISTENT} (no difference detected)"
EQUIVALENT = f"{CONSISTENT} (equivalent within the margin)"
NOT_SHOWN_EQUIVALENT = f"{UNDECIDED} (no difference detected, equivalence not shown)"


def verdict(expect: int, low: float, high: float, p_paper: float, p_against: float) -> str:
    """Reading of a difference's CI [low, high] and its rank test against the expected sign (module docstring):
    ``p_paper`` the rank test's p in the paper's direction, ``p_against`` in the opposite one (both the
    two-sided p for a claim of no difference, ``expect`` 0)."""
    if math.isnan(low):
        return NO_DATA
    side = 1 if low > 0 else (-1 if high < 0 else 0)
    if expect == 0:
        if side == 0:
            return NO_DIFFERENCE
        return AGAINST if p_against <= ALPHA else UNDECIDED
    if side == expect and p_paper <= ALPHA:
        return CONSISTENT
    if side == -expect and p_against <= ALPHA:
        return AGAINST
    return UNDECIDED


def holm(pvalues: Sequence[float]) -> list[float]:
    """Holm's step-down adjustment of ``pvalues`` (NaNs left out of the family and kept NaN): the i-th smallest of
    the m p-values becomes max over j ≤ i of min(1, (m − j + 1) · p_(j))."""
    finite = [(p, i) for i, p in enumerate(pvalues) if not math.isnan(p)]
    out = [math.nan] * len(pvalues)
    running = 0.0
    for rank, (p, i) in enumerate(sorted(finite)):
        running = max(running, min(1.0, (len(finite) - rank) * p))
        out[i] = running
    return out


def _side(low: float, high: float) -> int:
    return 1 if low > 0 else (-1 if high < 0 else 0)


def _test_p(expect: int, low: float, high: float, p_paper: float, p_against: float) -> float:
    """The rank test's p of the direction the CI lies on (the paper's when it contains 0; two-sided for a claim
    of no difference): the one p of this claim in the family Holm adjusts."""
    if math.isnan(low) or expect == 0:
        return p_paper if not math.isnan(low) else math.nan
    return p_against if _side(low, high) == -expect else p_paper


def family_verdict(expect: int, low: float, high: float, holm_p: float, equivalent: bool) -> str:
    """A claim's verdict read with its Holm-adjusted p (the same rule as :func:`verdict`); a claim of no
    difference is consistent only when shown equivalent (TOST), not for a CI that merely contains 0."""
    if math.isnan(low):
        return NO_DATA
    side = _side(low, high)
    if expect == 0:
        if equivalent:
            return EQUIVALENT
        if side == 0:
            return NOT_SHOWN_EQUIVALENT
        return AGAINST if holm_p <= ALPHA else UNDECIDED
    if side == expect and holm_p <= ALPHA:
        return CONSISTENT
    if side == -expect and holm_p <= ALPHA:
        return AGAINST
    return UNDECIDED


def _shared(comparisons: Sequence[Comparison]) -> list[str]:
    """For each comparison the rows (1-based) of the same metric that use one of its groups."""
    out = []
    for i, c in enumerate(comparisons):
        rows = [str(j + 1) for j, d in enumerate(comparisons) if j != i and d.metric == c.metric
                and {c.a, c.b} & {d.a, d.b}]
        out.append(", ".join(rows))
    return out


def _label(key: Key) -> str:
    algo, preset, density = key
    return f"{algo}/{preset}/{density:g}"


def _paper_difference(c: Comparison) -> float:
    if c.window is not None:
        return math.nan
    ra, rb = paper_reference(*c.a), paper_reference(*c.b)
    if ra is None or rb is None:
        return math.nan
    field = "collisions" if c.metric == "collisions" else "speed_dev_mps"
    return float(getattr(ra, field) - getattr(rb, field))


def decidable(settings: Iterable[Key]) -> tuple[Comparison, ...]:
    """The comparisons whose two settings are both among ``settings`` (a sweep's grid): the claims its
    runs can decide once complete."""
    present = {(algo, preset, float(density)) for algo, preset, density in settings}
    return tuple(c for c in COMPARISONS if c.a in present and c.b in present)


def check_claims(groups: Mapping[Key, Sequence[RunData]], last: int = 50,
                 comparisons: Sequence[Comparison] = COMPARISONS) -> pd.DataFrame:
    """One row per comparison (default every :data:`COMPARISONS` entry; columns :data:`COLUMNS`) from
    runs grouped by setting."""
    rows: list[dict[str, Any]] = []
    shared = _shared(comparisons)
    for c, shares in zip(comparisons, shared):
        a = per_run(groups.get(c.a, ()), c.metric, last, c.window)
        b = per_run(groups.get(c.b, ()), c.metric, last, c.window)
        diff, low, high = difference_ci(a, b)
        above, p = rank_test(a, b, c.expect)
        p_against = p if c.expect == 0 else rank_test(a, b, -c.expect)[1]
        paper = _paper_difference(c)
        margin, equivalent = math.nan, False
        if c.expect == 0:
            ref = paper_reference(*c.b)
            if ref is not None:
                margin = EQUIVALENCE_SHARE * (ref.collisions if c.metric == "collisions" else ref.speed_dev_mps)
                _, low90, high90 = difference_ci(a, b, level=0.90)
                equivalent = not math.isnan(low90) and -margin < low90 and high90 < margin
        rows.append({"claim": c.claim, "metric": c.metric + (f" (episodes {c.window[0]}–{c.window[1]})" if c.window
                                                             else f" (last {last})"),
                     "a": _label(c.a), "b": _label(c.b),
                     "n_a": len(a), "n_b": len(b), "paper_difference": paper, "difference": diff,
                     "ci95_low": low, "ci95_high": high, "pairs_a_above_b": above, "rank_p": p,
                     "rank_p_against": p_against, "verdict": verdict(c.expect, low, high, p, p_against),
                     "test_p": _test_p(c.expect, low, high, p, p_against),
                     "paper_in_ci": (None if math.isnan(low) or math.isnan(paper) else bool(low <= paper <= high)),
                     "equivalence_margin": margin, "equivalent": equivalent, "shares_group_with": shares,
                     "_expect": c.expect})
    adjusted = holm([r["test_p"] for r in rows])
    for r, q in zip(rows, adjusted):
        r["holm_p"] = q
        r["verdict_holm"] = family_verdict(r.pop("_expect"), r["ci95_low"], r["ci95_high"], q, r["equivalent"])
    return pd.DataFrame(rows, columns=list(COLUMNS))


def p_text(p: float) -> str:
    """A p-value for a table: two decimals, or two significant digits below 0.01 (10 runs a side reach 5e-06)."""
    return f"{p:.2f}" if p >= 0.01 else f"{p:.1e}"


def _num(x: float) -> str:
    return "–" if math.isnan(x) else f"{x:+.3f}"


def _row_cells(r: Any, other_way: bool = True) -> list[str]:
    """A claims row's shared cells: n (a, b), the paper's difference, ours with its CI, the rank test (with the
    other direction's p where it differs and ``other_way``)."""
    ci = "" if math.isnan(r.ci95_low) else f" [{r.ci95_low:+.3f}, {r.ci95_high:+.3f}]"
    rank = "–" if math.isnan(r.rank_p) else f"{r.pairs_a_above_b:g}/{r.n_a * r.n_b}, p = {p_text(r.rank_p)}"
    if other_way and not math.isnan(r.rank_p) and r.rank_p_against != r.rank_p:
        rank += f" (other way {p_text(r.rank_p_against)})"
    return [f"{r.n_a}, {r.n_b}", _num(r.paper_difference), f"{_num(r.difference)}{ci}", rank]


def readings_markdown(table: pd.DataFrame) -> list[str]:
    """The speed claims under the other readings (``table``: :func:`check_claims` of :func:`reading_comparisons`):
    a section of the claims page, fenced as ``readings``."""
    if table.empty:
        return []
    labels = dict(OTHER_READINGS)
    rows = []
    for r in table.itertuples():
        metric = str(r.metric).split(" (")[0]
        label = labels.get(metric, metric).replace("|", "\\|")  # a pipe inside a Markdown table cell
        rows.append([str(r.claim), label, *_row_cells(r, other_way=False), str(r.verdict),
                     "–" if math.isnan(r.holm_p) else p_text(r.holm_p), str(r.verdict_holm)])
    return ["", "## The speed claims under the other two readings", "",
            "The same claims with the speed deviation read per episode and signed (docs/interpretation.md); the "
            "paper's difference is its one number, the same as above. Holm's adjustment here runs over these rows "
            "alone.", "", *markdown.table(["claim", "reading", "n (a, b)", "paper", "ours [95 % CI]",
                                           "rank: a > b, p in the paper's direction", "verdict", "Holm p",
                                           "verdict, as a family"], rows, fence="readings")]


def claims_markdown(table: pd.DataFrame, readings: pd.DataFrame | None = None) -> str:
    """The claims table as Markdown, with how to read it; ``readings`` (:func:`check_claims` of
    :func:`reading_comparisons`) adds the speed claims under the other readings."""
    lines = ["# The paper's claims, checked", "",
             "Difference of per-run means (group a − group b) with a 95 % percentile-bootstrap CI over runs "
             "(`lanefree_sumo/experiments/analysis/claims.py`); collisions per episode, speed deviation in m/s. "
             "Rank: in how many pairs of runs a's value is above b's (the Mann–Whitney U, ties ½), and its exact "
             "permutation p-value in the paper's direction (two-sided for a claim of no difference). Verdicts: "
             f"*{CONSISTENT}* when the CI excludes 0 on the paper's side and the rank test's p ≤ {ALPHA}; "
             f"*{AGAINST}* when the CI excludes 0 on the other side and the rank test in that direction has "
             f"p ≤ {ALPHA} (for a claim of no difference: a difference, two-sided); *{UNDECIDED}* otherwise; "
             f"*{NO_DIFFERENCE}* for a claim of no difference whose CI contains 0 (with few runs: low power, not "
             f"equivalence); *{NO_DATA}* below {MIN_RUNS} complete runs per group. With 3 runs per group the rank "
             "test cannot go below p = 0.05 one-sided (every a above every b) or 0.10 two-sided, and the "
             "percentile bootstrap is narrow: read n beside the verdict.", "",
             "**The claims as one family.** Each claim's p in the direction its CI lies on is adjusted by Holm's "
             "step-down over every claim of this table with data (*Holm p*), and the verdict read again with it "
             "(*verdict, as a family*); there a claim of no difference is consistent only when its 90 % CI lies "
             f"within ± {EQUIVALENCE_SHARE:g} × the paper's value of group b (two one-sided tests at 0.05; the "
             "margin's reason: `EQUIVALENCE_SHARE` in claims.py), not for a CI that merely contains 0. *Paper in "
             "CI*: whether the paper's own difference lies inside our CI (the magnitude, beyond the sign). "
             "*Shares a group with*: the rows of the same metric that use one of its groups (their verdicts are "
             "not independent facts).", ""]
    rows = []
    for number, r in enumerate(table.itertuples(), start=1):
        inside = "–" if r.paper_in_ci is None or pd.isna(r.paper_in_ci) else ("yes" if r.paper_in_ci else "no")
        holm_p = "–" if math.isnan(r.holm_p) else p_text(r.holm_p)
        rows.append([str(number), str(r.claim), str(r.metric), *_row_cells(r), str(r.verdict), holm_p, inside,
                     str(r.shares_group_with) or "–", str(r.verdict_holm)])
    lines += markdown.table(["#", "claim", "metric", "n (a, b)", "paper", "ours [95 % CI]",
                             "rank: a > b, p in the paper's direction", "verdict", "Holm p", "paper in CI",
                             "shares a group with", "verdict, as a family"], rows)
    if readings is not None:
        lines += readings_markdown(readings)
    return "\n".join(lines) + "\n"

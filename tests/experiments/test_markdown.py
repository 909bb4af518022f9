"""The fenced Markdown tables of the result files (what docs/results.md includes)."""

from __future__ import annotations

import pytest

from lanefree_sumo.experiments.analysis.markdown import count, table

from conftest import fenced_rows


def test_a_table_is_fenced_and_every_row_has_one_cell_per_header() -> None:
    lines = table(["a", "b"], [["1", "2"], ["3", "4"]])
    assert fenced_rows("\n".join(lines)) == ["| a | b |", "|---|---|", "| 1 | 2 |", "| 3 | 4 |"]
    with pytest.raises(ValueError, match="2 cells"):
        table(["a", "b"], [["1"]])


def test_columns_the_same_in_every_row_are_named_once_above_the_table() -> None:
    lines = table(["algorithm", "runs", "collisions"], [["ddpg", "3/3", "2.5"], ["dqn", "3/3", "19.9"]],
                  drop_constant=True)
    assert fenced_rows("\n".join(lines)) == ["Every row: runs 3/3.", "| algorithm | collisions |", "|---|---|",
                                             "| ddpg | 2.5 |", "| dqn | 19.9 |"]
    one_row = table(["a", "b"], [["1", "2"]], drop_constant=True)  # one row: nothing is "the same in every row"
    assert fenced_rows("\n".join(one_row)) == ["| a | b |", "|---|---|", "| 1 | 2 |"]


def test_a_count_is_plural_unless_it_is_one() -> None:
    assert [count(n, "episode") for n in (0, 1, 2)] == ["0 episodes", "1 episode", "2 episodes"]

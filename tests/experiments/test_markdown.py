"""The fenced Markdown tables of the result files (what docs/results.md includes)."""

from __future__ import annotations

import pytest

from lanefree_sumo.experiments.markdown import table

from conftest import fenced_rows


def test_a_table_is_fenced_and_every_row_has_one_cell_per_header() -> None:
    lines = table(["a", "b"], [["1", "2"], ["3", "4"]])
    assert fenced_rows("\n".join(lines)) == ["| a | b |", "|---|---|", "| 1 | 2 |", "| 3 | 4 |"]
    with pytest.raises(ValueError, match="2 cells"):
        table(["a", "b"], [["1"]])

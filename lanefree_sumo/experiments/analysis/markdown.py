"""Markdown tables of the result files (``summary.md``, ``claims.md``), fenced by two HTML comments.

The comments are invisible where Markdown is rendered, and they let the documentation include a
committed table as it stands (``{include}`` with ``:start-after: "<!-- table -->"`` and
``:end-before: "<!-- /table -->"``, see ``docs/results.md``) instead of copying its numbers by hand.
"""

from __future__ import annotations

from collections.abc import Sequence

__all__ = ["TABLE_BEGIN", "TABLE_END", "count", "table"]

TABLE_BEGIN = "<!-- table -->"
"""The line before a result file's table."""
TABLE_END = "<!-- /table -->"
"""The line after a result file's table."""


def count(n: int, noun: str) -> str:
    """``n`` and ``noun``, plural unless ``n`` is 1: "1 episode", "3 episodes" (for tables and messages)."""
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


def table(headers: Sequence[str], rows: Sequence[Sequence[str]], fence: str = "table",
          drop_constant: bool = False) -> list[str]:
    """The lines of a Markdown table of ``headers`` and ``rows`` (cells already formatted), fenced by
    :data:`TABLE_BEGIN` and :data:`TABLE_END` with a blank line on either side of the table (a second
    table of the same file by ``<!-- fence -->`` and ``<!-- /fence -->``).

    ``drop_constant``: with two rows or more, a column whose cells are the same in every row leaves the
    table and is named once, in a line "Every row: header value; …" above it (inside the fence)."""
    width = len(headers)
    if any(len(row) != width for row in rows):
        raise ValueError(f"every row needs {width} cells, one per header")
    begin, end = (TABLE_BEGIN, TABLE_END) if fence == "table" else (f"<!-- {fence} -->", f"<!-- /{fence} -->")
    note: list[str] = []
    if drop_constant and len(rows) >= 2:
        constant = [k for k in range(width) if len({row[k] for row in rows}) == 1]
        if len(constant) < width:
            note = ["Every row: " + "; ".join(f"{headers[k]} {rows[0][k]}" for k in constant) + ".", ""] \
                if constant else []
            kept = [k for k in range(width) if k not in constant]
            headers, rows = [headers[k] for k in kept], [[row[k] for k in kept] for row in rows]
    return [begin, "", *note,
            "| " + " | ".join(headers) + " |",
            "|" + "|".join("---" for _ in headers) + "|",
            *("| " + " | ".join(row) + " |" for row in rows),
            "", end]

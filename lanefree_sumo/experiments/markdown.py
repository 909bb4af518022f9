"""Markdown tables of the result files (``summary.md``, ``claims.md``), fenced by two HTML comments.

The comments are invisible where Markdown is rendered, and they let the documentation include a
committed table as it stands (``{include}`` with ``:start-after: "<!-- table -->"`` and
``:end-before: "<!-- /table -->"``, see ``docs/results.md``) instead of copying its numbers by hand.
"""

from __future__ import annotations

from collections.abc import Sequence

__all__ = ["TABLE_BEGIN", "TABLE_END", "table"]

TABLE_BEGIN = "<!-- table -->"
"""The line before a result file's table."""
TABLE_END = "<!-- /table -->"
"""The line after a result file's table."""


def table(headers: Sequence[str], rows: Sequence[Sequence[str]], fence: str = "table") -> list[str]:
    """The lines of a Markdown table of ``headers`` and ``rows`` (cells already formatted), fenced by
    :data:`TABLE_BEGIN` and :data:`TABLE_END` with a blank line on either side of the table (a second
    table of the same file by ``<!-- fence -->`` and ``<!-- /fence -->``)."""
    width = len(headers)
    if any(len(row) != width for row in rows):
        raise ValueError(f"every row needs {width} cells, one per header")
    begin, end = (TABLE_BEGIN, TABLE_END) if fence == "table" else (f"<!-- {fence} -->", f"<!-- /{fence} -->")
    return [begin, "",
            "| " + " | ".join(headers) + " |",
            "|" + "|".join("---" for _ in headers) + "|",
            *("| " + " | ".join(row) + " |" for row in rows),
            "", end]

"""Every Python block of docs/libraries.md runs as written (in a fresh interpreter, in a scratch folder)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

PAGE = Path(__file__).resolve().parents[2] / "docs" / "libraries.md"
BLOCKS = re.findall(r"```python\n(.*?)```", PAGE.read_text(), flags=re.S)


def test_the_page_has_its_snippets():
    assert len(BLOCKS) == 8


@pytest.mark.slow
@pytest.mark.parametrize("index", range(len(BLOCKS)))
def test_each_snippet_runs(index, tmp_path):
    out = subprocess.run([sys.executable, "-c", BLOCKS[index]], cwd=tmp_path, capture_output=True, text=True,
                         timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    if "RecordVideo" in BLOCKS[index] or "VecVideoRecorder" in BLOCKS[index]:
        assert list((tmp_path / "videos").glob("*.mp4"))
    if "CleanRL" in BLOCKS[index] or "policy = torch" in BLOCKS[index]:
        assert "iteration 1: return" in out.stdout

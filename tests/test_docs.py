"""The repository stands alone: its texts cite its own specification, sections that exist, nothing outside it."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SPECIFICATION = ROOT / "docs" / "specification.md"


def _texts() -> list[Path]:
    """README, the docs, the code, the scripts, the tests and the committed result pages."""
    files = [ROOT / "README.md", ROOT / "Makefile", *sorted((ROOT / "docs").glob("*.md"))]
    for folder, pattern in (("lanefree_sumo", "*.py"), ("scripts", "*.py"), ("tests", "*.py"), ("results", "*.md")):
        files += sorted((ROOT / folder).rglob(pattern))
    return files


def _sections() -> set[str]:
    """The section numbers of docs/specification.md ("## 7. Reward" gives "7")."""
    return set(re.findall(r"^## (\d+)\. ", SPECIFICATION.read_text(), flags=re.MULTILINE))


def test_the_specification_has_its_sections_and_cites_both_papers():
    assert {str(n) for n in range(14)} <= _sections()
    text = " ".join(SPECIFICATION.read_text().split())
    assert "Deep Reinforcement Learning Reward Function Design for Autonomous Driving in Lane-Free Traffic" in text
    assert "Vehicle Simulation Algorithm for Observations with Variable Dimensions" in text


def test_no_text_points_outside_the_repository():
    shared = "shared"  # spelled apart, so that this file does not itself name the folder
    outside = (f"../{shared}", f"/work/{shared}", "SPEC.md", "SPEC §")
    found = [(str(path.relative_to(ROOT)), name) for path in _texts() if path != Path(__file__).resolve()
             for name in outside if name in path.read_text(errors="replace")]
    assert not found, f"texts citing something outside the repository (cite docs/specification.md): {found}"


def test_every_specification_citation_names_an_existing_section():
    sections = _sections()
    cited = {(path.relative_to(ROOT), number) for path in _texts()
             for number in re.findall(r"specification(?:\.md)? §(\d+)", path.read_text(errors="replace"))}
    assert cited, "nothing cites the specification"
    missing = sorted((str(path), number) for path, number in cited if number not in sections)
    assert not missing, f"citations of sections docs/specification.md does not have: {missing}"


def test_the_markdown_links_to_specification_sections_resolve():
    """``specification.md#7-reward`` style anchors (myst's heading slugs) match a heading."""
    slugs = {re.sub(r"[^\w\- ]", "", heading).strip().lower().replace(" ", "-")
             for heading in re.findall(r"^## (.+)$", SPECIFICATION.read_text(), flags=re.MULTILINE)}
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        for anchor in re.findall(r"specification\.md#([\w\-]+)", path.read_text()):
            assert anchor in slugs, f"{path.relative_to(ROOT)}: no heading for #{anchor}"


def test_the_user_documentation_speaks_of_the_project_not_of_how_it_was_built():
    """History lives in git: no "session N", "this session" or "issue N" in the README or the docs (a run's
    training sessions are the project's own term)."""
    history = re.compile(r"\bsessions? \d|\b(?:this|previous) session\b|\bsession could\b|"
                         r"\bissues? \d|\bthe issue\b", re.IGNORECASE)
    found = [(path.name, line.strip()[:80]) for path in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
             for line in path.read_text().splitlines() if history.search(line)]
    assert not found, f"history in the user documentation: {found}"

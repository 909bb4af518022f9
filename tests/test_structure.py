"""The package's shape: no import circles (none even through an import inside a function), and the scripts use
public names only."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "lanefree_sumo"


def _module(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path, modules: set[str]) -> set[str]:
    """The package's modules that ``path`` imports anywhere in it (``from a.b import c`` counts ``a.b.c``
    when that is a module, else ``a.b``)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found |= {f"{node.module}.{a.name}" if f"{node.module}.{a.name}" in modules else node.module
                      for a in node.names}
    return found & modules


def _graph() -> dict[str, set[str]]:
    paths = {_module(p): p for p in PACKAGE.rglob("*.py")}
    modules = set(paths)
    # a package's __init__ runs before any of its modules: importing ``a.b`` imports ``a`` too, which the
    # graph leaves out (every module would sit in a circle with its package's __init__ otherwise)
    return {name: {m for m in _imports(path, modules) if not name.startswith(m + ".")} - {name}
            for name, path in paths.items()}


def _circle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import circle of ``graph`` (its modules in order), or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state and (found := visit(nxt)):
                return found
        state[node] = 2
        stack.pop()
        return None

    for node in sorted(graph):
        if node not in state and (found := visit(node)):
            return found
    return None


def test_the_algorithms_import_no_circle():
    graph = _graph()
    algorithms = {k: {m for m in v if m.startswith("lanefree_sumo.rl.algorithms.")}
                  for k, v in graph.items() if k.startswith("lanefree_sumo.rl.algorithms.")}
    assert _circle(algorithms) is None, f"import circle: {' -> '.join(_circle(algorithms) or [])}"
    # the registry names stock SB3's classes: no module of the project's is an SB3 algorithm class
    assert not {f"lanefree_sumo.rl.algorithms.{name}" for name in ("ddpg", "dqn", "double_dqn", "dueling",
                                                                    "prioritized")} & set(algorithms)


def test_the_circle_finder_finds_a_circle():
    assert _circle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _circle({"a": {"b"}, "b": set()}) is None


def test_evaluation_does_not_import_training():
    assert "lanefree_sumo.experiments.runners.train" not in _graph()["lanefree_sumo.experiments.runners.evaluate"]


def test_the_scripts_use_public_names_only():
    private = []
    for path in sorted((ROOT / "scripts").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("lanefree_sumo"):
                private += [f"{path.name}: {node.module}.{a.name}" for a in node.names if a.name.startswith("_")]
    assert not private, f"scripts importing private names of the package: {private}"


def test_the_package_imports_no_circle():
    """Rooms import downwards only (experiments -> rl -> sim -> config), and within a room no module imports
    one that imports it back."""
    assert _circle(_graph()) is None, f"import circle: {' -> '.join(_circle(_graph()) or [])}"


def test_the_rooms_import_downwards_only():
    """experiments -> rl -> sim -> config/errors: a room imports nothing of the rooms above it."""
    verbs = ("commands", "cli", "options")  # the command line, above every room (rollout's own options aside)
    above = {"config": ("sim", "rl", "experiments", "tools", *verbs), "sim": ("rl", "experiments", "tools", *verbs),
             "rl": ("experiments", "tools", *verbs), "experiments": ("tools", "commands", "cli")}
    wrong = [(module, imported) for module, imports in _graph().items() for imported in imports
             for room, higher in above.items() if module.startswith(f"lanefree_sumo.{room}.")
             and any(imported.startswith(f"lanefree_sumo.{h}.") or imported == f"lanefree_sumo.{h}" for h in higher)]
    assert not wrong, f"imports against the arrows: {wrong}"


def test_the_algorithm_names_are_the_configs_and_the_registry_is_keyed_by_them():
    """The names are declared once, in the config (``AlgorithmName``); the registry takes them in their order,
    each class under its name, and the config room imports nothing from the RL room to know them."""
    from typing import get_args

    from lanefree_sumo.config import AlgorithmName
    from lanefree_sumo.rl.algorithms import ALGORITHMS

    assert tuple(ALGORITHMS) == get_args(AlgorithmName)
    assert all(spec.name == name for name, spec in ALGORITHMS.items())
    assert not any(m.startswith("lanefree_sumo.rl") for m in _graph()["lanefree_sumo.config.schema"])


def test_the_experiment_rooms_point_down():
    """``experiments/`` by trade: storage imports no other room, analysis no runner and no sweep, a runner no
    sweep (runners → analysis → storage; sweep → all three)."""
    graph = _graph()
    room = "lanefree_sumo.experiments."
    allowed = {"storage": {"storage"}, "analysis": {"analysis", "storage"},
               "runners": {"runners", "analysis", "storage"}}
    seen = set()
    for name, imports in graph.items():
        mine = name.removeprefix(room).split(".")[0]
        if not name.startswith(room) or mine not in allowed:
            continue
        seen.add(mine)
        theirs = {m.removeprefix(room).split(".")[0] for m in imports if m.startswith(room)}
        assert theirs <= allowed[mine], f"{name} imports from {sorted(theirs - allowed[mine])}"
    assert seen == set(allowed)

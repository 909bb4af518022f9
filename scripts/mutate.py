"""Mutation testing of the modules that decide results (``make mutate``; docs/development.md).

Runs mutmut (configured in pyproject.toml, ``[tool.mutmut]``: the modules and their fast tests) on the given
modules, or on every configured one, then prints per module the mutants killed, those that survived, those
listed as equivalent in ``scripts/mutate_equivalent.txt`` (with the reason) and the score: killed over
non-equivalent mutants. Surviving mutants not on that list are printed by name (``mutmut show NAME`` shows the
change). Results are kept in ``mutants/``: a second run of every module tests only the mutants of functions
that changed (or that have no result yet); naming modules tests all their mutants again.

    python scripts/mutate.py [MODULE ...] [--report] [--fail-under PERCENT]

Needs Python ≥ 3.11 (tomllib) and the ``mutate`` extra (mutmut).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import tomllib

ROOT = Path(__file__).resolve().parents[1]
EQUIVALENT = ROOT / "scripts" / "mutate_equivalent.txt"
MUTANTS = ROOT / "mutants"
KILLED = {1, 3, 24, -24, 36, 37, 152, 255}
"""mutmut's exit codes of a mutant its tests caught (a failure, a pytest error, a timeout, the type checker)."""
SURVIVED = 0
NO_TESTS = {5, 33}


def configured_modules() -> list[str]:
    """The dotted names of the modules pyproject.toml's ``[tool.mutmut] only_mutate`` lists."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    return [path.removesuffix(".py").replace("/", ".") for path in config["tool"]["mutmut"]["only_mutate"]]


def equivalent_mutants() -> dict[str, str]:
    """Mutant name → why it cannot change a result, from ``scripts/mutate_equivalent.txt``
    (``NAME  reason`` per line, ``#`` comments)."""
    found = {}
    for line in EQUIVALENT.read_text(encoding="utf-8").splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            name, _, reason = line.partition(" ")
            found[name] = reason.strip()
    return found


@dataclass
class Score:
    """The mutants of one module by outcome."""

    killed: list[str] = field(default_factory=list)
    survived: list[str] = field(default_factory=list)
    equivalent: list[str] = field(default_factory=list)
    untested: list[str] = field(default_factory=list)
    """No fast test reaches the mutated function."""
    not_run: list[str] = field(default_factory=list)

    @property
    def total(self) -> int:
        return len(self.killed) + len(self.survived) + len(self.equivalent) + len(self.untested) + len(self.not_run)

    @property
    def percent(self) -> float | None:
        """Killed over the non-equivalent mutants tested (%); None before any was tested."""
        tested = len(self.killed) + len(self.survived) + len(self.untested)
        return 100.0 * len(self.killed) / tested if tested else None


def score(module: str, equivalent: dict[str, str]) -> Score:
    """The outcome of each mutant of ``module`` recorded in ``mutants/`` (nothing before a first run)."""
    result = Score()
    meta = MUTANTS / (module.replace(".", "/") + ".py.meta")
    if not meta.is_file():
        return result
    for name, code in json.loads(meta.read_text(encoding="utf-8"))["exit_code_by_key"].items():
        if name in equivalent:
            (result.equivalent if code == SURVIVED else result.killed).append(name)
        elif code in KILLED:
            result.killed.append(name)
        elif code == SURVIVED:
            result.survived.append(name)
        elif code in NO_TESTS:
            result.untested.append(name)
        else:
            result.not_run.append(name)
    return result


def report(modules: list[str], fail_under: float) -> int:
    """Print the table and the survivors; 1 when a fully run module scores below ``fail_under`` %."""
    equivalent = equivalent_mutants()
    print(f"{'module':<40} {'mutants':>7} {'killed':>6} {'survived':>8} {'no test':>7} {'equiv.':>6} "
          f"{'not run':>7} {'score':>7}")
    low = False
    survivors: list[str] = []
    for module in modules:
        s = score(module, equivalent)
        pct = "–" if s.percent is None else f"{s.percent:.1f} %"
        print(f"{module:<40} {s.total:>7} {len(s.killed):>6} {len(s.survived):>8} {len(s.untested):>7} "
              f"{len(s.equivalent):>6} {len(s.not_run):>7} {pct:>7}")
        survivors += s.survived + s.untested
        low |= s.percent is not None and not s.not_run and s.percent < fail_under
    if survivors:
        print(f"\n{len(survivors)} mutants neither killed nor listed as equivalent in "
              f"{EQUIVALENT.relative_to(ROOT)} (see each with `mutmut show NAME`):")
        for name in sorted(survivors):
            print(f"  {name}")
    return 1 if low else 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("modules", nargs="*", metavar="MODULE",
                        help="dotted module names (default: every module of [tool.mutmut] only_mutate)")
    parser.add_argument("--report", action="store_true", help="print the scores of the last run; run nothing")
    parser.add_argument("--fail-under", type=float, default=90.0, metavar="PERCENT",
                        help="exit 1 when a fully run module scores below this (default 90)")
    args = parser.parse_args(argv)
    known = configured_modules()
    unknown = [m for m in args.modules if m not in known]
    if unknown:
        parser.error(f"not a module of [tool.mutmut] only_mutate: {', '.join(unknown)}; choose from {', '.join(known)}")
    modules = args.modules or known
    if not args.report:
        # one worker: the tests are short, and the machine is shared
        names = [f"{m}.*" for m in args.modules]  # none: every module, only what has no result yet
        cmd = [sys.executable, "-m", "mutmut", "run", "--max-children", "1", *names]
        if subprocess.run(cmd, cwd=ROOT).returncode != 0:
            print("mutmut failed (its output is above)", file=sys.stderr)
            return 2
    return report(modules, args.fail_under)


if __name__ == "__main__":
    sys.exit(main())

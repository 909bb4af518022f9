"""``lanefree`` command line: ``simulate`` (background traffic), ``train``, ``evaluate``,
``rollout`` (built-in or trained policy, optionally shielded), ``replay`` (sumo-gui), ``export``
(CSV + FCD XML), ``report`` (figures, tables), ``sweep``, ``mixed-autonomy``, ``config`` and ``net``.

This module assembles the verbs and dispatches only: each verb's module declares its options
(:mod:`lanefree_sumo.options`), builds its parser and runs it; the work is in :mod:`lanefree_sumo.experiments`.
Every default shown in ``--help`` comes from :mod:`lanefree_sumo.config`. Every
:class:`~lanefree_sumo.errors.LaneFreeError` ends in ONE line on stderr saying what was wrong and
what to do, with its exit code (2 for bad input, 1 when SUMO fails); 130 on Ctrl-C.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from types import ModuleType
from typing import Any

from lanefree_sumo.commands import config, evaluate, export, net, replay, report, simulate, train
from lanefree_sumo.errors import EXIT_INTERRUPTED, LaneFreeError, OperatingSystemError, UsageError, os_error_message
from lanefree_sumo.experiments.runners import mixed_autonomy, rollout
from lanefree_sumo.experiments.runners.signals import sigterm_as_interrupt
from lanefree_sumo.experiments.sweep import command as sweep_command

EXIT_BAD_INPUT = 2
EXIT_BUG = 3
VERBS: dict[str, ModuleType] = {
    "simulate": simulate, "train": train, "evaluate": evaluate, "rollout": rollout, "replay": replay,
    "export": export, "report": report, "sweep": sweep_command, "mixed-autonomy": mixed_autonomy, "config": config,
    "net": net,
}
"""Each verb's module: its ``add_parser(subparsers)`` and its ``run(args) -> exit code``."""


class _Parser(argparse.ArgumentParser):
    """argparse that reports errors as one line instead of usage + error, and takes no
    abbreviated options (``--dens`` is an error, not ``--density``)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> None:  # type: ignore[override]
        raise UsageError(f"{self.prog}: {message} (see '{self.prog} --help')")


def build_parser() -> argparse.ArgumentParser:
    """The ``lanefree`` parser: one sub-parser per verb, each built by its module."""
    parser = _Parser(prog="lanefree", description="Deep RL in lane-free traffic on Eclipse SUMO.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    parser.set_defaults(verb_parsers={name: module.add_parser(sub) for name, module in VERBS.items()})
    return parser


def _end_progress_bars() -> None:
    """Close every progress bar a failed verb left open: each ends its line now (not later, when it is
    collected), so that the error line that follows comes last on stderr, on a line of its own."""
    tqdm_module = sys.modules.get("tqdm")
    if tqdm_module is not None:
        for bar in list(getattr(tqdm_module.tqdm, "_instances", ())):
            bar.close()


def _error(line: str) -> None:
    """Print ``lanefree: LINE`` as the last line of stderr (after any progress bar), whitespace folded."""
    _end_progress_bars()
    print(f"lanefree: {' '.join(line.split())}", file=sys.stderr, flush=True)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``lanefree`` console script."""
    parser = build_parser()
    try:
        argv = list(sys.argv[1:] if argv is None else argv)
        args, unknown = parser.parse_known_args(argv)
        if unknown:  # after the verb: named by the verb's parser, whose --help lists what it takes
            after_verb = args.command in argv and argv.index(unknown[0]) > argv.index(args.command)
            (args.verb_parsers[args.command] if after_verb else parser).error(
                f"unrecognized arguments: {' '.join(unknown)}")
        args.given = {token.split("=", 1)[0] for token in argv if token.startswith("--")}
        if args.command is None:
            parser.print_help()
            return EXIT_BAD_INPUT
        handler = VERBS[args.command].run
        with sigterm_as_interrupt():  # `kill PID` stops every verb as Ctrl-C does
            return handler(args)
    except LaneFreeError as exc:  # the user's to fix: one line, no traceback
        _error(f"error: {exc}")
        return exc.exit_code
    except KeyboardInterrupt:
        _error("interrupted")
        return EXIT_INTERRUPTED
    except MemoryError:
        _error("error: out of memory; use fewer processes (--envs, --workers) or a smaller buffer")
        return OperatingSystemError.exit_code
    except OSError as exc:  # the operating system's limit, not a bug: one line, named
        _error(f"error: {os_error_message(exc)}")
        return OperatingSystemError.exit_code
    except Exception as exc:  # a bug in lanefree_sumo, not a user mistake
        _error(f"internal error {type(exc).__name__}: {exc} (a bug; please report it with the command line)")
        return EXIT_BUG


if __name__ == "__main__":
    sys.exit(main())

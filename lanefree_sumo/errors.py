"""One error hierarchy for everything a user can get wrong or act on.

The command line turns a :class:`LaneFreeError` into ONE line on stderr and its ``exit_code``;
anything else reaching the top is a bug in lanefree_sumo and is reported as such.
"""

from __future__ import annotations


class LaneFreeError(Exception):
    """A problem the user can act on; the message says what was wrong and what to do."""

    exit_code = 2


class ConfigError(LaneFreeError, ValueError):
    """A configuration value or key that cannot be used."""


class UsageError(LaneFreeError):
    """Bad command-line input."""


class RunError(LaneFreeError):
    """A run folder, checkpoint, model or recording that cannot be used."""


class ReportError(LaneFreeError, ValueError):
    """A report that cannot be made (no usable run, unwritable output)."""


class SumoError(LaneFreeError, RuntimeError):
    """SUMO failed to start or to execute a command."""

    exit_code = 1

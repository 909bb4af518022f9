"""One error hierarchy for everything a user can get wrong or act on.

The command line turns a :class:`LaneFreeError` into ONE line on stderr and its ``exit_code``;
anything else reaching the top is a bug in lanefree_sumo and is reported as such.
"""

from __future__ import annotations

EXIT_INTERRUPTED = 130
"""Exit code of every verb stopped by Ctrl-C or SIGTERM (128 + SIGINT, the shell's convention)."""


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


class OperatingSystemError(LaneFreeError):
    """The operating system refused something (a full disk, a read-only place, a name too long)."""

    exit_code = 1


def os_error_message(exc: OSError) -> str:
    """One line for an operating-system error: what failed, on which path, and what to do."""
    import errno

    what = exc.strerror or str(exc) or type(exc).__name__
    where = " ".join(str(p) for p in (exc.filename, exc.filename2) if p)
    advice = {
        errno.ENOSPC: "free some space or write elsewhere",
        errno.EDQUOT: "free some space or write elsewhere",
        errno.EROFS: "choose a writable location",
        errno.EACCES: "choose a location you may write, or fix its permissions",
        errno.EPERM: "choose a location you may write, or fix its permissions",
        errno.ENAMETOOLONG: "choose a shorter name",
        errno.EMFILE: "raise the open-file limit (ulimit -n) or use fewer processes",
        errno.ENOMEM: "use fewer processes (--envs, --workers) or free memory",
        errno.EAGAIN: "use fewer processes (--envs, --workers)",
    }.get(exc.errno or -1, "")
    return f"{what}{': ' + where if where else ''}" + (f"; {advice}" if advice else "")

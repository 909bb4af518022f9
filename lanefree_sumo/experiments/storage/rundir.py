"""THE module that knows the file names of run folders and output folders.

A training run ``runs/<date-time>_<algo>_<reward>_d<density>_s<seed>/`` (``…_shield/`` when trained
with the safety shield) holds::

    config.yaml          the full resolved LaneFreeConfig (env + algorithm), enough to rebuild both
    command.txt          every command that worked on the run, one per line
    versions.json        python, torch, SB3, gymnasium, numpy (and the SIMD kernels numpy and torch run on),
                         SUMO, lanefree_sumo, git commit
    episodes.csv         one row per finished episode (specification §8 + algorithm, timesteps), flushed each time
    tb/                  TensorBoard logs
    checkpoints/ep_NNNNN/  model.zip, replay_buffer.pkl (off-policy), state.json (written last)
    model.zip            the final model
    last_session.json    wall time, steps/s and how the latest session ended
    sessions.jsonl       one line per training session that ended (finished, interrupted; not one killed
                         outright): its episodes, start, end, the versions and SIMD kernels it ran on (read at
                         its start; versions.json is the first session's)
    eval/                an evaluation (eval_d<density>/ at another density; eval[_d<density>]_shield/ or
                         _noshield/ with the safety shield switched): config.yaml, episodes.csv,
                         recording.json, trajectories/episode_NNNN.csv and episode_NNNN.vehicles.csv

``lanefree simulate --out DIR`` writes ``trajectory.csv``, ``summary.json``, ``config.yaml`` and
``command.txt``.  Every other module asks this one for a path.
"""

from __future__ import annotations

import contextlib
import fcntl
import itertools
import json
import os
import re
import shutil
import sys
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from lanefree_sumo.config import RETIRED, LaneFreeConfig, config_to_dict, drop_retired, merge_config, missing_keys
from lanefree_sumo.errors import ConfigError, RunError

CONFIG = "config.yaml"
BATCH_FILE = "batch.json"
"""A batch folder's list of its run folders (``lanefree train --seeds``,
:mod:`~lanefree_sumo.experiments.runners.batch`); a single run trained as a batch of one is its own batch folder
(``{"runs": ["."]}``)."""
BATCH_CHECKPOINTS = "batch_checkpoints"
"""A batch folder's checkpoints of the whole batch (learners, replay, random streams, environment)."""
COMMAND = "command.txt"
VERSIONS = "versions.json"
EPISODES = "episodes.csv"
MODEL = "model.zip"
LAST_SESSION = "last_session.json"
SESSIONS = "sessions.jsonl"
TENSORBOARD = "tb"
CHECKPOINTS = "checkpoints"
LOCK = ".lock"
"""Held (flock) by the process training the run: one writer at a time."""
REPLAY_BUFFER = "replay_buffer.pkl"
CHECKPOINT_STATE = "state.json"
EVAL = "eval"
TRAJECTORIES = "trajectories"
RECORDING = "recording.json"
SIM_TRAJECTORY = "trajectory.csv"
SIM_SUMMARY = "summary.json"
MIXED_AUTONOMY = "mixed_autonomy"
"""``lanefree mixed-autonomy RUN``'s default output folder inside RUN."""


OUTPUT_MARKER = ".lanefree-output"
"""File in every folder a verb writes (simulate, evaluate), naming the verb: ``--overwrite``
replaces only such folders."""


def check_replaceable(out: Path, overwrite: bool, verb: str) -> None:
    """Refuse an existing ``out`` unless ``overwrite``, and even then unless it is a previous
    output of ``lanefree VERB`` (marker file) or empty: never a run folder, a file, the current
    folder or one of its parents."""
    if not out.exists():
        return
    if not overwrite:
        raise RunError(f"{out} exists; choose another --out or pass --overwrite to replace it")
    resolved, cwd = out.resolve(), Path.cwd().resolve()
    if resolved == cwd or resolved in cwd.parents:
        raise RunError(f"refusing to replace {out}: it is the current folder or one of its parents")
    if not out.is_dir():
        raise RunError(f"refusing to replace {out}: it is a file, not an output folder")
    if any((out / name).exists() for name in (CHECKPOINTS, MODEL, VERSIONS)):
        raise RunError(f"refusing to replace {out}: it is a training run folder")
    marker = out / OUTPUT_MARKER
    made_by = marker.read_text(errors="replace").strip() if marker.is_file() else None
    if made_by != verb and any(out.iterdir()):
        raise RunError(f"refusing to replace {out}: it is not the output of an earlier 'lanefree {verb}' "
                       "(no marker file); remove it yourself or choose another --out")


def check_writable(path: Path, folder: bool = False) -> None:
    """Fail now, not after the work, when ``path`` (a file, or a ``folder``) cannot be written."""
    where = path if folder else path.parent
    try:
        where.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=where):
            pass
    except OSError as exc:
        raise RunError(f"cannot write {path}: {exc.strerror or exc}") from None


RUN_OWNED: tuple[str, ...] = (CONFIG, COMMAND, VERSIONS, EPISODES, MODEL, LAST_SESSION, SESSIONS, LOCK, CHECKPOINTS,
                               TENSORBOARD, BATCH_FILE, BATCH_CHECKPOINTS)
"""Top-level names in a run folder that only training writes."""


def _owner(path: Path, verb: str) -> Path | None:
    """The folder whose file ``path`` is, for ``lanefree VERB``: a run folder (its config, episodes, model,
    checkpoints, TensorBoard logs, or anything in its evaluation folders but their ``export/``) or another
    verb's output folder (marker file; its ``export/`` excepted); None for anything else."""
    resolved = path.resolve()
    for folder in resolved.parents:
        parts = resolved.relative_to(folder).parts
        marker = folder / OUTPUT_MARKER
        if marker.is_file():
            if marker.read_text(errors="replace").strip() != verb and parts[0] != "export":
                return folder
        elif (folder / CONFIG).is_file() and ((folder / EPISODES).exists() or (folder / CHECKPOINTS).exists()):
            if parts[0] in RUN_OWNED or (parts[0].startswith(EVAL) and (len(parts) < 3 or parts[1] != "export")):
                return folder
    return None


def check_new_file(path: Path, overwrite: bool, verb: str, marker_folder: bool = False) -> None:
    """Refuse, before any work, an output file ``path`` of ``lanefree VERB`` that a run folder owns (whatever
    ``overwrite`` says), a path that exists and is not a file, or an existing file without ``overwrite`` —
    with ``marker_folder``, also one whose folder was not made by the same verb (its marker file)."""
    owner = _owner(path, verb)
    if owner is not None:
        raise RunError(f"refusing to write {path}: it belongs to the run folder or output {owner}; choose another path")
    if path.exists() or path.is_symlink():
        if not path.is_file():
            raise RunError(f"refusing to write {path}: it exists and is not a file")
        if not overwrite:
            raise RunError(f"{path} exists; choose another path" + (" or pass --overwrite" if verb == "export" else ""))
        marker = path.parent / OUTPUT_MARKER
        if marker_folder and (not marker.is_file() or marker.read_text(errors="replace").strip() != verb):
            raise RunError(f"refusing to replace {path}: its folder is not the output of an earlier "
                           f"'lanefree {verb}' (no marker file); remove it yourself or choose another --out")
    check_writable(path)


def _leftover(path: Path) -> re.Pattern[str]:
    """Names of the temporaries a writer of ``path`` makes beside it: ``.<name>.new-XXXXXXXX`` (the output being
    written) and ``.<name>.old-XXXXXXXX`` (an earlier output on its way out), as :mod:`tempfile` names them."""
    return re.compile(rf"\.{re.escape(path.name)}\.(new|old)-[a-z0-9_]{{8}}")


def _clean_leftovers(path: Path) -> None:
    """Remove what writers of ``path`` that died left beside it (called under the claim, so no live writer
    owns one): their ``.new-`` temporaries, and their ``.old-`` folders — put back first when the writer died
    between moving the earlier output aside and moving the new one in, so that nothing is lost."""
    pattern = _leftover(path)
    with contextlib.suppress(OSError):
        for entry in path.parent.iterdir():
            match = pattern.fullmatch(entry.name)
            if match is None:
                continue
            aside = entry / path.name
            if match.group(1) == "old" and aside.exists() and not path.exists():
                with contextlib.suppress(OSError):
                    aside.rename(path)
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry, ignore_errors=True)
            else:
                with contextlib.suppress(OSError):
                    entry.unlink()


def claim_path(path: Path) -> Path:
    """The lock file of output ``path`` (a folder or a file a verb writes): ``.<name>.lock`` beside it."""
    return path.parent / f".{path.name}.lock"


def _lock(lock: Path, path: Path, verb: str) -> int:
    """Open and lock ``lock`` (the lock file of output ``path``), write this process's id and ``verb`` into it;
    its descriptor. RunError naming the holder when another process holds it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            same = os.stat(lock).st_ino == os.fstat(fd).st_ino
        except BlockingIOError:
            holder = os.read(fd, 100).decode(errors="replace").split() or ["?"]
            os.close(fd)
            raise RunError(f"{path} is being written by process {holder[0]} (another 'lanefree "
                           f"{holder[1] if len(holder) > 1 else verb}'); wait for it or choose another "
                           "output") from None
        except FileNotFoundError:
            same = False
        except BaseException:
            os.close(fd)
            raise
        if same:  # the lock file in place, not one its last holder removed while we opened it
            try:
                os.ftruncate(fd, 0)
                os.write(fd, f"{os.getpid()} {verb}\n".encode())
            except BaseException:
                os.close(fd)
                raise
            return fd
        os.close(fd)


@contextlib.contextmanager
def claim(path: Path, verb: str) -> Iterator[None]:
    """Hold the claim on output ``path`` for ``lanefree VERB``: an exclusive ``flock`` on :func:`claim_path`,
    released by the kernel when the process ends however it ends, the lock file removed on the way out. One
    writer per output at a time: RunError naming the holder's process id while another holds it. Under the
    claim, the temporaries that dead writers of ``path`` left are removed (:func:`_clean_leftovers`)."""
    lock = claim_path(path)
    try:
        fd = _lock(lock, path, verb)
    except OSError as exc:
        raise RunError(f"cannot write {path}: {exc.strerror or exc}") from None
    try:
        _clean_leftovers(path)
        yield
    finally:
        with contextlib.suppress(OSError):
            lock.unlink()
        os.close(fd)


@contextlib.contextmanager
def new_file(path: Path, verb: str) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` to write one output file of ``lanefree VERB`` into, holding the
    claim on ``path`` (:func:`claim`); it replaces ``path`` when the block ends without an exception and is
    removed otherwise, so ``path`` is never half-written. Check it first with :func:`check_new_file`."""
    with claim(path, verb):
        fd, name = tempfile.mkstemp(prefix=f".{path.name}.new-", dir=path.parent)
        os.close(fd)
        tmp = Path(name)
        umask = os.umask(0)
        os.umask(umask)
        tmp.chmod(0o666 & ~umask)  # mkstemp makes it private; an output file is an ordinary one
        try:
            yield tmp
            os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)


def _identity(path: Path) -> tuple[int, int] | None:
    """What ``path`` is now (device and inode), None when nothing is there."""
    try:
        st = path.lstat()
    except FileNotFoundError:
        return None
    return st.st_dev, st.st_ino


def write_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` whole or not at all: into a file beside it, then renamed over it (a reader
    never sees half a file; an interrupted write leaves ``path`` as it was)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.fchmod(fd, 0o666 & ~umask)  # mkstemp makes it private; these are ordinary files
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


@contextlib.contextmanager
def fresh_output(out: Path, overwrite: bool, verb: str) -> Iterator[Path]:
    """Write a verb's output safely. ``out`` is claimed at once (:func:`claim`: a second writer is refused
    while this one runs) and checked under the claim (:func:`check_replaceable`); the block gets a new folder
    beside ``out``. When the block ends without an exception the new folder replaces ``out`` — only if ``out``
    is still what it was when claimed (nothing, or the earlier output ``overwrite`` allowed to replace); else
    ``out`` is left alone and the new output kept beside it under a name the RunError gives. When the block
    fails the new folder is deleted and ``out`` is untouched."""
    check_replaceable(out, overwrite, verb)  # before the claim too: a refusal writes not even a lock file
    with claim(out, verb):
        check_replaceable(out, overwrite, verb)
        before = _identity(out)
        try:
            tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.new-", dir=out.parent))
            umask = os.umask(0)
            os.umask(umask)
            tmp.chmod(0o777 & ~umask)  # mkdtemp makes it private; an output folder is an ordinary one
            (tmp / OUTPUT_MARKER).write_text(verb + "\n")
        except OSError as exc:
            raise RunError(f"cannot write {out}: {exc.strerror or exc}") from None
        try:
            yield tmp
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        _swap_in(tmp, out, before, verb)


def _swap_in(tmp: Path, out: Path, before: tuple[int, int] | None, verb: str) -> None:
    """Move the complete output ``tmp`` to ``out``, which was ``before`` when claimed (:func:`fresh_output`)."""
    if _identity(out) != before:
        for k in itertools.count(1):
            kept = out.with_name(f"{out.name}.{verb}-{k}")
            if not kept.exists():
                break
        tmp.rename(kept)
        raise RunError(f"{out} was made or replaced by another program while 'lanefree {verb}' wrote; it is left as "
                       f"it is, and this output is in {kept}")
    if before is not None:
        old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
        out.rename(old / out.name)
        tmp.rename(out)
        shutil.rmtree(old, ignore_errors=True)
    else:
        tmp.rename(out)


def write_config(folder: Path, cfg: LaneFreeConfig) -> None:
    """``folder/config.yaml``: the full resolved configuration."""
    (folder / CONFIG).write_text(yaml.safe_dump(config_to_dict(cfg), sort_keys=False))


def record_session(folder: Path, session: dict[str, Any]) -> None:
    """The end of a training session: ``last_session.json`` becomes ``session`` and ``sessions.jsonl`` gains it
    as one line (the run's history: which code, versions and kernels trained which episodes)."""
    (folder / LAST_SESSION).write_text(json.dumps(session, indent=2) + "\n")
    path = folder / SESSIONS
    cut_short = path.is_file() and path.stat().st_size > 0 and not path.read_bytes().endswith(b"\n")
    with open(path, "a") as fh:  # after a line cut short (a process killed mid-write), on a line of its own
        fh.write(("\n" if cut_short else "") + json.dumps(session) + "\n")


def read_sessions(folder: Path) -> list[dict[str, Any]]:
    """The training sessions recorded in the run's ``sessions.jsonl``, oldest first (its lines that parse as
    JSON objects; a half-written or damaged line is left out); empty for a run without that file (trained
    before it existed)."""
    try:
        lines = (folder / SESSIONS).read_text().splitlines()
    except (OSError, UnicodeDecodeError):
        return []
    sessions = []
    for line in lines:
        try:
            entry = json.loads(line)
        except ValueError:
            continue
        if isinstance(entry, dict):
            sessions.append(entry)
    return sessions


def append_command(folder: Path, command: str) -> None:
    """Add one command line to ``folder/command.txt``."""
    with open(folder / COMMAND, "a") as fh:
        fh.write(command + "\n")


def read_config(folder: Path, note_retired: bool = False) -> LaneFreeConfig:
    """The configuration saved in ``folder/config.yaml`` (a run or an evaluation), validated whole:
    unreadable text, a missing or unknown key, a wrong type or value is a RunError naming it. A retired key
    (:data:`~lanefree_sumo.config.RETIRED`) is dropped; with ``note_retired`` (a run about to train on) one line
    on stderr says so."""
    path = folder / CONFIG
    if not path.is_file() and (folder / BATCH_FILE).is_file():
        runs = sorted(p.name for p in folder.iterdir() if (p / CONFIG).is_file())
        raise RunError(f"{folder} is a batch of 'lanefree train --seeds' ({len(runs)} runs); pass one of its run "
                       f"folders, e.g. {folder / (runs[0] if runs else '<run>')} ('lanefree report {folder}' reports "
                       "them all)")
    if not path.is_file():
        raise RunError(f"{folder} is not a run folder (no {CONFIG}); pass the folder that 'lanefree train' made")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
        if not isinstance(data, dict):
            raise ConfigError("it is not a mapping of config keys")
        missing = missing_keys(LaneFreeConfig(), data)
        if missing:
            more = f" and {len(missing) - 1} more" if len(missing) > 1 else ""
            raise ConfigError(f"key '{missing[0]}'{more} missing (file cut short?)")
        data, dropped = drop_retired(data)
        if note_retired:
            _note_retired(path, dropped)
        return merge_config(LaneFreeConfig(), data)
    except (OSError, UnicodeDecodeError, yaml.YAMLError, ConfigError, TypeError) as exc:
        reason = " ".join(str(exc).split())[:300]
        raise RunError(f"{path} is unusable ({reason}); restore it or start a new run") from None


_NOTED_RETIRED: set[str] = set()
"""The retired keys :func:`_note_retired` has named in this process (each is named once)."""


def _note_retired(path: Path, dropped: list[str]) -> None:
    """One line on stderr for each retired key (:data:`~lanefree_sumo.config.RETIRED`) a saved config names,
    the first time this process meets it: the key is ignored, and why."""
    for key in dropped:
        if key not in _NOTED_RETIRED:
            _NOTED_RETIRED.add(key)
            print(f"lanefree: note: {path} names '{key}', which is ignored now ({RETIRED[key]})", file=sys.stderr)


@dataclass(frozen=True)
class Checkpoint:
    """A complete checkpoint: its folder and the counters it was saved at."""

    path: Path
    episodes: int
    timesteps: int

    @property
    def model(self) -> Path:
        return self.path / MODEL

    @property
    def replay_buffer(self) -> Path:
        return self.path / REPLAY_BUFFER


@dataclass(frozen=True)
class RunDir:
    """A training run folder and the paths inside it."""

    path: Path

    @property
    def config(self) -> Path:
        return self.path / CONFIG

    @property
    def episodes(self) -> Path:
        return self.path / EPISODES

    @property
    def model(self) -> Path:
        return self.path / MODEL

    @property
    def versions(self) -> Path:
        return self.path / VERSIONS

    @property
    def last_session(self) -> Path:
        return self.path / LAST_SESSION

    @property
    def tensorboard(self) -> Path:
        return self.path / TENSORBOARD

    @property
    def checkpoints(self) -> Path:
        return self.path / CHECKPOINTS

    @property
    def lock_file(self) -> Path:
        return self.path / LOCK

    @contextlib.contextmanager
    def writer_lock(self) -> Iterator[None]:
        """Hold the run's writer lock (``flock`` on ``.lock``, released by the kernel when the process
        ends, however it ends); RunError naming the holder's process id when another process holds it."""
        fh = open(self.lock_file, "a+")
        try:
            try:
                fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                fh.seek(0)
                holder = fh.read().strip() or "?"
                raise RunError(f"{self.path} is being written by process {holder} (a training of this run); "
                               "wait for it to finish or stop it first") from None
            fh.seek(0)
            fh.truncate()
            fh.write(f"{os.getpid()}\n")
            fh.flush()
            yield
        finally:
            fh.close()

    def checkpoint(self, episodes: int) -> Path:
        """Folder of the checkpoint taken after ``episodes`` episodes."""
        return self.checkpoints / f"ep_{episodes:05d}"

    def load_config(self, note_retired: bool = False) -> LaneFreeConfig:
        """The run's config (:func:`read_config`)."""
        return read_config(self.path, note_retired)

    def eval_dir(self, density: float | None = None, shield: bool | None = None, scenario: str | None = None) -> Path:
        """``eval/`` at the training density (``density`` None), else ``eval_d<density>/``; on another road
        than trained (``scenario``) ``eval_<scenario>`` first (``eval_onramp_d90``); with ``shield`` True/False
        (the shield switched on/off against the run's config) ``_shield`` or ``_noshield`` appended."""
        name = EVAL if scenario is None else f"{EVAL}_{scenario}"
        name = name if density is None else f"{name}_d{density:g}"
        return self.path / (name if shield is None else f"{name}_{'shield' if shield else 'noshield'}")

    def newest_checkpoint(self) -> Checkpoint:
        """The newest complete checkpoint; RunError when there is none usable."""
        folders = sorted(self.checkpoints.glob("ep_*")) if self.checkpoints.is_dir() else []
        for folder in reversed(folders):
            try:
                state = json.loads((folder / CHECKPOINT_STATE).read_text())
                if (folder / MODEL).is_file():
                    return Checkpoint(folder, int(state["episodes"]), int(state["timesteps"]))
            except (OSError, ValueError, KeyError, TypeError):
                continue
        raise RunError(f"{self.path} has no usable checkpoint under {CHECKPOINTS}/ (it never reached its first); "
                       f"start it afresh with 'lanefree train … --out {self.path}' (no --resume)")

    def has_checkpoint(self) -> bool:
        """Whether the run holds a complete checkpoint (:meth:`newest_checkpoint` finds one)."""
        try:
            self.newest_checkpoint()
        except RunError:
            return False
        return True

    def never_checkpointed(self) -> bool:
        """A new run that ended (killed outright, or failed) before its first checkpoint: it holds only what
        training writes (:data:`RUN_OWNED`), no final model and no complete checkpoint, so nothing in it can be
        resumed. Its lock file, the first thing a training writes, tells it from a folder of the user's. A new
        start into its folder begins afresh (:meth:`clear`)."""
        try:
            names = {entry.name for entry in self.path.iterdir()}
        except OSError:
            return False
        return LOCK in names and names <= set(RUN_OWNED) and MODEL not in names and not self.has_checkpoint()

    def clear(self) -> None:
        """Remove everything in the folder but its lock file (call holding :meth:`writer_lock`)."""
        for entry in self.path.iterdir():
            if entry.name == LOCK:
                continue
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry)
            else:
                entry.unlink()

    def prune_replay_buffers(self, keep: int) -> None:
        """Delete the replay buffers of all but the ``keep`` newest checkpoints (models stay)."""
        folders = sorted(self.checkpoints.glob("ep_*")) if self.checkpoints.is_dir() else []
        for folder in folders[:-keep] if keep > 0 else folders:
            (folder / REPLAY_BUFFER).unlink(missing_ok=True)

    def write_checkpoint_state(self, folder: Path, state: dict[str, Any]) -> None:
        """Written last: marks a checkpoint complete."""
        (folder / CHECKPOINT_STATE).write_text(json.dumps(state, indent=2))

    def find_model(self) -> Path:
        """The final model, else the newest checkpoint's."""
        if self.model.is_file():
            return self.model
        try:
            return self.newest_checkpoint().model
        except RunError:
            raise RunError(f"{self.path} has no {MODEL} and no checkpoint; train it first with 'lanefree train'") \
                from None


def find_eval_dir(folder: Path) -> Path:
    """``folder`` itself if it holds a recording (``trajectories/``), else ``folder/eval``."""
    return folder if (folder / TRAJECTORIES).is_dir() else folder / EVAL


def trajectory_path(eval_dir: Path, episode: int) -> Path:
    """Recording of evaluation episode ``episode`` (every vehicle, every step)."""
    return eval_dir / TRAJECTORIES / f"episode_{episode:04d}.csv"


def vehicles_path(eval_dir: Path, episode: int) -> Path:
    """Length, width and desired speed of each vehicle of a recorded episode."""
    return eval_dir / TRAJECTORIES / f"episode_{episode:04d}.vehicles.csv"

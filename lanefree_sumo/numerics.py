"""Process-wide settings made when the package is imported: the same episodes on every machine (numpy kept on
its portable SIMD kernels, MKL's products independent of where their operands lie in memory), and the C heap
kept for the array temporaries a step makes.

numpy picks its SIMD kernels for the CPU when it is imported, and its AVX-512 kernels of ``exp``, ``log``, …
round differently in the last bit from its AVX2 ones; the driver model and the reward fields use them, and one
bit changes an episode. Measured: on an AVX-512 machine, DDPG seed 0's first episode differs from the
committed run trained on an AVX2 machine (4 collisions against 5) with numpy's AVX-512 kernels and is
identical, every column but wall time, on its AVX2 kernels (``tests/experiments/test_reproducibility.py``).
torch gave the same bits on both machines; its kernel level is recorded, not pinned.

MKL (torch's CPU matrix products) may pick its kernels by the operands' memory alignment: on an AMD EPYC with
AVX-512, run k ≥ 1 of a batch (its rows of a stacked ``[K, …]`` buffer start mid-cache-line) got other bits from
``bmm``/``addmm`` than the run alone (8.9e-08 after one DDPG update; ``tests/rl/test_batched_learners.py``), where
an Intel machine had given the same. :func:`keep_mkl_reproducible` sets MKL's conditional numerical
reproducibility (``MKL_CBWR=AUTO,STRICT``: the CPU's best kernels, results independent of alignment) before torch
loads MKL; measured on that machine, the batched products of a DDPG update cost the same with it (1.75 ms).

A step of the driver model makes some forty temporaries of ``[K, N, N]`` pairs and frees them again. glibc's
malloc hands memory freed at the top of its heap back to the kernel once more than its trim threshold is free
(128 KiB at first, at most 64 MiB as it adapts), and serves blocks above its mmap threshold (128 KiB at first) by
``mmap``: either way the next step's temporaries are fresh pages, and each page's first touch is a page fault.
With the thresholds that glibc's own adaptation reaches at most, set from the start
(:func:`keep_heap_for_temporaries`), 100 steps of the vector env fault 5 pages instead of 25 000 at K = 8 and
cost 1.37× less CPU time (1.53× at K = 64; whole processes, docs/performance.md); the numbers a step computes do not
depend on where its arrays lie.

This module imports nothing of the package (the package's ``__init__`` calls :func:`keep_numpy_portable`,
:func:`keep_mkl_reproducible` and :func:`keep_heap_for_temporaries` before anything imports numpy or torch).
"""

from __future__ import annotations

import contextlib
import ctypes
import importlib.util
import json
import os
import platform
import subprocess
import sys
from pathlib import Path

PORTABLE_NUMPY_DISPATCH = "X86_V4 AVX512_ICL AVX512_SPR"
"""numpy's (≥ 2.4) AVX-512 kernel tiers on x86-64: switched off, numpy runs its x86-64-v3 (AVX2) kernels."""

VARIABLE = "NPY_DISABLE_CPU_FEATURES"
"""numpy's environment variable, read once when numpy is imported (and inherited by child processes)."""


PROBE_CACHE = "numpy_tiers.json"
"""The file (in :func:`cache_folder`) that keeps each numpy installation's probe outcome: {key: bool}."""


def cache_folder() -> Path:
    """``$XDG_CACHE_HOME/lanefree_sumo`` (default ``~/.cache/lanefree_sumo``)."""
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "lanefree_sumo"


def _numpy_identity(tiers: str) -> str | None:
    """What the probe's outcome depends on, found without importing numpy: this interpreter, the tiers, and
    numpy's compiled core (path, size, modification time: a reinstalled numpy is probed again); None: no numpy."""
    spec = importlib.util.find_spec("numpy")
    if spec is None or not spec.submodule_search_locations:
        return None
    cores = sorted(Path(next(iter(spec.submodule_search_locations)), "_core").glob("_multiarray_umath*"))
    if not cores:
        return None
    stat = cores[0].stat()
    return f"{sys.executable}|{tiers}|{cores[0]}|{stat.st_size}|{stat.st_mtime_ns}"


def _probe(tiers: str) -> bool:
    """Whether numpy imports with ``tiers`` switched off, asked of a child interpreter once per numpy installation
    (the answer is kept in :data:`PROBE_CACHE`; an unreadable or unwritable cache only means asking again)."""
    key = _numpy_identity(tiers)
    path: Path | None = None
    known: dict[str, bool] = {}
    with contextlib.suppress(OSError, ValueError, TypeError, RuntimeError):  # RuntimeError: no home folder
        path = cache_folder() / PROBE_CACHE
        known = dict(json.loads(path.read_text()))
    if key is not None and isinstance(known.get(key), bool):
        return known[key]
    probe = subprocess.run([sys.executable, "-c", "import numpy"], env={**os.environ, VARIABLE: tiers},
                           capture_output=True, check=False)
    works = probe.returncode == 0  # else "You cannot disable CPU feature …, since it is part of the baseline"
    if key is not None and path is not None:
        with contextlib.suppress(OSError):
            path.parent.mkdir(parents=True, exist_ok=True)
            temporary = path.with_name(f"{path.name}.{os.getpid()}")
            temporary.write_text(json.dumps({**known, key: works}))
            os.replace(temporary, path)
    return works


def keep_numpy_portable(tiers: str = PORTABLE_NUMPY_DISPATCH) -> bool:
    """Switch numpy's ``tiers`` off before numpy is imported, on x86-64, unless the user set :data:`VARIABLE`
    (empty: every kernel of the CPU) or numpy is already imported. A numpy built with one of them in its
    baseline refuses to import with them switched off, and a failed import cannot be retried in the same
    process, so a child interpreter tries first, once per numpy installation (:func:`_probe`); if it fails, numpy
    keeps its kernels (the variable is set empty). Either way child processes inherit the decision. True when the
    setting applies."""
    if ("numpy" in sys.modules or VARIABLE in os.environ or not sys.executable
            or platform.machine().lower() not in ("x86_64", "amd64")):
        return False
    if not _probe(tiers):
        os.environ[VARIABLE] = ""  # numpy's own kernels, decided once: child processes do not probe again
        return False
    os.environ[VARIABLE] = tiers
    return True


MKL_VARIABLE = "MKL_CBWR"
"""MKL's conditional-numerical-reproducibility setting, read when MKL initialises (inherited by child processes)."""
MKL_REPRODUCIBLE = "AUTO,STRICT"


def keep_mkl_reproducible() -> bool:
    """Set :data:`MKL_VARIABLE` to :data:`MKL_REPRODUCIBLE` unless the user set it or torch is already imported
    (its MKL may have initialised). True when the setting applies."""
    if MKL_VARIABLE in os.environ or "torch" in sys.modules:
        return False
    os.environ[MKL_VARIABLE] = MKL_REPRODUCIBLE
    return True


MALLOC_VARIABLES = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_")
"""glibc's environment variables for the heap's thresholds: a user who sets one keeps glibc's behaviour as set."""
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
"""glibc's ``mallopt`` parameter numbers (``malloc.h``)."""
MMAP_THRESHOLD_BYTES = 32 * 2**20
"""Blocks from 32 MiB up come from ``mmap`` (glibc's largest adaptive mmap threshold on 64-bit): replay buffers do;
a step's temporaries come from the heap."""
TRIM_THRESHOLD_BYTES = 64 * 2**20
"""Up to 64 MiB freed at the heap's top stay in the process (glibc's adaptive trim threshold is twice the mmap
threshold)."""


def keep_heap_for_temporaries() -> bool:
    """Set glibc's mmap and trim thresholds to :data:`MMAP_THRESHOLD_BYTES` and :data:`TRIM_THRESHOLD_BYTES`
    (module docstring) unless the user set one of :data:`MALLOC_VARIABLES` or the C library is not glibc.
    True when the setting applies."""
    if sys.platform != "linux" or platform.libc_ver()[0] != "glibc" or any(v in os.environ for v in MALLOC_VARIABLES):
        return False
    mallopt = ctypes.CDLL(None).mallopt
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) & bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))

"""The same episodes on every machine: numpy kept on its portable SIMD kernels, MKL's products independent of
where their operands lie in memory.

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

This module imports nothing of the package (the package's ``__init__`` calls :func:`keep_numpy_portable` and
:func:`keep_mkl_reproducible` before anything imports numpy or torch).
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys

PORTABLE_NUMPY_DISPATCH = "X86_V4 AVX512_ICL AVX512_SPR"
"""numpy's (≥ 2.4) AVX-512 kernel tiers on x86-64: switched off, numpy runs its x86-64-v3 (AVX2) kernels."""

VARIABLE = "NPY_DISABLE_CPU_FEATURES"
"""numpy's environment variable, read once when numpy is imported (and inherited by child processes)."""


def keep_numpy_portable(tiers: str = PORTABLE_NUMPY_DISPATCH) -> bool:
    """Switch numpy's ``tiers`` off before numpy is imported, on x86-64, unless the user set :data:`VARIABLE`
    (empty: every kernel of the CPU) or numpy is already imported. A numpy built with one of them in its
    baseline refuses to import with them switched off, and a failed import cannot be retried in the same
    process, so a child interpreter tries first; if it fails, numpy keeps its kernels (the variable is set
    empty). Either way child processes inherit the decision. True when the setting applies."""
    if ("numpy" in sys.modules or VARIABLE in os.environ or not sys.executable
            or platform.machine().lower() not in ("x86_64", "amd64")):
        return False
    probe = subprocess.run([sys.executable, "-c", "import numpy"], env={**os.environ, VARIABLE: tiers},
                           capture_output=True, check=False)
    if probe.returncode != 0:  # "You cannot disable CPU feature …, since it is part of the baseline"
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

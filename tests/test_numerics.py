"""The package's process-wide heap setting (lanefree_sumo/numerics.py): the vector env's steps reuse the heap's pages
for their array temporaries instead of faulting in fresh ones, and a user's own glibc setting is left as it is."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

from lanefree_sumo.numerics import MALLOC_VARIABLES

STEPS = 100
STEP_FAULTS = f"""
import resource
import gymnasium as gym
import numpy as np
import lanefree_sumo  # noqa: F401  (the setting under test is made here)

envs = gym.make_vec("LaneFree-v0", num_envs=8, vectorization_mode="vector_entry_point")
envs.reset(seed=0)
zero = np.zeros(envs.action_space.shape, dtype=envs.action_space.dtype)
for _ in range(20):
    envs.step(zero)
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range({STEPS}):
    envs.step(zero)
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""
"""Minor page faults of STEPS steps of 8 rings (70 veh/km: [8, 36, 36] pairs) after 20 steps of warm-up."""


def step_faults(env: dict[str, str]) -> int:
    out = subprocess.run([sys.executable, "-c", STEP_FAULTS], env=env, capture_output=True, text=True, check=True)
    return int(out.stdout)


@pytest.mark.skipif(sys.platform != "linux" or platform.libc_ver()[0] != "glibc",
                    reason="glibc's heap thresholds: the setting applies on Linux with glibc only")
def test_a_steps_temporaries_reuse_the_heap_and_a_users_own_setting_is_kept() -> None:
    env = {k: v for k, v in os.environ.items() if k not in MALLOC_VARIABLES}
    kept = step_faults(env)
    # the user's own trim threshold (glibc's initial 128 KiB, not adapted): the package leaves glibc as set, and
    # each step faults in its temporaries' pages again (about 250 per step of 8 rings)
    handed_back = step_faults({**env, "MALLOC_TRIM_THRESHOLD_": str(128 * 1024)})
    assert kept < 10 * STEPS < handed_back, (kept, handed_back)

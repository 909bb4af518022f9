"""lanefree_sumo: deep RL in lane-free traffic on Eclipse SUMO.

Importing the package registers the gymnasium environment ``LaneFree-v0``::

    import gymnasium, lanefree_sumo
    env = gymnasium.make("LaneFree-v0", config={"scenario": {"density_veh_per_km": 90}})
"""

import os
import platform
import sys

PORTABLE_NUMPY_DISPATCH = "X86_V4 AVX512_ICL AVX512_SPR"
"""numpy's AVX-512 kernel tiers, switched off on x86-64 (``NPY_DISABLE_CPU_FEATURES``) before numpy is imported.

numpy picks its SIMD kernels for the CPU at import, and its AVX-512 kernels of ``exp``, ``log``, … round
differently in the last bit from the AVX2 ones; the driver model and the reward fields use them, and one bit
changes an episode. On AVX2 kernels (x86-64-v3, every x86 server CPU since about 2015) a run gives the same
episodes on every machine: measured, the same ``episodes.csv`` rows on this project's AVX-512 machine as on the
AVX2 machine that trained the committed runs, and different rows without this setting. It applies when this
package is imported before numpy (the ``lanefree`` command and its child processes) and the user has not set
``NPY_DISABLE_CPU_FEATURES`` (set it empty to give numpy every kernel of the CPU). Each run's
``versions.json`` records the kernels numpy used (``numpy_simd``)."""

if "numpy" not in sys.modules and platform.machine().lower() in ("x86_64", "amd64"):
    os.environ.setdefault("NPY_DISABLE_CPU_FEATURES", PORTABLE_NUMPY_DISPATCH)

from gymnasium.envs.registration import register  # noqa: E402  (numpy's kernels are chosen above)

from lanefree_sumo.rl import rewards  # noqa: E402

# SPEC §7 names the pure reward functions `lanefree_sumo.rewards`: the same module as rl.rewards.
sys.modules[f"{__name__}.rewards"] = rewards

register(id="LaneFree-v0", entry_point="lanefree_sumo.rl.env:LaneFreeEnv")

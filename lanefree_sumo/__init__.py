"""lanefree_sumo: deep RL in lane-free traffic on Eclipse SUMO.

Importing the package registers the gymnasium environment ``LaneFree-v0``::

    import gymnasium, lanefree_sumo
    env = gymnasium.make("LaneFree-v0", config={"scenario": {"density_veh_per_km": 90}})
"""

import sys

from gymnasium.envs.registration import register

from lanefree_sumo.rl import rewards

# SPEC §7 names the pure reward functions `lanefree_sumo.rewards`: the same module as rl.rewards.
sys.modules[f"{__name__}.rewards"] = rewards

register(id="LaneFree-v0", entry_point="lanefree_sumo.rl.env:LaneFreeEnv")

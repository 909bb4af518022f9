"""lanefree_sumo: deep RL in lane-free traffic on Eclipse SUMO.

Importing the package registers the gymnasium environment ``LaneFree-v0`` and its vector entry point::

    import gymnasium, lanefree_sumo
    env = gymnasium.make("LaneFree-v0", config={"scenario": {"density_veh_per_km": 90}})
    envs = gymnasium.make_vec("LaneFree-v0", num_envs=8, vectorization_mode="vector_entry_point")

A process that has not imported the package finds it by the module-qualified id
``gymnasium.make("lanefree_sumo:LaneFree-v0")`` (gymnasium imports ``lanefree_sumo`` first).

Citations "specification §N" in the docstrings refer to the project's specification, docs/specification.md.
"""

from lanefree_sumo.numerics import keep_heap_for_temporaries, keep_mkl_reproducible, keep_numpy_portable

keep_numpy_portable()  # before anything imports numpy: the same episodes on every machine (numerics.py)
keep_mkl_reproducible()  # before torch loads MKL: a batch's runs get the bits of the runs alone (numerics.py)
keep_heap_for_temporaries()  # a step's array temporaries reuse the heap's pages, no page faults (numerics.py)

from gymnasium.envs.registration import register  # noqa: E402  (numpy's kernels are chosen above)

register(id="LaneFree-v0", entry_point="lanefree_sumo.rl.env:LaneFreeEnv",
         vector_entry_point="lanefree_sumo.rl.vector_env:LaneFreeVectorEnv")

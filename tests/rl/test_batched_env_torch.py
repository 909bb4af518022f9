"""The batched environment on a torch device (CPU here) against the numpy reference: the same functions
(:mod:`lanefree_sumo.sim.xp`), bit for bit with numpy's transcendental functions (see
``tests/sim/test_world_torch.py`` for why those are exchanged)."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from lanefree_sumo.rl.batched_env import BatchedRingEnv  # noqa: E402
from lanefree_sumo.sim.xp_torch import numpy_transcendentals  # noqa: E402
from tests.rl.test_batched_env import PER_RUN_LIMITS, TERMS, actions, configs  # noqa: E402


def _host(a):
    return a.numpy() if isinstance(a, torch.Tensor) else np.asarray(a)


@pytest.mark.parametrize("kind, bonuses", [("continuous", None), ("discrete", None),
                                            ("continuous", ("once_per_vehicle", "net_passes", "every_pass"))])
def test_the_torch_batched_env_is_the_numpy_one_bit_for_bit(kind, bonuses):
    """``bonuses``: each run's reward.overtake_bonus (None: every pass), the ledger on the device too; with the
    bonuses, each run its own top speed and lateral bound too (the per-run limits on the device)."""
    cfgs = configs(kind) if bonuses is None else configs(kind, bonuses=bonuses, steps=120, limits=PER_RUN_LIMITS)
    reference, twin = BatchedRingEnv(cfgs), BatchedRingEnv(cfgs, device="torch-cpu")
    rng = np.random.default_rng(1)
    seen = {"ended": 0, "overtakes": 0, "collision_events": 0, "unpaid": 0}
    with numpy_transcendentals():
        for _episode in range(2):
            obs, obs_twin = reference.reset(), twin.reset()
            assert isinstance(obs_twin, torch.Tensor) and obs_twin.dtype == torch.float32
            np.testing.assert_array_equal(obs, obs_twin.numpy())
            for step in range(cfgs[0]["sim"]["episode_steps"]):
                act = actions(rng, kind, step, surge=bonuses is not None)  # surges: the same cars passed again
                got, want = twin.step(act), reference.step(act)
                for i in range(4):
                    np.testing.assert_array_equal(_host(got[i]), _host(want[i]), err_msg=f"step {step}, item {i}")
                assert isinstance(got[2], np.ndarray) and isinstance(got[3], np.ndarray)  # episode ends: host
                for term in TERMS:
                    np.testing.assert_array_equal(_host(got[4][term]), _host(want[4][term]), err_msg=term)
                for mine, theirs in zip(got[4]["episode_metrics"], want[4]["episode_metrics"]):
                    assert (mine is None) == (theirs is None)
                    if mine is not None:
                        seen["ended"] += 1
                        assert {**mine, "wall_s": 0} == {**theirs, "wall_s": 0}
                for key in ("overtakes", "collision_events"):
                    seen[key] += int(want[4][key].sum())
                seen["unpaid"] += int(((want[4]["overtakes"] > 0) & (want[4]["overtook"] == 0)).sum())
    assert seen["ended"] == 6 and seen["overtakes"] > 0 and seen["collision_events"] > 0
    assert (seen["unpaid"] > 0) == (bonuses is not None)  # the ledger withheld some bonus, on both

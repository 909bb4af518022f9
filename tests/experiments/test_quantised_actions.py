"""scripts/analysis/quantised_actions.py: continuous accelerations turned into the DQN family's 9 discrete actions."""

from __future__ import annotations

import importlib.util

import numpy as np

from lanefree_sumo.config import LaneFreeConfig, merge_config
from lanefree_sumo.rl.env import DISCRETE_ACTIONS, action_to_acceleration

from conftest import ROOT

spec = importlib.util.spec_from_file_location("quantised_actions",
                                              ROOT / "scripts" / "analysis" / "quantised_actions.py")
assert spec is not None and spec.loader is not None
quantised_actions = importlib.util.module_from_spec(spec)
spec.loader.exec_module(quantised_actions)
Quantiser = quantised_actions.Quantiser


def accelerations(cfg: LaneFreeConfig, index: int) -> np.ndarray:
    """(ax, ay) in m/s² of a discrete action, as the env applies it."""
    return np.array(action_to_acceleration(merge_config(cfg, {"action": {"kind": "discrete"}}), index, "test"))


def test_nearest_takes_the_nearest_level_of_each_component():
    cfg = LaneFreeConfig()  # levels: ax -2, 0, +2 m/s²; ay -1, 0, +1 m/s²
    nearest = Quantiser(cfg, carry=False)
    cases = {(0.9, 0.4): (0, 0), (1.1, 0.0): (2, 0), (-4.5, 0.6): (-2, 1), (-1.2, -1.8): (-2, -1), (0.0, -0.6): (0, -1)}
    for wanted, expected in cases.items():
        index = nearest(np.array(wanted))
        assert tuple(accelerations(cfg, index)) == expected, wanted
        assert tuple(DISCRETE_ACTIONS[index]) == (np.sign(expected[0]), np.sign(expected[1]))
    assert nearest(np.array((0.9, 0.4))) == nearest(np.array((0.9, 0.4)))  # no memory


def test_sigma_delta_averages_to_the_wanted_acceleration():
    cfg = LaneFreeConfig()
    carried = Quantiser(cfg, carry=True)
    wanted = np.array([0.5, -0.3])  # nearest alone would give (0, 0) on every step
    applied = np.array([accelerations(cfg, carried(wanted)) for _ in range(400)])
    assert np.allclose(applied.mean(axis=0), wanted, atol=0.01)
    assert set(applied[:, 0]) == {0.0, 2.0} and set(applied[:, 1]) == {0.0, -1.0}
    carried.reset()
    hard = np.array([accelerations(cfg, carried(np.array([-4.5, 0.0]))) for _ in range(50)])
    assert (hard[:, 0] == -2.0).all()  # braking beyond the levels: the hardest level, no wind-up after
    assert tuple(accelerations(cfg, carried(np.array([0.0, 0.0])))) == (-2.0, 0.0)  # the carried error: one level
    assert tuple(accelerations(cfg, carried(np.array([0.0, 0.0])))) == (0.0, 0.0)

"""What the tests of the project's SB3 classes (``test_ddpg.py``, ``test_dqn.py``) share: a toy env with
LaneFree-v0's observation size, a model whose replay buffer is filled with random transitions, seeded gradient
steps, and "the same": ``torch.equal`` on every tensor listed."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm

OBS, BATCH = 24, 64
"""LaneFree-v0's vector observation size; the paper's batch."""

Reward = Callable[[Any, np.random.Generator], float]


class ToyEnv(gym.Env):
    """Gaussian observations (a flat Box, or the same vector in a Dict), ``reward(action, rng)``, episodes of 40 steps
    ending in truncation or, every third episode, termination."""

    def __init__(self, action_space: spaces.Space, reward: Reward, as_dict: bool = False) -> None:
        box = spaces.Box(-np.inf, np.inf, (OBS,), np.float32)
        self.observation_space = spaces.Dict({"x": box}) if as_dict else box
        self.action_space = action_space
        self.reward, self.as_dict = reward, as_dict
        self.t = self.episode = 0

    def _obs(self) -> Any:
        x = self.np_random.normal(size=OBS).astype(np.float32)
        return {"x": x} if self.as_dict else x

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        super().reset(seed=seed)
        self.t = 0
        self.episode += 1
        return self._obs(), {}

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        self.t += 1
        end = self.t >= 40
        reward = self.reward(action, self.np_random)
        return self._obs(), reward, end and self.episode % 3 == 0, end and self.episode % 3 != 0, {}


def fill(model: OffPolicyAlgorithm, action: Callable[[np.random.Generator], np.ndarray], reward_scale: float,
         as_dict: bool) -> OffPolicyAlgorithm:
    """``model`` with 1000 random transitions in its replay buffer (some terminal, some truncated; actions
    ``action(rng)``, rewards normal × ``reward_scale``), a silent logger and full progress left."""
    rng = np.random.default_rng(7)
    for k in range(1000):
        obs, next_obs = (rng.normal(size=(1, OBS)).astype(np.float32) for _ in range(2))
        if as_dict:
            obs, next_obs = {"x": obs}, {"x": next_obs}
        done = k % 40 == 39
        model.replay_buffer.add(obs, next_obs, action(rng),  # type: ignore[arg-type, union-attr]
                                (reward_scale * rng.normal(size=1)).astype(np.float32), np.array([done]),
                                [{"TimeLimit.truncated": done and k % 80 == 79}])
    model.set_logger(Logger(None, []))
    model._current_progress_remaining = 1.0
    return model


def gradient_steps(model: OffPolicyAlgorithm, n: int) -> tuple[th.Tensor, np.ndarray, dict[str, float]]:
    """n gradient steps from seeded random streams; (torch RNG state, numpy RNG key, logged values)."""
    np.random.seed(123)
    th.manual_seed(123)
    for _ in range(n):
        model.train(gradient_steps=1, batch_size=BATCH)
    return th.get_rng_state(), np.random.get_state()[1].copy(), dict(model.logger.name_to_value)  # type: ignore[index]


def adam_states(*optimizers: th.optim.Optimizer) -> list[th.Tensor]:
    """Each Adam state's step and first and second moments."""
    return [state[key] for optimizer in optimizers for state in optimizer.state_dict()["state"].values()
            for key in ("step", "exp_avg", "exp_avg_sq")]


def assert_tensors_equal(a: list[th.Tensor], b: list[th.Tensor], at_least: int) -> None:
    """``a`` and ``b`` equal tensor by tensor, more than ``at_least`` of them (the message: the largest difference)."""
    assert len(a) == len(b) > at_least
    diff = max((x - y).abs().max().item() for x, y in zip(a, b))
    assert all(th.equal(x, y) for x, y in zip(a, b)), f"max |difference| {diff:g}"

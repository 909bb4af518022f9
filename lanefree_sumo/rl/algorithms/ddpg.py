"""DDPG as an SB3 class: Stable-Baselines3's :class:`~stable_baselines3.DDPG` with the project's two actor-critic
choices (``train.actor_critic``): the class of the batched learner's ``model.zip`` and the reference its tests
compare it with (every run trains in the batched learner).

:class:`LaneFreeDDPG` is SB3's DDPG — same constructor, ``save``/``load`` (either class loads the other's
``model.zip``), callbacks, TensorBoard, replay buffer, resume — and with the defaults (``warmup_actions =
uniform``, ``pre_tanh_penalty = 0``) it computes SB3's numbers: it runs SB3's own ``train`` and collection.
The choices:

* ``warmup_actions = policy``: the actor and its noise act from the first step (Keras-RL's DDPG) instead of
  SB3's uniformly random actions for the first ``learning_starts`` steps; updates still wait for them;
* ``pre_tanh_penalty = λ > 0``: λ·mean(u²) added to the actor loss, u the actor's pre-tanh output (a remedy for
  an actor stuck at its tanh bound); the update is SB3's otherwise (same calls, draws and order).

The batched learner (:mod:`.batched.ddpg`) computes the same numbers for one run (``tests/rl/
test_batched_learners.py`` compares every parameter, target and Adam moment with this class bit for bit).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch as th
from stable_baselines3 import DDPG
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.type_aliases import RolloutReturn, TrainFreq
from stable_baselines3.common.utils import polyak_update
from stable_baselines3.common.vec_env import VecEnv
from torch.nn import functional as F

WARMUP_ACTIONS: tuple[str, ...] = ("uniform", "policy")
"""What DDPG does before its first update (``train.actor_critic.warmup_actions``)."""


class LaneFreeDDPG(DDPG):
    """SB3's DDPG with the warm-up choice and the pre-tanh penalty (module docstring).

    :param warmup_actions: ``uniform`` (SB3's random actions for ``learning_starts`` steps) or ``policy``.
    :param pre_tanh_penalty: λ ≥ 0 of λ·mean(u²) added to the actor loss.

    All other parameters are :class:`stable_baselines3.DDPG`'s."""

    def __init__(self, *args: Any, warmup_actions: str = "uniform", pre_tanh_penalty: float = 0.0,
                 **kwargs: Any) -> None:
        if warmup_actions not in WARMUP_ACTIONS:
            raise ValueError(f"unknown warm-up {warmup_actions!r}; valid: {', '.join(WARMUP_ACTIONS)}")
        if not pre_tanh_penalty >= 0:
            raise ValueError(f"pre_tanh_penalty must be ≥ 0, got {pre_tanh_penalty!r}")
        self.pre_tanh_penalty = float(pre_tanh_penalty)
        self.warmup_actions = warmup_actions
        super().__init__(*args, **kwargs)

    def _penalty(self) -> float:
        """λ of the pre-tanh penalty (0 for models saved before it existed)."""
        return float(getattr(self, "pre_tanh_penalty", 0.0))

    def _random_steps(self, learning_starts: int) -> int:
        """Steps that act uniformly at random: SB3's ``learning_starts``, or none with ``warmup_actions =
        policy`` (the actor and its noise from the first step, as Keras-RL's DDPG; updates still wait)."""
        return learning_starts if getattr(self, "warmup_actions", "uniform") == "uniform" else 0

    def collect_rollouts(self, env: VecEnv, callback: BaseCallback, train_freq: TrainFreq,
                         replay_buffer: ReplayBuffer, action_noise: ActionNoise | None = None,
                         learning_starts: int = 0, log_interval: int | None = None) -> RolloutReturn:
        """SB3's collection, whose ``learning_starts`` only decides random actions: see :meth:`_random_steps`."""
        return super().collect_rollouts(env, callback, train_freq, replay_buffer, action_noise,
                                        self._random_steps(learning_starts), log_interval)

    def train(self, gradient_steps: int, batch_size: int = 100) -> None:
        """SB3's update; with a pre-tanh penalty, SB3's TD3/DDPG step with the penalty added to the actor loss."""
        penalty = self._penalty()
        if not penalty:
            super().train(gradient_steps, batch_size)
            return
        self.policy.set_training_mode(True)
        self._update_learning_rate([self.actor.optimizer, self.critic.optimizer])
        actor_losses, critic_losses = [], []
        for _ in range(gradient_steps):
            self._n_updates += 1
            data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)  # type: ignore[union-attr]
            discounts = data.discounts if data.discounts is not None else self.gamma
            with th.no_grad():
                noise = data.actions.clone().data.normal_(0, self.target_policy_noise)
                noise = noise.clamp(-self.target_noise_clip, self.target_noise_clip)
                next_actions = (self.actor_target(data.next_observations) + noise).clamp(-1, 1)
                next_q = th.cat(self.critic_target(data.next_observations, next_actions), dim=1)
                next_q, _ = th.min(next_q, dim=1, keepdim=True)
                target_q = data.rewards + (1 - data.dones) * discounts * next_q
            current_q = self.critic(data.observations, data.actions)
            critic_loss = sum(F.mse_loss(q, target_q) for q in current_q)
            assert isinstance(critic_loss, th.Tensor)
            critic_losses.append(critic_loss.item())
            self.critic.optimizer.zero_grad()
            critic_loss.backward()
            self.critic.optimizer.step()
            if self._n_updates % self.policy_delay == 0:  # the actor's pre-tanh output kept: mu = [..., Tanh]
                pre = self.actor.mu[:-1](self.actor.extract_features(data.observations,
                                                                     self.actor.features_extractor))
                actor_loss = (-self.critic.q1_forward(data.observations, th.tanh(pre)).mean()
                              + penalty * pre.square().mean())
                actor_losses.append(actor_loss.item())
                self.actor.optimizer.zero_grad()
                actor_loss.backward()
                self.actor.optimizer.step()
                polyak_update(self.critic.parameters(), self.critic_target.parameters(), self.tau)
                polyak_update(self.actor.parameters(), self.actor_target.parameters(), self.tau)
                polyak_update(self.critic_batch_norm_stats, self.critic_batch_norm_stats_target, 1.0)
                polyak_update(self.actor_batch_norm_stats, self.actor_batch_norm_stats_target, 1.0)
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        if actor_losses:
            self.logger.record("train/actor_loss", np.mean(actor_losses))
        self.logger.record("train/critic_loss", np.mean(critic_losses))

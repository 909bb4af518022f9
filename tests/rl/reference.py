"""The references the batched learners are compared with where stock SB3 has no class: SB3's own DDPG and DQN
with the project's learner choices written into their autograd update (tests only; every run trains in the
batched learners, :mod:`lanefree_sumo.rl.algorithms.batched`).

* :class:`ReferenceDDPG`: SB3's ``DDPG`` with the warm-up from the policy (no random steps; updates still wait for
  ``learning_starts``) and the pre-tanh penalty λ·mean(u²) on the actor loss;
* :class:`ReferenceDQN`: SB3's ``DQN`` with the double-Q target, Keras-RL's ½·δ² loss and proportional prioritised
  replay (the trees of :class:`~lanefree_sumo.rl.algorithms.batched.replay.RunPriorities`, whose sampling
  ``tests/rl/test_algorithms.py`` checks against a brute-force draw); the dueling network is the policy
  (:mod:`lanefree_sumo.rl.algorithms.q_networks`).

With none of the choices each update is SB3's own, call for call and draw for draw (the tests compare that too).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch as th
from stable_baselines3 import DDPG, DQN
from stable_baselines3.common.type_aliases import ReplayBufferSamples
from stable_baselines3.common.utils import polyak_update
from torch.nn import functional as F

from lanefree_sumo.rl.algorithms.batched.replay import RunPriorities


class ReferenceDDPG(DDPG):
    """SB3's DDPG; ``warmup_actions = "policy"``: the actor and its noise from the first step; ``pre_tanh_penalty``
    λ ≥ 0 of λ·mean(u²) added to the actor loss (u: the actor's output before its tanh)."""

    def __init__(self, *args: Any, warmup_actions: str = "uniform", pre_tanh_penalty: float = 0.0,
                 **kwargs: Any) -> None:
        self.warmup_actions, self.pre_tanh_penalty = warmup_actions, float(pre_tanh_penalty)
        super().__init__(*args, **kwargs)

    def collect_rollouts(self, *args: Any, **kwargs: Any) -> Any:
        """SB3's collection, whose ``learning_starts`` decides only the random actions."""
        if self.warmup_actions == "policy":
            kwargs["learning_starts"] = 0
        return super().collect_rollouts(*args, **kwargs)

    def train(self, gradient_steps: int, batch_size: int = 100) -> None:
        if not self.pre_tanh_penalty:
            super().train(gradient_steps, batch_size)
            return
        self._update_learning_rate([self.actor.optimizer, self.critic.optimizer])
        actor_losses, critic_losses = [], []
        for _ in range(gradient_steps):  # DDPG is SB3's TD3 with one critic, no target noise, policy_delay 1
            self._n_updates += 1
            data = self.replay_buffer.sample(batch_size)  # type: ignore[union-attr]
            with th.no_grad():
                noise = data.actions.clone().data.normal_(0, self.target_policy_noise)
                noise = noise.clamp(-self.target_noise_clip, self.target_noise_clip)
                next_actions = (self.actor_target(data.next_observations) + noise).clamp(-1, 1)
                next_q = th.cat(self.critic_target(data.next_observations, next_actions), dim=1)
                next_q, _ = th.min(next_q, dim=1, keepdim=True)
                target_q = data.rewards + (1 - data.dones) * self.gamma * next_q
            critic_loss = sum(F.mse_loss(q, target_q) for q in self.critic(data.observations, data.actions))
            assert isinstance(critic_loss, th.Tensor)
            critic_losses.append(critic_loss.item())
            self.critic.optimizer.zero_grad()
            critic_loss.backward()
            self.critic.optimizer.step()
            pre = self.actor.mu[:-1](self.actor.extract_features(data.observations, self.actor.features_extractor))
            actor_loss = (-self.critic.q1_forward(data.observations, th.tanh(pre)).mean()
                          + self.pre_tanh_penalty * pre.square().mean())
            actor_losses.append(actor_loss.item())
            self.actor.optimizer.zero_grad()
            actor_loss.backward()
            self.actor.optimizer.step()
            polyak_update(self.critic.parameters(), self.critic_target.parameters(), self.tau)
            polyak_update(self.actor.parameters(), self.actor_target.parameters(), self.tau)
        self.logger.record("train/actor_loss", np.mean(actor_losses))
        self.logger.record("train/critic_loss", np.mean(critic_losses))


class ReferenceDQN(DQN):
    """SB3's DQN; ``double_q``: the TD target takes the online network's argmax; ``loss = "squared"``: ½·δ²
    (else SB3's Huber); ``per``: proportional prioritised replay with α, β₀ → 1 over training and ε as given
    (``per = (alpha, beta0, eps)``)."""

    def __init__(self, *args: Any, double_q: bool = False, loss: str = "huber",
                 per: tuple[float, float, float] | None = None, **kwargs: Any) -> None:
        self.double_q, self.loss, self.per = double_q, loss, per
        super().__init__(*args, **kwargs)
        self.priorities: RunPriorities | None = None
        if per is not None:
            self.priorities = RunPriorities(self.buffer_size, per[0], per[2])
            add = self.replay_buffer.add  # type: ignore[union-attr]

            def added(*args: Any, **kwargs: Any) -> None:
                pos = self.replay_buffer.pos  # type: ignore[union-attr]
                add(*args, **kwargs)
                self.priorities.added(pos)  # type: ignore[union-attr]

            self.replay_buffer.add = added  # type: ignore[union-attr, method-assign]

    def _sample(self, batch_size: int) -> tuple[Any, th.Tensor | None, np.ndarray | None]:
        """A minibatch, its importance weights and positions (None, None: uniform, SB3's draw)."""
        if self.priorities is None:
            return self.replay_buffer.sample(batch_size), None, None  # type: ignore[union-attr]
        assert self.per is not None
        beta = self.per[1] + (1.0 - self.per[1]) * min(max(1.0 - self._current_progress_remaining, 0.0), 1.0)
        pos, weights = self.priorities.sample(np.random.mtrand._rand, batch_size, beta)
        rb = self.replay_buffer
        assert rb is not None

        def at(values: Any) -> Any:
            return {key: th.as_tensor(v[pos, 0]) for key, v in values.items()} if isinstance(values, dict) \
                else th.as_tensor(values[pos, 0])

        data = ReplayBufferSamples(at(rb.observations), th.as_tensor(rb.actions[pos, 0]), at(rb.next_observations),
                                   th.as_tensor((rb.dones[pos, 0] * (1 - rb.timeouts[pos, 0])).reshape(-1, 1)),
                                   th.as_tensor(rb.rewards[pos, 0].reshape(-1, 1)))
        return data, th.as_tensor(weights).reshape(-1, 1), pos

    def train(self, gradient_steps: int, batch_size: int = 100) -> None:
        self.policy.set_training_mode(True)
        self._update_learning_rate(self.policy.optimizer)
        losses = []
        for _ in range(gradient_steps):
            data, weights, pos = self._sample(batch_size)
            with th.no_grad():
                if self.double_q:
                    best = self.q_net(data.next_observations).argmax(dim=1, keepdim=True)
                    next_q = th.gather(self.q_net_target(data.next_observations), dim=1, index=best)
                else:
                    next_q, _ = self.q_net_target(data.next_observations).max(dim=1)
                target_q = data.rewards + (1 - data.dones) * self.gamma * next_q.reshape(-1, 1)
            current_q = th.gather(self.q_net(data.observations), dim=1, index=data.actions.long())
            squared = self.loss == "squared"
            if weights is None:
                loss = 0.5 * F.mse_loss(current_q, target_q) if squared else F.smooth_l1_loss(current_q, target_q)
            else:
                each = (0.5 * F.mse_loss(current_q, target_q, reduction="none") if squared
                        else F.smooth_l1_loss(current_q, target_q, reduction="none"))
                loss = (weights.reshape(each.shape) * each).mean()
            losses.append(loss.item())
            self.policy.optimizer.zero_grad()
            loss.backward()
            th.nn.utils.clip_grad_norm_(self.policy.parameters(), self.max_grad_norm)
            self.policy.optimizer.step()
            if self.priorities is not None:
                self.priorities.update(pos, (target_q - current_q.detach()).reshape(-1).abs().numpy())
        self._n_updates += gradient_steps
        self.logger.record("train/loss", np.mean(losses))

"""Double DQN (Van Hasselt, Guez & Silver 2016) as a Stable-Baselines3 class.

The TD target uses the action chosen by the *online* network and evaluated by the *target*
network: ``y = r + γ (1 − d) Q_target(s', argmax_a Q_online(s', a))``.

:class:`DoubleDQN` is :class:`~.fast_dqn.FastDQN` with ``double_q``: for plain MLPs the update is
written out there. :meth:`DoubleDQN._autograd_train`, the update for any other network (or with
``fast_learner=False``), reproduces SB3's ``DQN.train`` through autograd (Huber loss
``smooth_l1_loss`` with β = 1, gradient-norm clipping at ``max_grad_norm``, the n-step
``discounts`` field, ``train/loss`` and ``train/n_updates`` logging) split into overridable hooks:
``_sample_batch`` (data + optional per-sample weights), ``_compute_target_q_values`` (the TD
target), ``_compute_loss`` (Huber, optionally weighted) and ``_after_gradient_step`` (receives the
TD errors), so the PER class overrides hooks instead of duplicating the loop. The online network's
greedy action on ``s'`` is computed with the online net in its current (training) mode, as the
online Q(s, a) is.
"""

from typing import ClassVar

import numpy as np
import torch as th
from stable_baselines3.common.type_aliases import (
    ReplayBufferSamples,
)
from torch.nn import functional as F

from lanefree_sumo.rl.algorithms.fast_dqn import FastDQN


class DoubleDQN(FastDQN):
    """Double DQN (Van Hasselt, Guez & Silver 2016) on top of SB3's ``DQN`` (through :class:`~.fast_dqn.FastDQN`).

    Identical to ``stable_baselines3.DQN`` except for the TD target, which
    decouples action selection (online ``q_net``) from evaluation (``q_net_target``):
    ``y = r + γ (1 - d) Q_target(s', argmax_a Q_online(s', a))``.
    Constructor arguments are those of ``DQN``.

    The autograd update is split into hooks so variants can override single pieces:
    ``_sample_batch``, ``_compute_target_q_values``, ``_compute_loss`` and
    ``_after_gradient_step``.
    """

    double_q: ClassVar[bool] = True

    def _compute_target_q_values(self, replay_data: ReplayBufferSamples) -> th.Tensor:
        """Double-Q TD target, shape ``(batch, 1)`` (no gradient).

        Uses ``replay_data.discounts`` (n-step buffer) when present, else γ.
        """
        discounts = replay_data.discounts if replay_data.discounts is not None else self.gamma
        with th.no_grad():
            # Select the greedy next action with the online network ...
            next_actions = self.q_net(replay_data.next_observations).argmax(dim=1, keepdim=True)
            # ... and evaluate it with the target network.
            next_q_values = th.gather(self.q_net_target(replay_data.next_observations), dim=1, index=next_actions)
            next_q_values = next_q_values.reshape(-1, 1)
            return replay_data.rewards + (1 - replay_data.dones) * discounts * next_q_values

    def _compute_loss(
        self, current_q_values: th.Tensor, target_q_values: th.Tensor, weights: th.Tensor | None = None
    ) -> th.Tensor:
        """Huber loss; with ``weights`` it is ``mean_i(w_i · huber_i)`` (same as SB3 when None)."""
        if weights is None:
            return F.smooth_l1_loss(current_q_values, target_q_values)
        per_sample = F.smooth_l1_loss(current_q_values, target_q_values, reduction="none")
        return (weights.reshape(per_sample.shape) * per_sample).mean()

    def _autograd_train(self, gradient_steps: int, batch_size: int) -> None:
        """SB3's ``DQN.train`` loop through autograd with the double-Q target (and hooks, see class doc)."""
        self.policy.set_training_mode(True)
        self._update_learning_rate(self.policy.optimizer)

        losses = []
        for _ in range(gradient_steps):
            replay_data, weights = self._sample_batch(batch_size)
            target_q_values = self._compute_target_q_values(replay_data)

            current_q_values = self.q_net(replay_data.observations)
            current_q_values = th.gather(current_q_values, dim=1, index=replay_data.actions.long())

            loss = self._compute_loss(current_q_values, target_q_values, weights)
            losses.append(loss.item())

            self.policy.optimizer.zero_grad()
            loss.backward()
            th.nn.utils.clip_grad_norm_(self.policy.parameters(), self.max_grad_norm)
            self.policy.optimizer.step()

            self._after_gradient_step((target_q_values - current_q_values.detach()).reshape(-1))

        self._n_updates += gradient_steps

        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/loss", np.mean(losses))

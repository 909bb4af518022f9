"""The DQN family as SB3 classes: Stable-Baselines3's :class:`~stable_baselines3.DQN` with its ``train`` split into
hooks, the base of the project's :class:`~.double_dqn.DoubleDQN`, :class:`~.dueling.DuelingDoubleDQN` and
:class:`~.prioritized.PrioritizedDoubleDQN`: the classes of the batched learner's ``model.zip`` and the
references its tests compare it with (every run trains in the batched learner).

:class:`LaneFreeDQN` is SB3's DQN (same constructor, ``save``/``load`` both ways, callbacks, TensorBoard, replay buffer,
resume); with the default hooks and loss its update is SB3's, call for call and draw for draw
(``tests/rl/test_dqn.py`` trains both and compares every parameter):

* the TD target ``r + γ (1 − d) Q'(s', a*)`` with ``a*`` the target's argmax (DQN) or the online network's
  (double DQN, :attr:`LaneFreeDQN.double_q`), the loss (``train.dqn.loss``: SB3's Huber, or Keras-RL's ½·δ²; the
  importance-weighted mean under prioritised replay), one Adam step after clipping the gradient norm at
  ``max_grad_norm``; the target copied every ``target_update_interval`` steps by SB3's own ``_on_step``.

The batched learners (:mod:`.batched.dqn`) compute the same numbers for one run (``tests/rl/
test_batched_learners.py``).
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import torch as th
from stable_baselines3 import DQN
from stable_baselines3.common.type_aliases import ReplayBufferSamples
from torch.nn import functional as F

NO_REDUCTION = 0
"""torch's ``Reduction::None`` (the batched learner's loss gradient: ``smooth_l1_loss_backward``)."""
HUBER_BETA = 1.0
"""``F.smooth_l1_loss``'s default β, which SB3's DQN uses."""


LOSSES: tuple[str, ...] = ("huber", "squared")
"""The TD losses (``train.dqn.loss``): SB3's Huber (smooth L1, β = 1) or Keras-RL's ½·δ²."""


class LaneFreeDQN(DQN):
    """SB3's DQN with its update split into hooks (module docstring); the base of the project's DQN variants,
    which set :attr:`double_q` and override the hooks.

    Hooks: :meth:`_sample_batch` (data + optional per-sample loss weights), :meth:`_compute_target_q_values`,
    :meth:`_compute_loss`, :meth:`_after_gradient_step` (receives the TD errors).

    :param loss: ``huber`` (SB3's) or ``squared`` (½·δ²).

    All other parameters are :class:`stable_baselines3.DQN`'s."""

    double_q: ClassVar[bool] = False
    """The TD target's next action: the target network's argmax (False, DQN) or the online network's (True)."""

    def __init__(self, *args: Any, loss: str = "huber", **kwargs: Any) -> None:
        if loss not in LOSSES:
            raise ValueError(f"unknown TD loss {loss!r}; valid: {', '.join(LOSSES)}")
        self.loss = loss
        super().__init__(*args, **kwargs)

    def _sample_batch(self, batch_size: int) -> tuple[ReplayBufferSamples, th.Tensor | None]:
        """Draw a minibatch; return it with per-sample loss weights (None = uniform)."""
        replay_data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)  # type: ignore[union-attr]
        return replay_data, None

    def _compute_target_q_values(self, replay_data: ReplayBufferSamples) -> th.Tensor:
        """The TD target, shape ``(batch, 1)`` (no gradient): the target network's value of its own greedy
        action (DQN, SB3's) or of the online network's (``double_q``); ``replay_data.discounts`` (n-step buffer)
        when present, else γ."""
        discounts = replay_data.discounts if replay_data.discounts is not None else self.gamma
        with th.no_grad():
            if self.double_q:
                next_actions = self.q_net(replay_data.next_observations).argmax(dim=1, keepdim=True)
                next_q_values = th.gather(self.q_net_target(replay_data.next_observations), dim=1,
                                          index=next_actions)
            else:
                next_q_values, _ = self.q_net_target(replay_data.next_observations).max(dim=1)
            next_q_values = next_q_values.reshape(-1, 1)
            return replay_data.rewards + (1 - replay_data.dones) * discounts * next_q_values

    def _compute_loss(self, current_q_values: th.Tensor, target_q_values: th.Tensor,
                      weights: th.Tensor | None = None) -> th.Tensor:
        """The TD loss (:attr:`loss`: Huber, or ½·δ²); with ``weights`` it is ``mean_i(w_i · loss_i)`` (SB3's
        Huber when None)."""
        squared = getattr(self, "loss", "huber") == "squared"
        if weights is None:
            if squared:
                return 0.5 * F.mse_loss(current_q_values, target_q_values)
            return F.smooth_l1_loss(current_q_values, target_q_values)
        if squared:
            per_sample = 0.5 * F.mse_loss(current_q_values, target_q_values, reduction="none")
        else:
            per_sample = F.smooth_l1_loss(current_q_values, target_q_values, reduction="none")
        return (weights.reshape(per_sample.shape) * per_sample).mean()

    def _after_gradient_step(self, td_errors: th.Tensor) -> None:
        """Called after each gradient step with the batch TD errors ``y − Q(s, a)`` (detached, 1-D)."""

    def train(self, gradient_steps: int, batch_size: int = 100) -> None:
        """SB3's ``DQN.train`` (the same calls and draws; with the default hooks the same numbers), split into the
        hooks."""
        self.policy.set_training_mode(True)
        self._update_learning_rate(self.policy.optimizer)
        losses = []
        for _ in range(gradient_steps):
            replay_data, weights = self._sample_batch(batch_size)
            target_q_values = self._compute_target_q_values(replay_data)
            current_q_values = th.gather(self.q_net(replay_data.observations), dim=1,
                                         index=replay_data.actions.long())
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

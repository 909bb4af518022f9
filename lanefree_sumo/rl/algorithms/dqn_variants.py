"""DQN variants of the paper's comparison (SPEC §9), as Stable-Baselines3 classes.

Karalakou et al. (2023) compare DDPG with DQN, double DQN, dueling double DQN
and double DQN with prioritised experience replay. Stable-Baselines3 only ships
plain DQN, so this module adds the rest on top of ``stable_baselines3.DQN``:

* :class:`DoubleDQN` -- Van Hasselt, Guez & Silver (2016), "Deep Reinforcement
  Learning with Double Q-learning": the TD target uses the action chosen by the
  *online* network and evaluated by the *target* network,
  ``y = r + γ (1 - d) Q_target(s', argmax_a Q_online(s', a))``.
* :class:`DuelingQNetwork` / :class:`DuelingDQNPolicy` /
  :class:`MultiInputDuelingDQNPolicy` -- Wang et al. (2016), "Dueling Network
  Architectures for Deep Reinforcement Learning":
  ``Q(s, a) = V(s) + A(s, a) - mean_a' A(s, a')``. :class:`DuelingDoubleDQN` is
  :class:`DoubleDQN` whose ``"MlpPolicy"`` / ``"MultiInputPolicy"`` aliases are
  the dueling policies.
* :class:`PrioritizedReplayBuffer` / :class:`PrioritizedDictReplayBuffer` /
  :class:`PrioritizedDoubleDQN` -- Schaul, Quan, Antonoglou & Silver (2016),
  "Prioritized Experience Replay", proportional variant with a sum-tree.

Choices (where the papers leave room)
-------------------------------------
* ``DoubleDQN.train`` reproduces SB3's ``DQN.train`` (Huber loss
  ``smooth_l1_loss`` with its default β = 1, gradient-norm clipping at
  ``max_grad_norm``, the n-step ``discounts`` field, ``train/loss`` and
  ``train/n_updates`` logging) but is split into overridable hooks:
  ``_sample_batch`` (data + optional per-sample weights),
  ``_compute_target_q_values`` (the TD target), ``_compute_loss`` (Huber,
  optionally weighted) and ``_after_gradient_step`` (receives the TD errors).
  The PER class only overrides the hooks, it does not duplicate the loop.
* The online network's greedy action on ``s'`` is computed with the online net
  in its current (training) mode, exactly as the online Q(s, a) is.
* PER priorities: the trees store ``p_i^α`` with ``p_i = |δ_i| + eps``; a new
  transition gets the largest ``p^α`` ever set (1.0 initially). Sampling is
  stratified (Schaul 2016, App. B.2.1): the total mass is cut into
  ``batch_size`` equal segments and one value is drawn uniformly in each.
* Importance weights ``w_i = (N·P(i))^-β / max_j w_j`` where ``N`` is the number
  of stored transitions and the max runs over the *whole buffer* (via a
  min-tree on the priorities, as in Schaul 2016's Algorithm 1), so
  ``w_i = (P(i) / min_j P(j))^-β ≤ 1``.
* Weights multiply the per-sample Huber loss, which is then averaged over the
  batch (``mean(w_i · huber_i)``); priorities are updated after each gradient
  step with the |TD errors| computed in that step's forward pass (i.e. before
  the optimiser step, as in Algorithm 1).
* β is annealed linearly from ``beta0`` (0.4) at the start of ``learn`` to 1.0
  at its end: ``β = beta0 + (1 - beta0)(1 - progress_remaining)``, set on the
  buffer (``buffer.set_beta``) after every environment step and before every
  training call, so it is exactly 1.0 after the last step.
* n-step returns are not combined with PER (``PrioritizedDoubleDQN`` raises for
  ``n_steps > 1``); plain ``DoubleDQN`` supports them like SB3's DQN.
* Flat buffer index ``i = pos * n_envs + env`` (SB3 stores ``(buffer_size,
  n_envs)`` arrays); ``buffer.last_indices`` holds these flat indices.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3 import DQN
from stable_baselines3.common.buffers import DictReplayBuffer, ReplayBuffer
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor, CombinedExtractor, create_mlp
from stable_baselines3.common.type_aliases import (
    DictReplayBufferSamples,
    GymEnv,
    PyTorchObs,
    ReplayBufferSamples,
    Schedule,
)
from stable_baselines3.common.vec_env import VecNormalize
from stable_baselines3.dqn.policies import CnnPolicy, DQNPolicy, QNetwork
from torch import nn
from torch.nn import functional as F

__all__ = [
    "SumTree",
    "MinTree",
    "DoubleDQN",
    "DuelingQNetwork",
    "DuelingDQNPolicy",
    "MultiInputDuelingDQNPolicy",
    "DuelingDoubleDQN",
    "PrioritizedReplayBuffer",
    "PrioritizedDictReplayBuffer",
    "PrioritizedDoubleDQN",
    "DQN_VARIANTS",
]


# ---------------------------------------------------------------------------
# Segment trees (numpy, vectorised over batches of indices)
# ---------------------------------------------------------------------------
class _SegmentTree:
    """Complete binary tree over ``capacity`` leaves stored in one flat array.

    Node 1 is the root, node ``k`` has children ``2k`` and ``2k+1``; leaf ``i``
    is node ``size + i`` where ``size`` is the next power of two ≥ capacity.
    Subclasses define the associative operation and its neutral element.
    """

    neutral: ClassVar[float] = 0.0

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        self.capacity = int(capacity)
        self.size = 1 << (self.capacity - 1).bit_length()  # next power of two
        self.depth = self.size.bit_length() - 1  # log2(size)
        self.tree = np.full(2 * self.size, self.neutral, dtype=np.float64)

    @staticmethod
    def _combine(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def _check(self, indices: np.ndarray) -> np.ndarray:
        idx = np.asarray(indices, dtype=np.int64).reshape(-1)
        if idx.size and (idx.min() < 0 or idx.max() >= self.capacity):
            raise IndexError(f"tree index out of range [0, {self.capacity}): {idx.min()}..{idx.max()}")
        return idx

    def update(self, indices: np.ndarray | int, values: np.ndarray | float) -> None:
        """Set leaves ``indices`` to ``values`` and recompute their ancestors."""
        idx = self._check(indices)
        if idx.size == 0:
            return
        vals = np.broadcast_to(np.asarray(values, dtype=np.float64).reshape(-1), idx.shape)
        nodes = idx + self.size
        self.tree[nodes] = vals  # duplicate indices: last value wins
        for _ in range(self.depth):
            nodes = np.unique(nodes >> 1)
            self.tree[nodes] = self._combine(self.tree[2 * nodes], self.tree[2 * nodes + 1])

    def get(self, indices: np.ndarray | int) -> np.ndarray:
        """Leaf values at ``indices``."""
        return self.tree[self._check(indices) + self.size]

    def reduce(self) -> float:
        """Reduction (sum or min) over all leaves."""
        return float(self.tree[1])

    def clear(self) -> None:
        self.tree.fill(self.neutral)


class SumTree(_SegmentTree):
    """Sum-tree: O(log n) update, total mass and prefix-sum search (Schaul 2016)."""

    neutral: ClassVar[float] = 0.0

    @staticmethod
    def _combine(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return a + b

    def total(self) -> float:
        """Sum of all leaves."""
        return self.reduce()

    def find_prefixsum_idx(self, values: np.ndarray | float) -> np.ndarray:
        """For each ``v`` return the leaf ``i`` with ``sum(p[:i]) <= v < sum(p[:i+1])``.

        Never returns a zero-mass leaf while the tree has positive mass (values
        at or above the total, e.g. from rounding, map to the last non-empty leaf).
        """
        v = np.array(values, dtype=np.float64).reshape(-1)
        node = np.ones(v.shape, dtype=np.int64)
        for _ in range(self.depth):
            left = 2 * node
            left_mass = self.tree[left]
            go_right = (v >= left_mass) & (self.tree[left + 1] > 0.0)
            v = np.where(go_right, v - left_mass, v)
            node = np.where(go_right, left + 1, left)
        return node - self.size


class MinTree(_SegmentTree):
    """Min-tree: O(log n) update and global minimum (empty leaves are +inf)."""

    neutral: ClassVar[float] = float("inf")

    @staticmethod
    def _combine(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.minimum(a, b)

    def min(self) -> float:
        """Minimum over all leaves (+inf when empty)."""
        return self.reduce()


# ---------------------------------------------------------------------------
# Double DQN (Van Hasselt et al. 2016)
# ---------------------------------------------------------------------------
class DoubleDQN(DQN):
    """Double DQN (Van Hasselt, Guez & Silver 2016) on top of SB3's ``DQN``.

    Identical to ``stable_baselines3.DQN`` except for the TD target, which
    decouples action selection (online ``q_net``) from evaluation (``q_net_target``):
    ``y = r + γ (1 - d) Q_target(s', argmax_a Q_online(s', a))``.
    Constructor arguments are those of ``DQN``.

    ``train`` is split into hooks so variants can override single pieces:
    ``_sample_batch``, ``_compute_target_q_values``, ``_compute_loss`` and
    ``_after_gradient_step``.
    """

    def _sample_batch(self, batch_size: int) -> tuple[ReplayBufferSamples, th.Tensor | None]:
        """Draw a minibatch; return it with per-sample loss weights (None = uniform)."""
        replay_data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)  # type: ignore[union-attr]
        return replay_data, None

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

    def _after_gradient_step(self, td_errors: th.Tensor) -> None:
        """Hook called after each gradient step with the batch TD errors ``y - Q(s, a)`` (detached, 1-D)."""

    def train(self, gradient_steps: int, batch_size: int = 100) -> None:
        """SB3's ``DQN.train`` loop with the double-Q target (and hooks, see class doc)."""
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


# ---------------------------------------------------------------------------
# Dueling architecture (Wang et al. 2016)
# ---------------------------------------------------------------------------
class DuelingHead(nn.Module):
    """Shared MLP trunk + value head V(s) and advantage head A(s, a) (Wang et al. 2016).

    ``forward(features) = V + A - mean_a A`` with shape ``(batch, n_actions)``.
    """

    def __init__(self, features_dim: int, n_actions: int, net_arch: list[int], activation_fn: type[nn.Module]) -> None:
        super().__init__()
        trunk = create_mlp(features_dim, -1, net_arch, activation_fn)  # hidden layers only, each + activation
        self.trunk = nn.Sequential(*trunk)
        last_dim = net_arch[-1] if len(net_arch) > 0 else features_dim
        self.value_head = nn.Linear(last_dim, 1)
        self.advantage_head = nn.Linear(last_dim, n_actions)

    def forward(self, features: th.Tensor) -> th.Tensor:
        hidden = self.trunk(features)
        value = self.value_head(hidden)
        advantage = self.advantage_head(hidden)
        return value + advantage - advantage.mean(dim=1, keepdim=True)


class DuelingQNetwork(QNetwork):
    """Dueling Q-network (Wang et al. 2016) with SB3's ``QNetwork`` interface.

    ``self.q_net`` maps features to Q-values like in ``QNetwork``, but it is a
    :class:`DuelingHead`: trunk = ``net_arch`` hidden layers (e.g. ``[128, 64]``
    -> 128-64 with activations), then linear heads ``value_head`` (1 output) and
    ``advantage_head`` (n actions), combined as ``Q = V + A - mean_a A``.
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Discrete,
        features_extractor: BaseFeaturesExtractor,
        features_dim: int,
        net_arch: list[int] | None = None,
        activation_fn: type[nn.Module] = nn.ReLU,
        normalize_images: bool = True,
    ) -> None:
        # Skip QNetwork.__init__ (it would build a throw-away plain MLP) and set the same attributes.
        BasePolicy.__init__(
            self,
            observation_space,
            action_space,
            features_extractor=features_extractor,
            normalize_images=normalize_images,
        )
        if net_arch is None:
            net_arch = [64, 64]
        self.net_arch = net_arch
        self.activation_fn = activation_fn
        self.features_dim = features_dim
        self.q_net = DuelingHead(self.features_dim, int(self.action_space.n), self.net_arch, self.activation_fn)

    def value_and_advantage(self, obs: PyTorchObs) -> tuple[th.Tensor, th.Tensor]:
        """Raw head outputs ``(V (batch, 1), A (batch, n_actions))``."""
        hidden = self.q_net.trunk(self.extract_features(obs, self.features_extractor))
        return self.q_net.value_head(hidden), self.q_net.advantage_head(hidden)


class DuelingDQNPolicy(DQNPolicy):
    """``DQNPolicy`` whose online and target networks are :class:`DuelingQNetwork` (Wang et al. 2016)."""

    q_net: DuelingQNetwork
    q_net_target: DuelingQNetwork

    def make_q_net(self) -> DuelingQNetwork:
        net_args = self._update_features_extractor(self.net_args, features_extractor=None)
        return DuelingQNetwork(**net_args).to(self.device)


class MultiInputDuelingDQNPolicy(DuelingDQNPolicy):
    """Dueling policy for ``spaces.Dict`` observations (``CombinedExtractor`` by default)."""

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Discrete,
        lr_schedule: Schedule,
        net_arch: list[int] | None = None,
        activation_fn: type[nn.Module] = nn.ReLU,
        features_extractor_class: type[BaseFeaturesExtractor] = CombinedExtractor,
        features_extractor_kwargs: dict[str, Any] | None = None,
        normalize_images: bool = True,
        optimizer_class: type[th.optim.Optimizer] = th.optim.Adam,
        optimizer_kwargs: dict[str, Any] | None = None,
    ) -> None:
        super().__init__(
            observation_space,
            action_space,
            lr_schedule,
            net_arch,
            activation_fn,
            features_extractor_class,
            features_extractor_kwargs,
            normalize_images,
            optimizer_class,
            optimizer_kwargs,
        )


class DuelingDoubleDQN(DoubleDQN):
    """Dueling double DQN (Wang et al. 2016 + Van Hasselt et al. 2016).

    Same as :class:`DoubleDQN`; only the policy aliases differ: ``"MlpPolicy"``
    is :class:`DuelingDQNPolicy` and ``"MultiInputPolicy"`` is
    :class:`MultiInputDuelingDQNPolicy`.
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": DuelingDQNPolicy,
        "CnnPolicy": CnnPolicy,  # no dueling CNN variant is needed by the project
        "MultiInputPolicy": MultiInputDuelingDQNPolicy,
    }


# ---------------------------------------------------------------------------
# Prioritised experience replay (Schaul et al. 2016)
# ---------------------------------------------------------------------------
class _PrioritizedMixin:
    """Proportional prioritisation (Schaul et al. 2016) for SB3 replay buffers.

    Must precede an SB3 ``ReplayBuffer`` subclass in the bases. Subclasses
    implement ``_gather(batch_inds, env_inds, env)``.
    """

    buffer_size: int
    n_envs: int
    pos: int

    def __init__(
        self,
        *args: Any,
        alpha: float = 0.6,
        beta0: float = 0.4,
        eps: float = 1e-6,
        optimize_memory_usage: bool = False,
        **kwargs: Any,
    ) -> None:
        if optimize_memory_usage:
            raise ValueError(f"{type(self).__name__} does not support optimize_memory_usage=True")
        if alpha < 0:
            raise ValueError(f"alpha must be >= 0, got {alpha}")
        if not 0.0 <= beta0 <= 1.0:
            raise ValueError(f"beta0 must be in [0, 1], got {beta0}")
        if eps <= 0:
            raise ValueError(f"eps must be > 0, got {eps}")
        super().__init__(*args, optimize_memory_usage=False, **kwargs)  # type: ignore[call-arg]
        self.alpha = float(alpha)
        self.beta0 = float(beta0)
        self.beta = float(beta0)
        self.eps = float(eps)
        capacity = self.buffer_size * self.n_envs
        self.sum_tree = SumTree(capacity)
        self.min_tree = MinTree(capacity)
        self.max_priority = 1.0  # largest p^alpha set so far; new transitions get it
        self.last_indices = np.zeros(0, dtype=np.int64)
        self.last_weights = np.zeros(0, dtype=np.float32)

    # --- public API -------------------------------------------------------
    def set_beta(self, beta: float) -> None:
        """Set the importance-sampling exponent used by the next ``sample`` calls."""
        if not 0.0 <= beta <= 1.0:
            raise ValueError(f"beta must be in [0, 1], got {beta}")
        self.beta = float(beta)

    def n_stored(self) -> int:
        """Number of stored transitions N (all envs)."""
        return self.size() * self.n_envs  # type: ignore[attr-defined]

    def flat_index(self, pos: np.ndarray | int, env_idx: np.ndarray | int) -> np.ndarray:
        """Map ``(pos, env)`` storage coordinates to flat indices ``pos * n_envs + env``."""
        return np.asarray(pos, dtype=np.int64) * self.n_envs + np.asarray(env_idx, dtype=np.int64)

    def priorities(self, indices: np.ndarray | int) -> np.ndarray:
        """Stored priorities ``p_i^alpha`` at flat ``indices``."""
        return self.sum_tree.get(indices)

    def update_priorities(self, indices: np.ndarray, td_errors: np.ndarray | th.Tensor) -> None:
        """Set ``p_i = |td_i| + eps`` (stored as ``p_i^alpha``) for flat ``indices``."""
        if isinstance(td_errors, th.Tensor):
            td_errors = td_errors.detach().cpu().numpy()
        idx = np.asarray(indices, dtype=np.int64).reshape(-1)
        td = np.asarray(td_errors, dtype=np.float64).reshape(-1)
        if idx.shape != td.shape:
            raise ValueError(f"{idx.size} indices but {td.size} TD errors")
        if idx.size == 0:
            return
        if not np.all(np.isfinite(td)):
            raise ValueError("non-finite TD error passed to update_priorities")
        n = self.n_stored()
        if idx.min() < 0 or idx.max() >= n:
            raise IndexError(f"priority index out of range [0, {n}): {idx.min()}..{idx.max()}")
        prio = (np.abs(td) + self.eps) ** self.alpha
        self.sum_tree.update(idx, prio)
        self.min_tree.update(idx, prio)
        self.max_priority = max(self.max_priority, float(prio.max()))

    # --- SB3 buffer API -----------------------------------------------------
    def add(self, *args: Any, **kwargs: Any) -> None:
        """Store one step of all envs (SB3 signature); the new transitions get the max priority."""
        pos = self.pos
        super().add(*args, **kwargs)  # type: ignore[misc]
        idx = self.flat_index(pos, np.arange(self.n_envs))
        self.sum_tree.update(idx, self.max_priority)
        self.min_tree.update(idx, self.max_priority)

    def reset(self) -> None:
        super().reset()  # type: ignore[misc]
        self.sum_tree.clear()
        self.min_tree.clear()
        self.max_priority = 1.0

    def sample(self, batch_size: int, env: VecNormalize | None = None) -> Any:
        """Sample ∝ ``p_i^alpha`` (stratified); sets ``last_indices`` and ``last_weights``."""
        n = self.n_stored()
        if n == 0:
            raise ValueError("cannot sample from an empty replay buffer")
        total = self.sum_tree.total()
        segment = total / batch_size
        values = (np.arange(batch_size) + np.random.random_sample(batch_size)) * segment
        flat = self.sum_tree.find_prefixsum_idx(values)
        probs = self.sum_tree.get(flat) / total
        min_prob = self.min_tree.min() / total
        # w_i = (N P(i))^-beta / max_j (N P(j))^-beta = (P(i) / min_j P(j))^-beta
        weights = (probs / min_prob) ** (-self.beta)
        self.last_indices = flat
        self.last_weights = weights.astype(np.float32)
        batch_inds, env_inds = np.divmod(flat, self.n_envs)
        return self._gather(batch_inds, env_inds, env)

    def _gather(self, batch_inds: np.ndarray, env_inds: np.ndarray, env: VecNormalize | None) -> Any:
        raise NotImplementedError


class PrioritizedReplayBuffer(_PrioritizedMixin, ReplayBuffer):
    """Proportional prioritised replay (Schaul et al. 2016) as an SB3 ``ReplayBuffer``.

    :param buffer_size, observation_space, action_space, device, n_envs,
        handle_timeout_termination: as in ``ReplayBuffer``
    :param optimize_memory_usage: must be False (raises ``ValueError`` otherwise)
    :param alpha: priority exponent, ``P(i) = p_i^α / Σ_k p_k^α`` (0.6)
    :param beta0: initial importance-sampling exponent β (0.4); change with ``set_beta``
    :param eps: added to |TD error| so no priority is zero (1e-6)

    ``sample()`` returns ``ReplayBufferSamples`` and records ``last_indices``
    (flat indices ``pos * n_envs + env``) and ``last_weights`` (normalised IS
    weights, float32); feed them back with ``update_priorities``.
    """

    def _gather(self, batch_inds: np.ndarray, env_inds: np.ndarray, env: VecNormalize | None) -> ReplayBufferSamples:
        data = (
            self._normalize_obs(self.observations[batch_inds, env_inds, :], env),
            self.actions[batch_inds, env_inds, :],
            self._normalize_obs(self.next_observations[batch_inds, env_inds, :], env),
            (self.dones[batch_inds, env_inds] * (1 - self.timeouts[batch_inds, env_inds])).reshape(-1, 1),
            self._normalize_reward(self.rewards[batch_inds, env_inds].reshape(-1, 1), env),
        )
        return ReplayBufferSamples(*tuple(map(self.to_torch, data)))  # type: ignore[arg-type]


class PrioritizedDictReplayBuffer(_PrioritizedMixin, DictReplayBuffer):
    """:class:`PrioritizedReplayBuffer` for ``spaces.Dict`` observations (same arguments)."""

    def _gather(
        self, batch_inds: np.ndarray, env_inds: np.ndarray, env: VecNormalize | None
    ) -> DictReplayBufferSamples:
        obs = self._normalize_obs({k: o[batch_inds, env_inds] for k, o in self.observations.items()}, env)
        next_obs = self._normalize_obs({k: o[batch_inds, env_inds] for k, o in self.next_observations.items()}, env)
        assert isinstance(obs, dict) and isinstance(next_obs, dict)
        dones = self.dones[batch_inds, env_inds] * (1 - self.timeouts[batch_inds, env_inds])
        return DictReplayBufferSamples(
            observations={k: self.to_torch(v) for k, v in obs.items()},
            actions=self.to_torch(self.actions[batch_inds, env_inds]),
            next_observations={k: self.to_torch(v) for k, v in next_obs.items()},
            dones=self.to_torch(dones.reshape(-1, 1)),
            rewards=self.to_torch(self._normalize_reward(self.rewards[batch_inds, env_inds].reshape(-1, 1), env)),
        )


class PrioritizedDoubleDQN(DoubleDQN):
    """Double DQN (Van Hasselt et al. 2016) with proportional prioritised replay (Schaul et al. 2016).

    All ``DQN`` arguments plus:

    :param per_alpha: priority exponent α (0.6)
    :param per_beta0: initial importance-sampling exponent; annealed linearly to
        1.0 over the ``learn`` call via ``_current_progress_remaining`` (0.4)
    :param per_eps: small constant added to |TD error| (1e-6)

    ``replay_buffer_class`` defaults to :class:`PrioritizedReplayBuffer`
    (:class:`PrioritizedDictReplayBuffer` for Dict observations); a custom class
    must derive from one of them. The three ``per_*`` values are forwarded to the
    buffer as ``alpha``/``beta0``/``eps`` (conflicting ``replay_buffer_kwargs``
    raise ``ValueError``). ``n_steps > 1`` is not supported.
    """

    replay_buffer: PrioritizedReplayBuffer | PrioritizedDictReplayBuffer  # type: ignore[assignment]

    def __init__(
        self,
        policy: str | type[DQNPolicy],
        env: GymEnv | str,
        *args: Any,
        per_alpha: float = 0.6,
        per_beta0: float = 0.4,
        per_eps: float = 1e-6,
        _init_setup_model: bool = True,
        **kwargs: Any,
    ) -> None:
        if kwargs.get("n_steps", 1) != 1:
            raise ValueError("PrioritizedDoubleDQN does not support n-step returns (n_steps must be 1)")
        super().__init__(policy, env, *args, _init_setup_model=False, **kwargs)
        self.per_alpha = float(per_alpha)
        self.per_beta0 = float(per_beta0)
        self.per_eps = float(per_eps)
        self._per_indices: np.ndarray | None = None  # flat buffer indices of the current minibatch
        if _init_setup_model:
            self._setup_model()

    def _setup_model(self) -> None:
        if self.replay_buffer_class is None:
            if isinstance(self.observation_space, spaces.Dict):
                self.replay_buffer_class = PrioritizedDictReplayBuffer
            else:
                self.replay_buffer_class = PrioritizedReplayBuffer
        if not issubclass(self.replay_buffer_class, _PrioritizedMixin):
            raise TypeError(
                "PrioritizedDoubleDQN needs a prioritised replay buffer "
                f"(PrioritizedReplayBuffer / PrioritizedDictReplayBuffer), got {self.replay_buffer_class.__name__}"
            )
        for key, value in (("alpha", self.per_alpha), ("beta0", self.per_beta0), ("eps", self.per_eps)):
            if key in self.replay_buffer_kwargs and self.replay_buffer_kwargs[key] != value:
                raise ValueError(
                    f"replay_buffer_kwargs[{key!r}]={self.replay_buffer_kwargs[key]} conflicts with per_{key}={value}"
                )
            self.replay_buffer_kwargs[key] = value
        super()._setup_model()
        self._update_beta()

    def per_beta(self, progress_remaining: float) -> float:
        """Linear schedule ``beta0 -> 1``: ``beta0 + (1 - beta0)(1 - progress_remaining)``."""
        fraction = min(max(1.0 - float(progress_remaining), 0.0), 1.0)
        return self.per_beta0 + (1.0 - self.per_beta0) * fraction

    def _update_beta(self) -> None:
        if self.replay_buffer is not None:
            self.replay_buffer.set_beta(self.per_beta(self._current_progress_remaining))

    def _on_step(self) -> None:
        super()._on_step()
        self._update_beta()

    def _sample_batch(self, batch_size: int) -> tuple[ReplayBufferSamples, th.Tensor | None]:
        replay_data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)
        weights = th.as_tensor(self.replay_buffer.last_weights, device=self.device).reshape(-1, 1)
        self._per_indices = self.replay_buffer.last_indices.copy()
        return replay_data, weights  # type: ignore[return-value]

    def _after_gradient_step(self, td_errors: th.Tensor) -> None:
        assert self._per_indices is not None, "_sample_batch must run before _after_gradient_step"
        self.replay_buffer.update_priorities(self._per_indices, td_errors.abs())
        self._per_indices = None

    def train(self, gradient_steps: int, batch_size: int = 100) -> None:
        self._update_beta()
        super().train(gradient_steps, batch_size)
        self.logger.record("train/per_beta", self.replay_buffer.beta)

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "_per_indices"]


#: Paper name -> algorithm class (policy "MlpPolicy"/"MultiInputPolicy" for all).
DQN_VARIANTS: dict[str, type[DQN]] = {
    "dqn": DQN,
    "ddqn": DoubleDQN,
    "dueling": DuelingDoubleDQN,
    "per": PrioritizedDoubleDQN,
}

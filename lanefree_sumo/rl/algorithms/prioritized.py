"""Double DQN with proportional prioritised experience replay (Schaul et al. 2016).

Choices where the paper leaves room:

* Priorities: the trees store ``p_i^α`` with ``p_i = |δ_i| + eps``; a new transition gets the
  largest ``p^α`` ever set (1.0 initially). Sampling is stratified (App. B.2.1): the total mass
  is cut into ``batch_size`` equal segments and one value is drawn uniformly in each.
* Importance weights ``w_i = (N·P(i))^−β / max_j w_j``, the max over the *whole buffer* (a
  min-tree, as in Algorithm 1), so ``w_i = (P(i) / min_j P(j))^−β ≤ 1``. They multiply the
  per-sample Huber loss, averaged over the batch; priorities are updated after each gradient
  step with the |TD errors| of that step's forward pass (before the optimiser step).
* β is annealed linearly from ``beta0`` (0.4) at the start of ``learn`` to 1.0 at its end,
  set on the buffer after every environment step and before every training call.
* n-step returns are not combined with PER (``n_steps > 1`` raises).
* Flat buffer index ``i = pos · n_envs + env`` (SB3 stores ``(buffer_size, n_envs)`` arrays);
  ``buffer.last_indices`` holds these flat indices.
"""


from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import DictReplayBuffer, ReplayBuffer
from stable_baselines3.common.type_aliases import (
    DictReplayBufferSamples,
    GymEnv,
    ReplayBufferSamples,
)
from stable_baselines3.common.vec_env import VecNormalize
from stable_baselines3.dqn.policies import DQNPolicy

from lanefree_sumo.rl.algorithms.double_dqn import DoubleDQN
from lanefree_sumo.rl.algorithms.segment_tree import MinTree, SumTree


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
        return ReplayBufferSamples(*tuple(map(self.to_torch, data)))


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

    replay_buffer: PrioritizedReplayBuffer | PrioritizedDictReplayBuffer

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
        return replay_data, weights

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

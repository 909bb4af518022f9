"""Per-run replay buffers ``[K, capacity, …]`` and per-run random streams.

A single run draws from numpy's global generator (seeded by SB3's ``set_random_seed``): the exploration
decision and Ornstein-Uhlenbeck noise when it acts, the replay indices when it updates — and from its action
space's own generator (seeded with the run's seed) for random actions. :class:`RunStreams` gives run k a
``numpy.random.RandomState(seed_k)`` (the global generator's algorithm and seeding) and a copy of the action
space seeded with ``seed_k``; the learners call them in the single run's order, so run k draws the single
run's numbers. :class:`BatchedReplay` stores what SB3's ``ReplayBuffer`` stores (float32; SB3's action dtype)
as tensors on the learner's device; :class:`RunPriorities` is one run's prioritised replay index (on
:mod:`.segment_tree`'s trees).
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from typing import Any, cast

import numpy as np
import torch as th
from gymnasium import spaces

from lanefree_sumo.rl.algorithms.batched.segment_tree import MinTree, SumTree


class RunStreams:
    """Run k's random streams: numpy's legacy generator seeded ``seeds[k]`` and the action space seeded so."""

    def __init__(self, seeds: Sequence[int], action_space: spaces.Space) -> None:
        self.numpy = [np.random.RandomState(int(seed)) for seed in seeds]
        self.spaces = []
        for seed in seeds:
            space = copy.deepcopy(action_space)
            space.seed(int(seed))
            self.spaces.append(space)

    def sample_indices(self, upper: int, batch_size: int, slots: int = 1) -> np.ndarray:
        """``ReplayBuffer.sample``'s draws for every run: ``[K, batch]`` flat indices ``position · slots + slot``
        (:class:`BatchedReplay`) from the step position drawn below ``upper``, then the env index (SB3's
        ``env_indices``: always 0 with one env), each run from its stream as SB3 draws them."""
        out = np.empty((len(self.numpy), batch_size), dtype=np.int64)
        for k, rs in enumerate(self.numpy):
            out[k] = rs.randint(0, upper, size=batch_size) * slots
            out[k] += rs.randint(0, high=slots, size=(batch_size,))
        return out

    def state(self) -> dict[str, Any]:
        """The streams' states as tensors and Python numbers (what ``torch.load(weights_only=True)`` reads)."""
        numpy = []
        for rs in self.numpy:
            _, key, pos, has_gauss, cached = cast(tuple[str, np.ndarray, int, int, float], rs.get_state())
            numpy.append({"key": th.from_numpy(key.astype(np.int64)), "pos": int(pos), "has_gauss": int(has_gauss),
                          "cached_gaussian": float(cached)})
        return {"numpy": numpy, "spaces": [space.np_random.bit_generator.state for space in self.spaces]}

    def load_state(self, state: dict[str, Any]) -> None:
        for rs, s in zip(self.numpy, state["numpy"]):
            rs.set_state(("MT19937", np.asarray(s["key"], dtype=np.uint32), s["pos"], s["has_gauss"],
                          s["cached_gaussian"]))
        for space, s in zip(self.spaces, state["spaces"]):
            space.np_random.bit_generator.state = s


class OUNoise:
    """SB3's ``OrnsteinUhlenbeckActionNoise`` (dt = 0.01, mean 0, float64 state, float32 noise) for K runs of
    ``slots`` environments or agents each (SB3's ``VectorizedActionNoise``: one process per slot), ``[K · slots,
    actions]`` (run k's slots in rows k · slots …), each run with its own σ and θ, drawing from its own stream
    slot after slot."""

    DT = 1e-2

    def __init__(self, sigma: Sequence[float], theta: Sequence[float], n_actions: int, slots: int = 1) -> None:
        rows = len(sigma) * slots
        self.slots = slots
        self.mu = np.zeros((rows, n_actions))
        self.sigma = np.array([float(s) * np.ones(n_actions) for s in sigma for _ in range(slots)])
        self.theta = np.array([[float(t)] for t in theta for _ in range(slots)])
        self.prev = np.zeros((rows, n_actions))

    def __call__(self, streams: RunStreams) -> np.ndarray:
        normal = np.stack([streams.numpy[row // self.slots].normal(size=self.mu.shape[1])
                           for row in range(self.mu.shape[0])])
        noise = (self.prev + self.theta * (self.mu - self.prev) * self.DT
                 + self.sigma * np.sqrt(self.DT) * normal)
        self.prev = noise
        return noise.astype(np.float32)

    def reset(self, rows: np.ndarray) -> None:
        """Back to zero for the slots whose episode ended (``rows``: bool ``[K · slots]``)."""
        self.prev[rows] = 0.0


class BatchedReplay:
    """K replay buffers of one capacity as tensors ``[K, capacity · slots, …]`` (SB3's ``ReplayBuffer`` contents:
    observations, next observations, actions, rewards, dones, timeouts); all runs store together. A run of
    ``slots`` environments or agents stores one transition per slot at each step position, as SB3's buffer of
    ``n_envs`` does (its ``[capacity, n_envs]`` flattened: position p, slot m at p · slots + m); ``capacity``
    counts step positions."""

    def __init__(self, runs: int, capacity: int, obs_dim: int, action_dim: int, action_dtype: th.dtype,
                 device: th.device, slots: int = 1) -> None:
        self.capacity, self.slots = capacity, slots
        rows = capacity * slots
        self.observations = th.zeros(runs, rows, obs_dim, device=device)
        self.next_observations = th.zeros(runs, rows, obs_dim, device=device)
        self.actions = th.zeros(runs, rows, action_dim, dtype=action_dtype, device=device)
        self.rewards = th.zeros(runs, rows, device=device)
        self.dones = th.zeros(runs, rows, device=device)
        self.timeouts = th.zeros(runs, rows, device=device)
        self.pos = 0
        self.full = False
        self._runs = th.arange(runs, device=device).unsqueeze(1)

    def size(self) -> int:
        return self.capacity if self.full else self.pos

    def add(self, obs: np.ndarray, next_obs: np.ndarray, actions: np.ndarray, rewards: np.ndarray,
            dones: np.ndarray, timeouts: np.ndarray) -> int:
        """Store one transition per run and slot (rows of the arrays, run-major, cast as SB3's numpy buffer casts;
        tensors already on a device are cast there, with the same rounding); returns its step position."""
        pos = self.pos
        device = self.observations.device
        at = slice(pos * self.slots, (pos + 1) * self.slots)
        for target, values in ((self.observations, obs), (self.next_observations, next_obs),
                               (self.actions, actions), (self.rewards, rewards), (self.dones, dones),
                               (self.timeouts, timeouts)):
            view = target[:, at]
            if isinstance(values, th.Tensor):
                view.copy_(values.to(device=device, dtype=target.dtype).reshape(view.shape))
                continue
            host = np.asarray(values).astype(_NUMPY[target.dtype]).reshape(view.shape)
            view.copy_(th.from_numpy(host).to(device, non_blocking=True))
        self.pos += 1
        if self.pos == self.capacity:
            self.full, self.pos = True, 0
        return pos

    def add_at(self, pos: th.Tensor, obs: th.Tensor, next_obs: th.Tensor, actions: th.Tensor,
               rewards: th.Tensor) -> None:
        """Store one transition per run at the device position ``pos`` (a 0-d int64 tensor), with no host read:
        the lockstep loop's store (its episodes end by the time limit only, so done · (1 − timeout) is 0: both
        are stored as 0). The caller moves ``pos`` and the host's :attr:`pos`."""
        at = pos.reshape(1)
        for target, values in ((self.observations, obs), (self.next_observations, next_obs),
                               (self.actions, actions), (self.rewards, rewards)):
            target.index_copy_(1, at, values.to(target.dtype).reshape(target.shape[0], 1, *target.shape[2:]))
        self.dones.index_fill_(1, at, 0.0)
        self.timeouts.index_fill_(1, at, 0.0)

    def gather(self, indices: np.ndarray | th.Tensor) -> tuple[th.Tensor, th.Tensor, th.Tensor, th.Tensor, th.Tensor]:
        """(observations, actions, next observations, dones · (1 − timeouts), rewards) at ``indices``
        ``[K, batch]`` (host flat indices, or a tensor on the device): ``[K, batch, …]``, the last two
        ``[K, batch, 1]``."""
        index = (indices if isinstance(indices, th.Tensor)
                 else th.from_numpy(indices).to(self.observations.device, non_blocking=True))
        runs = self._runs
        dones = self.dones[runs, index] * (1 - self.timeouts[runs, index])
        return (self.observations[runs, index], self.actions[runs, index], self.next_observations[runs, index],
                dones.unsqueeze(2), self.rewards[runs, index].unsqueeze(2))

    def state_dict(self) -> dict[str, Any]:
        return {"observations": self.observations, "next_observations": self.next_observations,
                "actions": self.actions, "rewards": self.rewards, "dones": self.dones, "timeouts": self.timeouts,
                "pos": self.pos, "full": self.full}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        for name in ("observations", "next_observations", "actions", "rewards", "dones", "timeouts"):
            getattr(self, name).copy_(state[name])
        self.pos, self.full = int(state["pos"]), bool(state["full"])


_NUMPY = {th.float32: np.float32, th.int64: np.int64}


class RunPriorities:
    """One run's proportional prioritised replay index (Schaul et al. 2016), with the choices the paper leaves open:

    * the trees hold ``p_i^α`` with ``p_i = |δ_i| + eps``; a new transition gets the largest ``p^α`` set so far
      (1.0 at first); priorities are updated after each gradient step with the |TD errors| of its forward pass;
    * sampling is stratified (App. B.2.1): the total mass cut into ``batch_size`` equal segments, one value drawn
      uniformly in each;
    * importance weights ``w_i = (P(i) / min_j P(j))^−β ≤ 1``, the minimum over the whole buffer (a min-tree, as
      in Algorithm 1); they multiply the per-sample loss, averaged over the batch; β annealed linearly from
      ``per_beta0`` to 1 over training (:meth:`~.dqn.BatchedDQN.per_beta`);
    * the flat index of a transition is ``position · slots + slot`` (SB3's ``(buffer_size, n_envs)`` layout)."""

    def __init__(self, capacity: int, alpha: float, eps: float) -> None:
        self.sum_tree, self.min_tree = SumTree(capacity), MinTree(capacity)
        self.alpha, self.eps = float(alpha), float(eps)
        self.max_priority = 1.0

    def added(self, pos: int | np.ndarray) -> None:
        """New transitions at flat index ``pos`` (one, or a step's of every slot) get the largest ``p^α``."""
        self.sum_tree.update(pos, self.max_priority)
        self.min_tree.update(pos, self.max_priority)

    def sample(self, rs: np.random.RandomState, batch_size: int, beta: float) -> tuple[np.ndarray, np.ndarray]:
        """(positions, float32 importance weights) of one minibatch, drawn from ``rs``."""
        total = self.sum_tree.total()
        segment = total / batch_size
        values = (np.arange(batch_size) + rs.random_sample(batch_size)) * segment
        flat = self.sum_tree.find_prefixsum_idx(values)
        probs = self.sum_tree.get(flat) / total
        min_prob = self.min_tree.min() / total
        weights = (probs / min_prob) ** (-beta)
        return flat, weights.astype(np.float32)

    def leaves(self) -> np.ndarray:
        """Every position's ``p^α`` (0 where nothing is stored yet), float64 ``[capacity]``."""
        return self.sum_tree.tree[self.sum_tree.size:self.sum_tree.size + self.sum_tree.capacity].copy()

    def update(self, indices: np.ndarray, td_errors: np.ndarray) -> None:
        """``p = |δ| + eps`` stored as ``p^α`` (``td_errors``: |δ|, float32 as the single run hands them)."""
        prio = (np.abs(np.asarray(td_errors, dtype=np.float64)) + self.eps) ** self.alpha
        self.sum_tree.update(indices, prio)
        self.min_tree.update(indices, prio)
        self.max_priority = max(self.max_priority, float(prio.max()))

    def state(self) -> dict[str, Any]:
        return {"sum": th.from_numpy(self.sum_tree.tree.copy()), "min": th.from_numpy(self.min_tree.tree.copy()),
                "max": self.max_priority}

    def load_state(self, state: dict[str, Any]) -> None:
        self.sum_tree.tree[:] = np.asarray(state["sum"])
        self.min_tree.tree[:] = np.asarray(state["min"])
        self.max_priority = float(state["max"])

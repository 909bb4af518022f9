"""The DQN family for K runs at once: SB3's DQN update and its variants, written out with a leading run axis.

``algo`` is a registry name: ``dqn`` (the target network's argmax), ``ddqn`` (the online network's),
``dueling`` (double DQN with the dueling head), ``per`` (double DQN with proportional prioritised replay,
one :class:`~.replay.RunPriorities` per run); or one name per run, of one :func:`batch_group`: ``dqn`` and
``ddqn`` runs share a batch (one network shape; each run takes its own target). Run k starts from the weights
SB3's DQN gets with seed k (the dueling policy of :mod:`..q_networks` for ``dueling``), draws its ε-greedy
decisions, random actions and replay indices from its own streams in SB3's order, and has its own learning rate,
γ and ε schedule; the network shape, batch size, buffer size, ``learning_starts``, target interval, gradient clip
and TD loss (:data:`LOSSES`) are the batch's. On CPU a DQN run equals SB3's ``DQN`` bit for bit, and every
variant SB3's update with the variant written in (``tests/rl/reference.py``, ``tests/rl/test_batched_learners.py``;
on the set observation to float tolerance, ``tests/rl/test_batched_set.py``: the set encoder comes first,
:mod:`.set_encoder`); the variants' golden files were frozen from SB3's loop
(``tests/experiments/test_golden_runs.py``).
Prioritised replay keeps its trees on the host: its TD errors come back from the device once per update. With
device streams (the lockstep loop) its priorities live on the device instead (:meth:`BatchedDQN.sample_on_device`).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.utils import LinearSchedule
from torch import nn
from torch.nn import functional as F

from lanefree_sumo.rl.algorithms.batched.learner import BatchedLearner, SpacesEnv, kept_random_state, per_run
from lanefree_sumo.rl.algorithms.batched.replay import RunPriorities
from lanefree_sumo.rl.algorithms.batched.set_encoder import Encoded, SetLayout, encode, encode_backward
from lanefree_sumo.rl.algorithms.batched.stack import (
    Linear,
    ParamStack,
    Products,
    StackedAdam,
    aten,
    hard_update,
    mlp_backward,
    mlp_forward,
    per_run_column,
)
from lanefree_sumo.rl.encoder import SetFeaturesExtractor

FAMILY = ("dqn", "ddqn", "dueling", "per")
NO_REDUCTION = 0
"""torch's ``Reduction::None`` (the loss gradient: ``smooth_l1_loss_backward``)."""
HUBER_BETA = 1.0
"""``F.smooth_l1_loss``'s default β, which SB3's DQN uses."""
LOSSES: tuple[str, ...] = ("huber", "squared")
"""The TD losses (``train.dqn.loss``): SB3's Huber (smooth L1, β = 1) or Keras-RL's ½·δ²."""


def batch_group(algo: str) -> str:
    """The algorithm whose batches runs of ``algo`` join: ``dqn`` for dqn and ddqn (the same network, their
    targets differ), else ``algo`` itself."""
    return "dqn" if algo in ("dqn", "ddqn") else algo


class _QNet:
    """K Q-networks on a :class:`ParamStack`: a plain MLP, or the dueling head (ReLU trunk, then
    ``V + A − mean_a A``), forward and backward written out with the kernels autograd calls for them; on the set
    observation (``layout``) the set encoder (:mod:`.set_encoder`) comes first, its tensors at the stack's
    head."""

    def __init__(self, stack: ParamStack, dueling: bool, layout: SetLayout | None = None) -> None:
        self.stack, self.dueling, self.layout = stack, dueling, layout

    def forward(self, mm: Products, x: th.Tensor,
                dense: bool = False) -> tuple[tuple[list[Encoded] | None, list[th.Tensor]], th.Tensor]:
        """((what :meth:`backward` needs: the encoder's saved values, the head's inputs and outputs), Q-values
        ``[K, M, actions]``) of observations ``[K, M, obs]``; ``dense``: :func:`~.set_encoder.encode`'s."""
        saved = None
        if self.layout is not None:
            x, saved = encode(mm, self.layout, self.stack.views(), x, dense)
        layers = self.stack.layers()
        if not self.dueling:
            outs = mlp_forward(mm, layers, x, False)
            return (saved, outs), outs[-1]
        outs = [x]
        for layer in layers[:-2]:
            x = th.relu(mm.linear(x, layer))
            outs.append(x)
        value = mm.linear(x, layers[-2])
        advantage = mm.linear(x, layers[-1])
        return (saved, outs), value + advantage - advantage.mean(dim=2, keepdim=True)

    def backward(self, mm: Products, state: tuple[list[Encoded] | None, list[th.Tensor]],
                 grad_q: th.Tensor) -> list[th.Tensor]:
        """Gradients of the stack's tensors (in order: the encoder's, then the head's) given the Q-values'
        gradient."""
        saved, outs = state
        to_input = saved is not None
        layers: list[Linear] = self.stack.layers()
        if not self.dueling:
            grads, grad_input = mlp_backward(mm, layers, outs, grad_q, False, to_input=to_input)
        else:
            hidden = outs[-1]
            value, advantage = layers[-2], layers[-1]
            grad_mean = (-grad_q).sum(dim=2, keepdim=True)
            grad_value = grad_q.sum(dim=2, keepdim=True)
            grad_advantage = grad_q + grad_mean.expand(grad_q.shape) / grad_q.shape[2]
            grads_value = [mm.weight_grad(grad_value, hidden), grad_value.sum(1)]
            grads_advantage = [mm.weight_grad(grad_advantage, hidden), grad_advantage.sum(1)]
            grad_hidden = mm.input_grad(grad_value, value[0]) + mm.input_grad(grad_advantage, advantage[0])
            grads_trunk: list[th.Tensor] = []
            grad_input = grad_hidden
            if len(layers) > 2:
                grad_hidden = aten.threshold_backward(grad_hidden, hidden, 0)
                grads_trunk, grad_input = mlp_backward(mm, layers[:-2], outs, grad_hidden, False, to_input=to_input)
            grads = [*grads_trunk, *grads_value, *grads_advantage]
        if saved is None or self.layout is None:
            return grads
        assert grad_input is not None
        return [*encode_backward(mm, self.layout, self.stack.views(), saved, grad_input), *grads]


class BatchedDQN(BatchedLearner):
    """DQN, double DQN, dueling double DQN or PER double DQN (``algo``) for K runs; module docstring.

    Per run (one number for all or one per run): ``learning_rate``, ``gamma``, ``exploration_fraction``,
    ``exploration_initial_eps``, ``exploration_final_eps``. The batch's: the rest, as SB3's DQN names them
    (``max_grad_norm``: ``inf`` for no clip; ``loss``: :data:`LOSSES`, SB3's Huber or Keras-RL's ½·δ²;
    ``per_alpha``, ``per_beta0``, ``per_eps``: the prioritised replay's, :class:`~.replay.RunPriorities`;
    ``encoder``: the set encoder's name for the set observation (a Dict observation space; :mod:`.set_encoder`),
    None for the vector observation)."""

    def __init__(self, algo: str | Sequence[str], observation_space: spaces.Space, action_space: spaces.Space,
                 seeds: Sequence[int], *, learning_rate: float | Sequence[float] = 1e-3,
                 gamma: float | Sequence[float] = 0.98, layers: Sequence[int] = (128, 64), batch_size: int = 64,
                 buffer_size: int = 50_000, learning_starts: int = 800, target_update_interval: int = 10_000,
                 exploration_fraction: float | Sequence[float] = 0.1,
                 exploration_initial_eps: float | Sequence[float] = 1.0,
                 exploration_final_eps: float | Sequence[float] = 0.05, max_grad_norm: float = 10.0,
                 loss: str = "huber", total_timesteps: int = 1, per_alpha: float = 0.6, per_beta0: float = 0.4,
                 per_eps: float = 1e-6, encoder: str | None = None,
                 device: str = "cpu", exact: bool | None = None, slots: int = 1) -> None:
        algos = [algo] * len(seeds) if isinstance(algo, str) else list(algo)
        for name in algos:
            if name not in FAMILY:
                raise ValueError(f"unknown DQN variant '{name}'; choose one of {', '.join(FAMILY)}")
        if len(algos) != len(seeds) or len({batch_group(a) for a in algos}) != 1:
            raise ValueError(f"one DQN variant per run, all of one batch group (dqn and ddqn may mix); got {algos} "
                             f"for {len(seeds)} run(s)")
        if not isinstance(action_space, spaces.Discrete):
            raise ValueError("batched DQN takes a Discrete action space")
        if loss not in LOSSES:
            raise ValueError(f"unknown TD loss {loss!r}; valid: {', '.join(LOSSES)}")
        if (encoder is None) != isinstance(observation_space, spaces.Box):
            raise ValueError("the set observation (a Dict space) takes an encoder, the vector observation none")
        super().__init__(observation_space, action_space, seeds, batch_size=batch_size, buffer_size=buffer_size,
                         learning_starts=learning_starts, total_timesteps=total_timesteps, action_dim=1,
                         action_dtype=th.int64, device=device, exact=exact, slots=slots)
        from lanefree_sumo.rl.algorithms import get_algorithm

        k = self.runs
        self.algos = algos
        """Each run's variant."""
        self.specs = [get_algorithm(a) for a in algos]
        """Each run's registry entry (its target, its network, the class of its ``model.zip``)."""
        double = [spec.double_q for spec in self.specs]
        self.double_q = all(double)
        """Every run takes the double-Q target (none does where False and :attr:`_double` is None)."""
        self._double = (th.tensor(double, device=self.device).view(k, 1, 1) if len(set(double)) > 1 else None)
        """Where the runs differ (dqn and ddqn in one batch): ``[K, 1, 1]`` True for a double-Q run."""
        self.learning_rate, self.gamma = per_run(learning_rate, k, "learning_rate"), per_run(gamma, k, "gamma")
        self.exploration = [LinearSchedule(start, end, fraction) for start, end, fraction in zip(
            per_run(exploration_initial_eps, k, "exploration_initial_eps"),
            per_run(exploration_final_eps, k, "exploration_final_eps"),
            per_run(exploration_fraction, k, "exploration_fraction"))]
        self.exploration_rate = [0.0] * k  # SB3's value before its first _on_step
        self.layers, self.max_grad_norm, self.loss = tuple(layers), float(max_grad_norm), loss
        self.target_update_interval = int(target_update_interval)
        self.per_alpha, self.per_beta0, self.per_eps = float(per_alpha), float(per_beta0), float(per_eps)
        self.encoder = encoder
        policies = []
        for spec, seed, lr in zip(self.specs, self.seeds, self.learning_rate):
            policy_class = spec.policy(self._policy_name)
            with th.random.fork_rng(devices=[]):  # as DQN._setup_model builds it after set_random_seed(seed)
                th.manual_seed(seed)
                policies.append(policy_class(observation_space, action_space, lambda _, lr=lr: lr,
                                             **self._policy_kwargs()))
        self.dueling = type(policies[0].q_net.q_net) is not nn.Sequential
        self.layout: SetLayout | None = None
        """The set observation's layout (None: the vector observation)."""
        if encoder is not None:
            extractor = policies[0].q_net.features_extractor
            assert isinstance(extractor, SetFeaturesExtractor)
            self.layout = SetLayout.of(extractor.encoder, int(observation_space["ego"].shape[0]),  # type: ignore
                                       int(observation_space["others"].shape[0]))  # type: ignore[index]
        head = 0 if self.layout is None else self.layout.tensors
        self.q_net, self.q_net_target = (
            _QNet(ParamStack([list(getattr(p, name).parameters()) for p in policies], self.device, head),
                  self.dueling, self.layout) for name in ("q_net", "q_net_target"))
        group = policies[0].optimizer.param_groups[0]
        self.adam = StackedAdam(self.q_net.stack, self.learning_rate, group["betas"], group["eps"])
        self._gamma = per_run_column(self.gamma, self.device).unsqueeze(2)
        self._mean_grad = th.full((k, self.batch_size, 1), 1.0 / self.batch_size, device=self.device)
        self._one = th.tensor(1.0, device=self.device)
        self._n_calls = 0
        self.priorities = ([RunPriorities(self.replay.capacity * self.slots, per_alpha, per_eps) for _ in range(k)]
                           if self.specs[0].prioritized else [])

    @property
    def _policy_name(self) -> str:
        return "MlpPolicy" if self.encoder is None else "MultiInputPolicy"

    def _policy_kwargs(self) -> dict[str, Any]:
        """SB3's ``policy_kwargs`` of ``build_model``'s DQN: the layer widths, ReLU, and the set encoder."""
        kwargs: dict[str, Any] = {"net_arch": list(self.layers), "activation_fn": nn.ReLU}
        if self.encoder is not None:
            kwargs.update(features_extractor_class=SetFeaturesExtractor,
                          features_extractor_kwargs={"encoder": self.encoder})
        return kwargs

    def optimisers(self) -> list[StackedAdam]:
        return [self.adam]

    def _q(self, obs: th.Tensor) -> tuple[tuple[list[Encoded] | None, list[th.Tensor]], th.Tensor]:
        """The online network's forward pass on observations ``[K, M, obs]``."""
        return self.q_net.forward(self.mm, obs, self.dense)

    # -- acting -----------------------------------------------------------------------------------------------

    def q_values(self, obs: np.ndarray | th.Tensor) -> th.Tensor:
        """Q(s, ·) of every run's slots, ``[K · slots, actions]`` (obs ``[K · slots, obs]``)."""
        with th.no_grad():
            return self._q(self._obs(obs))[1].reshape(self.rows, -1)

    def act(self, obs: np.ndarray, explore: bool = True) -> np.ndarray:
        """Every run's actions ``[K · slots]`` (SB3's ``_sample_action``: random before ``learning_starts``, then
        ε-greedy with the run's ε, one draw for all its slots as SB3's ``predict`` draws it; without ``explore``
        the greedy action)."""
        m = self.slots
        actions = np.zeros(self.rows, dtype=np.int64)
        greedy = np.ones(self.rows, dtype=bool)
        if explore:
            warm_up = self.num_timesteps < self.learning_starts
            for k, (rs, space) in enumerate(zip(self.streams.numpy, self.streams.spaces)):
                if warm_up or rs.rand() < self.exploration_rate[k]:
                    actions[k * m:(k + 1) * m] = [space.sample() for _ in range(m)]
                    greedy[k * m:(k + 1) * m] = False
        if greedy.any():
            best = self.q_values(obs).argmax(dim=1).cpu().numpy()
            actions[greedy] = best[greedy]
        return actions

    def use_device_streams(self, generator: th.Generator | None) -> None:
        super().use_device_streams(generator)
        d = self.device
        start, end, fraction = (th.tensor([getattr(s, name) for s in self.exploration], dtype=th.float64).to(d)
                                for name in ("start", "end", "end_fraction"))
        self._eps = (start, end, fraction)
        if self.priorities:  # the trees' leaves (p^α; 0 where nothing is stored) and the largest p^α so far
            self._leaves = th.as_tensor(np.stack([p.leaves() for p in self.priorities])).to(d)
            self._max_leaf = th.tensor([p.max_priority for p in self.priorities], dtype=th.float64).to(d)
            self._strata = th.arange(self.batch_size, dtype=th.float64).to(d)
            self._slots = th.arange(self.buffer_size).to(d)

    def store_on_device(self, obs: th.Tensor, action: th.Tensor, reward: th.Tensor, next_obs: th.Tensor) -> None:
        if self.priorities:  # a new transition gets the largest p^α so far (RunPriorities.added)
            self._leaves.index_copy_(1, self._pos.reshape(1), self._max_leaf.unsqueeze(1))
        super().store_on_device(obs, action, reward, next_obs)

    def sample_on_device(self) -> tuple[th.Tensor, ...]:
        """The gradient step's arguments: uniform indices, or with prioritised replay (indices, weights) drawn as
        :meth:`RunPriorities.sample` draws them (one uniform number per stratum of the total mass, the leaf whose
        running sum first exceeds it, weights ``(P / P_min)^-β`` with β at the device's step count), the running
        sum taken over the leaves at each draw instead of read from a sum tree."""
        if not self.priorities:
            return super().sample_on_device()
        leaves = self._leaves
        running = th.cumsum(leaves, dim=1)
        total = running[:, -1:]
        values = (self._strata + self._rand(self.runs, self.batch_size)) * (total / self.batch_size)
        last = self._size.long() - 1  # values at or past the total (rounding): the last stored leaf, as the tree
        indices = th.minimum(th.searchsorted(running, values, right=True), last)
        stored = self._slots < self._size
        smallest = leaves.masked_fill(~stored, float("inf")).amin(dim=1, keepdim=True)
        beta = self.per_beta0 + (1.0 - self.per_beta0) * th.clamp(self._count / float(self.total_timesteps), 0.0, 1.0)
        weights = (leaves.gather(1, indices) / smallest) ** (-beta)
        return indices, weights.float().unsqueeze(2)

    def device_state(self) -> dict[str, Any]:
        if not self.priorities:
            return super().device_state()
        return {**super().device_state(), "leaves": self._leaves.cpu(), "max_leaf": self._max_leaf.cpu()}

    def load_device_state(self, state: dict[str, Any]) -> None:
        super().load_device_state(state)
        if self.priorities:
            self._leaves.copy_(state["leaves"])
            self._max_leaf.copy_(state["max_leaf"])

    def act_on_device(self, obs: th.Tensor, random: bool) -> tuple[th.Tensor, th.Tensor]:
        """:meth:`act` (exploring) with device streams: (the env's actions ``[K]``, the buffer's ``[K, 1]``); ε from
        the run's schedule at the device's step count (SB3's ``LinearSchedule``)."""
        n = int(self.action_space.n)  # type: ignore[attr-defined]
        draws = self._rand(self.runs, 2)
        uniform = th.clamp((draws[:, 1] * n).long(), max=n - 1)
        if random:
            actions = uniform
        else:
            start, end, fraction = self._eps
            done = self._count / float(self.total_timesteps)
            eps = th.where(done > fraction, end, start + done * (end - start) / fraction)
            eps = eps * (self._count > 0)  # SB3's ε is 0 before its first _on_step
            greedy = self._q(self._obs(obs))[1].reshape(self.runs, -1).argmax(dim=1)
            actions = th.where(draws[:, 0] < eps, uniform, greedy)
        return actions, actions.reshape(self.runs, 1)

    def _buffer_actions(self, action: np.ndarray) -> np.ndarray:
        return np.asarray(action).reshape(self.rows, 1)

    def _stored(self, pos: int) -> None:
        flat = np.arange(pos * self.slots, (pos + 1) * self.slots)  # the step's transitions, one per slot
        for priorities in self.priorities:
            priorities.added(flat)

    def _on_step(self) -> None:
        """SB3's DQN ``_on_step``: the target copied every ``target_update_interval`` timesteps (every
        ``target_update_interval // slots`` steps), ε from the schedule."""
        self._n_calls += 1
        if self._n_calls % max(self.target_update_interval // self.slots, 1) == 0:
            hard_update(self.q_net_target.stack, self.q_net.stack)
        self.exploration_rate = [schedule(self.progress_remaining) for schedule in self.exploration]

    def per_beta(self) -> float:
        """The importance-sampling exponent now: β0 → 1 linearly over training (:class:`~.replay.RunPriorities`)."""
        fraction = min(max(1.0 - float(self.progress_remaining), 0.0), 1.0)
        return self.per_beta0 + (1.0 - self.per_beta0) * fraction

    # -- the update -------------------------------------------------------------------------------------------

    def _sample(self) -> tuple[np.ndarray, th.Tensor | None]:
        """Every run's minibatch positions ``[K, batch]`` and, with prioritised replay, loss weights."""
        if not self.priorities:
            return self.streams.sample_indices(self.replay.size(), self.batch_size, self.slots), None
        beta = self.per_beta()
        drawn = [p.sample(rs, self.batch_size, beta) for p, rs in zip(self.priorities, self.streams.numpy)]
        indices = np.stack([d[0] for d in drawn])
        weights = th.from_numpy(np.stack([d[1] for d in drawn])).to(self.device).unsqueeze(2)
        return indices, weights

    def _update(self) -> None:
        self._learn(*self._sample())

    def _learn(self, indices: np.ndarray | th.Tensor, weights: th.Tensor | None = None) -> None:
        mm = self.mm
        obs, actions, next_obs, dones, rewards = self.replay.gather(indices)
        with th.no_grad():
            target_next = self.q_net_target.forward(mm, next_obs, self.dense)[1]
            if self._double is not None:  # dqn and ddqn runs: both targets, each run takes its own
                next_actions = self._q(next_obs)[1].argmax(dim=2, keepdim=True)
                next_q = th.where(self._double, th.gather(target_next, dim=2, index=next_actions),
                                  target_next.max(dim=2, keepdim=True)[0])
            elif self.double_q:
                next_actions = self._q(next_obs)[1].argmax(dim=2, keepdim=True)
                next_q = th.gather(target_next, dim=2, index=next_actions)
            else:
                next_q = target_next.max(dim=2, keepdim=True)[0]
            target_q = rewards + (1 - dones) * self._gamma * next_q

            outs, q_values = self._q(obs)
            index = actions.long()
            current_q = th.gather(q_values, dim=2, index=index)
            loss, grad_current = self._loss(current_q, target_q, weights)
            grad_q = th.zeros_like(q_values).scatter_add_(2, index, grad_current)  # the gather's backward
            grads = self.q_net.backward(mm, outs, grad_q)
            # clip_grad_norm_(max_grad_norm) per run, as torch computes it
            norms = th.stack([th.linalg.vector_norm(g.reshape(self.runs, -1), 2.0, dim=1) for g in grads], dim=1)
            total_norm = th.linalg.vector_norm(norms, 2.0, dim=1)
            scale = th.clamp(self.max_grad_norm / (total_norm + 1e-6), max=1.0)
            for g in grads:
                g.mul_(scale.view(self.runs, *([1] * (g.dim() - 1))))
            self.adam.step(grads)
        self.losses = {"loss": loss}
        if self.priorities:
            td_errors = (target_q - current_q).reshape(self.runs, -1).abs()
            if self.device_streams:  # RunPriorities.update on the device's leaves (a position drawn twice in the
                # minibatch keeps one of its two new priorities: on a GPU either, in the host trees the last)
                assert isinstance(indices, th.Tensor)
                leaves = (td_errors.double() + self.per_eps) ** self.per_alpha
                self._leaves.scatter_(1, indices, leaves)
                self._max_leaf.copy_(th.maximum(self._max_leaf, leaves.amax(dim=1)))
                return
            for priorities, idx, td in zip(self.priorities, indices, td_errors.cpu().numpy()):
                priorities.update(idx, td)

    def _loss(self, current_q: th.Tensor, target_q: th.Tensor,
              weights: th.Tensor | None) -> tuple[th.Tensor, th.Tensor]:
        """(loss per run ``[K]``, its gradient with respect to ``current_q``) as the single run computes them:
        the mean over the batch as each element's 1/n (the mean reduction's backward, per run), the weighted
        mean's expand / n and product g · w; the squared loss's ½ on the gradient (autograd's for
        ``0.5 · mse_loss``)."""
        if self.loss == "squared":
            per_sample = 0.5 * F.mse_loss(current_q, target_q, reduction="none")
            if weights is None:  # 2/n · δ · ½ of the mean reduction equals 2 · δ · (½ / n): both scale by powers of 2
                grad = aten.mse_loss_backward(self._mean_grad * 0.5, current_q, target_q, NO_REDUCTION)
                return 0.5 * F.mse_loss(current_q, target_q, reduction="none").mean(dim=(1, 2)), grad
            grad_mean = self._one.expand(per_sample.shape) / self.batch_size
            grad = aten.mse_loss_backward(grad_mean * weights * 0.5, current_q, target_q, NO_REDUCTION)
            return (weights * per_sample).mean(dim=(1, 2)), grad
        per_sample = F.smooth_l1_loss(current_q, target_q, reduction="none")
        if weights is None:
            grad = aten.smooth_l1_loss_backward(self._mean_grad, current_q, target_q, NO_REDUCTION, HUBER_BETA)
            return per_sample.mean(dim=(1, 2)), grad
        grad_mean = self._one.expand(per_sample.shape) / self.batch_size
        grad = aten.smooth_l1_loss_backward(grad_mean * weights, current_q, target_q, NO_REDUCTION, HUBER_BETA)
        return (weights * per_sample).mean(dim=(1, 2)), grad

    # -- checkpoint and export --------------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        return {**super().state_dict(), "q_net": self.q_net.stack.flat, "q_net_target": self.q_net_target.stack.flat,
                "adam": self.adam.state_dict(), "n_calls": self._n_calls,
                "exploration_rate": list(self.exploration_rate),
                "priorities": [p.state() for p in self.priorities]}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        self.q_net.stack.flat.copy_(state["q_net"])
        self.q_net_target.stack.flat.copy_(state["q_net_target"])
        self.adam.load_state_dict(state["adam"])
        self._n_calls = int(state["n_calls"])
        self.exploration_rate = [float(e) for e in state["exploration_rate"]]
        for priorities, saved in zip(self.priorities, state["priorities"]):
            priorities.load_state(saved)

    def sb3_model(self, k: int) -> Any:
        """Run k as a model of SB3's ``DQN`` (the class of its ``model.zip``; the dueling network's policy for
        ``dueling``): its hyperparameters, networks, Adam state, step counts and ε. The TD target, loss and replay
        of its variant are the batched learner's (SB3's ``DQN`` trains a plain DQN)."""
        schedule = self.exploration[k]
        with kept_random_state():
            model = self.specs[k].cls(self.specs[k].policy(self._policy_name),
                                      SpacesEnv(self.observation_space, self.action_space),
                                      learning_rate=self.learning_rate[k], buffer_size=self.buffer_size,
                                      batch_size=self.batch_size, gamma=self.gamma[k],
                                      learning_starts=self.learning_starts,
                                      target_update_interval=self.target_update_interval,
                                      exploration_initial_eps=schedule.start, exploration_final_eps=schedule.end,
                                      exploration_fraction=schedule.end_fraction, max_grad_norm=self.max_grad_norm,
                                      train_freq=1, gradient_steps=1, seed=self.seeds[k], device="cpu", verbose=0,
                                      policy_kwargs=self._policy_kwargs())
        with th.no_grad():
            for net, stack in ((model.q_net, self.q_net.stack), (model.q_net_target, self.q_net_target.stack)):
                for p, value in zip(net.parameters(), stack.row(k)):
                    p.copy_(value)
        if self.adam.steps:
            state = model.policy.optimizer.state_dict()
            state["state"] = self.adam.sb3_state(k, list(model.q_net.parameters()))
            model.policy.optimizer.load_state_dict(state)
        model.num_timesteps, model._n_updates = self.num_timesteps, self.n_updates
        model.exploration_rate = self.exploration_rate[k]
        for key, value in self._choices(k).items():
            setattr(model, key, value)
        return model

    def _choices(self, k: int) -> dict[str, Any]:
        """Run k's choices SB3's ``DQN`` lacks, kept as attributes of its exported model (``model.zip`` records
        them; SB3 itself trains a plain DQN): the TD loss, the double-Q target, and prioritised replay's α, β₀, ε."""
        spec = self.specs[k]
        per = {"per_alpha": self.per_alpha, "per_beta0": self.per_beta0, "per_eps": self.per_eps}
        return {"loss": self.loss, "double_q": spec.double_q, **(per if spec.prioritized else {})}

    def export(self, k: int, path: str | Path) -> None:
        """Write run k as an ordinary ``model.zip`` (``stable_baselines3.DQN.load`` loads it)."""
        self.sb3_model(k).save(path)

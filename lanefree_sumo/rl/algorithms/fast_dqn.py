"""The DQN family's update as Stable-Baselines3 computes it, with less overhead: the same parameters, bit for bit.

:class:`FastDQN` is SB3's :class:`~stable_baselines3.DQN` (same constructor, ``save``/``load`` both ways,
callbacks, TensorBoard, replay buffer, resume) whose :meth:`~FastDQN.train` computes exactly SB3's gradient
step, and the base of the project's :class:`~.double_dqn.DoubleDQN`, :class:`~.dueling.DuelingDoubleDQN` and
:class:`~.prioritized.PrioritizedDoubleDQN`, whose steps it computes the same way:

* the TD target ``r + γ (1 − d) Q'(s', a*)`` with ``a*`` the target's argmax (DQN) or the online network's
  (double DQN), the Huber loss (mean, or the importance-weighted mean of prioritised replay), one Adam step
  after clipping the gradient norm at ``max_grad_norm``; the target copied every ``target_update_interval``
  steps by SB3's own ``_on_step``;
* the same replay draws (the same numpy calls in the same order) and the same ε-greedy draws.

How (``tests/rl/test_fast_dqn.py`` compares every parameter, the target, the Adam state and both random
streams with ``torch.equal`` after many steps, and whole ``learn`` calls with callbacks):

* plain MLP Q-networks and the dueling head on a flat Box observation: forward and backward written out
  with the kernels autograd calls (:mod:`.lean`; ``smooth_l1_loss_backward``, the gather's
  ``scatter_add`` into zeros, the dueling mean's ``expand / n``), no graph, no module calls;
* the gradient-norm clip as ``clip_grad_norm_`` computes it (``_foreach_norm``, the norm of the norms,
  ``_foreach_mul_`` by ``min(max_norm / (norm + 1e-6), 1)``); Adam as :class:`~.lean.LeanAdam`;
* the ε-greedy action with the Q-network written out instead of ``predict`` (:class:`~.lean.LeanCollector`).

``fast_learner=False`` runs the autograd update (SB3's ``DQN.train`` split into hooks), and so does
anything the written-out path does not cover (another extractor, e.g. the set encoder, a Dict observation,
another device or replay buffer, a network, policy or hook that a subclass overrides).
Another optimiser than a plain Adam keeps the written-out gradients but steps itself.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3 import DQN
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.torch_layers import FlattenExtractor
from stable_baselines3.common.type_aliases import ReplayBufferSamples
from stable_baselines3.dqn.policies import DQNPolicy, QNetwork
from torch import nn
from torch.nn import functional as F

from lanefree_sumo.rl.algorithms.lean import (
    MEAN,
    Layer,
    LeanAdam,
    LeanCollector,
    aten,
    backward,
    defined_by,
    flatten_parameters,
    forward,
    mean_of,
    mlp_layers,
)
from lanefree_sumo.rl.algorithms.q_networks import DuelingHead, DuelingQNetwork

NO_REDUCTION = 0
"""torch's ``Reduction::None``, the reduction argument of ``smooth_l1_loss_backward``."""
HUBER_BETA = 1.0
"""``F.smooth_l1_loss``'s default β, which SB3's DQN uses."""


LOSSES: tuple[str, ...] = ("huber", "squared")
"""The TD losses (``train.dqn.loss``): SB3's Huber (smooth L1, β = 1) or Keras-RL's ½·δ²."""


def _squared_loss(one: th.Tensor, current_q: th.Tensor, target_q: th.Tensor,
                  weights: th.Tensor | None) -> tuple[th.Tensor, th.Tensor]:
    """(loss, its gradient with respect to ``current_q``) of ``0.5 · mse`` — or of ``mean_i(w_i · ½δ_i²)`` with
    ``weights`` — with the kernels autograd calls for :meth:`FastDQN._compute_loss`'s expression (the
    product's ``g · 0.5``, then ``mse_loss_backward``)."""
    if weights is None:
        loss = 0.5 * F.mse_loss(current_q, target_q)
        return loss, aten.mse_loss_backward(one * 0.5, current_q, target_q, MEAN)
    per_sample = 0.5 * F.mse_loss(current_q, target_q, reduction="none")
    weights = weights.reshape(per_sample.shape)
    loss = (weights * per_sample).mean()
    grad_mean = one.expand(per_sample.shape) / per_sample.numel()
    return loss, aten.mse_loss_backward(grad_mean * weights * 0.5, current_q, target_q, NO_REDUCTION)


class _MlpQ:
    """A plain ``Sequential(Linear, ReLU, …, Linear)`` Q-network, written out."""

    def __init__(self, layers: list[Layer]) -> None:
        self.layers = layers

    def forward(self, x: th.Tensor) -> tuple[list[th.Tensor], th.Tensor]:
        """(what :meth:`backward` needs, Q-values (batch, actions))."""
        outs = forward(self.layers, x, False)
        return outs, outs[-1]

    def backward(self, outs: list[th.Tensor], grad_q: th.Tensor) -> list[th.Tensor]:
        """Gradients of the parameters in module order, given the gradient of the Q-values."""
        return backward(self.layers, outs, grad_q, False)[0]


class _DuelingQ:
    """The dueling head (:class:`~.q_networks.DuelingHead`): a ReLU trunk, then ``V + A − mean_a A``, written out."""

    def __init__(self, trunk: list[Layer], value: Layer, advantage: Layer) -> None:
        self.trunk, self.value, self.advantage = trunk, value, advantage

    def forward(self, x: th.Tensor) -> tuple[list[th.Tensor], th.Tensor]:
        outs = [x]
        for _, weight_t, bias in self.trunk:
            x = th.relu(th.addmm(bias, x, weight_t))
            outs.append(x)
        value = th.addmm(self.value[2], x, self.value[1])
        advantage = th.addmm(self.advantage[2], x, self.advantage[1])
        return outs, value + advantage - advantage.mean(dim=1, keepdim=True)

    def backward(self, outs: list[th.Tensor], grad_q: th.Tensor) -> list[th.Tensor]:
        """Autograd's formulas for ``(v + a) − mean(a)``: the subtraction's ``−g`` summed to (batch, 1) and
        the mean's ``expand / n``; the addition's ``g`` summed to (batch, 1) for V and ``g`` for A."""
        hidden = outs[-1]
        grad_mean = (-grad_q).sum(dim=1, keepdim=True)
        grad_value = grad_q.sum(dim=1, keepdim=True)
        grad_advantage = grad_q + grad_mean.expand(grad_q.shape) / grad_q.shape[1]
        grads_value = [grad_value.t().mm(hidden), grad_value.sum(0)]
        grads_advantage = [grad_advantage.t().mm(hidden), grad_advantage.sum(0)]
        grad_hidden = grad_value.mm(self.value[0]) + grad_advantage.mm(self.advantage[0])
        if self.trunk:
            grad_hidden = aten.threshold_backward(grad_hidden, hidden, 0)
            grads_trunk = backward(self.trunk, outs, grad_hidden, False)[0]
        else:
            grads_trunk = []
        return [*grads_trunk, *grads_value, *grads_advantage]


def _stock_methods(model: FastDQN) -> bool:
    """What the written-out path replaces is SB3's or :class:`FastDQN`'s own: the action (``_sample_action``,
    ``predict``, the policy's ``_predict``/``predict``: the lean loop), the Q-network classes, the hooks the
    written-out step computes itself (``_compute_target_q_values``, ``_compute_loss``) and the autograd update
    it stands in for (``_autograd_train``). Checked on every use (a patch after the first update counts)."""
    return (defined_by(model, "predict") is DQN and defined_by(model, "_sample_action") is OffPolicyAlgorithm
            and defined_by(model.policy, "_predict") is DQNPolicy
            and defined_by(model.policy, "predict") is BasePolicy
            and all(type(net) in (QNetwork, DuelingQNetwork) for net in (model.q_net, model.q_net_target))
            and all(defined_by(model, name) is FastDQN
                    for name in ("_compute_target_q_values", "_compute_loss", "_autograd_train")))


def _q_head(net: nn.Module) -> _MlpQ | _DuelingQ | None:
    """The written-out form of a QNetwork's ``q_net`` (a plain MLP or a dueling head), or None."""
    if isinstance(net, nn.Sequential):
        layers = mlp_layers(net, False)
        return None if layers is None else _MlpQ(layers)
    if type(net) is not DuelingHead:
        return None
    modules = list(net.trunk)
    if len(modules) % 2 or any(type(m) is not (nn.Linear if k % 2 == 0 else nn.ReLU) for k, m in enumerate(modules)):
        return None
    linears = [m for m in modules if isinstance(m, nn.Linear)] + [net.value_head, net.advantage_head]
    if any(m.bias is None or m.weight.dtype != th.float32 for m in linears):
        return None
    layers = [(m.weight, m.weight.t(), m.bias) for m in linears]
    return _DuelingQ(layers[:-2], layers[-2], layers[-1])


class _QPlan:
    """What the fast update needs of a model, fetched once; rebuilt when the policy, its optimiser, the
    replay buffer or the VecNormalize wrapper is replaced (``load``, ``load_replay_buffer``)."""

    def __init__(self, model: FastDQN) -> None:
        self.policy = model.policy
        self.replay_buffer = model.replay_buffer
        self.vec_normalize = model._vec_normalize_env
        self.optimizer = model.policy.optimizer
        self.params: list[th.Tensor] = list(model.q_net.parameters())
        self.target_params: list[th.Tensor] = list(model.q_net_target.parameters())
        self.flat = th.empty(0)
        self.online: _MlpQ | _DuelingQ | None = None
        self.target: _MlpQ | _DuelingQ | None = None
        self.written_out = self._written_out(model)
        self.adam = LeanAdam(self.optimizer, self.params, self.flat if self.written_out else None)
        self.one = th.tensor(1.0)

    def _written_out(self, model: FastDQN) -> bool:
        """A flat float32 Box observation through SB3's FlattenExtractor into a plain MLP or dueling head, on
        the CPU, with a float32 replay buffer the model samples itself (:meth:`FastDQN._written_out_buffer`),
        and nothing the written-out path replaces overridden (:func:`_stock_methods`). The optimiser may be
        any: :class:`~.lean.LeanAdam` lets any but a plain Adam step itself."""
        rb, space = model.replay_buffer, model.observation_space
        if not (model.device.type == "cpu" and model._vec_normalize_env is None and isinstance(space, spaces.Box)
                and len(space.shape) == 1 and isinstance(model.action_space, spaces.Discrete)
                and isinstance(rb, ReplayBuffer) and model._written_out_buffer(rb) and not rb.optimize_memory_usage
                and all(a.dtype == np.float32 for a in (rb.observations, rb.next_observations, rb.rewards,
                                                        rb.dones, rb.timeouts))
                and type(model.q_net.features_extractor) is FlattenExtractor
                and type(model.q_net_target.features_extractor) is FlattenExtractor
                and not model.batch_norm_stats and _stock_methods(model)):
            return False
        online, target = _q_head(model.q_net.q_net), _q_head(model.q_net_target.q_net)
        if online is None or target is None or type(online) is not type(target):
            return False
        # one buffer per network (parameters in module order), then the layers again: their transposed views
        # must see the moved weights
        self.flat = flatten_parameters(self.params)
        flatten_parameters(self.target_params)
        self.online, self.target = _q_head(model.q_net.q_net), _q_head(model.q_net_target.q_net)
        return True

    def valid(self, model: FastDQN) -> bool:
        return (self.policy is model.policy and self.replay_buffer is model.replay_buffer
                and self.vec_normalize is model._vec_normalize_env and self.optimizer is model.policy.optimizer
                and (not self.written_out or _stock_methods(model)))


class FastDQN(LeanCollector, DQN):
    """SB3's DQN with the same update computed with less overhead (module docstring); the base of the
    project's DQN variants, which set :attr:`double_q` and override the hooks.

    Hooks, called by both update paths: :meth:`_sample_batch` (data + optional per-sample loss weights),
    :meth:`_after_gradient_step` (receives the TD errors), :meth:`_written_out_buffer`; a subclass that
    overrides :meth:`_compute_target_q_values` or :meth:`_compute_loss` trains through autograd.

    :param fast_learner: False runs the autograd update (:meth:`_autograd_train`: SB3's ``DQN.train`` split
        into the hooks).
    :param lean_loop: collect with the lean loop (SB3's, bit for bit, without the per-step mode switches and
        ``predict``'s generic path); False runs SB3's own.

    All other parameters are :class:`stable_baselines3.DQN`'s."""

    double_q: ClassVar[bool] = False
    """The TD target's next action: the target network's argmax (False, DQN) or the online network's (True)."""
    _fast_plan: _QPlan | None = None

    def __init__(self, *args: Any, fast_learner: bool = True, lean_loop: bool = True, loss: str = "huber",
                 **kwargs: Any) -> None:
        if loss not in LOSSES:
            raise ValueError(f"unknown TD loss {loss!r}; valid: {', '.join(LOSSES)}")
        self.fast_learner = fast_learner
        self.lean_loop = lean_loop
        self.loss = loss
        super().__init__(*args, **kwargs)

    def _excluded_save_params(self) -> list[str]:
        """Never pickled into ``model.zip``: the plan holds the policy, the optimiser and the replay buffer."""
        return [*super()._excluded_save_params(), "_fast_plan"]

    # -- hooks (both update paths call them) -----------------------------------------------------------

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

    def _written_out_buffer(self, buffer: ReplayBuffer) -> bool:
        """The replay buffer is one the written-out update samples: SB3's plain ``ReplayBuffer`` (drawn as
        ``ReplayBuffer.sample`` draws, without copies); a subclass may accept its own (drawn through
        :meth:`_sample_batch`)."""
        return type(buffer) is ReplayBuffer

    # -- the update -------------------------------------------------------------------------------------

    def _plan(self) -> _QPlan | None:
        """The fast update's plan (rebuilt when the model's parts were replaced); None without the fast learner."""
        if not getattr(self, "fast_learner", True):
            return None
        plan = self._fast_plan
        if plan is None or not plan.valid(self):
            plan = self._fast_plan = _QPlan(self)
        return plan

    def _lean_plan(self) -> _QPlan | None:
        """The plan when the lean collection loop applies (a written-out Q-network), else None."""
        plan = self._plan()
        return plan if getattr(self, "lean_loop", True) and plan is not None and plan.written_out else None

    def _lean_action(self, plan: _QPlan, learning_starts: int, action_noise: ActionNoise | None,
                     n_envs: int) -> tuple[np.ndarray, np.ndarray]:
        """SB3's ``_sample_action`` with DQN's ε-greedy ``predict`` (the same draws, in the same order), the
        greedy action from the written-out Q-network."""
        space = self.action_space
        if self.num_timesteps < learning_starts:
            action = np.array([space.sample() for _ in range(n_envs)])
        elif np.random.rand() < self.exploration_rate:
            action = np.array([space.sample() for _ in range(self._last_obs.shape[0])])  # type: ignore[union-attr]
        else:
            assert plan.online is not None
            obs = th.as_tensor(self._last_obs).float().reshape((-1, *self.observation_space.shape))  # type: ignore[misc]
            with th.no_grad():
                q_values = plan.online.forward(obs)[1]
            action = q_values.argmax(dim=1).reshape(-1).numpy()  # SB3 reshapes to (-1, *shape): shape () for Discrete
        return action, action

    def train(self, gradient_steps: int, batch_size: int = 100) -> None:
        plan = self._plan()
        if plan is None or not plan.written_out:
            self._autograd_train(gradient_steps, batch_size)
            return
        if not self._lean_collecting():
            self.policy.set_training_mode(True)
        self._update_learning_rate(self.policy.optimizer)
        losses = [self._written_out_step(plan, batch_size) for _ in range(gradient_steps)]
        self._n_updates += gradient_steps
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/loss", mean_of(losses))

    def _autograd_train(self, gradient_steps: int, batch_size: int) -> None:
        """SB3's ``DQN.train`` through autograd (the same calls and draws; with the default hooks the same
        numbers), split into the hooks."""
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

    def _batch(self, batch_size: int) -> tuple[th.Tensor, th.Tensor, th.Tensor, th.Tensor, th.Tensor, th.Tensor | None]:
        """(observations, actions, next observations, dones, rewards, weights or None) of one minibatch: SB3's
        ``ReplayBuffer.sample`` draws wrapped without copies (when :meth:`_sample_batch` is not overridden), or
        :meth:`_sample_batch`'s."""
        rb = self.replay_buffer
        if type(rb) is ReplayBuffer and defined_by(self, "_sample_batch") is FastDQN:
            upper = rb.buffer_size if rb.full else rb.pos
            batch = np.random.randint(0, upper, size=batch_size)
            env = np.random.randint(0, high=rb.n_envs, size=(batch_size,))
            return (th.from_numpy(rb.observations[batch, env, :]), th.from_numpy(rb.actions[batch, env, :]),
                    th.from_numpy(rb.next_observations[batch, env, :]),
                    th.from_numpy((rb.dones[batch, env] * (1 - rb.timeouts[batch, env])).reshape(-1, 1)),
                    th.from_numpy(rb.rewards[batch, env].reshape(-1, 1)), None)
        data, weights = self._sample_batch(batch_size)
        assert isinstance(data.observations, th.Tensor) and isinstance(data.next_observations, th.Tensor)
        assert data.discounts is None, "the written-out step uses one γ: n-step samples need the autograd update"
        return data.observations, data.actions, data.next_observations, data.dones, data.rewards, weights

    def _written_out_step(self, plan: _QPlan, batch_size: int) -> float:
        """One gradient step, written out (module docstring); returns the loss."""
        assert plan.online is not None and plan.target is not None
        obs, actions, next_obs, dones, rewards, weights = self._batch(batch_size)
        with th.no_grad():
            if self.double_q:
                next_actions = plan.online.forward(next_obs)[1].argmax(dim=1, keepdim=True)
                next_q = th.gather(plan.target.forward(next_obs)[1], dim=1, index=next_actions).reshape(-1, 1)
            else:
                next_q = plan.target.forward(next_obs)[1].max(dim=1)[0].reshape(-1, 1)
            target_q = rewards + (1 - dones) * self.gamma * next_q

            outs, q_values = plan.online.forward(obs)
            index = actions.long()
            current_q = th.gather(q_values, dim=1, index=index)
            if getattr(self, "loss", "huber") == "squared":
                loss, grad_current = _squared_loss(plan.one, current_q, target_q, weights)
            elif weights is None:
                loss = F.smooth_l1_loss(current_q, target_q)
                grad_current = aten.smooth_l1_loss_backward(plan.one, current_q, target_q, MEAN, HUBER_BETA)
            else:  # mean_i(w_i · huber_i): the mean's expand / n, the product's g · w
                per_sample = F.smooth_l1_loss(current_q, target_q, reduction="none")
                weights = weights.reshape(per_sample.shape)
                loss = (weights * per_sample).mean()
                grad_mean = plan.one.expand(per_sample.shape) / per_sample.numel()
                grad_current = aten.smooth_l1_loss_backward(grad_mean * weights, current_q, target_q,
                                                            NO_REDUCTION, HUBER_BETA)
            grad_q = th.zeros_like(q_values).scatter_add_(1, index, grad_current)  # the gather's backward
            grads = plan.online.backward(outs, grad_q)
            # clip_grad_norm_(max_grad_norm), as torch computes it
            total_norm = th.linalg.vector_norm(th.stack(th._foreach_norm(grads, 2.0)), 2.0)
            th._foreach_mul_(grads, th.clamp(self.max_grad_norm / (total_norm + 1e-6), max=1.0))
            plan.adam.step(grads)
        self._after_gradient_step((target_q - current_q).reshape(-1))
        return loss.item()

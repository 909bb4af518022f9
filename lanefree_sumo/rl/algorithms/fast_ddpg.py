"""DDPG whose update is Stable-Baselines3's, computed with less overhead: the same parameters, bit for bit.

:class:`FastDDPG` is SB3's :class:`~stable_baselines3.DDPG` — same constructor, ``save``/``load`` (either
class loads the other's ``model.zip``), callbacks, TensorBoard, replay buffer save/load, resume — whose
:meth:`~FastDDPG.train` computes exactly SB3's update (``tests/rl/test_fast_ddpg.py`` compares every
parameter, both targets and the Adam state bit for bit after many steps):

* critic: one Adam step on MSE(Q(s, a), r + γ (1 − d) Q'(s', μ'(s'))); actor: one Adam step on
  −mean Q(s, μ(s)) with the updated critic; then θ' ← (1 − τ) θ' + τ θ, critic first; per env step;
* the same replay draws (the same numpy calls in the same order), and the same torch draw for the target
  noise, which DDPG clips to zero: it is drawn anyway so torch's random stream stays in step with SB3's.

Where the time goes instead (one thread, batch 64, actor and critic 256-128; README "Training speed"):

* MLP policies (the vector observation): forward and backward passes written out with the kernels
  autograd itself calls for them (``addmm``; ``mm`` of the same operands for the gradients;
  ``threshold_backward``, ``tanh_backward``, ``mse_loss_backward``), so no graph is built, no module is
  called, and the actor's backward skips the critic's weight gradients SB3 computes and throws away;
* any other policy (e.g. the set encoder): SB3's autograd update, with the actor's backward limited to
  the actor's parameters;
* Adam: the arithmetic of torch's multi-tensor ("foreach") Adam, which on CPU gives the same bits as the
  default per-tensor loop, with its state lists fetched once instead of regrouped each step (torch's own
  ``fused=True`` Adam is faster still but NOT bit-identical, so it is not used);
* target updates with ``torch._foreach_mul_``/``_foreach_add_`` (SB3's arithmetic, fewer calls); replay
  samples wrapped with ``torch.from_numpy`` instead of copied.

``fast_learner=False`` runs SB3's ``train`` unchanged, and so does anything the fast path does not cover
(another device, optimiser or Adam option, several critics, a delayed policy).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, cast

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3 import DDPG
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.torch_layers import FlattenExtractor
from stable_baselines3.common.utils import polyak_update
from torch import nn
from torch.nn import functional as F

_aten = th.ops.aten
_MEAN = 1
"""torch's ``Reduction::Mean``, the reduction argument of ``mse_loss_backward``."""

Layer = tuple[th.Tensor, th.Tensor, th.Tensor]
"""A linear layer: weight W, the view Wᵀ (kept: in-place updates of W show through it), bias."""


# -- the MLP, written out ------------------------------------------------------------------------------

def mlp_layers(net: nn.Module, squash: bool) -> list[Layer] | None:
    """The layers of ``Sequential(Linear, ReLU, …, Linear[, Tanh])`` (Tanh iff ``squash``), all with a
    bias and float32; None for any other network."""
    modules = list(net) if isinstance(net, nn.Sequential) else []
    if squash:
        if not modules or type(modules[-1]) is not nn.Tanh:
            return None
        modules = modules[:-1]
    if len(modules) % 2 != 1:
        return None
    layers: list[Layer] = []
    for k, module in enumerate(modules):
        if k % 2 == 1:
            if type(module) is not nn.ReLU:
                return None
        elif type(module) is not nn.Linear or module.bias is None or module.weight.dtype != th.float32:
            return None
        else:
            layers.append((module.weight, module.weight.t(), module.bias))
    return layers


def forward(layers: Sequence[Layer], x: th.Tensor, squash: bool) -> list[th.Tensor]:
    """[input, output of each layer] of the MLP, as ``nn.Linear`` (``addmm(b, x, Wᵀ)``), ReLU and Tanh
    compute them."""
    outs = [x]
    last = len(layers) - 1
    for k, (_, weight_t, bias) in enumerate(layers):
        z = th.addmm(bias, x, weight_t)
        x = th.relu(z) if k < last else (th.tanh(z) if squash else z)
        outs.append(x)
    return outs


def backward(
    layers: Sequence[Layer], outs: Sequence[th.Tensor], grad: th.Tensor, squash: bool,
    weights: bool = True, to_input: bool = False,
) -> tuple[list[th.Tensor], th.Tensor | None]:
    """(gradients [W1, b1, W2, b2, …] — empty unless ``weights``, gradient of the input — None unless
    ``to_input``) given ``grad``, the gradient of the output, and ``outs`` from :func:`forward`.

    The kernels and operands are those of autograd's formulas for ``addmm`` with a transposed
    weight (weight: gᵀ·x; bias: g summed over the batch; input: g·W), ReLU (``threshold_backward`` on
    its output) and Tanh (``tanh_backward`` on its output), so the gradients are the same bits."""
    if squash:
        grad = _aten.tanh_backward(grad, outs[-1])
    grads: list[th.Tensor] = []
    for k in range(len(layers) - 1, -1, -1):
        if weights:
            grads += [grad.sum(0), grad.t().mm(outs[k])]
        if k > 0 or to_input:
            grad = grad.mm(layers[k][0])
            if k > 0:
                grad = _aten.threshold_backward(grad, outs[k], 0)
    grads.reverse()
    return grads, grad if to_input else None


# -- Adam -----------------------------------------------------------------------------------------------

def _plain_adam(optimizer: th.optim.Optimizer, params: Sequence[th.Tensor]) -> bool:
    """``optimizer`` is a ``torch.optim.Adam`` with one group of exactly ``params`` (CPU float32), default
    options and no hooks: the case :class:`LeanAdam` reproduces."""
    if type(optimizer) is not th.optim.Adam or len(optimizer.param_groups) != 1:
        return False
    group = optimizer.param_groups[0]
    return (
        {id(p) for p in group["params"]} == {id(p) for p in params} and len(group["params"]) == len(params)
        and all(p.device.type == "cpu" and p.dtype == th.float32 for p in params)
        and not group.get("amsgrad") and group.get("weight_decay") == 0 and not group.get("maximize")
        and not group.get("capturable") and not group.get("differentiable") and not group.get("fused")
        and not group.get("decoupled_weight_decay")
        and isinstance(group["lr"], float) and all(isinstance(b, float) for b in group["betas"])
        and not getattr(optimizer, "_optimizer_step_pre_hooks", None)
        and not getattr(optimizer, "_optimizer_step_post_hooks", None)
    )


class LeanAdam:
    """``optimizer.step()`` for gradients given as a list, in ``params`` order.

    For a plain Adam (:func:`_plain_adam`) this is the arithmetic of torch 2.13's multi-tensor Adam
    (``torch.optim.adam._multi_tensor_adam`` without the options) on the optimiser's own state tensors,
    fetched once; otherwise, and for the very first step (which creates the state), the gradients go to
    ``.grad`` and the optimiser steps itself. Call under ``torch.no_grad()``."""

    def __init__(self, optimizer: th.optim.Optimizer, params: Sequence[th.Tensor]) -> None:
        self.optimizer = optimizer
        self.params = list(params)
        self.plain = _plain_adam(optimizer, self.params)
        self._state: Any = None
        self._one = th.tensor(1.0)
        self.exp_avgs: list[th.Tensor] = []
        self.exp_avg_sqs: list[th.Tensor] = []
        self.steps: list[th.Tensor] = []

    def _fetch(self) -> bool:
        """Point at the optimiser's state tensors (again after a ``load_state_dict``); False before its
        first step."""
        state = self.optimizer.state
        if state is self._state:
            return True
        if not all(p in state for p in self.params):
            return False
        self.plain = _plain_adam(self.optimizer, self.params)  # a loaded state brings its own options
        per_param = [state[p] for p in self.params]
        self.exp_avgs = [s["exp_avg"] for s in per_param]
        self.exp_avg_sqs = [s["exp_avg_sq"] for s in per_param]
        self.steps = [s["step"] for s in per_param]
        self._state = state
        return all(t.device.type == "cpu" for t in self.steps)

    def step(self, grads: Sequence[th.Tensor | None]) -> None:
        if any(g is None for g in grads) or not self._fetch() or not self.plain:
            for p, g in zip(self.params, grads):
                p.grad = g
            self.optimizer.step()
            for p in self.params:
                p.grad = None
            return
        given = cast(list[th.Tensor], list(grads))
        group = self.optimizer.param_groups[0]
        lr, (beta1, beta2), eps = group["lr"], group["betas"], group["eps"]
        th._foreach_add_(self.steps, self._one, alpha=1.0)
        th._foreach_lerp_(self.exp_avgs, given, 1 - beta1)
        th._foreach_mul_(self.exp_avg_sqs, beta2)
        th._foreach_addcmul_(self.exp_avg_sqs, given, given, 1 - beta2)
        counts = [s.item() for s in self.steps]
        step_size = [(lr / (1 - beta1**n)) * -1 for n in counts]
        bias_correction2_sqrt = [(1 - beta2**n) ** 0.5 for n in counts]
        denom = th._foreach_sqrt(self.exp_avg_sqs)
        th._foreach_div_(denom, bias_correction2_sqrt)
        th._foreach_add_(denom, eps)
        th._foreach_addcdiv_(self.params, self.exp_avgs, denom, step_size)


# -- the update -----------------------------------------------------------------------------------------

class _Plan:
    """What the fast update needs of a model, fetched once; rebuilt when the policy, an optimiser, the
    replay buffer or the VecNormalize wrapper is replaced (``load``, ``load_replay_buffer``)."""

    def __init__(self, model: FastDDPG) -> None:
        self.policy = model.policy
        self.replay_buffer = model.replay_buffer
        self.vec_normalize = model._vec_normalize_env
        self.actor_opt, self.critic_opt = model.actor.optimizer, model.critic.optimizer
        self.actor_params: list[th.Tensor] = list(model.actor.parameters())
        self.critic_params: list[th.Tensor] = list(model.critic.parameters())
        self.actor_targets: list[th.Tensor] = list(model.actor_target.parameters())
        self.critic_targets: list[th.Tensor] = list(model.critic_target.parameters())
        self.batch_norm = [(model.critic_batch_norm_stats, model.critic_batch_norm_stats_target),
                           (model.actor_batch_norm_stats, model.actor_batch_norm_stats_target)]
        self.supported = (
            model.policy_delay == 1 and len(model.critic.q_networks) == 1 and model.device.type == "cpu"
        )
        self.mlp = self.supported and self._mlp(model)
        if self.mlp:
            self.actor_adam = LeanAdam(self.actor_opt, [t for layer in self.actor for t in (layer[0], layer[2])])
            self.critic_adam = LeanAdam(self.critic_opt, [t for layer in self.critic for t in (layer[0], layer[2])])
        else:
            self.actor_adam = LeanAdam(self.actor_opt, self.actor_params)
            self.critic_adam = LeanAdam(self.critic_opt, self.critic_params)
        self._noise = th.empty(0)
        self.one = th.tensor(1.0)

    def _mlp(self, model: FastDDPG) -> bool:
        """Flat Box observations through SB3's FlattenExtractor into plain MLPs, and a plain float32
        replay buffer: the case written out by hand."""
        rb, space = model.replay_buffer, model.observation_space
        extractors = (model.actor.features_extractor, model.critic.features_extractor,
                      model.actor_target.features_extractor, model.critic_target.features_extractor)
        if not (type(rb) is ReplayBuffer and not rb.optimize_memory_usage and model._vec_normalize_env is None
                and isinstance(space, spaces.Box) and len(space.shape) == 1
                and all(type(e) is FlattenExtractor for e in extractors)
                and all(a.dtype == np.float32 for a in (rb.observations, rb.next_observations, rb.actions,
                                                        rb.rewards, rb.dones, rb.timeouts))
                and not any(stats for pair in self.batch_norm for stats in pair)):
            return False
        nets = (mlp_layers(model.actor.mu, True), mlp_layers(model.critic.q_networks[0], False),
                mlp_layers(model.actor_target.mu, True), mlp_layers(model.critic_target.q_networks[0], False))
        if any(n is None for n in nets):
            return False
        self.actor, self.critic, self.actor_target, self.critic_target = (n or [] for n in nets)
        owned = [t for layer in self.actor for t in (layer[0], layer[2])]
        critic_owned = [t for layer in self.critic for t in (layer[0], layer[2])]
        return ({id(p) for p in owned} == {id(p) for p in self.actor_params}
                and {id(p) for p in critic_owned} == {id(p) for p in self.critic_params})

    def valid(self, model: FastDDPG) -> bool:
        return (self.policy is model.policy and self.replay_buffer is model.replay_buffer
                and self.vec_normalize is model._vec_normalize_env
                and self.actor_opt is model.actor.optimizer and self.critic_opt is model.critic.optimizer)

    def noise(self, like: th.Tensor) -> th.Tensor:
        """A reused tensor shaped like ``like`` for the target noise draw (SB3 draws into a clone of the
        sampled actions: the same shape and dtype consume the same random numbers)."""
        if self._noise.shape != like.shape or self._noise.dtype != like.dtype:
            self._noise = th.empty_like(like)
        return self._noise

    def soft_update(self, tau: float) -> None:
        """SB3's ``polyak_update`` of the critic, then the actor: θ' · (1 − τ), then + τ · θ."""
        th._foreach_mul_(self.critic_targets, 1 - tau)
        th._foreach_add_(self.critic_targets, self.critic_params, alpha=tau)
        th._foreach_mul_(self.actor_targets, 1 - tau)
        th._foreach_add_(self.actor_targets, self.actor_params, alpha=tau)
        for stats, targets in self.batch_norm:
            if stats:
                polyak_update(stats, targets, 1.0)


class FastDDPG(DDPG):
    """SB3's DDPG with the same update computed with less overhead (module docstring).

    :param fast_learner: False runs SB3's own ``train`` (the reference the fast one equals).
    All other parameters are :class:`stable_baselines3.DDPG`'s."""

    _fast_plan: _Plan | None = None

    def __init__(self, *args: Any, fast_learner: bool = True, **kwargs: Any) -> None:
        self.fast_learner = fast_learner
        super().__init__(*args, **kwargs)

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "_fast_plan"]

    def train(self, gradient_steps: int, batch_size: int = 100) -> None:
        plan = self._fast_plan
        if self.fast_learner and (plan is None or not plan.valid(self)):
            plan = self._fast_plan = _Plan(self)
        if plan is None or not self.fast_learner or not plan.supported:
            super().train(gradient_steps, batch_size)
            return
        self.policy.set_training_mode(True)
        self._update_learning_rate([self.actor.optimizer, self.critic.optimizer])
        step = self._mlp_step if plan.mlp else self._autograd_step
        actor_losses, critic_losses = [], []
        for _ in range(gradient_steps):
            self._n_updates += 1
            critic_loss, actor_loss = step(plan, batch_size)
            critic_losses.append(critic_loss)
            actor_losses.append(actor_loss)
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        if len(actor_losses) > 0:
            self.logger.record("train/actor_loss", np.mean(actor_losses))
        self.logger.record("train/critic_loss", np.mean(critic_losses))

    def _target_actions(self, plan: _Plan, actions: th.Tensor, next_actions: th.Tensor) -> th.Tensor:
        """μ'(s') plus SB3's clipped target noise (drawn as SB3 draws it), clipped to [−1, 1]."""
        noise = plan.noise(actions).normal_(0, self.target_policy_noise)
        noise = noise.clamp_(-self.target_noise_clip, self.target_noise_clip)
        return (next_actions + noise).clamp_(-1, 1)

    def _mlp_step(self, plan: _Plan, batch_size: int) -> tuple[float, float]:
        """One gradient step of SB3's DDPG, written out; returns (critic loss, actor loss)."""
        rb = self.replay_buffer
        assert isinstance(rb, ReplayBuffer)
        # ReplayBuffer.sample and _get_samples: the same draws, the same arrays, not copied again
        upper = rb.buffer_size if rb.full else rb.pos
        batch = np.random.randint(0, upper, size=batch_size)
        env = np.random.randint(0, high=rb.n_envs, size=(batch_size,))
        obs = th.from_numpy(rb.observations[batch, env, :])
        actions = th.from_numpy(rb.actions[batch, env, :])
        next_obs = th.from_numpy(rb.next_observations[batch, env, :])
        dones = th.from_numpy((rb.dones[batch, env] * (1 - rb.timeouts[batch, env])).reshape(-1, 1))
        rewards = th.from_numpy(rb.rewards[batch, env].reshape(-1, 1))
        with th.no_grad():
            next_actions = self._target_actions(plan, actions, forward(plan.actor_target, next_obs, True)[-1])
            next_q = forward(plan.critic_target, th.cat([next_obs, next_actions], dim=1), False)[-1]
            target_q = rewards + (1 - dones) * self.gamma * next_q

            critic = forward(plan.critic, th.cat([obs, actions], dim=1), False)
            critic_loss = F.mse_loss(critic[-1], target_q)
            grad_q = _aten.mse_loss_backward(plan.one, critic[-1], target_q, _MEAN)
            plan.critic_adam.step(backward(plan.critic, critic, grad_q, False)[0])

            actor = forward(plan.actor, obs, True)
            q = forward(plan.critic, th.cat([obs, actor[-1]], dim=1), False)
            actor_loss = -q[-1].mean()
            grad_mean = (-plan.one).expand(q[-1].shape) / q[-1].numel()  # autograd's d(−mean)/dq
            grad_input = backward(plan.critic, q, grad_mean, False, weights=False, to_input=True)[1]
            assert grad_input is not None
            plan.actor_adam.step(backward(plan.actor, actor, grad_input[:, obs.shape[1]:], True)[0])

            plan.soft_update(self.tau)
        return critic_loss.item(), actor_loss.item()

    def _autograd_step(self, plan: _Plan, batch_size: int) -> tuple[float, float]:
        """One gradient step of SB3's DDPG through autograd (any policy); returns (critic loss, actor loss)."""
        data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)  # type: ignore[union-attr]
        discounts = data.discounts if data.discounts is not None else self.gamma
        with th.no_grad():
            next_actions = self._target_actions(plan, data.actions, self.actor_target(data.next_observations))
            next_q = self.critic_target(data.next_observations, next_actions)[0]
            target_q = data.rewards + (1 - data.dones) * discounts * next_q
        critic_loss = F.mse_loss(self.critic(data.observations, data.actions)[0], target_q)
        self.critic.optimizer.zero_grad()
        critic_loss.backward()
        with th.no_grad():
            plan.critic_adam.step([p.grad for p in plan.critic_params])

        actor_loss = -self.critic.q1_forward(data.observations, self.actor(data.observations)).mean()
        self.actor.optimizer.zero_grad()
        actor_loss.backward(inputs=plan.actor_params)  # SB3 also fills the critic's .grad, then discards it
        with th.no_grad():
            plan.actor_adam.step([p.grad for p in plan.actor_params])
            plan.soft_update(self.tau)
        return critic_loss.item(), actor_loss.item()

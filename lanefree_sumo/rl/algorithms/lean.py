"""What the fast learners share (:mod:`.fast_ddpg`, :mod:`.fast_dqn`): the same numbers as Stable-Baselines3,
computed with less overhead.

* MLPs written out (:func:`forward`, :func:`backward`) with the kernels autograd itself calls for
  ``nn.Linear`` and ReLU/Tanh, so the activations and gradients are the same bits without a graph;
* :class:`LeanAdam`: torch's multi-tensor Adam arithmetic on the optimiser's own state (same bits as the
  per-tensor loop on CPU), over one flat buffer per network (:func:`flatten_parameters`);
* :class:`LeanCollector`: SB3's ``collect_rollouts`` with the same draws and calls, minus the per-step
  ``set_training_mode`` walks and ``predict``'s generic path (each algorithm supplies its action rule).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, cast

import numpy as np
import torch as th
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.type_aliases import RolloutReturn, TrainFreq, TrainFrequencyUnit
from stable_baselines3.common.vec_env import VecEnv
from torch import nn

aten = th.ops.aten
MEAN = 1
"""torch's ``Reduction::Mean``, the reduction argument of ``mse_loss_backward``."""

Layer = tuple[th.Tensor, th.Tensor, th.Tensor]
"""A linear layer: weight W, the view Wᵀ (kept: in-place updates of W show through it), bias."""


def mean_of(values: list[float]) -> float:
    """``np.mean`` (SB3's loss logging), without its overhead for the usual single value."""
    return values[0] if len(values) == 1 else float(np.mean(values))


# -- the MLP, written out ------------------------------------------------------------------------------

def mlp_layers(net: nn.Module, squash: bool) -> list[Layer] | None:
    """The layers of ``Sequential(Linear, ReLU, …, Linear[, Tanh])`` (Tanh iff ``squash``), all with a
    bias and float32; None for any other network."""
    modules = list(net) if type(net) is nn.Sequential else []  # a subclass may compute something else
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
        grad = aten.tanh_backward(grad, outs[-1])
    grads: list[th.Tensor] = []
    for k in range(len(layers) - 1, -1, -1):
        if weights:
            grads += [grad.sum(0), grad.t().mm(outs[k])]
        if k > 0 or to_input:
            grad = grad.mm(layers[k][0])
            if k > 0:
                grad = aten.threshold_backward(grad, outs[k], 0)
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


def flatten_parameters(params: Sequence[th.Tensor]) -> th.Tensor:
    """Move ``params`` into one contiguous buffer, in order, and return it: each parameter's ``.data``
    becomes a view of it (the values are unchanged), so elementwise updates can run once over the buffer
    instead of once per tensor — the same kernels on the same elements, the same bits."""
    flat = th.cat([p.detach().reshape(-1) for p in params])
    at = 0
    for p in params:
        p.data = flat[at:at + p.numel()].view_as(p)
        at += p.numel()
    return flat


def _flat_state(state: dict[Any, Any], params: Sequence[th.Tensor], key: str) -> th.Tensor:
    """Like :func:`flatten_parameters` for the optimiser's ``state[p][key]`` tensors (replaced by views)."""
    flat = th.cat([state[p][key].reshape(-1) for p in params])
    at = 0
    for p in params:
        state[p][key] = flat[at:at + p.numel()].view_as(p)
        at += p.numel()
    return flat


class LeanAdam:
    """``optimizer.step()`` for gradients given as a list, in ``params`` order.

    For a plain Adam (:func:`_plain_adam`) this is the arithmetic of torch 2.13's multi-tensor Adam
    (``torch.optim.adam._multi_tensor_adam`` without the options) on the optimiser's own state tensors,
    fetched once; with ``flat`` (the buffer :func:`flatten_parameters` made of ``params``) the state is
    moved into buffers of the same layout too and each of Adam's elementwise operations runs once over
    the buffers. Otherwise, and for the very first step (which creates the state), the gradients go to
    ``.grad`` and the optimiser steps itself. Call under ``torch.no_grad()``."""

    def __init__(self, optimizer: th.optim.Optimizer, params: Sequence[th.Tensor],
                 flat: th.Tensor | None = None) -> None:
        self.optimizer = optimizer
        self.params = list(params)
        self.flat = flat
        self.plain = _plain_adam(optimizer, self.params)
        self._state: Any = None
        self._one = th.tensor(1.0)
        self.exp_avgs: list[th.Tensor] = []
        self.exp_avg_sqs: list[th.Tensor] = []
        self.steps: list[th.Tensor] = []
        self.flat_exp_avg = self.flat_exp_avg_sq = th.empty(0)

    def _fetch(self) -> bool:
        """Point at the optimiser's state tensors (again after a ``load_state_dict``); False before its
        first step."""
        state = self.optimizer.state
        if state is self._state:
            return True
        if not all(p in state for p in self.params):
            return False
        self.plain = _plain_adam(self.optimizer, self.params)  # a loaded state brings its own options
        if not self.plain:  # another optimiser (or Adam option): it steps itself, its state is its own
            self._state = state
            return False
        if self.flat is not None:
            self.flat_exp_avg = _flat_state(state, self.params, "exp_avg")
            self.flat_exp_avg_sq = _flat_state(state, self.params, "exp_avg_sq")
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
        counts = [s.item() for s in self.steps]
        if self.flat is not None and len(set(counts)) == 1:
            n = counts[0]
            grad = th.cat([g.reshape(-1) for g in given])
            self.flat_exp_avg.lerp_(grad, 1 - beta1)
            self.flat_exp_avg_sq.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
            denom = self.flat_exp_avg_sq.sqrt().div_((1 - beta2**n) ** 0.5).add_(eps)
            self.flat.addcdiv_(self.flat_exp_avg, denom, value=(lr / (1 - beta1**n)) * -1)
            return
        th._foreach_lerp_(self.exp_avgs, given, 1 - beta1)
        th._foreach_mul_(self.exp_avg_sqs, beta2)
        th._foreach_addcmul_(self.exp_avg_sqs, given, given, 1 - beta2)
        step_size = [(lr / (1 - beta1**n)) * -1 for n in counts]
        bias_correction2_sqrt = [(1 - beta2**n) ** 0.5 for n in counts]
        denom_list = th._foreach_sqrt(self.exp_avg_sqs)
        th._foreach_div_(denom_list, bias_correction2_sqrt)
        th._foreach_add_(denom_list, eps)
        th._foreach_addcdiv_(self.params, self.exp_avgs, denom_list, step_size)


def defined_by(obj: object, name: str) -> type | None:
    """The class whose definition of ``name`` ``obj`` uses; None when ``obj`` itself holds one (a patch) or none.
    The fast learners take their written-out paths only where what they replace is the library's own."""
    if name in vars(obj):
        return None
    return next((klass for klass in type(obj).__mro__ if name in vars(klass)), None)


# -- the collection loop --------------------------------------------------------------------------------

class LeanCollector:
    """Mixin (before the SB3 class in the bases) replacing ``collect_rollouts`` by SB3's loop without what
    cannot change a number for plain MLPs. The algorithm supplies :meth:`_lean_plan` (None: SB3's own
    loop) and :meth:`_lean_action` (SB3's ``_sample_action``, the same draws and arithmetic)."""

    num_timesteps: int
    _episode_num: int
    _total_timesteps: int

    def _lean_plan(self) -> Any:
        """What :meth:`_lean_action` needs, or None when the lean loop does not apply."""
        raise NotImplementedError

    def _lean_action(self, plan: Any, learning_starts: int, action_noise: ActionNoise | None,
                     n_envs: int) -> tuple[np.ndarray, np.ndarray]:
        """(actions for the env, actions for the buffer), as SB3's ``_sample_action`` returns them."""
        raise NotImplementedError

    def _after_step(self, replay_buffer: ReplayBuffer, buffer_actions: np.ndarray, new_obs: Any, rewards: np.ndarray,
                    dones: np.ndarray, infos: list[dict[str, Any]], action_noise: ActionNoise | None,
                    log_interval: int | None) -> int:
        """What SB3's ``collect_rollouts`` does after ``callback.on_step``: episode info, the transition into
        the buffer, progress, ``_on_step``, noise resets and logs at episode ends. Returns episodes ended."""
        algo = cast(Any, self)
        algo._update_info_buffer(infos, dones)
        algo._store_transition(replay_buffer, buffer_actions, new_obs, rewards, dones, infos)
        algo._update_current_progress_remaining(self.num_timesteps, self._total_timesteps)
        algo._on_step()
        ended = 0
        for idx, done in enumerate(dones):
            if done:
                ended += 1
                self._episode_num += 1
                if action_noise is not None:
                    action_noise.reset(**({"indices": [idx]} if len(dones) > 1 else {}))
                if log_interval is not None and self._episode_num % log_interval == 0:
                    algo.dump_logs()
        return ended

    def collect_rollouts(self, env: VecEnv, callback: BaseCallback, train_freq: TrainFreq,
                         replay_buffer: ReplayBuffer, action_noise: ActionNoise | None = None,
                         learning_starts: int = 0, log_interval: int | None = None) -> RolloutReturn:
        """SB3's ``collect_rollouts`` with the same arithmetic, draws and calls to the env, the callback, the
        replay buffer and the logger, minus the three ``set_training_mode`` walks over every module per step
        (here, ``predict`` and ``train``) and ``predict``'s generic path (:meth:`_lean_action`)."""
        plan = self._lean_plan()
        if plan is None or train_freq.unit != TrainFrequencyUnit.STEP:
            return cast(Any, super()).collect_rollouts(env, callback, train_freq, replay_buffer, action_noise,
                                                       learning_starts, log_interval)
        # SB3's local names: a callback reads them through ``self.locals``
        num_collected_steps, num_collected_episodes, n_envs = 0, 0, env.num_envs
        continue_training = True
        callback.on_rollout_start()
        while num_collected_steps < train_freq.frequency:
            actions, buffer_actions = self._lean_action(plan, learning_starts, action_noise, n_envs)
            new_obs, rewards, dones, infos = env.step(actions)
            self.num_timesteps += n_envs
            num_collected_steps += 1
            callback.update_locals(locals())
            if not callback.on_step():
                return RolloutReturn(num_collected_steps * n_envs, num_collected_episodes, continue_training=False)
            num_collected_episodes += self._after_step(replay_buffer, buffer_actions, new_obs, rewards, dones, infos,
                                                       action_noise, log_interval)
        callback.on_rollout_end()
        return RolloutReturn(num_collected_steps * n_envs, num_collected_episodes, continue_training)

    def _lean_collecting(self) -> bool:
        """The lean loop collects (so no ``set_training_mode(False)`` happened that ``train`` must undo)."""
        return self._lean_plan() is not None and cast(Any, self).train_freq.unit == TrainFrequencyUnit.STEP

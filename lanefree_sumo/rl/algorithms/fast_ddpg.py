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
(another device, several critics, a delayed policy); another network, action rule or policy class than SB3's
(a subclass's) gets SB3's autograd update and loop; another optimiser than a plain Adam steps itself on the
computed gradients.
"""

from __future__ import annotations

from typing import Any, cast

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3 import DDPG
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy, ContinuousCritic
from stable_baselines3.common.torch_layers import FlattenExtractor
from stable_baselines3.common.type_aliases import MaybeCallback, RolloutReturn, TrainFreq, TrainFrequencyUnit
from stable_baselines3.common.utils import polyak_update
from stable_baselines3.common.vec_env import VecEnv
from stable_baselines3.td3.policies import Actor, TD3Policy
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

WARMUP_ACTIONS: tuple[str, ...] = ("uniform", "policy")
"""What DDPG does before its first update (``train.actor_critic.warmup_actions``)."""

# -- the update -----------------------------------------------------------------------------------------

def _stock_methods(model: FastDDPG) -> bool:
    """What the written-out path and the lean loop replace is SB3's own: the action (``_sample_action``,
    ``predict``, the policy's ``_predict``/``predict``) and the actor and critic classes. Checked on every use."""
    return (defined_by(model, "predict") is BaseAlgorithm
            and defined_by(model, "_sample_action") is OffPolicyAlgorithm
            and defined_by(model.policy, "_predict") is TD3Policy
            and defined_by(model.policy, "predict") is BasePolicy
            and type(model.actor) is Actor and type(model.actor_target) is Actor
            and type(model.critic) is ContinuousCritic and type(model.critic_target) is ContinuousCritic)


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
        self.flat: list[th.Tensor] = []
        """Flat parameter buffers of actor, critic and their targets (MLP case; :func:`flatten_parameters`)."""
        self.mlp = self.supported and self._mlp(model)
        if self.mlp:
            self.actor_adam = LeanAdam(self.actor_opt, self.actor_params, self.flat[0])
            self.critic_adam = LeanAdam(self.critic_opt, self.critic_params, self.flat[1])
        else:
            self.actor_adam = LeanAdam(self.actor_opt, self.actor_params)
            self.critic_adam = LeanAdam(self.critic_opt, self.critic_params)
        self._noise = th.empty(0)
        self.one = th.tensor(1.0)

    def _mlp(self, model: FastDDPG) -> bool:
        """Flat Box observations through SB3's FlattenExtractor into plain MLPs, and a plain float32
        replay buffer: the case written out by hand (with :func:`_stock_methods`)."""
        rb, space = model.replay_buffer, model.observation_space
        if not _stock_methods(model):
            return False
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
        owned = [[t for layer in net or [] for t in (layer[0], layer[2])] for net in nets]
        if not all([id(p) for p in mine] == [id(p) for p in theirs] for mine, theirs in zip(
                owned, (self.actor_params, self.critic_params, self.actor_targets, self.critic_targets))):
            return False
        # one buffer per network (parameters in module order, so a net and its target line up), then the
        # layers again: their transposed views must see the moved weights
        self.flat = [flatten_parameters(params) for params in
                     (self.actor_params, self.critic_params, self.actor_targets, self.critic_targets)]
        self.actor, self.critic, self.actor_target, self.critic_target = (
            cast(list[Layer], mlp_layers(net, squash)) for net, squash in (
                (model.actor.mu, True), (model.critic.q_networks[0], False),
                (model.actor_target.mu, True), (model.critic_target.q_networks[0], False)))
        return True

    def valid(self, model: FastDDPG) -> bool:
        return (self.policy is model.policy and self.replay_buffer is model.replay_buffer
                and self.vec_normalize is model._vec_normalize_env
                and self.actor_opt is model.actor.optimizer and self.critic_opt is model.critic.optimizer
                and (not self.mlp or _stock_methods(model)))

    def noise(self, like: th.Tensor) -> th.Tensor:
        """A reused tensor shaped like ``like`` for the target noise draw (SB3 draws into a clone of the
        sampled actions: the same shape and dtype consume the same random numbers)."""
        if self._noise.shape != like.shape or self._noise.dtype != like.dtype:
            self._noise = th.empty_like(like)
        return self._noise

    def soft_update(self, tau: float) -> None:
        """SB3's ``polyak_update`` of the critic, then the actor: θ' · (1 − τ), then + τ · θ."""
        if self.flat:
            actor, critic, actor_target, critic_target = self.flat
            critic_target.mul_(1 - tau).add_(critic, alpha=tau)
            actor_target.mul_(1 - tau).add_(actor, alpha=tau)
        else:
            th._foreach_mul_(self.critic_targets, 1 - tau)
            th._foreach_add_(self.critic_targets, self.critic_params, alpha=tau)
            th._foreach_mul_(self.actor_targets, 1 - tau)
            th._foreach_add_(self.actor_targets, self.actor_params, alpha=tau)
        for stats, targets in self.batch_norm:
            if stats:
                polyak_update(stats, targets, 1.0)


class FastDDPG(LeanCollector, DDPG):
    """SB3's DDPG with the same update computed with less overhead (module docstring).

    :param fast_learner: False runs SB3's own ``train`` (the reference the fast one equals).
    :param lean_loop: collect with :meth:`collect_rollouts`' lean loop (SB3's, bit for bit, without the
        per-step mode switches and ``predict``'s generic path); False runs SB3's own.
    :param overlap: step the environment while updating (with a ``SubprocVecEnv`` of one env, on another
        core): the acting policy lags the learner by one update (:meth:`learn`); not bit-identical to SB3.
    :param pre_tanh_penalty: λ ≥ 0 of λ·mean(u²) added to the actor loss, u the actor's pre-tanh output
        (``train.actor_critic.pre_tanh_penalty``); with λ > 0 every update takes the autograd path.

    All other parameters are :class:`stable_baselines3.DDPG`'s."""

    _fast_plan: _Plan | None = None

    def __init__(self, *args: Any, fast_learner: bool = True, lean_loop: bool = True, overlap: bool = False,
                 warmup_actions: str = "uniform", pre_tanh_penalty: float = 0.0, **kwargs: Any) -> None:
        if warmup_actions not in WARMUP_ACTIONS:
            raise ValueError(f"unknown warm-up {warmup_actions!r}; valid: {', '.join(WARMUP_ACTIONS)}")
        if not pre_tanh_penalty >= 0:
            raise ValueError(f"pre_tanh_penalty must be ≥ 0, got {pre_tanh_penalty!r}")
        self.pre_tanh_penalty = float(pre_tanh_penalty)
        self.fast_learner = fast_learner
        self.lean_loop = lean_loop
        self.overlap = overlap
        self.warmup_actions = warmup_actions
        super().__init__(*args, **kwargs)

    def _penalty(self) -> float:
        """λ of the pre-tanh penalty (0 for models saved before it existed)."""
        return float(getattr(self, "pre_tanh_penalty", 0.0))

    def _random_steps(self, learning_starts: int) -> int:
        """Steps that act uniformly at random: SB3's ``learning_starts``, or none with ``warmup_actions =
        policy`` (the actor and its noise from the first step, as Keras-RL's DDPG; updates still wait)."""
        return learning_starts if getattr(self, "warmup_actions", "uniform") == "uniform" else 0

    def collect_rollouts(self, env: VecEnv, callback: BaseCallback, train_freq: TrainFreq,
                         replay_buffer: ReplayBuffer, action_noise: ActionNoise | None = None,
                         learning_starts: int = 0, log_interval: int | None = None) -> RolloutReturn:
        """SB3's (or the lean) collection, whose ``learning_starts`` only decides random actions: see
        :meth:`_random_steps`."""
        return super().collect_rollouts(env, callback, train_freq, replay_buffer, action_noise,
                                        self._random_steps(learning_starts), log_interval)

    def _excluded_save_params(self) -> list[str]:
        """Never pickled into ``model.zip``: the plan holds the policy, the optimisers and the replay buffer."""
        return [*super()._excluded_save_params(), "_fast_plan"]

    def _plan(self) -> _Plan | None:
        """The fast update's plan (rebuilt when the model's parts were replaced); None without the fast learner."""
        if not self.fast_learner:
            return None
        plan = self._fast_plan
        if plan is None or not plan.valid(self):
            plan = self._fast_plan = _Plan(self)
        return plan

    def _lean(self, plan: _Plan | None) -> bool:
        """The lean collection loop applies: plain MLPs (no module whose train/eval mode changes a number),
        a Box action space, no gSDE."""
        return (getattr(self, "lean_loop", True) and plan is not None and plan.mlp
                and isinstance(self.action_space, spaces.Box) and not self.use_sde)

    def _lean_action(self, plan: _Plan, learning_starts: int, action_noise: ActionNoise | None,
                     n_envs: int) -> tuple[np.ndarray, np.ndarray]:
        """SB3's ``_sample_action`` (same draws, same arithmetic) with the actor run through :func:`forward`
        (the kernels ``nn.Linear`` calls) instead of ``predict``: (actions for the env, actions for the buffer)."""
        policy, space = self.policy, self.action_space
        assert isinstance(space, spaces.Box)
        if self.num_timesteps < learning_starts:
            unscaled = np.array([space.sample() for _ in range(n_envs)])
        else:
            obs = th.as_tensor(self._last_obs).float().reshape((-1, *self.observation_space.shape))  # type: ignore[misc]
            with th.no_grad():
                raw = forward(plan.actor, obs, True)[-1]
            unscaled = policy.unscale_action(raw.numpy().reshape((-1, *space.shape)))
        scaled = policy.scale_action(unscaled)
        if action_noise is not None:
            scaled = np.clip(scaled + action_noise(), -1, 1)
        return policy.unscale_action(scaled), scaled

    def _lean_plan(self) -> _Plan | None:
        """The plan when the lean collection loop applies (:class:`~.lean.LeanCollector`), else None."""
        plan = self._plan()
        return plan if self._lean(plan) else None

    def learn(self, total_timesteps: int, callback: MaybeCallback = None, log_interval: int = 4,
              tb_log_name: str = "run", reset_num_timesteps: bool = True, progress_bar: bool = False) -> FastDDPG:
        """SB3's ``learn``; with ``overlap`` (and the lean loop, one step per update) the environment steps
        in its own process while this one updates: the action of step t is chosen before update t − 1 runs,
        so the policy that acts lags the learner by exactly one update (deterministic: the same run twice
        gives the same numbers). Without ``overlap``: SB3's order, bit for bit."""
        plan = self._plan()
        if not (self.overlap and self._lean(plan) and self.train_freq == TrainFreq(1, TrainFrequencyUnit.STEP)
                and self.gradient_steps == 1 and self.env is not None and self.env.num_envs == 1):
            return super().learn(total_timesteps, callback, log_interval, tb_log_name, reset_num_timesteps,
                                 progress_bar)
        assert plan is not None and isinstance(self.replay_buffer, ReplayBuffer)
        total_timesteps, callback = self._setup_learn(total_timesteps, callback, reset_num_timesteps, tb_log_name,
                                                      progress_bar)
        callback.on_training_start(locals(), globals())
        env, replay_buffer, action_noise = self.env, self.replay_buffer, self.action_noise
        update_due = False
        while self.num_timesteps < total_timesteps:
            callback.on_rollout_start()
            plan = self._plan() or plan  # rebuilt if a callback replaced the buffer or the policy
            actions, buffer_actions = self._lean_action(plan, self._random_steps(self.learning_starts),
                                                        action_noise, 1)
            env.step_async(actions)
            if update_due:  # update t − 1 while the env computes step t
                self.train(batch_size=self.batch_size, gradient_steps=1)
            new_obs, rewards, dones, infos = env.step_wait()
            self.num_timesteps += 1
            callback.update_locals(locals())
            if not callback.on_step():
                break
            self._after_step(replay_buffer, buffer_actions, new_obs, rewards, dones, infos, action_noise,
                             log_interval)
            callback.on_rollout_end()
            update_due = self.num_timesteps > self.learning_starts
        else:
            if update_due:
                self.train(batch_size=self.batch_size, gradient_steps=1)
        callback.on_training_end()
        return self

    def train(self, gradient_steps: int, batch_size: int = 100) -> None:
        plan = self._plan()
        if plan is None or not plan.supported:
            super().train(gradient_steps, batch_size)
            return
        if not self._lean_collecting():
            self.policy.set_training_mode(True)
        self._update_learning_rate([self.actor.optimizer, self.critic.optimizer])
        step = self._mlp_step if plan.mlp and not self._penalty() else self._autograd_step
        actor_losses, critic_losses = [], []
        for _ in range(gradient_steps):
            self._n_updates += 1
            critic_loss, actor_loss = step(plan, batch_size)
            critic_losses.append(critic_loss)
            actor_losses.append(actor_loss)
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        if len(actor_losses) > 0:
            self.logger.record("train/actor_loss", mean_of(actor_losses))
        self.logger.record("train/critic_loss", mean_of(critic_losses))

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
            grad_q = aten.mse_loss_backward(plan.one, critic[-1], target_q, MEAN)
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

        penalty = self._penalty()
        if penalty:  # the actor's forward pass, its pre-tanh output kept: mu = [..., Linear, Tanh]
            pre = self.actor.mu[:-1](self.actor.extract_features(data.observations, self.actor.features_extractor))
            actor_loss = (-self.critic.q1_forward(data.observations, th.tanh(pre)).mean()
                          + penalty * pre.square().mean())
        else:
            actor_loss = -self.critic.q1_forward(data.observations, self.actor(data.observations)).mean()
        self.actor.optimizer.zero_grad()
        actor_loss.backward(inputs=plan.actor_params)  # SB3 also fills the critic's .grad, then discards it
        with th.no_grad():
            plan.actor_adam.step([p.grad for p in plan.actor_params])
            plan.soft_update(self.tau)
        return critic_loss.item(), actor_loss.item()

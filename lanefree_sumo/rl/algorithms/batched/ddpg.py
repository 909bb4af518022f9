"""DDPG for K runs at once: SB3's DDPG update, written out with a leading run axis, with two choices SB3 lacks.

Run k starts from the weights SB3's DDPG gets with seed k (its policy built under ``torch.manual_seed(k)``,
as ``DDPG._setup_model`` builds it), draws its replay indices and Ornstein-Uhlenbeck noise from its own
stream (:class:`~.replay.RunStreams`) in the single run's order, and has its own learning rate, γ, τ, σ and θ;
the network shapes, batch size, buffer size and ``learning_starts`` are the batch's. On CPU run k's
parameters, targets and Adam moments equal SB3's ``DDPG`` of that run bit for bit (``tests/rl/
test_batched_learners.py``). The choices: ``warmup_actions = policy`` (Keras-RL's DDPG: the actor and its noise act
from the first step instead of SB3's uniformly random actions before ``learning_starts``; updates still wait) and
``pre_tanh_penalty = λ > 0`` (λ·mean(u²) added to the actor loss, u the actor's pre-tanh output: a remedy for an
actor stuck at its tanh bound); both bit for bit against SB3's update with the choice written in
(``tests/rl/reference.py``), and in the golden files frozen from SB3's loop
(``tests/experiments/test_golden_runs.py``). SB3 also
draws DDPG's target-policy noise, which DDPG clips to zero; it changes no number (only a −0.0 action to +0.0),
so it is not drawn here. On the set observation each network starts with the set encoder (:mod:`.set_encoder`),
and run k agrees with the single run to float tolerance (``tests/rl/test_batched_set.py``). TD3 is this class
with two Q-networks (:mod:`.td3`).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.noise import OrnsteinUhlenbeckActionNoise
from stable_baselines3.td3.policies import TD3Policy
from torch import nn
from torch.nn import functional as F

from lanefree_sumo.rl.algorithms.batched.learner import BatchedLearner, SpacesEnv, kept_random_state, per_run
from lanefree_sumo.rl.algorithms.batched.replay import OUNoise
from lanefree_sumo.rl.algorithms.batched.set_encoder import Encoded, SetLayout, encode, encode_backward
from lanefree_sumo.rl.algorithms.batched.stack import (
    ParamStack,
    StackedAdam,
    aten,
    mlp_backward,
    mlp_forward,
    per_run_column,
    soft_update,
)
from lanefree_sumo.rl.encoder import SetFeaturesExtractor

WARMUP_ACTIONS: tuple[str, ...] = ("uniform", "policy")
"""What DDPG does before its first update (``train.actor_critic.warmup_actions``)."""


def policy_kwargs(actor_layers: Sequence[int], critic_layers: Sequence[int], encoder: str | None) -> dict[str, Any]:
    """SB3's ``policy_kwargs`` of ``build_model``'s DDPG: the layer widths, ReLU, and the set encoder ``encoder``
    (None: the vector observation's flat input)."""
    kwargs: dict[str, Any] = {"net_arch": {"pi": list(actor_layers), "qf": list(critic_layers)},
                              "activation_fn": nn.ReLU}
    if encoder is not None:
        kwargs.update(features_extractor_class=SetFeaturesExtractor, features_extractor_kwargs={"encoder": encoder})
    return kwargs


def sb3_policy(observation_space: spaces.Space, action_space: spaces.Space, seed: int, learning_rate: float,
               actor_layers: Sequence[int], critic_layers: Sequence[int], encoder: str | None = None,
               n_critics: int = 1) -> tuple[TD3Policy, th.Tensor]:
    """(the policy SB3's DDPG — TD3 with ``n_critics`` 2 — builds with ``seed`` (``build_model``'s network
    settings), torch's CPU random state after it: where the single run's update draws from), built on the CPU
    under ``torch.manual_seed(seed)`` without touching the caller's torch random state."""
    with th.random.fork_rng(devices=[]):
        th.manual_seed(seed)
        policy = TD3Policy(observation_space, action_space, lambda _: learning_rate,  # type: ignore[arg-type]
                           n_critics=n_critics, **policy_kwargs(actor_layers, critic_layers, encoder))
        return policy, th.random.get_rng_state()


class BatchedDDPG(BatchedLearner):
    """DDPG (SB3's, as ``lanefree train`` configures it) for K runs; module docstring.

    Per run (one number for all or one per run): ``learning_rate``, ``gamma``, ``tau``, ``ou_sigma``,
    ``ou_theta``, ``pre_tanh_penalty`` (λ of λ·mean(u²) on the actor's pre-tanh
    output u). The batch's: the layer widths, ``batch_size``, ``buffer_size``, ``learning_starts``,
    ``warmup_actions`` (``uniform``: random actions before
    ``learning_starts``, or ``policy``: the actor and its noise from the first step), ``encoder``: the set
    encoder's name for the set observation (a Dict observation space; :mod:`.set_encoder`), None for the
    vector observation."""

    n_critics = 1
    """Q-networks in the critic (TD3: 2)."""
    algo = "ddpg"
    """The registry's name of the algorithm (:meth:`sb3_model`'s class)."""

    def __init__(self, observation_space: spaces.Space, action_space: spaces.Space, seeds: Sequence[int], *,
                 learning_rate: float | Sequence[float] = 1e-3, gamma: float | Sequence[float] = 0.98,
                 tau: float | Sequence[float] = 0.001, ou_sigma: float | Sequence[float] = 0.2,
                 ou_theta: float | Sequence[float] = 0.15, actor_layers: Sequence[int] = (256, 128),
                 critic_layers: Sequence[int] = (256, 128), batch_size: int = 64, buffer_size: int = 100_000,
                 learning_starts: int = 800, warmup_actions: str = "uniform", total_timesteps: int = 1,
                 pre_tanh_penalty: float | Sequence[float] = 0.0, encoder: str | None = None,
                 device: str = "cpu", exact: bool | None = None, slots: int = 1) -> None:
        if not isinstance(action_space, spaces.Box) or len(action_space.shape) != 1:
            raise ValueError("batched DDPG takes a flat Box action space")
        if warmup_actions not in WARMUP_ACTIONS:
            raise ValueError(f"unknown warm-up {warmup_actions!r}; valid: {', '.join(WARMUP_ACTIONS)}")
        n_actions = int(action_space.shape[0])
        super().__init__(observation_space, action_space, seeds, batch_size=batch_size, buffer_size=buffer_size,
                         learning_starts=learning_starts, total_timesteps=total_timesteps, action_dim=n_actions,
                         action_dtype=th.float32, device=device, exact=exact, slots=slots)
        k = self.runs
        self.learning_rate = per_run(learning_rate, k, "learning_rate")
        self.gamma = per_run(gamma, k, "gamma")
        self.tau = per_run(tau, k, "tau")
        self.ou_sigma, self.ou_theta = per_run(ou_sigma, k, "ou_sigma"), per_run(ou_theta, k, "ou_theta")
        self.actor_layers, self.critic_layers = tuple(actor_layers), tuple(critic_layers)
        self.warmup_actions = warmup_actions
        self.pre_tanh_penalty = per_run(pre_tanh_penalty, k, "pre_tanh_penalty")
        if not all(v >= 0 for v in self.pre_tanh_penalty):
            raise ValueError(f"pre_tanh_penalty must be ≥ 0, got {self.pre_tanh_penalty}")
        self.encoder = encoder
        if (encoder is None) != isinstance(observation_space, spaces.Box):
            raise ValueError("the set observation (a Dict space) takes an encoder, the vector observation none")
        built = [sb3_policy(observation_space, action_space, seed, lr, actor_layers, critic_layers, encoder,
                            self.n_critics) for seed, lr in zip(self.seeds, self.learning_rate)]
        policies = [policy for policy, _ in built]
        self._torch_states = [state for _, state in built]
        """Each run's torch CPU random state after its policy was built (SB3's draws in the update start there)."""
        self._policy = policies[0]  # scale/unscale of actions (the same for all runs)
        self.layout: SetLayout | None = None
        """The set observation's layout (None: the vector observation)."""
        if encoder is not None:
            others = observation_space["others"]  # type: ignore[index]
            extractor = policies[0].actor.features_extractor
            assert isinstance(extractor, SetFeaturesExtractor)
            self.layout = SetLayout.of(extractor.encoder,
                                       int(observation_space["ego"].shape[0]),  # type: ignore[index]
                                       int(others.shape[0]))
        head = 0 if self.layout is None else self.layout.tensors
        self.features_dim = int(policies[0].actor.features_dim)
        """The width of the features the actor's and the critic's MLP heads read (the observation's, or the
        encoder's output with the ego features)."""
        self.actor, self.critic, self.actor_target, self.critic_target = (
            ParamStack([list(getattr(p, name).parameters()) for p in policies], self.device, head)
            for name in ("actor", "critic", "actor_target", "critic_target"))
        group = policies[0].actor.optimizer.param_groups[0]
        self.actor_adam = StackedAdam(self.actor, self.learning_rate, group["betas"], group["eps"])
        self.critic_adam = StackedAdam(self.critic, self.learning_rate, group["betas"], group["eps"])
        self._gamma = per_run_column(self.gamma, self.device).unsqueeze(2)
        self._tau = per_run_column(self.tau, self.device)
        self._one_minus_tau = per_run_column([1 - t for t in self.tau], self.device)
        self._shared_tau = self.tau[0] if len(set(self.tau)) == 1 else None
        self.noise = OUNoise(self.ou_sigma, self.ou_theta, n_actions, self.slots)
        self._one = th.tensor(1.0, device=self.device)
        self._penalty = (None if not any(self.pre_tanh_penalty)
                         else per_run_column(self.pre_tanh_penalty, self.device).unsqueeze(2))
        """λ per run ``[K, 1, 1]`` float32 (as autograd rounds a Python λ), None when no run has a penalty."""
        self._last: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def random_steps(self) -> int:
        """Steps that act uniformly at random: SB3's ``learning_starts``, or none with ``warmup_actions = policy``."""
        return self.learning_starts if self.warmup_actions == "uniform" else 0

    def optimisers(self) -> list[StackedAdam]:
        return [self.actor_adam, self.critic_adam]

    # -- acting -----------------------------------------------------------------------------------------------

    def _forward(self, net: ParamStack, obs: th.Tensor, actions: th.Tensor | None,
                 squash: bool) -> tuple[list[Encoded] | None, list[th.Tensor]]:
        """(the encoder's saved values — None for the vector observation —, the MLP head's [input, outputs]) of
        network ``net`` on observations ``[K, M, obs]`` (and, for a critic, ``actions`` ``[K, M, A]``)."""
        saved, features = self._features(net, obs, actions)
        return saved, mlp_forward(self.mm, net.layers(), features, squash)

    def _features(self, net: ParamStack, obs: th.Tensor,
                  actions: th.Tensor | None) -> tuple[list[Encoded] | None, th.Tensor]:
        """(the encoder's saved values — None for the vector observation —, the MLP head's input) of network
        ``net``: the set encoder's features (or ``obs`` itself), then ``actions`` appended for a critic."""
        saved = None
        features = obs
        if self.layout is not None:
            features, saved = encode(self.mm, self.layout, net.views(), obs, self.dense)
        if actions is not None:
            features = th.cat([features, actions], dim=2)
        return saved, features

    def _backward(self, net: ParamStack, saved: list[Encoded] | None, outs: list[th.Tensor], grad: th.Tensor,
                  squash: bool) -> list[th.Tensor]:
        """The gradients of ``net``'s tensors (its encoder's, then its head's) from its output's gradient."""
        grads, grad_input = mlp_backward(self.mm, net.layers(), outs, grad, squash, to_input=saved is not None)
        if saved is None or self.layout is None:
            return grads
        assert grad_input is not None
        return [*encode_backward(self.mm, self.layout, net.views(), saved, grad_input[..., :self.features_dim]),
                *grads]

    def actor_output(self, obs: Any) -> th.Tensor:
        """μ(s) of every run's slots, ``[K · slots, actions]`` in [−1, 1] (obs ``[K · slots, obs]``, or the set
        observation's dict)."""
        with th.no_grad():
            return self._forward(self.actor, self._obs(obs), None, True)[1][-1].reshape(self.rows, -1)

    def act(self, obs: np.ndarray, explore: bool = True) -> np.ndarray:
        """Every run's actions for the env, ``[K · slots, actions]`` (SB3's ``_sample_action``: random for the first
        :attr:`random_steps`, then μ(s); with ``explore`` plus the run's OU noise, clipped; without, ``predict``'s
        deterministic action)."""
        policy = self._policy
        if explore and self.num_timesteps < self.random_steps:
            unscaled = np.stack([space.sample() for space in self.streams.spaces for _ in range(self.slots)])
        else:
            unscaled = policy.unscale_action(self.actor_output(obs).cpu().numpy())
            if not explore:
                return unscaled
        scaled = np.clip(policy.scale_action(unscaled) + self.noise(self.streams), -1, 1)
        actions = policy.unscale_action(scaled)
        self._last = (actions, scaled)
        return actions

    def use_device_streams(self, generator: th.Generator | None) -> None:
        super().use_device_streams(generator)
        d = self.device
        self._ou_prev = th.as_tensor(self.noise.prev, dtype=th.float64).to(d)
        self._ou_sigma = th.as_tensor(self.noise.sigma, dtype=th.float64).to(d)
        self._ou_theta = th.as_tensor(self.noise.theta, dtype=th.float64).to(d)
        low, high = (th.as_tensor(np.asarray(b, dtype=np.float32)).to(d) for b in
                     (self.action_space.low, self.action_space.high))  # type: ignore[attr-defined]
        self._low, self._span = low, high - low

    def act_on_device(self, obs: th.Tensor, random: bool) -> tuple[th.Tensor, th.Tensor]:
        """:meth:`act` (exploring) with device streams: (the env's actions, the buffer's scaled ones) ``[K, A]``:
        uniform random actions where ``random``, else μ(s), plus the OU noise as SB3's (dt = 0.01, float64 state,
        from device normals; added to the random actions too, as SB3 adds it), clipped to [−1, 1]."""
        normal = th.randn(self._ou_prev.shape, generator=self.generator, dtype=th.float64, device=self.device)
        noise = (self._ou_prev - self._ou_theta * self._ou_prev * OUNoise.DT
                 + self._ou_sigma * OUNoise.DT ** 0.5 * normal)
        self._ou_prev.copy_(noise)
        base = ((self._rand(self.runs, self._low.shape[0]) * 2.0 - 1.0).float() if random  # SB3: uniform, noise too
                else self.actor_output(obs))
        scaled = th.clamp(base + noise.float(), -1.0, 1.0)
        return self._low + 0.5 * (scaled + 1.0) * self._span, scaled

    def device_state(self) -> dict[str, Any]:
        return {**super().device_state(), "ou": self._ou_prev.cpu()}

    def load_device_state(self, state: dict[str, Any]) -> None:
        super().load_device_state(state)
        self._ou_prev.copy_(state["ou"])

    def _buffer_actions(self, action: np.ndarray) -> np.ndarray:
        """The scaled action SB3 stores: the one :meth:`act` computed for ``action``, else ``action`` scaled."""
        if self._last is not None and action is self._last[0]:
            return self._last[1]
        return self._policy.scale_action(np.asarray(action).reshape(self.rows, -1))

    def _episodes_ended(self, done: np.ndarray) -> None:
        self.noise.reset(done)
        if self.device_streams:
            self._ou_prev[th.as_tensor(done).to(self.device)] = 0.0

    # -- the update -------------------------------------------------------------------------------------------

    def _update(self) -> None:
        self._learn(self.streams.sample_indices(self.replay.size(), self.batch_size, self.slots))

    def _learn(self, indices: np.ndarray | th.Tensor) -> None:
        mm = self.mm
        obs, actions, next_obs, dones, rewards = self.replay.gather(indices)
        critic = self.critic.layers()
        with th.no_grad():
            next_actions = self._forward(self.actor_target, next_obs, None, True)[1][-1]
            next_q = self._forward(self.critic_target, next_obs, next_actions, False)[1][-1]
            target_q = rewards + (1 - dones) * self._gamma * next_q

            saved, q_outs = self._forward(self.critic, obs, actions, False)
            critic_loss = F.mse_loss(q_outs[-1], target_q, reduction="none").mean(dim=(1, 2))
            grad_q = (q_outs[-1] - target_q).mul_(2.0 / self.batch_size)  # mse_loss_backward (mean)
            self.critic_adam.step(self._backward(self.critic, saved, q_outs, grad_q, False))

            if self._penalty is None:
                saved, actor_outs = self._forward(self.actor, obs, None, True)
                action = actor_outs[-1]
            else:  # keep the pre-tanh output u
                saved, actor_outs = self._forward(self.actor, obs, None, False)
                action = th.tanh(actor_outs[-1])
            q = self._forward(self.critic, obs, action, False)[1]
            actor_loss = -q[-1].mean(dim=(1, 2))
            grad_mean = (-self._one).expand(q[-1].shape) / self.batch_size  # autograd's d(−mean)/dq
            grad_input = mlp_backward(mm, critic, q, grad_mean, False, weights=False, to_input=True)[1]
            assert grad_input is not None
            grad_action = grad_input[:, :, self.features_dim:]
            if self._penalty is None:
                self.actor_adam.step(self._backward(self.actor, saved, actor_outs, grad_action, True))
            else:  # + λ·mean(u²): autograd's (λ / numel) · (2 u) added to the tanh's gradient
                u = actor_outs[-1]
                actor_loss = actor_loss + self._penalty[:, 0, 0] * u.square().mean(dim=(1, 2))
                grad_u = aten.tanh_backward(grad_action, action) + (self._penalty / u[0].numel()) * (2.0 * u)
                self.actor_adam.step(self._backward(self.actor, saved, actor_outs, grad_u, False))

            soft_update(self.critic_target, self.critic, self._tau, self._one_minus_tau, self._shared_tau)
            soft_update(self.actor_target, self.actor, self._tau, self._one_minus_tau, self._shared_tau)
        self.losses = {"critic_loss": critic_loss, "actor_loss": actor_loss}

    # -- checkpoint and export --------------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        return {**super().state_dict(), "actor": self.actor.flat, "critic": self.critic.flat,
                "actor_target": self.actor_target.flat, "critic_target": self.critic_target.flat,
                "actor_adam": self.actor_adam.state_dict(), "critic_adam": self.critic_adam.state_dict(),
                "noise": th.from_numpy(self.noise.prev.copy())}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        for name in ("actor", "critic", "actor_target", "critic_target"):
            getattr(self, name).flat.copy_(state[name])
        self.actor_adam.load_state_dict(state["actor_adam"])
        self.critic_adam.load_state_dict(state["critic_adam"])
        self.noise.prev = th.as_tensor(state["noise"], dtype=th.float64).cpu().numpy().copy()
        self._last = None

    def _model_kwargs(self, k: int) -> dict[str, Any]:
        """Run k's constructor arguments of the SB3 class beyond those all these learners share."""
        return {}

    def _choices(self, k: int) -> dict[str, Any]:
        """Run k's choices SB3's class lacks, kept as attributes of its exported model (``model.zip`` records
        them; SB3 itself trains without them)."""
        return {"warmup_actions": self.warmup_actions, "pre_tanh_penalty": self.pre_tanh_penalty[k]}

    def sb3_model(self, k: int) -> Any:
        """Run k as a model of the registry's SB3 class (``DDPG``, or ``TD3``): its hyperparameters, its networks,
        Adam states and step counts, and the learner choices SB3's class lacks as attributes."""
        from lanefree_sumo.rl.algorithms import get_algorithm

        cls = get_algorithm(self.algo).cls
        n_actions = int(self.action_space.shape[0])  # type: ignore[index]
        noise = OrnsteinUhlenbeckActionNoise(np.zeros(n_actions), self.ou_sigma[k] * np.ones(n_actions),
                                             theta=self.ou_theta[k])
        with kept_random_state():
            model = cls("MlpPolicy" if self.encoder is None else "MultiInputPolicy",
                        SpacesEnv(self.observation_space, self.action_space),
                        learning_rate=self.learning_rate[k], buffer_size=self.buffer_size, batch_size=self.batch_size,
                        gamma=self.gamma[k], tau=self.tau[k], learning_starts=self.learning_starts, train_freq=1,
                        gradient_steps=1, action_noise=noise, seed=self.seeds[k], device="cpu", verbose=0,
                        policy_kwargs=policy_kwargs(self.actor_layers, self.critic_layers, self.encoder),
                        **self._model_kwargs(k))
        for key, value in self._choices(k).items():
            setattr(model, key, value)
        with th.no_grad():
            for net, stack in ((model.actor, self.actor), (model.critic, self.critic),
                               (model.actor_target, self.actor_target), (model.critic_target, self.critic_target)):
                for p, value in zip(net.parameters(), stack.row(k)):
                    p.copy_(value)
        for net, adam in ((model.actor, self.actor_adam), (model.critic, self.critic_adam)):
            if adam.steps:
                state = net.optimizer.state_dict()
                state["state"] = adam.sb3_state(k, list(net.parameters()))
                net.optimizer.load_state_dict(state)
        model.num_timesteps, model._n_updates = self.num_timesteps, self.n_updates
        return model

    def export(self, k: int, path: str | Path) -> None:
        """Write run k as an ordinary ``model.zip`` (``stable_baselines3.DDPG.load`` loads it)."""
        self.sb3_model(k).save(path)

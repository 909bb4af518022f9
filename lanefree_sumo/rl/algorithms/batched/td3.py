"""TD3 for K runs at once: SB3's ``TD3.train`` with a leading run axis, on :class:`~.ddpg.BatchedDDPG`'s parts.

What TD3 adds to DDPG (Fujimoto et al. 2018, as SB3 implements it): two Q-networks on one critic encoder, the
target the smaller of the two target Q-values, clipped Gaussian noise on the target action (σ 0.2, clipped at
0.5), and the actor and both targets updated every ``policy_delay`` (2) critic updates. Run k draws that noise
from its own torch generator, started where SB3's global generator stands after building run k's policy, so on
CPU run k's parameters, targets and Adam moments equal ``stable_baselines3.TD3``'s with seed k bit for bit on
the vector observation (``tests/rl/test_batched_learners.py``), and to float tolerance on the set observation
(``tests/rl/test_batched_set.py``). The noise is drawn on the host, so TD3 trains in the exact loop, never the
lockstep loop (:func:`~lanefree_sumo.rl.lockstep.lockstep_refusal`). ``losses["actor_loss"]`` is the last actor
update's (every ``policy_delay``-th update; absent before the first).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch as th
from gymnasium import spaces
from torch.nn import functional as F

from lanefree_sumo.rl.algorithms.batched.ddpg import BatchedDDPG
from lanefree_sumo.rl.algorithms.batched.learner import per_run
from lanefree_sumo.rl.algorithms.batched.set_encoder import Encoded, encode_backward
from lanefree_sumo.rl.algorithms.batched.stack import Linear, ParamStack, mlp_backward, mlp_forward, soft_update


class BatchedTD3(BatchedDDPG):
    """TD3 (SB3's, as ``lanefree train --algo td3`` configures it) for K runs; module docstring.

    :param policy_delay: critic updates per actor and target update.
    :param target_policy_noise: σ of the target action's Gaussian noise (scaled action units).
    :param target_noise_clip: the bound of that noise.

    The other parameters are :class:`~.ddpg.BatchedDDPG`'s (TD3 has no pre-tanh penalty and SB3's uniform
    warm-up only)."""

    n_critics = 2
    algo = "td3"
    host_draws = "TD3's target noise"

    def __init__(self, observation_space: spaces.Space, action_space: spaces.Space, seeds: Sequence[int], *,
                 policy_delay: int = 2, target_policy_noise: float = 0.2, target_noise_clip: float = 0.5,
                 **kwargs: Any) -> None:
        if kwargs.get("warmup_actions", "uniform") != "uniform" or any(
                per_run(kwargs.get("pre_tanh_penalty", 0.0), len(seeds), "pre_tanh_penalty")):
            raise ValueError("batched TD3 takes SB3's uniform warm-up and no pre-tanh penalty")
        super().__init__(observation_space, action_space, seeds, **kwargs)
        self.policy_delay = int(policy_delay)
        self.target_policy_noise, self.target_noise_clip = float(target_policy_noise), float(target_noise_clip)
        self.generators = []
        """Run k's torch generator of the target noise (on the CPU, where SB3 draws it)."""
        for state in self._torch_states:
            generator = th.Generator()
            generator.set_state(state)
            self.generators.append(generator)

    def use_device_streams(self, generator: th.Generator | None) -> None:
        raise RuntimeError("batched TD3 draws its target noise on the host: it trains in the exact loop only")

    def _heads(self, layers: list[Linear]) -> list[list[Linear]]:
        """The critic's layers as its Q-networks' (in order)."""
        n = len(layers) // self.n_critics
        return [layers[i * n:(i + 1) * n] for i in range(self.n_critics)]

    def _critic(self, net: ParamStack, obs: th.Tensor, actions: th.Tensor,
                heads: int = 2) -> tuple[list[Encoded] | None, list[list[th.Tensor]]]:
        """(the encoder's saved values — None for the vector observation —, the first ``heads`` Q-networks'
        [input, outputs]) of critic ``net``: one encoder, its features and the actions the heads' input."""
        saved, x = self._features(net, obs, actions)
        return saved, [mlp_forward(self.mm, head, x, False) for head in self._heads(net.layers())[:heads]]

    def _noise(self, shape: th.Size) -> th.Tensor:
        """Every run's target noise ``[K, batch, actions]``: SB3's ``normal_(0, σ)`` on the run's generator,
        clipped."""
        draws = [th.empty(tuple(shape[1:])).normal_(0, self.target_policy_noise, generator=g)
                 for g in self.generators]
        return th.stack(draws).to(self.device).clamp(-self.target_noise_clip, self.target_noise_clip)

    def _learn(self, indices: Any) -> None:
        mm = self.mm
        obs, actions, next_obs, dones, rewards = self.replay.gather(indices)
        with th.no_grad():
            noise = self._noise(actions.shape)
            next_actions = (self._forward(self.actor_target, next_obs, None, True)[1][-1] + noise).clamp(-1, 1)
            next_q = th.minimum(*(outs[-1] for outs in self._critic(self.critic_target, next_obs, next_actions)[1]))
            target_q = rewards + (1 - dones) * self._gamma * next_q

            saved, q_outs = self._critic(self.critic, obs, actions)
            critic_loss = sum(F.mse_loss(outs[-1], target_q, reduction="none").mean(dim=(1, 2)) for outs in q_outs)
            grads: list[th.Tensor] = []
            grad_in: th.Tensor | None = None
            for head, outs in zip(self._heads(self.critic.layers()), q_outs):
                grad_q = (outs[-1] - target_q).mul_(2.0 / self.batch_size)  # mse_loss_backward (mean)
                head_grads, head_in = mlp_backward(mm, head, outs, grad_q, False, to_input=saved is not None)
                grads += head_grads
                if head_in is not None:
                    grad_in = head_in if grad_in is None else grad_in + head_in
            if saved is not None and self.layout is not None and grad_in is not None:
                grads = [*encode_backward(mm, self.layout, self.critic.views(), saved,
                                          grad_in[..., :self.features_dim]), *grads]
            self.critic_adam.step(grads)
            self.losses = {**self.losses, "critic_loss": th.as_tensor(critic_loss)}

            if self.n_updates % self.policy_delay == 0:  # SB3's q1_forward: the first Q-network
                saved, actor_outs = self._forward(self.actor, obs, None, True)
                q = self._critic(self.critic, obs, actor_outs[-1], heads=1)[1][0]
                actor_loss = -q[-1].mean(dim=(1, 2))
                grad_mean = (-self._one).expand(q[-1].shape) / self.batch_size  # autograd's d(−mean)/dq
                first = self._heads(self.critic.layers())[0]
                grad_input = mlp_backward(mm, first, q, grad_mean, False, weights=False, to_input=True)[1]
                assert grad_input is not None
                self.actor_adam.step(self._backward(self.actor, saved, actor_outs,
                                                    grad_input[:, :, self.features_dim:], True))
                soft_update(self.critic_target, self.critic, self._tau, self._one_minus_tau, self._shared_tau)
                soft_update(self.actor_target, self.actor, self._tau, self._one_minus_tau, self._shared_tau)
                self.losses["actor_loss"] = actor_loss

    def _model_kwargs(self, k: int) -> dict[str, Any]:
        return {"policy_delay": self.policy_delay, "target_policy_noise": self.target_policy_noise,
                "target_noise_clip": self.target_noise_clip}

    def _choices(self, k: int) -> dict[str, Any]:
        return {}

    def state_dict(self) -> dict[str, Any]:
        return {**super().state_dict(), "target_noise": [g.get_state() for g in self.generators]}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        for g, s in zip(self.generators, state["target_noise"]):
            g.set_state(s)

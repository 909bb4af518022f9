"""The DQN family's Q-network heads that SB3 lacks: the dueling head (Wang et al. 2016) and its policies.

``Q(s, a) = V(s) + A(s, a) − mean_a' A(s, a')``. A module of its own, below the algorithms: the
batched learner (:mod:`.batched.dqn`) writes these heads out, and a ``dueling`` run's ``model.zip`` is SB3's
``DQN`` with these policies (the registry's :meth:`~lanefree_sumo.rl.algorithms.AlgorithmSpec.policy`).
"""

from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.torch_layers import (
    BaseFeaturesExtractor,
    CombinedExtractor,
    create_mlp,
)
from stable_baselines3.common.type_aliases import (
    PyTorchObs,
    Schedule,
)
from stable_baselines3.dqn.policies import DQNPolicy, QNetwork
from torch import nn

__all__ = ["DuelingDQNPolicy", "DuelingHead", "DuelingQNetwork", "MultiInputDuelingDQNPolicy"]


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
        self.q_net = DuelingHead(  # type: ignore[assignment]  # SB3 types q_net as the plain Sequential
            self.features_dim, int(self.action_space.n), self.net_arch, self.activation_fn
        )

    def value_and_advantage(self, obs: PyTorchObs) -> tuple[th.Tensor, th.Tensor]:
        """Raw head outputs ``(V (batch, 1), A (batch, n_actions))``."""
        head: DuelingHead = self.q_net  # type: ignore[assignment]
        hidden = head.trunk(self.extract_features(obs, self.features_extractor))
        return head.value_head(hidden), head.advantage_head(hidden)


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

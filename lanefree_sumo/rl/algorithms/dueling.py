"""Dueling architecture (Wang et al. 2016) on double DQN.

``Q(s, a) = V(s) + A(s, a) − mean_a' A(s, a')``. :class:`DuelingDoubleDQN` is
:class:`~lanefree_sumo.rl.algorithms.double_dqn.DoubleDQN` whose ``"MlpPolicy"`` /
``"MultiInputPolicy"`` aliases are the dueling policies of :mod:`.q_networks`.
"""


from typing import ClassVar

from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.dqn.policies import CnnPolicy

from lanefree_sumo.rl.algorithms.double_dqn import DoubleDQN
from lanefree_sumo.rl.algorithms.q_networks import DuelingDQNPolicy, MultiInputDuelingDQNPolicy

__all__ = ["DuelingDoubleDQN"]


class DuelingDoubleDQN(DoubleDQN):
    """Dueling double DQN (Wang et al. 2016 + Van Hasselt et al. 2016).

    Same as :class:`DoubleDQN`; only the policy aliases differ: ``"MlpPolicy"``
    is :class:`DuelingDQNPolicy` and ``"MultiInputPolicy"`` is
    :class:`MultiInputDuelingDQNPolicy`.
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": DuelingDQNPolicy,
        "CnnPolicy": CnnPolicy,  # no dueling CNN variant is needed by the project
        "MultiInputPolicy": MultiInputDuelingDQNPolicy,
    }

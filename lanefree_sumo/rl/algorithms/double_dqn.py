"""Double DQN (Van Hasselt, Guez & Silver 2016) as a Stable-Baselines3 class.

The TD target uses the action chosen by the *online* network and evaluated by the *target*
network: ``y = r + γ (1 − d) Q_target(s', argmax_a Q_online(s', a))``. :class:`DoubleDQN` is
:class:`~.dqn.LaneFreeDQN` with ``double_q`` set: its update's target hook computes that target.
"""

from typing import ClassVar

from lanefree_sumo.rl.algorithms.dqn import LaneFreeDQN


class DoubleDQN(LaneFreeDQN):
    """Double DQN (Van Hasselt, Guez & Silver 2016) on top of SB3's ``DQN`` (through :class:`~.dqn.LaneFreeDQN`).

    Identical to ``stable_baselines3.DQN`` except for the TD target, which
    decouples action selection (online ``q_net``) from evaluation (``q_net_target``):
    ``y = r + γ (1 - d) Q_target(s', argmax_a Q_online(s', a))``.
    Constructor arguments are those of ``DQN``.

    The hooks (``_sample_batch``, ``_compute_target_q_values``, ``_compute_loss``,
    ``_after_gradient_step``) are :class:`~.dqn.LaneFreeDQN`'s, which computes the
    double-Q target when ``double_q`` is set.
    """

    double_q: ClassVar[bool] = True

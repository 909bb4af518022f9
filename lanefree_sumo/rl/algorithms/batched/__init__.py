"""Off-policy learners for K runs of one algorithm (or dqn and ddqn together) in one process: weights stacked
``[K, …]``, one batched product per layer for all runs, one Adam buffer ``[K, P]``, per-run replay
``[K, capacity, …]`` and per-run random streams.

:class:`BatchedDDPG`, :class:`BatchedTD3` and :class:`BatchedDQN` (DQN, double, dueling, prioritised) take every run's
observation and give every run's action (:meth:`~.learner.BatchedLearner.act`), store every run's transition
(``store``), and make one gradient step per run (``update``); ``state_dict``/``load_state_dict`` checkpoint the
batch and ``export(k, path)`` writes run k as an ordinary SB3 ``model.zip``. On CPU run k computes exactly what
SB3's update (SB3's DDPG, TD3 and DQN, with the choices SB3 lacks written in) computes for one run of seed k (on the
set observation: to float tolerance, :mod:`.set_encoder`). They are the only implementation of these algorithms'
updates; SB3's classes are their ``model.zip``.
"""

from lanefree_sumo.rl.algorithms.batched.ddpg import BatchedDDPG
from lanefree_sumo.rl.algorithms.batched.dqn import BatchedDQN
from lanefree_sumo.rl.algorithms.batched.td3 import BatchedTD3

__all__ = ["BatchedDDPG", "BatchedDQN", "BatchedTD3"]

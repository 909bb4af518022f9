"""THE algorithm registry: name → the SB3 class of its ``model.zip``, action kind, on/off-policy, config section,
its batched learner; the names are the config's ``AlgorithmName`` (the config room imports nothing of this one).

Training, evaluation, the benchmark, the CLI's help and the tests all read :data:`ALGORITHMS`.
Classes are imported only when asked for (``spec.cls``), so listing algorithms costs no torch
import. Every algorithm with a batched learner (:mod:`.batched`: DDPG, TD3 and the DQN family) trains there,
for one run and for K; its ``model.zip`` is an ordinary model of stock SB3's class (``DDPG``, ``TD3``, ``DQN``; the
dueling network's policy from :mod:`.q_networks`), which evaluation loads. SAC and PPO train in SB3's own loop.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any, Literal, get_args

from lanefree_sumo.config import AlgorithmName
from lanefree_sumo.errors import ConfigError


@dataclass(frozen=True)
class AlgorithmSpec:
    """What the platform needs to know about one algorithm."""

    name: AlgorithmName
    """One of the config's names (a name the schema lacks is a type error)."""
    target: str
    """``module:attribute`` of the SB3 class of its ``model.zip`` (and, for SAC and PPO, of its training)."""
    actions: Literal["continuous", "discrete"]
    off_policy: bool
    """Keeps a replay buffer (checkpointed with the model)."""
    config_section: Literal["actor_critic", "dqn"]
    """Section of ``TrainConfig`` with its hyperparameters."""
    summary: str
    """One line for ``--help``."""
    choices: tuple[str, ...] = ()
    """Keys of its ``config_section`` that SB3's class lacks and its batched learner takes (``warmup_actions``,
    ``pre_tanh_penalty``, ``loss``); a value other than SB3's for a key an algorithm does not take is refused."""
    double_q: bool = False
    """The DQN family's TD target takes the online network's argmax (double DQN) rather than the target's."""
    dueling: bool = False
    """The DQN family's Q-network is the dueling head (:mod:`.q_networks`)."""
    prioritized: bool = False
    """The DQN family's replay is proportional prioritised replay (:class:`~.batched.replay.RunPriorities`)."""
    batched_target: str = ""
    """``module:attribute`` of its batched learner (:mod:`.batched`), which trains it as a batch of K runs in one
    array program (``lanefree train``, ``--seeds``, ``sweep --batch``, the GPU); empty: SB3's loop only."""
    unread_keys: tuple[str, ...] = ()
    """Keys of its own ``config_section`` the model never reads (PPO keeps no replay buffer, SAC adds no
    Ornstein-Uhlenbeck noise, the off-policy algorithms have no rollout length)."""

    @property
    def cls(self) -> Any:
        """Stock SB3's class of its ``model.zip`` (imported on first use)."""
        return _load(self.target)

    def policy(self, name: str) -> Any:
        """The SB3 policy class of ``name`` (``MlpPolicy``, ``MultiInputPolicy``) for this algorithm: the dueling
        policies of :mod:`.q_networks` for the dueling network, else :attr:`cls`'s own alias."""
        if self.dueling:
            from lanefree_sumo.rl.algorithms.q_networks import DuelingDQNPolicy, MultiInputDuelingDQNPolicy

            return {"MlpPolicy": DuelingDQNPolicy, "MultiInputPolicy": MultiInputDuelingDQNPolicy}[name]
        return self.cls.policy_aliases[name]

    @property
    def batched(self) -> bool:
        """It has a batched learner (:attr:`batched_target`)."""
        return bool(self.batched_target)

    @property
    def batched_cls(self) -> Any:
        """The batched learner's class (imported on first use); ConfigError for an algorithm without one."""
        if not self.batched:
            raise ConfigError(f"batched training covers {', '.join(BATCHED)}, not {self.name}; train it run by run")
        return _load(self.batched_target)


def _load(target: str) -> Any:
    """The attribute ``module:attribute`` names."""
    module, attribute = target.split(":")
    return getattr(importlib.import_module(module), attribute)


_BATCHED = "lanefree_sumo.rl.algorithms.batched"
_OU = ("ou_sigma", "ou_theta")
_DQN = "stable_baselines3:DQN"
_SPECS: dict[str, AlgorithmSpec] = {
    spec.name: spec
    for spec in (
        AlgorithmSpec("ddpg", "stable_baselines3:DDPG", "continuous", True, "actor_critic",
                      "DDPG with Ornstein-Uhlenbeck noise (the paper's main algorithm)",
                      choices=("warmup_actions", "pre_tanh_penalty"),
                      batched_target=f"{_BATCHED}.ddpg:BatchedDDPG", unread_keys=("ppo_n_steps",)),
        AlgorithmSpec("td3", "stable_baselines3:TD3", "continuous", True, "actor_critic", "TD3",
                      batched_target=f"{_BATCHED}.td3:BatchedTD3", unread_keys=("ppo_n_steps",)),
        AlgorithmSpec("sac", "stable_baselines3:SAC", "continuous", True, "actor_critic", "SAC",
                      unread_keys=("ppo_n_steps", *_OU)),
        AlgorithmSpec("ppo", "stable_baselines3:PPO", "continuous", False, "actor_critic", "PPO",
                      unread_keys=("buffer_size", "tau", "learning_starts_steps", *_OU)),
        AlgorithmSpec("dqn", _DQN, "discrete", True, "dqn", "DQN", choices=("loss",),
                      batched_target=f"{_BATCHED}.dqn:BatchedDQN"),
        AlgorithmSpec("ddqn", _DQN, "discrete", True, "dqn", "double DQN", choices=("loss",), double_q=True,
                      batched_target=f"{_BATCHED}.dqn:BatchedDQN"),
        AlgorithmSpec("dueling", _DQN, "discrete", True, "dqn", "dueling double DQN", choices=("loss",),
                      double_q=True, dueling=True, batched_target=f"{_BATCHED}.dqn:BatchedDQN"),
        AlgorithmSpec("per", _DQN, "discrete", True, "dqn", "double DQN with prioritised replay",
                      choices=("loss",), double_q=True, prioritized=True,
                      batched_target=f"{_BATCHED}.dqn:BatchedDQN"),
    )
}
ALGORITHM_NAMES: tuple[str, ...] = get_args(AlgorithmName)
"""The algorithms' names: the config's :data:`~lanefree_sumo.config.AlgorithmName`, in its order."""
if set(_SPECS) != set(ALGORITHM_NAMES):  # a name without a class, or a class the config would refuse
    raise ImportError(f"the registry's algorithms {sorted(_SPECS)} are not the config's {sorted(ALGORITHM_NAMES)}")
ALGORITHMS: dict[str, AlgorithmSpec] = {name: _SPECS[name] for name in ALGORITHM_NAMES}
"""THE registry, keyed by the config's algorithm names."""


BATCHED: tuple[str, ...] = tuple(name for name, spec in ALGORITHMS.items() if spec.batched)
"""The algorithms a batch trains (:attr:`AlgorithmSpec.batched`), in the registry's order."""


def get_algorithm(name: str) -> AlgorithmSpec:
    """The registry entry of ``name``; ConfigError naming the valid ones otherwise."""
    try:
        return ALGORITHMS[name]
    except KeyError:
        raise ConfigError(f"unknown algorithm '{name}'; choose one of {', '.join(ALGORITHM_NAMES)}") from None


def unused_config(name: str) -> tuple[str, ...]:
    """Config sections and keys (dotted) a run of algorithm ``name`` never reads: the other family's
    hyperparameters (``train.dqn`` for DDPG, ``train.actor_critic`` for DQN) and its own section's
    :attr:`~AlgorithmSpec.unread_keys` (``train.actor_critic.ppo_n_steps`` for DDPG). A difference there
    does not make another run, so report variants and sweep adoption ignore them."""
    spec = ALGORITHMS.get(name)
    if spec is None:
        return ()
    sections = dict.fromkeys(s.config_section for s in ALGORITHMS.values())
    return (*(f"train.{section}" for section in sections if section != spec.config_section),
            *(f"train.{spec.config_section}.{key}" for key in spec.unread_keys))


def help_text() -> str:
    """``name (summary, action kind)`` of every algorithm, for ``--help``."""
    return "; ".join(f"{s.name}: {s.summary} ({s.actions} actions)" for s in ALGORITHMS.values())

"""Models and environments with the paper's hyperparameters (specification §9).

``training_config`` fixes what the algorithm decides (action kind, the agent on the road);
``make_vec_env`` builds the environments (one process each when several: libsumo runs one
simulation per process); ``build_model`` a new model of stock SB3's class for ``cfg.train.algo`` with the
hyperparameters of ``cfg.train`` (SAC's, PPO's training); ``build_batched`` the batched learner
(:mod:`lanefree_sumo.rl.algorithms.batched`) of several runs of one algorithm, each with its config's;
``load_saved_model`` a run's ``model.zip``.
"""

from __future__ import annotations

import math
import os
import signal
from collections.abc import Callable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np

from lanefree_sumo.config import LaneFreeConfig, ResolvedConfig, merge_config
from lanefree_sumo.errors import ConfigError
from lanefree_sumo.rl.algorithms import get_algorithm

MAX_ENVS_PER_CORE = 4
"""Parallel environments (one process each) allowed per core: more only thrash and exhaust memory."""


def training_config(base: LaneFreeConfig) -> ResolvedConfig:
    """``base`` resolved for training, once: the parts training decides fixed (the action kind from the
    algorithm, the backend from ``train.backend``), then :func:`~lanefree_sumo.rl.env.resolve_config`; what the
    environments would refuse is refused here, not inside their processes. A config this resolved already is
    returned as it is."""
    kind = get_algorithm(base.train.algo).actions
    if base.train.episodes < 1 or base.train.envs < 1 or base.train.checkpoint_every_episodes < 1:
        raise ConfigError("episodes, envs and checkpoint-every must be at least 1")
    t = base.train
    if base.scenario.agents > 1 and t.envs > 1:
        raise ConfigError(f"--agents {base.scenario.agents} trains one shared policy in one simulation: "
                          "use --envs 1 with it")
    most = MAX_ENVS_PER_CORE * (os.cpu_count() or 1)
    if base.train.envs > most and not get_algorithm(t.algo).batched:  # the one trainer runs them in this process
        raise ConfigError(f"--envs {base.train.envs} starts one process per environment with {t.algo}; this machine "
                          f"has {os.cpu_count()} cores: use at most {most}")
    if isinstance(base, ResolvedConfig) and base.action.kind == kind and base.backend == t.backend:
        return base
    from lanefree_sumo.rl.env import resolve_config

    return resolve_config(merge_config(base, {"action": {"kind": kind}, "backend": t.backend}))


def slots(cfg: LaneFreeConfig) -> int:
    """The environments or learning vehicles one policy of run ``cfg`` acts for at each step (SB3's ``n_envs``):
    ``train.envs`` environments, or ``scenario.agents`` vehicles of one simulation (never both)."""
    return cfg.train.envs * cfg.scenario.agents


def total_timesteps(cfg: LaneFreeConfig) -> int:
    """SB3 timesteps (transitions) of a whole run: every episode, plus one round of the parallel envs as
    slack (the callback stops learning at the episode count; this only has to be enough); with several
    agents each simulation step is one transition per agent."""
    return (cfg.train.episodes + cfg.train.envs) * cfg.sim.episode_steps * cfg.scenario.agents


def episode_seed(run_seed: int, rank: int, episode: int) -> int:
    """The traffic seed (0 … 2³¹ − 1) of the ``episode``-th episode (1, 2, …) of environment ``rank`` of
    a run seeded ``run_seed``: a function of these three numbers only, so a resumed run sees the same
    traffic as one that was never interrupted."""
    return int(np.random.SeedSequence([run_seed, rank, episode]).generate_state(1)[0] & 0x7FFFFFFF)


class EpisodeSeeds(gym.Wrapper):
    """Gives the episodes of a training environment the traffic seeds :func:`episode_seed` (``run_seed``,
    ``rank``, k) for k = ``first_episode``, ``first_episode`` + 1, …; a seed passed to ``reset`` (SB3
    passes the model's seed) is ignored: the schedule decides."""

    def __init__(self, env: gym.Env, run_seed: int, rank: int, first_episode: int) -> None:
        super().__init__(env)
        self.run_seed, self.rank, self.next_episode = run_seed, rank, first_episode

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> Any:
        chosen = episode_seed(self.run_seed, self.rank, self.next_episode)
        self.next_episode += 1
        return self.env.reset(seed=chosen, options=options)


def _env_factory(cfg: LaneFreeConfig, rank: int, seed: int, first_episode: int,
                 subprocess_env: bool) -> Callable[[], Any]:
    """Makes environment ``rank``; in a worker process too, from ``cfg`` as resolved (pickled, not resolved
    again)."""

    def make() -> Any:
        from stable_baselines3.common.monitor import Monitor

        from lanefree_sumo.rl.env import LaneFreeEnv

        if subprocess_env:
            # Ctrl-C reaches the whole process group: only the trainer handles it (checkpoint,
            # then closing the workers); a worker dying first would lose the checkpoint.
            signal.signal(signal.SIGINT, signal.SIG_IGN)

        return Monitor(EpisodeSeeds(LaneFreeEnv(cfg), seed, rank, first_episode))

    return make


def make_vec_env(cfg: LaneFreeConfig, episodes_done: int = 0) -> Any:
    """``cfg.train.envs`` environments (in this process for 1, else one process each) whose episodes continue a
    run of seed ``cfg.seed`` after ``episodes_done`` episodes: environment r's k-th episode has the traffic seed
    :func:`episode_seed` (seed, r, k). With one environment episode k of the run is episode k of the environment,
    so a resumed run sees exactly the traffic of an uninterrupted one; with several, which environment finishes
    which episode depends on timing, and a resume restarts each environment at episode ``episodes_done // envs +
    1``. With ``scenario.agents`` > 1: the agents of one multi-agent simulation as the environments
    (:class:`~lanefree_sumo.rl.multi_agent.SharedPolicyVecEnv`), episode k with the traffic seed (seed, 0, k) as a
    one-agent run's."""
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecEnv

    if cfg.scenario.agents > 1:
        from lanefree_sumo.rl.multi_agent import LaneFreeParallelEnv, SharedPolicyVecEnv

        return SharedPolicyVecEnv(LaneFreeParallelEnv(cfg), seeds=lambda k: episode_seed(cfg.seed, 0, k),
                                  first_episode=episodes_done + 1)
    from lanefree_sumo.rl.env import resolve_config

    resolved = resolve_config(cfg)  # as it is when the run resolved it (training_config)
    n_envs = cfg.train.envs
    own_process = n_envs > 1
    first = episodes_done // n_envs + 1
    factories = [_env_factory(resolved, rank, cfg.seed, first, own_process) for rank in range(n_envs)]
    vec: VecEnv = SubprocVecEnv(factories, start_method="spawn") if own_process else DummyVecEnv(factories)
    return vec


def exploration_fraction(cfg: LaneFreeConfig) -> float:
    """SB3's ``exploration_fraction`` for the DQN family: ε decays over ``epsilon_decay_episodes`` episodes."""
    dq = cfg.train.dqn
    return min(1.0, dq.epsilon_decay_episodes * cfg.sim.episode_steps * cfg.scenario.agents / total_timesteps(cfg))


def _taking(key: str) -> str:
    """The algorithms whose learners take the choice ``key`` (:attr:`~.algorithms.AlgorithmSpec.choices`)."""
    from lanefree_sumo.rl.algorithms import ALGORITHMS

    return ", ".join(name for name, spec in ALGORITHMS.items() if key in spec.choices)


def check_actor_critic_choices(cfg: LaneFreeConfig) -> None:
    """ConfigError (one line) for an actor-critic choice the algorithm's learner does not take (its
    :attr:`~.algorithms.AlgorithmSpec.choices`): the pre-tanh penalty and the warm-up from the policy (an on-policy
    learner has no warm-up)."""
    ac, algo = cfg.train.actor_critic, cfg.train.algo
    spec = get_algorithm(algo)
    takes = spec.choices
    if ac.pre_tanh_penalty and "pre_tanh_penalty" not in takes:
        raise ConfigError(f"train.actor_critic.pre_tanh_penalty = {ac.pre_tanh_penalty:g} is built into the "
                          f"project's {_taking('pre_tanh_penalty')} only; set it to 0 for {algo}")
    if ac.warmup_actions != "uniform" and spec.off_policy and "warmup_actions" not in takes:
        by_profile = cfg.train.profile == "kerasrl" and ac.warmup_actions == "policy"
        raise ConfigError(f"train.actor_critic.warmup_actions = {ac.warmup_actions}"
                          + (" (what train.profile = kerasrl sets)" if by_profile else "")
                          + f" is built for {_taking('warmup_actions')} only; {algo} takes SB3's uniform warm-up"
                          + ("; add --set train.actor_critic.warmup_actions=uniform beside the profile"
                             if by_profile else ""))


def check_trainable(cfg: LaneFreeConfig) -> None:
    """ConfigError (one line) for what no run of ``cfg`` trains, checked alike for one run, a batch and every run
    of a sweep's grid before anything starts: several environments inside SUMO for a batchable algorithm, and the
    learner choices its algorithm lacks (:func:`check_actor_critic_choices`)."""
    spec = get_algorithm(cfg.train.algo)
    if spec.batched and cfg.train.envs != 1 and cfg.train.backend != "numpy":
        raise ConfigError(f"{spec.name} does not train several environments (--envs) inside SUMO (--backend "
                          f"{cfg.train.backend}); train them on --backend numpy (the same episodes), or one "
                          "environment (--envs 1) inside SUMO (libsumo holds one simulation per process)")
    if spec.config_section == "actor_critic":
        check_actor_critic_choices(cfg)


def build_model(cfg: LaneFreeConfig, env: Any, seed: int, tensorboard_log: str | None) -> Any:
    """A new model of stock SB3's class for ``cfg.train.algo`` with the paper's hyperparameters (specification
    §9): how SAC and PPO train (SB3's loop), and SB3's own DDPG, TD3 and DQN, which the benchmark sets beside the
    batched learners. ConfigError for a choice SB3's class lacks (the DQN variants, the learner choices)."""
    import torch
    from stable_baselines3.common.noise import OrnsteinUhlenbeckActionNoise

    algo = cfg.train.algo
    spec = get_algorithm(algo)
    if spec.double_q or spec.dueling or spec.prioritized:
        raise ConfigError(f"SB3 has no {spec.summary}; {algo} trains in its batched learner (lanefree train; "
                          "from Python, build_batched)")
    cls = spec.cls
    set_obs = cfg.observation.kind == "set"
    extractor: dict[str, Any] = {}
    if set_obs:
        from lanefree_sumo.rl.encoder import SetFeaturesExtractor

        extractor = {"features_extractor_class": SetFeaturesExtractor,
                     "features_extractor_kwargs": {"encoder": cfg.observation.encoder}}
    common = {"seed": seed, "verbose": 0, "tensorboard_log": tensorboard_log, "device": "cpu"}
    if spec.config_section == "actor_critic":
        ac = cfg.train.actor_critic
        policy = "MultiInputPolicy" if set_obs else "MlpPolicy"
        nets = {"pi": list(ac.actor_layers), "qf": list(ac.critic_layers)}
        kwargs: dict[str, Any] = {"learning_rate": ac.learning_rate, "gamma": ac.gamma, **common}
        if not spec.off_policy:  # PPO
            nets = {"pi": list(ac.actor_layers), "vf": list(ac.critic_layers)}
            kwargs.update(n_steps=ac.ppo_n_steps, batch_size=ac.batch_size)
        else:
            kwargs.update(
                buffer_size=ac.buffer_size, batch_size=ac.batch_size, tau=ac.tau,
                learning_starts=ac.learning_starts_steps, train_freq=1, gradient_steps=1,
            )
        if "ou_sigma" not in spec.unread_keys:  # DDPG, TD3: Ornstein-Uhlenbeck exploration
            n_actions = env.action_space.shape[0]
            kwargs["action_noise"] = OrnsteinUhlenbeckActionNoise(
                mean=np.zeros(n_actions), sigma=ac.ou_sigma * np.ones(n_actions), theta=ac.ou_theta
            )
        if spec.choices and (ac.pre_tanh_penalty or ac.warmup_actions != "uniform"):
            raise ConfigError(f"SB3's {cls.__name__} has no pre_tanh_penalty or warmup_actions = policy (the "
                              f"latter set by train.profile = kerasrl); {algo} trains with them in its batched learner "
                              "(lanefree train; from Python, build_batched)")
        check_actor_critic_choices(cfg)
        kwargs["policy_kwargs"] = {"net_arch": nets, "activation_fn": torch.nn.ReLU, **extractor}
        return cls(policy, env, **kwargs)

    dq = cfg.train.dqn
    policy = "MultiInputPolicy" if set_obs else "MlpPolicy"
    if dq.loss != "huber":
        raise ConfigError(f"train.dqn.loss = {dq.loss} is the batched learner's; SB3's DQN takes its Huber loss")
    return cls(
        policy, env, learning_rate=dq.learning_rate, buffer_size=dq.buffer_size, batch_size=dq.batch_size,
        gamma=dq.gamma, learning_starts=dq.learning_starts_steps, target_update_interval=dq.target_update_steps,
        exploration_initial_eps=dq.epsilon_start, exploration_final_eps=dq.epsilon_end,
        exploration_fraction=exploration_fraction(cfg), train_freq=1, gradient_steps=1,
        max_grad_norm=math.inf if dq.max_grad_norm is None else dq.max_grad_norm,
        policy_kwargs={"net_arch": list(dq.layers), "activation_fn": torch.nn.ReLU, **extractor},
        **common,
    )


_BATCH_SHARED = {"actor_critic": ("actor_layers", "critic_layers", "batch_size", "buffer_size",
                                  "learning_starts_steps", "warmup_actions"),
                 "dqn": ("layers", "batch_size", "buffer_size", "learning_starts_steps", "target_update_steps",
                         "loss", "max_grad_norm")}
"""What the runs of one batch must share (network shapes and replay sizes); the rest may differ per run."""


def load_saved_model(algo: str, path: Any, **kwargs: Any) -> Any:
    """The ``model.zip`` (or checkpoint) at ``path`` of an ``algo`` run as a model of stock SB3's class, on the CPU
    (``kwargs``: more of SB3's ``load`` arguments, e.g. ``env``)."""
    kwargs.setdefault("device", "cpu")
    # the replay buffer's class and arguments are SB3's again, picked from the spaces: a per model of an earlier
    # version named a buffer class of the project's that no longer exists (a fresh dict each time: SB3 may change it)
    legacy: dict[str, Any] = {"replay_buffer_class": None, "replay_buffer_kwargs": {}}
    return get_algorithm(algo).cls.load(path, custom_objects=legacy, **kwargs)


def build_batched(cfgs: Sequence[LaneFreeConfig], seeds: list[int], observation_space: Any, action_space: Any,
                  device: str = "cpu") -> Any:
    """The batched learner of runs ``cfgs`` (run k seeded ``seeds[k]``): for each run the hyperparameters
    :func:`build_model` gives it; ConfigError when the runs cannot share a batch."""
    from lanefree_sumo.rl.algorithms.batched.dqn import batch_group

    algo = cfgs[0].train.algo
    spec = get_algorithm(algo)
    if any(batch_group(c.train.algo) != batch_group(algo) for c in cfgs):
        raise ConfigError("the runs of one batch must share train.algo (dqn and ddqn may mix); "
                          f"got {', '.join(sorted({c.train.algo for c in cfgs}))}")
    cls = spec.batched_cls  # (ConfigError for an algorithm without a batched learner)
    actor_critic = spec.config_section == "actor_critic"
    if len(seeds) != len(cfgs):
        raise ConfigError(f"{len(cfgs)} configs but {len(seeds)} seeds: give one seed per run")
    sections = [getattr(c.train, spec.config_section) for c in cfgs]
    shared = _BATCH_SHARED[spec.config_section] + (("timesteps",) if not actor_critic else ())
    for key in shared:
        values = {total_timesteps(c) if key == "timesteps" else getattr(s, key) for c, s in zip(cfgs, sections)}
        if len(values) > 1:
            raise ConfigError(f"the runs of one batch must share train.{spec.config_section}.{key} "
                              f"(got {sorted(values, key=str)}); put runs that differ there in separate batches")
    per_run_slots = {slots(c) for c in cfgs}
    if len(per_run_slots) > 1:
        raise ConfigError("the runs of one batch must share scenario.agents and train.envs; put runs that differ "
                          "there in separate batches")
    first = sections[0]
    encoder = cfgs[0].observation.encoder if cfgs[0].observation.kind == "set" else None
    if actor_critic:
        return cls(
            observation_space, action_space, seeds, learning_rate=[s.learning_rate for s in sections],
            gamma=[s.gamma for s in sections], tau=[s.tau for s in sections], ou_sigma=[s.ou_sigma for s in sections],
            ou_theta=[s.ou_theta for s in sections], actor_layers=first.actor_layers,
            critic_layers=first.critic_layers, batch_size=first.batch_size, buffer_size=first.buffer_size,
            learning_starts=first.learning_starts_steps, warmup_actions=first.warmup_actions,
            pre_tanh_penalty=[s.pre_tanh_penalty for s in sections],
            encoder=encoder, total_timesteps=total_timesteps(cfgs[0]), device=device, slots=slots(cfgs[0]))
    return cls(
        [c.train.algo for c in cfgs], observation_space, action_space, seeds,
        learning_rate=[s.learning_rate for s in sections], gamma=[s.gamma for s in sections], layers=first.layers,
        batch_size=first.batch_size, buffer_size=first.buffer_size, learning_starts=first.learning_starts_steps,
        target_update_interval=first.target_update_steps,
        exploration_fraction=[exploration_fraction(c) for c in cfgs],
        exploration_initial_eps=[s.epsilon_start for s in sections],
        exploration_final_eps=[s.epsilon_end for s in sections], loss=first.loss,
        max_grad_norm=math.inf if first.max_grad_norm is None else first.max_grad_norm, encoder=encoder,
        total_timesteps=total_timesteps(cfgs[0]), device=device, slots=slots(cfgs[0]))

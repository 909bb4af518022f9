"""Models and environments with the paper's hyperparameters (SPEC §9).

``training_config`` fixes what the algorithm decides (action kind, the agent on the road);
``make_vec_env`` builds the environments (one process each when several: libsumo runs one
simulation per process); ``build_model`` a new model of the registry's class for
``cfg.train.algo`` with the hyperparameters of ``cfg.train``.
"""

from __future__ import annotations

import signal
from collections.abc import Callable
from typing import Any

import numpy as np

from lanefree_sumo.config import LaneFreeConfig, config_to_dict, merge_config
from lanefree_sumo.errors import ConfigError
from lanefree_sumo.rl.algorithms import get_algorithm


def training_config(base: LaneFreeConfig) -> LaneFreeConfig:
    """Fix the parts of the config the algorithm decides: action kind from the algorithm."""
    kind = get_algorithm(base.train.algo).actions
    if base.train.episodes < 1 or base.train.envs < 1 or base.train.checkpoint_every_episodes < 1:
        raise ConfigError("episodes, envs and checkpoint-every must be at least 1")
    return merge_config(base, {"action": {"kind": kind}, "scenario": {"with_agent": True}})


def total_timesteps(cfg: LaneFreeConfig) -> int:
    """Steps of a whole run: every episode, plus one round of the parallel envs as slack (the
    callback stops learning at the episode count; this only has to be enough)."""
    return (cfg.train.episodes + cfg.train.envs) * cfg.sim.episode_steps


def _env_factory(cfg_dict: dict[str, Any], rank: int, seed: int, subprocess_env: bool) -> Callable[[], Any]:
    def make() -> Any:
        from stable_baselines3.common.monitor import Monitor

        from lanefree_sumo.rl.env import LaneFreeEnv

        if subprocess_env:
            # Ctrl-C reaches the whole process group: only the trainer handles it (checkpoint,
            # then closing the workers); a worker dying first would lose the checkpoint.
            signal.signal(signal.SIGINT, signal.SIG_IGN)

        env = Monitor(LaneFreeEnv(cfg_dict))
        env.reset(seed=seed + 1000 * rank)
        return env

    return make


def make_vec_env(cfg: LaneFreeConfig, seed: int, n_envs: int) -> Any:
    """``n_envs`` environments: in this process for 1, else one process each."""
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecEnv

    cfg_dict = config_to_dict(cfg)
    factories = [_env_factory(cfg_dict, rank, seed, n_envs > 1) for rank in range(n_envs)]
    vec: VecEnv = DummyVecEnv(factories) if n_envs == 1 else SubprocVecEnv(factories, start_method="spawn")
    vec.seed(seed)
    return vec


def build_model(cfg: LaneFreeConfig, env: Any, seed: int, tensorboard_log: str | None) -> Any:
    """A new model for ``cfg.train.algo`` with the paper's hyperparameters (SPEC §9)."""
    import torch
    from stable_baselines3.common.noise import OrnsteinUhlenbeckActionNoise

    algo = cfg.train.algo
    spec = get_algorithm(algo)
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
        if algo == "ppo":
            nets = {"pi": list(ac.actor_layers), "vf": list(ac.critic_layers)}
            kwargs.update(n_steps=ac.ppo_n_steps, batch_size=ac.batch_size)
        else:
            kwargs.update(
                buffer_size=ac.buffer_size, batch_size=ac.batch_size, tau=ac.tau,
                learning_starts=ac.learning_starts_steps, train_freq=1, gradient_steps=1,
            )
        if algo in ("ddpg", "td3"):
            n_actions = env.action_space.shape[0]
            kwargs["action_noise"] = OrnsteinUhlenbeckActionNoise(
                mean=np.zeros(n_actions), sigma=ac.ou_sigma * np.ones(n_actions), theta=ac.ou_theta
            )
        if spec.fast_learner:
            kwargs["fast_learner"] = cfg.train.fast_learner
        kwargs["policy_kwargs"] = {"net_arch": nets, "activation_fn": torch.nn.ReLU, **extractor}
        return cls(policy, env, **kwargs)

    dq = cfg.train.dqn
    policy = "MultiInputPolicy" if set_obs else "MlpPolicy"  # the dueling class maps these to dueling heads
    decay = min(1.0, dq.epsilon_decay_episodes * cfg.sim.episode_steps / total_timesteps(cfg))
    return cls(
        policy, env, learning_rate=dq.learning_rate, buffer_size=dq.buffer_size, batch_size=dq.batch_size,
        gamma=dq.gamma, learning_starts=dq.learning_starts_steps, target_update_interval=dq.target_update_steps,
        exploration_initial_eps=dq.epsilon_start, exploration_final_eps=dq.epsilon_end,
        exploration_fraction=decay, train_freq=1, gradient_steps=1,
        policy_kwargs={"net_arch": list(dq.layers), "activation_fn": torch.nn.ReLU, **extractor},
        **common,
    )



"""Run-updates per second of the batched learners against K single runs on SB3's loop, one thread.

The paper's shapes (DDPG actor 24-256-128-2, critic 26-256-128-1; DQN 24-128-64-9; batch 64) and full replay
buffers (100 000 random transitions per run). For each K: one batched update of K runs against one update of
each of K single runs (SB3's ``DDPG``/``DQN``: SB3's update), timed in turn five times; the best CPU
time of this process counts (on a shared machine the least disturbed repeat).

    python scripts/analysis/batched_learner_speed.py [--algo ddpg|dqn] [--runs 1 4 8 16] [--updates 160]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3 import DDPG, DQN
from stable_baselines3.common.logger import configure
from stable_baselines3.common.noise import OrnsteinUhlenbeckActionNoise

from lanefree_sumo.rl.algorithms.batched import BatchedDDPG, BatchedDQN
from lanefree_sumo.rl.algorithms.batched.learner import BatchedLearner, SpacesEnv

OBS, ACT, ACTIONS, CAPACITY = 24, 2, 9, 100_000


def _spaces(algo: str) -> tuple[spaces.Box, spaces.Space]:
    box = spaces.Box(-np.inf, np.inf, (OBS,), np.float32)
    return box, (spaces.Box(-1.0, 1.0, (ACT,), np.float32) if algo == "ddpg" else spaces.Discrete(ACTIONS))


def _random_actions(algo: str, rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    return rng.uniform(-1, 1, shape).astype(np.float32) if algo == "ddpg" else rng.integers(0, ACTIONS, shape)


def batched(algo: str, runs: int, rng: np.random.Generator) -> BatchedLearner:
    """K runs with full replay buffers, past ``learning_starts``."""
    obs_space, act_space = _spaces(algo)
    seeds = list(range(runs))
    learner: BatchedLearner = (
        BatchedDDPG(obs_space, act_space, seeds, buffer_size=CAPACITY) if algo == "ddpg"
        else BatchedDQN("dqn", obs_space, act_space, seeds, buffer_size=CAPACITY, total_timesteps=10**6))
    replay = learner.replay
    for name in ("observations", "next_observations", "rewards"):
        tensor = getattr(replay, name)
        tensor.copy_(th.from_numpy(rng.normal(size=tuple(tensor.shape)).astype(np.float32)))
    replay.actions.copy_(th.from_numpy(_random_actions(algo, rng, tuple(replay.actions.shape))))
    replay.full = True
    learner.num_timesteps = CAPACITY + 1
    return learner


def single(algo: str, seed: int, rng: np.random.Generator) -> Any:
    """One single run's learner (``build_model``'s settings) with a full replay buffer."""
    obs_space, act_space = _spaces(algo)
    env = SpacesEnv(obs_space, act_space)
    model: Any
    if algo == "ddpg":
        model = DDPG("MlpPolicy", env, buffer_size=CAPACITY, batch_size=64, gamma=0.98, tau=0.001, seed=seed,
                     device="cpu", action_noise=OrnsteinUhlenbeckActionNoise(np.zeros(ACT), 0.2 * np.ones(ACT)),
                     policy_kwargs={"net_arch": {"pi": [256, 128], "qf": [256, 128]}, "activation_fn": th.nn.ReLU})
    else:
        model = DQN("MlpPolicy", env, buffer_size=CAPACITY, batch_size=64, gamma=0.98, seed=seed, device="cpu",
                    policy_kwargs={"net_arch": [128, 64], "activation_fn": th.nn.ReLU})
    rb = model.replay_buffer
    rb.observations[:] = rng.normal(size=rb.observations.shape)
    rb.next_observations[:] = rng.normal(size=rb.next_observations.shape)
    rb.actions[:] = _random_actions(algo, rng, rb.actions.shape)
    rb.rewards[:] = rng.normal(size=rb.rewards.shape)
    rb.full = True
    model.set_logger(configure(None, [""]))
    return model


def interleaved(steps: Sequence[Callable[[], object]], calls: int, repeats: int = 5) -> list[float]:
    """Best CPU seconds of this process per call of each step, the steps timed in turn ``repeats`` times."""
    for step in steps:
        for _ in range(5):
            step()
    best = [float("inf")] * len(steps)
    for _ in range(repeats):
        for i, step in enumerate(steps):
            start = time.process_time()
            for _ in range(calls):
                step()
            best[i] = min(best[i], (time.process_time() - start) / calls)
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--algo", choices=("ddpg", "dqn"), default="ddpg")
    parser.add_argument("--runs", type=int, nargs="+", default=[1, 4, 8, 16])
    parser.add_argument("--updates", type=int, default=160, help="run-updates per timed repeat")
    args = parser.parse_args()
    th.set_num_threads(1)
    rng = np.random.default_rng(0)
    print(f"{args.algo}: run-updates per second, one thread, batch 64, {CAPACITY} transitions per run")
    print(f"{'K':>3} {'sequential':>11} {'batched':>9} {'speed-up':>8} {'ms per batched update':>22}")
    for runs in args.runs:
        learner = batched(args.algo, runs, rng)
        models = [single(args.algo, seed, rng) for seed in range(runs)]

        def sequential(models: list[Any] = models) -> None:
            for model in models:
                model.train(gradient_steps=1, batch_size=64)

        t_batched, t_sequential = interleaved([learner.update, sequential], max(args.updates // runs, 10))
        print(f"{runs:>3} {runs / t_sequential:>11.0f} {runs / t_batched:>9.0f} {t_sequential / t_batched:>7.2f}x "
              f"{t_batched * 1e3:>22.2f}", flush=True)
        del learner, models


if __name__ == "__main__":
    main()

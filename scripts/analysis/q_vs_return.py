"""Does a trained critic over- or underestimate what its own policy earns? (why the DQN family races)

For each run: drives the final policy deterministically (numpy backend, the traffic seeds of `lanefree
evaluate`: the run's seed + 100000 + k) and
compares, state by state, the critic's Q(s, a) of the action taken (DQN family: ``q_net``; DDPG: the first
critic) with the discounted return G the episode then realised (γ of the run). States of the last 300 steps
are left out (γ^300 < 0.003 at γ = 0.98, so G is the full discounted return). A Q far above G would say
the policy chases values that are not there.

    python scripts/analysis/q_vs_return.py RUN... [--episodes 10]
"""

from __future__ import annotations

from lanefree_sumo.numerics import keep_numpy_portable

keep_numpy_portable()  # before numpy is imported: the episodes `lanefree` gives (lanefree_sumo/numerics.py)

import argparse  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from lanefree_sumo.config import merge_config  # noqa: E402
from lanefree_sumo.experiments.runners.evaluate import EVALUATION, load_model  # noqa: E402
from lanefree_sumo.experiments.storage.rundir import RunDir  # noqa: E402
from lanefree_sumo.rl.env import LaneFreeEnv  # noqa: E402

TAIL_STEPS = 300
"""Steps at an episode's end whose return is cut short by the episode's end (left out)."""


def discounted_returns(rewards: np.ndarray, gamma: float) -> np.ndarray:
    """G_t = Σ_k γ^k r_{t+k} to the episode's end, for every t."""
    out, acc = np.zeros_like(rewards), 0.0
    for t in range(len(rewards) - 1, -1, -1):
        acc = rewards[t] + gamma * acc
        out[t] = acc
    return out


def critic_values(model: Any, observations: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """Q(s, a) of the actions taken, one per state."""
    obs = torch.as_tensor(observations, dtype=torch.float32)
    with torch.no_grad():
        if hasattr(model, "q_net"):
            q_all = model.q_net(obs).numpy()
            return q_all[np.arange(len(actions)), actions.astype(int).ravel()]
        return model.critic(obs, torch.as_tensor(actions, dtype=torch.float32))[0].numpy().ravel()


def measure(run: Path, episodes: int) -> tuple[np.ndarray, np.ndarray, float]:
    """(Q, G, γ) over the kept states of ``episodes`` deterministic episodes of ``run``."""
    folder = RunDir(run)
    cfg = merge_config(folder.load_config(), {"backend": "numpy"})
    model = load_model(folder, cfg)
    env = LaneFreeEnv(cfg)
    qs, gs = [], []
    base_seed = cfg.seed + EVALUATION.seed_offset  # as lanefree evaluate: episode k drives base_seed + k
    for k in range(1, episodes + 1):
        obs, _ = env.reset(seed=base_seed + k)
        observations, actions, rewards = [], [], []
        done = False
        while not done:
            action, _ = model.predict(obs, deterministic=True)
            observations.append(obs)
            actions.append(action)
            obs, reward, terminated, truncated, _ = env.step(action)
            rewards.append(reward)
            done = terminated or truncated
        keep = slice(0, max(0, len(rewards) - TAIL_STEPS))
        qs.append(critic_values(model, np.array(observations), np.array(actions))[keep])
        gs.append(discounted_returns(np.array(rewards, dtype=float), model.gamma)[keep])
    env.close()
    return np.concatenate(qs), np.concatenate(gs), model.gamma


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="run folders with model.zip (vector observation)")
    parser.add_argument("--episodes", type=int, default=10, help="deterministic episodes per run")
    args = parser.parse_args()
    print("| run | γ | states | mean Q | mean G | mean Q − G (sd) | corr(Q, G) |")
    print("|---|---|---|---|---|---|---|")
    for run in args.runs:
        q, g, gamma = measure(run, args.episodes)
        print(f"| `{run.name}` | {gamma:g} | {len(q)} | {q.mean():.2f} | {g.mean():.2f} | "
              f"{np.mean(q - g):+.2f} ({np.std(q - g):.2f}) | {np.corrcoef(q, g)[0, 1]:.2f} |")


if __name__ == "__main__":
    main()

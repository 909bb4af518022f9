"""How fast DDPG's actor saturates its tanh output: trains the paper's DDPG (the config of
`lanefree train`, numpy backend) for a few episodes per observation and prints, every K environment steps
after learning starts, the actor's median |pre-tanh| activation and the share of action components at the
bound (|a| > 0.999) over 256 fixed states of the random warm-up (drawn with a generator of their own, so the
probe leaves the training's random draws, and so the run, exactly as `lanefree train` has them). Past
|pre-tanh| ≈ 10 the gradient reaching the actor is tanh' < 1e-8 of dQ/da, below Adam's epsilon: the policy can
no longer move there.

    python scripts/analysis/actor_saturation.py [--episodes 6] [--seeds 0 1 2] [--every 400] \\
        [--obs vector set:paper ...]
"""

from __future__ import annotations

from lanefree_sumo.numerics import keep_numpy_portable

keep_numpy_portable()  # before numpy is imported: the episodes `lanefree` gives (lanefree_sumo/numerics.py)

import argparse  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402
from stable_baselines3.common.callbacks import BaseCallback  # noqa: E402

from lanefree_sumo.config import LaneFreeConfig, merge_config  # noqa: E402
from lanefree_sumo.rl.models import build_model, make_vec_env, training_config  # noqa: E402


class Probe(BaseCallback):
    """Every ``every`` environment steps after learning starts: (gradient steps, median |pre-tanh|, share of
    action components at the bound) over ``states`` warm-up states."""

    def __init__(self, every: int, states: int = 256) -> None:
        super().__init__()
        self.every, self.states = every, states
        self.rows: list[tuple[int, float, float]] = []
        self.returns: list[float] = []  # per finished episode, to compare with a `lanefree train` run's episodes.csv
        self.probe: Any = None

    def _on_step(self) -> bool:
        model: Any = self.model
        self.returns += [i["episode_metrics"]["return"] for i in self.locals["infos"] if "episode_metrics" in i]
        if self.num_timesteps <= model.learning_starts or self.num_timesteps % self.every:
            return True
        if self.probe is None:  # states of the random warm-up, the same for every later probe
            rb = model.replay_buffer
            rows = np.random.default_rng(0).integers(0, model.learning_starts, self.states)
            if isinstance(rb.observations, dict):
                self.probe = {key: rb.to_torch(value[rows, 0]) for key, value in rb.observations.items()}
            else:
                self.probe = rb.to_torch(rb.observations[rows, 0])
        actor: Any = model.policy.actor
        with torch.no_grad():
            features = actor.extract_features(self.probe, actor.features_extractor)
            pre = actor.mu[:-1](features)  # mu = [..., Linear, Tanh]
        at_bound = float((pre.tanh().abs() > 0.999).float().mean())
        self.rows.append((model._n_updates, float(pre.abs().median()), at_bound))
        return True


def measure(obs: str, episodes: int, seed: int, every: int) -> Probe:
    kind, _, encoder = obs.partition(":")
    overrides: dict[str, Any] = {"seed": seed, "train": {"episodes": episodes, "backend": "numpy"},
                                 "observation": {"kind": kind, **({"encoder": encoder} if encoder else {})}}
    cfg = training_config(merge_config(LaneFreeConfig(), overrides))
    env = make_vec_env(cfg)
    model = build_model(cfg, env, seed, None)
    probe = Probe(every)
    model.learn(total_timesteps=episodes * cfg.sim.episode_steps, callback=probe)
    env.close()
    return probe


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=6, help="episodes of 800 steps (the first is random)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--every", type=int, default=400, help="environment steps between probes")
    parser.add_argument("--obs", nargs="+", default=["vector", "set:paper", "set:small"],
                        help="observations: vector, set:paper, set:small")
    args = parser.parse_args()
    torch.set_num_threads(1)
    print("# DDPG's actor at the tanh bound: the vector and the set observations\n")
    print(f"`python scripts/analysis/actor_saturation.py --episodes {args.episodes} --every {args.every} --seeds "
          f"{' '.join(map(str, args.seeds))} --obs {' '.join(args.obs)}`: DDPG, fields_zones_overtake_collision, "
          "70 veh/km. Cell: median |pre-tanh| of the actor over 256 fixed states of the random warm-up (share of "
          "action components at the bound, |a| > 0.999) after n gradient steps.", flush=True)
    for seed in args.seeds:
        results = {obs: measure(obs, args.episodes, seed, args.every) for obs in args.obs}
        print(f"\nseed {seed}\n\n| gradient steps | " + " | ".join(results) + " |")
        print("|---|" + "---|" * len(results))
        for i, (steps, *_rest) in enumerate(next(iter(results.values())).rows):
            cells = [f"{p.rows[i][1]:.2f} ({p.rows[i][2]:.0%})" if i < len(p.rows) else "–" for p in results.values()]
            print(f"| {steps} | " + " | ".join(cells) + " |", flush=True)
        print("| episode returns | " + " | ".join(", ".join(f"{r:.3f}" for r in p.returns) for p in results.values())
              + " |", flush=True)


if __name__ == "__main__":
    main()

"""Can the DQN family's 9 discrete actions drive as calmly as DDPG? (why the DQN family races)

Drives a trained DDPG policy deterministically (numpy backend, the traffic seeds of `lanefree evaluate`: the
run's seed + 100000 + k) three ways on the same traffic: its own continuous actions, and each action turned
into one of the 9 discrete actions the DQN family chooses from (ax in {-2, 0, +2} m/s², ay in {-1, 0, +1} m/s²,
specification §6) by

* ``nearest``: the nearest level per component (|ax| ≤ 1 → 0, halves rounding to 0; braking harder than
  −2 m/s² becomes −2);
* ``sigma-delta``: the level nearest to the wanted acceleration plus the error carried from the steps before
  (the carried error kept within one level), so the accelerations average out to the wanted ones over a few
  steps, as a bang-bang controller would.

If the discretised policy drives like the continuous one, the action set can express calm driving and the
DQN family's racing comes from what it learned, not from what it can do.

    python scripts/analysis/quantised_actions.py RUN... [--episodes 20]
"""

from __future__ import annotations

from lanefree_sumo.numerics import keep_numpy_portable

keep_numpy_portable()  # before numpy is imported: the episodes `lanefree` gives (lanefree_sumo/numerics.py)

import argparse  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

from lanefree_sumo.config import LaneFreeConfig, merge_config  # noqa: E402
from lanefree_sumo.experiments.runners.evaluate import EVALUATION, load_model  # noqa: E402
from lanefree_sumo.experiments.storage.rundir import RunDir  # noqa: E402
from lanefree_sumo.rl.env import DISCRETE_ACTIONS, LaneFreeEnv, action_to_acceleration  # noqa: E402

MODES = ("continuous", "nearest", "sigma-delta")
COLUMNS = ("collisions", "speed_dev_mps", "mean_speed_mps", "overtakes", "return")


def discrete_index(sign_x: float, sign_y: float) -> int:
    """The index of (sign of ax, sign of ay) in the discrete action table."""
    return int(np.flatnonzero((DISCRETE_ACTIONS == (sign_x, sign_y)).all(axis=1))[0])


class Quantiser:
    """Turns wanted accelerations (ax, ay) in m/s² into discrete actions (module docstring)."""

    def __init__(self, cfg: LaneFreeConfig, carry: bool) -> None:
        self.levels = np.array([cfg.action.discrete_ax_mps2, cfg.action.discrete_ay_mps2])
        self.carry = carry
        self.error = np.zeros(2)

    def reset(self) -> None:
        self.error[:] = 0.0

    def __call__(self, wanted: np.ndarray) -> int:
        target = wanted + self.error if self.carry else wanted
        signs = np.clip(np.round(target / self.levels), -1, 1)
        if self.carry:
            self.error = np.clip(target - signs * self.levels, -self.levels, self.levels)
        return discrete_index(float(signs[0]), float(signs[1]))


def drive(run: Path, mode: str, episodes: int) -> list[dict[str, Any]]:
    """The metrics rows of ``episodes`` deterministic episodes of the run's policy, its actions as ``mode``."""
    folder = RunDir(run)
    cfg = merge_config(folder.load_config(), {"backend": "numpy"})
    model = load_model(folder, cfg)
    if mode == "continuous":
        env_cfg, quantiser = cfg, None
    else:
        env_cfg = merge_config(cfg, {"action": {"kind": "discrete"}})
        quantiser = Quantiser(env_cfg, carry=mode == "sigma-delta")
    env = LaneFreeEnv(env_cfg)
    rows = []
    base_seed = cfg.seed + EVALUATION.seed_offset  # as lanefree evaluate: episode k drives base_seed + k
    for k in range(1, episodes + 1):
        obs, _ = env.reset(seed=base_seed + k)
        if quantiser is not None:
            quantiser.reset()
        done = False
        while not done:
            action, _ = model.predict(obs, deterministic=True)
            if quantiser is not None:
                action = quantiser(np.array(action_to_acceleration(cfg, action, "quantised_actions")))
            obs, _, terminated, truncated, _ = env.step(action)
            done = terminated or truncated
        rows.append(env.episode_metrics())
    env.close()
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="DDPG run folders with model.zip (vector observation)")
    parser.add_argument("--episodes", type=int, default=20, help="deterministic episodes per run and mode")
    args = parser.parse_args()
    print("| run | actions | " + " | ".join(COLUMNS) + " |")
    print("|---|---|" + "---|" * len(COLUMNS))
    for run in args.runs:
        for mode in MODES:
            rows = drive(run, mode, args.episodes)
            means = [np.mean([row[c] for row in rows]) for c in COLUMNS]
            print(f"| `{run.name}` | {mode} | " + " | ".join(f"{m:.2f}" for m in means) + " |", flush=True)


if __name__ == "__main__":
    main()

"""What an actor-critic run's actor makes of different states, checkpoint by checkpoint.

The set encoder under DDPG collapses: its features barely depend on the state and the actor's output sits at
its tanh bound, where tanh' (< 1e-8 past |u| ≈ 10) stops the critic's gradient. This module measures both on a
run's checkpoints and final model, over the same probe states for each:

* **feature state-dependence** of the actor's input (the features extractor's output: the vector observation
  itself, or the set encoder's features): the mean cosine similarity between the inputs of two different states
  (1: the same direction for every state) and the share of the input's energy that varies across states,
  Σ_i ‖f_i − f̄‖² / Σ_i ‖f_i‖² (0: one vector for every state);
* **the pre-tanh output** u of the actor (before its tanh squash): the median |u| over states and action
  components, and the share of action components at the bound (|tanh u| > 0.999).

The probe states are observations of the run's own environment (its config: observation, road, density)
driven by uniformly random actions from a fixed seed (:data:`PROBE_SEED`), every :data:`PROBE_EVERY` th step:
the same states for every checkpoint, none drawn from the run's own random streams.

    python -m lanefree_sumo.experiments.analysis.actor_probe RUN [RUN ...] [--states 256] [--out FILE.md]
"""

from __future__ import annotations

from lanefree_sumo.numerics import keep_numpy_portable

keep_numpy_portable()  # before numpy is imported: the episodes `lanefree` gives (lanefree_sumo/numerics.py)

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
from collections.abc import Sequence  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

from lanefree_sumo.config import LaneFreeConfig  # noqa: E402
from lanefree_sumo.errors import LaneFreeError, RunError  # noqa: E402
from lanefree_sumo.experiments.analysis import markdown  # noqa: E402
from lanefree_sumo.experiments.storage.rundir import CHECKPOINTS, MODEL, read_config, write_atomic  # noqa: E402
from lanefree_sumo.rl.env import action_space, observation_space  # noqa: E402
from lanefree_sumo.rl.models import build_batched, load_saved_model  # noqa: E402

PROBE_SEED = 0
"""Seed of the probe's traffic and random actions."""
PROBE_EVERY = 3
"""Steps between two probe states (consecutive steps are nearly the same state)."""
AT_BOUND = 0.999
"""|tanh u| above which an action component counts as at the bound."""
ACTOR_ALGORITHMS = ("ddpg", "td3")
"""Algorithms whose policy is a deterministic tanh actor (what the probe reads)."""


@dataclass(frozen=True)
class Probe:
    """The probe's readings of one model."""

    label: str
    """``initial`` (the untrained actor of the run's seed), ``ep_NNNNN`` of a checkpoint, or ``final``."""
    timesteps: int | None
    """Environment steps the model was trained for (None: unknown)."""
    cosine: float
    """Mean cosine similarity between the actor inputs of two different probe states."""
    varying: float
    """Share of the actor input's energy that varies across states (0 … 1)."""
    median_pre_tanh: float
    """Median |u| of the actor's pre-tanh output over states and action components."""
    at_bound: float
    """Share of action components with |tanh u| > :data:`AT_BOUND`."""


def probe_states(cfg: LaneFreeConfig, states: int = 256) -> Any:
    """``states`` observations of ``cfg``'s environment under uniformly random actions (:data:`PROBE_SEED`),
    every :data:`PROBE_EVERY` th step; a stacked array, or a dict of them for the set observation."""
    from gymnasium import spaces

    from lanefree_sumo.rl.env import LaneFreeEnv

    env = LaneFreeEnv(cfg)
    rng = np.random.default_rng(PROBE_SEED)
    box = env.action_space
    if not isinstance(box, spaces.Box):
        raise RunError(f"the probe drives a continuous action space, not {box}")
    seen: list[Any] = []
    obs, _ = env.reset(seed=PROBE_SEED)
    step = 0
    try:
        while len(seen) < states:
            if step % PROBE_EVERY == 0:
                seen.append(obs)
            obs, _, terminated, truncated, _ = env.step(rng.uniform(box.low, box.high).astype(np.float32))
            step += 1
            if terminated or truncated:
                obs, _ = env.reset(seed=PROBE_SEED + step)
    finally:
        env.close()
    if isinstance(seen[0], dict):
        return {key: np.stack([o[key] for o in seen]) for key in seen[0]}
    return np.stack(seen)


def feature_dependence(features: np.ndarray) -> tuple[float, float]:
    """(mean cosine similarity over pairs of different rows, share of the energy varying across rows) of
    ``features`` (states × features)."""
    f = np.asarray(features, dtype=np.float64)
    if f.ndim != 2 or f.shape[0] < 2:
        raise ValueError(f"need at least 2 states of features, got shape {f.shape}")
    norms = np.linalg.norm(f, axis=1, keepdims=True)
    unit = f / np.where(norms > 0, norms, 1.0)
    gram = unit @ unit.T
    n = f.shape[0]
    cosine = float((gram.sum() - np.trace(gram)) / (n * (n - 1)))
    energy = float((f ** 2).sum())
    varying = float(((f - f.mean(axis=0)) ** 2).sum() / energy) if energy > 0 else 0.0
    return cosine, varying


def read_actor(model: Any, observations: Any) -> tuple[np.ndarray, np.ndarray]:
    """(the actor's input features, its pre-tanh output) for ``observations`` (a batch)."""
    import torch

    actor = model.policy.actor
    obs, _ = model.policy.obs_to_tensor(observations)
    with torch.no_grad():
        features = actor.extract_features(obs, actor.features_extractor)
        pre = actor.mu[:-1](features)  # mu = [..., Linear, Tanh]
    return features.numpy(), pre.numpy()


def probe_model(model: Any, observations: Any, label: str, timesteps: int | None) -> Probe:
    features, pre = read_actor(model, observations)
    cosine, varying = feature_dependence(features)
    return Probe(label, timesteps, cosine, varying, float(np.median(np.abs(pre))),
                 float((np.abs(np.tanh(pre)) > AT_BOUND).mean()))


def _models(run: Path) -> list[tuple[str, Path, int | None]]:
    """(label, model.zip, timesteps) of every complete checkpoint, oldest first, then the final model."""
    out = []
    folder = run / CHECKPOINTS
    for ckpt in sorted(folder.glob("ep_*")) if folder.is_dir() else []:
        state, model = ckpt / "state.json", ckpt / MODEL
        if state.is_file() and model.is_file():
            try:
                timesteps = int(json.loads(state.read_text())["timesteps"])
            except (ValueError, KeyError, TypeError):
                timesteps = None
            out.append((ckpt.name, model, timesteps))
    if (run / MODEL).is_file():
        out.append(("final", run / MODEL, None))
    return out


def probe_run(run: Path, states: int = 256) -> list[Probe]:
    """The probe's readings of the run's untrained actor (built anew from its config and seed), every checkpoint
    and the final model of ``run``; RunError when it has none of the latter or is not a tanh actor's run."""
    import torch

    cfg = read_config(run)
    if cfg.train.algo not in ACTOR_ALGORITHMS:
        raise RunError(f"{run} is a {cfg.train.algo} run; the probe reads the tanh actor of "
                       f"{' or '.join(ACTOR_ALGORITHMS)}")
    models = _models(run)
    if not models:
        raise RunError(f"{run} has neither a model nor a complete checkpoint to probe")
    torch.set_num_threads(cfg.train.torch_threads)
    observations = probe_states(cfg, states)
    initial = build_batched([cfg], [cfg.seed], observation_space(cfg), action_space(cfg)).sb3_model(0)
    out = [probe_model(initial, observations, "initial", 0)]
    for label, path, timesteps in models:
        try:
            model = load_saved_model(cfg.train.algo, path)
        except Exception as exc:
            raise RunError(f"{path} cannot be loaded ({type(exc).__name__}: {exc})") from None
        out.append(probe_model(model, observations, label, timesteps))
    return out


def probe_markdown(runs: Sequence[tuple[Path, Sequence[Probe]]], states: int) -> str:
    """One table per run."""
    lines = ["# The actor's inputs and pre-tanh output, checkpoint by checkpoint", "",
             "`python -m lanefree_sumo.experiments.analysis.actor_probe`: "
             f"{states} probe states of each run's environment "
             f"under uniformly random actions (seed {PROBE_SEED}, every {PROBE_EVERY}rd step). Cosine: the mean "
             "cosine similarity between the actor's inputs of two different states (1: one direction for all); "
             "varying: the share of the input's energy that varies across states; median abs(u): the median |pre-tanh| "
             f"output; at bound: the share of action components with |tanh u| > {AT_BOUND}.", ""]
    for run, probes in runs:
        lines += [f"## {run}", ""]
        lines += markdown.table(["model", "env steps", "cosine", "varying", "median abs(u)", "at bound"], [
            [p.label, "–" if p.timesteps is None else str(p.timesteps), f"{p.cosine:.3f}", f"{p.varying:.3f}",
             f"{p.median_pre_tanh:.2f}", f"{p.at_bound:.0%}"] for p in probes])
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, metavar="RUN", help="run folders of ddpg or td3")
    parser.add_argument("--states", type=int, default=256, help="probe states (default 256)")
    parser.add_argument("--out", type=Path, default=None, help="write the tables there too (markdown)")
    args = parser.parse_args(argv)
    if args.states < 2:
        print("actor_probe: --states must be at least 2", file=sys.stderr)
        return 2
    try:
        text = probe_markdown([(run, probe_run(run, args.states)) for run in args.runs], args.states)
        if args.out is not None:
            write_atomic(args.out, text)
    except (LaneFreeError, OSError) as exc:
        print(f"actor_probe: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

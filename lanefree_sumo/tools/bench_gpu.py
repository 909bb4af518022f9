"""``make bench-gpu`` (``python -m lanefree_sumo.tools.bench --gpu``): the batched path on a torch device.

Printed in one run, as markdown tables: the card (or CPU), torch's and CUDA's versions; the environment alone
(:class:`~lanefree_sumo.rl.batched_env.BatchedRingEnv` on the device, float64, random actions) in agent-steps/s
at K = 1, 1024, 16 384 rings; batched DDPG training (the paper's settings: act, env step, store, one update per
run; :mod:`lanefree_sumo.rl.algorithms.batched`) in lockstep iterations/s at K = 1, 150, 1024 runs; and the
projected wall time of the paper's 150-run grid (15 settings × 10 seeds × 625 episodes × 800 steps) from the
K = 150 rate. Each measurement is capped in steps and the whole run in time (``--budget-s``, default 420 s, so
that it ends within 8 minutes on one card): a row whose turn comes after the budget is printed as skipped.
``--device cpu`` with small sizes runs the same code on the CPU (a test does).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from lanefree_sumo.config import LaneFreeConfig, merge_config

GRID_RUNS = 150
"""The paper's grid: 15 settings × 10 seeds."""
RUN_ITERATIONS = 625 * 800
"""Lockstep iterations of a paper run (625 episodes of 800 steps)."""
DENSITY = 90.0
LEARNING_STARTS = 64
"""Updates start after this many steps here (a paper run: 800): the time of an iteration once learning runs is
what is measured, and the warm-up before it costs the budget nothing it need not."""


def _sync(device: Any) -> None:
    if device is None:
        return
    import torch

    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


def _configs(runs: int, seed: int) -> list[LaneFreeConfig]:
    from lanefree_sumo.rl.models import training_config

    return [training_config(merge_config(LaneFreeConfig(), {
        "seed": seed + k, "scenario": {"density_veh_per_km": DENSITY},
        "train": {"algo": "ddpg", "actor_critic": {"learning_starts_steps": LEARNING_STARTS}}}))
        for k in range(runs)]


def env_rate(runs: int, steps: int, device: str, seed: int = 0) -> float:
    """Agent-steps/s of the batched environment alone, ``runs`` rings on ``device`` (random actions drawn on the
    host, as the learners draw theirs), timed over ``steps`` steps after two untimed ones."""
    from lanefree_sumo.rl.batched_env import BatchedRingEnv

    env = BatchedRingEnv(_configs(runs, seed), device=device)
    env.reset()
    rng = np.random.default_rng(seed)
    actions = rng.uniform(-1.0, 1.0, (steps + 2, runs, 2)).astype(np.float32)
    for i in range(2):
        env.step(actions[i])
    _sync(device)
    t0 = time.perf_counter()
    for i in range(steps):
        env.step(actions[2 + i])
    _sync(device)
    return runs * steps / (time.perf_counter() - t0)


def train_rate(runs: int, steps: int, device: str, seed: int = 0) -> float:
    """Lockstep iterations/s of ``runs`` batched DDPG runs on ``device`` (act, env step, store, one update per
    run), timed over ``steps`` iterations once updates run."""
    from lanefree_sumo.rl.batched_env import BatchedRingEnv
    from lanefree_sumo.rl.env import action_space, observation_space
    from lanefree_sumo.rl.models import build_batched

    cfgs = _configs(runs, seed)
    env = BatchedRingEnv(cfgs, device=device)
    learner = build_batched(cfgs, [c.seed for c in cfgs], observation_space(cfgs[0]), action_space(cfgs[0]),
                            device=device)
    return lockstep_rate(env, learner, learner.learning_starts + 2, steps, device)


def lockstep_rate(env: Any, learner: Any, warm: int, steps: int, device: Any = None) -> float:
    """Lockstep iterations/s of a batched ``learner`` on its ``env`` (act, env step, store, update, reset the runs
    whose episode ended, as :mod:`lanefree_sumo.experiments.batch` trains), timed over ``steps`` iterations after
    ``warm`` untimed ones; ``device``: the torch device to wait for around the timing (None: the CPU, numpy)."""
    obs = env.reset()
    t0 = 0.0
    for step in range(warm + steps):
        if step == warm:
            _sync(device)
            t0 = time.perf_counter()
        actions = learner.act(obs, explore=True)
        new_obs, reward, terminated, truncated, _ = env.step(actions)
        learner.store(obs, actions, reward, new_obs, terminated | truncated, truncated & ~terminated)
        learner.update()
        ended = np.flatnonzero(terminated | truncated)
        obs = env.reset(list(ended)) if len(ended) else new_obs
    _sync(device)
    return steps / (time.perf_counter() - t0)


def describe(device: str) -> str:
    """The card's name (or the CPU), torch's and CUDA's versions."""
    import platform

    import torch

    dev = torch.device(device)
    card = torch.cuda.get_device_name(dev) if dev.type == "cuda" else f"CPU ({platform.processor() or 'unknown'})"
    return f"device: {dev} — {card}; torch {torch.__version__}; CUDA {torch.version.cuda or 'none'}"


def run(device: str, env_sizes: Sequence[int], train_sizes: Sequence[int], env_steps: int, train_steps: int,
        budget_s: float, seed: int = 0) -> str:
    """The benchmark's text (module docstring); each row is printed as soon as it is measured."""
    import torch

    from lanefree_sumo.experiments.batch import check_device

    check_device(torch.device(device).type)
    start = time.perf_counter()
    lines = [describe(device), "", "Environment alone (float64, random actions):", "",
             "| section | K | steps | agent-steps/s |", "|---|---|---|---|"]
    print("\n".join(lines), flush=True)

    def row(text: str) -> None:
        lines.append(text)
        print(text, flush=True)

    def left() -> bool:
        return time.perf_counter() - start < budget_s

    for k in env_sizes:
        if not left():
            row(f"| env | {k} | 0 | skipped (time budget) |")
            continue
        row(f"| env | {k} | {env_steps} | {env_rate(k, env_steps, device, seed):.0f} |")
    row("")
    row(f"Batched DDPG training (the paper's networks, batch 64, buffer 100 000 per run; updates from step "
        f"{LEARNING_STARTS}):")
    row("")
    row("| section | K | iterations | iterations/s |")
    row("|---|---|---|---|")
    rates: dict[int, float] = {}
    for k in train_sizes:
        if not left():
            row(f"| train | {k} | 0 | skipped (time budget) |")
            continue
        rates[k] = train_rate(k, train_steps, device, seed)
        row(f"| train | {k} | {train_steps} | {rates[k]:.1f} |")
    row("")
    basis = GRID_RUNS if GRID_RUNS in rates else (max(rates) if rates else None)
    if basis is None:
        row("projected grid: not measured (time budget)")
    else:
        batches = -(-GRID_RUNS // basis)
        minutes = batches * RUN_ITERATIONS / rates[basis] / 60.0
        row(f"projected grid: {GRID_RUNS} runs × 625 episodes × 800 steps = {batches} batch(es) of {basis} × "
            f"{RUN_ITERATIONS} iterations at {rates[basis]:.1f} iterations/s: {minutes:.1f} min")
    row(f"(bench took {time.perf_counter() - start:.0f} s)")
    return "\n".join(lines)

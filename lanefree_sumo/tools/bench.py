"""``make bench``: step rates measured side by side in one run, printed as a table and written
to ``runs/bench/``.

For 70, 90 and 120 veh/km, 800 steps each:
(a) bare SUMO — the same ring and vehicles, SUMO's own models drive, no Python per step;
(b) the libsumo backend with the force model (read state, forces, commands, collisions);
(c) the TraCI backend (same, over a socket);
(d) the numpy-only physics (no SUMO).
(a) and (b) are measured alternately ``REPEATS`` times and the median is reported, so that
machine noise hits both alike.  Timings are not tests: the numbers are for reading.
Last, :func:`training_speed`: DDPG's env steps/s on LaneFree-v0 with plain SB3, on SB3's loop and as a batch of
one (``lanefree train``), against the peer HighwayEnv ``highway-v0`` (``pip install -e '.[bench]'``), interleaved,
and :func:`dqn_family_speed`: the DQN family as a batch of one beside SB3's own DQN
(``--training-only`` runs just these sections, ``--dqn-only`` the last), :func:`single_run_speed`: one run in
SB3's loop against one run as a batch of one (``--single-only``), :func:`slot_speed`: the same for a run of
several agents or environments (``--slots-only``), and :func:`batch_speed`: runs per
core-hour of sequential runs against batches of K runs in one process, then :func:`set_update_speed`: the set
observation's update, sequential against batched (``--batch-only``), and :func:`vector_speed`: the vector entry
point against gymnasium's SyncVectorEnv and the cost of a frame (``--vector-only``). ``--gpu``: the
batched path on a torch device instead (:mod:`lanefree_sumo.tools.bench_gpu`, ``make bench-gpu``).
"""

from __future__ import annotations

import argparse
import functools
import os
import statistics
import time
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

from lanefree_sumo.config import LaneFreeConfig, merge_config
from lanefree_sumo.sim.simulation import Simulation
from lanefree_sumo.sim.spawn import spawn

DENSITIES = (70, 90, 120)
REPEATS = 3


def _rate(cfg: LaneFreeConfig, steps: int, seed: int) -> tuple[float, float, dict[str, float]]:
    """(steps per second, reset time in ms, ms per step split into SUMO's own step, the
    per-vehicle commands and reads, and the Python physics) on ``cfg.backend``."""
    sim = Simulation(cfg)
    try:
        sim.reset(seed)
        t0 = time.perf_counter()
        sim.reset(seed + 1)
        reset_ms = 1000.0 * (time.perf_counter() - t0)
        sim.backend_seconds = 0.0
        sumo_step = getattr(sim.backend, "sumo_step_seconds", 0.0)
        t0 = time.perf_counter()
        for _ in range(steps):
            sim.step()
        total = time.perf_counter() - t0
        sumo_step = getattr(sim.backend, "sumo_step_seconds", 0.0) - sumo_step
        split = {
            "sumo_step": 1000.0 * sumo_step / steps,
            "api_calls": 1000.0 * (sim.backend_seconds - sumo_step) / steps,
            "physics": 1000.0 * (total - sim.backend_seconds) / steps,
        }
        return steps / total, reset_ms, split
    finally:
        sim.close()


def env_overhead(steps: int, seed: int, density: float = 120.0) -> list[tuple[str, float, float]]:
    """(observation kind, env work ms per step, core step ms) of LaneFree-v0 on libsumo: the
    env's own work (observation, reward, bookkeeping) against the simulation core's step."""
    from lanefree_sumo.rl.env import LaneFreeEnv

    out = []
    for kind in ("vector", "set"):
        env = LaneFreeEnv({"scenario": {"density_veh_per_km": density}, "observation": {"kind": kind}})
        try:
            env.reset(seed=seed)
            env.env_seconds = 0.0
            action = np.array([0.3, 0.0])
            t0 = time.perf_counter()
            for _ in range(steps):
                env.step(action)
            total = time.perf_counter() - t0
        finally:
            env.close()
        out.append((kind, 1000.0 * env.env_seconds / steps, 1000.0 * (total - env.env_seconds) / steps))
    return out


def training_rate(algo: str, seed: int, density: float = 90.0, steps: int = 1600,
                  encoder: str | None = None, extra: dict[str, Any] | None = None) -> float:
    """Env steps per second of a training run of ``algo`` on SB3's loop including its learning updates,
    measured over ``steps`` transitions after learning has started (specification §9 settings); with
    ``encoder`` (``small`` or ``paper``), on the set observation through that set encoder; ``extra``: more
    overrides (several agents or environments: a step is one of each)."""
    from stable_baselines3.common.callbacks import BaseCallback

    from lanefree_sumo.rl.models import build_model, make_vec_env, slots, training_config

    cfg = training_config(merge_config(merge_config(LaneFreeConfig(), {
        "scenario": {"density_veh_per_km": density}, "train": {"algo": algo},
        **({"observation": {"kind": "set", "encoder": encoder}} if encoder else {})}), extra or {}))
    starts = cfg.train.dqn.learning_starts_steps if algo in ("dqn", "ddqn", "dueling", "per") \
        else cfg.train.actor_critic.learning_starts_steps
    import torch

    torch.set_num_threads(cfg.train.torch_threads)

    class Clock(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.t_start = self.t_end = 0.0

        def _on_step(self) -> bool:
            if self.num_timesteps == starts:
                self.t_start = time.perf_counter()
            if self.num_timesteps == starts + steps:
                self.t_end = time.perf_counter()
                return False
            return True

    env = make_vec_env(merge_config(cfg, {"seed": seed}))
    try:
        model = build_model(cfg, env, seed, None)
        clock = Clock()
        model.learn(total_timesteps=starts + steps + 1, callback=clock)
    finally:
        env.close()
    return steps / slots(cfg) / (clock.t_end - clock.t_start)


# -- training speed: DDPG on SB3's loop and as a batch of one, and the HighwayEnv peer ---------------------

PEER_DENSITY = 90.0
"""LaneFree-v0's density in the training-speed section: round(90 · 0.5 km) = 45 vehicles besides the agent,
the count the highway-v0 peer gets."""
SPEED_STARTS = 100
"""Random steps before learning in the training-speed runs: an update costs the same however full the
replay buffer is, and the paper's 800 would cost the slow peer a minute per repeat."""


def _highway_env(vehicles: int, sim_hz: int, seed: int) -> Any:
    """HighwayEnv ``highway-v0`` as a one-env VecEnv: ``vehicles`` others, 0.25 s per env step (policy
    frequency 4 Hz) in ``sim_hz / 4`` physics steps, continuous actions, the kinematics of the 5 nearest
    flattened (25 numbers; LaneFree-v0 has 24), 800-step episodes unless the ego crashes."""
    import gymnasium
    import highway_env  # noqa: F401  (registers highway-v0)
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.vec_env import DummyVecEnv

    def make() -> Any:
        env = gymnasium.make("highway-v0", config={
            "vehicles_count": vehicles, "policy_frequency": 4, "simulation_frequency": sim_hz, "duration": 200,
            "action": {"type": "ContinuousAction"}, "observation": {"type": "Kinematics"}})
        env = Monitor(gymnasium.wrappers.FlattenObservation(env))
        env.reset(seed=seed)
        return env

    vec = DummyVecEnv([make])
    vec.seed(seed)
    return vec


def _env_rate(make_env: Callable[[], Any], steps: int, seed: int) -> float:
    """Env steps per second of a one-env VecEnv under uniform random actions, resets included."""
    env = make_env()
    try:
        env.action_space.seed(seed)
        env.reset()
        t0 = time.perf_counter()
        for _ in range(steps):
            env.step(np.array([env.action_space.sample()]))
        return steps / (time.perf_counter() - t0)
    finally:
        env.close()


def _train_rate(cfg: LaneFreeConfig, make_env: Callable[[], Any], seed: int, steps: int) -> float:
    """Env steps per second of a training run of ``cfg.train.algo`` in SB3's loop with stock SB3's class
    (build_model: the paper's settings) over ``steps`` steps after ``SPEED_STARTS`` random ones: env step,
    exploration, one update per step."""
    import torch
    from stable_baselines3.common.callbacks import BaseCallback

    from lanefree_sumo.rl.models import build_model

    torch.set_num_threads(cfg.train.torch_threads)  # as training does: 2 threads on a busy core crawl
    cfg = merge_config(cfg, {"train": {"actor_critic": {"learning_starts_steps": SPEED_STARTS},
                                       "dqn": {"learning_starts_steps": SPEED_STARTS}}})
    stamps: dict[int, float] = {}

    class Clock(BaseCallback):
        def _on_step(self) -> bool:
            if self.num_timesteps in (SPEED_STARTS, SPEED_STARTS + steps):
                stamps[self.num_timesteps] = time.perf_counter()
            return self.num_timesteps < SPEED_STARTS + steps

    env = make_env()
    try:
        build_model(cfg, env, seed, None).learn(total_timesteps=SPEED_STARTS + steps + 1, callback=Clock())
    finally:
        env.close()
    return steps / (stamps[SPEED_STARTS + steps] - stamps[SPEED_STARTS])


def update_costs(seed: int, updates: int = 300, repeats: int = REPEATS) -> dict[str, float]:
    """ms per DDPG update — the learner alone, batch 64, actor and critic 256-128, LaneFree-v0's spaces, a filled
    replay buffer — median of ``repeats`` interleaved: SB3's ``train`` (SB3's loop), the batched learner's update
    at K = 1 (``lanefree train``), and the update's 28 matrix products alone (``torch.mm`` of the same shapes into
    preallocated outputs)."""
    import gymnasium
    import torch
    from stable_baselines3.common.logger import Logger

    from lanefree_sumo.rl.env import action_space, observation_space
    from lanefree_sumo.rl.models import build_batched, build_model, training_config

    cfg = training_config(merge_config(LaneFreeConfig(), {"seed": seed, "train": {"algo": "ddpg"}}))
    obs_space, act_space = observation_space(cfg), action_space(cfg)
    obs_dim, act_dim = int(np.prod(obs_space.shape or ())), int(np.prod(act_space.shape or ()))

    class Shapes(gymnasium.Env):  # LaneFree-v0's spaces without SUMO
        observation_space = obs_space
        action_space = act_space

    ac, batch = cfg.train.actor_critic, cfg.train.actor_critic.batch_size
    torch.set_num_threads(cfg.train.torch_threads)
    rng = np.random.default_rng(seed)
    fill = [(rng.normal(size=(1, obs_dim)), rng.uniform(-1, 1, (1, act_dim)), rng.normal(size=1),
             rng.normal(size=(1, obs_dim))) for _ in range(2000)]
    model = build_model(cfg, Shapes(), seed, None)
    for obs, act, reward, next_obs in fill:
        model.replay_buffer.add(obs, next_obs, act, reward, np.array([False]), [{}])
    model.set_logger(Logger(None, []))
    model._current_progress_remaining = 1.0
    learner = build_batched([cfg], [seed], obs_space, act_space)
    no = np.array([False])
    for obs, act, reward, next_obs in fill:
        learner.store(obs.astype(np.float32), act.astype(np.float32), reward.astype(np.float32),
                      next_obs.astype(np.float32), no, no)
    runs: dict[str, Callable[[], Any]] = {"SB3 `DDPG.train` (SB3's loop)": functools.partial(model.train, 1, batch),
                                          "the batched update, K = 1 (`lanefree train`)": learner.update}
    actor = list(zip([obs_dim, *ac.actor_layers], [*ac.actor_layers, act_dim]))  # (in, out) per layer
    critic = list(zip([obs_dim + act_dim, *ac.critic_layers], [*ac.critic_layers, 1]))
    shapes = [(batch, i, o) for i, o in actor * 2 + critic * 3]  # forward: targets, critic, actor, critic
    shapes += [(o, batch, i) for i, o in critic + actor]  # weight gradients
    shapes += [(batch, o, i) for i, o in critic[1:] + critic + actor[1:]]  # input gradients
    operands = [(torch.randn(m, k), torch.randn(k, n), torch.empty(m, n)) for m, k, n in shapes]

    def products() -> None:
        for a, b, out in operands:
            torch.mm(a, b, out=out)

    runs[f"its {len(shapes)} matrix products alone"] = products
    samples: dict[str, list[float]] = {name: [] for name in runs}
    for _ in range(repeats):
        for name, run_once in runs.items():
            for _ in range(20):
                run_once()
            t0 = time.perf_counter()
            for _ in range(updates):
                run_once()
            samples[name].append(1000.0 * (time.perf_counter() - t0) / updates)
    return {name: statistics.median(v) for name, v in samples.items()}


def _interleaved(cases: dict[tuple[str, str], Callable[[], float]], repeats: int) -> dict[tuple[str, str], float]:
    """Each case's median rate (env steps/s) over ``repeats`` rounds that measure every case in turn — A, B, C, …,
    A, B, C, … — so machine noise hits every case alike; each measurement printed as it comes."""
    samples: dict[tuple[str, str], list[float]] = {case: [] for case in cases}
    for _ in range(repeats):
        for case, measure in cases.items():
            samples[case].append(measure())
            print(f"  {case[0]} {case[1]}: {samples[case][-1]:.1f} steps/s", flush=True)
    return {case: statistics.median(v) for case, v in samples.items()}


TRAINING_CASES: dict[str, tuple[str, dict[str, Any]]] = {
    "plain SB3 DDPG, libsumo": ("sb3", {"backend": "libsumo"}),
    "SB3's loop, numpy (SAC's, PPO's path)": ("sb3", {}),
    "a batch of one, numpy (`lanefree train`)": ("one", {}),
}
"""The DDPG training paths compared (label: (``sb3``: SB3's loop with SB3's ``DDPG``, ``one``: the batched trainer
with K = 1; ``train`` overrides))."""


DQN_FAMILY = ("dqn", "ddqn", "dueling", "per")
"""The discrete-action algorithms of Table 8."""


def dqn_family_speed(seed: int, steps: int = 1600, repeats: int = REPEATS) -> str:
    """Markdown: env steps/s of each DQN-family algorithm on LaneFree-v0 at 90 veh/km (numpy backend, the paper's
    settings) as a batch of one (``lanefree train``), beside SB3's own ``DQN`` in SB3's loop (what a user would
    write; SB3 has no double, dueling or prioritised DQN), every case measured ``repeats`` times interleaved
    (medians)."""
    from lanefree_sumo.rl.models import make_vec_env, training_config

    cfg = training_config(merge_config(LaneFreeConfig(), {
        "seed": seed, "scenario": {"density_veh_per_km": PEER_DENSITY}, "train": {"algo": "dqn"}}))
    cases: dict[tuple[str, str], Callable[[], float]] = {
        ("dqn", "sb3"): functools.partial(_train_rate, cfg, functools.partial(make_vec_env, cfg), seed, steps)}
    for algo in DQN_FAMILY:
        cases[(algo, "one")] = functools.partial(lambda a: batched_rate(a, 1, seed, steps)[0], algo)
    rate = _interleaved(cases, repeats)
    total = 625 * LaneFreeConfig().sim.episode_steps
    slow = rate[("dqn", "sb3")]
    lines = [
        f"The DQN family (paper settings: 128-64, batch 64, one update per env step, target copy every 10 000 steps; "
        f"LaneFree-v0 at {PEER_DENSITY:g} veh/km, numpy backend, one env; {SPEED_STARTS} random steps, then {steps} "
        f"timed; median of {repeats} interleaved repeats; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} "
        "cores at the end), env steps/s; × and the minutes against SB3's own `DQN` in SB3's loop "
        f"({slow:.1f} steps/s, {total / slow / 60:.0f} min for 625 episodes), which has no double, dueling or "
        "prioritised variant:",
        "",
        "| algorithm | a batch of one (`lanefree train`) | × SB3's `DQN` | 625 episodes |",
        "|---|---|---|---|",
    ]
    for algo in DQN_FAMILY:
        fast = rate[(algo, "one")]
        lines.append(f"| {algo} | {fast:.1f} | {fast / slow:.2f}× | {total / fast / 60:.0f} min |")
    return "\n".join(lines)


def training_speed(seed: int, steps: int = 1600, peer_steps: int = 200, repeats: int = REPEATS) -> str:
    """Markdown: env steps/s of DDPG on LaneFree-v0 at 90 veh/km along the training paths of
    :data:`TRAINING_CASES` (plain SB3 DDPG — what a user would write — first), of the peer highway-v0 with
    as many vehicles and a 0.25 s step, and of the envs alone — every case measured ``repeats`` times
    interleaved in this run (medians) — plus the update alone and its floor."""
    from lanefree_sumo.rl.models import make_vec_env, training_config

    cfg = training_config(merge_config(LaneFreeConfig(), {
        "seed": seed, "scenario": {"density_veh_per_km": PEER_DENSITY}, "train": {"algo": "ddpg"}}))
    n = cfg.background_vehicles

    def lanefree(backend: str) -> Any:
        return make_vec_env(merge_config(cfg, {"backend": backend}))

    cases: dict[tuple[str, str], Callable[[], float]] = {
        ("lanefree", "env libsumo"): functools.partial(_env_rate, functools.partial(lanefree, "libsumo"), steps, seed),
        ("lanefree", "env numpy"): functools.partial(_env_rate, functools.partial(lanefree, "numpy"), steps, seed),
    }
    for label, (kind, train) in TRAINING_CASES.items():
        case_cfg = merge_config(cfg, {"train": train})
        case_cfg = merge_config(case_cfg, {"backend": case_cfg.train.backend})
        make = functools.partial(make_vec_env, case_cfg)
        cases[("lanefree", label)] = (functools.partial(_train_rate, case_cfg, make, seed, steps)
                                      if kind == "sb3" else lambda: batched_rate("ddpg", 1, seed, steps)[0])
    try:
        import highway_env  # noqa: F401
        peers: tuple[int, ...] = (4, 16)
    except ImportError:
        peers = ()
    for hz in peers:
        highway = functools.partial(_highway_env, n, hz, seed)
        cases[(f"highway{hz}", "env")] = functools.partial(_env_rate, highway, peer_steps, seed)
        cases[(f"highway{hz}", "sb3")] = functools.partial(_train_rate, cfg, highway, seed, peer_steps)
    rate = _interleaved(cases, repeats)
    total = 625 * cfg.sim.episode_steps

    def minutes(r: float) -> str:
        return f"{total / r / 60:.0f} min"

    plain = rate[("lanefree", next(iter(TRAINING_CASES)))]
    lines = [
        f"Training speed (DDPG, paper settings: actor and critic 256-128, batch 64, one update per env step, "
        f"{cfg.train.torch_threads} torch thread; LaneFree-v0 at {PEER_DENSITY:g} veh/km ({n} + agent), one env, "
        f"0.25 s per env step; {SPEED_STARTS} random steps, then {steps} (highway-v0: {peer_steps}) timed; median "
        f"of {repeats} interleaved repeats; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores at the "
        "end), env steps/s:",
        "",
        f"| LaneFree-v0 | env steps/s | × plain SB3 | {total:,} steps (625 episodes) at this rate |\n|---|---|---|---|",
        f"| env alone, libsumo | {rate[('lanefree', 'env libsumo')]:.1f} | | |",
        f"| env alone, numpy | {rate[('lanefree', 'env numpy')]:.1f} | | |",
    ]
    for label in TRAINING_CASES:
        r = rate[("lanefree", label)]
        lines.append(f"| DDPG: {label} | {r:.1f} | {r / plain:.2f}× | {minutes(r)} |")
    if peers:
        names = {4: "highway-v0, 4 Hz physics (1 step)", 16: "highway-v0, 16 Hz physics (4 steps)"}
        lines += ["", "The peer, highway-v0 with as many vehicles (env steps/s; LaneFree-v0 / highway-v0 in brackets, "
                  "against LaneFree-v0's libsumo env and its plain SB3 row):", "",
                  "| env | env alone | DDPG, plain SB3 |\n|---|---|---|"]
        for hz in peers:
            e, s = (rate[(f"highway{hz}", k)] for k in ("env", "sb3"))
            lines.append(f"| {names[hz]} | {e:.1f} ({rate[('lanefree', 'env libsumo')] / e:.1f}×) "
                         f"| {s:.1f} ({plain / s:.1f}×) |")
    else:
        lines += ["", "(highway-env is not installed: `pip install -e '.[bench]'` adds the highway-v0 peer.)"]
    costs = update_costs(seed, repeats=repeats)
    reference = next(iter(costs.values()))
    lines += ["", "One update, the learner alone (ms, median of interleaved repeats):", "",
              "| update | ms | SB3 / this |\n|---|---|---|"]
    lines += [f"| {name} | {ms:.2f} | {reference / ms:.2f}× |" for name, ms in costs.items()]
    lines += ["", dqn_family_speed(seed, steps, repeats)]
    return "\n".join(lines)


# -- batched training: K runs in one process against sequential runs --------------------------------------------

BATCH_SIZES = (1, 4, 8, 16)
PAPER_RUN_STEPS = 625 * 800
"""Env steps of a paper run (625 episodes of 800 steps)."""


def batched_rate(algo: str, runs: int, seed: int, steps: int, density: float = PEER_DENSITY) -> tuple[float, float]:
    """(batch steps/s, replay bytes per run) of ``runs`` runs of ``algo`` (the paper's settings, seeds ``seed`` …)
    trained as one batch, as :mod:`lanefree_sumo.experiments.runners.batch` trains them (act, env step, store, update),
    timed over ``steps`` steps once learning has started; one thread."""
    import torch

    from lanefree_sumo.rl.batched_env import BatchedRingEnv
    from lanefree_sumo.rl.env import action_space, observation_space
    from lanefree_sumo.rl.models import build_batched, training_config
    from lanefree_sumo.tools.bench_gpu import lockstep_rate

    cfgs = [training_config(merge_config(LaneFreeConfig(), {
        "seed": seed + k, "scenario": {"density_veh_per_km": density}, "train": {"algo": algo}})) for k in range(runs)]
    torch.set_num_threads(cfgs[0].train.torch_threads)
    env = BatchedRingEnv(cfgs)
    learner = build_batched(cfgs, [c.seed for c in cfgs], observation_space(cfgs[0]), action_space(cfgs[0]))
    rate = lockstep_rate(env, learner, learner.learning_starts, steps)
    replay = sum(v.nbytes for v in learner.replay.state_dict().values() if isinstance(v, torch.Tensor))
    return rate, replay / runs


def single_run_speed(seed: int, steps: int = 800, repeats: int = REPEATS) -> str:
    """Markdown: env steps/s of one run of DDPG and of DQN (the paper's settings at 90 veh/km, one thread) along
    the two single-run paths, measured ``repeats`` times interleaved (medians): SB3's loop with stock SB3's class
    (SAC's and PPO's loop) and a batch of one (``lanefree train`` for every batchable run)."""
    cases: dict[tuple[str, str], Callable[[], float]] = {}
    for algo in ("ddpg", "dqn"):
        cases[(algo, "sb3")] = functools.partial(training_rate, algo, seed, steps=steps)
        cases[(algo, "one")] = functools.partial(lambda a: batched_rate(a, 1, seed, steps)[0], algo)
    rate = _interleaved(cases, repeats)
    lines = [
        f"One run, the two paths (paper settings, {PEER_DENSITY:g} veh/km, one thread; {steps} steps timed after "
        f"learning starts; median of {repeats} interleaved repeats; load average {os.getloadavg()[0]:.1f} on "
        f"{os.cpu_count()} cores at the end), env steps/s:",
        "",
        "| algorithm | SB3's loop | a batch of one (`lanefree train`) | × |",
        "|---|---|---|---|",
    ]
    for algo in ("ddpg", "dqn"):
        before, now = rate[(algo, "sb3")], rate[(algo, "one")]
        lines.append(f"| {algo} | {before:.1f} | {now:.1f} | {now / before:.2f}× |")
    return "\n".join(lines)


def slot_rate(algo: str, seed: int, extra: dict[str, Any], steps: int, density: float = PEER_DENSITY) -> float:
    """Env steps/s of one run of several agents or environments (``extra``) in the one trainer (its slots rows
    of :class:`~lanefree_sumo.rl.env_batch.SlotBatch`: act, env step, store, update, reset), timed over ``steps``
    steps once learning has started; one thread."""
    import torch

    from lanefree_sumo.rl.env import action_space, observation_space
    from lanefree_sumo.rl.env_batch import SlotBatch
    from lanefree_sumo.rl.models import build_batched, training_config

    cfg = training_config(merge_config(merge_config(LaneFreeConfig(), {
        "seed": seed, "scenario": {"density_veh_per_km": density}, "train": {"algo": algo}}), extra))
    torch.set_num_threads(cfg.train.torch_threads)
    env = SlotBatch([cfg])
    learner = build_batched([cfg], [seed], observation_space(cfg), action_space(cfg))
    obs = env.reset()
    warm = learner.learning_starts // learner.slots
    t0 = 0.0
    for step in range(warm + steps):
        if step == warm:
            t0 = time.perf_counter()
        actions = learner.act(obs, explore=True)
        new_obs, reward, terminated, truncated, _ = env.step(actions)
        learner.store(obs, actions, reward, new_obs, terminated | truncated, truncated & ~terminated)
        learner.update()
        obs = env.reset([0]) if (terminated | truncated).any() else new_obs
    rate = steps / (time.perf_counter() - t0)
    env.close()
    return rate


SLOT_CASES: dict[str, dict[str, Any]] = {"4 agents": {"scenario": {"agents": 4}},
                                         "2 environments": {"train": {"envs": 2}}}
"""The runs of several slots :func:`slot_speed` times."""


def slot_speed(seed: int, steps: int = 400, repeats: int = REPEATS) -> str:
    """Markdown: env steps/s of one DDPG run of several agents, and of several environments, on SB3's loop (its
    ``SharedPolicyVecEnv``; one process per environment) and in the one trainer (``lanefree train``), measured
    ``repeats`` times interleaved (medians)."""
    cases: dict[tuple[str, str], Callable[[], float]] = {}
    for label, extra in SLOT_CASES.items():
        cases[(label, "sb3")] = functools.partial(training_rate, "ddpg", seed, PEER_DENSITY,
                                                  steps * slots_of(extra), extra=extra)
        cases[(label, "one")] = functools.partial(slot_rate, "ddpg", seed, extra, steps)
    rate = _interleaved(cases, repeats)
    lines = [
        f"One DDPG run of several agents or environments, the two paths (paper settings, {PEER_DENSITY:g} veh/km, one "
        f"thread; {steps} steps timed after learning starts; median of {repeats} interleaved repeats; load average "
        f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores at the end), env steps/s (a step moves every agent or "
        "environment):",
        "",
        "| run | SB3's loop | the one trainer (`lanefree train`) | × |",
        "|---|---|---|---|",
    ]
    for label in SLOT_CASES:
        before, now = rate[(label, "sb3")], rate[(label, "one")]
        lines.append(f"| DDPG, {label} | {before:.1f} | {now:.1f} | {now / before:.2f}× |")
    return "\n".join(lines)


def slots_of(extra: dict[str, Any]) -> int:
    """The slots of a run with the overrides ``extra``."""
    return int(extra.get("scenario", {}).get("agents", 1)) * int(extra.get("train", {}).get("envs", 1))


def batch_speed(seed: int, steps: int = 800) -> str:
    """Markdown: runs per core-hour of sequential ``lanefree train`` against batches of K runs (one process, one
    thread each, measured one after another in this run), DDPG and DQN, and the replay memory per run."""
    lines = [
        f"Batched training against sequential runs (paper settings, {PEER_DENSITY:g} veh/km, one thread; {steps} "
        f"steps timed after learning starts; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores at the "
        "start — on a shared machine the figures move with the load):",
        "",
        "| algorithm | runs | env steps/s per run | runs per core-hour | × sequential | replay per run |",
        "|---|---|---|---|---|---|",
    ]
    for algo in ("ddpg", "dqn"):
        base = 0.0
        for k in BATCH_SIZES:
            rate, replay = batched_rate(algo, k, seed, steps)
            per_hour = k * rate * 3600 / PAPER_RUN_STEPS
            base = base or per_hour  # the first size, 1: sequential `lanefree train` runs
            label = "one run (`lanefree train`, a batch of one)" if k == 1 else f"batch of {k}"
            lines.append(f"| {algo} | {label} | {rate:.0f} | {per_hour:.2f} | {per_hour / base:.2f}× "
                         f"| {replay / 2**20:.0f} MiB ({int(24 * 2**30 // replay)} runs in 24 GiB) |")
            print(f"  {algo} batch {k}: {rate:.0f} steps/s", flush=True)
    return "\n".join(lines)


SET_BATCH = 6
"""Runs of the set observation's batch in :func:`set_update_speed` (the remedies' DDPG grid: 2 variants × 3 seeds)."""


def set_update_speed(seed: int, updates: int = 30, fill: int = 1000) -> str:
    """Markdown: the CPU time of one DDPG update on the set observation (the paper encoder, the paper's settings
    at 70 veh/km): one run on SB3's loop (SB3's autograd update) against the batched learner's per run, for a batch
    of 1 (``lanefree train --obs set``) and of :data:`SET_BATCH`; the replay filled with ``fill`` steps of uniformly
    random actions."""
    import torch

    from lanefree_sumo.rl.algorithms.batched.learner import SpacesEnv
    from lanefree_sumo.rl.batched_env import BatchedRingEnv
    from lanefree_sumo.rl.env import action_space, observation_space
    from lanefree_sumo.rl.models import build_batched, build_model, training_config

    cfgs = [training_config(merge_config(LaneFreeConfig(), {
        "seed": seed + k, "scenario": {"density_veh_per_km": 70.0}, "observation": {"kind": "set", "encoder": "paper"},
        "train": {"algo": "ddpg"}})) for k in range(SET_BATCH)]
    torch.set_num_threads(1)
    env = BatchedRingEnv(cfgs)
    spaces = (observation_space(cfgs[0]), action_space(cfgs[0]))
    learners = {k: build_batched(cfgs[:k], [c.seed for c in cfgs[:k]], *spaces) for k in (1, SET_BATCH)}
    single = build_model(cfgs[0], SpacesEnv(*spaces), cfgs[0].seed, None)
    rng = np.random.default_rng(seed)
    obs = env.reset()
    seen = []
    for _ in range(fill):
        actions = rng.uniform(-1, 1, (SET_BATCH, 2)).astype(np.float32)
        new_obs, reward, terminated, truncated, _ = env.step(actions)
        done = terminated | truncated
        seen.append(float(obs["others"][..., -1].sum(axis=1).mean()))
        for k, learner in learners.items():
            learner.store({key: v[:k] for key, v in obs.items()}, actions[:k], reward[:k],
                          {key: v[:k] for key, v in new_obs.items()}, done[:k], (truncated & ~terminated)[:k])
        single.replay_buffer.add({key: v[:1] for key, v in obs.items()}, {key: v[:1] for key, v in new_obs.items()},
                                 actions[:1], reward[:1], done[:1], [{}])
        obs = env.reset([k for k in range(SET_BATCH) if done[k]]) if done.any() else new_obs

    def cpu_ms(step: Callable[[], None]) -> float:
        step()  # warm up (first products probed)
        began = time.thread_time()
        for _ in range(updates):
            step()
        return (time.thread_time() - began) / updates * 1000

    from stable_baselines3.common.logger import Logger

    single.set_logger(Logger(None, []))
    base = cpu_ms(lambda: single.train(gradient_steps=1, batch_size=single.batch_size))
    lines = [f"The set observation's DDPG update (paper encoder, 70 veh/km, batch {single.batch_size}, "
             f"{cfgs[0].observation.max_rows} rows, {statistics.mean(seen):.1f} vehicles seen on average; CPU time of "
             f"one thread, {updates} updates after {fill} random steps):", "",
             "| learner | ms per update per run | × SB3's |", "|---|---|---|",
             f"| one run on SB3's loop (SB3's autograd update) | {base:.1f} | 1.00× |"]
    for k, learner in learners.items():
        per_run = cpu_ms(learner._update) / k
        label = "a batch of one (`lanefree train --obs set`)" if k == 1 else f"batched, {k} runs"
        lines.append(f"| {label} | {per_run:.1f} | {base / per_run:.2f}× |")
    return "\n".join(lines)


def _vector_rate(make: Callable[[], Any], k: int, steps: int, render: bool = False) -> float:
    """Env steps/s (summed over the K environments) of the vector env ``make()`` gives — a gymnasium ``VectorEnv``
    or an SB3 ``VecEnv`` —, zero actions, after 10 warm-up steps; ``render``: a frame of every environment each step
    too."""
    env = make()
    try:
        if hasattr(env, "step_async"):  # SB3's VecEnv: seeds before its reset, the action space per environment
            env.seed(0)
            env.reset()
            shape = env.action_space.shape
        else:
            env.reset(seed=0)
            shape = env.single_action_space.shape
        actions = np.zeros((k, *shape), dtype=np.float32)
        for _ in range(10):
            env.step(actions)
        t0 = time.perf_counter()
        for _ in range(steps):
            env.step(actions)
            if render:
                env.render()
        return steps * k / (time.perf_counter() - t0)
    finally:
        env.close()


def vector_speed(sizes: tuple[int, ...] = (8, 64), steps: int = 200, repeats: int = REPEATS) -> str:
    """LaneFree-v0's vector entry point (K worlds as one batched array program) against gymnasium's
    SyncVectorEnv over K LaneFree-v0 (numpy backend), the defaults' 70 veh/km, interleaved ``repeats`` times
    (median); the same for SB3: :class:`~lanefree_sumo.rl.sb3_vec_env.BatchedVecEnv` against SB3's DummyVecEnv
    over K LaneFree-v0; then what an ``rgb_array`` frame costs beside a step, for one LaneFree-v0."""
    import gymnasium as gym
    from stable_baselines3.common.vec_env import DummyVecEnv

    import lanefree_sumo  # noqa: F401 - registers LaneFree-v0
    from lanefree_sumo.rl.sb3_vec_env import BatchedVecEnv

    lines = ["Vector environments (LaneFree-v0, 70 veh/km, numpy worlds, zero actions; env steps/s summed over K, "
             f"median of {repeats} interleaved repeats of {steps} steps):", "",
             "| K | vector entry point | SyncVectorEnv | × |", "|---|---|---|---|"]
    for k in sizes:
        vector, sync = [], []
        n = max(10, steps * 8 // k)
        for _ in range(repeats):
            vector.append(_vector_rate(functools.partial(gym.make_vec, "LaneFree-v0", num_envs=k,
                                                         vectorization_mode="vector_entry_point"), k, n))
            sync.append(_vector_rate(functools.partial(gym.make_vec, "LaneFree-v0", num_envs=k,
                                                       vectorization_mode="sync"), k, n))
        v, y = statistics.median(vector), statistics.median(sync)
        lines.append(f"| {k} | {v:.0f} | {y:.0f} | {v / y:.2f}× |")
    lines += ["", "| K | BatchedVecEnv (SB3) | DummyVecEnv over LaneFree-v0 | × |", "|---|---|---|---|"]
    for k in sizes:
        batched, dummy = [], []
        n = max(10, steps * 8 // k)
        for _ in range(repeats):
            batched.append(_vector_rate(functools.partial(BatchedVecEnv, k), k, n))
            dummy.append(_vector_rate(functools.partial(DummyVecEnv, [functools.partial(gym.make, "LaneFree-v0")] * k),
                                   k, n))
        b, d = statistics.median(batched), statistics.median(dummy)
        lines.append(f"| {k} | {b:.0f} | {d:.0f} | {b / d:.2f}× |")
    plain, drawn = [], []
    for _ in range(repeats):
        plain.append(_vector_rate(lambda: gym.make_vec("LaneFree-v0", num_envs=1, vectorization_mode="sync"), 1,
                                  steps))
        drawn.append(_vector_rate(lambda: gym.make_vec("LaneFree-v0", num_envs=1, vectorization_mode="sync",
                                                       render_mode="rgb_array"), 1, steps, render=True))
    p, d = statistics.median(plain), statistics.median(drawn)
    lines += ["", "| LaneFree-v0, one env | steps/s | ms per step |", "|---|---|---|",
              f"| step | {p:.0f} | {1000.0 / p:.2f} |", f"| step + rgb_array frame | {d:.0f} | {1000.0 / d:.2f} |",
              f"| the frame alone | | {1000.0 / d - 1000.0 / p:.2f} |"]
    return "\n".join(lines)


def run(steps: int, seed: int, out_dir: Path) -> str:
    from lanefree_sumo.sim.backends.sumo import bare_step_rate

    rows = []
    profile = []
    for density in DENSITIES:
        base = merge_config(LaneFreeConfig(), {"scenario": {"density_veh_per_km": density}})
        state = spawn(base, np.random.default_rng(seed))
        bare, lib, resets, splits = [], [], [], []
        for _ in range(REPEATS):
            bare.append(bare_step_rate(base, state, steps))
            rate, reset_ms, split = _rate(merge_config(base, {"backend": "libsumo"}), steps, seed)
            lib.append(rate)
            resets.append(reset_ms)
            splits.append(split)
        traci_rate, _, _ = _rate(merge_config(base, {"backend": "traci"}), steps, seed)
        numpy_rate, _, _ = _rate(merge_config(base, {"backend": "numpy"}), steps, seed)
        a, b = statistics.median(bare), statistics.median(lib)
        rows.append((density, state.n, a, b, traci_rate, numpy_rate, b / a, statistics.median(resets)))
        split = {k: statistics.median(s[k] for s in splits) for k in splits[0]}
        ceiling = (1000.0 / a) / (split["sumo_step"] + split["api_calls"])
        profile.append((density, 1000.0 / a, split["sumo_step"], split["api_calls"], split["physics"], ceiling))
        print(f"  {density} veh/km done", flush=True)
    header = (
        "| density (veh/km) | vehicles | (a) bare SUMO | (b) libsumo + forces | (c) TraCI + forces "
        "| (d) numpy only | (b)/(a) | reset (ms) |\n|---|---|---|---|---|---|---|---|"
    )
    lines = [header] + [
        f"| {d} | {n} | {a:.0f} | {b:.0f} | {c:.0f} | {e:.0f} | {r:.2f} | {ms:.1f} |"
        for d, n, a, b, c, e, r, ms in rows
    ]
    lines += [
        "",
        "Where (b)'s time goes, ms per step (median of the repeats):",
        "",
        "| density (veh/km) | bare SUMO step (a) | SUMO step under control | setSpeed/changeSublane + read "
        "| Python physics | (b)/(a) ceiling with zero physics |\n|---|---|---|---|---|---|",
    ] + [
        f"| {d} | {bare_ms:.3f} | {st:.3f} | {api:.3f} | {phys:.3f} | {ceil:.2f} |"
        for d, bare_ms, st, api, phys, ceil in profile
    ]
    lines += [
        "",
        "LaneFree-v0 at 120 veh/km on libsumo: the env's own work per step against the core step:",
        "",
        "| observation | env work (ms/step) | core step (ms/step) | share |\n|---|---|---|---|",
    ] + [f"| {kind} | {work:.3f} | {core:.3f} | {work / core:.1%} |" for kind, work, core in env_overhead(steps, seed)]
    lines += [
        "",
        "Training throughput at 90 veh/km (`lanefree train`'s defaults: numpy backend, one env, learning updates every "
        "step, docs/specification.md §9 settings):",
        "",
        "| algorithm | env steps/s incl. learning | projected 625-episode run |\n|---|---|---|",
    ]
    for algo in ("ddpg", "dqn"):
        rate = batched_rate(algo, 1, seed, 1600, density=90.0)[0]
        hours = 625 * 800 / rate / 3600.0
        lines.append(f"| {algo} | {rate:.0f} | {hours:.2f} h ({625 * 800 / rate / 625:.1f} s/episode) |")
    lines += ["", vector_speed(), "", training_speed(seed),
              "", single_run_speed(seed), "", slot_speed(seed), "", batch_speed(seed), "", set_update_speed(seed)]
    table = "\n".join(lines)
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    out_dir.mkdir(parents=True, exist_ok=True)
    text = (
        f"Step rates in steps/s ({steps} steps, median of {REPEATS} for (a) and (b)), "
        f"SUMO {_sumo_version()}, {stamp}\n\n{table}\n"
    )
    (out_dir / f"bench-{stamp}.md").write_text(text)
    (out_dir / "latest.md").write_text(text)
    return text


def _sizes(text: str) -> tuple[int, ...]:
    """``1,150,1024`` → (1, 150, 1024)."""
    try:
        sizes = tuple(int(part) for part in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected numbers separated by commas, got {text!r}") from None
    if not sizes or min(sizes) < 1:
        raise argparse.ArgumentTypeError(f"sizes are whole numbers ≥ 1, got {text!r}")
    return sizes


def _sumo_version() -> str:
    from lanefree_sumo.sim.backends.sumo import sumo_version

    return sumo_version()


def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m lanefree_sumo.tools.bench", description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=800, help="steps per measurement (default 800)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the traffic (default 0)")
    parser.add_argument("--out", type=Path, default=Path("runs/bench"), help="folder for the table")
    parser.add_argument("--training-only", action="store_true", help="only the training-speed sections")
    parser.add_argument("--dqn-only", action="store_true", help="only the DQN family's training-speed section")
    parser.add_argument("--vector-only", action="store_true",
                        help="only the vector environments and the cost of a frame (--steps per row)")
    parser.add_argument("--batch-only", action="store_true",
                        help="only the batched-training section (sequential against batches of 1, 4, 8, 16 runs)")
    parser.add_argument("--single-only", action="store_true",
                        help="only one run's two paths: SB3's loop against a batch of one")
    parser.add_argument("--slots-only", action="store_true",
                        help="only a run of several agents or environments: SB3's loop against the one trainer")
    gpu = parser.add_argument_group("--gpu: the batched path on a torch device (lanefree_sumo.tools.bench_gpu)")
    gpu.add_argument("--gpu", action="store_true", help="run the device benchmark (make bench-gpu)")
    gpu.add_argument("--device", default="cuda", choices=("cuda", "torch-cpu"),
                     help="train.device of --gpu (default cuda; torch-cpu runs the same torch program on the CPU)")
    gpu.add_argument("--env-sizes", type=_sizes, default=(16384, 1024, 1),
                     help="K of the env rows, measured after the training rows (16384,1024,1)")
    gpu.add_argument("--train-sizes", type=_sizes, default=(110, 1, 150, 1024),
                     help="K of the DDPG training rows; the first two are measured first (110,1,150,1024)")
    gpu.add_argument("--dqn-sizes", type=_sizes, default=(20, 10, 1, 1024),
                     help="K of the DQN training rows; the first two are measured first (20,10,1,1024)")
    gpu.add_argument("--per-sizes", type=_sizes, default=(10,),
                     help="K of the prioritised-replay DQN rows, measured after the first two of each other (10)")
    gpu.add_argument("--env-steps", type=int, default=100, help="steps per env row (default 100)")
    gpu.add_argument("--train-steps", type=int, default=100, help="iterations per training row (default 100)")
    gpu.add_argument("--budget-s", type=float, default=420.0,
                     help="rows whose turn comes later are skipped (default 420 s: done within 8 minutes)")
    args = parser.parse_args()
    if args.gpu:
        from lanefree_sumo.errors import LaneFreeError
        from lanefree_sumo.tools import bench_gpu

        try:
            bench_gpu.run(args.device, args.env_sizes, args.train_sizes, args.dqn_sizes, args.env_steps,
                          args.train_steps, args.budget_s, args.seed, per_sizes=args.per_sizes)
        except LaneFreeError as exc:
            raise SystemExit(f"error: {exc}") from None
    elif args.vector_only:
        print(vector_speed(steps=args.steps))
    elif args.single_only:
        print(single_run_speed(args.seed, steps=args.steps))
    elif args.slots_only:
        print(slot_speed(args.seed, steps=args.steps))
    elif args.batch_only:
        print(single_run_speed(args.seed, steps=args.steps))
        print()
        print(batch_speed(args.seed, steps=args.steps))
        print()
        print(set_update_speed(args.seed))
    elif args.dqn_only:
        print(dqn_family_speed(args.seed))
    else:
        print(training_speed(args.seed) if args.training_only else run(args.steps, args.seed, args.out))


if __name__ == "__main__":
    main()

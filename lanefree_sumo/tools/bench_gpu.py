"""``make bench-gpu`` (``python -m lanefree_sumo.tools.bench --gpu``): the lockstep loop on a torch device.

Printed in one run: the card (or CPU), torch's and CUDA's versions; whether an iteration reads anything from the
host (torch's sync debug mode, on CUDA); how far the compiled ring step strays from the step as written; then, as
markdown tables, training (:mod:`lanefree_sumo.rl.lockstep`: act, env step, store, one update per run, the paper's
settings; on a GPU each iteration a CUDA graph with the ring step and the update compiled) in iterations/s for
DDPG at K = 110 (the paper grid's DDPG runs), 1, 150, 1024 and for DQN at K = 20 (the grid's dqn and ddqn runs),
10 (dueling's), 1, 1024 — the first two of each first, then prioritised replay at K = 10 (per's) —, the same DDPG
iteration with graphs but not compiled at
K = 110; the environment alone (:class:`~lanefree_sumo.rl.batched_env.BatchedRingEnv`, float64, uniformly random
actions drawn on the device) in agent-steps/s at K = 16 384, 1024, 1; the projected wall time of a 625-episode run
and of the paper's grid. On a fresh GPU machine each new K costs a compilation (about 40 s to 200 s for the
first); inductor's cache on the machine makes a second run's cheap. Each measurement is capped in steps and the
whole run in time (``--budget-s``, default 420 s, so that it ends within 8 minutes on one card): a row whose turn
comes after the budget is printed as skipped. ``--device torch-cpu`` with small sizes runs the same code on the CPU,
without graphs or compiling (a test does).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from lanefree_sumo.config import LaneFreeConfig, merge_config
from lanefree_sumo.sim.xp import on_cpu, torch_device

GRID_DDPG_RUNS = 110
"""The paper grid's DDPG runs: 11 settings × 10 seeds (one batch: they may differ in preset and density)."""
GRID_DQN_BATCHES = (20, 10)
"""The grid's DQN-family batches with uniform replay: dqn and ddqn's 20 runs together (one network), dueling's
10 (timed at DQN's rate; its head is a little more work)."""
GRID_PER_RUNS = 10
"""The grid's prioritised-replay runs (one batch)."""
RUN_ITERATIONS = 625 * 800
"""Lockstep iterations of a paper run (625 episodes of 800 steps)."""
DENSITY = 90.0
LEARNING_STARTS = 64
"""Updates start after this many steps here (a paper run: 800): the time of an iteration once learning runs is
what is measured, and the warm-up before it costs the budget nothing it need not."""


def _sync(device: str) -> None:
    """Wait for ``device`` (``train.device``) to finish what it was given (nothing to wait for on the CPU)."""
    if not on_cpu(device):
        import torch

        torch.cuda.synchronize()


def _configs(runs: int, seed: int, algo: str = "ddpg") -> list[LaneFreeConfig]:
    from lanefree_sumo.rl.models import training_config

    section = "actor_critic" if algo == "ddpg" else "dqn"
    return [training_config(merge_config(LaneFreeConfig(), {
        "seed": seed + k, "scenario": {"density_veh_per_km": DENSITY},
        "train": {"algo": algo, section: {"learning_starts_steps": LEARNING_STARTS}}}))
        for k in range(runs)]


def _loop(runs: int, device: str, seed: int, algo: str | None, graphs: bool | None = None,
          compile: str | None | bool = True) -> Any:
    """A started :class:`~lanefree_sumo.rl.lockstep.Lockstep` of ``runs`` rings (``algo`` None: no learner)."""
    from lanefree_sumo.rl.batched_env import BatchedRingEnv
    from lanefree_sumo.rl.env import action_space, observation_space
    from lanefree_sumo.rl.lockstep import Lockstep
    from lanefree_sumo.rl.models import build_batched

    cfgs = _configs(runs, seed, algo or "ddpg")
    env = BatchedRingEnv(cfgs, device=device)
    learner = None if algo is None else build_batched(cfgs, [c.seed for c in cfgs], observation_space(cfgs[0]),
                                                      action_space(cfgs[0]), device=device)
    loop = Lockstep(env, learner, seed, graphs=graphs, compile=compile)
    loop.start(env.reset())
    return loop


WARM_S: list[float] = []
"""The seconds the untimed iterations of each timed loop took (on CUDA: compiling and capturing), in order."""


def _timed(loop: Any, warm: int, steps: int, device: str) -> float:
    """Iterations/s of ``loop`` over ``steps`` iterations after ``warm`` untimed ones (their time is appended to
    :data:`WARM_S`)."""
    t0 = time.perf_counter()
    for _ in range(warm):
        loop.iterate()
    _sync(device)
    WARM_S.append(time.perf_counter() - t0)
    t0 = time.perf_counter()
    for _ in range(steps):
        loop.iterate()
    _sync(device)
    return steps / (time.perf_counter() - t0)


def env_rate(runs: int, steps: int, device: str, seed: int = 0) -> float:
    """Agent-steps/s of the batched environment alone, ``runs`` rings on ``device`` driven by uniformly random
    actions drawn there (the lockstep loop without a learner), timed over ``steps`` steps after three untimed ones."""
    return runs * _timed(_loop(runs, device, seed, None), 3, steps, device)


def train_rate(runs: int, steps: int, device: str, seed: int = 0, algo: str = "ddpg",
               graphs: bool | None = None, compile: str | None | bool = True) -> float:
    """Lockstep iterations/s of ``runs`` batched ``algo`` runs on ``device`` (act, env step, store, one update per
    run), timed over ``steps`` iterations once updates run (``graphs``, ``compile``: as :class:`~lanefree_sumo.rl.
    lockstep.Lockstep`'s)."""
    loop = _loop(runs, device, seed, algo, graphs, compile)
    return _timed(loop, loop.learner.learning_starts + 3, steps, device)


def host_reads(device: str, seed: int = 0) -> str:
    """Whether a lockstep iteration (DDPG and DQN, with updates, two runs, no graphs) makes torch wait for the
    device: 'none', or the first operation torch's sync debug mode stopped at (CUDA only)."""
    import torch

    if on_cpu(device):
        return "not checked (torch's sync debug mode watches CUDA only)"
    for algo in ("ddpg", "dqn", "per"):
        loop = _loop(2, device, seed, algo, graphs=False, compile=None)
        for _ in range(loop.learner.learning_starts + 1):
            loop.iterate()
        torch.cuda.synchronize()
        torch.cuda.set_sync_debug_mode("error")
        try:
            loop._iteration(False, True)
        except RuntimeError as exc:
            return f"{algo}: {str(exc).splitlines()[0]}"
        finally:
            torch.cuda.set_sync_debug_mode("default")
    return "none"


def compiled_drift(device: str, runs: int = 64, steps: int = 100, seed: int = 0,
                   compile: str | bool = True) -> str:
    """How far the compiled ring step (``compile``: :class:`~lanefree_sumo.rl.lockstep.Lockstep`'s; by default
    inductor on CUDA) strays from the step as written, the same rings under the same random actions: the largest
    |Δx| along the ring (m) and |Δvx| (m/s) after one step and after ``steps`` (fused kernels may round otherwise;
    the rings are chaotic, so the gap grows)."""
    import torch

    from lanefree_sumo.sim.state import wrap

    loops = [_loop(runs, device, seed, None, graphs=False, compile=c) for c in (compile, None)]
    if loops[0].compiled is None:
        return "not compiled on this device"
    out = []
    for step in range(1, steps + 1):
        state = torch.cuda.get_rng_state(loops[0].active.device) if loops[0].cuda else None
        for loop in loops:
            if state is not None:
                torch.cuda.set_rng_state(state, loop.active.device)
            else:
                loop.generator.manual_seed(seed + step)
            loop.iterate()
        if step in (1, steps):
            a, b = (loop.env.world for loop in loops)
            gap = abs(wrap(a.x - b.x, a.road_length[:, None]))  # along the ring: 0.1 m and 499.9 m: 0.2 m
            out.append(f"after {step} step(s) |Δx| ≤ {float(gap.max()):.1e} m (along the ring), "
                       f"|Δvx| ≤ {float((a.vx - b.vx).abs().max()):.1e} m/s")
    return f"{loops[0].compiled}, K = {runs}: " + "; ".join(out)


def lockstep_rate(env: Any, learner: Any, warm: int, steps: int, device: str = "cpu") -> float:
    """Lockstep iterations/s of a batched ``learner`` on its ``env`` (act, env step, store, update, reset the runs
    whose episode ended, as :mod:`lanefree_sumo.experiments.runners.batch` trains), timed over ``steps`` iterations
    after ``warm`` untimed ones; ``device``: the ``train.device`` to wait for around the timing (none on the CPU)."""
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

    dev = torch_device(device)
    card = torch.cuda.get_device_name(dev) if dev.type == "cuda" else f"CPU ({platform.processor() or 'unknown'})"
    return f"device: {dev} — {card}; torch {torch.__version__}; CUDA {torch.version.cuda or 'none'}"


def run(device: str, env_sizes: Sequence[int], train_sizes: Sequence[int], dqn_sizes: Sequence[int],
        env_steps: int, train_steps: int, budget_s: float, seed: int = 0,
        per_sizes: Sequence[int] = (GRID_PER_RUNS,)) -> str:
    """The benchmark's text (module docstring); each row is printed as soon as it is measured."""
    import torch

    from lanefree_sumo.experiments.runners.batch import check_device

    check_device(device)
    import torch._dynamo

    # every row is a new K, so a new compilation of the same functions (K is a size the code specialises on)
    torch._dynamo.config.recompile_limit = max(torch._dynamo.config.recompile_limit, 64)
    start = time.perf_counter()
    lines: list[str] = []

    def row(text: str) -> None:
        lines.append(text)
        print(text, flush=True)

    def left() -> bool:
        return time.perf_counter() - start < budget_s

    row(describe(device))
    row(f"host reads inside an iteration: {host_reads(device, seed)}")
    drift_runs = train_sizes[0] if train_sizes else 64  # the first DDPG row then reuses the compiled step
    row(f"compiled ring step against the step as written: {compiled_drift(device, drift_runs, seed=seed)}")
    graphs = not on_cpu(device)
    row("")
    row(f"Training, one iteration {'a CUDA graph, the ring step and the update compiled' if graphs else 'eager'} "
        f"(the paper's networks and batch 64; updates from step {LEARNING_STARTS}; the first two sizes of each "
        "algorithm first):")
    row("")
    row("| section | algo | K | iterations | iterations/s | ms/iteration |")
    row("|---|---|---|---|---|---|")
    rates: dict[tuple[str, int], float] = {}
    order = [("ddpg", k) for k in train_sizes[:2]] + [("dqn", k) for k in dqn_sizes[:2]]
    order += [("per", k) for k in per_sizes]
    order += [("ddpg", k) for k in train_sizes[2:]] + [("dqn", k) for k in dqn_sizes[2:]]
    for algo, k in order:
        if not left():
            row(f"| train | {algo} | {k} | 0 | skipped (time budget) | |")
            continue
        rates[algo, k] = rate = train_rate(k, train_steps, device, seed, algo)
        row(f"| train | {algo} | {k} | {train_steps} | {rate:.1f} | {1000 / rate:.2f} |")
    if graphs and left():
        rate = train_rate(GRID_DDPG_RUNS, train_steps, device, seed, "ddpg", compile=None)
        row(f"| train, graph, not compiled | ddpg | {GRID_DDPG_RUNS} | {train_steps} | {rate:.1f} | "
            f"{1000 / rate:.2f} |")
    row("")
    row("Environment alone (float64, random actions drawn on the device):")
    row("")
    row("| section | K | steps | agent-steps/s |")
    row("|---|---|---|---|")
    for k in env_sizes:
        if not left():
            row(f"| env | {k} | 0 | skipped (time budget) |")
            continue
        row(f"| env | {k} | {env_steps} | {env_rate(k, env_steps, device, seed):.0f} |")
    row("")
    if ("ddpg", 1) in rates:
        row(f"one 625-episode DDPG run (K = 1): {RUN_ITERATIONS / rates['ddpg', 1] / 60:.1f} min")
    needed = [("ddpg", GRID_DDPG_RUNS), *(("dqn", k) for k in GRID_DQN_BATCHES), ("per", GRID_PER_RUNS)]
    if any(key not in rates for key in needed):
        row("projected grid: not measured (its batch sizes were not among the rows, or the time budget ran out)")
    else:
        minutes = [RUN_ITERATIONS / rates[key] / 60.0 for key in needed]
        row(f"projected grid: DDPG's {GRID_DDPG_RUNS} runs as one batch {minutes[0]:.1f} min + dqn and ddqn's "
            f"{GRID_DQN_BATCHES[0]} runs as one batch {minutes[1]:.1f} min + dueling's {GRID_DQN_BATCHES[1]} at "
            f"DQN's rate {minutes[2]:.1f} min + per's {GRID_PER_RUNS} {minutes[3]:.1f} min = {sum(minutes):.1f} min, "
            "compiling not counted")
    row(f"(bench took {time.perf_counter() - start:.0f} s; the untimed first iterations of each row, compiling and "
        f"capturing included: {', '.join(f'{w:.0f}' for w in WARM_S)} s)")
    return "\n".join(lines)

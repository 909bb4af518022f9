"""The lockstep loop (lanefree_sumo.rl.lockstep) on the CPU: what a CUDA graph needs of an iteration (nothing read
from the host, no number written from the host, the state copied back into the same buffers) and the device-stream
learners equal to the exact ones given the same minibatch (the device step equal to the host step:
tests/rl/test_batched_env.py)."""

from __future__ import annotations

import contextlib
import traceback
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
import torch as th
from torch.utils._python_dispatch import TorchDispatchMode

from lanefree_sumo.config import LaneFreeConfig, merge_config
from lanefree_sumo.errors import ConfigError
from lanefree_sumo.rl.batched_env import BatchedRingEnv
from lanefree_sumo.rl.env import action_space, observation_space
from lanefree_sumo.rl.lockstep import Lockstep
from lanefree_sumo.rl.models import build_batched, training_config

PHASES = ((True, False), (False, False), (False, True))
"""(random actions, update) of the three iterations a loop captures."""


def configs(algo: str, runs: int = 2, **extra: Any) -> list[LaneFreeConfig]:
    """``runs`` runs of ``algo`` ("dqn+ddqn": dqn, ddqn, dqn, …; "ddpg-set", "per-set": the algorithm on the set
    observation with the paper encoder), densities 70 and 90 by turns."""
    if algo.endswith("-set"):
        algo, extra = algo[:-4], {**extra, "observation": {"kind": "set", "encoder": "paper"}}
    section = "actor_critic" if algo == "ddpg" else "dqn"
    return [training_config(merge_config(LaneFreeConfig(), {
        "seed": k, "scenario": {"density_veh_per_km": 90.0 if k % 2 else 70.0}, **extra,
        "train": {"algo": ("dqn", "ddqn")[k % 2] if algo == "dqn+ddqn" else algo,
                  section: {"learning_starts_steps": 6, "buffer_size": 50}}})) for k in range(runs)]


def loop_of(algo: str | None, seed: int = 0, runs: int = 2, compile: str | None = None, per_run_limits: bool = False,
            **extra: Any) -> Lockstep:
    """A started loop of ``runs`` runs (``per_run_limits``: run 1 with a 25 m/s top speed and a lateral bound)."""
    cfgs = configs(algo or "ddpg", runs, **extra)
    if per_run_limits:
        cfgs[1] = merge_config(cfgs[1], {"scenario": {"agent_max_speed_mps": 25.0, "agent_lateral_speed_ratio": 0.5}})
    env = BatchedRingEnv(cfgs, device="torch-cpu")
    learner = None if algo is None else build_batched(cfgs, [c.seed for c in cfgs], observation_space(cfgs[0]),
                                                      action_space(cfgs[0]), device="cpu")
    loop = Lockstep(env, learner, seed, compile=compile)
    loop.start(env.reset())
    return loop


@contextlib.contextmanager
def no_host_reads() -> Iterator[None]:
    """Every way Python code reads a tensor on the host (or copies an array to the device) raises inside."""
    def refuse(name: str) -> Any:
        def refused(*args: Any, **kwargs: Any) -> Any:
            raise AssertionError(f"a host read inside an iteration: {name}")
        return refused

    targets = [(th, "as_tensor"), (th, "tensor"), (th, "from_numpy"), *((th.Tensor, name) for name in (
        "item", "cpu", "numpy", "tolist", "__bool__", "__int__", "__float__", "__index__", "__array__"))]
    saved = [(owner, name, getattr(owner, name)) for owner, name in targets]
    for owner, name, _ in saved:
        setattr(owner, name, refuse(name))
    try:
        yield
    finally:
        for owner, name, original in saved:
            setattr(owner, name, original)


class HostNumbers(TorchDispatchMode):
    """Collects the writes of a host number into a tensor (``a[i] = 0.0``: an index_put of a 0-d tensor made from
    the number, which on CUDA is a copy from the host that a graph cannot hold)."""

    def __init__(self) -> None:
        super().__init__()
        self.found: list[str] = []

    def __torch_dispatch__(self, func: Any, types: Any, args: Any = (), kwargs: Any = None) -> Any:
        name = str(func)
        if name.startswith("aten.lift_fresh") or ("index_put" in name and any(
                isinstance(a, th.Tensor) and a.dim() == 0 for a in args[1:])):
            self.found.append(name + "\n" + "".join(traceback.format_stack(limit=6)[:-1]))
        return func(*args, **(kwargs or {}))


def test_the_host_number_detector_sees_a_scalar_written_by_index() -> None:
    """The detector below is real: the spelling that once broke the capture is seen, its replacement is not."""
    a = th.zeros(2, 3, 3, dtype=th.bool)
    with HostNumbers() as seen:
        a[..., th.arange(3), th.arange(3)] = False
    assert seen.found
    with HostNumbers() as seen:
        a.diagonal(dim1=-2, dim2=-1).fill_(False)
    assert seen.found == []


@pytest.mark.parametrize("algo", [None, "ddpg", "ddpg-set", "dqn", "dqn+ddqn", "per", "per-set"])
def test_an_iteration_reads_nothing_from_the_host_and_writes_no_host_number(algo: str | None) -> None:
    """What a CUDA graph needs: each phase's iteration (random actions; acting; acting and updating) runs with
    every host read refused and writes no number from the host into a tensor."""
    loop = loop_of(algo)
    for _ in range(8):  # past learning_starts: the replay holds transitions
        loop.iterate()
    for phase in PHASES:
        with no_host_reads(), HostNumbers() as seen:
            loop._iteration(*phase)
        assert seen.found == [], seen.found[0]


def tensors_of(obj: Any, path: str = "", depth: int = 2) -> dict[str, int]:
    """``id`` of every tensor an object holds (its attributes, their dicts, lists and tuples, and the attributes of
    the project's objects it holds, ``depth`` levels down), by attribute path."""
    found: dict[str, int] = {}

    def visit(value: Any, where: str, level: int) -> None:
        if isinstance(value, th.Tensor):
            found[where] = id(value)
        elif isinstance(value, dict):
            for key, item in value.items():
                visit(item, f"{where}[{key!r}]", level)
        elif isinstance(value, (list, tuple)):
            for i, item in enumerate(value):
                visit(item, f"{where}[{i}]", level)
        elif level > 0 and type(value).__module__.startswith("lanefree_sumo") and hasattr(value, "__dict__"):
            for name, item in vars(value).items():
                if name != "losses":  # the last update's outputs, read after it (a graph's outputs on a GPU)
                    visit(item, f"{where}.{name}", level - 1)

    visit(obj, path, depth + 1)
    return found


def test_the_state_is_copied_back_into_the_same_buffers() -> None:
    """A graph replays on the buffers it captured: after iterations and a reset every tensor the env and the
    learner hold (the world, the books, the replay, the weights, Adam, the counts) is the same tensor object as
    before — a step that replaced one the loop does not copy back would show here — and pinning changes no number
    (a loop whose state moves freely from step to step gives the same books and weights)."""
    pinned, free = loop_of("ddpg", seed=3), loop_of("ddpg", seed=3)
    for _ in range(8):  # past learning_starts: every tensor of an update exists
        pinned.iterate()
        free.iterate()
    held = {**tensors_of(pinned.env, "env"), **tensors_of(pinned.learner, "learner"), "obs": id(pinned.obs)}
    assert any(".world." in k for k in held) and any("replay" in k for k in held) and any("_count" in k for k in held)
    free._pin = lambda: None  # type: ignore[method-assign]
    for _ in range(6):
        pinned.iterate()
        free.iterate()
    pinned.start(pinned.env.reset([1]))
    free.obs = free.env.reset([1])
    for _ in range(5):
        pinned.iterate()
        free.iterate()
    assert {**tensors_of(pinned.env, "env"), **tensors_of(pinned.learner, "learner"), "obs": id(pinned.obs)} == held
    for name in pinned.env.state.books:
        assert th.equal(pinned.env.state.books[name], free.env.state.books[name]), name
    assert th.equal(pinned.obs, free.obs)
    assert th.equal(pinned.learner.actor.flat, free.learner.actor.flat)


@pytest.mark.parametrize("per_run_limits", [False, True])
def test_the_compiled_ring_step_traces_as_one_graph_and_equals_the_eager_one(per_run_limits: bool) -> None:
    """What a GPU compiles, traced on the CPU without fusing (``aot_eager``): the ring's step is one graph
    (``fullgraph``: a graph break would raise) and gives the eager loop's world, observations and books bit for
    bit (runs of two densities, so padded rows too; and with each run its own top speed and lateral bound)."""
    import torch._dynamo

    torch._dynamo.reset()
    traced = loop_of(None, seed=5, compile="aot_eager", per_run_limits=per_run_limits)
    eager = loop_of(None, seed=5, per_run_limits=per_run_limits)
    assert isinstance(eager.env.params.agent_max_speed_mps, th.Tensor) == per_run_limits
    assert traced.compiled == "aot_eager" and eager.compiled is None
    for _ in range(20):
        traced.iterate()
        eager.iterate()
    assert th.equal(traced.obs, eager.obs)
    for name in ("x", "y", "vx", "vy", "overlap", "dx"):
        assert th.equal(getattr(traced.env.world, name), getattr(eager.env.world, name)), name
    for name in eager.env.state.books:
        assert th.equal(traced.env.state.books[name], eager.env.state.books[name]), name


def test_a_compiler_that_fails_leaves_the_loop_uncompiled_with_a_warning() -> None:
    """A machine whose compiler tool chain fails (no C compiler for Triton, say): one warning naming the failure,
    and the loop runs as written, with the uncompiled loop's numbers."""
    import torch._dynamo
    from torch._dynamo import register_backend

    @register_backend(name="lanefree_failing_test_backend")  # type: ignore[misc]
    def failing(gm: Any, example_inputs: Any) -> Any:
        raise RuntimeError("no C compiler found")

    torch._dynamo.reset()
    broken, plain = loop_of("dqn", seed=2, compile="lanefree_failing_test_backend"), loop_of("dqn", seed=2)
    with pytest.warns(RuntimeWarning, match="runs uncompiled: .*no C compiler found") as caught:
        for _ in range(8):
            broken.iterate()
            plain.iterate()
    assert len(caught) == 1 and broken.compiled is None
    assert th.equal(broken.obs, plain.obs) and th.equal(broken.learner.q_net.stack.flat, plain.learner.q_net.stack.flat)


@pytest.mark.parametrize("algo", ["ddpg", "ddpg-set", "dqn", "dqn+ddqn", "per", "dueling-set"])
def test_the_compiled_update_traces_as_one_graph_and_moves_the_weights_as_the_eager_one(algo: str) -> None:
    """The gradient step traced as one graph (``aot_eager``) moves the weights, the targets and Adam's moments as
    the eager step does, to float32 rounding (the traced graph runs the in-place updates in functional form: the
    last bits may differ; the step counts on the device must not)."""
    import torch._dynamo

    torch._dynamo.reset()
    traced, eager = loop_of(algo, seed=5, compile="aot_eager"), loop_of(algo, seed=5)
    for _ in range(6):  # learning_starts 6: the same random steps, then the first update
        traced.iterate()
        eager.iterate()
    assert th.equal(traced.obs, eager.obs)
    before = [adam.params.flat.clone() for adam in eager.learner.optimisers()]
    for _ in range(4):
        traced.iterate()
        eager.iterate()
    assert traced.learner.n_updates == eager.learner.n_updates == 4
    ddpg = algo.startswith("ddpg")
    nets = ("actor", "critic", "actor_target", "critic_target") if ddpg else ("q_net", "q_net_target")
    for name in nets:
        a, b = getattr(traced.learner, name), getattr(eager.learner, name)
        a, b = (a if ddpg else a.stack).flat, (b if ddpg else b.stack).flat
        # to float32 rounding on the weights' own scale (max |w| ≈ 1: a few ulps), 100× below what the updates move
        # them by (asserted below); the set encoder's reordered sums: 4.4e-7 measured for dueling-set on an AMD EPYC
        assert th.allclose(a, b, rtol=1e-5, atol=1e-6 * float(b.abs().max())), name
    if algo.startswith("per"):  # the priorities the traced step wrote back
        assert th.allclose(traced.learner._leaves, eager.learner._leaves, rtol=1e-5)
        assert ((eager.learner._leaves > 0) & (eager.learner._leaves != 1.0)).any()  # the updates moved some
    for mine, theirs in zip(traced.learner.optimisers(), eager.learner.optimisers(), strict=True):
        assert th.equal(mine.count, theirs.count) and float(mine.count) == 4.0
        # to float32 rounding on the moment's own scale: the set encoder's pooled sums, reordered by the trace,
        # leave the small entries ~1e-6 of the largest apart (measured on an Intel Xeon; 1e-9 held on AMD EPYC)
        scale = float(theirs.exp_avg.abs().max())
        assert th.allclose(mine.exp_avg, theirs.exp_avg, rtol=1e-5, atol=1e-5 * scale)
    for adam, old in zip(eager.learner.optimisers(), before, strict=True):  # the updates moved the weights
        assert (adam.params.flat - old).abs().max() > 1e-4


@pytest.mark.parametrize("algo", ["ddpg", "dqn"])
def test_a_device_stream_update_equals_the_exact_update_on_the_same_minibatch(algo: str) -> None:
    """Given the same replay and the same minibatch positions, the update with the step count on the device
    (Adam's bias corrections in float64 there) moves the weights as the exact update does, to float32 rounding."""
    cfgs = configs(algo)
    exact = build_batched(cfgs, [0, 1], observation_space(cfgs[0]), action_space(cfgs[0]), device="cpu")
    streams = build_batched(cfgs, [0, 1], observation_space(cfgs[0]), action_space(cfgs[0]), device="cpu")
    streams.use_device_streams(th.Generator().manual_seed(0))
    rng = np.random.default_rng(1)
    for _ in range(20):
        obs, next_obs = rng.normal(size=(2, 24)).astype(np.float32), rng.normal(size=(2, 24)).astype(np.float32)
        action = rng.uniform(-1, 1, (2, 2)).astype(np.float32) if algo == "ddpg" else rng.integers(0, 9, (2, 1))
        reward = rng.normal(size=2)
        for learner in (exact, streams):
            learner.replay.add(obs, next_obs, action, reward, np.zeros(2, bool), np.zeros(2, bool))
    nets = ("actor", "critic") if algo == "ddpg" else ("q_net",)
    for step in range(5):
        indices = rng.integers(0, 20, (2, 64))
        exact._learn(indices)
        streams._learn(th.as_tensor(indices))
        for adam in streams.optimisers():
            adam.steps += 1
        for name in nets:
            a, b = getattr(exact, name), getattr(streams, name)
            a, b = (a.stack if algo != "ddpg" else a).flat, (b.stack if algo != "ddpg" else b).flat
            assert th.allclose(a, b, rtol=1e-5, atol=1e-7), (name, step)
    assert [adam.steps for adam in exact.optimisers()] == [adam.steps for adam in streams.optimisers()] == \
        [5] * len(exact.optimisers())


def test_the_device_epsilon_follows_the_schedule() -> None:
    """DQN's ε on the device: SB3's LinearSchedule of the progress, per run; a run acts at random with it."""
    cfgs = configs("dqn")
    learner = build_batched(cfgs, [0, 1], observation_space(cfgs[0]), action_space(cfgs[0]), device="cpu")
    learner.use_device_streams(th.Generator().manual_seed(0))
    obs = th.zeros(2, 24)
    q_greedy = learner.q_values(obs).argmax(dim=1)
    draws = []
    for count in (0, 1, learner.total_timesteps):  # ε = 0 before SB3's first _on_step, ≈ start (1.0), then end
        learner._count.fill_(float(count))
        draws.append(th.stack([learner.act_on_device(obs, False)[0] for _ in range(200)]))
    assert th.equal(draws[0], q_greedy.expand(200, 2))
    assert (draws[1] != q_greedy).float().mean() > 0.8  # ε = 1: 8 in 9 random actions differ from the greedy one
    end = learner.exploration[0].end
    assert (draws[2] != q_greedy).float().mean() < end + 0.05


def test_the_lockstep_loop_refuses_what_it_cannot_run() -> None:
    cfgs = configs("ddpg", episode={"terminate_on_collision": True})
    env = BatchedRingEnv(cfgs, device="torch-cpu")
    with pytest.raises(ConfigError, match="terminate_on_collision"):
        Lockstep(env, None, 0)
    with pytest.raises(ConfigError, match="torch simulation"):
        Lockstep(BatchedRingEnv(configs("ddpg")), None, 0)
    td3 = [training_config(merge_config(c, {"train": {"algo": "td3"}})) for c in configs("ddpg")]
    learner = build_batched(td3, [0, 1], observation_space(td3[0]), action_space(td3[0]), device="cpu")
    with pytest.raises(ConfigError, match="TD3.s target noise is drawn on the host"):
        Lockstep(BatchedRingEnv(td3, device="torch-cpu"), learner, 0)


class Draws:
    """A stand-in for a run's numpy stream that hands out given uniform numbers (RunPriorities.sample's draws)."""

    def __init__(self, values: np.ndarray) -> None:
        self.values = values

    def random_sample(self, n: int) -> np.ndarray:
        assert n == len(self.values)
        return self.values


def test_prioritised_replay_on_the_device_samples_and_updates_as_the_host_trees() -> None:
    """With the same uniform numbers, the device's draw (running sums of the leaves) picks the positions the host's
    sum trees pick, with the same importance weights (β at the same step count); the update on the device writes
    the priorities the host trees get, and the largest so far; a transition stored on the device gets it."""
    cfgs = configs("per")  # replay of 50
    space, actions = observation_space(cfgs[0]), action_space(cfgs[0])
    host = build_batched(cfgs, [0, 1], space, actions, device="cpu")
    device = build_batched(cfgs, [0, 1], space, actions, device="cpu")
    rng = np.random.default_rng(4)
    for _ in range(40):  # 40 of 50 slots stored, with unequal priorities
        row = (rng.normal(size=(2, 24)).astype(np.float32), rng.integers(0, 9, 2), rng.normal(size=2),
               rng.normal(size=(2, 24)).astype(np.float32), np.zeros(2, bool))
        for learner in (host, device):
            learner.store(*row)
    for k, priorities in enumerate(host.priorities):
        positions = rng.choice(40, 25, replace=False)
        priorities.update(positions, rng.exponential(2.0, 25).astype(np.float32))
        device.priorities[k].load_state(priorities.state())
    device.use_device_streams(th.Generator().manual_seed(0))
    assert np.allclose(device._leaves.numpy(), np.stack([p.leaves() for p in host.priorities]), rtol=1e-12)
    uniform = rng.random((2, host.batch_size))
    device._rand = lambda *shape: th.as_tensor(uniform)  # type: ignore[method-assign]
    got_indices, got_weights = device.sample_on_device()
    beta = host.per_beta()
    assert beta > host.per_beta0  # 40 steps in: β has moved, on both sides from the same count
    for k, priorities in enumerate(host.priorities):
        indices, weights = priorities.sample(Draws(uniform[k]), host.batch_size, beta)
        assert np.array_equal(got_indices[k].numpy(), indices)
        assert np.allclose(got_weights[k, :, 0].numpy(), weights, rtol=1e-6)
    assert len(set(got_indices[0].tolist())) < host.batch_size  # the large priorities drawn more than once
    host._learn(got_indices.numpy(), got_weights)
    device._learn(got_indices, got_weights)
    assert th.allclose(device._leaves, th.as_tensor(np.stack([p.leaves() for p in host.priorities])), rtol=1e-5)
    assert np.allclose(device._max_leaf.numpy(), [p.max_priority for p in host.priorities], rtol=1e-5)
    device.store_on_device(th.zeros(2, 24), th.zeros(2, 1, dtype=th.int64), th.zeros(2), th.zeros(2, 24))
    assert th.equal(device._leaves[:, 40], device._max_leaf)


def test_sums_in_torchs_order_agree_with_numpys_to_rounding(monkeypatch: pytest.MonkeyPatch) -> None:
    """A GPU sums rows over vehicles in torch's order (one kernel) instead of numpy's (formed step by step): over 30
    steps the observations and rewards agree with the numpy-order sums to 1e-9."""
    from lanefree_sumo.sim.xp import torch_namespace

    cfgs = configs("ddpg", runs=3)
    exact, fast = BatchedRingEnv(cfgs, device="torch-cpu"), BatchedRingEnv(cfgs, device="torch-cpu")
    exact.reset()
    fast.reset()
    rng = np.random.default_rng(2)
    active = th.ones(3, dtype=th.bool)
    differ = 0
    for _ in range(30):
        actions = th.as_tensor(rng.uniform(-1, 1, (3, 2)))
        obs, reward, _ = exact.step_on_device(actions, active)
        monkeypatch.setattr(torch_namespace("cpu"), "numpy_order_sums", False)
        got_obs, got_reward, _ = fast.step_on_device(actions, active)
        monkeypatch.undo()
        assert th.allclose(got_obs, obs, rtol=1e-6, atol=1e-6) and th.allclose(got_reward, reward, rtol=1e-9)
        differ += int(not th.equal(got_reward, reward))
    assert differ > 0  # the orders do differ in the last bits somewhere: the fast sums ran


def test_dqns_target_is_copied_before_the_update_of_its_step() -> None:
    """SB3's order at a target step: store, _on_step (the target copy), then the update. So after step
    n · target_update_steps the target holds the weights from before that step's update."""
    cfgs = [training_config(merge_config(LaneFreeConfig(), {"seed": k, "train": {"algo": "dqn", "dqn": {
        "learning_starts_steps": 4, "buffer_size": 50, "target_update_steps": 10}}})) for k in range(2)]
    env = BatchedRingEnv(cfgs, device="torch-cpu")
    learner = build_batched(cfgs, [0, 1], observation_space(cfgs[0]), action_space(cfgs[0]), device="cpu")
    loop = Lockstep(env, learner, 0)
    loop.start(env.reset())
    for _ in range(9):
        loop.iterate()
    before = learner.q_net.stack.flat.clone()
    assert not th.equal(learner.q_net_target.stack.flat, before)  # the target: the initial weights still
    loop.iterate()  # step 10
    assert learner.num_timesteps == 10
    assert th.equal(learner.q_net_target.stack.flat, before)
    assert not th.equal(learner.q_net.stack.flat, before)

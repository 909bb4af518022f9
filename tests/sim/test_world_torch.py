"""The world core as torch (float64, CPU here; the same functions on a GPU) against the numpy reference.

With numpy's sqrt, hypot, power and erfc (:func:`~lanefree_sumo.sim.xp.numpy_transcendentals`) every other
operation of a torch step is IEEE arithmetic and gives numpy's bits: the states are compared bit for bit over
hundreds of steps with collisions and the ring's wrap. With torch's own functions (what a GPU run computes) one
step from the same state agrees to a few ulp (these functions may differ in the last bit); over hundreds of steps
two such trajectories part, as the traffic amplifies any difference, so the long comparison is the bitwise one."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from lanefree_sumo.sim.spawn import spawn  # noqa: E402
from lanefree_sumo.sim.world import WorldParams, replace_runs, reset_world, step_world, world_to  # noqa: E402
from lanefree_sumo.sim.xp import namespace  # noqa: E402
from lanefree_sumo.sim.xp_torch import numpy_transcendentals  # noqa: E402
from tests.sim.test_world import RUNS, ring  # noqa: E402

STATE = ("x", "y", "vx", "vy", "edge", "pos", "lat", "dx", "dy", "overlap", "steps")


def _assert_same(world, twin, err: str) -> None:
    for name in STATE:
        np.testing.assert_array_equal(getattr(world, name), getattr(twin, name).numpy(), err_msg=f"{err}: {name}")


def test_torch_world_is_the_numpy_world_bit_for_bit_with_numpys_transcendental_functions():
    cfgs = [ring(seed, density) for seed, density in RUNS]
    params = WorldParams.of(cfgs)
    world = reset_world(cfgs, [seed for seed, _ in RUNS])
    twin = world_to(world, "torch-cpu")
    assert isinstance(twin.x, torch.Tensor) and twin.x.dtype == torch.float64 and namespace(twin.x).is_numpy is False
    rng = np.random.default_rng(5)
    collisions = wraps = 0
    with numpy_transcendentals():
        for step in range(300):
            accel = np.column_stack([rng.uniform(-4.5, 2.0, 3), rng.uniform(-1.8, 1.8, 3)])
            edge = world.edge
            world, out = step_world(world, params, accel)
            twin, twin_out = step_world(twin, params, torch.from_numpy(accel))
            _assert_same(world, twin, f"step {step}")
            for name in ("ax", "ay", "boundary_contact", "new_collisions"):
                np.testing.assert_array_equal(getattr(out, name), getattr(twin_out, name).numpy(), err_msg=name)
            collisions += int(out.new_collisions.sum())
            wraps += int(((edge == 3) & (world.edge == 0) & world.present).sum())
    assert collisions > 0 and wraps > 0  # collisions and the ring's wrap were compared too


def test_torch_step_with_its_own_functions_is_the_numpy_step_to_a_few_ulp():
    cfgs = [ring(seed, density) for seed, density in RUNS]
    params = WorldParams.of(cfgs)
    world = reset_world(cfgs, [seed for seed, _ in RUNS])
    rng = np.random.default_rng(6)
    worst = 0.0
    for _ in range(60):  # each step from the numpy state: the one-step difference, not its amplification
        accel = np.column_stack([rng.uniform(-4.5, 2.0, 3), rng.uniform(-1.8, 1.8, 3)])
        twin, _ = step_world(world_to(world, "torch-cpu"), params, torch.from_numpy(accel))
        world, _ = step_world(world, params, accel)
        for name in ("x", "y", "vx", "vy"):
            got, want = getattr(twin, name).numpy(), getattr(world, name)
            np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12, err_msg=name)
            worst = max(worst, float(np.abs(got - want).max()))
    assert worst < 1e-12


def test_a_run_reset_alone_in_a_torch_world_is_the_numpy_reset():
    cfgs = [ring(seed, density) for seed, density in RUNS]
    params = WorldParams.of(cfgs)
    world = reset_world(cfgs, [seed for seed, _ in RUNS])
    twin = world_to(world, "torch-cpu")
    with numpy_transcendentals():
        for _ in range(5):
            world, _ = step_world(world, params, np.zeros((3, 2)))
            twin, _ = step_world(twin, params, torch.zeros(3, 2, dtype=torch.float64))
        fresh = [spawn(cfgs[1], np.random.default_rng(99))]
        world, twin = replace_runs(world, [1], fresh), replace_runs(twin, [1], fresh)
        _assert_same(world, twin, "reset")
        world, _ = step_world(world, params, np.zeros((3, 2)))
        twin, _ = step_world(twin, params, torch.zeros(3, 2, dtype=torch.float64))
    _assert_same(world, twin, "after the reset")
    assert world_to(twin, "cpu").x.tolist() == world.x.tolist()


def test_train_device_is_one_name_from_the_option_to_the_tensors():
    """``train.device``'s names map to one namespace and one torch device each, and a namespace names itself
    back; what older checkpoints saved in their place (None, a ``torch.device``) reads as the same names."""
    from lanefree_sumo.config.schema import DEVICES
    from lanefree_sumo.sim.xp import NUMPY, array_namespace, device_name, on_cpu, torch_device

    assert DEVICES == ("cpu", "torch-cpu", "cuda")
    assert array_namespace("cpu") is NUMPY and NUMPY.name == "cpu"
    xp = array_namespace("torch-cpu")
    assert not xp.is_numpy and xp.device == torch.device("cpu") and xp.name == "torch-cpu"
    assert array_namespace("torch-cpu") is xp  # cached: one namespace per device
    assert [torch_device(d) for d in DEVICES] == [torch.device("cpu"), torch.device("cpu"), torch.device("cuda")]
    assert [on_cpu(d) for d in DEVICES] == [True, True, False]
    assert [device_name(s) for s in (None, torch.device("cpu"), torch.device("cuda", 1), "torch-cpu", "cpu")] \
        == ["cpu", "torch-cpu", "cuda:1", "torch-cpu", "cpu"]

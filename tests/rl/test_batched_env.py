"""The batched environment: run k is, bit for bit, LaneFree-v0 (numpy) with its config and a training run's seeds."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from lanefree_sumo.errors import ConfigError
from lanefree_sumo.rl.batched_env import BatchedRingEnv
from lanefree_sumo.rl.env import LaneFreeEnv
from lanefree_sumo.rl.models import EpisodeSeeds

# (seed, density, preset): three vehicle counts (padding), presets with and without zones, fields and bonuses
RUNS = [(3, 70.0, "fields_zones_overtake_collision"), (4, 120.0, "collision"), (5, 90.0, "fields_overtake_collision")]
STEPS = 40
TERMS = ("c_x", "c_y", "c_f", "y_d", "v_d_eff", "blocked", "collided", "overtook", "reward", "overtakes",
         "collision_events", "boundary_contact")


def configs(kind: str, observation: str = "vector", *, bonuses: tuple[str, ...] = ("every_pass",) * len(RUNS),
            scenario: dict | None = None, action: dict | None = None, steps: int = STEPS,
            limits: tuple[dict, ...] = ({},) * len(RUNS)) -> list[dict]:
    """The runs' configs: ``bonuses`` each run's reward.overtake_bonus; ``scenario`` and ``action`` keys every
    run's; ``limits`` scenario keys of each run."""
    return [{"seed": seed, "backend": "numpy",
             "scenario": {"density_veh_per_km": density, **(scenario or {}), **own},
             "reward": {"preset": preset, "overtake_bonus": bonus}, "action": {"kind": kind, **(action or {})},
             "observation": {"kind": observation}, "sim": {"episode_steps": steps}}
            for (seed, density, preset), bonus, own in zip(RUNS, bonuses, limits)]


def actions(rng: np.random.Generator, kind: str, step: int = 0, surge: bool = False) -> np.ndarray:
    """Mostly accelerating, so the agents race, overtake and collide; ``surge``: (continuous) 30 steps at full
    throttle, 30 braking at half, so the agents pass, are passed back and pass the same vehicles again."""
    if kind == "discrete":
        return rng.choice([1, 5, 7, 0, 3, 4], size=len(RUNS))
    ax = rng.uniform(-0.3, 1.0, len(RUNS)) if not surge else np.full(len(RUNS), 1.0 if step // 30 % 2 == 0 else -0.5)
    return np.column_stack([ax, rng.uniform(-1.0, 1.0, len(RUNS))]).astype(np.float32)


def assert_same_obs(batched, k: int, single) -> None:
    if isinstance(single, dict):
        for key in single:
            np.testing.assert_array_equal(batched[key][k], single[key])
    else:
        np.testing.assert_array_equal(batched[k], single)


def without_wall(row: dict) -> dict:
    return {key: value for key, value in row.items() if key != "wall_s"}


@pytest.mark.parametrize(("kind", "observation"), [("continuous", "vector"), ("discrete", "vector"),
                                                   ("continuous", "set")])
def test_each_run_is_lanefree_v0_with_a_training_runs_episode_seeds(kind, observation):
    assert_runs_are_lanefree_v0(configs(kind, observation), kind)


PER_RUN_LIMITS = ({"agent_max_speed_mps": 24.0}, {"agent_lateral_speed_ratio": 0.3},
                  {"agent_max_speed_mps": 26.0, "agent_lateral_speed_ratio": 0.1})
"""Each run its own top speed and lateral bound (run 0 none: the default's 30 m/s and no bound)."""

# the open modelling choices: the overtake bonus and the agents' limits per run; the discrete action sizes per batch
SWITCHES = {
    "overtake_bonus": ("continuous", {"bonuses": ("once_per_vehicle", "net_passes", "every_pass"), "steps": 120}),
    "agent_limits": ("continuous", {"scenario": {"agent_max_speed_mps": 24.0, "agent_lateral_speed_ratio": 0.3}}),
    "agent_limits_per_run": ("continuous", {"limits": PER_RUN_LIMITS, "steps": 120}),
    "discrete_sizes": ("discrete", {"action": {"discrete_ax_mps2": 3.0, "discrete_ay_mps2": 0.5}}),
}


@pytest.mark.parametrize("switch", list(SWITCHES))
def test_each_run_is_lanefree_v0_under_the_open_choices(switch):
    kind, options = SWITCHES[switch]
    seen = assert_runs_are_lanefree_v0(configs(kind, **options), kind, surge=switch == "overtake_bonus")
    if switch == "overtake_bonus":  # the ledgers refused some passes their bonus (else nothing was compared)
        assert seen["unpaid"] > 0


def assert_runs_are_lanefree_v0(cfgs: list[dict], kind: str, surge: bool = False) -> dict[str, int]:
    """Two episodes of every run of ``cfgs`` in one batch against LaneFree-v0 alone: the same observations,
    rewards, terms and episode metrics (``surge``: :func:`actions`'); returns what happened (overtakes, collisions,
    steps with passes but without a bonus)."""
    steps = cfgs[0]["sim"]["episode_steps"]
    batch = BatchedRingEnv(cfgs)
    singles = [EpisodeSeeds(LaneFreeEnv(cfg), cfg["seed"], 0, 1) for cfg in cfgs]
    rng = np.random.default_rng(1)
    seen = {"overtakes": 0, "collision_events": 0, "ended": 0, "unpaid": 0}
    for _episode in range(2):
        obs = batch.reset()
        for k, env in enumerate(singles):
            single_obs, info = env.reset()
            assert_same_obs(obs, k, single_obs)
            assert info["episode_seed"] == batch.episode_seeds[k]
        for step in range(steps):
            act = actions(rng, kind, step, surge)
            obs, reward, terminated, truncated, info = batch.step(act)
            for k, env in enumerate(singles):
                single_obs, single_reward, single_term, single_trunc, single_info = env.step(act[k])
                assert_same_obs(obs, k, single_obs)
                assert reward[k] == single_reward
                assert (terminated[k], truncated[k]) == (single_term, single_trunc)
                for term in TERMS:
                    assert info[term][k] == single_info[term], term
                if single_term or single_trunc:
                    assert without_wall(info["episode_metrics"][k]) == without_wall(single_info["episode_metrics"])
                    seen["ended"] += 1
                else:
                    assert info["episode_metrics"][k] is None
                seen["overtakes"] += single_info["overtakes"]
                seen["collision_events"] += single_info["collision_events"]
                seen["unpaid"] += single_info["overtakes"] > 0 and not single_info["overtook"]
    assert seen["ended"] == 2 * len(RUNS)
    assert seen["overtakes"] > 0 and seen["collision_events"] > 0  # the bonuses and penalties were compared too
    return seen


def started(cfgs: list[dict]) -> tuple[BatchedRingEnv, list[EpisodeSeeds]]:
    """The runs of ``cfgs`` as one batch and as LaneFree-v0 each alone (a training run's episode seeds), reset."""
    batch = BatchedRingEnv(cfgs)
    singles = [EpisodeSeeds(LaneFreeEnv(cfg), cfg["seed"], 0, 1) for cfg in cfgs]
    batch.reset()
    for env in singles:
        env.reset()
    return batch, singles


def test_a_run_with_a_nan_action_stops_alone_and_the_others_go_on():
    batch, singles = started(configs("continuous"))
    rng = np.random.default_rng(2)
    for step in range(STEPS):
        act = actions(rng, "continuous")
        if step == 5:
            act[1, 0] = np.nan
        obs, reward, terminated, truncated, info = batch.step(act)
        if step == 5:
            assert list(info["stopped"]) == [1] and "not finite" in info["stopped"][1]
        else:
            assert info["stopped"] == {}
        assert batch.stopped.tolist() == [False, step >= 5, False]
        for k in (0, 2):
            single_obs, single_reward, *_ = singles[k].step(act[k])
            np.testing.assert_array_equal(obs[k], single_obs)
            assert reward[k] == single_reward
        if step >= 5:
            assert reward[1] == 0.0 and not terminated[1] and not truncated[1]
            assert info["episode_metrics"][1] is None
    assert truncated.tolist() == [True, False, True]
    batch.reset([0, 2])
    batch.reset()  # a stopped run is not restarted
    assert batch.episode.tolist() == [3, 1, 3] and batch.stopped[1]
    assert not math.isnan(float(batch.episode_metrics(1)["return"]))


def test_runs_that_cannot_share_a_batch_are_refused():
    base = configs("continuous")[:2]
    only = ("the runs of one batch may differ in seed, density, reward preset, overtake bonus and the agent's top "
            "speed and lateral bound only")
    refused = {
        "a batched environment needs at least one run": [],
        f"run 1 differs from run 0 in sim: {only}": [base[0], {**base[1], "sim": {"episode_steps": 50}}],
        f"run 1 differs from run 0 in action, sim: {only}": [base[0], {**base[1], "action": {"kind": "discrete"},
                                                                       "sim": {"episode_steps": 50}}],
        "run 0: the batched environment has no safety shield; use LaneFree-v0 with shield.enabled":
            [{**base[0], "shield": {"enabled": True}}],
        "run 1: the batched environment runs one agent on the ring (road.kind = ring, scenario.agents = 1); use "
        "LaneFree-v0 for the others": [base[0], {**base[1], "road": {"kind": "onramp"}}],
        "run 0: the batched environment runs one agent on the ring (road.kind = ring, scenario.agents = 1); use "
        "LaneFree-v0 for the others": [{**base[0], "scenario": {"agents": 2}}],
        f"run 1 differs from run 0 in reward: {only}": [base[0], {**base[1], "reward": {"preset": "collision",
                                                                                        "overtake_reward": 0.5}}],
    }
    for message, cfgs in refused.items():
        with pytest.raises(ConfigError) as err:
            BatchedRingEnv(cfgs)
        assert str(err.value) == message
    with pytest.raises(ConfigError, match="acceleration bounds; these differ: agent_bounds"):
        BatchedRingEnv([base[0], {**base[1], "scenario": {"agent_bounds": {"ay_max": 1.0}}}])


def test_a_reset_of_no_run_returns_every_runs_observation_as_it_stands() -> None:
    """``reset([])`` (or of stopped runs only) changes nothing and returns the observation as the last call left it;
    the first reset starts every run; one seed per run reset; the world is padded to the largest run, no more."""
    env = BatchedRingEnv(configs("continuous", "set"))
    with pytest.raises(RuntimeError) as err:
        env.reset([0])
    assert str(err.value) == "the first reset starts every run"
    assert env.episode.tolist() == [0, 0, 0] and env.world is None  # the refused reset changed nothing
    first = env.reset()
    assert env.world.present.shape == (3, max(c.background_vehicles for c in env.cfgs) + 1)
    again = env.reset([])
    assert all(np.array_equal(again[key], first[key]) for key in first)
    rng = np.random.default_rng(7)
    stepped, *_ = env.step(actions(rng, "continuous"))
    assert env.reset([]) is stepped
    restarted = env.reset([1], seeds=[11])
    assert env.episode_seeds[1] == 11 and env.episode.tolist() == [1, 2, 1] and env.steps.tolist() == [1, 0, 1]
    assert env.steps.dtype.kind == "i" and env.episode_seeds.dtype == np.int64
    after = env.reset([])
    assert all(np.array_equal(after[key], restarted[key]) for key in restarted)
    assert not np.array_equal(after["others"][1], stepped["others"][1])
    with pytest.raises(ValueError) as err:
        env.reset([0], seeds=[1, 2])
    assert str(err.value) == "reset: 2 seed(s) for 1 run(s); give one seed per run"


@pytest.mark.parametrize("constants", [("_w", "_once", "_net_passes", "_range", "_ego_scale", "_neighbour_scale"),
                                       ("_w", "_once")])
def test_a_batch_pickled_before_the_learning_problem_had_its_module_continues_as_it_was(constants):
    """A batch checkpoint pickles its env; one of the earlier layout (the problem's arrays and books as private
    attributes of the env, with the reward's ``constants`` as versions of it kept them) unpickles into the same
    env: the same steps follow, bit for bit."""
    import pickle

    cfgs = configs("continuous", bonuses=("every_pass", "once_per_vehicle", "net_passes"))
    env = BatchedRingEnv(cfgs)
    env.reset()
    rng = np.random.default_rng(2)
    for step in range(30):
        env.step(actions(rng, "continuous", step, surge=True))
    old = dict(env.__dict__)
    state = old.pop("state")
    old.pop("problem")
    old["_books"] = {name: value for name, value in state.books.items() if not name.startswith("shield_")}
    old.update({f"_{name}": getattr(state, name) for name in state.ARRAYS})
    old["_terminate"] = old.pop("terminate_on_collision")
    old.pop("_lo")
    old.pop("_seen")
    old.pop("xp")
    old["device"] = None  # the numpy simulation, as that layout named it
    kept = {"_w": env.problem.weights, "_once": env.problem.once, "_net_passes": env.problem.net_passes,
            "_range": 80.0, "_ego_scale": np.ones(3), "_neighbour_scale": np.ones(3)}
    old.update({name: kept[name] for name in constants})
    earlier = BatchedRingEnv.__new__(BatchedRingEnv)
    earlier.__setstate__(pickle.loads(pickle.dumps(old)))
    now = pickle.loads(pickle.dumps(env))
    assert earlier.reset([]).tobytes() == now.reset([]).tobytes()  # the earlier layout kept no last observation
    for step in range(30, 70):
        a = actions(rng, "continuous", step, surge=True)
        (obs_a, r_a, *_), (obs_b, r_b, *_) = earlier.step(a), now.step(a)
        assert obs_a.tobytes() == obs_b.tobytes() and r_a.tobytes() == r_b.tobytes()
    assert all(earlier.state.books[name].tobytes() == now.state.books[name].tobytes() for name in now.state.books)
    assert set(earlier.__dict__) == set(now.__dict__)  # the earlier layout's private names are gone


@pytest.mark.parametrize("kind", ["continuous", "discrete"])
def test_the_device_step_equals_the_host_step(kind: str) -> None:
    """step_on_device with the actions on the device gives step's observations, rewards and books bit for bit
    (a non-finite continuous action: acceleration 0, the run flagged and not scored); count_step counts its steps."""
    import torch as th

    cfgs = configs(kind)
    host, device = BatchedRingEnv(cfgs, device="torch-cpu"), BatchedRingEnv(cfgs, device="torch-cpu")
    host.reset()
    device.reset()
    rng = np.random.default_rng(0)
    active = th.ones(3, dtype=th.bool)
    for step in range(15):
        if kind == "continuous":
            act = rng.uniform(-1.2, 1.2, (3, 2)).astype(np.float32)
            if step == 10:
                act[2, 0] = np.nan
        else:
            act = rng.integers(0, 9, 3).astype(np.float32)  # whole numbers as floats, as a network's argmax may give
        accel, host_bad = host.accelerations(act)
        got_accel, got_bad = device.device_accelerations(th.as_tensor(act))
        assert th.equal(got_accel[:, 0, :], th.as_tensor(accel)) and got_bad.tolist() == host_bad.tolist()
        obs, reward, *_ = host.step(act)
        got_obs, got_reward, bad = device.step_on_device(th.as_tensor(act), active)
        device.count_step()
        active &= ~bad
        assert th.equal(got_obs, obs) and th.equal(got_reward, reward)
        assert bad.tolist() == [False, False, kind == "continuous" and step == 10]
    assert host.stopped.tolist() == [False, False, kind == "continuous"]
    assert device.steps.tolist() == host.steps.tolist() == [15] * 3
    for name in host.state.books:
        assert th.equal(device.state.books[name], host.state.books[name]), name
    with pytest.raises(RuntimeError, match=r"^call reset\(\) before step_on_device\(\)$"):
        BatchedRingEnv(cfgs, device="torch-cpu").step_on_device(th.as_tensor(act), active)


def test_the_torch_simulation_books_and_episode_rows_are_numpys() -> None:
    """On ``torch-cpu`` the episode books come back to the host (:meth:`host_books`) as the numpy simulation's, and
    the episode rows with them; the actions may be a host array, a tensor or a list."""
    import torch as th

    cfgs = configs("continuous")
    on_numpy, on_torch = BatchedRingEnv(cfgs), BatchedRingEnv(cfgs, device="torch-cpu")
    on_numpy.reset()
    on_torch.reset()
    rng = np.random.default_rng(3)
    for step in range(STEPS):
        act = actions(rng, "continuous", step, surge=True)
        given = (act, th.as_tensor(act), act.tolist())[step % 3]
        *_, info_numpy = on_numpy.step(act)
        *_, info_torch = on_torch.step(given)
    books = on_torch.host_books()
    assert set(books) == set(on_numpy.state.books)
    for name, value in on_numpy.state.books.items():
        assert isinstance(books[name], np.ndarray) and books[name].shape == (3,)
        np.testing.assert_allclose(books[name], value, rtol=1e-12, atol=1e-12, err_msg=name)
    for k in range(3):
        row_numpy, row_torch = info_numpy["episode_metrics"][k], info_torch["episode_metrics"][k]
        assert row_numpy is not None and row_torch is not None
        assert row_torch.keys() == row_numpy.keys()
        for key, value in without_wall(row_numpy).items():
            close = value if isinstance(value, str) else pytest.approx(value, rel=1e-12, abs=1e-12)
            assert row_torch[key] == close, key
    assert on_numpy.state.books["collisions"].sum() > 0  # the books counted something


def test_a_batch_on_torch_pickles_and_continues_on_torch() -> None:
    import pickle

    env = BatchedRingEnv(configs("continuous"), device="torch-cpu")
    env.reset()
    again = pickle.loads(pickle.dumps(env))
    assert again.device == "torch-cpu" and not again.xp.is_numpy
    rng = np.random.default_rng(4)
    act = actions(rng, "continuous")
    (obs_a, r_a, *_), (obs_b, r_b, *_) = env.step(act), again.step(act)
    assert obs_a.equal(obs_b) and r_a.equal(r_b)


def test_an_episode_ends_at_a_collision_where_the_config_says_so() -> None:
    """``episode.terminate_on_collision``: each run's episode ends at its agent's first collision, as LaneFree-v0's;
    the ended runs restart alone while the others go on."""
    cfgs = configs("continuous", steps=150)
    for cfg in cfgs:
        cfg["episode"] = {"terminate_on_collision": True}
    batch, singles = started(cfgs)
    rng = np.random.default_rng(5)
    terminations = 0
    for _ in range(300):
        act = np.column_stack([np.ones(3), rng.uniform(-1.0, 1.0, 3)]).astype(np.float32)
        obs, reward, terminated, truncated, info = batch.step(act)
        ended = []
        for k, env in enumerate(singles):
            single_obs, single_reward, single_term, single_trunc, single_info = env.step(act[k])
            assert (terminated[k], truncated[k]) == (single_term, single_trunc)
            assert reward[k] == single_reward
            if single_term or single_trunc:
                assert without_wall(info["episode_metrics"][k]) == without_wall(single_info["episode_metrics"])
                terminations += single_term
                ended.append(k)
                env.reset()
            else:
                np.testing.assert_array_equal(obs[k], single_obs)
        if ended:
            obs = batch.reset(ended)
            for k in ended:
                assert batch.steps[k] == 0
    assert terminations >= 2  # episodes cut short by a collision were compared


def test_a_stopped_run_books_nothing_more() -> None:
    """After a run's non-finite action its episode books stay as they were while the other runs' go on; the stop's
    reason names the action's step and episode."""
    batch = BatchedRingEnv(configs("continuous"))
    batch.reset()
    rng = np.random.default_rng(6)
    for step in range(STEPS - 1):
        act = actions(rng, "continuous", step, surge=True)
        if step == 4:
            act[0] = [np.nan, 0.5]
        *_, info = batch.step(act)
        if step == 4:
            assert info["stopped"] == {0: f"run 0: action {act[0]!r} at step 5 of episode 1 is not finite; a "
                                          "diverged policy must not drive the car"}
            at_stop = {name: value.copy() for name, value in batch.state.books.items()}
    for name, value in batch.state.books.items():
        assert value[0] == at_stop[name][0], name
    assert batch.state.books["return"][1] != at_stop["return"][1]


def test_the_episode_row_times_the_episode() -> None:
    batch = BatchedRingEnv(configs("continuous", steps=3))
    before = time.perf_counter()
    batch.reset()
    for _ in range(3):
        *_, info = batch.step(np.zeros((3, 2)))
    wall = info["episode_metrics"][0]["wall_s"]
    assert isinstance(wall, float) and 0.0 <= wall <= time.perf_counter() - before


@pytest.mark.parametrize(("kind", "act", "message"), [
    ("continuous", np.zeros((2, 3)), "step: actions of shape (3, 2) expected (one row per run of the batch's 3), got "
                                     "shape (2, 3)"),
    ("discrete", np.zeros((3, 2)), "step: actions of shape (3,) or (3, 1) expected (one row per run of the batch's "
                                   "3), got shape (3, 2)"),
    ("discrete", np.array([0, 9, 1]), "a discrete action is one whole number 0 … 8 per run, got array([0, 9, 1])"),
    ("discrete", np.array([0, -1, 1]), "a discrete action is one whole number 0 … 8 per run, got array([ 0, -1,  1])"),
    ("discrete", np.array([0, 1.5, 1]), "a discrete action is one whole number 0 … 8 per run, got "
                                        "array([0. , 1.5, 1. ])"),
])
def test_a_bad_action_is_one_clear_error(kind: str, act: np.ndarray, message: str) -> None:
    env = BatchedRingEnv(configs(kind))
    with pytest.raises(RuntimeError, match=r"^call reset\(\) before step\(\)$"):
        env.step(act)
    env.reset()
    with pytest.raises(ValueError) as err:
        env.step(act)
    assert str(err.value) == message
    assert env.steps.tolist() == [0, 0, 0]


@pytest.mark.parametrize("kind", ["continuous", "discrete"])
def test_a_non_finite_action_accelerates_nothing_and_is_flagged(kind: str) -> None:
    """(specification §6) a NaN or infinite action: acceleration (0, 0), flagged, the run stopped at that step; the
    others' accelerations as given (discrete: a column of indices is taken too)."""
    env = BatchedRingEnv(configs(kind))
    env.reset()
    if kind == "continuous":
        act = np.array([[np.nan, 0.5], [0.5, -1.0], [np.inf, 0.0]])
        want = [[0.0, 0.0], [0.5 * env.cfg.scenario.agent_bounds.ax_max, -env.cfg.scenario.agent_bounds.ay_max],
                [0.0, 0.0]]
    else:
        act = np.array([[np.nan], [5.0], [np.inf]])
        want = [[0.0, 0.0], [env.cfg.action.discrete_ax_mps2, env.cfg.action.discrete_ay_mps2], [0.0, 0.0]]
    accel, bad = env.accelerations(act)
    np.testing.assert_array_equal(accel, want)
    assert bad.tolist() == [True, False, True]
    *_, info = env.step(act)
    assert sorted(info["stopped"]) == [0, 2] and env.stopped.tolist() == [True, False, True]
    np.testing.assert_array_equal(np.column_stack([info["ax"], info["ay"]]), want)

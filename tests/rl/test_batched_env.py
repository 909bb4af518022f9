"""The batched environment: run k is, bit for bit, LaneFree-v0 (numpy) with its config and a training run's seeds."""

from __future__ import annotations

import math

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


def test_a_run_with_a_nan_action_stops_alone_and_the_others_go_on():
    cfgs = configs("continuous")
    batch = BatchedRingEnv(cfgs)
    singles = [EpisodeSeeds(LaneFreeEnv(cfg), cfg["seed"], 0, 1) for cfg in cfgs]
    batch.reset()
    for env in singles:
        env.reset()
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
    with pytest.raises(ConfigError, match="run 1 differs from run 0 in sim"):
        BatchedRingEnv([base[0], {**base[1], "sim": {"episode_steps": 50}}])
    with pytest.raises(ConfigError, match="action"):
        BatchedRingEnv([base[0], {**base[1], "action": {"kind": "discrete"}}])
    with pytest.raises(ConfigError, match="shield"):
        BatchedRingEnv([{**base[0], "shield": {"enabled": True}}])
    with pytest.raises(ConfigError, match="ring"):
        BatchedRingEnv([{**base[0], "road": {"kind": "onramp"}}])
    with pytest.raises(ConfigError, match="run 1 differs from run 0 in reward"):
        BatchedRingEnv([base[0], {**base[1], "reward": {"preset": "collision", "overtake_reward": 0.5}}])
    with pytest.raises(ConfigError, match="acceleration bounds; these differ: agent_bounds"):
        BatchedRingEnv([base[0], {**base[1], "scenario": {"agent_bounds": {"ay_max": 1.0}}}])


def test_a_batch_pickled_before_the_learning_problem_had_its_module_continues_as_it_was():
    """A batch checkpoint pickles its env; one of the earlier layout (the problem's arrays and books as private
    attributes of the env) unpickles into the same env: the same steps follow, bit for bit."""
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
    old.pop("xp")
    old["device"] = None  # the numpy simulation, as that layout named it
    old.update(_w=env.problem.weights, _once=env.problem.once, _net_passes=env.problem.net_passes, _range=80.0)
    earlier = BatchedRingEnv.__new__(BatchedRingEnv)
    earlier.__setstate__(pickle.loads(pickle.dumps(old)))
    now = pickle.loads(pickle.dumps(env))
    for step in range(30, 70):
        a = actions(rng, "continuous", step, surge=True)
        (obs_a, r_a, *_), (obs_b, r_b, *_) = earlier.step(a), now.step(a)
        assert obs_a.tobytes() == obs_b.tobytes() and r_a.tobytes() == r_b.tobytes()
    assert all(earlier.state.books[name].tobytes() == now.state.books[name].tobytes() for name in now.state.books)

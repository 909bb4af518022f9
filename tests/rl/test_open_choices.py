"""The open modelling choices as config switches (the interpretation page lists each with the paper's words):
which passes earn the overtake bonus, the agent's lateral speed bound, the DQN's TD loss and gradient clip,
DDPG's warm-up actions, the ``kerasrl`` learner profile, and the episode metrics that read each run
(both speed-deviation readings, the return decomposition)."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import pytest
import torch as th

from lanefree_sumo.config import AccelerationBounds, ConfigError, LaneFreeConfig, merge_config
from lanefree_sumo.config.schema import LEARNER_PROFILES
from lanefree_sumo.rl.env import LaneFreeEnv, resolve_config
from lanefree_sumo.rl.problem import Problem, ProblemState
from lanefree_sumo.rl.rewards import pass_events
from lanefree_sumo.sim.simulation import clip_acceleration
from lanefree_sumo.sim.xp import NUMPY


def test_pass_events_tell_passes_from_being_passed() -> None:
    """Rows: passed (+1 → −1), passed by (−1 → +2), still ahead, a seam jump (never a pass), out of range."""
    prev = np.array([1.0, -1.0, 5.0, 240.0, 90.0])
    now = np.array([-1.0, 2.0, 4.0, -245.0, -85.0])
    passed, passed_by = pass_events(prev, now, 80.0, 500.0)
    assert passed.tolist() == [True, False, False, False, False]
    assert passed_by.tolist() == [False, True, False, False, False]
    # exactly 0 after the step is a pass; exactly 0 before it is not one (dx ≤ 0 is behind)
    passed, passed_by = pass_events(np.array([0.5, 0.0]), np.array([0.0, -0.5]), 80.0, 500.0)
    assert passed.tolist() == [True, False] and passed_by.tolist() == [False, False]


@pytest.mark.parametrize(("mode", "earned"), [
    ("every_pass", [2, 0, 2, 1]),        # every pass pays, the re-pass and the next lap too
    ("once_per_vehicle", [2, 0, 0, 0]),  # a and b once each
    ("net_passes", [2, 0, 1, 0]),        # a's re-pass after being passed back: no; b lapped again: yes
])
def test_the_pass_book_pays_the_passes_each_mode_counts(mode: str, earned: list[int]) -> None:
    """Rows a, b, c of one run; each step: (the rows the agent passed, the rows that passed it)."""
    cfg = resolve_config({"reward": {"overtake_bonus": mode}})
    problem, state = Problem([cfg], NUMPY), ProblemState.empty(NUMPY, 1, 3)
    a, b, c = 0, 1, 2
    steps = [([a, b], []),   # passes a and b in one step
             ([], [a]),      # a passes the agent back ...
             ([a, b], []),   # ... the agent passes it again (no pay but every_pass), and b a lap later
             ([c], []) if mode == "every_pass" else ([], [])]

    def rows(which: list[int]) -> np.ndarray:
        mask = np.zeros((1, 3), dtype=bool)
        mask[0, which] = True
        return mask

    got = [int(problem.earned(state, rows(passed), rows(by))[0]) for passed, by in steps]
    assert got == earned
    with pytest.raises(ValueError, match="unknown overtake bonus mode 'twice'"):
        Problem([dataclasses.replace(cfg, reward=dataclasses.replace(cfg.reward, overtake_bonus="twice"))], NUMPY)


def test_the_agent_lateral_speed_bound_clips_ay_both_ways() -> None:
    """|vy + ay·T| ≤ r·vx: vx 10 m/s, r 0.05 → |vy| ≤ 0.5 m/s; T = 0.25 s."""
    bounds = AccelerationBounds()
    # vy 0.4 to the left, asking +1.8: at most (0.5 − 0.4)/0.25 = 0.4 m/s²
    assert clip_acceleration(0.0, 1.8, bounds, 10.0, 30.0, 0.25, 0.4, 0.05)[1] == pytest.approx(0.4)
    # vy −0.4, asking −1.8: at least −(0.5 − 0.4)/0.25 = −0.4
    assert clip_acceleration(0.0, -1.8, bounds, 10.0, 30.0, 0.25, -0.4, 0.05)[1] == pytest.approx(-0.4)
    # vy 0.8 (above the bound): the bound asks −1.2, within the hard bounds
    assert clip_acceleration(0.0, 0.0, bounds, 10.0, 30.0, 0.25, 0.8, 0.05)[1] == pytest.approx(-1.2)
    # far above: the hard bound −1.8 wins again
    assert clip_acceleration(0.0, 0.0, bounds, 10.0, 30.0, 0.25, 3.0, 0.05)[1] == pytest.approx(-1.8)
    # no bound (the default): only the hard bounds
    assert clip_acceleration(0.0, 1.8, bounds, 10.0, 30.0, 0.25, 0.4)[1] == 1.8


def _full_throttle(overrides: dict[str, Any], steps: int = 400) -> dict[str, Any]:
    """An episode of ``steps`` steps at full throttle, straight (numpy backend), its metrics."""
    cfg = merge_config(LaneFreeConfig(), {"backend": "numpy", "sim": {"episode_steps": steps}, **overrides})
    env = LaneFreeEnv(cfg)
    env.reset(seed=3)
    info: dict[str, Any] = {}
    done = False
    while not done:
        _, _, terminated, truncated, info = env.step(np.array([1.0, 0.0], dtype=np.float32))
        done = terminated or truncated
    env.close()
    return info["episode_metrics"]


def test_the_bonus_modes_on_a_lapping_agent_and_the_return_decomposition() -> None:
    """At the 30 m/s cap for 100 s the agent passes cars again on a later lap: every pass pays more than
    once per vehicle; the net mode pays at least what once per vehicle does. The return splits exactly into
    the reciprocal term, the bonus and the collision penalty, and the bonus is r_o per paying step."""
    every = _full_throttle({})
    once = _full_throttle({"reward": {"overtake_bonus": "once_per_vehicle"}})
    net = _full_throttle({"reward": {"overtake_bonus": "net_passes"}})
    assert every["overtakes"] == once["overtakes"] == net["overtakes"] > 40  # the same driving: passes counted alike
    assert every["return_bonus"] >= net["return_bonus"] >= once["return_bonus"] > 0
    assert every["return_bonus"] > once["return_bonus"]
    assert once["return_bonus"] / 2.0 <= 36  # at most one paying step per background vehicle (35) + rounding
    for m in (every, once, net):
        assert m["return_reciprocal"] + m["return_bonus"] + m["return_collision"] == pytest.approx(m["return"])
        assert m["return_bonus"] % 2.0 == 0 and m["return_collision"] % 2.5 == 0
        assert m["speed_error_mps"] == pytest.approx(m["mean_speed_mps"] - 20.0)
        assert m["speed_dev_episode_mps"] == pytest.approx(abs(m["mean_speed_mps"] - 20.0))
        assert m["speed_dev_mps"] >= m["speed_dev_episode_mps"]


def test_the_lateral_bound_holds_in_the_env() -> None:
    cfg = merge_config(LaneFreeConfig(), {"backend": "numpy", "scenario": {"agent_lateral_speed_ratio": 0.02}})
    env = LaneFreeEnv(cfg)
    env.reset(seed=1)
    for _ in range(60):
        env.step(np.array([0.0, 1.0], dtype=np.float32))
        state = env.sim.current()[0]
        a = env._agent
        assert abs(state.vy[a]) <= 0.02 * state.vx[a] + 1e-9 or state.vy[a] == 0.0
    env.close()


def test_the_kerasrl_profile_sets_its_keys_and_keys_beside_it_win() -> None:
    cfg = merge_config(LaneFreeConfig(), {"train": {"profile": "kerasrl"}})
    assert (cfg.train.dqn.loss, cfg.train.dqn.max_grad_norm, cfg.train.dqn.learning_starts_steps) == \
        ("squared", None, 1000)
    assert (cfg.train.actor_critic.warmup_actions, cfg.train.actor_critic.learning_starts_steps) == ("policy", 1000)
    assert cfg.train.dqn.gamma == LaneFreeConfig().train.dqn.gamma  # the paper's values are not a profile's
    mixed = merge_config(LaneFreeConfig(), {"train": {"profile": "kerasrl", "dqn": {"max_grad_norm": 5.0}}})
    assert mixed.train.dqn.max_grad_norm == 5.0 and mixed.train.dqn.loss == "squared"
    back = merge_config(cfg, {"train": {"profile": "sb3"}})
    assert back.train == LaneFreeConfig().train
    assert set(LEARNER_PROFILES) == {"sb3", "kerasrl"}
    with pytest.raises(ConfigError, match="train.profile"):
        merge_config(LaneFreeConfig(), {"train": {"profile": "keras"}})
    with pytest.raises(ConfigError, match=r"max_grad_norm.*\(or null\)"):
        merge_config(LaneFreeConfig(), {"train": {"dqn": {"max_grad_norm": "ten"}}})


def _drive(cfg: LaneFreeConfig, steps: int) -> tuple[Any, np.ndarray]:
    """The batched learner of one run of ``cfg`` after ``steps`` steps of the one trainer's cycle (act, env step,
    store, update) on LaneFree-v0; its actions, ``[steps, 2]``."""
    from lanefree_sumo.rl.env import action_space, observation_space
    from lanefree_sumo.rl.env_batch import SlotBatch
    from lanefree_sumo.rl.models import build_batched

    env = SlotBatch([cfg])
    learner = build_batched([cfg], [cfg.seed], observation_space(cfg), action_space(cfg))
    obs, actions = env.reset(), []
    try:
        for _ in range(steps):
            action = learner.act(obs, explore=True)
            new_obs, reward, terminated, truncated, _ = env.step(action)
            learner.store(obs, action, reward, new_obs, terminated | truncated, truncated & ~terminated)
            learner.update()
            actions.append(action[0])
            obs = env.reset([0]) if (terminated | truncated).any() else new_obs
    finally:
        env.close()
    return learner, np.array(actions)


@pytest.mark.usefixtures("one_torch_thread")
@pytest.mark.parametrize("algo", ["dqn", "per"])
def test_the_squared_loss_is_half_the_squared_error_and_another_update_than_huber(algo: str) -> None:
    """Keras-RL's ½·δ² with no clip: the loss of errors (1, 3) is ½·mean(1, 9) = 2.5 where Huber's is
    mean(0.5, 2.5) = 1.5 (with PER's weights (1, 2): mean(0.5, 9) and mean(0.5, 5)), each with its gradient
    (δ/n, and Huber's δ clipped at ±1, over n = 2), and training with it is another update than with Huber (the
    toy's TD errors exceed 1)."""
    from gymnasium import spaces

    from lanefree_sumo.rl.algorithms.batched import BatchedDQN

    obs_space, act_space = spaces.Box(-np.inf, np.inf, (24,), np.float32), spaces.Discrete(9)

    def learner(loss: str, batch: int) -> BatchedDQN:
        return BatchedDQN(algo, obs_space, act_space, [0], loss=loss, max_grad_norm=math.inf, batch_size=batch,
                          buffer_size=500, learning_starts=50, total_timesteps=500)

    squared, huber = learner("squared", 2), learner("huber", 2)
    current, target, weights = th.tensor([[[0.0], [3.0]]]), th.tensor([[[1.0], [0.0]]]), th.tensor([[[1.0], [2.0]]])
    for model, w, value, grad in ((squared, None, 2.5, [-0.5, 1.5]), (huber, None, 1.5, [-0.5, 0.5]),
                                  (squared, weights, 4.75, [-0.5, 3.0]), (huber, weights, 2.75, [-0.5, 1.0])):
        loss, d_current = model._loss(current, target, w)
        assert loss.item() == value and d_current.reshape(-1).tolist() == grad
    rng = np.random.default_rng(0)
    squared, huber = learner("squared", 16), learner("huber", 16)
    for _ in range(100):
        step = (rng.normal(size=(1, 24)).astype(np.float32), rng.integers(0, 9, 1),
                (5 * rng.normal(size=1)).astype(np.float32), rng.normal(size=(1, 24)).astype(np.float32),
                np.array([False]), np.array([False]))
        for model in (squared, huber):
            model.store(*step)
            model.update()
    assert squared.n_updates == huber.n_updates == 50
    assert not th.equal(squared.q_net.stack.flat, huber.q_net.stack.flat)


def test_ddpg_policy_warmup_acts_with_the_actor_from_the_first_step() -> None:
    """``warmup_actions: policy``: the first actions are the actor's plus noise (the same for two seeds'
    runs with the same actor would differ if uniform); updates still wait for learning_starts."""
    from lanefree_sumo.rl.models import training_config

    cfg = merge_config(LaneFreeConfig(), {"backend": "numpy", "sim": {"episode_steps": 50},
                                          "train": {"episodes": 1, "actor_critic": {"ou_sigma": 0.0}}})
    seen: dict[str, np.ndarray] = {}
    for warmup in ("uniform", "policy"):
        c = training_config(merge_config(cfg, {"train": {"actor_critic": {"warmup_actions": warmup}}}))
        learner, seen[warmup] = _drive(c, 20)
        assert learner.n_updates == 0  # 20 steps < learning_starts (800): no update either way
    # with σ = 0 and no update, the policy warm-up takes the untrained actor's (nearly constant) action
    policy, uniform = seen["policy"], seen["uniform"]
    assert np.ptp(policy, axis=0).max() < 0.2 < np.ptp(uniform, axis=0).max()


@pytest.mark.slow
def test_the_pre_tanh_penalty_holds_the_actor_off_its_bound_and_is_refused_where_it_is_not_built() -> None:
    """``train.actor_critic.pre_tanh_penalty``: λ·mean(u²) in DDPG's actor loss (u before the tanh) keeps the actor's
    pre-tanh output near 0 where λ = 0 lets it grow; TD3 (single or batched) and SB3's own DDPG refuse a λ > 0,
    the batched DDPG takes it per run and its model.zip keeps it."""
    from lanefree_sumo.experiments.runners.batch import check_batchable
    from lanefree_sumo.rl.models import build_batched, build_model, make_vec_env, training_config

    cfg = merge_config(LaneFreeConfig(), {"backend": "numpy", "sim": {"episode_steps": 50}, "train": {
        "episodes": 1, "actor_critic": {"learning_starts_steps": 50, "learning_rate": 1e-2}}})
    pre = {}
    for penalty in (0.0, 1000.0):
        c = training_config(merge_config(cfg, {"train": {"actor_critic": {"pre_tanh_penalty": penalty}}}))
        learner, _ = _drive(c, 250)
        assert learner.n_updates == 200
        model = learner.sb3_model(0)
        assert model.pre_tanh_penalty == penalty
        states = learner.replay.observations[0, :250]
        with th.no_grad():
            u = model.actor.mu[:-1](model.actor.extract_features(states, model.actor.features_extractor))
        pre[penalty] = float(u.abs().median())
    assert pre[1000.0] < 0.05 < pre[0.0]
    for algo in ("td3", "ddpg"):
        c = training_config(merge_config(cfg, {"train": {"algo": algo, "actor_critic": {"pre_tanh_penalty": 0.1}}}))
        with pytest.raises(ConfigError, match="pre_tanh_penalty"):
            build_model(c, make_vec_env(c), 0, None)
    c = training_config(merge_config(cfg, {"train": {"actor_critic": {"pre_tanh_penalty": 0.1}}}))
    env = make_vec_env(c)
    assert build_batched([c, c], [0, 1], env.observation_space, env.action_space).pre_tanh_penalty == [0.1, 0.1]
    with pytest.raises(ConfigError, match="pre_tanh_penalty"):
        check_batchable(training_config(merge_config(c, {"train": {"algo": "td3"}})))

"""Tests for the DQN variants of lanefree_sumo.rl.algorithms (double / dueling / prioritised) and the registry."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3 import DQN
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.type_aliases import ReplayBufferSamples
from torch.nn import functional as F

from lanefree_sumo.rl.algorithms import ALGORITHMS
from lanefree_sumo.rl.algorithms.double_dqn import DoubleDQN
from lanefree_sumo.rl.algorithms.dqn import LaneFreeDQN
from lanefree_sumo.rl.algorithms.dueling import DuelingDoubleDQN
from lanefree_sumo.rl.algorithms.prioritized import (
    PrioritizedDictReplayBuffer,
    PrioritizedDoubleDQN,
    PrioritizedReplayBuffer,
)
from lanefree_sumo.rl.algorithms.q_networks import DuelingDQNPolicy, DuelingQNetwork, MultiInputDuelingDQNPolicy
from lanefree_sumo.rl.algorithms.segment_tree import MinTree, SumTree

ALPHA, EPS = 0.6, 1e-6


pytestmark = pytest.mark.usefixtures("one_torch_thread")


# ---------------------------------------------------------------------------
# Inline toy environments
# ---------------------------------------------------------------------------
class ToyEnv(gym.Env):
    """Box(3) obs, Discrete(3); reward 1 when the action is the argmax of the obs; 20-step episodes."""

    def __init__(self) -> None:
        self.observation_space = spaces.Box(-1.0, 1.0, (3,), np.float32)
        self.action_space = spaces.Discrete(3)
        self._t = 0
        self._obs = np.zeros(3, np.float32)

    def _draw(self) -> np.ndarray:
        self._obs = self.np_random.uniform(-1, 1, 3).astype(np.float32)
        return self._obs

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self._t = 0
        return self._draw(), {}

    def step(self, action):
        reward = float(int(action) == int(np.argmax(self._obs)))
        self._t += 1
        return self._draw(), reward, False, self._t >= 20, {}


class DictToyEnv(ToyEnv):
    """Same task with a Dict observation {"a": Box(3), "b": Box(2)}."""

    def __init__(self) -> None:
        super().__init__()
        self.observation_space = spaces.Dict(
            {"a": spaces.Box(-1.0, 1.0, (3,), np.float32), "b": spaces.Box(-1.0, 1.0, (2,), np.float32)}
        )

    def _wrap(self, x: np.ndarray) -> dict:
        return {"a": x, "b": x[:2].copy()}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, info = super().reset(seed=seed, options=options)
        return self._wrap(obs), info

    def step(self, action):
        obs, r, term, trunc, info = super().step(action)
        return self._wrap(obs), r, term, trunc, info


SMALL = dict(learning_starts=50, buffer_size=1000, batch_size=16, train_freq=1, target_update_interval=50, seed=0)


def _set_linear(layer: th.nn.Linear, weight, bias) -> None:
    with th.no_grad():
        layer.weight.copy_(th.as_tensor(weight, dtype=th.float32))
        layer.bias.copy_(th.as_tensor(bias, dtype=th.float32))


def _add(buf, obs, next_obs, action, reward, done) -> None:
    n = buf.n_envs
    buf.add(
        np.asarray(obs, np.float32).reshape(n, -1),
        np.asarray(next_obs, np.float32).reshape(n, -1),
        np.asarray(action).reshape(n, 1),
        np.asarray(reward, np.float32).reshape(n),
        np.asarray(done, np.float32).reshape(n),
        [{} for _ in range(n)],
    )


def _per_buffer(n: int, n_envs: int = 1, size: int | None = None) -> PrioritizedReplayBuffer:
    """Buffer with ``n`` steps; obs of (pos, env) = [pos, env, 0] so samples can be identified."""
    env = ToyEnv()
    buf = PrioritizedReplayBuffer((size or n) * n_envs, env.observation_space, env.action_space, "cpu", n_envs=n_envs)
    for pos in range(n):
        obs = np.array([[pos, e, 0.0] for e in range(n_envs)])
        _add(buf, obs, obs, np.zeros(n_envs), np.zeros(n_envs), np.zeros(n_envs))
    return buf


def _td_for_priority(p_alpha: float) -> float:
    """|td| such that the stored priority (|td| + eps)^alpha equals ``p_alpha``."""
    return p_alpha ** (1.0 / ALPHA) - EPS


# ---------------------------------------------------------------------------
# Double DQN
# ---------------------------------------------------------------------------
# Linear Q-nets (net_arch=[]): online Q(s') = s', target Q(s') = permutation of s'.
S_NEXT = np.array([0.1, 0.9, 0.3], np.float32)
PERM = np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0]], np.float32)  # Q_t(s') = [s'_2, s'_0, s'_1]
R, GAMMA = 1.0, 0.9


def _hand_set_model(cls):
    model = cls("MlpPolicy", ToyEnv(), learning_starts=0, buffer_size=10, batch_size=4, gamma=GAMMA,
                policy_kwargs=dict(net_arch=[]), seed=0)
    _set_linear(model.q_net.q_net[0], np.eye(3), np.zeros(3))
    _set_linear(model.q_net_target.q_net[0], PERM, np.zeros(3))
    _add(model.replay_buffer, [0.2, -0.4, 0.5], S_NEXT, [2], [R], [0.0])
    return model


def test_double_q_target_is_online_argmax_evaluated_by_target_net():
    model = _hand_set_model(DoubleDQN)
    q_online = S_NEXT  # argmax = 1
    q_target = PERM @ S_NEXT  # [0.3, 0.1, 0.9] -> max at action 2
    assert np.argmax(q_online) != np.argmax(q_target)
    expected_double = R + GAMMA * q_target[np.argmax(q_online)]  # 1.09
    plain_dqn = R + GAMMA * q_target.max()  # 1.81
    data = model.replay_buffer.sample(4)
    target = model._compute_target_q_values(data)
    assert target.shape == (4, 1)
    np.testing.assert_allclose(target.numpy(), expected_double, rtol=1e-6)
    assert not np.allclose(target.numpy(), plain_dqn)


def test_double_q_target_respects_done_and_nstep_discounts():
    model = _hand_set_model(DoubleDQN)
    obs = th.tensor(np.stack([S_NEXT, S_NEXT]))
    data = ReplayBufferSamples(
        observations=obs, actions=th.zeros(2, 1, dtype=th.long), next_observations=obs,
        dones=th.tensor([[1.0], [0.0]]), rewards=th.tensor([[2.0], [2.0]]), discounts=th.tensor([[0.5], [0.25]]),
    )
    target = model._compute_target_q_values(data).numpy().ravel()
    np.testing.assert_allclose(target, [2.0, 2.0 + 0.25 * 0.1], rtol=1e-6)


@pytest.mark.parametrize("cls, expected", [(DoubleDQN, R + GAMMA * 0.1), (DQN, R + GAMMA * 0.9)])
def test_train_step_uses_the_right_target(monkeypatch, cls, expected):
    """Spy on the Huber loss inside ``train``: DoubleDQN regresses on the double-Q target, SB3's DQN does not."""
    model = _hand_set_model(cls)
    model._logger = Logger(None, [])
    seen = []
    real = F.smooth_l1_loss

    def spy(input, target, *args, **kwargs):
        seen.append(target.detach().clone())
        return real(input, target, *args, **kwargs)

    monkeypatch.setattr(th.nn.functional, "smooth_l1_loss", spy)
    model.train(gradient_steps=1, batch_size=4)
    assert len(seen) == 1
    np.testing.assert_allclose(seen[0].numpy(), expected, rtol=1e-6)
    assert model._n_updates == 1


# ---------------------------------------------------------------------------
# Dueling
# ---------------------------------------------------------------------------
def _dueling_policy(net_arch):
    env = ToyEnv()
    return DuelingDQNPolicy(env.observation_space, env.action_space, lambda _: 1e-3, net_arch=net_arch)


def test_dueling_network_structure():
    policy = _dueling_policy([128, 64])
    for net in (policy.q_net, policy.q_net_target):
        assert isinstance(net, DuelingQNetwork)
        trunk = list(net.q_net.trunk)
        linears = [m for m in trunk if isinstance(m, th.nn.Linear)]
        assert [(m.in_features, m.out_features) for m in linears] == [(3, 128), (128, 64)]
        assert isinstance(trunk[-1], th.nn.ReLU)  # trunk ends with an activation, heads are linear
        assert (net.q_net.value_head.in_features, net.q_net.value_head.out_features) == (64, 1)
        assert (net.q_net.advantage_head.in_features, net.q_net.advantage_head.out_features) == (64, 3)
    assert policy.q_net.q_net is not policy.q_net_target.q_net


def test_dueling_q_is_v_plus_centred_advantage():
    net = _dueling_policy([]).q_net  # trunk = identity, so heads act on the raw obs
    wv, bv = np.array([[1.0, -2.0, 0.5]]), np.array([0.3])
    wa, ba = np.array([[1.0, 0.0, 2.0], [0.0, -1.0, 1.0], [3.0, 1.0, 0.0]]), np.array([0.1, -0.2, 0.7])
    _set_linear(net.q_net.value_head, wv, bv)
    _set_linear(net.q_net.advantage_head, wa, ba)
    x = np.array([[0.5, -0.3, 0.8], [-1.0, 0.2, 0.1]], np.float32)
    v = x @ wv.T + bv
    a = x @ wa.T + ba
    expected = v + a - a.mean(axis=1, keepdims=True)
    with th.no_grad():
        q = net(th.tensor(x)).numpy()
        v_net, a_net = net.value_and_advantage(th.tensor(x))
    np.testing.assert_allclose(q, expected, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(v_net.numpy(), v, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(a_net.numpy(), a, rtol=1e-5, atol=1e-6)
    assert not np.allclose(q, v + a)  # the mean really is subtracted

    # Shifting all advantages by a constant leaves Q unchanged; shifting V shifts Q.
    _set_linear(net.q_net.advantage_head, wa, ba + 5.0)
    with th.no_grad():
        np.testing.assert_allclose(net(th.tensor(x)).numpy(), expected, rtol=1e-5, atol=1e-5)
    _set_linear(net.q_net.value_head, wv, bv + 5.0)
    with th.no_grad():
        np.testing.assert_allclose(net(th.tensor(x)).numpy(), expected + 5.0, rtol=1e-5, atol=1e-5)


def test_dqn_with_dueling_policy_trains_and_predicts():
    env = ToyEnv()
    model = DQN(DuelingDQNPolicy, env, policy_kwargs=dict(net_arch=[32, 32]), **SMALL)
    before = {k: v.clone() for k, v in model.policy.q_net.state_dict().items()}
    model.learn(total_timesteps=300)
    after = model.policy.q_net.state_dict()
    assert model._n_updates > 0
    assert not th.equal(before["q_net.value_head.weight"], after["q_net.value_head.weight"])
    assert not th.equal(before["q_net.advantage_head.weight"], after["q_net.advantage_head.weight"])
    obs, _ = env.reset(seed=3)
    action, _ = model.predict(obs, deterministic=True)
    assert env.action_space.contains(int(action))


# ---------------------------------------------------------------------------
# Segment trees
# ---------------------------------------------------------------------------
def test_sum_tree_sums_and_prefix_search():
    tree = SumTree(5)  # not a power of two
    tree.update(np.arange(5), [1.0, 2.0, 3.0, 4.0, 0.0])
    assert tree.total() == pytest.approx(10.0)
    queries = [0.0, 0.999, 1.0, 2.999, 3.0, 5.99, 6.0, 9.99, 10.0]
    np.testing.assert_array_equal(tree.find_prefixsum_idx(queries), [0, 0, 1, 1, 2, 2, 3, 3, 3])
    tree.update(1, 0.0)  # an empty leaf is never returned
    assert tree.total() == pytest.approx(8.0)
    np.testing.assert_array_equal(tree.find_prefixsum_idx([0.5, 1.0, 1.5, 3.9, 4.0]), [0, 2, 2, 2, 3])
    np.testing.assert_allclose(tree.get([0, 1, 2, 3]), [1.0, 0.0, 3.0, 4.0])
    with pytest.raises(IndexError):
        tree.update(5, 1.0)


def test_sum_tree_matches_brute_force_and_min_tree():
    rng = np.random.default_rng(0)
    cap = 37
    tree, mtree = SumTree(cap), MinTree(cap)
    assert mtree.min() == np.inf
    values = np.zeros(cap)
    for _ in range(20):
        idx = rng.integers(0, cap, size=6)
        vals = rng.uniform(0.01, 5.0, size=6)
        tree.update(idx, vals)
        mtree.update(idx, vals)
        for i, v in zip(idx, vals):
            values[i] = v  # last write wins, as in the tree
        assert tree.total() == pytest.approx(values.sum())
        assert mtree.min() == pytest.approx(values[values > 0].min())
    q = rng.uniform(0, values.sum(), size=500)
    expected = np.searchsorted(np.cumsum(values), q, side="right")
    np.testing.assert_array_equal(tree.find_prefixsum_idx(q), expected)


@pytest.mark.parametrize("cls", [SumTree, MinTree])
def test_every_node_is_exactly_its_childrens_combination_after_single_and_batch_updates(cls):
    """The tree's invariant, exactly (so the values are those of recomputing every ancestor from its children):
    after single-leaf updates (a new transition) and batches with repeated indices (a minibatch's priorities)."""
    rng = np.random.default_rng(1)
    cap = 1000
    tree = cls(cap)
    combine = np.add if cls is SumTree else np.minimum
    for step in range(300):
        if step % 3:
            tree.update(int(rng.integers(cap)), float(rng.uniform(0.01, 5.0)))
        else:
            idx = rng.integers(0, cap, size=64)
            idx[:8] = idx[8:16]  # duplicates: the last value wins
            tree.update(idx, rng.uniform(0.01, 5.0, size=64))
        internal = np.arange(1, tree.size)
        children = combine(tree.tree[2 * internal], tree.tree[2 * internal + 1])
        np.testing.assert_array_equal(tree.tree[internal], children)


# ---------------------------------------------------------------------------
# Prioritised replay buffer
# ---------------------------------------------------------------------------
def _frequency(buf, index: int, draws: int = 200, batch: int = 32) -> float:
    hits = 0
    for _ in range(draws):
        buf.sample(batch)
        hits += int(np.sum(buf.last_indices == index))
    return hits / (draws * batch)


def test_sampling_frequency_follows_priorities_and_returns_matching_data():
    np.random.seed(0)
    n, hot = 100, 7
    buf = _per_buffer(n)
    tds = np.full(n, _td_for_priority(1.0))
    tds[hot] = _td_for_priority(100.0)
    buf.update_priorities(np.arange(n), tds)
    data = buf.sample(64)
    # returned rows are the transitions named by last_indices
    np.testing.assert_array_equal(data.observations[:, 0].numpy(), buf.last_indices)
    freq = _frequency(buf, hot)
    assert freq == pytest.approx(100.0 / 199.0, abs=0.03)

    # a uniform ReplayBuffer with the same content would pick it ~1% of the time
    uni = ReplayBuffer(n, buf.observation_space, buf.action_space, "cpu")
    for pos in range(n):
        _add(uni, [pos, 0, 0], [pos, 0, 0], [0], [0], [0])
    hits = sum(int(np.sum(uni.sample(32).observations[:, 0].numpy() == hot)) for _ in range(200))
    assert hits / 6400 < 0.05


def test_update_priorities_changes_subsequent_sampling():
    np.random.seed(1)
    n = 50
    buf = _per_buffer(n)
    assert _frequency(buf, 3, draws=50) == pytest.approx(1 / n, abs=0.02)  # all new -> equal max priority
    tds = np.full(n, _td_for_priority(0.01))
    tds[3] = _td_for_priority(10.0)
    buf.update_priorities(np.arange(n), tds)
    assert _frequency(buf, 3, draws=50) > 0.9
    buf.update_priorities([3, 40], [_td_for_priority(0.01), _td_for_priority(10.0)])
    assert _frequency(buf, 3, draws=50) < 0.02
    assert _frequency(buf, 40, draws=50) > 0.9


def test_importance_weights_exact_formula():
    np.random.seed(2)
    buf = _per_buffer(4)
    td = np.array([0.5, 1.0, 2.0, 4.0])
    buf.update_priorities(np.arange(4), td)
    buf.set_beta(0.7)
    buf.sample(64)
    p = (np.abs(td) + EPS) ** ALPHA
    prob = p / p.sum()
    w = (4 * prob) ** -0.7
    w /= w.max()
    np.testing.assert_allclose(buf.last_weights, w[buf.last_indices], rtol=1e-5)
    assert len(np.unique(buf.last_indices)) > 1 and buf.last_weights.min() < 0.9
    np.testing.assert_allclose(buf.priorities(np.arange(4)), p, rtol=1e-12)
    # beta = 0 -> all weights 1
    buf.set_beta(0.0)
    buf.sample(16)
    np.testing.assert_allclose(buf.last_weights, 1.0)


def test_new_transitions_get_max_priority():
    buf = _per_buffer(5, size=10)
    np.testing.assert_allclose(buf.priorities(np.arange(5)), 1.0)  # initial max priority
    buf.update_priorities([0, 1, 2], [0.1, 50.0, 3.0])
    _add(buf, [9, 0, 0], [9, 0, 0], [0], [0], [0])
    assert buf.priorities(5)[0] == pytest.approx((50.0 + EPS) ** ALPHA)
    buf.update_priorities([1], [0.1])  # max is the largest priority ever seen
    _add(buf, [9, 0, 0], [9, 0, 0], [0], [0], [0])
    assert buf.priorities(6)[0] == pytest.approx((50.0 + EPS) ** ALPHA)
    with pytest.raises(IndexError):
        buf.update_priorities([8], [1.0])  # slot not filled yet


def test_multi_env_index_mapping():
    np.random.seed(3)
    n_envs, steps = 3, 6
    buf = _per_buffer(steps, n_envs=n_envs)
    assert buf.sum_tree.capacity == steps * n_envs and buf.n_stored() == steps * n_envs
    hot = int(buf.flat_index(4, 2))
    tds = np.full(steps * n_envs, _td_for_priority(1e-3))
    tds[hot] = _td_for_priority(10.0)
    buf.update_priorities(np.arange(steps * n_envs), tds)
    data = buf.sample(256)
    obs = data.observations.numpy()
    np.testing.assert_array_equal(obs[:, 0], buf.last_indices // n_envs)  # pos
    np.testing.assert_array_equal(obs[:, 1], buf.last_indices % n_envs)  # env
    assert np.mean((obs[:, 0] == 4) & (obs[:, 1] == 2)) > 0.95
    # a new step writes max priority for every env of that step
    _per_obs = np.array([[9, e, 0] for e in range(n_envs)])
    buf2 = _per_buffer(2, n_envs=n_envs, size=4)
    buf2.update_priorities([0], [8.0])
    _add(buf2, _per_obs, _per_obs, np.zeros(n_envs), np.zeros(n_envs), np.zeros(n_envs))
    np.testing.assert_allclose(buf2.priorities(buf2.flat_index(2, np.arange(n_envs))), (8.0 + EPS) ** ALPHA)


def test_optimize_memory_usage_rejected():
    env = ToyEnv()
    with pytest.raises(ValueError, match="optimize_memory_usage"):
        PrioritizedReplayBuffer(10, env.observation_space, env.action_space, optimize_memory_usage=True,
                                handle_timeout_termination=False)


def test_dict_buffer_samples_dicts_with_priorities():
    np.random.seed(4)
    env = DictToyEnv()
    buf = PrioritizedDictReplayBuffer(10, env.observation_space, env.action_space, "cpu")
    for pos in range(10):
        o = {"a": np.array([[pos, 0, 0]], np.float32), "b": np.array([[pos, 1]], np.float32)}
        buf.add(o, o, np.array([[0]]), np.array([0.0]), np.array([0.0]), [{}])
    tds = np.full(10, _td_for_priority(1e-3))
    tds[6] = _td_for_priority(10.0)
    buf.update_priorities(np.arange(10), tds)
    data = buf.sample(64)
    np.testing.assert_array_equal(data.observations["a"][:, 0].numpy(), buf.last_indices)
    np.testing.assert_array_equal(data.next_observations["b"][:, 0].numpy(), buf.last_indices)
    assert np.mean(buf.last_indices == 6) > 0.9


# ---------------------------------------------------------------------------
# PER algorithm
# ---------------------------------------------------------------------------
def test_weighted_loss_zero_weight_gives_no_gradient():
    model = DoubleDQN("MlpPolicy", ToyEnv(), policy_kwargs=dict(net_arch=[]), seed=0)
    lin = model.q_net.q_net[0]
    obs = th.tensor([[0.5, -0.2, 0.1], [0.9, 0.4, -0.7]])
    target = th.tensor([[3.0], [-2.0]])

    def grads(weights, rows):
        lin.zero_grad()
        q = model.q_net(obs[rows])[:, :1]
        model._compute_loss(q, target[rows], weights).backward()
        return lin.weight.grad.clone(), lin.bias.grad.clone()

    gw, gb = grads(th.tensor([[1.0], [0.0]]), [0, 1])
    ref_w, ref_b = grads(None, [0])  # sample 0 alone, mean over batch of 1
    th.testing.assert_close(gw, 0.5 * ref_w)  # batch of 2 -> mean halves it
    th.testing.assert_close(gb, 0.5 * ref_b)
    full_w, _ = grads(th.tensor([[1.0], [1.0]]), [0, 1])
    assert not th.allclose(full_w, gw)  # the second sample does contribute when weighted
    unweighted_w, _ = grads(None, [0, 1])
    th.testing.assert_close(full_w, unweighted_w)
    # explicit weights scale per sample: [2, 0] == 2 * [1, 0]
    g2, _ = grads(th.tensor([[2.0], [0.0]]), [0, 1])
    th.testing.assert_close(g2, 2 * gw)


def _filled_per_model(**kw):
    model = PrioritizedDoubleDQN("MlpPolicy", ToyEnv(), learning_starts=0, buffer_size=20, batch_size=8,
                                 gamma=GAMMA, policy_kwargs=dict(net_arch=[8]), seed=0, **kw)
    rng = np.random.default_rng(0)
    for _ in range(12):
        _add(model.replay_buffer, rng.uniform(-1, 1, 3), rng.uniform(-1, 1, 3), [rng.integers(3)],
             [rng.uniform(-1, 1)], [float(rng.random() < 0.2)])
    model._logger = Logger(None, [])
    return model


def test_per_train_passes_weights_and_updates_priorities_with_td_errors():
    """The update sets the priorities from the step's TD errors; its loss hook receives the importance weights."""
    np.random.seed(5)
    model = _filled_per_model()
    buf = model.replay_buffer
    buf.update_priorities(np.arange(12), np.linspace(0.1, 3.0, 12))  # non-uniform -> non-trivial weights
    # TD errors of every stored transition under the pre-step networks (double-Q target)
    n = buf.n_stored()
    all_data = buf._gather(np.arange(n), np.zeros(n, dtype=np.int64), None)
    with th.no_grad():
        target = model._compute_target_q_values(all_data)
        q = th.gather(model.q_net(all_data.observations), 1, all_data.actions.long())
    td = (target - q).numpy().ravel()
    prio_before = buf.priorities(np.arange(n)).copy()

    seen = {}
    real = model._compute_loss

    def spy(current, tgt, weights=None):
        seen["weights"] = weights
        return real(current, tgt, weights)

    model._compute_loss = spy
    model.train(gradient_steps=1, batch_size=8)
    idx = buf.last_indices
    assert seen["weights"] is not None
    np.testing.assert_allclose(seen["weights"].numpy().ravel(), buf.last_weights)
    assert seen["weights"].numpy().min() < 1.0
    np.testing.assert_allclose(buf.priorities(idx), (np.abs(td[idx]) + EPS) ** ALPHA, rtol=1e-5)
    untouched = np.setdiff1d(np.arange(n), idx)
    np.testing.assert_array_equal(buf.priorities(untouched), prio_before[untouched])


def test_beta_annealing_schedule_reaches_one():
    env = ToyEnv()
    model = PrioritizedDoubleDQN("MlpPolicy", env, **SMALL)
    assert isinstance(model.replay_buffer, PrioritizedReplayBuffer)
    assert model.replay_buffer.beta == pytest.approx(0.4)
    assert model.per_beta(1.0) == pytest.approx(0.4)
    assert model.per_beta(0.5) == pytest.approx(0.7)
    assert model.per_beta(0.0) == pytest.approx(1.0)

    betas = []

    class Record(BaseCallback):
        def _on_step(self) -> bool:
            betas.append(self.model.replay_buffer.beta)
            return True

    model.learn(total_timesteps=300, callback=Record())
    assert model.replay_buffer.beta == pytest.approx(1.0)
    assert betas[0] == pytest.approx(0.4)
    assert np.all(np.diff(betas) >= -1e-12)
    # linear in time: at callback k (k steps completed) beta = 0.4 + 0.6 * k / 300
    np.testing.assert_allclose(betas[150], 0.4 + 0.6 * 150 / 300, rtol=1e-6)


def test_per_buffer_save_load_keeps_priorities(tmp_path):
    np.random.seed(6)
    model = _filled_per_model()
    buf = model.replay_buffer
    buf.update_priorities(np.arange(12), np.linspace(0.1, 30.0, 12))
    buf.set_beta(0.55)
    path = tmp_path / "buffer.pkl"
    model.save_replay_buffer(path)

    other = PrioritizedDoubleDQN("MlpPolicy", ToyEnv(), buffer_size=20, seed=1)
    other.load_replay_buffer(path)
    loaded = other.replay_buffer
    assert isinstance(loaded, PrioritizedReplayBuffer)
    np.testing.assert_array_equal(loaded.priorities(np.arange(12)), buf.priorities(np.arange(12)))
    assert loaded.sum_tree.total() == pytest.approx(buf.sum_tree.total())
    assert loaded.min_tree.min() == pytest.approx(buf.min_tree.min())
    assert loaded.max_priority == pytest.approx(buf.max_priority)
    assert loaded.n_stored() == 12 and loaded.beta == pytest.approx(0.55)
    loaded.sample(8)
    assert np.all(loaded.last_indices < 12)
    other.learn(total_timesteps=60)  # keeps training with the loaded buffer


def test_per_argument_validation():
    env = ToyEnv()
    with pytest.raises(ValueError, match="n_steps"):
        PrioritizedDoubleDQN("MlpPolicy", env, n_steps=3)
    with pytest.raises(ValueError, match="conflicts"):
        PrioritizedDoubleDQN("MlpPolicy", env, replay_buffer_kwargs={"alpha": 0.9})
    with pytest.raises(TypeError, match="prioritised"):
        PrioritizedDoubleDQN("MlpPolicy", env, replay_buffer_class=ReplayBuffer)
    model = PrioritizedDoubleDQN("MlpPolicy", env, per_alpha=0.7, per_beta0=0.5, buffer_size=100)
    assert model.replay_buffer.alpha == 0.7 and model.replay_buffer.beta0 == 0.5


# ---------------------------------------------------------------------------
# Every class: learn, save, load, predict
# ---------------------------------------------------------------------------
CASES = [
    ("ddqn-box", DoubleDQN, "MlpPolicy", ToyEnv, {}),
    ("ddqn-nstep", DoubleDQN, "MlpPolicy", ToyEnv, {"n_steps": 3}),
    ("dqn-dueling", DQN, DuelingDQNPolicy, ToyEnv, {}),
    ("dqn-dueling-dict", DQN, MultiInputDuelingDQNPolicy, DictToyEnv, {}),
    ("dueling-ddqn-box", DuelingDoubleDQN, "MlpPolicy", ToyEnv, {}),
    ("dueling-ddqn-dict", DuelingDoubleDQN, "MultiInputPolicy", DictToyEnv, {}),
    ("per-ddqn-box", PrioritizedDoubleDQN, "MlpPolicy", ToyEnv, {}),
    ("per-ddqn-dict-dueling", PrioritizedDoubleDQN, MultiInputDuelingDQNPolicy, DictToyEnv, {}),
]


# SB3 itself warns when re-loading any DQN saved with n_steps > 1 (the resolved NStepReplayBuffer is stored)
@pytest.mark.filterwarnings("ignore:`n_steps=3` is ignored")
@pytest.mark.parametrize("name, cls, policy, env_cls, extra", CASES, ids=[c[0] for c in CASES])
def test_learn_save_load_predict(tmp_path, name, cls, policy, env_cls, extra):
    env = env_cls()
    model = cls(policy, env, policy_kwargs=dict(net_arch=[32, 16]), **SMALL, **extra)
    model.learn(total_timesteps=300)
    assert model._n_updates > 0
    dueling = policy in (DuelingDQNPolicy, MultiInputDuelingDQNPolicy) or cls is DuelingDoubleDQN
    assert isinstance(model.q_net, DuelingQNetwork) == dueling
    if cls is PrioritizedDoubleDQN:
        expected_buf = PrioritizedDictReplayBuffer if env_cls is DictToyEnv else PrioritizedReplayBuffer
        assert type(model.replay_buffer) is expected_buf
        # priorities moved away from the initial max priority during training
        assert not np.allclose(model.replay_buffer.priorities(np.arange(model.replay_buffer.n_stored())), 1.0)

    obs_batch = [env.reset(seed=s)[0] for s in range(5)]
    actions = [int(model.predict(o, deterministic=True)[0]) for o in obs_batch]
    path = tmp_path / name
    model.save(path)
    loaded = cls.load(path, env=env_cls())
    assert type(loaded) is cls and type(loaded.policy) is type(model.policy)
    assert isinstance(loaded.q_net, DuelingQNetwork) == dueling
    assert [int(loaded.predict(o, deterministic=True)[0]) for o in obs_batch] == actions
    for key, val in model.q_net.state_dict().items():
        th.testing.assert_close(loaded.q_net.state_dict()[key], val)
    if cls is PrioritizedDoubleDQN:
        assert isinstance(loaded.replay_buffer, (PrioritizedReplayBuffer, PrioritizedDictReplayBuffer))
        assert loaded.per_beta0 == pytest.approx(0.4)
    loaded.learn(total_timesteps=100)
    assert env.action_space.contains(int(loaded.predict(obs_batch[0], deterministic=True)[0]))


def test_per_ddqn_with_multiple_envs():
    venv = make_vec_env(ToyEnv, n_envs=2, seed=0)
    model = PrioritizedDoubleDQN("MlpPolicy", venv, policy_kwargs=dict(net_arch=[16]), **SMALL)
    model.learn(total_timesteps=300)
    buf = model.replay_buffer
    assert buf.n_envs == 2 and buf.n_stored() == 300
    assert model._n_updates > 0 and model.replay_buffer.beta == pytest.approx(1.0)


def test_variant_registry():
    discrete = {name: spec.cls for name, spec in ALGORITHMS.items() if spec.actions == "discrete"}
    assert discrete == {"dqn": LaneFreeDQN, "ddqn": DoubleDQN, "dueling": DuelingDoubleDQN, "per": PrioritizedDoubleDQN}
    assert all(spec.config_section == "dqn" and spec.off_policy for spec in ALGORITHMS.values()
               if spec.actions == "discrete")
    assert [n for n, s in ALGORITHMS.items() if not s.off_policy] == ["ppo"]
    assert issubclass(PrioritizedDoubleDQN, DoubleDQN) and issubclass(DoubleDQN, LaneFreeDQN)
    assert issubclass(LaneFreeDQN, DQN)
    assert issubclass(PrioritizedReplayBuffer, ReplayBuffer)


def test_the_registry_names_each_batched_learner():
    from lanefree_sumo.errors import ConfigError
    from lanefree_sumo.rl.algorithms import BATCHED, get_algorithm
    from lanefree_sumo.rl.algorithms.batched import BatchedDDPG, BatchedDQN, BatchedTD3

    assert BATCHED == ("ddpg", "td3", "dqn", "ddqn", "dueling", "per")
    assert {name: get_algorithm(name).batched_cls for name in BATCHED} == {
        "ddpg": BatchedDDPG, "td3": BatchedTD3, "dqn": BatchedDQN, "ddqn": BatchedDQN, "dueling": BatchedDQN,
        "per": BatchedDQN}
    for name in ("sac", "ppo"):
        with pytest.raises(ConfigError, match=f"batched training covers ddpg, td3, .*, not {name}; train it run by"):
            _ = get_algorithm(name).batched_cls


_OTHER_FAMILY_JUNK = {
    "actor_critic": {"actor_layers": [8], "critic_layers": [8], "learning_rate": 0.5, "batch_size": 7, "gamma": 0.5,
                     "buffer_size": 123, "tau": 0.5, "learning_starts_steps": 5, "ou_sigma": 0.9, "ou_theta": 0.9,
                     "ppo_n_steps": 16},
    "dqn": {"layers": [8], "learning_rate": 0.5, "batch_size": 7, "gamma": 0.5, "buffer_size": 123,
            "epsilon_start": 0.5, "epsilon_end": 0.4, "epsilon_decay_episodes": 3, "target_update_steps": 1,
            "learning_starts_steps": 5},
}


class _SpacesOnly(gym.Env):
    """Just the spaces of LaneFree-v0 (24 observation values) for building a model."""

    def __init__(self, discrete: bool) -> None:
        self.observation_space = spaces.Box(-1.0, 1.0, shape=(24,), dtype=np.float32)
        self.action_space = spaces.Discrete(9) if discrete else spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)


@pytest.mark.parametrize("algo", list(ALGORITHMS))
def test_a_model_never_reads_what_unused_config_names(algo):
    """What unused_config promises (report variants and sweep adoption rely on it): the same model, bit for
    bit and hyperparameter for hyperparameter, whatever the other family's section and the algorithm's own
    unread keys hold; and a key it does read changes the model."""
    from lanefree_sumo.config import LaneFreeConfig, merge_config
    from lanefree_sumo.rl.algorithms import unused_config
    from lanefree_sumo.rl.models import build_model, training_config

    spec = ALGORITHMS[algo]
    unused = unused_config(algo)
    own = f"train.{spec.config_section}"
    (other,) = [key for key in unused if not key.startswith(own + ".")]
    assert other != own and [key for key in unused if key != other] == [f"{own}.{k}" for k in spec.unread_keys]
    base = training_config(merge_config(LaneFreeConfig(), {"train": {"algo": algo}}))
    other_section = other.split(".")[1]
    own_junk = {k: _OTHER_FAMILY_JUNK[spec.config_section][k] for k in spec.unread_keys}
    junk = merge_config(base, {"train": {other_section: _OTHER_FAMILY_JUNK[other_section],
                                         spec.config_section: own_junk}})
    read = merge_config(base, {"train": {spec.config_section: {"batch_size": 7}}})  # every algorithm reads it
    models = [build_model(cfg, _SpacesOnly(spec.actions == "discrete"), seed=0, tensorboard_log=None)
              for cfg in (base, junk, read)]
    names = ("learning_rate", "gamma", "batch_size", "buffer_size", "tau", "learning_starts", "n_steps",
             "target_update_interval", "exploration_initial_eps", "exploration_final_eps", "exploration_fraction")

    def hyperparameters(model: Any) -> dict[str, Any]:
        noise = getattr(model, "action_noise", None)  # OU: sigma and theta
        return {**{n: getattr(model, n, None) for n in names},
                "noise": None if noise is None else (noise._sigma.tolist(), noise._theta)}

    settings, junk_settings, read_settings = (hyperparameters(m) for m in models)
    assert settings == junk_settings and settings != read_settings
    first, second = (m.policy.state_dict() for m in models[:2])
    assert first.keys() == second.keys() and all(th.equal(first[k], second[k]) for k in first)

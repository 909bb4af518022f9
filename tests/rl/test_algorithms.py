"""The dueling Q-network and its policies, the prioritised replay's trees and its draw, and the algorithm registry."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3 import DDPG, DQN, PPO, SAC, TD3

from lanefree_sumo.rl.algorithms import ALGORITHMS
from lanefree_sumo.rl.algorithms.batched.replay import RunPriorities
from lanefree_sumo.rl.algorithms.batched.segment_tree import MinTree, SumTree
from lanefree_sumo.rl.algorithms.q_networks import DuelingDQNPolicy, DuelingQNetwork, MultiInputDuelingDQNPolicy

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


SMALL = dict(learning_starts=50, buffer_size=1000, batch_size=16, train_freq=1, target_update_interval=50, seed=0)


def _set_linear(layer: th.nn.Linear, weight, bias) -> None:
    with th.no_grad():
        layer.weight.copy_(th.as_tensor(weight, dtype=th.float32))
        layer.bias.copy_(th.as_tensor(bias, dtype=th.float32))


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
# Prioritised replay: one run's draw (RunPriorities)
# ---------------------------------------------------------------------------
def _priorities(leaves: np.ndarray) -> RunPriorities:
    """A RunPriorities whose leaves hold ``leaves`` (p^α) through ``update`` (α = 1, ε = 0: p^α = |δ|)."""
    priorities = RunPriorities(len(leaves), alpha=1.0, eps=1e-12)
    stored = np.flatnonzero(leaves)
    priorities.added(stored)
    priorities.update(stored, leaves[stored] - 1e-12)
    return priorities


def test_a_draw_is_the_stratified_prefix_search_and_its_weights_brute_force():
    """Each of the batch's segments of the total mass gets one uniform value; the position is the first whose
    running sum exceeds it; w_i = (P(i) / min_j P(j))^−β over the stored positions — all against numpy's
    cumulative sum, the same random draws."""
    rng = np.random.default_rng(4)
    leaves = np.where(rng.uniform(size=50) < 0.8, rng.uniform(0.05, 3.0, 50), 0.0)
    priorities = _priorities(leaves)
    batch, beta = 16, 0.55
    pos, weights = priorities.sample(np.random.RandomState(9), batch, beta)
    u = np.random.RandomState(9).random_sample(batch)
    total = leaves.sum()
    expected = np.searchsorted(np.cumsum(leaves), (np.arange(batch) + u) * total / batch, side="right")
    np.testing.assert_array_equal(pos, expected)
    assert np.all(leaves[pos] > 0)  # an empty position is never drawn
    prob = leaves / total
    np.testing.assert_allclose(weights, (prob[pos] / prob[leaves > 0].min()) ** -beta, rtol=1e-6)
    assert weights.dtype == np.float32 and weights.max() <= 1.0


def test_draws_follow_the_priorities():
    """Position i is drawn about as often as p_i / Σp says (10 000 draws, within 4 standard errors)."""
    leaves = np.array([1.0, 0.0, 4.0, 2.0, 1.0, 0.0, 8.0, 0.5])
    priorities = _priorities(leaves)
    rs = np.random.RandomState(0)
    counts = np.bincount(np.concatenate([priorities.sample(rs, 8, 1.0)[0] for _ in range(1250)]), minlength=8)
    share = leaves / leaves.sum()
    n = counts.sum()
    assert np.all(np.abs(counts / n - share) <= 4 * np.sqrt(share * (1 - share) / n) + 1e-12)


def test_new_transitions_get_the_largest_priority_and_td_errors_set_theirs():
    priorities = RunPriorities(8, alpha=0.6, eps=1e-6)
    priorities.added(np.arange(3))
    np.testing.assert_array_equal(priorities.leaves()[:4], [1.0, 1.0, 1.0, 0.0])  # nothing set yet: 1
    priorities.update(np.array([0, 2]), np.array([3.0, 0.1], dtype=np.float32))
    big = (3.0 + 1e-6) ** 0.6
    assert priorities.max_priority == pytest.approx(big)
    priorities.added(3)
    leaves = priorities.leaves()
    assert leaves[3] == priorities.max_priority and leaves[2] == pytest.approx((0.1 + 1e-6) ** 0.6)
    restored = RunPriorities(8, alpha=0.6, eps=1e-6)
    restored.load_state(priorities.state())
    assert np.array_equal(restored.leaves(), leaves) and restored.max_priority == priorities.max_priority


def test_the_registry_names_stock_sb3s_classes_and_each_variants_choices():
    """Every model.zip is stock SB3's class; the DQN variants are DQN's choices (double target, dueling policy,
    prioritised replay in the batched learner), never a class of their own."""
    assert {name: spec.cls for name, spec in ALGORITHMS.items()} == {
        "ddpg": DDPG, "td3": TD3, "sac": SAC, "ppo": PPO, "dqn": DQN, "ddqn": DQN, "dueling": DQN, "per": DQN}
    assert {name: (spec.double_q, spec.dueling) for name, spec in ALGORITHMS.items() if spec.actions == "discrete"} \
        == {"dqn": (False, False), "ddqn": (True, False), "dueling": (True, True), "per": (True, False)}
    assert all(spec.config_section == "dqn" and spec.off_policy for spec in ALGORITHMS.values()
               if spec.actions == "discrete")
    assert [n for n, s in ALGORITHMS.items() if not s.off_policy] == ["ppo"]
    assert ALGORITHMS["dueling"].policy("MlpPolicy") is DuelingDQNPolicy
    assert ALGORITHMS["dueling"].policy("MultiInputPolicy") is MultiInputDuelingDQNPolicy
    assert ALGORITHMS["per"].policy("MlpPolicy") is DQN.policy_aliases["MlpPolicy"]


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
    from lanefree_sumo.rl.models import build_batched, build_model, training_config

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
    env = _SpacesOnly(spec.actions == "discrete")

    def model(cfg: LaneFreeConfig) -> Any:  # the batched learner's model of the run where it trains, else SB3's
        if spec.batched:
            return build_batched([cfg], [0], env.observation_space, env.action_space).sb3_model(0)
        return build_model(cfg, env, seed=0, tensorboard_log=None)

    models = [model(cfg) for cfg in (base, junk, read)]
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


def test_a_per_model_of_an_earlier_version_loads_as_sb3s_dqn():
    """``tests/golden/legacy_per_model.zip`` was saved by the project's prioritised DQN class of an earlier version
    (its replay buffer class is named in the file): SB3's own ``load`` fails on it, ``load_saved_model`` gives SB3's
    DQN with the saved weights and SB3's replay buffer."""
    import io
    import zipfile
    from pathlib import Path

    from stable_baselines3.common.buffers import ReplayBuffer

    from lanefree_sumo.rl.models import load_saved_model

    path = Path(__file__).resolve().parents[1] / "golden" / "legacy_per_model.zip"
    with pytest.raises(ModuleNotFoundError, match="prioritized"):
        DQN.load(path, device="cpu")
    model = load_saved_model("per", path)
    assert type(model) is DQN and model.replay_buffer_class is ReplayBuffer
    saved = th.load(io.BytesIO(zipfile.ZipFile(path).read("policy.pth")), weights_only=True)
    mine = model.policy.state_dict()
    assert saved.keys() == mine.keys() and all(th.equal(saved[k], mine[k]) for k in saved)
    action, _ = model.predict(np.array([0.1, 0.2, 0.3], np.float32), deterministic=True)
    assert model.action_space.contains(int(action))

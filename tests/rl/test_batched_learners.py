"""Batched learners: run k of a batch of K is the single run of SB3's loop with seed k, bit for bit on CPU: stock
SB3's DDPG, TD3 and DQN, and where SB3 has no class (the DQN variants, the learner choices) SB3's autograd update
with the choice written in (:mod:`tests.rl.reference`).

"The same" is ``torch.equal`` on every parameter, target parameter and Adam moment (compared through the
SB3 model each run exports, against the single run's SB3 model), plus the numpy random stream each run drew
from. Three runs (seeds 0, 1, 2), one with another learning rate (and γ, τ); pure torch/SB3 on a toy env.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3 import DDPG, DQN, TD3
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.noise import OrnsteinUhlenbeckActionNoise
from stable_baselines3.common.vec_env import DummyVecEnv

from lanefree_sumo.config import LaneFreeConfig, merge_config
from lanefree_sumo.errors import ConfigError
from lanefree_sumo.rl.algorithms.batched import BatchedDDPG, BatchedDQN, BatchedTD3
from lanefree_sumo.rl.algorithms.batched.learner import BatchedLearner
from lanefree_sumo.rl.algorithms.q_networks import DuelingDQNPolicy
from lanefree_sumo.rl.models import build_batched, build_model
from tests.rl.reference import ReferenceDDPG, ReferenceDQN

OBS, ACT, ACTIONS, BATCH, UPDATES = 24, 2, 9, 64, 50
"""LaneFree-v0's vector observation, continuous action and discrete action counts; the paper's batch."""
SEEDS = (0, 1, 2)
HYPER = {"per-run": ((1e-3, 1e-3, 5e-4), (0.98, 0.98, 0.95), (0.001, 0.001, 0.005)),
         "shared": ((1e-3,) * 3, (0.98,) * 3, (0.001,) * 3)}
"""Learning rates, γ and τ of the three runs: run 2 differs (the per-run forms), or all alike (the scalar forms)."""
LR, GAMMA, TAU = HYPER["per-run"]
DQN_ALGOS: dict[str, dict[str, Any]] = {"dqn": {}, "ddqn": {"double_q": True},
                                        "dueling": {"double_q": True, "policy": DuelingDQNPolicy},
                                        "per": {"double_q": True, "per": (0.6, 0.4, 1e-6)}}
"""Each variant as :class:`~tests.rl.reference.ReferenceDQN`'s arguments (PER: α, β₀, ε, the learner's defaults)."""
MIXED = ("dqn", "ddqn", "dqn")
"""The variants of the three runs of a mixed batch ("dqn+ddqn"): one network, each run its own target."""
VARIANTS = [*DQN_ALGOS, "dqn+ddqn"]

pytestmark = pytest.mark.usefixtures("one_torch_thread")


class ToyEnv(gym.Env):  # type: ignore[type-arg]
    """Gaussian observations, reward from the action, episodes of 40 steps ending in truncation or, every
    third episode, termination; continuous (2) or discrete (9) actions."""

    def __init__(self, discrete: bool) -> None:
        self.observation_space = spaces.Box(-np.inf, np.inf, (OBS,), np.float32)
        self.action_space: spaces.Space = spaces.Discrete(ACTIONS) if discrete else spaces.Box(-1.0, 1.0, (ACT,),
                                                                                            np.float32)
        self.discrete = discrete
        self.t = self.episode = 0

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        super().reset(seed=seed)
        self.t = 0
        self.episode += 1
        return self.np_random.normal(size=OBS).astype(np.float32), {}

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        self.t += 1
        end = self.t >= 40
        reward = 3.0 * (int(action) - 4) if self.discrete else float(action[0])
        reward += float(self.np_random.normal())
        obs = self.np_random.normal(size=OBS).astype(np.float32)
        return obs, reward, end and self.episode % 3 == 0, end and self.episode % 3 != 0, {}


# -- building the two sides ---------------------------------------------------------------------------------

def _ddpg(k: int, learning_starts: int = 100, hyper: str = "per-run", warmup: str = "uniform",
          penalty: float = 0.0) -> DDPG:
    """Run k as SB3's DDPG (the reference where a choice differs from SB3's)."""
    lr, gamma, tau = (values[k] for values in HYPER[hyper])
    own = {"warmup_actions": warmup, "pre_tanh_penalty": penalty}
    return (DDPG if warmup == "uniform" and not penalty else ReferenceDDPG)(
        "MlpPolicy", ToyEnv(False), learning_rate=lr, buffer_size=5000, batch_size=BATCH,
                    gamma=gamma, tau=tau, learning_starts=learning_starts, train_freq=1, gradient_steps=1,
                    seed=SEEDS[k], device="cpu",
                    **({} if warmup == "uniform" and not penalty else own),
                    action_noise=OrnsteinUhlenbeckActionNoise(np.zeros(ACT), 0.2 * np.ones(ACT), theta=0.15),
                    policy_kwargs={"net_arch": {"pi": [256, 128], "qf": [256, 128]}, "activation_fn": th.nn.ReLU})


def _batched_ddpg(learning_starts: int = 100, total: int = 1, hyper: str = "per-run",
                  warmup: str = "uniform") -> BatchedDDPG:
    env = ToyEnv(False)
    lr, gamma, tau = HYPER[hyper]
    return BatchedDDPG(env.observation_space, env.action_space, SEEDS, learning_rate=lr, gamma=gamma, tau=tau,
                       warmup_actions=warmup,
                       batch_size=BATCH, buffer_size=5000, learning_starts=learning_starts, total_timesteps=total)


def _dqn(algo: str, k: int, total: int, learning_starts: int = 100, hyper: str = "per-run",
         loss: str = "huber") -> DQN:
    """Run k as SB3's DQN (stock for ``dqn`` with its Huber loss, else the reference)."""
    lr, gamma, _ = (values[k] for values in HYPER[hyper])
    variant = dict(DQN_ALGOS[MIXED[k] if algo == "dqn+ddqn" else algo])
    policy = variant.pop("policy", "MlpPolicy")
    stock = not variant and loss == "huber"
    return (DQN if stock else ReferenceDQN)(
               policy, ToyEnv(True), learning_rate=lr, buffer_size=5000, batch_size=BATCH,
               gamma=gamma, max_grad_norm=math.inf if loss == "squared" else 10.0,
               **({} if stock else {"loss": loss, **variant}),
               learning_starts=learning_starts, target_update_interval=50,
               exploration_fraction=0.3, exploration_initial_eps=1.0, exploration_final_eps=0.1,
               train_freq=1, gradient_steps=1, seed=SEEDS[k], device="cpu",
               policy_kwargs={"net_arch": [128, 64], "activation_fn": th.nn.ReLU})


def _batched_dqn(algo: str, total: int, learning_starts: int = 100, hyper: str = "per-run",
                 loss: str = "huber") -> BatchedDQN:
    env = ToyEnv(True)
    lr, gamma, _ = HYPER[hyper]
    return BatchedDQN(list(MIXED) if algo == "dqn+ddqn" else algo, env.observation_space, env.action_space, SEEDS,
                      learning_rate=lr, gamma=gamma,
                      loss=loss, max_grad_norm=math.inf if loss == "squared" else 10.0,
                      layers=(128, 64), batch_size=BATCH, buffer_size=5000, learning_starts=learning_starts,
                      target_update_interval=50, exploration_fraction=0.3, exploration_initial_eps=1.0,
                      exploration_final_eps=0.1, total_timesteps=total)


def _transitions(discrete: bool, n: int = 1000) -> list[tuple[np.ndarray, ...]]:
    """n random transitions for K runs (different per run; some terminal, some truncated)."""
    rng = np.random.default_rng(7)
    out = []
    for t in range(n):
        obs, next_obs = (rng.normal(size=(len(SEEDS), OBS)).astype(np.float32) for _ in range(2))
        action = (rng.integers(0, ACTIONS, len(SEEDS)) if discrete
                  else rng.uniform(-1, 1, (len(SEEDS), ACT)).astype(np.float32))
        done = np.full(len(SEEDS), t % 40 == 39)
        out.append((obs, action, rng.normal(size=len(SEEDS)).astype(np.float32), next_obs, done,
                    done & (t % 80 == 79)))
    return out


def _fill(single: Any, k: int, transitions: list[tuple[np.ndarray, ...]]) -> None:
    """The transitions of run k into the single run's buffer as SB3 stores them (DDPG: the action scaled)."""
    for obs, action, reward, next_obs, done, truncated in transitions:
        stored = single.policy.scale_action(action[k:k + 1]) if isinstance(single, TD3) else action[k:k + 1]
        single.replay_buffer.add(obs[k:k + 1], next_obs[k:k + 1], stored.reshape(1, -1), reward[k:k + 1],
                                 done[k:k + 1], [{"TimeLimit.truncated": bool(truncated[k])}])
    single.set_logger(Logger(None, []))


def _tensors(model: Any) -> list[th.Tensor]:
    """Every parameter, target parameter and Adam state tensor of an SB3 DDPG, TD3 or DQN model."""
    if isinstance(model, TD3):  # DDPG is SB3's TD3 with one critic
        nets, optimizers = (model.actor, model.critic, model.actor_target, model.critic_target), (
            model.actor.optimizer, model.critic.optimizer)
    else:
        nets, optimizers = (model.q_net, model.q_net_target), (model.policy.optimizer,)
    out = [p.detach() for net in nets for p in net.state_dict().values()]
    for optimizer in optimizers:
        for state in optimizer.state_dict()["state"].values():
            out += [state["step"], state["exp_avg"], state["exp_avg_sq"]]
    return out


def _assert_same(single: Any, batched: BatchedLearner, k: int) -> None:
    exported = batched.sb3_model(k)  # type: ignore[attr-defined]
    a, b = _tensors(single), _tensors(exported)
    assert len(a) == len(b) > 12
    diff = max((x.float() - y.float()).abs().max().item() for x, y in zip(a, b))
    assert all(th.equal(x, y) for x, y in zip(a, b)), f"run {k}: max |difference| {diff:g}"


# -- DDPG -----------------------------------------------------------------------------------------------

def test_ddpg_initial_weights_are_the_single_runs() -> None:
    batched = _batched_ddpg()
    for k in range(len(SEEDS)):
        single = _ddpg(k)
        params = [p.detach() for net in (single.actor, single.critic, single.actor_target, single.critic_target)
                  for p in net.parameters()]
        mine = [t for stack in (batched.actor, batched.critic, batched.actor_target, batched.critic_target)
                for t in stack.row(k)]
        assert len(params) == len(mine) == 24 and all(th.equal(p, q) for p, q in zip(params, mine))
    assert not th.equal(batched.actor.flat[0], batched.actor.flat[1])  # seeds differ: weights differ


@pytest.mark.parametrize("hyper", list(HYPER))
def test_ddpg_updates_equal_the_single_run_bit_for_bit(hyper: str) -> None:
    transitions = _transitions(False)
    batched = _batched_ddpg(hyper=hyper)
    for obs, action, reward, next_obs, done, truncated in transitions:
        batched.store(obs, action, reward, next_obs, done, truncated)
    for _ in range(UPDATES):
        assert batched.update()
    for k in range(len(SEEDS)):
        single = _ddpg(k, hyper=hyper)
        _fill(single, k, transitions)
        np.random.seed(SEEDS[k])  # the single run's global stream, as SB3 seeded it
        for _ in range(UPDATES):
            single.train(gradient_steps=1, batch_size=BATCH)
        _assert_same(single, batched, k)
        assert np.array_equal(np.random.get_state()[1], batched.streams.numpy[k].get_state()[1])
        assert float(batched.losses["critic_loss"][k]) == single.logger.name_to_value["train/critic_loss"]
        assert float(batched.losses["actor_loss"][k]) == single.logger.name_to_value["train/actor_loss"]


def _drive(batched: BatchedLearner, discrete: bool, steps: int) -> None:
    """act → env step → store → update for K toy envs seeded as SB3 seeds a single run's env."""
    envs = []
    for seed in SEEDS:
        env = DummyVecEnv([lambda: ToyEnv(discrete)])
        env.seed(seed)
        envs.append(env)
    obs = np.concatenate([env.reset() for env in envs])
    for _ in range(steps):
        actions = batched.act(obs, explore=True)
        results = [env.step(actions[k:k + 1]) for k, env in enumerate(envs)]
        new_obs = np.concatenate([r[0] for r in results])
        rewards = np.concatenate([r[1] for r in results])
        dones = np.concatenate([r[2] for r in results])
        next_obs = new_obs.copy()
        truncated = np.zeros(len(SEEDS), dtype=bool)
        for k, (_, _, done, infos) in enumerate(results):
            if done[0]:
                next_obs[k] = infos[0]["terminal_observation"]
                truncated[k] = infos[0].get("TimeLimit.truncated", False)
        batched.store(obs, actions, rewards, next_obs, dones, truncated)
        batched.update()
        obs = new_obs


@pytest.mark.parametrize("warmup", ["uniform", "policy"])
def test_ddpg_act_store_update_equals_single_learn(warmup: str) -> None:
    """The whole cycle (random warm-up actions or the actor's from the first step, OU noise and its resets,
    terminal observations, timeouts, updates) equals SB3's ``DDPG.learn`` (policy warm-up: the reference's) run by
    run."""
    steps = 260
    batched = _batched_ddpg(learning_starts=100, total=steps, warmup=warmup)
    _drive(batched, False, steps)
    for k in range(len(SEEDS)):
        single = _ddpg(k, warmup=warmup)
        single.learn(total_timesteps=steps)
        _assert_same(single, batched, k)
        assert np.array_equal(np.random.get_state()[1], batched.streams.numpy[k].get_state()[1])
        assert batched.n_updates == steps - 100


def test_ddpg_export_loads_in_sb3_and_predicts_the_batched_action(tmp_path: Path) -> None:
    batched = _batched_ddpg(learning_starts=10)
    for obs, action, reward, next_obs, done, truncated in _transitions(False, 40):
        batched.store(obs, action, reward, next_obs, done, truncated)
        batched.update()
    obs = np.random.default_rng(3).normal(size=(len(SEEDS), OBS)).astype(np.float32)
    deterministic = batched.act(obs, explore=False)
    for k in range(len(SEEDS)):
        batched.export(k, tmp_path / f"run{k}.zip")
        model = DDPG.load(tmp_path / f"run{k}.zip", device="cpu")
        action, _ = model.predict(obs[k], deterministic=True)
        assert np.array_equal(action, deterministic[k])
        assert model.learning_rate == LR[k] and model.gamma == GAMMA[k] and model.tau == TAU[k]
        assert model.num_timesteps == 40 and model._n_updates == 30


def _checkpoint_roundtrip(make: Callable[[], BatchedLearner], discrete: bool, path: Path) -> None:
    """A learner resumed from its ``state_dict`` (saved, then read with ``weights_only``) continues exactly as
    the one that was not interrupted."""
    first, second = make(), make()
    transitions = _transitions(discrete, 200)
    for obs, action, reward, next_obs, done, truncated in transitions[:150]:
        for learner in (first, second):
            learner.store(obs, action, reward, next_obs, done, truncated)
            learner.update()
    th.save(first.state_dict(), path)
    resumed = make()
    resumed.load_state_dict(th.load(path, weights_only=True))
    obs = transitions[0][0]
    for learner in (second, resumed):
        for obs, action, reward, next_obs, done, truncated in transitions[150:]:
            learner.act(obs, explore=True)
            learner.store(obs, action, reward, next_obs, done, truncated)
            learner.update()
    for k in range(len(SEEDS)):
        a, b = _tensors(second.sb3_model(k)), _tensors(resumed.sb3_model(k))  # type: ignore[attr-defined]
        assert all(th.equal(x, y) for x, y in zip(a, b))
    assert np.array_equal(second.act(obs, explore=True), resumed.act(obs, explore=True))


# -- TD3 ------------------------------------------------------------------------------------------------

def _td3(k: int) -> TD3:
    lr, gamma, tau = (values[k] for values in HYPER["per-run"])
    return TD3("MlpPolicy", ToyEnv(False), learning_rate=lr, buffer_size=5000, batch_size=BATCH, gamma=gamma,
               tau=tau, learning_starts=100, train_freq=1, gradient_steps=1, seed=SEEDS[k], device="cpu",
               action_noise=OrnsteinUhlenbeckActionNoise(np.zeros(ACT), 0.2 * np.ones(ACT), theta=0.15),
               policy_kwargs={"net_arch": {"pi": [256, 128], "qf": [256, 128]}, "activation_fn": th.nn.ReLU})


def _batched_td3(total: int = 1, learning_starts: int = 100) -> BatchedTD3:
    env = ToyEnv(False)
    lr, gamma, tau = HYPER["per-run"]
    return BatchedTD3(env.observation_space, env.action_space, SEEDS, learning_rate=lr, gamma=gamma, tau=tau,
                      batch_size=BATCH, buffer_size=5000, learning_starts=learning_starts, total_timesteps=total)


def test_td3_updates_equal_sb3s_bit_for_bit() -> None:
    """Twin critics, the clipped target noise from each run's torch stream, the actor and targets every second
    update: against ``stable_baselines3.TD3``'s autograd update."""
    transitions = _transitions(False)
    batched = _batched_td3()
    for obs, action, reward, next_obs, done, truncated in transitions:
        batched.store(obs, action, reward, next_obs, done, truncated)
    for _ in range(UPDATES + 1):  # an odd count: the last update leaves the actor alone
        assert batched.update()
    for k in range(len(SEEDS)):
        single = _td3(k)
        _fill(single, k, transitions)
        np.random.seed(SEEDS[k])
        for _ in range(UPDATES + 1):
            single.train(gradient_steps=1, batch_size=BATCH)
        _assert_same(single, batched, k)
        assert th.equal(th.random.get_rng_state(), batched.generators[k].get_state())
        assert float(batched.losses["critic_loss"][k]) == single.logger.name_to_value["train/critic_loss"]
        assert float(batched.losses["actor_loss"][k]) == single.logger.name_to_value["train/actor_loss"]
    assert batched.actor_adam.steps == UPDATES // 2 and batched.critic_adam.steps == UPDATES + 1


def test_td3_act_store_update_equals_sb3s_learn() -> None:
    steps = 230
    batched = _batched_td3(total=steps)
    _drive(batched, False, steps)
    for k in range(len(SEEDS)):
        single = _td3(k)
        single.learn(total_timesteps=steps)
        _assert_same(single, batched, k)


# -- the DQN family ---------------------------------------------------------------------------------------

def _per_trees(single: Any, batched: BatchedDQN, k: int) -> None:
    if getattr(single, "priorities", None) is not None:
        theirs, mine = single.priorities, batched.priorities[k]
        assert np.array_equal(theirs.sum_tree.tree, mine.sum_tree.tree) and mine.sum_tree.total() > 0
        assert np.array_equal(theirs.min_tree.tree, mine.min_tree.tree)
        assert theirs.max_priority == mine.max_priority > 1.0


@pytest.mark.parametrize(("hyper", "loss"), [("per-run", "huber"), ("shared", "huber"), ("per-run", "squared")])
@pytest.mark.parametrize("algo", VARIANTS)
def test_dqn_family_updates_equal_the_single_run_bit_for_bit(algo: str, hyper: str, loss: str) -> None:
    """Huber loss with the gradient clip (SB3's), or ½·δ² without a clip (Keras-RL's profile)."""
    transitions = _transitions(True)
    batched = _batched_dqn(algo, total=2000, hyper=hyper, loss=loss)
    for k in range(len(SEEDS)):  # the initial weights are the single run's
        single = _dqn(algo, k, 2000, hyper=hyper, loss=loss)
        assert all(th.equal(p.detach(), q) for p, q in zip(single.q_net.parameters(), batched.q_net.stack.row(k)))
    for obs, action, reward, next_obs, done, truncated in transitions:
        batched.store(obs, action, reward, next_obs, done, truncated)
    for _ in range(UPDATES):
        assert batched.update()
    for k in range(len(SEEDS)):
        single = _dqn(algo, k, 2000, hyper=hyper, loss=loss)
        _fill(single, k, transitions)
        single._current_progress_remaining = batched.progress_remaining  # PER's β
        np.random.seed(SEEDS[k])
        for _ in range(UPDATES):
            single.train(gradient_steps=1, batch_size=BATCH)
        _assert_same(single, batched, k)
        assert np.array_equal(np.random.get_state()[1], batched.streams.numpy[k].get_state()[1])
        assert float(batched.losses["loss"][k]) == single.logger.name_to_value["train/loss"]
        _per_trees(single, batched, k)


@pytest.mark.parametrize("algo", VARIANTS)
def test_dqn_family_act_store_update_equals_single_learn(algo: str) -> None:
    """The whole cycle (random warm-up, ε-greedy with its schedule, target copies every 50 steps, terminal
    observations, timeouts, PER's β schedule and priorities) equals the single run's ``learn``."""
    steps = 260
    batched = _batched_dqn(algo, total=steps)
    _drive(batched, True, steps)
    for k in range(len(SEEDS)):
        single = _dqn(algo, k, steps)
        single.learn(total_timesteps=steps)
        _assert_same(single, batched, k)
        assert np.array_equal(np.random.get_state()[1], batched.streams.numpy[k].get_state()[1])
        assert batched.exploration_rate[k] == single.exploration_rate
        _per_trees(single, batched, k)


@pytest.mark.parametrize("algo", ["dqn", "dueling", "dqn+ddqn"])
def test_dqn_export_loads_in_sb3_and_predicts_the_batched_action(algo: str, tmp_path: Path) -> None:
    batched = _batched_dqn(algo, total=100, learning_starts=10)
    for obs, action, reward, next_obs, done, truncated in _transitions(True, 40):
        batched.store(obs, action, reward, next_obs, done, truncated)
        batched.update()
    obs = np.random.default_rng(3).normal(size=(len(SEEDS), OBS)).astype(np.float32)
    greedy = batched.act(obs, explore=False)
    q_values = batched.q_values(obs)
    for k in range(len(SEEDS)):
        batched.export(k, tmp_path / f"run{k}.zip")
        model = DQN.load(tmp_path / f"run{k}.zip", device="cpu")
        assert type(model.q_net) is type(_dqn(algo, k, 100).q_net)  # the dueling network comes back
        action, _ = model.predict(obs[k], deterministic=True)
        assert int(action) == greedy[k]
        with th.no_grad():
            assert th.equal(model.q_net(th.as_tensor(obs[k:k + 1]))[0], q_values[k])
        assert model.learning_rate == LR[k] and model.gamma == GAMMA[k] and model._n_updates == 30


@pytest.mark.parametrize("algo", ["ddpg", "td3", "per"])
def test_a_batch_checkpoint_resumes_exactly(algo: str, tmp_path: Path) -> None:
    make = {"ddpg": lambda: _batched_ddpg(learning_starts=50, total=200),
            "td3": lambda: _batched_td3(total=200, learning_starts=50),
            "per": lambda: _batched_dqn("per", total=200, learning_starts=50)}[algo]
    _checkpoint_roundtrip(make, algo == "per", tmp_path / "batch.pt")


# -- from the runs' configs -------------------------------------------------------------------------------

@pytest.mark.parametrize(("algo", "profile"), [("ddpg", "sb3"), ("ddpg", "kerasrl"), ("td3", "sb3"),
                                               ("dqn", "kerasrl"), ("per", "sb3")])
def test_build_batched_gives_each_run_build_models_model(algo: str, profile: str) -> None:
    """Run k of ``build_batched`` is stock SB3's model of config k and seed k (``build_model``; for what SB3's class
    lacks, the config without those choices): the same class, hyperparameters and initial weights (run 1 with
    another learning rate and γ), for both learner profiles; the choices themselves come from the config."""
    actor_critic = algo in ("ddpg", "td3")
    section = "actor_critic" if actor_critic else "dqn"
    cfgs = [merge_config(LaneFreeConfig(), {"train": {"algo": algo, "profile": profile, "episodes": 50, section: {
        "learning_rate": lr, "gamma": gamma}}}) for lr, gamma in ((1e-3, 0.98), (3e-4, 0.95))]
    sb3s = {"train": {"algo": "dqn" if algo == "per" else algo, "actor_critic": {"warmup_actions": "uniform"},
                      "dqn": {"loss": "huber"}}}  # SB3's class: no choice of its own (per's network is DQN's)
    env = ToyEnv(not actor_critic)
    batched = build_batched(cfgs, [5, 6], env.observation_space, env.action_space)
    keys = ["learning_rate", "gamma", "buffer_size", "batch_size", "learning_starts", "seed"] + (
        ["tau"] if algo == "ddpg" else
        ["tau", "policy_delay", "target_policy_noise", "target_noise_clip"] if algo == "td3" else [
            "target_update_interval", "exploration_initial_eps", "exploration_final_eps", "exploration_fraction",
            "max_grad_norm"])
    for k, seed in enumerate((5, 6)):
        mine, theirs = batched.sb3_model(k), build_model(merge_config(cfgs[k], sb3s), env, seed, None)
        assert type(mine) is type(theirs)
        assert {key: getattr(mine, key) for key in keys} == {key: getattr(theirs, key) for key in keys}
        a, b = (th.cat([p.detach().reshape(-1) for p in m.policy.parameters()]) for m in (mine, theirs))
        assert th.equal(a, b)
        if actor_critic:
            noises = (mine.action_noise, theirs.action_noise)
            assert all(np.array_equal(getattr(noises[0], n), getattr(noises[1], n)) for n in ("_sigma", "_theta"))
        if algo == "ddpg":  # the choices SB3's DDPG lacks travel in its model.zip
            assert mine.warmup_actions == cfgs[k].train.actor_critic.warmup_actions
            assert mine.pre_tanh_penalty == cfgs[k].train.actor_critic.pre_tanh_penalty
    assert batched.learning_rate == [1e-3, 3e-4]
    if profile == "kerasrl":  # the profile reached the learner
        assert (batched.warmup_actions == "policy" if algo == "ddpg"
                else batched.loss == "squared" and batched.max_grad_norm == math.inf)
    if algo == "per":
        assert batched.priorities and batched.double_q
    if not actor_critic:  # the choices SB3's DQN lacks travel in its model.zip
        for k in range(2):
            mine = batched.sb3_model(k)
            assert (mine.loss, mine.double_q) == (cfgs[k].train.dqn.loss, algo != "dqn")
            assert (getattr(mine, "per_alpha", None) is not None) == (algo == "per")


def test_build_batched_refuses_runs_that_cannot_share_a_batch() -> None:
    env = ToyEnv(False)
    base = merge_config(LaneFreeConfig(), {"train": {"algo": "ddpg"}})
    wider = merge_config(base, {"train": {"actor_critic": {"actor_layers": [400, 300]}}})
    with pytest.raises(ConfigError, match="share train.actor_critic.actor_layers"):
        build_batched([base, wider], [0, 1], env.observation_space, env.action_space)
    with pytest.raises(ConfigError, match="not sac"):
        build_batched([merge_config(base, {"train": {"algo": "sac"}})], [0], env.observation_space, env.action_space)
    with pytest.raises(ConfigError, match="one seed per run"):
        build_batched([base, base], [0], env.observation_space, env.action_space)


def test_ddpg_pre_tanh_penalty_equals_the_single_autograd_update_bit_for_bit() -> None:
    """λ per run (0 for run 0: no term), against the single run's update with the penalty."""
    penalties = (0.0, 0.01, 0.05)
    transitions = _transitions(False)
    env = ToyEnv(False)
    lr, gamma, tau = HYPER["per-run"]
    batched = BatchedDDPG(env.observation_space, env.action_space, SEEDS, learning_rate=lr, gamma=gamma, tau=tau,
                          batch_size=BATCH, buffer_size=5000, learning_starts=100, pre_tanh_penalty=penalties)
    for obs, action, reward, next_obs, done, truncated in transitions:
        batched.store(obs, action, reward, next_obs, done, truncated)
    for _ in range(UPDATES):
        assert batched.update()
    for k in range(len(SEEDS)):
        single = _ddpg(k, penalty=penalties[k])
        _fill(single, k, transitions)
        np.random.seed(SEEDS[k])
        for _ in range(UPDATES):
            single.train(gradient_steps=1, batch_size=BATCH)
        _assert_same(single, batched, k)
        assert float(batched.losses["actor_loss"][k]) == single.logger.name_to_value["train/actor_loss"]


def test_each_references_choice_changes_its_update() -> None:
    """The references are not SB3's update in disguise: with its choice each trains other weights than stock SB3's
    from the same seed and transitions (so a choice the batched learner and its reference both dropped would show
    as a difference from stock here, not as their agreement)."""
    for algo, loss in (("ddqn", "huber"), ("per", "huber"), ("dqn", "squared")):
        transitions = _transitions(True)
        trained = []
        for model in (_dqn(algo, 0, 2000, loss=loss), _dqn("dqn", 0, 2000)):
            _fill(model, 0, transitions)
            model._current_progress_remaining = 0.5
            np.random.seed(SEEDS[0])
            for _ in range(UPDATES):
                model.train(gradient_steps=1, batch_size=BATCH)
            trained.append(_tensors(model))
        assert not all(th.equal(x, y) for x, y in zip(*trained)), (algo, loss)
    transitions = _transitions(False)
    trained = []
    for model in (_ddpg(1, penalty=0.05), _ddpg(1)):
        _fill(model, 1, transitions)
        np.random.seed(SEEDS[1])
        for _ in range(UPDATES):
            model.train(gradient_steps=1, batch_size=BATCH)
        trained.append(_tensors(model))
    assert not all(th.equal(x, y) for x, y in zip(*trained))
    policy, uniform = _ddpg(0, warmup="policy"), _ddpg(0)
    for model in (policy, uniform):
        model.learn(total_timesteps=50)  # all before learning_starts: the warm-up's actions alone
    assert not np.array_equal(policy.replay_buffer.actions[:50], uniform.replay_buffer.actions[:50])

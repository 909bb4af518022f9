"""The DQN family's written-out update computes the autograd update bit for bit (SB3's ``DQN.train`` for
DQN, the double-DQN loop with its hooks for the variants), and keeps SB3's interface (save/load both ways,
learn with callbacks, resume). Pure torch/SB3 on toy envs, no SUMO.

"The same" is ``torch.equal`` on every tensor: online and target network, the Adam state (step, first and
second moments), plus torch's and numpy's random streams, the logged values and PER's priorities.
"""

from __future__ import annotations

import zipfile
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3 import DQN
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import configure
from stable_baselines3.common.vec_env import DummyVecEnv

from lanefree_sumo.config import LaneFreeConfig, merge_config
from lanefree_sumo.rl.algorithms import get_algorithm
from lanefree_sumo.rl.algorithms.double_dqn import DoubleDQN
from lanefree_sumo.rl.algorithms.dueling import DuelingDoubleDQN
from lanefree_sumo.rl.algorithms.fast_dqn import FastDQN
from lanefree_sumo.rl.algorithms.prioritized import PrioritizedDoubleDQN
from lanefree_sumo.rl.models import build_model

OBS, ACTIONS, STEPS, BATCH = 24, 9, 60, 64
"""LaneFree-v0's vector observation and discrete action counts; the paper's batch."""

ALGOS: dict[str, type[FastDQN]] = {"dqn": FastDQN, "ddqn": DoubleDQN, "dueling": DuelingDoubleDQN,
                                   "per": PrioritizedDoubleDQN}

pytestmark = pytest.mark.usefixtures("one_torch_thread")


class ToyEnv(gym.Env):
    """Gaussian observations (a flat Box, or the same vector in a Dict), reward = 3 × (action − 4) plus noise
    (large enough for the gradient clip to act), episodes of 40 steps ending in truncation or, every third
    episode, termination."""

    def __init__(self, as_dict: bool = False) -> None:
        box = spaces.Box(-np.inf, np.inf, (OBS,), np.float32)
        self.observation_space = spaces.Dict({"x": box}) if as_dict else box
        self.action_space = spaces.Discrete(ACTIONS)
        self.as_dict = as_dict
        self.t = self.episode = 0

    def _obs(self) -> Any:
        x = self.np_random.normal(size=OBS).astype(np.float32)
        return {"x": x} if self.as_dict else x

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        super().reset(seed=seed)
        self.t = 0
        self.episode += 1
        return self._obs(), {}

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        self.t += 1
        end = self.t >= 40
        reward = 3.0 * (int(action) - 4) + float(self.np_random.normal())
        return self._obs(), reward, end and self.episode % 3 == 0, end and self.episode % 3 != 0, {}


def _model(cls: type[DQN], as_dict: bool = False, seed: int = 0, envs: int = 1, optimizer: Any = None,
           **kwargs: Any) -> DQN:
    """The paper's DQN settings (build_model's) on the toy env (``envs`` copies), with a short target interval."""
    policy_kwargs = {"net_arch": [128, 64], "activation_fn": th.nn.ReLU,
                     **({"optimizer_class": optimizer} if optimizer else {})}
    env = DummyVecEnv([lambda: ToyEnv(as_dict)] * envs) if envs > 1 else ToyEnv(as_dict)
    kwargs = {"learning_rate": 1e-3, **kwargs}
    return cls(
        "MultiInputPolicy" if as_dict else "MlpPolicy", env, buffer_size=5000,
        batch_size=BATCH, gamma=0.98, learning_starts=100, target_update_interval=50, exploration_fraction=0.3,
        exploration_initial_eps=1.0, exploration_final_eps=0.1, train_freq=1, gradient_steps=1, seed=seed,
        device="cpu", policy_kwargs=policy_kwargs, **kwargs,
    )


def _filled(cls: type[DQN], as_dict: bool = False, **kwargs: Any) -> DQN:
    """A model whose replay buffer holds 1000 random transitions (some terminal, some truncated)."""
    model = _model(cls, as_dict, **kwargs)
    rng = np.random.default_rng(7)
    for k in range(1000):
        obs, next_obs = (rng.normal(size=(1, OBS)).astype(np.float32) for _ in range(2))
        if as_dict:
            obs, next_obs = {"x": obs}, {"x": next_obs}
        done = k % 40 == 39
        model.replay_buffer.add(obs, next_obs, rng.integers(0, ACTIONS, (1, 1)),  # type: ignore[arg-type, union-attr]
                                (5 * rng.normal(size=1)).astype(np.float32), np.array([done]),
                                [{"TimeLimit.truncated": done and k % 80 == 79}])
    model.set_logger(configure(None, [""]))
    model._current_progress_remaining = 1.0
    return model


def _tensors(model: DQN) -> list[th.Tensor]:
    out = [p.detach() for net in (model.q_net, model.q_net_target) for p in net.state_dict().values()]
    for state in model.policy.optimizer.state_dict()["state"].values():
        out += [state["step"], state["exp_avg"], state["exp_avg_sq"]]
    return out


def _assert_params_same(a: DQN, b: DQN) -> None:
    pa, pb = ([p.detach() for net in (m.q_net, m.q_net_target) for p in net.state_dict().values()] for m in (a, b))
    assert all(th.equal(x, y) for x, y in zip(pa, pb))


def _assert_same(a: DQN, b: DQN) -> None:
    ta, tb = _tensors(a), _tensors(b)
    assert len(ta) == len(tb) > 8
    diff = max((x - y).abs().max().item() for x, y in zip(ta, tb))
    assert all(th.equal(x, y) for x, y in zip(ta, tb)), f"max |difference| {diff:g}"
    if isinstance(a, PrioritizedDoubleDQN):  # PER's priorities come from the TD errors of each step
        assert isinstance(b, PrioritizedDoubleDQN)
        every = np.arange(a.replay_buffer.n_stored())
        assert np.array_equal(a.replay_buffer.priorities(every), b.replay_buffer.priorities(every))


def _steps(model: DQN, n: int = STEPS) -> tuple[th.Tensor, np.ndarray, dict[str, float]]:
    """n gradient steps from seeded random streams; (torch RNG state, numpy RNG key, logged values)."""
    np.random.seed(123)
    th.manual_seed(123)
    for _ in range(n):
        model.train(gradient_steps=1, batch_size=BATCH)
    return th.get_rng_state(), np.random.get_state()[1].copy(), dict(model.logger.name_to_value)  # type: ignore[index]


@pytest.mark.parametrize("max_grad_norm", [10.0, 0.1], ids=["sb3-clip", "clip-always-acts"])
@pytest.mark.parametrize("algo", list(ALGOS))
def test_written_out_update_equals_autograd_bit_for_bit(algo: str, max_grad_norm: float) -> None:
    """The reference is the autograd update: SB3's own ``DQN.train`` for DQN (SB3's class itself), the
    double-DQN hooks loop for the variants (``fast_learner=False``, the code of the committed seed-0 runs)."""
    cls = ALGOS[algo]
    reference = _filled(DQN, max_grad_norm=max_grad_norm) if algo == "dqn" else \
        _filled(cls, fast_learner=False, max_grad_norm=max_grad_norm)
    fast = _filled(cls, max_grad_norm=max_grad_norm)
    _assert_same(reference, fast)  # same seed: same initial weights
    ref_rng, ref_np, ref_log = _steps(reference)
    fast_rng, fast_np, fast_log = _steps(fast)
    _assert_same(reference, fast)
    assert th.equal(ref_rng, fast_rng) and np.array_equal(ref_np, fast_np)
    assert ref_log == fast_log and fast_log["train/n_updates"] == STEPS
    plan = fast._fast_plan
    assert plan is not None and plan.written_out  # the path under test ran, on one flat parameter buffer
    assert plan.flat.numel() == sum(p.numel() for p in fast.q_net.parameters())


def test_the_clip_acts_and_the_dict_observation_takes_the_autograd_path() -> None:
    """With max_grad_norm 0.1 the clip scales every step (so the clip is tested above); a Dict observation
    (the set encoder's case) is not written out and still equals the reference."""
    model = _filled(DoubleDQN, max_grad_norm=0.1)
    norms: list[float] = []
    original = th.linalg.vector_norm

    def spy(x: th.Tensor, *args: Any, **kwargs: Any) -> th.Tensor:
        result = original(x, *args, **kwargs)
        norms.append(result.item())
        return result

    th.linalg.vector_norm = spy  # type: ignore[assignment]
    try:
        _steps(model, 5)
    finally:
        th.linalg.vector_norm = original  # type: ignore[assignment]
    assert len(norms) == 5 and min(norms) > 0.1

    reference, fast = _filled(DoubleDQN, True, fast_learner=False), _filled(DoubleDQN, True)
    _steps(reference, 20)
    _steps(fast, 20)
    _assert_same(reference, fast)
    assert fast._fast_plan is not None and not fast._fast_plan.written_out


@pytest.mark.parametrize("optimizer", [th.optim.RMSprop, th.optim.AdamW], ids=["rmsprop", "adamw"])
def test_another_optimiser_steps_itself_on_the_written_out_gradients(optimizer: Any) -> None:
    reference, fast = _filled(DQN, optimizer=optimizer), _filled(FastDQN, optimizer=optimizer)
    _steps(reference, 20)
    _steps(fast, 20)
    ref, got = (dict(m.policy.optimizer.state_dict()["state"]) for m in (reference, fast))
    assert ref.keys() == got.keys() and all(th.equal(ref[k][n], got[k][n]) for k in ref for n in ref[k])
    _assert_params_same(reference, fast)
    plan = fast._fast_plan
    assert plan is not None and plan.written_out and not plan.adam.plain


class HuberScaled(DoubleDQN):
    """A user's variant: its own loss through the double-DQN hook."""

    def _compute_loss(self, current: th.Tensor, target: th.Tensor, weights: th.Tensor | None = None) -> th.Tensor:
        return 2.0 * super()._compute_loss(current, target, weights)


class Weighted(FastDQN):
    """A user's variant: its own minibatch (with weights) through the ``_sample_batch`` hook."""

    calls = 0

    def _sample_batch(self, batch_size: int) -> tuple[Any, th.Tensor | None]:
        self.calls += 1
        data, _ = super()._sample_batch(batch_size)
        return data, th.linspace(0.5, 1.5, batch_size).reshape(-1, 1)


def test_overridden_hooks_are_honoured() -> None:
    """A variant's own loss hook sends it down the autograd path (the written-out step computes its own loss),
    also when patched after the first update; an own ``_sample_batch`` is drawn through, weights and all, by
    both paths alike; an own action rule (``_sample_action``, ``predict``) turns the lean loop off."""
    reference, fast = _filled(HuberScaled, fast_learner=False), _filled(HuberScaled)
    _steps(reference, 10)
    _steps(fast, 10)
    _assert_same(reference, fast)
    assert fast._fast_plan is not None and not fast._fast_plan.written_out
    weighted, weighted_autograd, plain = _filled(Weighted), _filled(Weighted, fast_learner=False), _filled(FastDQN)
    for model in (weighted, weighted_autograd, plain):
        _steps(model, 10)
    _assert_same(weighted, weighted_autograd)
    assert weighted.calls == weighted_autograd.calls == 10 and weighted._fast_plan.written_out  # type: ignore[union-attr]
    assert not all(th.equal(a, b) for a, b in zip(_tensors(weighted), _tensors(plain)))  # the weights acted
    later = _filled(FastDQN)
    _steps(later, 2)
    assert later._fast_plan is not None and later._fast_plan.written_out
    later._compute_loss = lambda *args: th.tensor(0.0, requires_grad=True)  # type: ignore[method-assign]
    assert later._lean_plan() is None  # patched after the first update: the plan is rebuilt, not written out
    for name in ("predict", "_sample_action"):
        patched = _filled(FastDQN)
        setattr(patched, name, lambda *args, **kwargs: (np.zeros(1, dtype=np.int64), None))
        assert patched._lean_plan() is None, name


def test_several_gradient_steps_per_call_and_the_switch() -> None:
    reference, fast, off = _filled(DQN), _filled(FastDQN), _filled(FastDQN, fast_learner=False)
    for model in (reference, fast, off):
        np.random.seed(5)
        model.train(gradient_steps=7, batch_size=BATCH)
    _assert_same(reference, fast)
    _assert_same(reference, off)
    assert off._fast_plan is None  # type: ignore[attr-defined]


@pytest.mark.parametrize("algo", ["dqn", "per"])
def test_learn_with_two_envs_and_a_learning_rate_schedule_equals_the_reference(algo: str) -> None:
    def schedule(progress_remaining: float) -> float:
        return 1e-3 * progress_remaining

    kwargs: dict[str, Any] = {"envs": 2, "seed": 4, "learning_rate": schedule}
    reference = _model(DQN, **kwargs) if algo == "dqn" else _model(ALGOS[algo], fast_learner=False,
                                                                    lean_loop=False, **kwargs)
    fast = _model(ALGOS[algo], **kwargs)
    for model in (reference, fast):
        np.random.seed(4)
        model.learn(total_timesteps=600)
    _assert_same(reference, fast)
    assert fast._n_updates == reference._n_updates > 100 and fast._fast_plan is not None and fast._fast_plan.written_out
    assert fast.policy.optimizer.param_groups[0]["lr"] < 1e-3


@pytest.mark.parametrize("algo", list(ALGOS))
def test_learn_equals_the_reference_with_callbacks_and_tensorboard(algo: str, tmp_path: Any) -> None:
    """The whole loop (ε-greedy exploration, replay, updates, target copies, episode ends) gives the same
    network and the same actions; the lean loop makes no mode switches; the callback and TensorBoard see it."""

    class Record(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.actions: list[int] = []

        def _on_step(self) -> bool:
            self.actions.append(int(self.locals["actions"][0]))
            return True

    cls = ALGOS[algo]
    reference = _model(DQN if algo == "dqn" else cls, seed=3, **({} if algo == "dqn" else
                                                                 {"fast_learner": False, "lean_loop": False}))
    fast = _model(cls, seed=3, tensorboard_log=str(tmp_path / "fast"))
    sb3_loop = _model(cls, seed=3, lean_loop=False)
    switches = {id(m): 0 for m in (reference, fast, sb3_loop)}
    recorded = {}
    for model in (reference, fast, sb3_loop):
        def count(mode: bool, model: DQN = model, original: Any = model.policy.set_training_mode) -> None:
            switches[id(model)] += 1
            original(mode)

        model.policy.set_training_mode = count  # type: ignore[method-assign]
        np.random.seed(3)
        callback = Record()
        model.learn(total_timesteps=400, callback=callback, log_interval=1)
        recorded[id(model)] = callback.actions
    _assert_same(reference, fast)
    _assert_same(reference, sb3_loop)
    assert recorded[id(reference)] == recorded[id(fast)] == recorded[id(sb3_loop)]
    assert len(set(recorded[id(fast)][100:])) > 1 and fast.exploration_rate < 1.0  # greedy and random actions
    assert fast._n_updates == reference._n_updates == 300
    assert list((tmp_path / "fast").rglob("events.out.tfevents.*"))
    assert switches[id(fast)] == 0 and switches[id(reference)] > 2 * 400 and switches[id(sb3_loop)] > 2 * 400


def test_save_load_round_trip_both_ways_and_resume(tmp_path: Any) -> None:
    """FastDQN's model.zip loads in FastDQN and SB3's DQN, SB3's loads in FastDQN; the replay buffer
    round-trips; training on from a loaded model stays identical to SB3's."""
    fast = _filled(FastDQN)
    _steps(fast, 10)
    fast.save(tmp_path / "fast.zip")
    fast.save_replay_buffer(tmp_path / "buffer.pkl")
    with zipfile.ZipFile(tmp_path / "fast.zip") as archive:  # the plan (policy, optimiser, buffer) is never saved
        assert "_fast_plan" not in archive.read("data").decode()
    DQN.save(_filled(DQN), tmp_path / "sb3.zip")

    again = FastDQN.load(tmp_path / "fast.zip", device="cpu")
    as_sb3 = DQN.load(tmp_path / "fast.zip", device="cpu")
    _assert_same(fast, again)
    _assert_same(fast, as_sb3)
    assert again.fast_learner is True
    assert FastDQN.load(tmp_path / "sb3.zip", device="cpu").fast_learner is True  # an older run's model

    for model in (again, as_sb3):  # resume: load the buffer, train on
        model.load_replay_buffer(tmp_path / "buffer.pkl")
        model.set_logger(configure(None, [""]))
        model._current_progress_remaining = 1.0
        _steps(model)
    _assert_same(again, as_sb3)
    assert again._fast_plan is not None and again._fast_plan.written_out


@pytest.mark.parametrize("algo", list(ALGOS))
def test_registry_and_build_model_pick_the_fast_learner(algo: str) -> None:
    spec = get_algorithm(algo)
    assert spec.cls is ALGOS[algo] and spec.fast_learner and not spec.overlap
    env = DummyVecEnv([ToyEnv])
    for fast in (True, False):
        for lean in (True, False):
            cfg = merge_config(LaneFreeConfig(), {"train": {"algo": algo, "fast_learner": fast, "lean_loop": lean}})
            model = build_model(cfg, env, 0, None)
            assert type(model) is ALGOS[algo] and model.fast_learner is fast and model.lean_loop is lean

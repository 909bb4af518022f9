"""FastDDPG computes SB3's DDPG update bit for bit, and keeps SB3's interface (save/load both ways,
replay buffer, learn with callbacks and TensorBoard). Pure torch/SB3 on toy envs, no SUMO.

"The same" is ``torch.equal`` on every tensor: actor, critic, both targets, both Adam states (step,
first and second moments), plus torch's and numpy's random streams and the logged losses.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3 import DDPG
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import configure
from stable_baselines3.common.noise import OrnsteinUhlenbeckActionNoise
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

from lanefree_sumo.config import LaneFreeConfig, merge_config
from lanefree_sumo.rl.algorithms import get_algorithm
from lanefree_sumo.rl.algorithms.fast_ddpg import FastDDPG
from lanefree_sumo.rl.models import build_model

OBS, ACT, STEPS, BATCH = 24, 2, 50, 64
"""LaneFree-v0's vector observation and action sizes; the paper's batch."""


pytestmark = pytest.mark.usefixtures("one_torch_thread")


class ToyEnv(gym.Env):
    """Gaussian observations (a flat Box, or the same vector in a Dict), reward = first action, episodes
    of 40 steps ending in truncation or, every third episode, termination."""

    def __init__(self, as_dict: bool = False) -> None:
        box = spaces.Box(-np.inf, np.inf, (OBS,), np.float32)
        self.observation_space = spaces.Dict({"x": box}) if as_dict else box
        self.action_space = spaces.Box(-1.0, 1.0, (ACT,), np.float32)
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

    def step(self, action: np.ndarray) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        self.t += 1
        end = self.t >= 40
        return self._obs(), float(action[0]), end and self.episode % 3 == 0, end and self.episode % 3 != 0, {}


def _model(cls: type[DDPG], as_dict: bool = False, seed: int = 0, policy_kwargs_extra: dict[str, Any] | None = None,
           **kwargs: Any) -> DDPG:
    """The paper's DDPG (build_model's settings) on the toy env."""
    return cls(
        "MultiInputPolicy" if as_dict else "MlpPolicy", ToyEnv(as_dict), learning_rate=1e-3, buffer_size=5000,
        batch_size=BATCH, gamma=0.98, tau=0.001, learning_starts=100, train_freq=1, gradient_steps=1, seed=seed,
        device="cpu", action_noise=OrnsteinUhlenbeckActionNoise(np.zeros(ACT), 0.2 * np.ones(ACT), theta=0.15),
        policy_kwargs={"net_arch": {"pi": [256, 128], "qf": [256, 128]}, "activation_fn": th.nn.ReLU,
                       **(policy_kwargs_extra or {})}, **kwargs,
    )


def _filled(cls: type[DDPG], as_dict: bool = False) -> DDPG:
    """A model whose replay buffer holds 1000 random transitions (some terminal, some truncated)."""
    model = _model(cls, as_dict)
    rng = np.random.default_rng(7)
    for k in range(1000):
        obs, next_obs = (rng.normal(size=(1, OBS)).astype(np.float32) for _ in range(2))
        if as_dict:
            obs, next_obs = {"x": obs}, {"x": next_obs}
        done = k % 40 == 39
        model.replay_buffer.add(obs, next_obs, rng.uniform(-1, 1, (1, ACT)).astype(np.float32),  # type: ignore[arg-type]
                                rng.normal(size=1).astype(np.float32), np.array([done]),
                                [{"TimeLimit.truncated": done and k % 80 == 79}])
    model.set_logger(configure(None, [""]))
    model._current_progress_remaining = 1.0
    return model


def _tensors(model: DDPG) -> list[th.Tensor]:
    out = [p.detach() for net in (model.actor, model.critic, model.actor_target, model.critic_target)
           for p in net.state_dict().values()]
    for optimizer in (model.actor.optimizer, model.critic.optimizer):
        for state in optimizer.state_dict()["state"].values():
            out += [state["step"], state["exp_avg"], state["exp_avg_sq"]]
    return out


def _assert_params(a: DDPG, b: DDPG) -> None:
    """Actor, critic and both targets equal (any optimiser's state aside)."""
    pa, pb = ([p.detach() for net in (m.actor, m.critic, m.actor_target, m.critic_target)
               for p in net.state_dict().values()] for m in (a, b))
    assert len(pa) == len(pb) > 8 and all(th.equal(x, y) for x, y in zip(pa, pb))


def _assert_same(a: DDPG, b: DDPG) -> None:
    ta, tb = _tensors(a), _tensors(b)
    assert len(ta) == len(tb) > 12
    diff = max((x - y).abs().max().item() for x, y in zip(ta, tb))
    assert all(th.equal(x, y) for x, y in zip(ta, tb)), f"max |difference| {diff:g}"


def _steps(model: DDPG, n: int = STEPS) -> tuple[th.Tensor, np.ndarray, dict[str, float]]:
    """n gradient steps from seeded random streams; (torch RNG state, numpy RNG key, logged values)."""
    np.random.seed(123)
    th.manual_seed(123)
    for _ in range(n):
        model.train(gradient_steps=1, batch_size=BATCH)
    return th.get_rng_state(), np.random.get_state()[1].copy(), dict(model.logger.name_to_value)  # type: ignore[index]


@pytest.mark.parametrize("as_dict", [False, True], ids=["mlp-written-out", "autograd-dict-obs"])
def test_fast_update_equals_sb3_bit_for_bit(as_dict: bool) -> None:
    reference, fast = _filled(DDPG, as_dict), _filled(FastDDPG, as_dict)
    _assert_same(reference, fast)  # same seed: same initial weights
    ref_rng, ref_np, ref_log = _steps(reference)
    fast_rng, fast_np, fast_log = _steps(fast)
    _assert_same(reference, fast)
    assert th.equal(ref_rng, fast_rng) and np.array_equal(ref_np, fast_np)
    assert ref_log == fast_log and fast_log["train/n_updates"] == STEPS
    assert fast._fast_plan is not None and fast._fast_plan.mlp is not as_dict  # the path named in the id ran
    assert bool(fast._fast_plan.flat) is not as_dict  # the MLP path updates flat buffers


def test_another_optimiser_steps_itself_and_an_own_action_rule_turns_the_fast_path_off() -> None:
    reference = _model(DDPG, policy_kwargs_extra={"optimizer_class": th.optim.RMSprop})
    fast = _model(FastDDPG, policy_kwargs_extra={"optimizer_class": th.optim.RMSprop})
    for model in (reference, fast):
        np.random.seed(2)
        model.learn(total_timesteps=200)
    _assert_params(reference, fast)
    assert fast._fast_plan is not None and fast._fast_plan.mlp and not fast._fast_plan.actor_adam.plain
    for name in ("predict", "_sample_action"):
        patched = _filled(FastDDPG)
        setattr(patched, name, lambda *args, **kwargs: (np.zeros((1, ACT), dtype=np.float32), None))
        assert patched._lean_plan() is None and patched._fast_plan is not None and not patched._fast_plan.mlp, name


def test_several_gradient_steps_per_call_and_the_switch() -> None:
    reference, fast, off = _filled(DDPG), _filled(FastDDPG), _filled(FastDDPG)
    off.fast_learner = False
    for model in (reference, fast, off):
        np.random.seed(5)
        model.train(gradient_steps=7, batch_size=BATCH)
    _assert_same(reference, fast)
    _assert_same(reference, off)
    assert off._fast_plan is None


def test_learn_equals_sb3_with_callbacks_and_tensorboard(tmp_path: Any) -> None:
    """The whole loop (OU exploration, replay, updates, episode ends) gives the same network, and the
    callback and TensorBoard see the run."""

    class Count(BaseCallback):
        calls = 0

        def _on_step(self) -> bool:
            self.calls += 1
            return True

    reference = _model(DDPG, seed=3, tensorboard_log=str(tmp_path / "sb3"))
    fast = _model(FastDDPG, seed=3, tensorboard_log=str(tmp_path / "fast"))
    sb3_loop = _model(FastDDPG, seed=3, lean_loop=False)
    switches = {id(m): 0 for m in (reference, fast, sb3_loop)}
    for model in (reference, fast, sb3_loop):
        def count(mode: bool, model: DDPG = model, original: Any = model.policy.set_training_mode) -> None:
            switches[id(model)] += 1
            original(mode)

        model.policy.set_training_mode = count  # type: ignore[method-assign]
        np.random.seed(3)
        callback = Count()
        model.learn(total_timesteps=260, callback=callback, log_interval=1)
        assert callback.calls == 260
    _assert_same(reference, fast)
    _assert_same(reference, sb3_loop)
    assert fast._n_updates == reference._n_updates == sb3_loop._n_updates == 160
    assert list((tmp_path / "fast").rglob("events.out.tfevents.*"))
    # the lean loop ran: no mode switches per step (SB3's loop makes ~3 per step)
    assert switches[id(fast)] == 0 and switches[id(reference)] > 2 * 260 and switches[id(sb3_loop)] > 2 * 260


def test_save_load_round_trip_both_ways_and_resume(tmp_path: Any) -> None:
    """FastDDPG's model.zip loads in FastDDPG and SB3's DDPG, SB3's loads in FastDDPG; the replay buffer
    round-trips; training on from a loaded model stays identical to SB3's."""
    fast = _filled(FastDDPG)
    _steps(fast, 10)
    fast.save(tmp_path / "fast.zip")
    fast.save_replay_buffer(tmp_path / "buffer.pkl")
    import zipfile
    with zipfile.ZipFile(tmp_path / "fast.zip") as archive:  # the plan (policy, optimisers, buffer) is never saved
        assert "_fast_plan" not in archive.read("data").decode()
    DDPG.save(_filled(DDPG), tmp_path / "sb3.zip")
    trained = _filled(DDPG)
    _steps(trained, 10)
    trained.save(tmp_path / "sb3_trained.zip")  # the same parameters and Adam state: about the same size
    assert (tmp_path / "fast.zip").stat().st_size < 1.1 * (tmp_path / "sb3_trained.zip").stat().st_size

    again = FastDDPG.load(tmp_path / "fast.zip", device="cpu")
    as_sb3 = DDPG.load(tmp_path / "fast.zip", device="cpu")
    _assert_same(fast, again)
    _assert_same(fast, as_sb3)
    assert again.fast_learner is True
    assert FastDDPG.load(tmp_path / "sb3.zip", device="cpu").fast_learner is True  # an older run's model

    for model in (again, as_sb3):  # resume: load the buffer, train on
        model.load_replay_buffer(tmp_path / "buffer.pkl")
        assert model.replay_buffer is not None and model.replay_buffer.pos == fast.replay_buffer.pos  # type: ignore[union-attr]
        model.set_logger(configure(None, [""]))
        model._current_progress_remaining = 1.0
        _steps(model)
    _assert_same(again, as_sb3)


def test_registry_and_build_model_pick_the_fast_learner() -> None:
    spec = get_algorithm("ddpg")
    assert spec.cls is FastDDPG and spec.fast_learner
    env = DummyVecEnv([ToyEnv])
    for fast in (True, False):
        cfg = merge_config(LaneFreeConfig(), {"train": {"algo": "ddpg", "fast_learner": fast}})
        model = build_model(cfg, env, 0, None)
        assert type(model) is FastDDPG and model.fast_learner is fast
    assert LaneFreeConfig().train.fast_learner is True
    for lean in (True, False):
        cfg = merge_config(LaneFreeConfig(), {"train": {"algo": "ddpg", "lean_loop": lean}})
        assert build_model(cfg, env, 0, None).lean_loop is lean


def _action_lags(model: FastDDPG) -> list[int]:
    """For each env step of ``model.learn``: how many updates the learner had made when the action was chosen."""
    lags: list[int] = []
    choose = model._lean_action

    def spy(*args: Any) -> Any:
        lags.append(model._n_updates)
        return choose(*args)

    model._lean_action = spy  # type: ignore[method-assign]
    return lags


def test_overlap_acts_one_update_behind_and_does_not_depend_on_the_process_layout() -> None:
    """The overlapped loop: the action of step t is chosen after t − 2 − learning_starts updates (SB3's
    order: t − 1 − learning_starts), every step after learning starts still gets its update, and the
    numbers are the same whether the env steps in this process or in its own (SubprocVecEnv)."""
    steps, starts = 260, 100
    sequential = _model(FastDDPG, seed=3)
    in_process = _model(FastDDPG, seed=3, overlap=True)
    own_process = _model(FastDDPG, seed=3, overlap=True)
    own_process.set_env(SubprocVecEnv([ToyEnv], start_method="spawn"))
    own_process.env.seed(3)  # type: ignore[union-attr]  # as the model seeded its own env
    lags = {}
    try:
        for name, model in (("sequential", sequential), ("in_process", in_process), ("own_process", own_process)):
            lags[name] = _action_lags(model)
            np.random.seed(3)
            model.learn(total_timesteps=steps)
            assert model._n_updates == steps - starts and model.num_timesteps == steps
    finally:
        own_process.env.close()  # type: ignore[union-attr]
    assert lags["sequential"] == [max(0, t - 1 - starts) for t in range(1, steps + 1)]
    assert lags["in_process"] == [max(0, t - 2 - starts) for t in range(1, steps + 1)]
    assert lags["own_process"] == lags["in_process"]
    _assert_same(in_process, own_process)
    assert not all(th.equal(a, b) for a, b in zip(_tensors(sequential), _tensors(in_process)))  # it is another order


def test_overlap_stops_with_the_callback_like_sb3() -> None:
    class StopAt(BaseCallback):
        def _on_step(self) -> bool:
            return self.num_timesteps < 150

    for overlap in (False, True):
        model = _model(FastDDPG, seed=1, overlap=overlap)
        model.learn(total_timesteps=260, callback=StopAt())
        assert model.num_timesteps == 150 and model._n_updates == 150 - 1 - 100

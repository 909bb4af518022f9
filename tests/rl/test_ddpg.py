"""DDPG on SB3's loop: the project's :class:`~lanefree_sumo.rl.algorithms.ddpg.LaneFreeDDPG` computes SB3's DDPG
bit for bit on its defaults and keeps SB3's interface (save/load both ways, replay buffer, learn with callbacks and
TensorBoard); its pre-tanh penalty is checked against the batched learner in ``test_batched_learners.py`` and for
its effect in ``test_open_choices.py``. Pure torch/SB3 on toy envs, no SUMO.

"The same" is ``torch.equal`` on every tensor: actor, critic, both targets, both Adam states (step,
first and second moments), plus torch's and numpy's random streams and the logged losses.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3 import DDPG
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.noise import OrnsteinUhlenbeckActionNoise
from stable_baselines3.common.vec_env import DummyVecEnv

from lanefree_sumo.config import LaneFreeConfig, merge_config
from lanefree_sumo.rl.algorithms import get_algorithm
from lanefree_sumo.rl.algorithms.ddpg import LaneFreeDDPG
from lanefree_sumo.rl.models import build_model
from tests.rl import sb3_toys
from tests.rl.sb3_toys import BATCH

ACT, STEPS = 2, 50
"""LaneFree-v0's action size; gradient steps per comparison."""


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def ToyEnv(as_dict: bool = False) -> sb3_toys.ToyEnv:  # noqa: N802  (used as the env's class)
    """The toy env with LaneFree-v0's continuous action; reward = the first action."""
    return sb3_toys.ToyEnv(spaces.Box(-1.0, 1.0, (ACT,), np.float32), lambda action, rng: float(action[0]), as_dict)


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
    sb3_toys.fill(model, lambda rng: rng.uniform(-1, 1, (1, ACT)).astype(np.float32), 1.0, as_dict)
    return model


def _params(model: DDPG) -> list[th.Tensor]:
    return [p.detach() for net in (model.actor, model.critic, model.actor_target, model.critic_target)
            for p in net.state_dict().values()]


def _assert_params(a: DDPG, b: DDPG) -> None:
    """Actor, critic and both targets equal (any optimiser's state aside)."""
    sb3_toys.assert_tensors_equal(_params(a), _params(b), 8)


def _tensors(model: DDPG) -> list[th.Tensor]:
    """The networks and both Adam states."""
    return [*_params(model), *sb3_toys.adam_states(model.actor.optimizer, model.critic.optimizer)]


def _assert_same(a: DDPG, b: DDPG) -> None:
    sb3_toys.assert_tensors_equal(_tensors(a), _tensors(b), 12)


def _steps(model: DDPG, n: int = STEPS) -> tuple[th.Tensor, np.ndarray, dict[str, float]]:
    return sb3_toys.gradient_steps(model, n)


@pytest.mark.parametrize("as_dict", [False, True], ids=["vector", "dict-obs"])
def test_the_update_equals_sb3s_bit_for_bit(as_dict: bool) -> None:
    reference, own = _filled(DDPG, as_dict), _filled(LaneFreeDDPG, as_dict)
    _assert_same(reference, own)  # same seed: same initial weights
    ref_rng, ref_np, ref_log = _steps(reference)
    own_rng, own_np, own_log = _steps(own)
    _assert_same(reference, own)
    assert th.equal(ref_rng, own_rng) and np.array_equal(ref_np, own_np)
    assert ref_log == own_log and own_log["train/n_updates"] == STEPS


def test_the_penalty_changes_the_update_and_bad_choices_are_refused() -> None:
    plain, penalised = _filled(LaneFreeDDPG), _filled(LaneFreeDDPG)
    penalised.pre_tanh_penalty = 1.0
    for model in (plain, penalised):
        _steps(model, 10)
    assert penalised._n_updates == plain._n_updates == 10
    assert not all(th.equal(a, b) for a, b in zip(_tensors(plain), _tensors(penalised)))
    with pytest.raises(ValueError, match="pre_tanh_penalty must be ≥ 0"):
        _model(LaneFreeDDPG, pre_tanh_penalty=-1.0)
    with pytest.raises(ValueError, match="unknown warm-up 'none'"):
        _model(LaneFreeDDPG, warmup_actions="none")


def test_learn_equals_sb3_with_callbacks_and_tensorboard(tmp_path: Any) -> None:
    """The whole loop (OU exploration, replay, updates, episode ends) gives the same network, and the
    callback and TensorBoard see the run."""

    class Count(BaseCallback):
        calls = 0

        def _on_step(self) -> bool:
            self.calls += 1
            return True

    reference = _model(DDPG, seed=3, tensorboard_log=str(tmp_path / "sb3"))
    own = _model(LaneFreeDDPG, seed=3, tensorboard_log=str(tmp_path / "own"))
    for model in (reference, own):
        np.random.seed(3)
        callback = Count()
        model.learn(total_timesteps=260, callback=callback, log_interval=1)
        assert callback.calls == 260
    _assert_same(reference, own)
    assert own._n_updates == reference._n_updates == 160
    assert list((tmp_path / "own").rglob("events.out.tfevents.*"))


def test_save_load_round_trip_both_ways_and_resume(tmp_path: Any) -> None:
    """The project's model.zip loads in its class and SB3's DDPG, SB3's loads in the project's; the replay buffer
    round-trips; training on from a loaded model stays identical to SB3's; the choices are saved."""
    own = _filled(LaneFreeDDPG)
    own.warmup_actions = "policy"
    _steps(own, 10)
    own.save(tmp_path / "own.zip")
    own.save_replay_buffer(tmp_path / "buffer.pkl")
    DDPG.save(_filled(DDPG), tmp_path / "sb3.zip")

    again = LaneFreeDDPG.load(tmp_path / "own.zip", device="cpu")
    as_sb3 = DDPG.load(tmp_path / "own.zip", device="cpu")
    _assert_same(own, again)
    _assert_same(own, as_sb3)
    assert again.warmup_actions == "policy"
    older = LaneFreeDDPG.load(tmp_path / "sb3.zip", device="cpu")  # SB3's model: the class defaults
    assert older._random_steps(100) == 100 and older._penalty() == 0.0

    for model in (again, as_sb3):  # resume: load the buffer, train on
        model.load_replay_buffer(tmp_path / "buffer.pkl")
        assert model.replay_buffer is not None and model.replay_buffer.pos == own.replay_buffer.pos  # type: ignore[union-attr]
        model.set_logger(Logger(None, []))
        model._current_progress_remaining = 1.0
        _steps(model)
    _assert_same(again, as_sb3)


def test_registry_and_build_model_pick_the_projects_class() -> None:
    spec = get_algorithm("ddpg")
    assert spec.cls is LaneFreeDDPG and spec.choices == ("warmup_actions", "pre_tanh_penalty") and spec.batched
    cfg = merge_config(LaneFreeConfig(), {"train": {"algo": "ddpg", "actor_critic": {
        "warmup_actions": "policy", "pre_tanh_penalty": 0.5}}})
    model = build_model(cfg, DummyVecEnv([ToyEnv]), 0, None)
    assert type(model) is LaneFreeDDPG and model.warmup_actions == "policy" and model.pre_tanh_penalty == 0.5

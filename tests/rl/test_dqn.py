"""The DQN family on SB3's loop: the project's :class:`~lanefree_sumo.rl.algorithms.dqn.LaneFreeDQN` computes SB3's own
``DQN.train`` bit for bit (its hooks at their defaults), the variants' hooks act (double target, loss, weights),
and SB3's interface holds (save/load both ways, learn with callbacks and TensorBoard, resume). Pure torch/SB3 on
toy envs, no SUMO.

"The same" is ``torch.equal`` on every tensor: online and target network, the Adam state (step, first and
second moments), plus torch's and numpy's random streams, the logged values and PER's priorities.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3 import DQN
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.vec_env import DummyVecEnv

from lanefree_sumo.config import LaneFreeConfig, merge_config
from lanefree_sumo.rl.algorithms import get_algorithm
from lanefree_sumo.rl.algorithms.double_dqn import DoubleDQN
from lanefree_sumo.rl.algorithms.dqn import LaneFreeDQN
from lanefree_sumo.rl.algorithms.dueling import DuelingDoubleDQN
from lanefree_sumo.rl.algorithms.prioritized import PrioritizedDoubleDQN
from lanefree_sumo.rl.models import build_model
from tests.rl import sb3_toys
from tests.rl.sb3_toys import BATCH

ACTIONS, STEPS = 9, 60
"""LaneFree-v0's discrete action count; gradient steps per comparison."""

ALGOS: dict[str, type[LaneFreeDQN]] = {"dqn": LaneFreeDQN, "ddqn": DoubleDQN, "dueling": DuelingDoubleDQN,
                                  "per": PrioritizedDoubleDQN}

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def ToyEnv(as_dict: bool = False) -> sb3_toys.ToyEnv:  # noqa: N802  (used as the env's class)
    """The toy env with LaneFree-v0's discrete actions; reward = 3 × (action − 4) plus noise (large enough for the
    gradient clip to act)."""
    return sb3_toys.ToyEnv(spaces.Discrete(ACTIONS), lambda action, rng: 3.0 * (int(action) - 4) + float(rng.normal()),
                           as_dict)


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
    sb3_toys.fill(model, lambda rng: rng.integers(0, ACTIONS, (1, 1)), 5.0, as_dict)
    return model


def _params(model: DQN) -> list[th.Tensor]:
    return [p.detach() for net in (model.q_net, model.q_net_target) for p in net.state_dict().values()]


def _assert_params_same(a: DQN, b: DQN) -> None:
    sb3_toys.assert_tensors_equal(_params(a), _params(b), 0)


def _tensors(model: DQN) -> list[th.Tensor]:
    """Both networks and the Adam state."""
    return [*_params(model), *sb3_toys.adam_states(model.policy.optimizer)]


def _assert_same(a: DQN, b: DQN) -> None:
    sb3_toys.assert_tensors_equal(_tensors(a), _tensors(b), 8)
    if isinstance(a, PrioritizedDoubleDQN):  # PER's priorities come from the TD errors of each step
        assert isinstance(b, PrioritizedDoubleDQN)
        every = np.arange(a.replay_buffer.n_stored())
        assert np.array_equal(a.replay_buffer.priorities(every), b.replay_buffer.priorities(every))


def _steps(model: DQN, n: int = STEPS) -> tuple[th.Tensor, np.ndarray, dict[str, float]]:
    return sb3_toys.gradient_steps(model, n)


@pytest.mark.parametrize("max_grad_norm", [10.0, 0.1], ids=["sb3-clip", "clip-always-acts"])
@pytest.mark.parametrize("as_dict", [False, True], ids=["vector", "dict-obs"])
def test_the_update_equals_sb3s_bit_for_bit(as_dict: bool, max_grad_norm: float) -> None:
    """SB3's own class is the reference: the same weights, Adam state, random streams and logged values after 60
    updates, with the gradient clip acting or not, on a flat and on a Dict observation (the set encoder's case)."""
    reference, own = (_filled(cls, as_dict, max_grad_norm=max_grad_norm) for cls in (DQN, LaneFreeDQN))
    _assert_same(reference, own)  # same seed: same initial weights
    ref_rng, ref_np, ref_log = _steps(reference)
    own_rng, own_np, own_log = _steps(own)
    _assert_same(reference, own)
    assert th.equal(ref_rng, own_rng) and np.array_equal(ref_np, own_np)
    assert ref_log == own_log and own_log["train/n_updates"] == STEPS


def test_the_clip_acts() -> None:
    """With max_grad_norm 0.1 the clip scales every step (so the clip is tested above)."""
    model = _filled(DoubleDQN, max_grad_norm=0.1)
    norms: list[float] = []
    original = th.nn.utils.clip_grad_norm_

    def spy(*args: Any, **kwargs: Any) -> th.Tensor:
        result = original(*args, **kwargs)
        norms.append(float(result))
        return result

    th.nn.utils.clip_grad_norm_ = spy  # type: ignore[assignment]
    try:
        _steps(model, 5)
    finally:
        th.nn.utils.clip_grad_norm_ = original  # type: ignore[assignment]
    assert len(norms) == 5 and min(norms) > 0.1


class HuberScaled(DoubleDQN):
    """A user's variant: its own loss through the loss hook."""

    def _compute_loss(self, current: th.Tensor, target: th.Tensor, weights: th.Tensor | None = None) -> th.Tensor:
        return 2.0 * super()._compute_loss(current, target, weights)


class Weighted(LaneFreeDQN):
    """A user's variant: its own minibatch (with weights) through the ``_sample_batch`` hook."""

    calls = 0

    def _sample_batch(self, batch_size: int) -> tuple[Any, th.Tensor | None]:
        self.calls += 1
        data, _ = super()._sample_batch(batch_size)
        return data, th.linspace(0.5, 1.5, batch_size).reshape(-1, 1)


def test_the_hooks_act() -> None:
    """The double-DQN target, a variant's own loss and its own weighted minibatch each change the update (and the
    weighted minibatch is drawn once per update); the same draws, so only the hook makes the difference."""
    plain, double, scaled, weighted = (_filled(cls) for cls in (LaneFreeDQN, DoubleDQN, HuberScaled, Weighted))
    for model in (plain, double, scaled, weighted):
        _steps(model, 10)
    assert weighted.calls == 10
    for a, b in ((plain, double), (double, scaled), (plain, weighted)):
        assert not all(th.equal(x, y) for x, y in zip(_tensors(a), _tensors(b)))
    squared, huber = _filled(LaneFreeDQN, loss="squared"), _filled(LaneFreeDQN)
    _steps(squared, 10)
    _steps(huber, 10)
    assert not all(th.equal(x, y) for x, y in zip(_tensors(squared), _tensors(huber)))
    with pytest.raises(ValueError, match="unknown TD loss 'l1'"):
        _model(LaneFreeDQN, loss="l1")


def test_several_gradient_steps_per_call() -> None:
    reference, own = _filled(DQN), _filled(LaneFreeDQN)
    for model in (reference, own):
        np.random.seed(5)
        model.train(gradient_steps=7, batch_size=BATCH)
    _assert_same(reference, own)


def test_learn_with_two_envs_and_a_learning_rate_schedule_equals_sb3s() -> None:
    def schedule(progress_remaining: float) -> float:
        return 1e-3 * progress_remaining

    kwargs: dict[str, Any] = {"envs": 2, "seed": 4, "learning_rate": schedule}
    reference, own = _model(DQN, **kwargs), _model(LaneFreeDQN, **kwargs)
    for model in (reference, own):
        np.random.seed(4)
        model.learn(total_timesteps=600)
    _assert_same(reference, own)
    assert own._n_updates == reference._n_updates > 100
    assert own.policy.optimizer.param_groups[0]["lr"] < 1e-3


@pytest.mark.parametrize("algo", list(ALGOS))
def test_learn_with_callbacks_and_tensorboard(algo: str, tmp_path: Any) -> None:
    """The whole loop (ε-greedy exploration, replay, updates, target copies, episode ends): DQN gives SB3's
    network and actions; every variant explores, acts greedily, updates and writes TensorBoard events."""

    class Record(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.actions: list[int] = []

        def _on_step(self) -> bool:
            self.actions.append(int(self.locals["actions"][0]))
            return True

    models = {"own": _model(ALGOS[algo], seed=3, tensorboard_log=str(tmp_path / "own"))}
    if algo == "dqn":
        models["sb3"] = _model(DQN, seed=3)
    recorded = {}
    for name, model in models.items():
        np.random.seed(3)
        callback = Record()
        model.learn(total_timesteps=400, callback=callback, log_interval=1)
        recorded[name] = callback.actions
    own = models["own"]
    if algo == "dqn":
        _assert_same(models["sb3"], own)
        assert recorded["sb3"] == recorded["own"]
    assert len(set(recorded["own"][100:])) > 1 and own.exploration_rate < 1.0  # greedy and random actions
    assert own._n_updates == 300
    assert list((tmp_path / "own").rglob("events.out.tfevents.*"))


def test_save_load_round_trip_both_ways_and_resume(tmp_path: Any) -> None:
    """The project's model.zip loads in its class and in SB3's DQN, SB3's loads in the project's; the replay buffer
    round-trips; training on from a loaded model stays identical to SB3's; the loss choice is saved."""
    own = _filled(LaneFreeDQN, loss="squared")
    _steps(own, 10)
    own.save(tmp_path / "own.zip")
    own.save_replay_buffer(tmp_path / "buffer.pkl")
    DQN.save(_filled(DQN), tmp_path / "sb3.zip")

    again = LaneFreeDQN.load(tmp_path / "own.zip", device="cpu")
    as_sb3 = DQN.load(tmp_path / "own.zip", device="cpu")
    _assert_same(own, again)
    _assert_same(own, as_sb3)
    assert again.loss == "squared"
    assert LaneFreeDQN.load(tmp_path / "sb3.zip", device="cpu").loss == "huber"  # SB3's model: the class default
    again.loss = "huber"  # SB3's class ignores the saved attribute: compare on its loss
    for model in (again, as_sb3):  # resume: load the buffer, train on
        model.load_replay_buffer(tmp_path / "buffer.pkl")
        model.set_logger(Logger(None, []))
        model._current_progress_remaining = 1.0
        _steps(model)
    _assert_same(again, as_sb3)


@pytest.mark.parametrize("algo", list(ALGOS))
def test_registry_and_build_model_pick_the_projects_class(algo: str) -> None:
    spec = get_algorithm(algo)
    assert spec.cls is ALGOS[algo] and spec.choices == ("loss",) and spec.batched
    cfg = merge_config(LaneFreeConfig(), {"train": {"algo": algo, "dqn": {"loss": "squared"}}})
    model = build_model(cfg, DummyVecEnv([ToyEnv]), 0, None)
    assert type(model) is ALGOS[algo] and model.loss == "squared"

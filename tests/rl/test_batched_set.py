"""Batched DDPG, TD3 and the DQN family on the set observation (the written-out set encoder,
:mod:`...batched.set_encoder`).

The chain: run k of a batch equals the batch of that one run bit for bit (CPU); a batch of one run equals
SB3's autograd update (SB3's DDPG, TD3 and DQN, and for the pre-tanh penalty and the DQN variants SB3's update
with the choice written in, :mod:`tests.rl.reference`; each with ``SetFeaturesExtractor``) to float tolerance — the
dense encoder sums the rows in another order than the gathered one — after 20 updates; the exported model loads in
SB3 and acts as the batch does (to the same tolerance). Both encoders (``paper``, ``small``), with and without the
pre-tanh penalty, runs with different seeds and penalties in one batch; TD3 (twin critics on one encoder) with the
paper encoder; every DQN variant (dueling: the encoder under the dueling head's trunk), prioritised replay compared
with its runs batched alone.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3 import DDPG, TD3
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.noise import OrnsteinUhlenbeckActionNoise

from lanefree_sumo.rl.algorithms.batched import BatchedDDPG, BatchedTD3
from lanefree_sumo.rl.algorithms.batched.learner import SpacesEnv
from lanefree_sumo.rl.encoder import SetFeaturesExtractor
from tests.rl.reference import ReferenceDDPG, ReferenceDQN

EGO, ROWS, WIDTH, ACT, BATCH, UPDATES = 4, 6, 5, 2, 16, 20
SEEDS = (0, 1, 2)
PENALTIES = (0.0, 0.01, 0.05)
LAYERS = (64, 32)
SPACE = spaces.Dict({"ego": spaces.Box(-np.inf, np.inf, (EGO,), np.float32),
                     "others": spaces.Box(-np.inf, np.inf, (ROWS, WIDTH), np.float32)})
ACTIONS = spaces.Box(-1.0, 1.0, (ACT,), np.float32)
TOLERANCE = 1e-5
"""The largest |difference| allowed between a batched and an SB3 parameter after the updates (measured:
1.2e-7–1.2e-6)."""

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _observations(rng: np.random.Generator) -> dict[str, np.ndarray]:
    """K set observations (padding rows zero, presence last): runs 0 and 1 see the first 0–2 and 0–3 rows (as
    the environment lists the vehicles, nearest first; a batch then cuts its table after more rows than either
    run alone), run 2 each row with probability 0.6, in any order."""
    present = np.zeros((len(SEEDS), ROWS), dtype=np.float32)
    for k, most in ((0, 2), (1, 3)):
        present[k, :rng.integers(0, most + 1)] = 1.0
    present[2] = rng.uniform(size=ROWS) < 0.6
    table = rng.normal(size=(len(SEEDS), ROWS, WIDTH)).astype(np.float32) * present[..., None]
    table[..., -1] = present
    return {"ego": rng.normal(size=(len(SEEDS), EGO)).astype(np.float32), "others": table}


def _transitions(n: int = 300) -> list[tuple[Any, ...]]:
    rng = np.random.default_rng(7)
    out = []
    for t in range(n):
        obs, next_obs = _observations(rng), _observations(rng)
        done = np.full(len(SEEDS), t % 40 == 39)
        out.append((obs, rng.uniform(-1, 1, (len(SEEDS), ACT)).astype(np.float32),
                    rng.normal(size=len(SEEDS)).astype(np.float32), next_obs, done, done & (t % 80 == 79)))
    return out


def _run(values: dict[str, np.ndarray], k: int) -> dict[str, np.ndarray]:
    return {key: v[k:k + 1] for key, v in values.items()}


def _batched(encoder: str, seeds: tuple[int, ...], penalties: tuple[float, ...], algo: str = "ddpg") -> BatchedDDPG:
    extra: dict[str, Any] = {"pre_tanh_penalty": penalties} if algo == "ddpg" else {}
    return (BatchedDDPG if algo == "ddpg" else BatchedTD3)(
        SPACE, ACTIONS, seeds, learning_rate=1e-3, batch_size=BATCH, buffer_size=1000, learning_starts=50,
        encoder=encoder, actor_layers=LAYERS, critic_layers=LAYERS, **extra)


def _trained(encoder: str, runs: list[int], transitions: list[tuple[Any, ...]], algo: str = "ddpg") -> BatchedDDPG:
    """A batch of runs ``runs`` (indices into SEEDS) after every transition and UPDATES updates."""
    batched = _batched(encoder, tuple(SEEDS[k] for k in runs), tuple(PENALTIES[k] for k in runs), algo)
    for obs, action, reward, next_obs, done, truncated in transitions:
        batched.store({key: v[runs] for key, v in obs.items()}, action[runs], reward[runs],
                      {key: v[runs] for key, v in next_obs.items()}, done[runs], truncated[runs])
    for _ in range(UPDATES):
        assert batched.update()
    return batched


def _single(encoder: str, k: int, algo: str = "ddpg") -> TD3:
    extra: dict[str, Any] = {"pre_tanh_penalty": PENALTIES[k]} if algo == "ddpg" and PENALTIES[k] else {}
    return (TD3 if algo == "td3" else ReferenceDDPG if extra else DDPG)(
        "MultiInputPolicy", SpacesEnv(SPACE, ACTIONS), learning_rate=1e-3, buffer_size=1000, batch_size=BATCH,
        gamma=0.98, tau=0.001, learning_starts=50, train_freq=1, gradient_steps=1, seed=SEEDS[k], device="cpu",
        action_noise=OrnsteinUhlenbeckActionNoise(np.zeros(ACT), 0.2 * np.ones(ACT), theta=0.15),
        policy_kwargs={"net_arch": {"pi": list(LAYERS), "qf": list(LAYERS)}, "activation_fn": th.nn.ReLU,
                       "features_extractor_class": SetFeaturesExtractor,
                       "features_extractor_kwargs": {"encoder": encoder}}, **extra)


NETS = ("actor", "critic", "actor_target", "critic_target")


CASES = [("paper", "ddpg"), ("small", "ddpg"), ("paper", "td3")]
"""(encoder, algorithm) of the comparisons."""


@pytest.mark.parametrize(("encoder", "algo"), CASES)
def test_initial_weights_are_sb3s(encoder: str, algo: str) -> None:
    batched = _batched(encoder, SEEDS, PENALTIES, algo)
    for k in range(len(SEEDS)):
        single = _single(encoder, k, algo)
        params = [p.detach() for net in NETS for p in getattr(single, net).parameters()]
        mine = [t for net in NETS for t in getattr(batched, net).row(k)]
        assert len(params) == len(mine) > 24 and all(th.equal(p, q) for p, q in zip(params, mine))


@pytest.mark.parametrize(("encoder", "algo"), CASES)
def test_a_batch_equals_its_runs_batched_alone_bit_for_bit(encoder: str, algo: str) -> None:
    transitions = _transitions()
    batch = _trained(encoder, [0, 1, 2], transitions, algo)
    for k in range(len(SEEDS)):
        alone = _trained(encoder, [k], transitions, algo)
        for net in NETS:
            assert th.equal(getattr(batch, net).flat[k], getattr(alone, net).flat[0]), (encoder, k, net)
        assert th.equal(batch.actor_adam.exp_avg_sq[k], alone.actor_adam.exp_avg_sq[0])
        assert th.equal(batch.losses["actor_loss"][k], alone.losses["actor_loss"][0])


@pytest.mark.parametrize(("encoder", "algo"), CASES)
def test_updates_equal_sb3s_autograd_update_to_float_tolerance(encoder: str, algo: str) -> None:
    transitions = _transitions()
    batched = _trained(encoder, [0, 1, 2], transitions, algo)
    for k in range(len(SEEDS)):
        single = _single(encoder, k, algo)
        for obs, action, reward, next_obs, done, truncated in transitions:
            single.replay_buffer.add(_run(obs, k), _run(next_obs, k), single.policy.scale_action(action[k:k + 1]),
                                     reward[k:k + 1], done[k:k + 1], [{"TimeLimit.truncated": bool(truncated[k])}])
        single.set_logger(Logger(None, []))
        np.random.seed(SEEDS[k])  # the single run's global stream, as SB3 seeded it
        for _ in range(UPDATES):
            single.train(gradient_steps=1, batch_size=BATCH)
        exported = batched.sb3_model(k)
        moved = 0.0
        for net in NETS:
            for p, q, start in zip(getattr(single, net).parameters(), getattr(exported, net).parameters(),
                                   getattr(_batched(encoder, SEEDS, PENALTIES, algo), net).row(k)):
                assert (p - q).abs().max().item() < TOLERANCE, (encoder, k, net)
                moved = max(moved, (p - start).abs().max().item())
        assert moved > 100 * TOLERANCE  # the updates moved the weights far more than the tolerance
        for name in ("critic_loss", "actor_loss"):
            assert float(batched.losses[name][k]) == pytest.approx(single.logger.name_to_value[f"train/{name}"],
                                                                   rel=1e-5, abs=1e-6)


def test_the_export_loads_in_sb3_and_acts_as_the_batch(tmp_path: Path) -> None:
    batched = _trained("paper", [0, 1, 2], _transitions(120))
    obs = _observations(np.random.default_rng(3))
    deterministic = batched.act(obs, explore=False)
    for k in range(len(SEEDS)):
        batched.export(k, tmp_path / f"run{k}.zip")
        model = DDPG.load(tmp_path / f"run{k}.zip", device="cpu")
        action, _ = model.predict({key: v[k] for key, v in obs.items()}, deterministic=True)
        assert np.allclose(action, deterministic[k], atol=1e-6)
        assert model.pre_tanh_penalty == PENALTIES[k] and model.num_timesteps == 120


def test_the_learners_refuse_a_set_observation_without_an_encoder() -> None:
    from lanefree_sumo.rl.algorithms.batched import BatchedDQN

    with pytest.raises(ValueError, match="takes an encoder"):
        BatchedDDPG(SPACE, ACTIONS, SEEDS)
    with pytest.raises(ValueError, match="takes an encoder"):
        BatchedDQN("dqn", SPACE, spaces.Discrete(9), SEEDS)
    with pytest.raises(ValueError, match="the vector observation none"):
        BatchedDQN("dqn", spaces.Box(-1, 1, (EGO,), np.float32), spaces.Discrete(9), SEEDS, encoder="small")


def test_the_devices_dense_encoder_equals_the_cpus_run_by_run_encoder() -> None:
    """The pass a GPU and the lockstep loop take (every row of every run at once, no cut) against the CPU exact
    loop's (run by run, each table cut after its last present row), forward and backward, to float tolerance."""
    from lanefree_sumo.rl.algorithms.batched.set_encoder import _encode, _encode_backward, encode, encode_backward

    batched = _batched("paper", SEEDS, PENALTIES)
    obs = th.as_tensor(np.stack([np.concatenate([o["ego"], o["others"].reshape(len(SEEDS), -1)], axis=1)
                                 for o in (_observations(np.random.default_rng(i)) for i in range(BATCH))], axis=1))
    layout, tensors = batched.layout, batched.actor.views()[:batched.layout.tensors]  # type: ignore[union-attr]
    assert layout is not None
    features, saved = encode(batched.mm, layout, tensors, obs, dense=False)
    dense, dense_saved = _encode(batched.mm, layout, tensors, obs, cut=False)
    assert len(saved) == len(SEEDS) and saved[0].mask.shape[2] <= 3 < dense_saved.mask.shape[2] == ROWS
    assert th.allclose(features, dense, atol=1e-6)
    grad = th.as_tensor(np.random.default_rng(5).normal(size=features.shape).astype(np.float32))
    for mine, theirs in zip(encode_backward(batched.mm, layout, tensors, saved, grad),
                            _encode_backward(batched.mm, layout, tensors, dense_saved, grad)):
        assert mine.shape == theirs.shape and th.allclose(mine, theirs, atol=1e-5)
    assert features.shape == (len(SEEDS), BATCH, batched.features_dim)


# -- the DQN family ----------------------------------------------------------------------------------------------

N_ACTIONS = 9
DISCRETE = spaces.Discrete(N_ACTIONS)
DQN_CASES = [("paper", "dqn"), ("small", "ddqn"), ("small", "dueling"), ("paper", "per")]
"""(encoder, variant) of the DQN family's comparisons: every variant, both encoders."""


def _batched_dqn(encoder: str, algo: str, seeds: tuple[int, ...]) -> Any:
    from lanefree_sumo.rl.algorithms.batched import BatchedDQN

    return BatchedDQN(algo, SPACE, DISCRETE, seeds, learning_rate=1e-3, layers=LAYERS, batch_size=BATCH,
                      buffer_size=1000, learning_starts=50, target_update_interval=7, total_timesteps=400,
                      encoder=encoder)


def _dqn_transitions(n: int = 300) -> list[tuple[Any, ...]]:
    rng = np.random.default_rng(11)
    return [(obs, rng.integers(0, N_ACTIONS, len(SEEDS)), reward, next_obs, done, truncated)
            for obs, _, reward, next_obs, done, truncated in _transitions(n)]


def _trained_dqn(encoder: str, algo: str, runs: list[int], transitions: list[tuple[Any, ...]]) -> Any:
    batched = _batched_dqn(encoder, algo, tuple(SEEDS[k] for k in runs))
    for obs, action, reward, next_obs, done, truncated in transitions:
        batched.store({key: v[runs] for key, v in obs.items()}, action[runs], reward[runs],
                      {key: v[runs] for key, v in next_obs.items()}, done[runs], truncated[runs])
    for _ in range(UPDATES):
        assert batched.update()
    return batched


def _single_dqn(encoder: str, algo: str, k: int) -> Any:
    """Run k in SB3's autograd update: SB3's own DQN for ``dqn``, the reference's double-Q target for the other
    variants (dueling: its policy)."""
    from stable_baselines3 import DQN

    from lanefree_sumo.rl.algorithms.q_networks import MultiInputDuelingDQNPolicy

    policy = MultiInputDuelingDQNPolicy if algo == "dueling" else "MultiInputPolicy"
    extra: dict[str, Any] = {} if algo == "dqn" else {"double_q": True}
    return (ReferenceDQN if extra else DQN)(policy, SpacesEnv(SPACE, DISCRETE), learning_rate=1e-3, buffer_size=1000,
               batch_size=BATCH, gamma=0.98, learning_starts=50, target_update_interval=7, train_freq=1,
               gradient_steps=1, seed=SEEDS[k], device="cpu",
               policy_kwargs={"net_arch": list(LAYERS), "activation_fn": th.nn.ReLU,
                              "features_extractor_class": SetFeaturesExtractor,
                              "features_extractor_kwargs": {"encoder": encoder}}, **extra)


@pytest.mark.parametrize(("encoder", "algo"), DQN_CASES)
def test_the_dqn_familys_initial_weights_are_sb3s(encoder: str, algo: str) -> None:
    batched = _batched_dqn(encoder, algo, SEEDS)
    for k in range(len(SEEDS)):
        single = _single_dqn(encoder, algo, k)
        for net in ("q_net", "q_net_target"):
            params = [p.detach() for p in getattr(single, net).parameters()]
            mine = getattr(batched, net).stack.row(k)
            assert len(params) == len(mine) > 10 and all(th.equal(p, q) for p, q in zip(params, mine))


@pytest.mark.parametrize(("encoder", "algo"), DQN_CASES)
def test_the_dqn_familys_batch_equals_its_runs_batched_alone_bit_for_bit(encoder: str, algo: str) -> None:
    transitions = _dqn_transitions()
    batch = _trained_dqn(encoder, algo, [0, 1, 2], transitions)
    for k in range(len(SEEDS)):
        alone = _trained_dqn(encoder, algo, [k], transitions)
        for net in ("q_net", "q_net_target"):
            assert th.equal(getattr(batch, net).stack.flat[k], getattr(alone, net).stack.flat[0]), (algo, k, net)
        assert th.equal(batch.losses["loss"][k], alone.losses["loss"][0])


@pytest.mark.parametrize(("encoder", "algo"), [c for c in DQN_CASES if c[1] != "per"])
def test_the_dqn_familys_updates_equal_sb3s_autograd_update_to_float_tolerance(encoder: str, algo: str) -> None:
    """Uniform replay (PER's draws depend on the TD errors, whose float rounding differs: its runs are compared
    with themselves above); the target network is the initial one throughout (it is copied on stored steps)."""
    transitions = _dqn_transitions()
    batched = _trained_dqn(encoder, algo, [0, 1, 2], transitions)
    start = _batched_dqn(encoder, algo, SEEDS)
    for k in range(len(SEEDS)):
        single = _single_dqn(encoder, algo, k)
        for obs, action, reward, next_obs, done, truncated in transitions:
            single.replay_buffer.add(_run(obs, k), _run(next_obs, k), action[k:k + 1], reward[k:k + 1],
                                     done[k:k + 1], [{"TimeLimit.truncated": bool(truncated[k])}])
        single.set_logger(Logger(None, []))
        np.random.seed(SEEDS[k])  # the single run's global stream, as SB3 seeded it
        for _ in range(UPDATES):
            single.train(gradient_steps=1, batch_size=BATCH)
        moved = 0.0
        for p, q, first in zip(single.q_net.parameters(), batched.q_net.stack.row(k), start.q_net.stack.row(k)):
            assert (p.detach() - q).abs().max().item() < TOLERANCE, (algo, k)
            moved = max(moved, (p.detach() - first).abs().max().item())
        assert moved > 100 * TOLERANCE
        assert float(batched.losses["loss"][k]) == pytest.approx(single.logger.name_to_value["train/loss"],
                                                                 rel=1e-5, abs=1e-6)


def test_the_dqn_familys_export_loads_in_sb3_and_acts_as_the_batch(tmp_path: Path) -> None:
    from stable_baselines3 import DQN

    batched = _trained_dqn("paper", "dueling", [0, 1, 2], _dqn_transitions(120))
    obs = _observations(np.random.default_rng(3))
    greedy = batched.act(obs, explore=False)
    for k in range(len(SEEDS)):
        batched.export(k, tmp_path / f"run{k}.zip")
        model = DQN.load(tmp_path / f"run{k}.zip", device="cpu")
        action, _ = model.predict({key: v[k] for key, v in obs.items()}, deterministic=True)
        assert int(action) == int(greedy[k]) and model.num_timesteps == 120

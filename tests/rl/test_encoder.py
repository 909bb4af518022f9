"""Tests for lanefree_sumo.rl.encoder (set encoder of Liu, Zhang & Zhou 2023, specification §5)."""

from __future__ import annotations

from typing import get_args, get_type_hints

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium import spaces

from lanefree_sumo.errors import ConfigError
from lanefree_sumo.rl.encoder import ENCODER_NAMES, PRESETS, SetEncoder, SetFeaturesExtractor, encoder_kwargs

F = 5  # [dx, dy, vx, vy, presence]
ATOL = 1e-5


def _rows(n_present: int, max_rows: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    obs = np.zeros((max_rows, F), dtype=np.float32)
    obs[:n_present, :4] = rng.normal(size=(n_present, 4)).astype(np.float32)
    obs[:n_present, 4] = 1.0
    return obs


def _pad(obs: np.ndarray, max_rows: int) -> np.ndarray:
    out = np.zeros((max_rows, obs.shape[1]), dtype=obs.dtype)
    out[: obs.shape[0]] = obs
    return out


def _t(a: np.ndarray) -> torch.Tensor:
    return torch.as_tensor(a, dtype=torch.float32).unsqueeze(0)


@pytest.fixture(params=["layernorm", "l2", "none"])
def encoder(request) -> SetEncoder:
    torch.manual_seed(0)
    enc = SetEncoder(in_features=4, d1=6, d2=5, hidden=(32,), norm=request.param)
    enc.eval()
    return enc


def test_output_dim(encoder):
    out = encoder(_t(_rows(3, 8)))
    assert out.shape == (1, 30) == (1, encoder.out_dim)
    enc2 = SetEncoder(in_features=4, d1=6, d2=5, pool_over="rows+d1")
    assert enc2(_t(_rows(3, 8))).shape == (1, 5)
    # unbatched input also works
    assert encoder(torch.as_tensor(_rows(3, 8))).shape == (30,)


def test_permutation_invariance(encoder):
    obs = _rows(3, 8, seed=1)
    base = encoder(_t(obs))
    rng = np.random.default_rng(2)
    for _ in range(5):
        perm = rng.permutation(8)  # permutes present rows and interleaves padding
        out = encoder(_t(obs[perm]))
        torch.testing.assert_close(out, base, atol=ATOL, rtol=0)


def test_padding_invariance(encoder):
    obs8 = _rows(3, 8, seed=3)
    obs20 = _pad(obs8, 20)
    obs3 = obs8[:3]
    out8, out20, out3 = encoder(_t(obs8)), encoder(_t(obs20)), encoder(_t(obs3))
    torch.testing.assert_close(out8, out20, atol=ATOL, rtol=0)
    torch.testing.assert_close(out8, out3, atol=ATOL, rtol=0)


def test_padding_rows_ignored_even_if_nonzero(encoder):
    """Rows with presence 0 must not influence the output, whatever they contain."""
    obs = _rows(3, 8, seed=4)
    junk = obs.copy()
    junk[3:, :4] = 123.0
    junk[5, :4] = np.nan
    torch.testing.assert_close(encoder(_t(junk)), encoder(_t(obs)), atol=ATOL, rtol=0)


def test_zero_present_rows_no_nan(encoder):
    for rows in (8, 1, 0):
        out = encoder(torch.zeros(2, rows, F))
        assert out.shape == (2, 30)
        assert torch.isfinite(out).all()
    # pooled matrix is exactly zero for an empty set (before normalisation)
    raw = SetEncoder(in_features=4, d1=3, d2=3, norm="none")(torch.zeros(1, 8, F))
    assert torch.count_nonzero(raw) == 0


def test_batch_with_mixed_counts_matches_single(encoder):
    obs = [_rows(n, 10, seed=10 + n) for n in (0, 1, 4, 10)]
    batch = encoder(torch.as_tensor(np.stack(obs)))
    for i, o in enumerate(obs):
        torch.testing.assert_close(batch[i : i + 1], encoder(_t(o)), atol=ATOL, rtol=0)


def test_explicit_mask_equivalent(encoder):
    obs = _rows(4, 8, seed=5)
    x = _t(obs)
    out_mask = encoder(x[..., :4], mask=x[..., 4] > 0.5)
    torch.testing.assert_close(out_mask, encoder(x), atol=ATOL, rtol=0)


def test_output_depends_on_vehicles(encoder):
    a = encoder(_t(_rows(3, 8, seed=6)))
    b = encoder(_t(_rows(3, 8, seed=7)))
    c = encoder(_t(_rows(5, 8, seed=6)))
    assert not torch.allclose(a, b, atol=1e-3)
    assert not torch.allclose(a, c, atol=1e-3)
    # a single vehicle's position matters
    obs = _rows(3, 8, seed=6)
    obs2 = obs.copy()
    obs2[0, 0] += 1.0
    assert not torch.allclose(encoder(_t(obs)), encoder(_t(obs2)), atol=1e-4)


def test_gradients_flow():
    torch.manual_seed(0)
    enc = SetEncoder(in_features=4, d1=4, d2=4)
    out = enc(torch.as_tensor(np.stack([_rows(3, 6, 1), _rows(0, 6, 2)])))
    out.pow(2).sum().backward()
    for name, p in enc.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
    assert any(p.grad.abs().sum() > 0 for p in enc.f1.parameters())
    assert any(p.grad.abs().sum() > 0 for p in enc.f2.parameters())


def _others_space(max_rows: int) -> spaces.Box:
    return spaces.Box(-np.inf, np.inf, shape=(max_rows, F), dtype=np.float32)


def _dict_space(max_rows: int, k: int = 3) -> spaces.Dict:
    return spaces.Dict(
        {"ego": spaces.Box(-np.inf, np.inf, shape=(k,), dtype=np.float32), "others": _others_space(max_rows)}
    )


def test_extractor_weights_transfer_across_max_rows():
    torch.manual_seed(0)
    ext8 = SetFeaturesExtractor(_others_space(8), d1=4, d2=6, hidden=(16,))
    ext20 = SetFeaturesExtractor(_others_space(20), d1=4, d2=6, hidden=(16,))
    assert ext8.features_dim == ext20.features_dim == 24
    ext20.load_state_dict(ext8.state_dict())  # same parameter shapes whatever max_rows
    ext8.eval(), ext20.eval()
    obs8 = _rows(3, 8, seed=8)
    with torch.no_grad():
        torch.testing.assert_close(ext20(_t(_pad(obs8, 20))), ext8(_t(obs8)), atol=ATOL, rtol=0)
        # the same module also runs directly on any number of rows
        torch.testing.assert_close(ext8(_t(_pad(obs8, 50))), ext8(_t(obs8)), atol=ATOL, rtol=0)


def test_extractor_dict_passthrough():
    torch.manual_seed(0)
    ext = SetFeaturesExtractor(_dict_space(8, k=3), d1=4, d2=4, hidden=(16,))
    assert ext.features_dim == 3 + 16
    ego = torch.tensor([[0.1, -0.2, 0.3]])
    others = _t(_rows(2, 8, seed=9))
    out = ext({"ego": ego, "others": others})
    assert out.shape == (1, 19)
    torch.testing.assert_close(out[:, :3], ego)
    torch.testing.assert_close(out[:, 3:], ext.encoder(others))
    # weights transfer to a dict space with another max_rows
    ext12 = SetFeaturesExtractor(_dict_space(12, k=3), d1=4, d2=4, hidden=(16,))
    ext12.load_state_dict(ext.state_dict())
    out12 = ext12({"ego": ego, "others": _t(_pad(_rows(2, 8, seed=9), 12))})
    torch.testing.assert_close(out12, out, atol=ATOL, rtol=0)


def test_extractor_rejects_bad_spaces():
    with pytest.raises(ValueError):
        SetFeaturesExtractor(spaces.Box(-1, 1, shape=(5,)))
    with pytest.raises(ValueError):
        SetFeaturesExtractor(spaces.Dict({"ego": spaces.Box(-1, 1, shape=(2,))}))
    with pytest.raises(ValueError):
        SetFeaturesExtractor(spaces.Discrete(3))


# --------------------------------------------------------------------------- SB3 integration


class _SetEnv(gym.Env):
    """Tiny env: random set observations with a random number of present rows."""

    def __init__(self, max_rows: int = 6, discrete: bool = True, use_dict: bool = False, ep_len: int = 20):
        super().__init__()
        self.max_rows, self.use_dict, self.ep_len = max_rows, use_dict, ep_len
        others = _others_space(max_rows)
        self.observation_space = _dict_space(max_rows, k=2) if use_dict else others
        self.action_space = spaces.Discrete(9) if discrete else spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
        self._t = 0

    def _obs(self):
        n = int(self.np_random.integers(0, self.max_rows + 1))
        rows = np.zeros((self.max_rows, F), dtype=np.float32)
        rows[:n, :4] = self.np_random.normal(size=(n, 4)).astype(np.float32)
        rows[:n, 4] = 1.0
        rows = rows[self.np_random.permutation(self.max_rows)]
        if self.use_dict:
            return {"ego": self.np_random.normal(size=2).astype(np.float32), "others": rows}
        return rows

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self._t = 0
        return self._obs(), {}

    def step(self, action):
        self._t += 1
        reward = float(-np.sum(np.square(np.asarray(action, dtype=np.float32) - 0.5)) * 0.01)
        return self._obs(), reward, False, self._t >= self.ep_len, {}


_ALGOS = ["DQN", "DDPG", "SAC", "TD3", "PPO"]


@pytest.mark.parametrize("use_dict", [False, True], ids=["box", "dict"])
@pytest.mark.parametrize("algo", _ALGOS)
def test_sb3_training_and_predict(algo, use_dict):
    import stable_baselines3 as sb3

    torch.manual_seed(0)
    discrete = algo in ("DQN", "PPO")
    env = _SetEnv(max_rows=6, discrete=discrete, use_dict=use_dict)
    policy_kwargs = dict(
        features_extractor_class=SetFeaturesExtractor,
        features_extractor_kwargs=dict(d1=4, d2=4, hidden=(16,)),
        net_arch=[32],
    )
    kwargs: dict = dict(policy_kwargs=policy_kwargs, seed=0, device="cpu", verbose=0)
    if algo == "PPO":
        kwargs.update(n_steps=64, batch_size=32, n_epochs=1)
    else:
        kwargs.update(learning_starts=50, batch_size=32, buffer_size=1000)
    if algo == "DQN":
        kwargs.update(target_update_interval=50)
    policy = "MultiInputPolicy" if use_dict else "MlpPolicy"
    model = getattr(sb3, algo)(policy, env, **kwargs)
    model.learn(total_timesteps=200 if algo != "PPO" else 128)

    obs, _ = env.reset(seed=1)
    action, _ = model.predict(obs, deterministic=True)
    assert env.action_space.contains(np.asarray(action).astype(env.action_space.dtype).reshape(env.action_space.shape))
    # the policy's extractor is ours
    extractors = [m for m in model.policy.modules() if isinstance(m, SetFeaturesExtractor)]
    assert extractors

    # same trained weights, deployed on an env with more padding rows
    big = _SetEnv(max_rows=15, discrete=discrete, use_dict=use_dict)
    cls = getattr(sb3, algo)
    model_big = cls(policy, big, **kwargs)
    model_big.policy.load_state_dict(model.policy.state_dict())
    if use_dict:
        obs_big = {"ego": obs["ego"], "others": _pad(obs["others"], 15)}
    else:
        obs_big = _pad(obs, 15)
    action_big, _ = model_big.predict(obs_big, deterministic=True)
    np.testing.assert_allclose(np.asarray(action_big), np.asarray(action), atol=1e-5)


# --------------------------------------------------------------------------- named configurations (specification §5)


def _paper(seed: int = 0) -> SetEncoder:
    torch.manual_seed(seed)
    enc = SetEncoder(in_features=4, **encoder_kwargs("paper"))
    enc.eval()
    return enc


def test_named_configurations_and_unknown_name():
    assert ENCODER_NAMES == ("small", "paper")
    assert encoder_kwargs("small") == {"d1": 8, "d2": 8, "hidden": (64,), "pool_over": "rows",
                                       "presence_input": False, "feature_dim": None}
    encoder_kwargs("paper")["d1"] = 1  # a copy: the preset is not changed
    assert PRESETS["paper"]["d1"] == 256
    for bad in ("big", "", None):
        with pytest.raises(ConfigError, match="valid: small, paper"):
            encoder_kwargs(bad)
    with pytest.raises(ConfigError, match="valid: small, paper"):
        SetFeaturesExtractor(_dict_space(8), encoder="Paper")


def test_config_and_cli_offer_the_same_names():
    from lanefree_sumo.cli import build_parser
    from lanefree_sumo.config import LaneFreeConfig, ObservationConfig, merge_config

    assert get_args(get_type_hints(ObservationConfig)["encoder"]) == ENCODER_NAMES
    assert LaneFreeConfig().observation.encoder == "small"
    with pytest.raises(ConfigError, match="valid: small, paper"):
        merge_config(LaneFreeConfig(), {"observation": {"encoder": "large"}})
    args = build_parser().parse_args(["train", "--obs", "set", "--encoder", "paper"])
    assert args.encoder == "paper"
    assert build_parser().parse_args(["train"]).encoder == "small"


def test_small_is_the_previous_default():
    torch.manual_seed(0)
    enc = SetEncoder(in_features=4, **encoder_kwargs("small"))
    assert enc.out_dim == 64 and isinstance(enc.feature, torch.nn.Identity)
    assert [type(m) for m in enc.f1] == [torch.nn.Linear, torch.nn.ReLU, torch.nn.Linear, torch.nn.ReLU]
    assert (enc.f1[0].in_features, enc.f1[0].out_features, enc.f1[2].out_features) == (4, 64, 8)
    # same parameters (names and shapes) as SetEncoder's defaults: old checkpoints still load
    default = SetEncoder(in_features=4)
    assert {k: v.shape for k, v in default.state_dict().items()} == {k: v.shape for k, v in enc.state_dict().items()}


def test_paper_layers_are_table_1():
    enc = _paper()
    for f in (enc.f1, enc.f2):  # ONE 5→256 linear layer with ReLU each
        assert [type(m) for m in f] == [torch.nn.Linear, torch.nn.ReLU]
        assert (f[0].in_features, f[0].out_features) == (5, 256)
    assert enc.pooled_dim == 256 and isinstance(enc.norm, torch.nn.LayerNorm)
    assert [type(m) for m in enc.feature] == [torch.nn.Linear, torch.nn.ReLU]
    assert (enc.feature[0].in_features, enc.feature[0].out_features) == (256, 256)
    assert enc.out_dim == 256


def test_paper_intermediate_outputs():
    enc = _paper()
    x = torch.as_tensor(np.stack([_rows(3, 8, seed=1), _rows(6, 8, seed=2)]))
    with torch.no_grad():
        y = enc.matrix(x)
        pooled = enc.pooled(x)
        out = enc(x)
    assert y.shape == (2, 256, 256)
    # Y by hand: mean over the present rows of f1(x_i)ᵀ f2(x_i), presence (= 1) being the 5th input
    rows = x[0, :3]
    manual = torch.einsum("nd,ne->de", enc.f1(rows), enc.f2(rows)) / 3
    torch.testing.assert_close(y[0], manual, atol=1e-5, rtol=1e-4)
    # pooling = mean over the d1 axis of Y (computed without forming Y in forward)
    assert pooled.shape == (2, 256)
    torch.testing.assert_close(pooled, y.mean(dim=-2), atol=1e-6, rtol=1e-4)
    with torch.no_grad():
        torch.testing.assert_close(out, enc.feature(enc.norm(pooled)))
    assert out.shape == (2, 256) and (out >= 0).all()  # ReLU feature layer


def test_paper_permutation_and_padding_invariance():
    enc = _paper()
    obs = _rows(4, 10, seed=3)
    with torch.no_grad():
        base = enc(_t(obs))
        rng = np.random.default_rng(4)
        for _ in range(5):
            torch.testing.assert_close(enc(_t(obs[rng.permutation(10)])), base, atol=ATOL, rtol=0)
        for rows in (4, 32, 64):
            torch.testing.assert_close(enc(_t(_pad(obs[:4], rows))), base, atol=ATOL, rtol=0)
        junk = obs.copy()
        junk[4:, :4] = 77.0
        torch.testing.assert_close(enc(_t(junk)), base, atol=ATOL, rtol=0)
        assert torch.isfinite(enc(torch.zeros(2, 8, F))).all()


def test_paper_extractor_transfers_across_max_rows():
    torch.manual_seed(0)
    ext8 = SetFeaturesExtractor(_dict_space(8, k=4), encoder="paper")
    ext40 = SetFeaturesExtractor(_dict_space(40, k=4), encoder="paper")
    assert ext8.features_dim == ext40.features_dim == 4 + 256
    ext40.load_state_dict(ext8.state_dict())
    ego = torch.tensor([[0.1, -0.2, 0.3, 0.4]])
    others = _rows(5, 8, seed=5)
    with torch.no_grad():
        out8 = ext8({"ego": ego, "others": _t(others)})
        out40 = ext40({"ego": ego, "others": _t(_pad(others, 40))})
    torch.testing.assert_close(out40, out8, atol=ATOL, rtol=0)
    torch.testing.assert_close(out8[:, :4], ego)


def _paper_extractors(model) -> list[SetFeaturesExtractor]:
    extractors = [m for m in model.policy.modules() if isinstance(m, SetFeaturesExtractor)]
    assert extractors and all(e.encoder_name == "paper" and e.encoder.out_dim == 256 for e in extractors)
    return extractors


@pytest.mark.sumo
@pytest.mark.slow
def test_cli_trains_ddpg_with_the_paper_encoder(tmp_path):
    """``lanefree train --obs set --encoder paper``: a real 2-episode DDPG run whose saved model
    holds the paper's encoder."""
    import yaml
    from stable_baselines3 import DDPG

    from conftest import lanefree

    run = tmp_path / "run"
    proc = lanefree("train", "--algo", "ddpg", "--obs", "set", "--encoder", "paper", "--episodes", "2",
                    "--episode-steps", "50", "--out", str(run), timeout=120)
    assert proc.returncode == 0, proc.stderr
    observation = yaml.safe_load((run / "config.yaml").read_text())["observation"]
    assert (observation["kind"], observation["encoder"]) == ("set", "paper")
    model = DDPG.load(run / "model.zip", device="cpu")
    _paper_extractors(model)
    assert model.policy.actor.features_extractor.encoder.f1[0].weight.shape == (256, 5)


@pytest.mark.sumo
@pytest.mark.slow
def test_ddpg_learning_updates_the_paper_encoder(tmp_path):
    """Two short DDPG episodes with learning from step 50: the encoder's weights change between
    the first checkpoint and the end (the CLI cannot lower learning_starts, so this uses train())."""
    from stable_baselines3 import DDPG

    from lanefree_sumo.config import LaneFreeConfig, merge_config
    from lanefree_sumo.experiments.runners.train import train

    from conftest import TINY_TRAINING

    cfg = merge_config(LaneFreeConfig(), {**TINY_TRAINING, "observation": {"kind": "set", "encoder": "paper"},
                                          "train": {**TINY_TRAINING["train"], "algo": "ddpg"}})
    run, done = train(cfg, run=tmp_path / "run", progress=False)
    assert done == 2
    first = DDPG.load(run / "checkpoints" / "ep_00001" / "model.zip", device="cpu")
    last = DDPG.load(run / "model.zip", device="cpu")
    w_first, w_last = (_paper_extractors(m)[0].encoder.feature[0].weight for m in (first, last))
    assert torch.isfinite(w_last).all() and not torch.equal(w_first, w_last)

"""Tests for lanefree_sumo.rl.encoder (set encoder of Liu, Zhang & Zhou 2023, SPEC §5)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium import spaces

from lanefree_sumo.rl.encoder import SetEncoder, SetFeaturesExtractor

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

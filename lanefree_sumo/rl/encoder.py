"""Permutation-invariant encoder for variable-size *set* observations (SPEC §5).

Source followed
---------------
Liu, Zhang & Zhou (2023), "Vehicle Simulation Algorithm for Observations with
Variable Dimensions Based on Deep Reinforcement Learning", Electronics 12, 5029
(``/work/shared/seeds/004_6d9c0ce92b74d570.txt``):

* §3.1 and Figure 1: an observation ``obs ∈ R^{n × dim_fixed}`` (n = number of
  observed vehicles, variable) is mapped row-wise by two encoders
  ``f1: R^{dim_fixed} → R^{dim1}`` and ``f2: R^{dim_fixed} → R^{dim2}``; the
  result is ``f_final(obs) = f1(obs)ᵀ × f2(obs) ∈ R^{dim1 × dim2}``, whose shape
  does not depend on n. It is then passed through a *pooling* layer and a
  *normalisation* layer which "standardizes the vector after pooling" because
  "the value of the output feature matrix increases as the dimension of the
  input observation increases".
* Algorithm 1, steps 2–3: ``y1, y2 = f1(obs), f2(obs)``;
  ``y_fix = y1ᵀ y2``; ``y_in = Norm(POOL_mean(y_fix))``.
* Table 1: f1 and f2 are each a single ``5 × 256`` linear layer followed by a
  ReLU (so by default the row encoders end with a ReLU here too).
* The downstream "feature extraction layer" (one linear layer + ReLU) and
  "evaluation & decision layer" (MLP) of §3.2 are *not* part of this module:
  they are provided by the SB3 policy's ``net_arch`` on top of the features.

Choices where the paper is silent or ambiguous (documented here)
-----------------------------------------------------------------
* **Padding / mask.** Gymnasium spaces have fixed shapes, so the set is padded
  to ``max_rows`` rows; the LAST column is a presence flag (1 = real vehicle,
  0 = padding). The presence column is *not* fed to f1/f2 (the paper's
  highway-env input of width 5 contained it); instead it is used as a mask
  (``presence > 0.5``) so padding rows contribute exactly nothing, even though
  ``f(0) ≠ 0`` in general because of biases:
  ``Y = Σ_i m_i · f1(x_i)ᵀ f2(x_i)``  (d1 × d2).
* **Mean pooling** = divide the masked sum by the number of present rows
  ``n = Σ_i m_i`` (clamped to ≥ 1, so an empty set gives ``Y = 0``, never NaN).
  This is exactly the row-count dependence that the paper wants removed, and it
  makes the output invariant to row order and to the amount of padding. Note
  Algorithm 1 writes ``POOL_mean(y_fix) ∈ R^{dim_in}``, which reads as an
  additional mean over one axis of the ``dim_in × dim_in`` matrix; that variant
  is available with ``pool_over="rows+d1"`` (output dim ``d2``); the default
  ``pool_over="rows"`` keeps the whole flattened matrix (output ``d1·d2``).
* **Normalisation** (paper: "standardize the vector") — default ``"layernorm"``
  (``torch.nn.LayerNorm`` over the flattened, pooled vector, learnable affine),
  alternatives ``"l2"`` (unit Euclidean norm, eps-guarded) and ``"none"``. With
  an empty set the pooled vector is 0 and LayerNorm returns its bias (a learned
  "no vehicle" embedding), still finite.
* Row MLP hidden sizes are configurable (``hidden``; ``()`` = the paper's single
  linear layer). Defaults are small (d1 = d2 = 8, hidden = (64,)) rather than
  the paper's 256 × 256 = 65 536-dimensional matrix.
* The weights never depend on ``max_rows``: the same module (or the same
  ``state_dict``) runs on inputs with any number of rows.

Public API
----------
``SetEncoder``             torch module: (..., N, f) with presence last -> (..., out_dim)
``SetFeaturesExtractor``   SB3 ``BaseFeaturesExtractor`` for a Box (N, f) or a
                           Dict {"ego": Box(k,), "others": Box(N, f)} space;
                           output = concat(ego passthrough, encoder features).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import gymnasium as gym
import torch
from gymnasium import spaces
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

__all__ = ["SetEncoder", "SetFeaturesExtractor", "row_mlp"]

_ACTIVATIONS: dict[str, type[nn.Module]] = {
    "relu": nn.ReLU,
    "tanh": nn.Tanh,
    "elu": nn.ELU,
    "gelu": nn.GELU,
}


def _activation(name: str | type[nn.Module]) -> type[nn.Module]:
    if isinstance(name, str):
        try:
            return _ACTIVATIONS[name.lower()]
        except KeyError as exc:
            raise ValueError(f"unknown activation {name!r}; choose from {sorted(_ACTIVATIONS)}") from exc
    return name


def row_mlp(
    in_features: int,
    hidden: Sequence[int],
    out_features: int,
    activation: str | type[nn.Module] = "relu",
    out_activation: bool = True,
) -> nn.Sequential:
    """MLP applied independently to every row (``nn.Linear`` acts on the last dim)."""
    act = _activation(activation)
    layers: list[nn.Module] = []
    prev = in_features
    for h in hidden:
        layers += [nn.Linear(prev, int(h)), act()]
        prev = int(h)
    layers.append(nn.Linear(prev, out_features))
    if out_activation:
        layers.append(act())
    return nn.Sequential(*layers)


class SetEncoder(nn.Module):
    """Paper §3.1 encoder: ``Norm(mean_rows(f1(X)ᵀ f2(X)))`` with a presence mask.

    :param in_features: number of per-row features WITHOUT the presence column
        (e.g. 4 for ``[dx, dy, vx, vy, presence]`` rows).
    :param d1: output width of f1 (rows of Y).
    :param d2: output width of f2 (columns of Y).
    :param hidden: hidden layer sizes of both row MLPs (``()`` = one linear layer,
        as in the paper's Table 1).
    :param activation: hidden activation ("relu", "tanh", "elu", "gelu" or an nn.Module class).
    :param out_activation: apply the activation after the last layer of f1/f2
        (paper Table 1: ReLU). Default True.
    :param norm: "layernorm" (default), "l2" or "none".
    :param pool_over: "rows" (default, output ``d1*d2``) or "rows+d1" (also mean
        over the d1 axis as literally written in Algorithm 1, output ``d2``).
    :param presence_threshold: a row is present iff its presence value > threshold.

    ``forward(x, mask=None)``: if ``mask`` is None, ``x`` has shape
    ``(..., N, in_features + 1)`` with the presence flag as LAST column; otherwise
    ``x`` is ``(..., N, in_features)`` and ``mask`` is ``(..., N)`` (bool or 0/1).
    Any number of leading batch dims (including none) and any N (including 0).
    """

    def __init__(
        self,
        in_features: int = 4,
        d1: int = 8,
        d2: int = 8,
        hidden: Sequence[int] = (64,),
        activation: str | type[nn.Module] = "relu",
        out_activation: bool = True,
        norm: str = "layernorm",
        pool_over: str = "rows",
        presence_threshold: float = 0.5,
    ) -> None:
        super().__init__()
        if in_features < 1 or d1 < 1 or d2 < 1:
            raise ValueError("in_features, d1 and d2 must be >= 1")
        if pool_over not in ("rows", "rows+d1"):
            raise ValueError(f"pool_over must be 'rows' or 'rows+d1', got {pool_over!r}")
        norm = norm.lower()
        if norm not in ("layernorm", "l2", "none"):
            raise ValueError(f"norm must be 'layernorm', 'l2' or 'none', got {norm!r}")
        self.in_features = int(in_features)
        self.d1 = int(d1)
        self.d2 = int(d2)
        self.pool_over = pool_over
        self.norm_kind = norm
        self.presence_threshold = float(presence_threshold)
        self.f1 = row_mlp(self.in_features, hidden, self.d1, activation, out_activation)
        self.f2 = row_mlp(self.in_features, hidden, self.d2, activation, out_activation)
        self.out_dim = self.d1 * self.d2 if pool_over == "rows" else self.d2
        self.norm: nn.Module = nn.LayerNorm(self.out_dim) if norm == "layernorm" else nn.Identity()

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        if mask is None:
            if x.shape[-1] != self.in_features + 1:
                raise ValueError(
                    f"expected rows of width {self.in_features + 1} (features + presence), got {x.shape[-1]}"
                )
            feats = x[..., :-1]
            m = (x[..., -1] > self.presence_threshold).to(x.dtype)
        else:
            if x.shape[-1] != self.in_features:
                raise ValueError(f"expected rows of width {self.in_features}, got {x.shape[-1]}")
            feats = x
            m = (mask > self.presence_threshold).to(x.dtype) if mask.dtype != torch.bool else mask.to(x.dtype)
        # Zero the padding rows' inputs too (padding is zeros anyway; this also
        # protects against garbage/NaN in padded slots leaking through 0 * NaN).
        feats = torch.where(m.unsqueeze(-1) > 0, feats, torch.zeros_like(feats))
        y1 = self.f1(feats) * m.unsqueeze(-1)  # (..., N, d1), padding rows -> 0
        y2 = self.f2(feats)  # (..., N, d2)
        y = torch.einsum("...nd,...ne->...de", y1, y2)  # Σ_i m_i f1(x_i)ᵀ f2(x_i): (..., d1, d2)
        n = m.sum(dim=-1).clamp(min=1.0)  # number of present rows, ≥ 1 (empty set -> Y = 0)
        y = y / n[..., None, None]  # mean pooling over rows
        if self.pool_over == "rows+d1":
            y = y.mean(dim=-2)  # (..., d2)
        else:
            y = y.flatten(start_dim=-2)  # (..., d1*d2)
        if self.norm_kind == "l2":
            y = y / y.norm(dim=-1, keepdim=True).clamp(min=1e-6)
        return self.norm(y)


class SetFeaturesExtractor(BaseFeaturesExtractor):
    """SB3 features extractor around :class:`SetEncoder`.

    Accepts either
      * ``spaces.Box`` of shape ``(max_rows, f)`` (others only; last column = presence), or
      * ``spaces.Dict`` with a set key (default ``"others"``, Box ``(max_rows, f)``)
        plus any other Box keys (typically ``"ego"``, shape ``(k,)``) which are
        flattened and passed through unchanged (in sorted key order).

    Output = ``concat(passthrough keys, SetEncoder(others))``; ``features_dim`` is
    ``k + d1*d2`` (or ``k + d2`` with ``pool_over="rows+d1"``) and does not depend on
    ``max_rows``, so a ``state_dict`` trained with one ``max_rows`` loads into an
    extractor (or policy) built for another.

    Usage::

        policy_kwargs = dict(features_extractor_class=SetFeaturesExtractor,
                             features_extractor_kwargs=dict(d1=8, d2=8, hidden=(64,)))
        DQN("MlpPolicy", env, policy_kwargs=policy_kwargs)          # Box obs
        SAC("MultiInputPolicy", env, policy_kwargs=policy_kwargs)   # Dict obs

    Remaining keyword arguments (``activation``, ``out_activation``, ``norm``,
    ``pool_over``, ``presence_threshold``) are forwarded to :class:`SetEncoder`.
    """

    def __init__(
        self,
        observation_space: gym.Space,
        d1: int = 8,
        d2: int = 8,
        hidden: Sequence[int] = (64,),
        set_key: str = "others",
        **encoder_kwargs,
    ) -> None:
        if isinstance(observation_space, spaces.Dict):
            if set_key not in observation_space.spaces:
                raise ValueError(f"Dict observation space has no set key {set_key!r}: {list(observation_space.spaces)}")
            set_space = observation_space[set_key]
            pass_keys = sorted(k for k in observation_space.spaces if k != set_key)
            pass_dim = 0
            for k in pass_keys:
                sp = observation_space[k]
                if not isinstance(sp, spaces.Box):
                    raise ValueError(f"passthrough key {k!r} must be a Box, got {sp}")
                pass_dim += int(math.prod(sp.shape))
        elif isinstance(observation_space, spaces.Box):
            set_space = observation_space
            pass_keys = []
            pass_dim = 0
        else:
            raise ValueError(f"SetFeaturesExtractor needs a Box or Dict observation space, got {observation_space}")
        if not isinstance(set_space, spaces.Box) or len(set_space.shape) != 2 or set_space.shape[1] < 2:
            raise ValueError(f"set observation must be a Box of shape (max_rows, f>=2), got {set_space}")
        encoder = SetEncoder(in_features=set_space.shape[1] - 1, d1=d1, d2=d2, hidden=hidden, **encoder_kwargs)
        super().__init__(observation_space, features_dim=pass_dim + encoder.out_dim)
        self.encoder = encoder
        self.set_key = set_key
        self.pass_keys = list(pass_keys)
        self.is_dict = isinstance(observation_space, spaces.Dict)

    def forward(self, observations: torch.Tensor | dict[str, torch.Tensor]) -> torch.Tensor:
        if not self.is_dict:
            return self.encoder(observations)
        others = observations[self.set_key]
        parts = [observations[k].reshape(others.shape[0], -1) for k in self.pass_keys]
        parts.append(self.encoder(others))
        return torch.cat(parts, dim=-1)

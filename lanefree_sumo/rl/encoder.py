"""Permutation-invariant encoder for variable-size *set* observations (specification §5).

Source followed
---------------
Liu, Zhang & Zhou (2023), "Vehicle Simulation Algorithm for Observations with
Variable Dimensions Based on Deep Reinforcement Learning", Electronics 12, 5029
(doi:10.3390/electronics12245029):

* §3.1 and Figure 1: an observation ``obs ∈ R^{n × dim_fixed}`` (n = number of
  observed vehicles, variable) is mapped row-wise by two encoders
  ``f1: R^{dim_fixed} → R^{dim1}`` and ``f2: R^{dim_fixed} → R^{dim2}``; the
  result ``f1(obs)ᵀ × f2(obs) ∈ R^{dim1 × dim2}`` has a shape independent of n.
  It then goes through a *pooling* layer ("to reduce the dimension of the
  output") and a *normalisation* layer that "standardizes the vector after
  pooling", because "the value of the output feature matrix increases as the
  dimension of the input observation increases".
* Algorithm 1, steps 2–4: ``y1, y2 = f1(obs), f2(obs) ∈ R^{n × dim_in}``;
  ``y_fix = y1ᵀ y2 ∈ R^{dim_in × dim_in}``;
  ``y_in = Norm(POOL_mean(y_fix)) ∈ R^{dim_in}``;
  ``y_out = f_feature(y_in) ∈ R^{dim_out}``.
* Table 1: f1 and f2 are each ONE ``5 × 256`` linear layer with ReLU; the
  feature extraction layer ``f_feature`` is ``256 × 256`` with ReLU; the
  decision layer ``256 × 5`` (that one is the SB3 policy head, not this module).
  The 5 inputs are the paper's per-vehicle state ``[x, y, vx, vy, presence]``
  (§4: "The presence element is a special mask … set to 0 to indicate that the
  corresponding observation is invalid"), i.e. presence was a network input.

Named configurations (:data:`PRESETS`, :func:`encoder_kwargs`)
--------------------------------------------------------------
``paper`` — Table 1 / Alg. 1 as written: f1, f2 = ``Linear(5→256) + ReLU``
  (the 5 inputs are dx, dy, vx, vy AND presence), ``Y ∈ R^{256×256}``, mean
  over the present rows, mean over the d1 axis of Y → 256-vector, LayerNorm,
  then ``f_feature = Linear(256→256) + ReLU``. Output 256.
``small`` — the PROJECT'S OWN default, not the paper's: f1, f2 =
  ``Linear(4→64) + ReLU + Linear(64→8) + ReLU`` on dx, dy, vx, vy only,
  ``Y ∈ R^{8×8}`` averaged over present rows and kept whole (flattened to 64
  features, no axis pooling), LayerNorm, no feature layer (the policy's
  ``net_arch`` follows directly). Output 64. Chosen as cheap and because it
  keeps all of Y; its training cost against ``paper`` is measured in README.md.

Decisions where the paper is silent or where we deviate (documented)
--------------------------------------------------------------------
* **Presence is a mask** (deviation, for padding invariance). Gymnasium spaces
  have fixed shapes, so the set is padded to ``max_rows`` rows with the LAST
  column = presence (1 = real vehicle, 0 = padding). In the paper the padding
  rows (all zeros, presence 0) go through f1/f2 like real rows, and since
  ``f(0) = ReLU(b) ≠ 0`` each padding row adds ``ReLU(b1)ᵀReLU(b2)`` to Y: the
  output would depend on the amount of padding. Here rows with presence ≤ 0.5
  contribute exactly nothing: ``Y = (1/n) Σ_i m_i f1(x_i)ᵀ f2(x_i)``.
* **Presence as input** (``presence_input``). With the mask, the presence seen
  by f1/f2 is 1 on every row that counts, so its weight column only adds a
  second bias: ``Linear(5→256)`` on ``[x, 1]`` is the same function class as
  ``Linear(4→256)`` on ``x``. ``paper`` keeps the 5-wide input anyway so the
  layer is exactly Table 1's ``5 × 256`` (and the parameter count matches);
  ``small`` feeds the 4 real features (as it always did, so its checkpoints
  still load). The value fed is the binarised mask, not the raw column.
* **Mean pooling over rows** = divide the masked sum by ``n = Σ_i m_i``
  (clamped to ≥ 1: an empty set gives ``Y = 0``, never NaN). This removes the
  growth with n the paper complains about and makes the output independent of
  row order and padding. The same weights run with any ``max_rows``.
* **Which axis of Y is pooled** (``pool_over="rows+d1"``, used by ``paper``):
  Alg. 1 writes ``POOL_mean(y_fix) ∈ R^{dim_in}`` for a ``dim_in × dim_in``
  matrix, so one axis is averaged; the paper does not say which. We average
  over the d1 axis (the f1 side) and keep the f2 side:
  ``v_b = mean_a Y_ab = (1/n) Σ_i m_i s(x_i) f2(x_i)_b`` with the scalar
  ``s(x) = mean_a f1(x)_a ≥ 0``. The other axis is the same function class
  with f1 and f2 swapped (identical architecture, independent init), so the
  choice is immaterial. Note what the literal reading implies: after this
  pooling, f1 only contributes one non-negative weight per vehicle, so the
  pooled vector is a weighted mean of f2 over the vehicles. The identity above
  is also how it is computed — the 256×256 matrix is never formed in
  :meth:`SetEncoder.forward` (same result to float rounding, d1·d2/(d1+d2) = 128× fewer
  multiply-adds); :meth:`SetEncoder.matrix` returns the explicit Y for checks.
* **Normalisation**: ``torch.nn.LayerNorm`` over the pooled vector (zero mean,
  unit variance per sample = "standardize the vector", learnable affine);
  ``"l2"`` and ``"none"`` are available. With an empty set LayerNorm returns its
  bias (a learned "no vehicle" embedding), still finite.

Public API
----------
* ``PRESETS`` / ``ENCODER_NAMES`` / ``encoder_kwargs(name)``: named configurations.
* ``SetEncoder``: torch module, (..., N, f) with presence last -> (..., out_dim).
* ``SetFeaturesExtractor``: SB3 ``BaseFeaturesExtractor`` for a Box (N, f) or a Dict {"ego": Box(k,), "others":
  Box(N, f)} space; output = concat(ego passthrough, encoder features).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import torch
from gymnasium import spaces
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

from lanefree_sumo.errors import ConfigError

__all__ = ["ENCODER_NAMES", "PRESETS", "SetEncoder", "SetFeaturesExtractor", "encoder_kwargs", "row_mlp"]

PRESETS: dict[str, dict[str, Any]] = {
    # The project's own choice (not the paper's): small and keeps the whole 8×8 matrix.
    "small": {"d1": 8, "d2": 8, "hidden": (64,), "pool_over": "rows", "presence_input": False, "feature_dim": None},
    # Liu et al. (2023) Table 1 / Alg. 1: f1, f2 = Linear(5→256)+ReLU, mean over one axis, f_feature 256×256 ReLU.
    "paper": {"d1": 256, "d2": 256, "hidden": (), "pool_over": "rows+d1", "presence_input": True, "feature_dim": 256},
}
"""Named encoder configurations (keyword arguments of :class:`SetEncoder`)."""

ENCODER_NAMES: tuple[str, ...] = tuple(PRESETS)


def encoder_kwargs(name: str) -> dict[str, Any]:
    """A copy of the keyword arguments of the named configuration; ConfigError if unknown."""
    try:
        return dict(PRESETS[name])
    except (KeyError, TypeError):
        raise ConfigError(f"unknown set encoder {name!r}; valid: {', '.join(ENCODER_NAMES)}") from None


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
    """Paper §3.1 encoder: ``f_feature(Norm(pool(mean_rows(f1(X)ᵀ f2(X)))))`` with a presence mask.

    Defaults are the ``small`` configuration; ``SetEncoder(**encoder_kwargs("paper"))``
    builds the paper's.

    :param in_features: number of per-row features WITHOUT the presence column
        (4 for ``[dx, dy, vx, vy, presence]`` rows).
    :param d1: output width of f1 (rows of Y).
    :param d2: output width of f2 (columns of Y).
    :param hidden: hidden layer sizes of both row MLPs (``()`` = one linear layer,
        as in the paper's Table 1).
    :param activation: activation ("relu", "tanh", "elu", "gelu" or an nn.Module class).
    :param out_activation: apply the activation after the last layer of f1/f2
        (paper Table 1: ReLU). Default True.
    :param norm: "layernorm" (default), "l2" or "none".
    :param pool_over: "rows" (output ``d1*d2``, Y kept whole) or "rows+d1" (also
        mean over the d1 axis, as in Algorithm 1; output ``d2``).
    :param presence_input: also feed the (binarised) presence to f1/f2, which then
        take ``in_features + 1`` inputs (the paper's 5 × 256).
    :param feature_dim: if set, a ``Linear(pooled → feature_dim) + activation``
        feature layer follows the normalisation (the paper's ``f_feature``).
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
        presence_input: bool = False,
        feature_dim: int | None = None,
        presence_threshold: float = 0.5,
    ) -> None:
        super().__init__()
        if in_features < 1 or d1 < 1 or d2 < 1 or (feature_dim is not None and feature_dim < 1):
            raise ValueError("in_features, d1, d2 and feature_dim must be >= 1")
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
        self.presence_input = bool(presence_input)
        self.presence_threshold = float(presence_threshold)
        row_in = self.in_features + int(self.presence_input)
        self.f1 = row_mlp(row_in, hidden, self.d1, activation, out_activation)
        self.f2 = row_mlp(row_in, hidden, self.d2, activation, out_activation)
        self.pooled_dim = self.d1 * self.d2 if pool_over == "rows" else self.d2
        self.norm: nn.Module = nn.LayerNorm(self.pooled_dim) if norm == "layernorm" else nn.Identity()
        self.feature: nn.Module = nn.Identity()
        if feature_dim is not None:
            self.feature = nn.Sequential(nn.Linear(self.pooled_dim, int(feature_dim)), _activation(activation)())
        self.out_dim = self.pooled_dim if feature_dim is None else int(feature_dim)

    def _features_and_mask(self, x: torch.Tensor, mask: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """``(features, m)``: the row features (padding rows zeroed) and the presence mask as 0/1."""
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
        return torch.where(m.unsqueeze(-1) > 0, feats, torch.zeros_like(feats)), m

    def _rows(self, x: torch.Tensor, mask: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(m·f1(X), f2(X), n)``: row encodings of every row (padding rows of y1 zeroed) and present-row
        counts."""
        feats, m = self._features_and_mask(x, mask)
        if self.presence_input:
            feats = torch.cat([feats, m.unsqueeze(-1)], dim=-1)
        y1 = self.f1(feats) * m.unsqueeze(-1)  # (..., N, d1), padding rows -> 0
        y2 = self.f2(feats)  # (..., N, d2)
        n = m.sum(dim=-1).clamp(min=1.0)  # number of present rows, ≥ 1 (empty set -> Y = 0)
        return y1, y2, n

    def matrix(self, x: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """The explicit ``Y = (1/n) Σ_i m_i f1(x_i)ᵀ f2(x_i)``, shape ``(..., d1, d2)``."""
        y1, y2, n = self._rows(x, mask)
        return torch.einsum("...nd,...ne->...de", y1, y2) / n[..., None, None]

    def pooled(self, x: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """Y after pooling, before normalisation: ``(..., pooled_dim)``.

        Only the present rows go through f1 and f2: they are gathered from the whole batch, encoded, and
        summed back per set (``index_add``), so the cost follows the vehicles observed, not ``max_rows``
        (the padding contributes nothing either way; the result equals :meth:`matrix`'s up to float
        rounding)."""
        feats, m = self._features_and_mask(x, mask)
        lead, rows = feats.shape[:-2], feats.shape[-2]
        sets_total = math.prod(lead)
        flat_feats = feats.reshape(sets_total, rows, feats.shape[-1])
        present = m.reshape(sets_total, rows) > 0
        sets, slots = present.nonzero(as_tuple=True)
        picked = flat_feats[sets, slots]
        if self.presence_input:
            picked = torch.cat([picked, torch.ones_like(picked[:, :1])], dim=-1)
        y1, y2 = self.f1(picked), self.f2(picked)
        if self.pool_over == "rows":
            per_row = (y1.unsqueeze(-1) * y2.unsqueeze(-2)).flatten(start_dim=-2)
        else:  # mean over the d1 axis of Y without forming it: mean_a Σ_i y1_ia y2_ib = Σ_i (mean_a y1_ia) y2_ib
            per_row = y1.mean(dim=-1, keepdim=True) * y2
        total = torch.zeros(sets_total, self.pooled_dim, dtype=per_row.dtype, device=per_row.device)
        total = total.index_add(0, sets, per_row)
        n = present.sum(dim=-1).clamp(min=1).to(total.dtype)
        return (total / n[:, None]).reshape(*lead, self.pooled_dim)

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        y = self.pooled(x, mask)
        if self.norm_kind == "l2":
            y = y / y.norm(dim=-1, keepdim=True).clamp(min=1e-6)
        return self.feature(self.norm(y))


class SetFeaturesExtractor(BaseFeaturesExtractor):
    """SB3 features extractor around :class:`SetEncoder`.

    Accepts either
      * ``spaces.Box`` of shape ``(max_rows, f)`` (others only; last column = presence), or
      * ``spaces.Dict`` with a set key (default ``"others"``, Box ``(max_rows, f)``)
        plus any other Box keys (typically ``"ego"``, shape ``(k,)``) which are
        flattened and passed through unchanged (in sorted key order).

    :param encoder: name of the configuration in :data:`PRESETS` (``"small"``
        default, ``"paper"``); unknown names raise ConfigError naming the valid ones.
    :param overrides: any :class:`SetEncoder` keyword (``d1``, ``d2``, ``hidden``,
        ``norm``, …) replacing the named configuration's value.

    Output = ``concat(passthrough keys, SetEncoder(others))``; ``features_dim`` is
    ``k + encoder.out_dim`` (64 for ``small``, 256 for ``paper``) and does not depend
    on ``max_rows``, so a ``state_dict`` trained with one ``max_rows`` loads into an
    extractor (or policy) built for another.

    Usage::

        policy_kwargs = dict(features_extractor_class=SetFeaturesExtractor,
                             features_extractor_kwargs=dict(encoder="paper"))
        DQN("MlpPolicy", env, policy_kwargs=policy_kwargs)          # Box obs
        SAC("MultiInputPolicy", env, policy_kwargs=policy_kwargs)   # Dict obs
    """

    def __init__(
        self,
        observation_space: gym.Space,
        encoder: str = "small",
        set_key: str = "others",
        **overrides: Any,
    ) -> None:
        kwargs = {**encoder_kwargs(encoder), **overrides}
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
        set_encoder = SetEncoder(in_features=set_space.shape[1] - 1, **kwargs)
        super().__init__(observation_space, features_dim=pass_dim + set_encoder.out_dim)
        self.encoder = set_encoder
        self.encoder_name = encoder
        self.set_key = set_key
        self.pass_keys = list(pass_keys)

    def forward(self, observations: torch.Tensor | dict[str, torch.Tensor]) -> torch.Tensor:
        if not isinstance(observations, dict):
            return self.encoder(observations)
        others = observations[self.set_key]
        parts = [observations[k].reshape(others.shape[0], -1) for k in self.pass_keys]
        parts.append(self.encoder(others))
        return torch.cat(parts, dim=-1)

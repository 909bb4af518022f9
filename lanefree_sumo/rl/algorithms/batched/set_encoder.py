"""The set observation's encoder (:class:`~lanefree_sumo.rl.encoder.SetEncoder`) for K runs at once, written out.

A network of a batched learner that reads the set observation starts with the encoder's tensors in its
:class:`~.stack.ParamStack` (f1's layers, f2's, the LayerNorm's weight and bias, the feature layer's; module
order, as SB3's ``SetFeaturesExtractor`` holds them), then the MLP head. The observation arrives flattened,
``[K, M, ego + rows·width]`` (the ego features, then the padded table row by row, presence last), as the
batched replay stores it.

Dense, not gathered: :meth:`~lanefree_sumo.rl.encoder.SetEncoder.pooled` encodes only the present rows (a
gather whose size depends on the data); here every row of the padded table goes through f1 and f2 (one
batched product per layer over ``[K, M·rows, width]``, a fixed shape a CUDA graph can hold) and the padding rows
are masked to contribute nothing. In the CPU's exact loop the encoder runs run by run instead, each run's table
cut after its last row present in the minibatch (:func:`encode`), so its cost follows the vehicles seen, as the
single run's does. The result is the same function; its float rounding is not the single
run's (other summation order), so a batched set-observation run agrees with its sequential run to float
tolerance, not bit for bit (``tests/rl/test_batched_set.py``). Batched run k still equals the batch of one run
of its seed bit for bit on CPU: every product goes through :class:`~.stack.Products`, every reduction is over
one run's own axis.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch as th
from torch import nn

from lanefree_sumo.rl.algorithms.batched.stack import Linear, Products, aten, mlp_backward, mlp_forward
from lanefree_sumo.rl.encoder import SetEncoder

L2_FLOOR = 1e-6
""":class:`SetEncoder`'s floor on the L2 norm (``norm="l2"``)."""


@dataclass(frozen=True)
class SetLayout:
    """The shape of a set observation and of the encoder that reads it.

    :param ego: ego features (the passthrough part).
    :param rows: rows of the padded table (``observation.max_rows``).
    :param width: columns of a row, presence last.
    :param layers: linear layers in f1 (and f2).
    :param out_relu: ReLU after f1's and f2's last layer.
    :param pool_over: ``"rows"`` (Y kept whole) or ``"rows+d1"`` (also averaged over f1's axis).
    :param norm: ``"layernorm"``, ``"l2"`` or ``"none"``.
    :param d1, d2: f1's and f2's output widths.
    :param feature: a feature layer (Linear + ReLU) follows the normalisation.
    :param presence_input: f1 and f2 also read the (binarised) presence.
    :param threshold: a row is present iff its presence value is above this.
    :param eps: the LayerNorm's ε."""

    ego: int
    rows: int
    width: int
    layers: int
    out_relu: bool
    pool_over: str
    norm: str
    d1: int
    d2: int
    feature: bool
    presence_input: bool
    threshold: float
    eps: float

    @classmethod
    def of(cls, encoder: SetEncoder, ego: int, rows: int) -> SetLayout:
        """The layout of ``encoder`` reading ``ego`` features and a table of ``rows`` rows; ValueError for an
        encoder the written-out passes do not cover (another activation than ReLU)."""
        modules = [*encoder.f1, *encoder.f2, *encoder.feature.modules()]
        if any(not isinstance(m, (nn.Linear, nn.ReLU, nn.Identity, nn.Sequential)) for m in modules):
            raise ValueError("the batched set encoder covers ReLU encoders only")
        linears = [m for m in encoder.f1 if isinstance(m, nn.Linear)]
        eps = float(encoder.norm.eps) if isinstance(encoder.norm, nn.LayerNorm) else 0.0
        return cls(ego=ego, rows=rows, width=encoder.in_features + 1, layers=len(linears),
                   out_relu=isinstance(encoder.f1[-1], nn.ReLU), pool_over=encoder.pool_over,
                   norm=encoder.norm_kind, d1=encoder.d1, d2=encoder.d2,
                   feature=not isinstance(encoder.feature, nn.Identity), presence_input=encoder.presence_input,
                   threshold=encoder.presence_threshold, eps=eps)

    @property
    def obs_dim(self) -> int:
        """The flattened observation's length."""
        return self.ego + self.rows * self.width

    @property
    def tensors(self) -> int:
        """How many parameter tensors the encoder has (the head's start in its network's stack)."""
        return 4 * self.layers + (2 if self.norm == "layernorm" else 0) + (2 if self.feature else 0)

    @property
    def pooled_dim(self) -> int:
        return self.d1 * self.d2 if self.pool_over == "rows" else self.d2


def _linear(weight: th.Tensor, bias: th.Tensor) -> Linear:
    return weight, weight.transpose(1, 2), bias.unsqueeze(1)


@dataclass
class Encoded:
    """What :func:`encode` keeps for :func:`encode_backward`."""

    mask: th.Tensor
    count: th.Tensor
    outs1: list[th.Tensor]
    outs2: list[th.Tensor]
    weighted: th.Tensor
    """f1's output on the present rows (padding rows zero) ``[K, M, rows, d1]``; with ``rows+d1`` its mean over d1."""
    y2: th.Tensor
    pooled: th.Tensor
    normed: th.Tensor | None
    """LayerNorm: the standardised vector before the affine; L2: the output; else None."""
    stats: tuple[th.Tensor, th.Tensor] | None
    scale: th.Tensor | None
    """L2: the norm (floored)."""
    feature_in: th.Tensor
    feature_out: th.Tensor | None


def encode(mm: Products, layout: SetLayout, tensors: Sequence[th.Tensor], obs: th.Tensor,
           dense: bool) -> tuple[th.Tensor, list[Encoded]]:
    """(the features ``[K, M, ego + out]`` — the ego passthrough, then the encoder's output, as
    ``SetFeaturesExtractor`` concatenates them —, what the backward pass needs) of flattened observations
    ``obs`` ``[K, M, obs_dim]``; ``tensors``: the encoder's ``[K, …]`` views, in module order.

    ``dense``: all runs at once over every row (fixed shapes, nothing read from the host: a GPU, the lockstep
    loop). Else run by run, each run's table cut after its last row present in any of its sets (the observation
    lists the vehicles nearest first, so the present rows lead): the products' lengths are then the run's own,
    as in the batch of that run alone (the CPU's exact loop)."""
    if dense:
        features, saved = _encode(mm, layout, tensors, obs, cut=False)
        return features, [saved]
    parts = [_encode(mm, layout, [t[k:k + 1] for t in tensors], obs[k:k + 1], cut=True)
             for k in range(obs.shape[0])]
    return th.cat([f for f, _ in parts]), [saved for _, saved in parts]


def _encode(mm: Products, layout: SetLayout, tensors: Sequence[th.Tensor], obs: th.Tensor,
            cut: bool) -> tuple[th.Tensor, Encoded]:
    """:func:`encode` of the runs of ``obs`` together; ``cut``: drop the rows empty in every set first."""
    k, m = obs.shape[0], obs.shape[1]
    ego = obs[..., :layout.ego]
    table = obs[..., layout.ego:].reshape(k, m, layout.rows, layout.width)
    mask = (table[..., -1] > layout.threshold).to(obs.dtype)
    if cut:
        used = mask.amax(dim=(0, 1)).nonzero()
        rows_used = int(used[-1, 0]) + 1 if used.numel() else 1
        table, mask = table[:, :, :rows_used], mask[:, :, :rows_used]
    rows = th.where(mask.unsqueeze(-1) > 0, table[..., :-1], th.zeros_like(table[..., :-1]))
    if layout.presence_input:
        rows = th.cat([rows, mask.unsqueeze(-1)], dim=-1)
    flat = rows.reshape(k, m * mask.shape[2], rows.shape[-1])
    n = 2 * layout.layers
    f1 = [_linear(tensors[i], tensors[i + 1]) for i in range(0, n, 2)]
    f2 = [_linear(tensors[i], tensors[i + 1]) for i in range(n, 2 * n, 2)]
    outs1 = mlp_forward(mm, f1, flat, False, relu_out=layout.out_relu)
    outs2 = mlp_forward(mm, f2, flat, False, relu_out=layout.out_relu)
    y1 = outs1[-1].reshape(k, m, mask.shape[2], layout.d1) * mask.unsqueeze(-1)
    y2 = outs2[-1].reshape(k, m, mask.shape[2], layout.d2)
    if layout.pool_over == "rows":
        weighted = y1
        per_row = (y1.unsqueeze(-1) * y2.unsqueeze(-2)).flatten(start_dim=-2)
    else:  # mean over the d1 axis of Y: one weight per row, mean_a f1(x)_a
        weighted = y1.mean(dim=-1, keepdim=True)
        per_row = weighted * y2
    count = mask.sum(dim=-1).clamp(min=1.0).unsqueeze(-1)  # [K, M, 1]: present rows, ≥ 1
    pooled = per_row.sum(dim=2) / count
    at = 4 * layout.layers
    normed: th.Tensor | None = None
    stats: tuple[th.Tensor, th.Tensor] | None = None
    scale: th.Tensor | None = None
    if layout.norm == "layernorm":
        normed, mean, rstd = aten.native_layer_norm(pooled, [layout.pooled_dim], None, None, layout.eps)
        stats = (mean, rstd)
        out = normed * tensors[at].unsqueeze(1) + tensors[at + 1].unsqueeze(1)
        at += 2
    elif layout.norm == "l2":
        scale = pooled.norm(dim=-1, keepdim=True).clamp(min=L2_FLOOR)
        out = normed = pooled / scale
    else:
        out = pooled
    feature_out = None
    if layout.feature:
        feature_out = th.relu(mm.linear(out, _linear(tensors[at], tensors[at + 1])))
    features = th.cat([ego, out if feature_out is None else feature_out], dim=-1)
    return features, Encoded(mask, count, outs1, outs2, weighted, y2, pooled, normed, stats, scale, out, feature_out)


def encode_backward(mm: Products, layout: SetLayout, tensors: Sequence[th.Tensor], saved: list[Encoded],
                    grad: th.Tensor) -> list[th.Tensor]:
    """The gradients of the encoder's tensors ``[K, …]`` (module order) from the gradient ``grad`` of the
    features :func:`encode` returned (run by run where it encoded so)."""
    if len(saved) == 1:  # dense, or one run
        return _encode_backward(mm, layout, tensors, saved[0], grad)
    parts = [_encode_backward(mm, layout, [t[k:k + 1] for t in tensors], one, grad[k:k + 1])
             for k, one in enumerate(saved)]
    return [th.cat(grads) for grads in zip(*parts)]


def _encode_backward(mm: Products, layout: SetLayout, tensors: Sequence[th.Tensor], saved: Encoded,
                     grad: th.Tensor) -> list[th.Tensor]:
    """:func:`encode_backward` of the runs of ``grad`` together."""
    g = grad[..., layout.ego:]
    at = 4 * layout.layers + (2 if layout.norm == "layernorm" else 0)
    tail: list[th.Tensor] = []
    if saved.feature_out is not None:
        layer = _linear(tensors[at], tensors[at + 1])
        g = aten.threshold_backward(g, saved.feature_out, 0)
        tail = [mm.weight_grad(g, saved.feature_in), g.sum(1)]
        g = mm.input_grad(g, layer[0])
    if layout.norm == "layernorm":
        at = 4 * layout.layers
        assert saved.normed is not None and saved.stats is not None
        tail = [(g * saved.normed).sum(1), g.sum(1), *tail]
        g = aten.native_layer_norm_backward(g * tensors[at].unsqueeze(1), saved.pooled, [layout.pooled_dim],
                                            saved.stats[0], saved.stats[1], None, None, [True, False, False])[0]
    elif layout.norm == "l2":
        assert saved.normed is not None and saved.scale is not None
        along = (g * saved.normed).sum(dim=-1, keepdim=True)
        radial = th.where(saved.scale > L2_FLOOR, along * saved.normed, th.zeros_like(g))
        g = (g - radial) / saved.scale
    g_row = (g / saved.count).unsqueeze(2)  # each row's share of the mean over the present rows
    if layout.pool_over == "rows":
        g_row = g_row.unflatten(-1, (layout.d1, layout.d2))
        g_y1 = (g_row * saved.y2.unsqueeze(-2)).sum(-1)
        g_y2 = (g_row * saved.weighted.unsqueeze(-1)).sum(-2)
    else:
        g_y2 = g_row * saved.weighted
        g_y1 = ((g_row * saved.y2).sum(-1, keepdim=True) / layout.d1).expand(*saved.y2.shape[:-1], layout.d1)
    g_y1 = g_y1 * saved.mask.unsqueeze(-1)
    k, rows = g_y1.shape[0], g_y1.shape[1] * g_y1.shape[2]
    n = 2 * layout.layers
    f1 = [_linear(tensors[i], tensors[i + 1]) for i in range(0, n, 2)]
    f2 = [_linear(tensors[i], tensors[i + 1]) for i in range(n, 2 * n, 2)]
    grads1 = mlp_backward(mm, f1, saved.outs1, g_y1.reshape(k, rows, layout.d1), False,
                          relu_out=layout.out_relu)[0]
    grads2 = mlp_backward(mm, f2, saved.outs2, g_y2.reshape(k, rows, layout.d2), False,
                          relu_out=layout.out_relu)[0]
    return [*grads1, *grads2, *tail]

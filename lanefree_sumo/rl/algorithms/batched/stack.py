"""K networks of one architecture as stacked tensors: parameters ``[K, P]``, products over all K at once.

* :class:`ParamStack`: the parameters of K networks (one per run) in one buffer ``[K, P]``, each run's row
  laid out as the single run's parameters in module order, with views
  ``[K, *shape]`` per tensor;
* :class:`Products`: the three products of a linear layer (forward, weight gradient, input gradient) as one
  batched kernel (``baddbmm``/``bmm``) for all K runs; with ``exact`` (the CPU default) each product shape is
  probed once, and where the batched kernel gives other bits than the single run's ``addmm``/``mm`` (measured
  with MKL: an output width of 1, where ``addmm`` takes a matrix-vector kernel, and products under 400
  multiply-adds, which ``bmm`` computes with its own loop) it runs K single products instead;
* :func:`mlp_forward`/:func:`mlp_backward`: the MLP's forward and backward written out with the kernels
  autograd calls for them (``addmm``, ``mm``, ``threshold_backward``, ``tanh_backward``), with a leading run axis;
* :class:`StackedAdam`: torch's Adam arithmetic on ``[K, P]``,
  each run with its own learning rate; :func:`soft_update`: ``θ' ← (1 − τ) θ' + τ θ`` in one operation, τ per run.

On CPU every elementwise operation here gives the same bits on a run's row as on the single run's buffer
(``tests/rl/test_batched_learners.py``). A learning rate or τ all runs share enters as the single run's scalar;
where they differ they enter as ``[K, 1]`` tensors in forms measured to round as the scalar forms do
(``addcdiv``'s ``value·m / d``; ``add``'s fused multiply-add through ``addcmul``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch as th

aten = th.ops.aten

Linear = tuple[th.Tensor, th.Tensor, th.Tensor]
"""A stacked linear layer: weights W ``[K, out, in]``, the view Wᵀ ``[K, in, out]``, biases ``[K, 1, out]``
(views of a :class:`ParamStack`'s buffer: its in-place updates show through them)."""


class ParamStack:
    """The parameters of K networks of one architecture in one buffer ``[K, P]`` (row k: run k's parameters
    in ``per_run[k]``'s order, flattened), with a view ``[K, *shape]`` per parameter tensor."""

    def __init__(self, per_run: Sequence[Sequence[th.Tensor]], device: th.device, head_start: int = 0) -> None:
        shapes = [tuple(p.shape) for p in per_run[0]]
        if any([tuple(p.shape) for p in params] != shapes for params in per_run):
            raise ValueError("the networks of a batch must have one architecture")
        self.shapes = shapes
        self.head_start = head_start
        """The index of the first tensor of the MLP :meth:`layers` returns (the tensors before it: an encoder's)."""
        rows = [th.cat([p.detach().reshape(-1) for p in params]) for params in per_run]
        self.flat = th.stack(rows).to(device=device, dtype=th.float32).contiguous()
        self.tensors = self._views(self.flat)
        self._layers = self._linear(self.tensors[head_start:])

    def _views(self, flat: th.Tensor) -> list[th.Tensor]:
        views, at = [], 0
        for shape in self.shapes:
            n = 1
            for d in shape:
                n *= d
            views.append(flat[:, at:at + n].view(flat.shape[0], *shape))
            at += n
        return views

    @staticmethod
    def _linear(tensors: list[th.Tensor]) -> list[Linear]:
        return [(tensors[i], tensors[i].transpose(1, 2), tensors[i + 1].unsqueeze(1))
                for i in range(0, len(tensors), 2)]

    def layers(self) -> list[Linear]:
        """The tensors from :attr:`head_start` on as linear layers (weight, bias, weight, bias, … in order).
        Compiled code takes new views of the buffer (a compiled function must not see the buffer and its views as
        separate inputs: it would update one and read the other's stale copy)."""
        if th.compiler.is_compiling():
            return self._linear(self._views(self.flat)[self.head_start:])
        return self._layers

    def views(self) -> list[th.Tensor]:
        """Every tensor's view ``[K, *shape]`` (new views in compiled code, as :meth:`layers`)."""
        return self._views(self.flat) if th.compiler.is_compiling() else self.tensors

    def row(self, k: int) -> list[th.Tensor]:
        """Run k's parameter tensors (views)."""
        return [t[k] for t in self.tensors]


class Products:
    """The products of stacked linear layers, batched over the run axis (module docstring).

    :param exact: probe each product shape once and use K single products where the batched kernel gives
        other bits than the single run's (on CPU: what makes batched run k equal the single run); False:
        always one batched kernel (another device, where only speed matters)."""

    def __init__(self, exact: bool) -> None:
        self.exact = exact
        self._batched: dict[tuple[object, ...], bool] = {}
        self._probe = th.Generator().manual_seed(0)

    def _use_batched(self, key: tuple[object, ...], operands: Sequence[th.Tensor],
                     batched: Callable[..., th.Tensor], single: Callable[..., th.Tensor]) -> bool:
        """Whether ``batched`` gives ``single``'s bits for operands of these shapes and strides (probed once
        with random values of the same layout). Compiled code cannot probe: it takes the batched kernel where the
        shape was not probed before (the lockstep loop, which compiles, matches the single runs in distribution
        only)."""
        if not self.exact:
            return True
        known = self._batched.get(key)
        if known is None and th.compiler.is_compiling():
            return True
        if known is None:
            probes = []
            for t in operands:
                values = th.randn(t.shape, generator=self._probe).to(t.device)
                probe = th.empty_strided(t.shape, t.stride(), dtype=t.dtype, device=t.device)
                probes.append(probe.copy_(values))
            known = self._batched[key] = bool(th.equal(batched(*probes), single(*probes)))
        return known

    def _run(self, kind: str, operands: Sequence[th.Tensor], batched: Callable[..., th.Tensor],
             single: Callable[..., th.Tensor]) -> th.Tensor:
        key = (kind, *((tuple(t.shape), t.stride()) for t in operands), operands[0].device)
        if self._use_batched(key, operands, batched, single):
            return batched(*operands)
        return single(*operands)

    def linear(self, x: th.Tensor, layer: Linear) -> th.Tensor:
        """``x Wᵀ + b`` per run: x ``[K, M, in]`` → ``[K, M, out]`` (``nn.Linear``'s ``addmm(b, x, Wᵀ)``)."""
        return self._run("linear", (x, layer[1], layer[2]), lambda x, wt, b: th.baddbmm(b, x, wt),
                         lambda x, wt, b: th.stack([th.addmm(b[k, 0], x[k], wt[k]) for k in range(x.shape[0])]))

    def weight_grad(self, grad: th.Tensor, x: th.Tensor) -> th.Tensor:
        """``gᵀ x`` per run: the weight gradient ``[K, out, in]`` of a layer with input x and output gradient g."""
        return self._run("weight_grad", (grad, x), lambda g, x: th.bmm(g.transpose(1, 2), x),
                         lambda g, x: th.stack([g[k].t().mm(x[k]) for k in range(g.shape[0])]))

    def input_grad(self, grad: th.Tensor, weight: th.Tensor) -> th.Tensor:
        """``g W`` per run: the gradient of a layer's input ``[K, M, in]``."""
        return self._run("input_grad", (grad, weight), th.bmm,
                         lambda g, w: th.stack([g[k].mm(w[k]) for k in range(g.shape[0])]))


def mlp_forward(mm: Products, layers: Sequence[Linear], x: th.Tensor, squash: bool,
                relu_out: bool = False) -> list[th.Tensor]:
    """[input, output of each layer] of K MLPs (ReLU between layers; after the last Tanh iff ``squash``, ReLU iff
    ``relu_out``); x ``[K, M, in]``."""
    outs = [x]
    last = len(layers) - 1
    for k, layer in enumerate(layers):
        z = mm.linear(x, layer)
        x = th.relu(z) if k < last or relu_out else (th.tanh(z) if squash else z)
        outs.append(x)
    return outs


def mlp_backward(mm: Products, layers: Sequence[Linear], outs: Sequence[th.Tensor], grad: th.Tensor, squash: bool,
                 weights: bool = True, to_input: bool = False,
                 relu_out: bool = False) -> tuple[list[th.Tensor], th.Tensor | None]:
    """(gradients [W1, b1, W2, b2, …] ``[K, …]`` — empty unless ``weights``, the input's gradient — None unless
    ``to_input``) from the output's gradient ``grad``: autograd's kernels with a run axis
    (the bias gradient sums over the batch axis 1); ``squash``, ``relu_out``: as :func:`mlp_forward`'s."""
    if squash:
        grad = aten.tanh_backward(grad, outs[-1])
    elif relu_out:
        grad = aten.threshold_backward(grad, outs[-1], 0)
    grads: list[th.Tensor] = []
    for k in range(len(layers) - 1, -1, -1):
        if weights:
            grads += [grad.sum(1), mm.weight_grad(grad, outs[k])]
        if k > 0 or to_input:
            grad = mm.input_grad(grad, layers[k][0])
            if k > 0:
                grad = aten.threshold_backward(grad, outs[k], 0)
    grads.reverse()
    return grads, grad if to_input else None


def per_run_column(values: Sequence[float], device: th.device) -> th.Tensor:
    """``[K, 1]`` float32 tensor of per-run numbers (rounded from float64 as torch rounds a Python scalar)."""
    return th.tensor([[float(v)] for v in values], dtype=th.float64).to(device=device, dtype=th.float32)


class StackedAdam:
    """``torch.optim.Adam`` (no weight decay, AMSGrad or maximize; ``betas`` and ``eps`` the batch's) over a
    :class:`ParamStack`'s buffer, run k with learning rate ``lrs[k]``: the arithmetic of torch's multi-tensor
    Adam, with moments ``[K, P]``. All runs step together (one step count)."""

    def __init__(self, params: ParamStack, lrs: Sequence[float], betas: tuple[float, float], eps: float) -> None:
        self.params = params
        self.lrs = th.tensor([[float(v)] for v in lrs], dtype=th.float64, device=params.flat.device)
        self.shared_lr = float(lrs[0]) if len(set(lrs)) == 1 else None
        """The learning rate when all runs have the same: the single run's scalar form, no [K, P] product."""
        self.beta1, self.beta2 = float(betas[0]), float(betas[1])
        self.eps = float(eps)
        self.exp_avg = th.zeros_like(params.flat)
        self.exp_avg_sq = th.zeros_like(params.flat)
        self.steps = 0
        self.count: th.Tensor | None = None
        """The step count on the device (:meth:`count_on_device`), else None."""

    def count_on_device(self) -> None:
        """Count the steps on the device from now on (float64, from :attr:`steps`): a step then reads nothing
        from the host, so a CUDA graph can hold it; :attr:`steps` is the caller's to advance."""
        device = self.params.flat.device
        self.count = th.full((1,), float(self.steps), dtype=th.float64, device=device)  # not 0-d: compiled code
        # would not write a 0-d input back
        self._betas = th.tensor([self.beta1, self.beta2], dtype=th.float64).to(device)

    def step(self, grads: Sequence[th.Tensor]) -> None:
        """One step with the gradients of the stack's tensors (in order, each ``[K, …]``)."""
        k = self.params.flat.shape[0]
        grad = th.cat([g.reshape(k, -1) for g in grads], dim=1)
        self.exp_avg.lerp_(grad, 1 - self.beta1)
        self.exp_avg_sq.mul_(self.beta2).addcmul_(grad, grad, value=1 - self.beta2)
        if self.count is not None:  # the bias corrections from the device's count, in float64
            self.count.add_(1.0)
            corrections = 1.0 - th.pow(self._betas, self.count)
            denom = self.exp_avg_sq.sqrt().div_(corrections[1].sqrt().float()).add_(self.eps)
            step_size = (self.lrs / corrections[0]).neg_().to(th.float32)
            self.params.flat.addcdiv_(self.exp_avg * step_size, denom)
            return
        self.steps += 1
        n = self.steps
        denom = self.exp_avg_sq.sqrt().div_((1 - self.beta2**n) ** 0.5).add_(self.eps)
        if self.shared_lr is not None:  # torch's addcdiv_(m, denom, value=(lr / (1 − β1ⁿ)) · −1)
            self.params.flat.addcdiv_(self.exp_avg, denom, value=(self.shared_lr / (1 - self.beta1**n)) * -1)
            return
        # the value per run: (value · m) / denom, as addcdiv computes it
        step_size = (self.lrs / (1 - self.beta1**n)).neg_().to(th.float32)
        self.params.flat.addcdiv_(self.exp_avg * step_size, denom)

    def state_dict(self) -> dict[str, object]:
        return {"exp_avg": self.exp_avg, "exp_avg_sq": self.exp_avg_sq, "steps": self.steps}

    def load_state_dict(self, state: dict[str, object]) -> None:
        self.exp_avg.copy_(state["exp_avg"])  # type: ignore[arg-type]
        self.exp_avg_sq.copy_(state["exp_avg_sq"])  # type: ignore[arg-type]
        self.steps = int(state["steps"])  # type: ignore[call-overload]
        if self.count is not None:
            self.count.fill_(float(self.steps))

    def sb3_state(self, k: int, params: Sequence[th.Tensor]) -> dict[int, dict[str, th.Tensor]]:
        """Run k's state as ``torch.optim.Adam.state_dict()["state"]`` for ``params`` (its tensors, in order)."""
        state: dict[int, dict[str, th.Tensor]] = {}
        at = 0
        for i, p in enumerate(params):
            n = p.numel()
            state[i] = {"step": th.tensor(float(self.steps)),
                        "exp_avg": self.exp_avg[k, at:at + n].reshape(p.shape).cpu().clone(),
                        "exp_avg_sq": self.exp_avg_sq[k, at:at + n].reshape(p.shape).cpu().clone()}
            at += n
        return state


def soft_update(target: ParamStack, online: ParamStack, tau: th.Tensor, one_minus_tau: th.Tensor,
                shared_tau: float | None = None) -> None:
    """SB3's ``polyak_update`` for every run at once: ``θ' · (1 − τ)``, then ``+ τ · θ`` (τ, 1 − τ: ``[K, 1]``;
    ``shared_tau``: the τ of all runs when they share one, the single run's scalar form)."""
    if shared_tau is not None:
        target.flat.mul_(1 - shared_tau).add_(online.flat, alpha=shared_tau)
    else:
        target.flat.mul_(one_minus_tau).addcmul_(online.flat, tau)


def hard_update(target: ParamStack, online: ParamStack) -> None:
    """SB3's ``polyak_update`` with τ = 1 (DQN's target copy): ``θ' · 0 + θ``."""
    target.flat.mul_(0.0).add_(online.flat)

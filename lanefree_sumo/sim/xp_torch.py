"""The torch side of the array namespace (:mod:`.xp`): numpy's names over torch tensors on one device."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np
import torch
from scipy.special import erfc as _scipy_erfc

_HOST_TRANSCENDENTALS = False
"""Whether the torch namespaces compute the functions that differ with numpy's (:func:`numpy_transcendentals`)."""


@contextlib.contextmanager
def numpy_transcendentals() -> Iterator[None]:
    """Within the block, the torch namespaces compute ``erfc``, ``power``, ``sqrt`` and ``hypot`` with numpy's on
    the host (a test's means to show that every other operation gives numpy's bits; slow, never in a run)."""
    global _HOST_TRANSCENDENTALS
    saved, _HOST_TRANSCENDENTALS = _HOST_TRANSCENDENTALS, True
    try:
        yield
    finally:
        _HOST_TRANSCENDENTALS = saved


_DTYPES: dict[Any, Any] = {float: torch.float64, np.float64: torch.float64, bool: torch.bool, np.bool_: torch.bool,
                           int: torch.int64, np.int64: torch.int64, np.float32: torch.float32}
"""numpy's dtypes (as the physics names them) and torch's."""


class TorchNamespace:
    """numpy's names over torch tensors on one device (float64 for real numbers, int64 for indices). Its type tests
    take tuples (``isinstance(x, (float, int))``), not unions: ``torch.compile`` traces the one, not the other."""

    is_numpy = False
    inf = float("inf")
    nan = float("nan")
    newaxis = None

    def __init__(self, device: Any = "cpu") -> None:
        self.device = torch.device(device)
        self.name = "torch-cpu" if self.device.type == "cpu" else str(self.device)
        """This namespace's ``train.device`` name (:func:`~lanefree_sumo.sim.xp.array_namespace`)."""
        self.float64, self.int64, self.bool_ = torch.float64, torch.int64, torch.bool
        self.numpy_order_sums = self.device.type == "cpu"
        """Sum rows over vehicles in numpy's order (:func:`~lanefree_sumo.sim.state.row_sum`; on the CPU, where the
        torch simulation is proven equal to numpy's) or in torch's own (on a GPU: one kernel instead of ~40 per sum,
        the same sums to rounding)."""
        self._constants: dict[tuple[Any, Any, Any], Any] = {}
        """The numbers beside tensors as 0-d tensors on the device (:meth:`_number`), made once; never written."""

    # -- conversions --------------------------------------------------------------------------------------
    def _dtype(self, dtype: Any) -> Any:
        if dtype is None or isinstance(dtype, torch.dtype):
            return dtype
        found = _DTYPES.get(dtype)
        if found is None and isinstance(dtype, np.dtype):
            found = _DTYPES.get(dtype.type)
        if found is None:
            raise TypeError(f"no torch dtype for {dtype!r}")
        return found

    def asarray(self, a: Any, dtype: Any = None) -> Any:
        """A tensor on this namespace's device (numpy float arrays and Python floats become float64)."""
        dtype = self._dtype(dtype)
        if isinstance(a, torch.Tensor):
            return a if dtype is None or a.dtype == dtype else a.to(dtype)
        if isinstance(a, (bool, int, float)):  # filled on the device: no copy from the host
            return torch.full((), a, dtype=dtype or (torch.bool if isinstance(a, bool) else torch.int64
                                                     if isinstance(a, int) else torch.float64), device=self.device)
        if dtype is None and isinstance(a, (float, np.floating)) or (isinstance(a, np.ndarray) and a.dtype.kind == "f"
                                                                    and dtype is None):
            dtype = torch.float64
        return torch.as_tensor(np.asarray(a) if isinstance(a, np.generic) else a, dtype=dtype, device=self.device)

    array = asarray

    def to_numpy(self, a: Any) -> np.ndarray:
        """The tensor on the host as a numpy array (a device synchronisation)."""
        return a.detach().cpu().numpy() if isinstance(a, torch.Tensor) else np.asarray(a)

    def astype(self, a: Any, dtype: Any) -> Any:
        return a.to(self._dtype(dtype))

    def copy(self, a: Any) -> Any:
        return a.clone()

    def _number(self, x: Any, like: Any) -> Any:
        """A Python number as a 0-d tensor beside tensor ``like``: ``like``'s dtype where that is a float (as numpy
        treats a number beside an array), else float64, int64 or bool after the number. Made by a fill on the
        device, not copied from the host (a copy would synchronise with the device)."""
        if isinstance(x, torch.Tensor):
            return x
        if isinstance(x, (np.ndarray, np.generic)):
            return self.asarray(x)
        if like is not None and like.is_floating_point():
            dtype = like.dtype
        else:
            dtype = torch.bool if isinstance(x, bool) else torch.int64 if isinstance(x, int) else torch.float64
        if torch.compiler.is_compiling():  # a traced constant: the compiler folds it into its kernels
            return torch.full((), x, dtype=dtype, device=self.device)
        key = (type(x), repr(x), dtype)  # repr: −0.0 is not 0.0
        constant = self._constants.get(key)
        if constant is None:  # made once: a step then launches no fill per number
            constant = self._constants[key] = torch.full((), x, dtype=dtype, device=self.device)
        return constant

    def _pair(self, a: Any, b: Any) -> tuple[Any, Any]:
        """Both as tensors (:meth:`_number` for a Python number)."""
        if isinstance(a, torch.Tensor):
            return a, self._number(b, a)
        b = self._number(b, None)
        return self._number(a, b), b

    # -- elementwise --------------------------------------------------------------------------------------
    def abs(self, a: Any) -> Any:
        return torch.abs(self.asarray(a))

    def sqrt(self, a: Any) -> Any:
        if _HOST_TRANSCENDENTALS:
            return self.asarray(np.sqrt(self.to_numpy(a)))
        return torch.sqrt(a)

    def floor(self, a: Any) -> Any:
        return torch.floor(a)

    def sign(self, a: Any) -> Any:
        return torch.sign(a)

    def hypot(self, a: Any, b: Any) -> Any:
        if _HOST_TRANSCENDENTALS:
            return self.asarray(np.hypot(self.to_numpy(a), self.to_numpy(b)))
        return torch.hypot(*self._pair(a, b))

    def erfc(self, a: Any) -> Any:
        if _HOST_TRANSCENDENTALS:
            return self.asarray(_scipy_erfc(self.to_numpy(a)))
        return torch.special.erfc(a)

    def power(self, a: Any, p: float) -> Any:
        if _HOST_TRANSCENDENTALS:
            return self.asarray(np.power(self.to_numpy(a), p))
        return torch.pow(a, p)

    def isnan(self, a: Any) -> Any:
        return torch.isnan(a)

    def isfinite(self, a: Any) -> Any:
        return torch.isfinite(self.asarray(a))

    def maximum(self, a: Any, b: Any) -> Any:
        if isinstance(a, torch.Tensor) and isinstance(b, (float, int)) and a.is_floating_point():
            return torch.clamp(a, min=b)  # max(a, b) with the number as a kernel argument: the same values
        if isinstance(b, torch.Tensor) and isinstance(a, (float, int)) and b.is_floating_point():
            return torch.clamp(b, min=a)
        return torch.maximum(*self._pair(a, b))

    def minimum(self, a: Any, b: Any) -> Any:
        if isinstance(a, torch.Tensor) and isinstance(b, (float, int)) and a.is_floating_point():
            return torch.clamp(a, max=b)
        if isinstance(b, torch.Tensor) and isinstance(a, (float, int)) and b.is_floating_point():
            return torch.clamp(b, max=a)
        return torch.minimum(*self._pair(a, b))

    def clip(self, a: Any, lo: Any, hi: Any) -> Any:
        return self.minimum(self.maximum(a, lo), hi)

    def where(self, cond: Any, a: Any, b: Any) -> Any:
        if isinstance(a, torch.Tensor) and isinstance(b, (float, int)) and (a.is_floating_point() or
                                                                           isinstance(b, int)):
            return torch.where(cond, a, b)  # the number as a kernel argument, in the tensor's dtype
        if isinstance(b, torch.Tensor) and isinstance(a, (float, int)) and (b.is_floating_point() or
                                                                           isinstance(a, int)):
            return torch.where(cond, a, b)
        a, b = self._pair(a, b)
        return torch.where(self.asarray(cond), a, b)

    def subtract(self, a: Any, b: Any) -> Any:
        a, b = self._pair(a, b)
        return a - b

    def multiply(self, a: Any, b: Any) -> Any:
        a, b = self._pair(a, b)
        return a * b

    def divide(self, a: Any, b: Any) -> Any:
        """a / b, IEEE division also for a number divided by a tensor (torch's ``number / tensor`` is
        ``reciprocal(tensor) * number``, which rounds differently)."""
        return torch.div(*self._pair(a, b))

    def logical_and(self, a: Any, b: Any) -> Any:
        a, b = self._pair(a, b)
        return a.bool() & b.bool()

    def divide_where(self, num: Any, den: Any, fill: Any) -> Any:
        """num/den where den > 0, else ``fill``."""
        num, den = self._pair(num, den)
        ok = den > 0
        return self.where(ok, num / torch.where(ok, den, torch.ones_like(den)), fill)

    # -- construction --------------------------------------------------------------------------------------
    def arange(self, *args: int) -> Any:
        return torch.arange(*args, device=self.device)

    def zeros(self, shape: Any, dtype: Any = float) -> Any:
        return torch.zeros(shape, dtype=self._dtype(dtype), device=self.device)

    def ones(self, shape: Any, dtype: Any = float) -> Any:
        return torch.ones(shape, dtype=self._dtype(dtype), device=self.device)

    def full(self, shape: Any, value: Any, dtype: Any = None) -> Any:
        dtype = self._dtype(dtype) or (torch.float64 if isinstance(value, float) else None)
        return torch.full(shape if isinstance(shape, tuple) else (shape,), value, dtype=dtype, device=self.device)

    def zeros_like(self, a: Any) -> Any:
        return torch.zeros_like(a)

    def stack(self, arrays: Sequence[Any], axis: int = 0) -> Any:
        return torch.stack(list(arrays), dim=axis)

    def concatenate(self, arrays: Sequence[Any], axis: int = 0) -> Any:
        return torch.cat(list(arrays), dim=axis)

    def column_stack(self, arrays: Sequence[Any]) -> Any:
        return torch.stack(list(arrays), dim=1)

    def broadcast_to(self, a: Any, shape: Any) -> Any:
        return torch.broadcast_to(self.asarray(a), shape)

    def triu(self, a: Any, k: int = 0) -> Any:
        return torch.triu(a, diagonal=k)

    # -- indexing -------------------------------------------------------------------------------------------
    def take_along_axis(self, a: Any, index: Any, axis: int) -> Any:
        return torch.take_along_dim(a, index, dim=axis)

    def fill_where(self, a: Any, mask: Any, value: Any) -> None:
        """``a[mask] = value`` in place, without the host synchronisation of boolean indexing."""
        a.masked_fill_(mask, value)

    def fill_diagonal(self, a: Any, value: Any) -> None:
        """The diagonal of the last two axes set to ``value``, in place, by a fill on the device."""
        a.diagonal(dim1=-2, dim2=-1).fill_(value)

    def put_along_axis(self, a: Any, index: Any, values: Any, axis: int) -> None:
        """``a[..., index] = values`` along ``axis``, in place (numpy's ``put_along_axis``)."""
        values = self.asarray(values, a.dtype)
        a.scatter_(axis, index, torch.broadcast_to(values, index.shape))

    def argsort_stable(self, a: Any, axis: int = -1) -> Any:
        return torch.sort(a, dim=axis, stable=True).indices

    def largest_k(self, a: Any, k: int) -> Any:
        return torch.topk(a, k, dim=-1, sorted=False).indices

    # -- reductions -----------------------------------------------------------------------------------------
    def sum(self, a: Any, axis: Any = None) -> Any:
        return a.sum() if axis is None else a.sum(dim=axis)

    def any(self, a: Any, axis: int | None = None) -> Any:
        return a.any() if axis is None else a.any(dim=axis)

    def all(self, a: Any, axis: int | None = None) -> Any:
        return a.all() if axis is None else a.all(dim=axis)

    def count_nonzero(self, a: Any, axis: int | None = None) -> Any:
        return torch.count_nonzero(a, dim=axis)

    def min(self, a: Any, axis: int, keepdims: bool = False) -> Any:
        return torch.amin(a, dim=axis, keepdim=keepdims)

    def max(self, a: Any, axis: int, keepdims: bool = False) -> Any:
        return torch.amax(a, dim=axis, keepdim=keepdims)

    def argmin(self, a: Any, axis: int) -> Any:
        return torch.argmin(a, dim=axis)

    def argmax(self, a: Any, axis: int) -> Any:
        return torch.argmax(a, dim=axis)

    def accumulate_max(self, a: Any, axis: int = -1) -> Any:
        return torch.cummax(a, dim=axis).values

    def ndim(self, a: Any) -> int:
        return a.ndim if isinstance(a, torch.Tensor) else int(np.ndim(a))

    def errstate(self, **_: Any) -> contextlib.AbstractContextManager[None]:
        return contextlib.nullcontext()

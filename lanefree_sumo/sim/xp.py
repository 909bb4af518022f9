"""The array namespace the physics is written against: numpy, or torch on any device, behind one set of names.

:func:`namespace` returns, for the arrays a function receives, an object ``xp`` with numpy's names. For numpy arrays
it *is* numpy's functions (the attributes of the ``numpy`` module, plus the few helpers below with numpy's own
implementation), so the numpy path computes exactly what it computed before it was written this way. For torch
tensors it is :class:`~lanefree_sumo.sim.xp_torch.TorchNamespace`: the same names with numpy's signatures (``axis``,
scalars beside arrays), in float64 on the tensors' device. The physics (:mod:`.forces`, :mod:`.dynamics`,
:mod:`.collisions`, :mod:`.state`, :mod:`.world`) and the batched environment's observations and rewards call
``xp.<name>`` only: one copy of the physics, run as numpy on CPU and as torch on a GPU.

The helpers stand for numpy idioms without a portable spelling: ``erfc`` (scipy's for numpy), ``power``,
``divide_where`` (``np.divide`` with ``out``/``where``), ``put_along_axis`` (in place), ``accumulate_max``,
``argsort_stable``, ``largest_k`` (``argpartition``), ``fill_where`` (``a[mask] = value``; torch's boolean
indexing would synchronise with the device), ``fill_diagonal`` (``a[..., i, i] = value``; torch would copy the
number from the host, which a CUDA graph cannot hold), ``errstate``, ``copy``, ``astype``, and the flag
``is_numpy`` for result-preserving shortcuts that branch on values (taken on numpy only: on a GPU a branch on a
value is a host synchronisation).

Where torch and numpy differ in the last bit: the elementwise arithmetic (+ − × ÷, floor, min, max, clip, where) is
IEEE in both and gives the same bits (``divide`` for a number divided by an array: torch's ``number / tensor``
multiplies by a reciprocal); ``erfc``, ``power``, ``hypot`` and even ``sqrt`` (torch's CPU kernel is not correctly
rounded: 1–2 ulp off for some arguments, measured) are computed by different libraries and may differ in the last
bit (:func:`~lanefree_sumo.sim.xp_torch.numpy_transcendentals` exchanges them for numpy's in tests). Sums over
vehicles are formed in numpy's order on both (:func:`~lanefree_sumo.sim.state.row_sum`). Where forces tie for the
k-th strongest place, numpy's ``argpartition`` and torch's ``topk`` may pick different ones of the tied neighbours
(the specification does not say which).
"""

from __future__ import annotations

import operator
import sys
from types import SimpleNamespace
from typing import Any

import numpy as np
from scipy.special import erfc as _scipy_erfc


def _numpy_divide_where(num: np.ndarray, den: np.ndarray, fill: np.ndarray) -> np.ndarray:
    """num/den where den > 0, else ``fill`` (a new array of the broadcast shape)."""
    out = np.full(np.broadcast_shapes(np.shape(num), np.shape(den)), fill, dtype=float)
    np.divide(num, den, out=out, where=den > 0)
    return out


def _numpy_largest_k(a: np.ndarray, k: int) -> np.ndarray:
    """Indices of the k largest entries of each row (last axis), in no particular order."""
    return np.argpartition(-a, k - 1, axis=-1)[..., :k]


def _numpy_take_along_axis(a: np.ndarray, index: np.ndarray, axis: int) -> np.ndarray:
    """numpy's ``take_along_axis``; rows of a 2-D array indexed directly (the same values, less overhead)."""
    if a.ndim == 2 and index.ndim == 2 and axis in (1, -1):
        return a[np.arange(a.shape[0])[:, None], index]
    return np.take_along_axis(a, index, axis)


def _numpy_put_along_axis(a: np.ndarray, index: np.ndarray, values: Any, axis: int) -> None:
    """numpy's ``put_along_axis`` (in place); rows of a 2-D array indexed directly."""
    if a.ndim == 2 and index.ndim == 2 and axis in (1, -1):
        a[np.arange(a.shape[0])[:, None], index] = values
    else:
        np.put_along_axis(a, index, values, axis)


def _numpy_fill_where(a: np.ndarray, mask: np.ndarray, value: Any) -> None:
    """``a[mask] = value`` in place."""
    a[mask] = value


def _numpy_fill_diagonal(a: np.ndarray, value: Any) -> None:
    """The diagonal of the last two axes set to ``value``, in place (``a[..., i, i] = value``)."""
    n = a.shape[-1]
    a[..., np.arange(n), np.arange(n)] = value


def _numpy_namespace() -> SimpleNamespace:
    ns = SimpleNamespace(**{name: getattr(np, name) for name in dir(np) if not name.startswith("_")})
    ns.is_numpy = True
    ns.erfc = _scipy_erfc
    ns.power = operator.pow  # the ``**`` operator: numpy's shortcuts for squares and square roots included
    ns.divide_where = _numpy_divide_where
    ns.accumulate_max = lambda a, axis=-1: np.maximum.accumulate(a, axis=axis)
    ns.argsort_stable = lambda a, axis=-1: np.argsort(a, axis=axis, kind="stable")
    ns.largest_k = _numpy_largest_k
    ns.take_along_axis = _numpy_take_along_axis
    ns.put_along_axis = _numpy_put_along_axis
    ns.fill_where = _numpy_fill_where
    ns.fill_diagonal = _numpy_fill_diagonal
    ns.copy = lambda a: a.copy()
    ns.astype = lambda a, dtype: a.astype(dtype)
    ns.float64 = np.float64
    ns.int64 = np.int64
    ns.to_numpy = np.asarray
    ns.name = "cpu"
    return ns


NUMPY = _numpy_namespace()
"""numpy as an array namespace (numpy's own functions)."""


_TORCH: dict[Any, Any] = {}


def namespace(*arrays: Any) -> Any:
    """The namespace of ``arrays``: the torch namespace of their device (:mod:`.xp_torch`) if one is a torch
    tensor, else :data:`NUMPY`. (Without torch imported no tensor exists: the numpy path never imports it.)"""
    torch = sys.modules.get("torch")
    if torch is not None:
        for a in arrays:
            if isinstance(a, torch.Tensor):
                return torch_namespace(a.device)
    return NUMPY


def torch_namespace(device: Any = "cpu") -> Any:
    """The (cached) :class:`~lanefree_sumo.sim.xp_torch.TorchNamespace` of the torch device ``device``."""
    from lanefree_sumo.sim.xp_torch import TorchNamespace, torch

    key = torch.device(device)
    if key not in _TORCH:
        _TORCH[key] = TorchNamespace(key)
    return _TORCH[key]


TORCH_CPU = "torch-cpu"
"""The device name of the torch simulation on the CPU (``train.device = torch-cpu``): the GPU's program, run where
it can be checked against numpy's."""


def array_namespace(device: str) -> Any:
    """The namespace a simulation on ``device`` computes in — the one representation of ``train.device`` from the
    option to the tensors: ``cpu`` numpy (:data:`NUMPY`), ``torch-cpu`` torch on the CPU, ``cuda`` (or
    ``cuda:N``) torch on that GPU. Its ``name`` is ``device`` again."""
    return NUMPY if device == "cpu" else torch_namespace(torch_device(device))


def on_cpu(device: str) -> bool:
    """Whether ``device`` (``train.device``) computes on the CPU: ``cpu`` (numpy) and ``torch-cpu``."""
    return device in ("cpu", TORCH_CPU)


def torch_device(device: str) -> Any:
    """The ``torch.device`` the networks of a run on ``device`` (``train.device``) live on: the CPU for ``cpu``
    and ``torch-cpu``, else ``device`` itself."""
    import torch

    return torch.device("cpu" if on_cpu(device) else device)


def device_name(saved: Any) -> str:
    """A device as saved in a checkpoint, as a ``train.device`` name: None (numpy, before the name was kept) is
    ``cpu``, a ``torch.device`` of the CPU ``torch-cpu``, any other its own name."""
    if saved is None:
        return "cpu"
    if not isinstance(saved, str):
        return TORCH_CPU if saved.type == "cpu" else str(saved)
    return saved


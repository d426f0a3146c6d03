"""CUDA requests mapped to the CPU, for the process of a dry run only.

The upstream trainers ask for the GPU in a handful of ways; :func:`install` answers each of them
with the CPU:

- ``Tensor.cuda()``, ``Module.cuda()`` return the tensor / module on the CPU;
- ``Tensor.to(...)`` / ``Module.to(...)`` with a CUDA device go to the CPU;
- ``device="cuda"`` (or ``"cuda:0"``, ``torch.device("cuda")``) in the tensor factories
  (``torch.zeros``, ``tensor``, ``arange``, ``*_like``, ``Tensor.new_*`` ...) becomes the CPU;
- ``torch.cuda.set_device``, ``synchronize``, ``empty_cache``, ``reset_peak_memory_stats`` do
  nothing; ``memory_allocated``/``max_memory_allocated``/``memory_reserved`` answer 0;
  ``torch.cuda.Event(enable_timing=True)`` records wall-clock times (``elapsed_time`` in ms).

``torch.cuda.is_available()`` keeps answering False, so code that chooses its device by asking
gets the CPU without any of this. :func:`uninstall` restores everything (tests).
"""

from __future__ import annotations

import functools
import time
from typing import Any, Callable

import torch

__all__ = ["install", "uninstall", "installed", "cpu_device", "CpuEvent"]

_FACTORIES = (
    "zeros", "ones", "empty", "full", "rand", "randn", "randint", "randperm", "arange", "linspace", "logspace",
    "eye", "tensor", "as_tensor", "zeros_like", "ones_like", "empty_like", "full_like", "rand_like", "randn_like",
    "randint_like", "tril_indices", "triu_indices", "scalar_tensor",
)
_TENSOR_FACTORIES = ("new_zeros", "new_ones", "new_empty", "new_full", "new_tensor")
_SAVED: list[tuple[Any, str, Any]] = []


def cpu_device(device: Any) -> Any:
    """``device`` with any CUDA device replaced by the CPU (anything else unchanged)."""
    if isinstance(device, torch.device):
        return torch.device("cpu") if device.type == "cuda" else device
    if isinstance(device, str) and device.split(":")[0] == "cuda":
        return "cpu"
    if isinstance(device, int) and not isinstance(device, bool):
        return "cpu"  # an ordinal means a CUDA device
    return device


def _with_cpu_device(function: Callable[..., Any]) -> Callable[..., Any]:
    @functools.wraps(function)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        if "device" in kwargs:
            kwargs["device"] = cpu_device(kwargs["device"])
        return function(*args, **kwargs)

    return wrapper


def _to_cpu(function: Callable[..., Any]) -> Callable[..., Any]:
    """``Tensor.to`` / ``Module.to`` with CUDA devices (positional or keyword) sent to the CPU."""

    @functools.wraps(function)
    def wrapper(self: Any, *args: Any, **kwargs: Any) -> Any:
        args = tuple(cpu_device(a) if isinstance(a, (str, torch.device)) else a for a in args)
        if "device" in kwargs:
            kwargs["device"] = cpu_device(kwargs["device"])
        return function(self, *args, **kwargs)

    return wrapper


def _tensor_cuda(self: torch.Tensor, device: Any = None, non_blocking: bool = False, **kwargs: Any) -> torch.Tensor:
    return self.cpu()


def _module_cuda(self: torch.nn.Module, device: Any = None) -> torch.nn.Module:
    return self.cpu()


class CpuEvent:
    """``torch.cuda.Event`` on the wall clock: ``record()`` notes the time, ``elapsed_time(end)``
    is the milliseconds from this event to ``end``."""

    def __init__(self, enable_timing: bool = False, blocking: bool = False, interprocess: bool = False) -> None:
        self.time: float | None = None

    def record(self, stream: Any = None) -> None:
        self.time = time.perf_counter()

    def synchronize(self) -> None:
        """Nothing to wait for on the CPU."""

    def query(self) -> bool:
        return True

    def elapsed_time(self, end: "CpuEvent") -> float:
        if self.time is None or end.time is None:
            raise RuntimeError("both events must be recorded before elapsed_time")
        return (end.time - self.time) * 1000.0


def _constant(name: str, value: Any) -> Callable[..., Any]:
    """A stand-in of ``torch.cuda.<name>`` that returns ``value``; one function object per name
    (torch's compiler refuses one object registered under two names)."""

    def stand_in(*args: Any, **kwargs: Any) -> Any:
        return value

    stand_in.__name__ = stand_in.__qualname__ = name
    return stand_in


def _replace(owner: Any, name: str, value: Any) -> None:
    _SAVED.append((owner, name, getattr(owner, name, None)))
    setattr(owner, name, value)


def installed() -> bool:
    """Whether :func:`install` is in effect."""
    return bool(_SAVED)


def install() -> None:
    """Map CUDA requests to the CPU in this process (module docstring); idempotent."""
    if _SAVED:
        return
    for name in _FACTORIES:
        if hasattr(torch, name):
            _replace(torch, name, _with_cpu_device(getattr(torch, name)))
    for name in _TENSOR_FACTORIES:
        _replace(torch.Tensor, name, _with_cpu_device(getattr(torch.Tensor, name)))
    _replace(torch.Tensor, "cuda", _tensor_cuda)
    _replace(torch.Tensor, "to", _to_cpu(torch.Tensor.to))
    _replace(torch.nn.Module, "cuda", _module_cuda)
    _replace(torch.nn.Module, "to", _to_cpu(torch.nn.Module.to))
    for name in ("set_device", "synchronize", "empty_cache", "reset_peak_memory_stats", "ipc_collect"):
        _replace(torch.cuda, name, _constant(name, None))
    for name in ("memory_allocated", "max_memory_allocated", "memory_reserved", "max_memory_reserved"):
        _replace(torch.cuda, name, _constant(name, 0))
    _replace(torch.cuda, "Event", CpuEvent)


def uninstall() -> None:
    """Undo :func:`install`."""
    while _SAVED:
        owner, name, value = _SAVED.pop()
        setattr(owner, name, value)

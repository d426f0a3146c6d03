"""One threading policy for torch and numba (CPU), explicit and configurable.

Why. On CPU a training step alternates many short parallel regions: torch's (OpenMP, its own
``libgomp`` in ``torch/lib``) and numba's kernels (the rasterizer, the fused SSIM, PatchMatch),
which with numba's ``omp`` threading layer run on a *second* OpenMP runtime (the system
``libgomp``). When ``OMP_WAIT_POLICY`` is unset, GNU OpenMP workers busy-wait after each region
(``GOMP_SPINCOUNT`` 300000 pause loops, several milliseconds on a current Xeon) before they sleep.
Alone on a machine that costs little, but with a second training on the same two cores, the
spinning workers of both runtimes of both processes compete with the threads doing the work:
bench/rasterizer.py's forward + backward went from 0.10 s/iter to 0.94 s/iter (9x, where sharing
two cores should cost 2x). docs/speed.md has the measurements.

The policy (:class:`ThreadPolicy`, ``TrainConfig.threads``):

- ``threads``: one count for torch's intra-op pool and numba's kernels (default: the cores this
  process may run on, ``len(os.sched_getaffinity(0))``, but never more than torch was already
  told to use, by ``OMP_NUM_THREADS`` or ``torch.set_num_threads``: one per pytest-xdist worker
  or per ablation cell, say);
- ``numba_layer``: numba's threading layer, ``"workqueue"`` by default (its workers sleep on a
  condition variable, they never spin, and it needs no environment set before start-up);
- ``wait_policy``: ``OMP_WAIT_POLICY`` for the OpenMP runtimes (``"passive"`` by default: idle
  workers sleep at once).

Environment variables are read by an OpenMP runtime when it is loaded, which for torch's is
``import torch``: :meth:`ThreadPolicy.apply_environment` must run before that (the ``polargs``
command and the benches do it first thing). :meth:`ThreadPolicy.apply` (run by the reference
trainer at construction) sets what can still be set at run time (thread counts, numba's layer
until its first parallel kernel) and reports, in :attr:`AppliedPolicy.notes`, what came too late.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any, Literal, MutableMapping

from polargs_plugin.config import CheckedConfig, at_least

__all__ = [
    "ThreadPolicy", "AppliedPolicy", "NumbaLayer", "WaitPolicy", "available_cores", "numba_threads", "numba_scheduling", "current_policy",
    "numba_path",
]

#: numba's threading layers (:attr:`ThreadPolicy.numba_layer`).
NumbaLayer = Literal["workqueue", "omp", "tbb", "default"]
#: OpenMP's wait policies (:attr:`ThreadPolicy.wait_policy`).
WaitPolicy = Literal["passive", "active"]

_applied: "AppliedPolicy | None" = None


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity mask; ``os.cpu_count()`` where that is unknown)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # not Linux
        return max(1, os.cpu_count() or 1)


@dataclass
class ThreadPolicy(CheckedConfig):
    """How many threads torch and numba use, numba's threading layer, OpenMP's wait policy.

    Attributes:
        threads: threads for torch's intra-op pool and for numba's kernels; >= 1. ``None``
            (default): the cores available to the process (:func:`available_cores`), capped by
            torch's current count (which ``OMP_NUM_THREADS`` or an earlier
            ``torch.set_num_threads`` lowered).
        numba_layer: numba's threading layer: ``"workqueue"`` (default; workers never spin),
            ``"omp"`` (OpenMP, a second runtime next to torch's), ``"tbb"`` (needs TBB >= 2021.6)
            or ``"default"`` (numba's own choice: tbb, else omp, else workqueue). Takes effect only
            before numba's first parallel kernel in the process.
        wait_policy: ``OMP_WAIT_POLICY`` for OpenMP runtimes loaded after
            :meth:`apply_environment`: ``"passive"`` (default; idle workers sleep), ``"active"``
            (they spin: lowest latency on a machine of one's own) or ``None`` (leave the
            environment alone).
    """

    threads: int | None = field(default=None, metadata=at_least(1))
    numba_layer: NumbaLayer = "workqueue"
    wait_policy: WaitPolicy | None = "passive"

    # ------------------------------------------------------------------------ resolution
    def resolved_threads(self) -> int:
        """The thread count this policy sets (see :attr:`threads`)."""
        if self.threads is not None:
            return int(self.threads)
        cores = available_cores()
        if "torch" in sys.modules:
            import torch

            return max(1, min(cores, torch.get_num_threads()))
        env = os.environ.get("OMP_NUM_THREADS", "")
        if env.isdigit() and int(env) > 0:
            return min(cores, int(env))
        return cores

    def environment(self) -> dict[str, str]:
        """The environment variables of this policy (set by :meth:`apply_environment`)."""
        env: dict[str, str] = {}
        if self.wait_policy is not None:
            env["OMP_WAIT_POLICY"] = self.wait_policy.upper()
        if self.numba_layer != "default":
            env["NUMBA_THREADING_LAYER"] = self.numba_layer
        return env

    # --------------------------------------------------------------------------- applying
    def apply_environment(self, environ: MutableMapping[str, str] | None = None, override: bool = True) -> list[str]:
        """Set :meth:`environment` in ``environ`` (default ``os.environ``); call it before torch and
        numba are imported (first thing in a command's entry point) so that their OpenMP runtimes
        read it. With ``override=False`` variables already set are kept (the user's choice).

        Returns:
            notes on what came too late for this process (empty when called in time).
        """
        target = os.environ if environ is None else environ
        changed = False
        for key, value in self.environment().items():
            if (override or key not in target) and target.get(key) != value:
                changed = changed or key == "OMP_WAIT_POLICY"
                target[key] = value
        notes = []
        if environ is None and changed and "torch" in sys.modules:
            notes.append(
                "torch was imported before the thread policy's environment: OMP_WAIT_POLICY does not "
                "reach torch's OpenMP runtime in this process (set it before `import torch`, e.g. "
                "ThreadPolicy().apply_environment() first thing, or in the shell)"
            )
        return notes

    def apply(self) -> "AppliedPolicy":
        """Apply the policy to this process: environment (for runtimes not started yet), numba's
        threading layer (if no parallel kernel ran yet), numba's and torch's thread counts.

        Safe to call repeatedly (the reference trainer calls it at construction). The counts are
        process-wide: the last applied policy wins.

        Returns:
            :class:`AppliedPolicy`: what is in effect, with notes on what could not be changed.
        """
        global _applied
        notes = self.apply_environment()
        threads = self.resolved_threads()
        import numba
        import torch
        from numba.np.ufunc import parallel as numba_parallel

        if not numba_parallel._is_initialized:
            numba.config.THREADING_LAYER = self.numba_layer
        elif self.numba_layer != "default" and numba.threading_layer() != self.numba_layer:
            notes.append(
                f"numba's threading layer is already {numba.threading_layer()!r} (a parallel kernel ran "
                f"before the policy): {self.numba_layer!r} not applied"
            )
        limit = int(numba.config.NUMBA_NUM_THREADS)
        if threads > limit:
            notes.append(f"numba allows at most NUMBA_NUM_THREADS = {limit} threads: numba uses {limit}")
        numba.set_num_threads(min(threads, limit))
        if torch.get_num_threads() != threads:
            torch.set_num_threads(threads)
        _applied = AppliedPolicy(policy=self, threads=threads, numba_threads=min(threads, limit), notes=notes)
        return _applied

    # ------------------------------------------------------------------------ persistence
    @classmethod
    def from_dict(cls, data: "dict[str, Any] | ThreadPolicy | None", where: str = "") -> "ThreadPolicy":
        """Inverse of :meth:`to_dict` (a policy passes through; None gives the default); unknown
        keys raise ``KeyError``, bad values ``ValueError`` (:meth:`CheckedConfig.from_dict`)."""
        if isinstance(data, ThreadPolicy):
            return data
        return super().from_dict(data or {}, where)


@dataclass
class AppliedPolicy:
    """What :meth:`ThreadPolicy.apply` put in effect.

    Attributes:
        policy: the policy applied.
        threads: torch's intra-op thread count.
        numba_threads: numba's kernels' thread count (``threads`` capped by NUMBA_NUM_THREADS).
        notes: settings that came too late for this process (see the module docstring).
    """

    policy: ThreadPolicy
    threads: int
    numba_threads: int
    notes: list[str] = field(default_factory=list)

    def layer(self) -> str:
        """numba's threading layer in effect (``"not started"`` before the first parallel kernel)."""
        import numba

        try:
            return numba.threading_layer()
        except ValueError:
            return "not started"


def current_policy() -> AppliedPolicy | None:
    """The policy last applied in this process (None before any)."""
    return _applied


def numba_threads() -> int:
    """Threads for the next numba kernel: the applied policy's count when one was applied, else
    torch's (one per pytest-xdist worker, say), at most ``NUMBA_NUM_THREADS``.

    If torch's count was lowered after the policy (``torch.set_num_threads(1)`` in an ablation
    cell, say), the lower count wins, so numba never uses more threads than torch was told to.
    """
    import numba
    import torch

    count = torch.get_num_threads()
    if _applied is not None:
        count = min(count, _applied.numba_threads)
    return max(1, min(count, int(numba.config.NUMBA_NUM_THREADS)))


@contextlib.contextmanager
def numba_scheduling(threads: int | None = None, chunksize: int = 0) -> Iterator[None]:
    """The numba kernels run inside use ``threads`` threads (default :func:`numba_threads`, the
    policy's count; at most ``NUMBA_NUM_THREADS``) and hand a ``prange``'s iterations out
    ``chunksize`` at a time (0: numba's even split; a few at a time where iterations differ a lot
    in cost, like the rasterizer's tiles). Both settings are restored on exit, so a caller's own
    numba settings survive a render, an SSIM or a nearest-neighbour query."""
    import numba

    limit = int(numba.config.NUMBA_NUM_THREADS)
    count = numba_threads() if threads is None else max(1, min(int(threads), limit))
    previous_threads = numba.get_num_threads()
    numba.set_num_threads(count)
    previous_chunksize = numba.set_parallel_chunksize(chunksize)
    try:
        yield
    finally:
        numba.set_parallel_chunksize(previous_chunksize)
        numba.set_num_threads(previous_threads)


def numba_path(tensor) -> bool:
    """Whether a compiled CPU kernel (numba, with a hand-written backward) may serve ``tensor``:
    a CPU float32 / float64 tensor, outside tracing and ``torch.func`` transforms (they need the
    torch operations, whose graph they can follow). The losses and SSIM take their torch path
    otherwise (CUDA, other dtypes)."""
    import torch

    return (tensor.device.type == "cpu" and tensor.dtype in (torch.float32, torch.float64)
            and not (torch.jit.is_tracing() or torch._C._are_functorch_transforms_active()))

"""Before a training starts: the memory and the time it will take, and whether the memory is there.

:func:`estimate_memory` models a run's peak resident memory from what the process holds once
the data is read (the compact views) plus what training adds: the larger of one step's and one
Dense call's per-pixel buffers on the largest view, Dense's per-view state where it is held in
memory, the maps caches and the Gaussians. :func:`estimate_time` times a render + backward of the largest view on the model as
built (the model is left unchanged) and scales it by the schedule. The constants were measured on
the bundled scenes at the CPU preset (2 threads) at 128x128 to 1224x1024 (docs/real-size.md);
the estimate is a guide (within about 30 %), the progress bar then shows the measured rate.
"""

from __future__ import annotations

import math
import resource
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

if TYPE_CHECKING:
    from polargs_plugin.backends.reference.trainer import TrainConfig, Trainer
    from polargs_plugin.config import PolarConfig
    from polargs_plugin.types import View

__all__ = ["RunEstimate", "estimate_memory", "estimate_time", "available_memory", "resident_memory", "peak_memory",
           "device_memory", "dense_calls"]

#: Bytes per pixel of the largest view that one Base step allocates (render, loss, backward).
STEP_BYTES_PER_PIXEL = 450
#: ... and what the PolarGS loss terms add to a step.
HOOKS_BYTES_PER_PIXEL = 250
#: Bytes per pixel of the reference view that one Dense call allocates (PatchMatch, renders of
#: the sources, filters).
DENSE_BYTES_PER_PIXEL = 900
#: Bytes per pixel of every view that Dense keeps in memory once it visited the view (float16
#: depth and normal, a bool mask: ``densify.densifier.STATE_DTYPE``) when the maps have no cache
#: folder; with one (every ``polargs train``), that state lives in files there instead.
DENSE_STATE_BYTES_PER_PIXEL = 9
#: Bytes per Gaussian: parameters, gradients and Adam moments (SH degree 3 at most), density
#: statistics, the rasterizer's per-Gaussian buffers.
BYTES_PER_GAUSSIAN = 2048
#: Mean step time over a CPU-preset run / the step on the initial Gaussians (the model grows).
STEP_GROWTH = 1.6
#: Step time with the PolarGS loss terms / a Base step.
HOOKS_FACTOR = 1.2
#: One Dense call's time / one Base step's, at the same pixel count.
DENSE_STEPS_PER_CALL = 18.0


@dataclass(frozen=True)
class RunEstimate:
    """What a training is expected to need.

    Attributes:
        views: number of training views.
        size: (W, H) of the largest view.
        pixels: input pixels (the views' W x H summed).
        image_bytes: what the views' images take in memory as stored.
        fixed_bytes: the part of the peak that does not scale with the pixels (the process
            without its images, the Gaussians, the caches).
        held_bytes: resident memory of the process when the estimate was made (data read).
        peak_bytes: expected peak resident memory of the training.
        available_bytes: memory the system can still give the process (None: unknown).
        step_seconds: a timed render + backward of the largest view on the initial model (None:
            not timed yet).
        seconds: expected training wall time (None: not timed yet).
        dense_calls: Dense calls of the schedule.
        memory: which memory the figures are of: ``"memory"`` (the host's) or ``"GPU memory"``
            (a CUDA training: the views, a step's and Dense's buffers live there).
    """

    views: int
    size: tuple[int, int]
    pixels: int
    image_bytes: int
    fixed_bytes: int
    held_bytes: int
    peak_bytes: int
    available_bytes: int | None
    step_seconds: float | None = None
    seconds: float | None = None
    dense_calls: int = 0
    memory: str = "memory"

    @property
    def reach_bytes(self) -> int | None:
        """The most a training process can hold: what this one holds plus what is available."""
        return None if self.available_bytes is None else self.held_bytes + self.available_bytes

    @property
    def fits(self) -> bool:
        """Whether the peak is within reach (True when the available memory is unknown)."""
        return self.reach_bytes is None or self.peak_bytes <= self.reach_bytes

    def peak_at(self, resolution: int) -> int:
        """The peak of the same data read at a further divisor ``resolution``: the parts that
        scale with the pixels divided by its square."""
        return self.fixed_bytes + math.ceil((self.peak_bytes - self.fixed_bytes) / resolution**2)

    def memory_line(self) -> str:
        reach = "" if self.reach_bytes is None else f", {_gb(self.reach_bytes)} within reach"
        return (f"estimate: peak {self.memory} about {_gb(self.peak_bytes)} ({self.views} views of {self.size[0]}x"
                f"{self.size[1]}, {_gb(self.image_bytes)} of images held{reach})")

    def time_line(self, iterations: int) -> str:
        dense = f", {self.dense_calls} Dense calls" if self.dense_calls else ""
        return (f"estimate: about {_duration(self.seconds)} for {iterations} iterations (a first step takes "
                f"{self.step_seconds:.2f} s{dense}); the progress bar shows the measured rate")

    def refusal(self) -> str:
        """One line: what is needed, what is within reach, and the ``--resolution`` that fits."""
        from polargs_plugin.data.resolution import DIVISORS

        reach = self.reach_bytes or 0
        fitting = next((r for r in DIVISORS[1:] if self.peak_at(r) <= reach), None)
        advice = (f"read the images smaller with --resolution {fitting} (about {_gb(self.peak_at(fitting))})"
                  if fitting is not None else "read the images smaller with --resolution (8, or a target width) "
                  "or use fewer views")
        return (f"--resolution: training would need about {_gb(self.peak_bytes)} of {self.memory} ({self.views} views of "
                f"{self.size[0]}x{self.size[1]}) but {_gb(reach)} is within reach; {advice}")


def _gb(count: float) -> str:
    return f"{count / 2**30:.1f} GB" if count >= 2**30 else f"{count / 2**20:.0f} MB"


def _duration(seconds: float | None) -> str:
    if seconds is None:
        return "?"
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def peak_memory() -> int:
    """The process's peak resident memory so far, in bytes."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak if sys.platform == "darwin" else peak * 1024  # kilobytes elsewhere


def resident_memory() -> int:
    """The process's resident memory now (Linux ``/proc``), else its peak so far."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return peak_memory()


def available_memory() -> int | None:
    """Memory the system can still give: ``MemAvailable`` (Linux), capped by a cgroup's limit;
    None where neither can be read."""
    values = []
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                values.append(int(line.split()[1]) * 1024)
    except OSError:
        pass
    cgroup = Path("/sys/fs/cgroup")
    try:
        limit = (cgroup / "memory.max").read_text().strip()
        if limit != "max":
            values.append(int(limit) - int((cgroup / "memory.current").read_text()))
    except (OSError, ValueError):
        pass
    return min(values) if values else None


def dense_calls(polar: PolarConfig | None, iterations: int) -> int:
    """Dense calls of ``polar``'s schedule within ``iterations``."""
    if polar is None or not polar.densify.enabled:
        return 0
    d = polar.densify
    first = math.ceil(d.start_iter / d.interval) * d.interval
    last = min(d.end_iter, iterations)
    return max(0, (last - first) // d.interval + 1) if last >= first else 0


def estimate_memory(views: Sequence[View], train: TrainConfig, polar: PolarConfig | None,
                    held: int | None = None, available: int | None = -1,
                    maps_folder: bool | None = None) -> RunEstimate:
    """The peak memory of training ``views`` with these settings, and what is available.

    Args:
        views: the training views (read: their images are held).
        train: the trainer's settings.
        polar: the PolarGS settings (None: Base).
        held: the process's resident memory now (default: measured).
        available: the memory the system can still give (default -1: measured; None: unknown).
        maps_folder: whether the maps will have a cache folder, which also holds Dense's per-view
            state (default: whether ``polar.cache_dir`` is set).
    """
    from polargs_plugin.correction.store import MEMORY_BUDGET

    image_bytes = sum(v.nbytes for v in views)
    memory = "memory"
    on_device = device_memory(train.device) if held is None and available == -1 else None
    if on_device is not None:  # the views, the step and Dense live in the GPU's memory
        allocated, free = on_device
        held, available, memory = allocated + image_bytes, free - image_bytes, "GPU memory"
    held = resident_memory() if held is None else held
    available = available_memory() if available == -1 else available
    largest = max(views, key=lambda v: v.width * v.height)
    view_pixels = largest.width * largest.height
    pixels = sum(v.width * v.height for v in views)
    per_step = STEP_BYTES_PER_PIXEL + (HOOKS_BYTES_PER_PIXEL if polar is not None else 0)
    calls = dense_calls(polar, train.iterations)
    growth = per_step * view_pixels
    if calls:
        # a Dense call runs after the step's backward (its buffers are free by then): the larger of the two
        state_in_memory = not (polar.cache_dir is not None if maps_folder is None else maps_folder)
        growth = max(growth, DENSE_BYTES_PER_PIXEL * view_pixels) + DENSE_STATE_BYTES_PER_PIXEL * pixels * state_in_memory
    cap = train.density.max_gaussians or 3 * train.num_init_points
    appended = calls * polar.densify.max_new_per_call if calls else 0
    fixed = BYTES_PER_GAUSSIAN * (cap + appended) + 2 * MEMORY_BUDGET * (polar is not None)
    return RunEstimate(views=len(views), size=(largest.width, largest.height), pixels=pixels, image_bytes=image_bytes,
                       fixed_bytes=held - image_bytes + fixed, held_bytes=held, peak_bytes=held + growth + fixed,
                       available_bytes=available, dense_calls=calls, memory=memory)


def device_memory(device: str) -> tuple[int, int] | None:
    """(bytes torch holds, bytes free) on a CUDA ``device``; None for any other device."""
    import torch

    target = torch.device(device)
    if target.type != "cuda" or not torch.cuda.is_available():
        return None
    free, _ = torch.cuda.mem_get_info(target)
    return int(torch.cuda.memory_allocated(target)), int(free)


def estimate_time(estimate: RunEstimate, trainer: Trainer, iterations: int) -> RunEstimate:
    """``estimate`` with the expected training time: a timed step of the largest view on
    ``trainer``'s model (:meth:`Trainer.time_step`; the model is left unchanged) times the
    iterations left, grown as the model grows, plus the Dense calls."""
    largest = max(trainer.views, key=lambda v: v.width * v.height)
    step = trainer.time_step(largest)
    per_step = step * STEP_GROWTH * (HOOKS_FACTOR if trainer.hooks is not None else 1.0)
    left = max(0, iterations - trainer.iteration)
    seconds = per_step * left + estimate.dense_calls * step * DENSE_STEPS_PER_CALL * left / max(iterations, 1)
    return replace(estimate, step_seconds=step, seconds=seconds)


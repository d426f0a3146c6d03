"""Cost of ``PolarHooks.loss`` per training iteration, as a ratio to the base step.

One reference trainer (``TrainConfig.cpu()``: 600 iterations, refinement every 2 from 10 to 300)
on a synthetic scene alternates plain 3DGS steps and steps with PolarHooks
(``PolarConfig.cpu_demo(0.02)``: PC on, L_dn from iteration 140, L_scale on; Dense off, since its
cost is PatchMatch's, measured by bench/patchmatch.py, so L_n never has a target), so that both
see the same Gaussians and the same machine load. Two iteration ranges are measured: one before
``depth_normal_from_iter`` (hook terms L_s, L_o, L_scale) and one after it (plus L_dn).
Printed per range:

- step ratio: (mean step time with hooks - without) / mean step time without (target <= 10 %),
  and the median over ABBA quadruples of consecutive steps (less sensitive to load spikes; ABBA
  because vanilla refinement runs on every other iteration), in wall
  time and in this process's CPU time (less sensitive to other processes on a shared machine);
- paired ratio: at every measured iteration, render + colour loss + backward is timed with and
  without ``hooks.loss`` on the same view and the same Gaussians (no optimizer step in between,
  twice each, alternating); the mean difference (the hooks' forward and the backward they add)
  over the mean base step. Refinement and load changes cannot leak into this one;
- loss-call ratio: the time inside ``hooks.loss`` alone (forward) / the base step.

The machine's load average is printed: timings on a shared machine are noisy, compare ratios.

Usage: python bench/plugin_overhead.py [--scene bumpy_mixed] [--steps 40] [--size 96] [--threads 2]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time

import torch

from polargs_plugin.backends.reference.trainer import TrainConfig, Trainer
from polargs_plugin.config import PolarConfig
from polargs_plugin.data.synthetic import generate_scene
from polargs_plugin.hooks import PolarHooks


class TimedHooks(PolarHooks):
    """PolarHooks that accumulates the wall time spent in :meth:`loss`."""

    seconds = 0.0
    calls = 0

    def loss(self, *args, **kwargs):
        start = time.perf_counter()
        out = super().loss(*args, **kwargs)
        self.seconds += time.perf_counter() - start
        self.calls += 1
        return out


def _timed_step(trainer: Trainer, hooks: PolarHooks | None) -> tuple[float, float, dict[str, float]]:
    """(wall seconds, process CPU seconds, logs) of one step."""
    trainer.hooks = hooks
    wall, cpu = time.perf_counter(), time.process_time()
    logs = trainer.step()
    return time.perf_counter() - wall, time.process_time() - cpu, logs


def _forward_backward(trainer: Trainer, index: int, hooks: PolarHooks | None) -> tuple[float, float]:
    """(wall, process CPU) seconds of render + colour loss (+ hooks.loss) + backward, gradients
    discarded."""
    view, model = trainer.views[index], trainer.model
    wall, cpu = time.perf_counter(), time.process_time()
    render = trainer.render(view)
    loss = trainer.base_loss(render.color, trainer.target(view))
    if hooks is not None:
        loss = loss + hooks.loss(trainer.iteration + 1, view, render, model.state())[0]
    loss.backward()
    seconds = time.perf_counter() - wall, time.process_time() - cpu
    model.optimizer.zero_grad(set_to_none=True)
    return seconds


def _measure(trainer: Trainer, hooks: TimedHooks, steps: int) -> dict[str, float]:
    """Alternate plain and hooked steps; print the ratios for this iteration range and return them."""
    first = trainer.iteration + 1
    hooks.seconds, hooks.calls = 0.0, 0
    plain, hooked, paired = [], [], []
    for pair in range(steps):
        index = pair % len(trainer.views)
        times = [_forward_backward(trainer, index, h) for h in (None, hooks, hooks, None)]
        paired.append([(times[1][c] + times[2][c] - times[0][c] - times[3][c]) / 2 for c in (0, 1)])
        # ABBA order: refinement runs every other iteration, so a fixed order would give it to
        # one side only.
        for with_hooks in (False, True) if pair % 2 == 0 else (True, False):
            *seconds, step_logs = _timed_step(trainer, hooks if with_hooks else None)
            (hooked if with_hooks else plain).append(seconds)
            if with_hooks:
                logs = step_logs
    in_loss = hooks.seconds / hooks.calls  # the paired calls included
    terms = ", ".join(k for k in logs if k.startswith("l_"))
    figures: dict[str, float] = {"first_iteration": first, "last_iteration": trainer.iteration}
    print(f"iterations {first}-{trainer.iteration} ({steps} pairs), {trainer.model.num} Gaussians; hook terms: {terms}")
    for column, clock in enumerate(("wall", "CPU ")):
        base = statistics.fmean(p[column] for p in plain)
        marginal = statistics.fmean(m[column] for m in paired)
        print(f"  {clock} paired: hooks.loss forward + the backward it adds {marginal * 1e3:6.2f} ms = "
              f"{marginal / base:+6.1%} of the base step (target <= 10%)")
        figures[f"paired_overhead_{clock.strip().lower()}"] = marginal / base
    for column, clock in enumerate(("wall", "CPU ")):
        base = statistics.fmean(p[column] for p in plain)
        with_hooks = statistics.fmean(h[column] for h in hooked)
        quads = [(sum(h[column] for h in hooked[i : i + 2]), sum(p[column] for p in plain[i : i + 2]))
                 for i in range(0, steps - 1, 2)]
        median = statistics.median((h - p) / p for h, p in quads)
        print(f"  {clock} base step {base * 1e3:7.1f} ms, with PolarHooks {with_hooks * 1e3:7.1f} ms: overhead "
              f"{(with_hooks - base) / base:+6.1%} (median over ABBA quads {median:+6.1%}; target <= 10%)")
        figures[f"step_overhead_{clock.strip().lower()}"] = (with_hooks - base) / base
        figures[f"base_step_ms_{clock.strip().lower()}"] = base * 1e3
    base = statistics.fmean(p[0] for p in plain)
    print(f"  inside hooks.loss (forward, wall) {in_loss * 1e3:.2f} ms = {in_loss / base:.1%} of the base step")
    figures["hooks_loss_share_wall"] = in_loss / base
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="bumpy_mixed")
    parser.add_argument("--views", type=int, default=8)
    parser.add_argument("--size", type=int, default=96)
    parser.add_argument("--steps", type=int, default=40, help="pairs of steps per iteration range (even)")
    parser.add_argument("--warmup", type=int, default=10)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    scene = generate_scene(args.scene, num_views=args.views, width=args.size, height=args.size)
    polar = PolarConfig.cpu_demo(0.02)
    polar.densify.enabled = False
    from_iter = polar.losses.depth_normal_from_iter
    if args.warmup + 2 * args.steps >= from_iter:
        parser.error(f"--warmup + 2 --steps must stay below depth_normal_from_iter = {from_iter}")
    hooks = TimedHooks(polar)
    trainer = Trainer(scene.views, TrainConfig.cpu(progress=False), hooks=hooks)
    print(f"scene {args.scene}, {args.views} views {args.size}x{args.size}, torch threads {torch.get_num_threads()}, "
          f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())} ({os.cpu_count()} CPUs)")
    print(f"TrainConfig.cpu(), PolarConfig.cpu_demo(0.02) with Dense off: L_dn from iteration {from_iter}")
    for _ in range(args.warmup):  # the first step runs hooks.preprocess
        trainer.step()
    before_l_dn = _measure(trainer, hooks, args.steps)
    while trainer.iteration < from_iter:  # hooked steps up to L_dn's start
        trainer.step()
    with_l_dn = _measure(trainer, hooks, args.steps)
    print(f"load average at the end {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print(json.dumps({"bench": "plugin_overhead", "scene": args.scene, "views": args.views, "size": args.size,
                      "threads": args.threads, "before_l_dn": before_l_dn, "with_l_dn": with_l_dn,
                      "load_average": os.getloadavg()[0]}))


if __name__ == "__main__":
    main()

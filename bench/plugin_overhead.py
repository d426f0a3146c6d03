"""Cost of ``PolarHooks.loss`` per training iteration, as a ratio to the base step.

One reference trainer on a synthetic scene alternates plain 3DGS steps and steps with PolarHooks
(PC + every loss switched on from the first iteration; Dense off, since its cost is PatchMatch's,
measured by bench/patchmatch.py), so that both see the same Gaussians and the same machine load.
Printed:

- step ratio: (mean step time with hooks - without) / mean step time without (target <= 10 %);
- loss-call ratio: the time inside ``hooks.loss`` alone (forward) / the base step.

Usage: python bench/plugin_overhead.py [--scene bumpy_mixed] [--steps 60] [--size 96] [--threads 2]
"""

from __future__ import annotations

import argparse
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="bumpy_mixed")
    parser.add_argument("--views", type=int, default=8)
    parser.add_argument("--size", type=int, default=96)
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--warmup", type=int, default=10)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    scene = generate_scene(args.scene, num_views=args.views, width=args.size, height=args.size)
    train_cfg = TrainConfig.cpu(progress=False)
    polar = PolarConfig.synthetic()
    polar.densify.enabled = False
    polar.losses.depth_normal_from_iter = 0
    hooks = TimedHooks(polar)
    trainer = Trainer(scene.views, train_cfg, hooks=hooks)
    for _ in range(args.warmup):  # the first step runs hooks.preprocess
        trainer.step()
    hooks.seconds, hooks.calls = 0.0, 0
    t_plain = t_hooked = 0.0
    for _ in range(args.steps):
        trainer.hooks = None
        start = time.perf_counter()
        trainer.step()
        t_plain += time.perf_counter() - start
        trainer.hooks = hooks
        start = time.perf_counter()
        logs = trainer.step()
        t_hooked += time.perf_counter() - start
    base = t_plain / args.steps
    with_hooks = t_hooked / args.steps
    in_loss = hooks.seconds / hooks.calls
    print(f"scene {args.scene}, {args.views} views {args.size}x{args.size}, {args.steps} steps after "
          f"{args.warmup} warm-up, torch threads {torch.get_num_threads()}")
    print(f"{trainer.model.num} Gaussians; hook terms: " + ", ".join(k for k in logs if k.startswith("l_")))
    print(f"base step               {base * 1e3:8.1f} ms")
    print(f"step with PolarHooks    {with_hooks * 1e3:8.1f} ms   overhead {(with_hooks - base) / base:+.1%} (target <= 10%)")
    print(f"inside hooks.loss       {in_loss * 1e3:8.1f} ms   = {in_loss / base:.1%} of the base step")


if __name__ == "__main__":
    main()

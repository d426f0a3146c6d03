"""A custom 3DGS trainer that gains PolarGS through PolarHooks (the first way in).

Everything a trainer of your own does, in a few lines each: parameters in a dict with one Adam,
a render function returning ``RenderOut``, the trainer's colour loss, and the four hook calls.
The loop in :func:`train` is README's, line for line, and touches only what ``polargs_plugin``
itself exports. The bundled rasterizer renders here; with your own, return its colour, depth,
normal and alpha (``polargs_plugin.kit.aux_channels`` gives the extra channels for normal /
alpha / depth).

    python examples/custom_trainer.py --scene bumpy_mixed --iterations 300 --size 64
"""

from __future__ import annotations

import argparse

import torch

from polargs_plugin import PolarConfig, PolarHooks, RenderOut, View, append_rows, raw_from_new, state_from_raw

# the stand-ins for a trainer's own parts: the bundled rasterizer, a scene, the initial points
from polargs_plugin.backends.reference.model import init_points_from_masks
from polargs_plugin.backends.reference.rasterizer import rasterize
from polargs_plugin.data.synthetic import generate_scene
from polargs_plugin.kit import logit, rgb_to_sh
from polargs_plugin.losses import photometric_loss


def make_params(views: list[View], n: int) -> dict[str, torch.nn.Parameter]:
    """Raw parameters (names of ``polargs_plugin.kit.RAW_NAMES``), initialised on the masks' hull."""
    points, colors = init_points_from_masks(views, n, generator=torch.Generator().manual_seed(0))
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1
    raw = {
        "means": points,
        "sh_dc": rgb_to_sh(colors)[:, None],
        "sh_rest": torch.zeros(n, 0, 3),  # SH degree 0 in this example
        "opacity_logits": logit(torch.full((n,), 0.1)),
        "log_scales": torch.full((n, 3), -4.0),
        "quats": quats,
    }
    return {name: torch.nn.Parameter(value) for name, value in raw.items()}


def make_optimizer(params: dict[str, torch.nn.Parameter], extent: float) -> torch.optim.Adam:
    lrs = {"means": 1.6e-3 * extent, "sh_dc": 0.025, "sh_rest": 0.0, "opacity_logits": 0.05,
           "log_scales": 0.01, "quats": 0.002}
    return torch.optim.Adam([{"params": [p], "lr": lrs[k], "name": k} for k, p in params.items()], eps=1e-15)


def render_params(params: dict[str, torch.Tensor], view: View) -> RenderOut:
    state = state_from_raw(params)
    colors = torch.cat([params["sh_dc"], params["sh_rest"]], dim=1)
    return rasterize(state.means, state.quats, state.scales, state.opacities, colors,
                     view.K.float(), view.world_to_camera.float(), view.width, view.height)


def train(views: list[View], iterations: int, config: PolarConfig, num_points: int = 2000) -> dict[str, float]:
    params = make_params(views, num_points)
    centres = torch.stack([v.camera_center for v in views]).float()
    optimizer = make_optimizer(params, float((centres - centres.mean(0)).norm(dim=1).max()))

    def render_fn(view: View) -> RenderOut:
        return render_params(params, view)  # reads the dict each call: appended rows take part at once

    def colour_loss(color: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
        # the trainer's loss as the PC term assumes it: the same SSIM share, the target clamped
        return photometric_loss(color.clamp(0, 1), image.clamp(0, 1), ssim_weight=config.losses.ssim_weight)

    hooks = PolarHooks(config)
    hooks.preprocess(views)                           # once (maps cached on disk with config.cache_dir)
    for it in range(1, iterations + 1):               # iterations are 1-based for the hooks
        view = views[it % len(views)]
        render = render_fn(view)                      # -> RenderOut(color, depth, normal, alpha, ...)
        loss = colour_loss(render.color, view.image)  # your own loss terms
        extra, logs = hooks.loss(it, view, render, state_from_raw(params))  # activated Gaussians
        (loss + extra).backward(); optimizer.step(); optimizer.zero_grad()
        if hooks.densify_due(it):                     # Dense's schedule
            with torch.no_grad():
                new = hooks.densify(it, view, render_fn, state_from_raw(params), render=render)
            if new is not None:                       # NewGaussians: raw rows, zero Adam moments
                append_rows(params, optimizer, raw_from_new(new, params["sh_rest"].shape[1]))
        if it % 50 == 0 or it == iterations:
            print(f"it {it:5d}  loss {loss.item():.4f}  +polar {extra.item():.4f}  "
                  f"N {params['means'].shape[0]}", flush=True)
    return {"loss": loss.item(), "num_gaussians": params["means"].shape[0],
            "appended": params["means"].shape[0] - num_points}


def main(argv: list[str] | None = None) -> dict[str, float]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="bumpy_mixed", help="bundled scene name")
    parser.add_argument("--views", type=int, default=12, help="number of views")
    parser.add_argument("--size", type=int, default=64, help="image width and height (pixels)")
    parser.add_argument("--iterations", type=int, default=300, help="training iterations")
    args = parser.parse_args(argv)
    views = generate_scene(args.scene, num_views=args.views, width=args.size, height=args.size).views
    config = PolarConfig.synthetic()
    # the paper's schedule (Dense 1k-7k every 100, L_dn from 7k) shrunk to this short run
    config.densify.start_iter = args.iterations // 5
    config.densify.end_iter = args.iterations * 4 // 5
    config.densify.interval = max(1, args.iterations // 20)
    config.losses.depth_normal_from_iter = args.iterations // 2
    return train(views, args.iterations, config)


if __name__ == "__main__":
    main()

"""gsplat training with PolarGS (PolarStrategy + polar_loss): a short, self-contained snippet.

RUNS ONLY WITH CUDA: gsplat's ``rasterization`` (and ``spherical_harmonics``) are CUDA kernels,
compiled by gsplat on first use. On a CPU machine this script stops with a message; the same
code is exercised on CPU in tests/test_adapter_gsplat.py through a reference-rasterizer stand-in.

    pip install 'polargs_plugin[gsplat]'
    python examples/gsplat_polar_strategy.py [--steps 3000] [--mcmc]

The scene is the bundled synthetic ``glossy_plane_sphere`` (no download); with your own data,
build the views with ``view_from_gsplat(viewmats, Ks, stokes, name=...)`` from the ``viewmats``
(``inv(data["camtoworld"])``) and ``Ks`` your trainer already passes to ``rasterization``.
"""

from __future__ import annotations

import argparse
import math
import sys

import torch


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--mcmc", action="store_true", help="MCMCStrategy inside PolarStrategy")
    args = parser.parse_args()
    if not torch.cuda.is_available():
        sys.exit("gsplat's rasterization needs CUDA; this example does not run on CPU (see the docstring)")

    from gsplat import rasterization
    from gsplat.strategy import DefaultStrategy, MCMCStrategy

    from polargs_adapters.gsplat import (
        PolarStrategy, gsplat_cameras, make_render_fn, polar_backgrounds, polar_colors, polar_loss, sh_colors,
    )
    from polargs_plugin import PolarConfig, PolarHooks
    from polargs_plugin.backends.reference.model import init_points_from_masks
    from polargs_plugin.data.synthetic import generate_scene
    from polargs_plugin.kit import rgb_to_sh
    from polargs_plugin.losses import photometric_loss

    device = torch.device("cuda")
    cpu_views = generate_scene("glossy_plane_sphere", num_views=24, width=256, height=256).views
    views = [v.to(device) for v in cpu_views]
    sh_degree = 3

    # --- simple_trainer-style parameters and one Adam per name
    points, rgb = init_points_from_masks(cpu_views, 20_000, 64)
    n = len(points)
    params = torch.nn.ParameterDict({
        "means": torch.nn.Parameter(points.float()),
        "scales": torch.nn.Parameter(torch.full((n, 3), math.log(0.01))),
        "quats": torch.nn.Parameter(torch.nn.functional.normalize(torch.randn(n, 4), dim=-1)),
        "opacities": torch.nn.Parameter(torch.full((n,), math.log(0.1 / 0.9))),
        "sh0": torch.nn.Parameter(rgb_to_sh(rgb.float())[:, None, :]),
        "shN": torch.nn.Parameter(torch.zeros(n, (sh_degree + 1) ** 2 - 1, 3)),
    }).to(device)
    lrs = {"means": 1.6e-4, "scales": 5e-3, "quats": 1e-3, "opacities": 5e-2, "sh0": 2.5e-3, "shN": 2.5e-3 / 20}
    optimizers = {k: torch.optim.Adam([{"params": params[k], "lr": lr, "name": k}], eps=1e-15) for k, lr in lrs.items()}

    # --- PolarGS: hooks (preprocessed once) and the strategy wrapping gsplat's own
    hooks = PolarHooks(PolarConfig.synthetic())
    hooks.preprocess(views)
    inner = MCMCStrategy(cap_max=200_000) if args.mcmc else DefaultStrategy()
    strategy = PolarStrategy(hooks=hooks, inner=inner, render_fn=make_render_fn(params, rasterization, sh_degree=sh_degree))
    strategy.check_sanity(params, optimizers)
    state = strategy.initialize_state(scene_scale=1.0)

    for step in range(args.steps):
        view = views[step % len(views)]
        viewmats, Ks = gsplat_cameras(view, device)
        degree = min(step // 1000, sh_degree)
        colors = polar_colors(sh_colors(params, viewmats, degree), params, viewmats)  # RGB + 5 aux channels
        render_colors, render_alphas, info = rasterization(
            params["means"], params["quats"], torch.exp(params["scales"]), torch.sigmoid(params["opacities"]),
            colors, viewmats, Ks, view.width, view.height, sh_degree=None, packed=False,
            backgrounds=polar_backgrounds(torch.zeros(1, 3, device=device)),
        )
        strategy.step_pre_backward(params, optimizers, state, step, info)
        target = view.image.clamp(0, 1) * view.mask
        loss = photometric_loss(render_colors[0, ..., :3].permute(2, 0, 1), target)
        extra, logs = polar_loss(hooks, step, view, render_colors, render_alphas, info, params)
        (loss + extra).backward()
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        if args.mcmc:
            strategy.step_post_backward(params, optimizers, state, step, info, lr=lrs["means"])
        else:
            strategy.step_post_backward(params, optimizers, state, step, info, packed=False)
        if step % 500 == 0:
            print(f"step {step}: loss {float(loss):.4f}, {len(params['means'])} Gaussians, "
                  f"PolarGS appended {state['polar']['appended']}", {k: round(float(v), 4) for k, v in logs.items()})


if __name__ == "__main__":
    main()

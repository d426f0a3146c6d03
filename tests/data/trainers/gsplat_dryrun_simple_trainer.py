# Test fixture for the gsplat dry run: a placeholder with the statement shape of gsplat's
# examples/simple_trainer.py at v1.5.3 (nerfstudio-project/gsplat) that really trains, small: a
# Config whose strategy is DefaultStrategy or MCMCStrategy (first argument "default" / "mcmc"), a
# Runner that reads datasets.colmap (gsplat_support/), renders with gsplat.rasterization through
# rasterize_splats, adds fused_ssim to an L1 loss, lets the strategy densify, and saves
# ckpts/ckpt_<step>_rank0.pt; gsplat.distributed.cli starts it. Arguments are the ones a dry run
# passes (tyro's spelling, parsed here with argparse). Written for these tests; nothing here is
# upstream code.

import argparse
import os
from dataclasses import dataclass, field
from typing import Union

import torch
import tqdm
from datasets.colmap import Dataset, Parser
from fused_ssim import fused_ssim
from typing_extensions import assert_never

from gsplat.distributed import cli
from gsplat.rendering import rasterization
from gsplat.strategy import DefaultStrategy, MCMCStrategy


@dataclass
class Config:
    data_dir: str = "data"
    result_dir: str = "results"
    max_steps: int = 30_000
    save_steps: list = field(default_factory=lambda: [30_000])
    batch_size: int = 1
    packed: bool = False
    sh_degree: int = 1
    strategy: Union[DefaultStrategy, MCMCStrategy] = field(default_factory=DefaultStrategy)


class Runner:
    def __init__(self, local_rank, world_rank, world_size, cfg):
        self.cfg = cfg
        self.world_rank, self.world_size = world_rank, world_size
        self.device = f"cuda:{local_rank}"
        self.ckpt_dir = os.path.join(cfg.result_dir, "ckpts")
        os.makedirs(self.ckpt_dir, exist_ok=True)
        self.parser = Parser(cfg.data_dir)
        self.trainset = Dataset(self.parser, split="train")
        self.scene_scale = self.parser.scene_scale * 1.1
        points = torch.from_numpy(self.parser.points)
        gap = torch.cdist(points, points).topk(4, largest=False).values[:, 1:].mean(-1).clamp_min(1e-4)
        n = points.shape[0]
        sh = torch.zeros(n, (cfg.sh_degree + 1) ** 2, 3)
        sh[:, 0] = (torch.from_numpy(self.parser.points_rgb).float() / 255.0 - 0.5) / 0.28209479177387814
        params = {
            "means": (points, 1.6e-4 * self.scene_scale),
            "scales": (torch.log(gap)[:, None].repeat(1, 3), 5e-3),
            "quats": (torch.rand(n, 4), 1e-3),
            "opacities": (torch.logit(torch.full((n,), 0.1)), 5e-2),
            "sh0": (sh[:, :1], 2.5e-3),
            "shN": (sh[:, 1:], 2.5e-3 / 20),
        }
        self.splats = torch.nn.ParameterDict({k: torch.nn.Parameter(v) for k, (v, _) in params.items()}).to(self.device)
        self.optimizers = {k: torch.optim.Adam([{"params": self.splats[k], "lr": lr, "name": k}], eps=1e-15)
                           for k, (_, lr) in params.items()}
        self.cfg.strategy.check_sanity(self.splats, self.optimizers)
        if isinstance(self.cfg.strategy, DefaultStrategy):
            self.strategy_state = self.cfg.strategy.initialize_state(scene_scale=self.scene_scale)
        elif isinstance(self.cfg.strategy, MCMCStrategy):
            self.strategy_state = self.cfg.strategy.initialize_state()
        else:
            assert_never(self.cfg.strategy)

    def rasterize_splats(self, camtoworlds, Ks, width, height, **kwargs):
        kwargs.pop("image_ids", None)
        colors = torch.cat([self.splats["sh0"], self.splats["shN"]], 1)
        return rasterization(
            means=self.splats["means"],
            quats=self.splats["quats"],
            scales=torch.exp(self.splats["scales"]),
            opacities=torch.sigmoid(self.splats["opacities"]),
            colors=colors,
            viewmats=torch.linalg.inv(camtoworlds),
            Ks=Ks,
            width=width,
            height=height,
            packed=self.cfg.packed,
            absgrad=self.cfg.strategy.absgrad if isinstance(self.cfg.strategy, DefaultStrategy) else False,
            rasterize_mode="classic",
            **kwargs,
        )

    def train(self):
        cfg = self.cfg
        schedulers = [torch.optim.lr_scheduler.ExponentialLR(self.optimizers["means"], gamma=0.01 ** (1.0 / cfg.max_steps))]
        trainloader = torch.utils.data.DataLoader(self.trainset, batch_size=cfg.batch_size, shuffle=True,
                                                  generator=torch.Generator().manual_seed(0))
        trainloader_iter = iter(trainloader)
        pbar = tqdm.tqdm(range(0, cfg.max_steps))
        for step in pbar:
            try:
                data = next(trainloader_iter)
            except StopIteration:
                trainloader_iter = iter(trainloader)
                data = next(trainloader_iter)
            camtoworlds = data["camtoworld"].to(self.device)
            Ks = data["K"].to(self.device)
            pixels = data["image"].to(self.device) / 255.0
            image_ids = data["image_id"].to(self.device)
            height, width = pixels.shape[1:3]
            sh_degree_to_use = min(step // 20, cfg.sh_degree)

            renders, alphas, info = self.rasterize_splats(
                camtoworlds=camtoworlds,
                Ks=Ks,
                width=width,
                height=height,
                sh_degree=sh_degree_to_use,
                image_ids=image_ids,
                render_mode="RGB",
            )
            colors = renders

            self.cfg.strategy.step_pre_backward(
                params=self.splats,
                optimizers=self.optimizers,
                state=self.strategy_state,
                step=step,
                info=info,
            )

            l1loss = (colors - pixels).abs().mean()
            ssimloss = 1.0 - fused_ssim(colors.permute(0, 3, 1, 2), pixels.permute(0, 3, 1, 2), padding="valid")
            loss = 0.8 * l1loss + 0.2 * ssimloss
            loss.backward()
            pbar.set_description(f"loss={loss.item():.3f}")

            for optimizer in self.optimizers.values():
                optimizer.step()
                optimizer.zero_grad(set_to_none=True)
            for scheduler in schedulers:
                scheduler.step()

            if isinstance(self.cfg.strategy, DefaultStrategy):
                self.cfg.strategy.step_post_backward(
                    params=self.splats,
                    optimizers=self.optimizers,
                    state=self.strategy_state,
                    step=step,
                    info=info,
                    packed=cfg.packed,
                )
            elif isinstance(self.cfg.strategy, MCMCStrategy):
                self.cfg.strategy.step_post_backward(
                    params=self.splats,
                    optimizers=self.optimizers,
                    state=self.strategy_state,
                    step=step,
                    info=info,
                    lr=schedulers[0].get_last_lr()[0],
                )
            else:
                assert_never(self.cfg.strategy)

            if step in [i - 1 for i in cfg.save_steps] or step == cfg.max_steps - 1:
                data = {"step": step, "splats": self.splats.state_dict()}
                torch.save(data, f"{self.ckpt_dir}/ckpt_{step}_rank{self.world_rank}.pt")


def main(local_rank, world_rank, world_size, cfg):
    runner = Runner(local_rank, world_rank, world_size, cfg)
    runner.train()


def _arguments():
    parser = argparse.ArgumentParser()
    parser.add_argument("preset", choices=["default", "mcmc"])
    parser.add_argument("--data_dir", required=True)
    parser.add_argument("--result_dir", required=True)
    parser.add_argument("--max_steps", type=int, default=30_000)
    parser.add_argument("--save_steps", type=int, nargs="+", default=[30_000])
    parser.add_argument("--eval_steps", type=int, nargs="+", default=[30_000])
    parser.add_argument("--ply_steps", type=int, nargs="+", default=[30_000])
    parser.add_argument("--data_factor", type=int, default=4)
    parser.add_argument("--port", type=int, default=8080)
    parser.add_argument("--disable_viewer", action="store_true")
    for option in ("refine-start-iter", "refine-stop-iter", "refine-every", "reset-every"):
        parser.add_argument(f"--strategy.{option}", dest=option.replace("-", "_"), type=int)
    return parser.parse_args()


if __name__ == "__main__":
    args = _arguments()
    schedule = {k: getattr(args, k) for k in ("refine_start_iter", "refine_stop_iter", "refine_every", "reset_every")}
    schedule = {k: v for k, v in schedule.items() if v is not None}
    if args.preset == "default":
        # splits only Gaussians of a tenth of the scene, so that within a short run Dense's rows
        # (seeded at their pixel footprint) are duplicated and kept rather than split
        strategy = DefaultStrategy(verbose=True, grow_scale3d=0.1, **schedule)
    else:
        schedule.pop("reset_every", None)
        strategy = MCMCStrategy(verbose=True, **schedule)
    cfg = Config(data_dir=args.data_dir, result_dir=args.result_dir, max_steps=args.max_steps,
                 save_steps=args.save_steps, strategy=strategy)
    cli(main, cfg, verbose=True)

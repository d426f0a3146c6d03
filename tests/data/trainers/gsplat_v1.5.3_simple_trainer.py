# Test fixture for the patch scripts: a placeholder with the statement shape of gsplat's
# examples/simple_trainer.py at v1.5.3 (nerfstudio-project/gsplat): a Config whose strategy is a
# Union of the two gsplat strategies, a Runner whose train() renders with rasterize_splats and
# dispatches step_post_backward with isinstance ... assert_never. Written for these tests; the
# bodies do nothing useful and nothing here is upstream code.

import json
import math
from dataclasses import dataclass, field
from typing import Union

import torch
import tqdm
import tyro
from typing_extensions import assert_never

from gsplat.rendering import rasterization
from gsplat.strategy import DefaultStrategy, MCMCStrategy


@dataclass
class Config:
    max_steps: int = 30_000
    batch_size: int = 1
    packed: bool = False
    strategy: Union[DefaultStrategy, MCMCStrategy] = field(default_factory=DefaultStrategy)


class Runner:
    def __init__(self, local_rank, world_rank, world_size, cfg):
        self.cfg = cfg
        self.device = f"cuda:{local_rank}"
        self.splats, self.optimizers = {}, {}
        self.cfg.strategy.check_sanity(self.splats, self.optimizers)
        if isinstance(self.cfg.strategy, DefaultStrategy):
            self.strategy_state = self.cfg.strategy.initialize_state(scene_scale=1.0)
        elif isinstance(self.cfg.strategy, MCMCStrategy):
            self.strategy_state = self.cfg.strategy.initialize_state()
        else:
            assert_never(self.cfg.strategy)

    def rasterize_splats(self, camtoworlds, Ks, width, height, **kwargs):
        return rasterization(camtoworlds, Ks, width, height, **kwargs)

    def train(self):
        cfg = self.cfg
        schedulers = []
        trainloader_iter = iter([])
        pbar = tqdm.tqdm(range(0, cfg.max_steps))
        for step in pbar:
            data = next(trainloader_iter)
            camtoworlds = camtoworlds_gt = data["camtoworld"]
            Ks = data["K"]
            pixels = data["image"] / 255.0
            image_ids = data["image_id"]
            height, width = pixels.shape[1:3]
            sh_degree_to_use = min(step // 1000, 3)

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

            loss = (colors - pixels).abs().mean()
            loss.backward()

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


def main(local_rank, world_rank, world_size, cfg):
    runner = Runner(local_rank, world_rank, world_size, cfg)
    runner.train()


if __name__ == "__main__":
    configs = {
        "default": ("densification heuristics", Config(strategy=DefaultStrategy(verbose=True))),
        "mcmc": ("MCMC densification", Config(strategy=MCMCStrategy(verbose=True))),
    }
    cfg = tyro.extras.overridable_config_cli(configs)
    main(0, 0, 1, cfg)

# Test fixture for the patch scripts: a placeholder with the statement shape of gsplat's
# examples/simple_trainer.py on main (nerfstudio-project/gsplat @ 90d7b4b, version 1.6.0): the
# splats live in a GaussianScene rendered through a Stage, and step_post_backward gets scene=.
# Written for these tests; the bodies do nothing useful and nothing here is upstream code.

import math
from dataclasses import dataclass, field
from typing import Union

import torch
import tqdm
import tyro
from typing_extensions import assert_never

try:
    from gsplat.scene import GaussianScene
except ImportError:
    GaussianScene = None
from gsplat.rendering import rasterization
from gsplat.strategy import DefaultStrategy, MCMCStrategy


@dataclass
class Config:
    max_steps: int = 30_000
    batch_size: int = 1
    packed: bool = False
    strategy: Union[DefaultStrategy, MCMCStrategy] = field(
        default_factory=DefaultStrategy
    )


class Runner:
    def __init__(self, local_rank, world_rank, world_size, cfg):
        self.cfg = cfg
        self.device = f"cuda:{local_rank}"
        self.splats, self.optimizers = {}, {}
        self.scene = GaussianScene.from_splats(self.splats, id="scene")
        self.splats = self.scene.splats
        self.stage = None

        self.cfg.strategy.check_sanity(self.splats, self.optimizers)

        if isinstance(self.cfg.strategy, DefaultStrategy):
            self.strategy_state = self.cfg.strategy.initialize_state(
                scene_scale=1.0
            )
        elif isinstance(self.cfg.strategy, MCMCStrategy):
            self.strategy_state = self.cfg.strategy.initialize_state()
        else:
            assert_never(self.cfg.strategy)

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

            renders, alphas, info = self.stage.render(
                self.scene.id,
                camtoworlds=camtoworlds,
                Ks=Ks,
                width=width,
                height=height,
                sh_degree=sh_degree_to_use,
                image_ids=image_ids,
                render_mode="RGB",
                frame_idcs=image_ids,
            )
            if renders.shape[-1] == 4:
                colors, depths = renders[..., 0:3], renders[..., 3:4]
            else:
                colors, depths = renders, None

            if not self._gaussians_frozen:
                self.cfg.strategy.step_pre_backward(
                    params=self.splats,
                    optimizers=self.optimizers,
                    state=self.strategy_state,
                    step=step,
                    info=info,
                )

            loss = torch.lerp((colors - pixels).abs().mean(), (colors - pixels).square().mean(), 0.2)
            loss.backward()

            for optimizer in self.optimizers.values():
                optimizer.step()
                optimizer.zero_grad(set_to_none=True)

            if isinstance(self.cfg.strategy, DefaultStrategy):
                self.cfg.strategy.step_post_backward(
                    params=self.splats,
                    optimizers=self.optimizers,
                    state=self.strategy_state,
                    step=step,
                    info=info,
                    packed=cfg.packed,
                    scene=self.scene,
                )
            elif isinstance(self.cfg.strategy, MCMCStrategy):
                self.cfg.strategy.step_post_backward(
                    params=self.splats,
                    optimizers=self.optimizers,
                    state=self.strategy_state,
                    step=step,
                    info=info,
                    lr=schedulers[0].get_last_lr()[0],
                    scene=self.scene,
                )
            else:
                assert_never(self.cfg.strategy)


if __name__ == "__main__":
    configs = {
        "default": ("densification heuristics", Config(strategy=DefaultStrategy(verbose=True))),
        "mcmc": ("MCMC densification", Config(strategy=MCMCStrategy(verbose=True))),
    }
    cfg = tyro.extras.overridable_config_cli(configs)
    Runner(0, 0, 1, cfg).train()

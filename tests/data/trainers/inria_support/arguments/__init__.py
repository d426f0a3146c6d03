"""Placeholder argument groups (the upstream names: ModelParams, OptimizationParams, PipelineParams)."""

from argparse import ArgumentParser, Namespace


class _Group:
    def __init__(self, parser: ArgumentParser, values: dict):
        self._names = list(values)
        for name, default in values.items():
            kind = type(default)
            if kind is bool:
                parser.add_argument(f"--{name}", action="store_true", default=default)
            else:
                parser.add_argument(f"--{name}", type=kind, default=default)

    def extract(self, args: Namespace) -> Namespace:
        return Namespace(**{name: getattr(args, name) for name in self._names})


class ModelParams(_Group):
    def __init__(self, parser: ArgumentParser):
        parser.add_argument("-s", "--source_path", default="")
        parser.add_argument("-m", "--model_path", default="")
        super().__init__(parser, {"sh_degree": 1, "white_background": False, "train_test_exp": False})

    def extract(self, args: Namespace) -> Namespace:
        out = super().extract(args)
        out.source_path, out.model_path = args.source_path, args.model_path
        return out


class OptimizationParams(_Group):
    def __init__(self, parser: ArgumentParser):
        super().__init__(parser, {
            "iterations": 300, "position_lr_init": 0.00016, "position_lr_final": 0.0000016,
            "position_lr_max_steps": 300, "feature_lr": 0.0025, "opacity_lr": 0.05, "scaling_lr": 0.005,
            "rotation_lr": 0.001, "lambda_dssim": 0.2, "densification_interval": 100, "opacity_reset_interval": 3000,
            "densify_from_iter": 500, "densify_until_iter": 15000, "densify_grad_threshold": 0.0002,
            "random_background": False, "optimizer_type": "default", "depth_l1_weight_init": 0.0,
            "depth_l1_weight_final": 0.0, "exposure_lr_init": 0.01,
        })


class PipelineParams(_Group):
    def __init__(self, parser: ArgumentParser):
        super().__init__(parser, {"debug": False, "convert_SHs_python": False, "compute_cov3D_python": False})

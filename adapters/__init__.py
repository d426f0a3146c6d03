"""polargs_adapters: PolarGS for the upstream trainers, one sub-package per trainer.

- ``polargs_adapters.graphdeco``: graphdeco-inria/gaussian-splatting (vanilla 3DGS)
- ``polargs_adapters.gof``: Gaussian Opacity Fields (autonomousvision)
- ``polargs_adapters.pgsr``: PGSR (zju3dv)
- ``polargs_adapters.twodgs``: 2D Gaussian Splatting (hbb1)
- ``polargs_adapters.gsplat``: gsplat strategies and ``examples/simple_trainer.py`` (nerfstudio-project/gsplat)

Each one only translates between that trainer and the public API of ``polargs_plugin``
(``polargs_plugin.kit`` holds what they share). ``python adapters/<name>/patch.py CHECKOUT``
inserts the hook calls into a checkout of the trainer (see docs/adapters/); the scripts need only
the standard library (``patch_engine`` loads the engine without this package).
"""

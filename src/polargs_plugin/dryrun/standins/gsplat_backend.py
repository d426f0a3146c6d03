"""Stand-in for ``gsplat.cuda._backend`` in a dry run: ``_C = None``, gsplat's own state on a
machine without a CUDA toolkit ("gsplat will be disabled"), so that importing gsplat never starts
a JIT build of its CUDA extension. The kernels a trainer's path needs are replaced by
:mod:`.gsplat`; any other CUDA kernel fails when called."""

_C = None

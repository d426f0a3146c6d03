"""Dry runs: an upstream trainer's own ``train.py`` trained on the CPU, for a few hundred
iterations on a small scene, with CPU stand-ins of its CUDA extensions (docs/adapters/dryrun.md).

- :mod:`.splat` and :mod:`.standins`: the stand-in rasterizers (and ``simple_knn``) on the
  reference backend;
- :mod:`.finder`: the import hook that serves them under the upstream module names;
- :mod:`.cuda_cpu`: CUDA requests (``.cuda()``, ``device="cuda"``, ``torch.cuda.*``) mapped to the CPU;
- :mod:`.probe`: what a dry run watches inside the trainer (losses, step times, per-Gaussian
  state after every densification, the checkpoint);
- :mod:`.trainers`: per trainer, its stand-ins and how its schedule is shrunk;
- :mod:`.requirements`: the modules a checkout's training script requires that the environment
  lacks, found before any run;
- :mod:`.launch`: the process that runs one ``train.py`` with all of the above installed.

``polargs dryrun`` (:mod:`polargs_plugin.service.dryrun`) starts that process twice, patched and
unpatched, and checks the reports. Nothing here is imported by the rest of the package.
"""

"""CPU stand-ins for the CUDA extensions of the upstream trainers, one module each, with the
upstream Python API (names, arguments, outputs) and the reference backend underneath
(:mod:`polargs_plugin.dryrun.splat`). A dry run installs them under the upstream module names
(:mod:`polargs_plugin.dryrun.finder`); nothing imports them under their own names but the tests.

======================================  ==============================  =======================
upstream module                         trainer                         stand-in
======================================  ==============================  =======================
``diff_gaussian_rasterization`` (2023)  graphdeco 472689c               :mod:`.graphdeco_2023`
``diff_gaussian_rasterization`` (2024)  graphdeco 54c035f               :mod:`.graphdeco_2024`
``diff_gaussian_rasterization`` (GOF)   GOF 5245b20                     :mod:`.gof`
``diff_plane_rasterization``            PGSR de24f1a                    :mod:`.plane`
``diff_surfel_rasterization``           2DGS 1920a23                    :mod:`.surfel`
``simple_knn._C``                       all of them                     :mod:`.simple_knn`
``pytorch3d.transforms``                PGSR de24f1a                    :mod:`.pytorch3d_transforms`
======================================  ==============================  =======================

``pytorch3d.transforms`` is no CUDA extension but pytorch3d has no wheels for torch 2.x: it is
served only where pytorch3d is not installed (:data:`..trainers.FALLBACKS`).
"""

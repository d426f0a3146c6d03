"""Synthetic scenes shared by the tests: each set of arguments is generated once per process.

``generate_scene`` is a pure function of its arguments: geometry, texture and cameras follow the
scene, the sensor noise comes from streams spawned from ``seed``, and it draws nothing from the
global numpy / torch generators (so a cached scene leaves the seeds of ``conftest._seed`` where a
fresh one would). A scene generated once therefore serves every test that asks for the same
arguments. The cache is a module global: one per pytest process (each xdist worker has its own),
kept for the session.

Every call hands out a deep copy, never the cached object: a test may change the views' tensors
in place (``view.stokes[0] /= 2``), reassign their fields, append to the lists or edit ``meta``
without another test seeing it. The copy costs about a millisecond for the scenes the suite uses,
generating one 30 to 130 ms.

Use it from a test through the session fixtures ``synthetic_scene`` / ``synthetic_views`` of
conftest.py, or call :func:`scene` / :func:`views` directly where no fixture reaches (a module-level
helper, a module- or session-scoped fixture). The generator's own tests (tests/test_synthetic.py,
the generator-equivalence test of tests/test_real_size.py) call ``generate_scene`` themselves, and
must: a cache would hide a generator that stopped being deterministic.
"""

from __future__ import annotations

import copy
import inspect
from typing import Any

_CACHE: dict[tuple, Any] = {}


def scene(name, *args, **kwargs):
    """A deep copy of ``generate_scene(name, *args, **kwargs)``, generated once per process.

    Arguments exactly as :func:`polargs_plugin.data.synthetic.generate_scene`; spellings that mean
    the same call (a default given or left out, positional or keyword) share one cache entry.
    """
    # imported here, not at the top: conftest.py imports this module in every test process, and
    # some tests look at which modules a bare import pulls in
    from polargs_plugin.data.synthetic import generate_scene

    bound = inspect.signature(generate_scene).bind(name, *args, **kwargs)
    bound.apply_defaults()
    key = tuple(bound.arguments.items())
    try:
        made = _CACHE.get(key)
    except TypeError:  # an unhashable argument (a custom SceneSpec with lists): not cached
        return generate_scene(name, *args, **kwargs)
    if made is None:
        made = _CACHE[key] = generate_scene(**bound.arguments)
    return copy.deepcopy(made)


def views(name, *args, **kwargs) -> list:
    """The views of :func:`scene` (a fresh deep copy, as there)."""
    return scene(name, *args, **kwargs).views

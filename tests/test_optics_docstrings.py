"""Every docstring example of optics/, geometry, viz, config, losses and the fused L_dn, run one by one."""

import doctest

import pytest

import polargs_plugin.config
import polargs_plugin.depth_normal
import polargs_plugin.geometry
import polargs_plugin.losses
import polargs_plugin.reflective_window
import polargs_plugin.optics.azimuth
import polargs_plugin.optics.fresnel
import polargs_plugin.optics.mosaic
import polargs_plugin.optics.pattern
import polargs_plugin.optics.single_view
import polargs_plugin.optics.stokes
import polargs_plugin.viz

MODULES = [
    polargs_plugin.optics.azimuth,
    polargs_plugin.optics.fresnel,
    polargs_plugin.optics.mosaic,
    polargs_plugin.optics.pattern,
    polargs_plugin.optics.single_view,
    polargs_plugin.optics.stokes,
    polargs_plugin.geometry,
    polargs_plugin.viz,
]
# Modules whose examples run too, without an example required of every public name.
ALSO_RUN = [polargs_plugin.config, polargs_plugin.depth_normal, polargs_plugin.losses, polargs_plugin.reflective_window]
EXAMPLES = [test for module in MODULES + ALSO_RUN for test in doctest.DocTestFinder().find(module) if test.examples]


def test_every_public_function_has_an_example():
    documented = {test.name.rsplit(".", 1)[-1] for test in EXAMPLES}
    public = {name for module in MODULES for name in module.__all__ if callable(getattr(module, name))}
    assert public <= documented, f"missing examples: {sorted(public - documented)}"


@pytest.mark.parametrize("test", EXAMPLES, ids=lambda t: t.name)
def test_docstring_example(test):
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    runner.run(test)
    assert runner.failures == 0, f"{test.name}: docstring example failed (run with -s to see it)"

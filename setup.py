"""Package list for setuptools (everything else is in pyproject.toml).

Two import packages: the core ``polargs_plugin`` (``src/``) and the per-trainer adapters
``polargs_adapters`` (the top-level ``adapters/`` folder, one sub-package per trainer).
"""

from setuptools import find_packages, setup

adapters = ["polargs_adapters"] + [f"polargs_adapters.{name}" for name in find_packages("adapters")]
setup(
    packages=find_packages("src") + adapters,
    package_dir={"": "src", "polargs_adapters": "adapters"},
)

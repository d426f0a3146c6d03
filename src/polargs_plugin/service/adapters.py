"""What a patched upstream trainer reads from its environment: the polarimetric data and the
PolarGS settings (docs/adapters/).

==========================  ======================================================================
``POLARGS_DATA``            the polarimetric dataset folder of the scene (any format ``polargs``
                            reads; required)
``POLARGS_PRESET``          ``real`` (default) or ``synthetic``: the paper's values
``POLARGS_CONFIG``          a JSON file of PolarConfig fields set on the preset (a bare
                            PolarConfig, or ``{"polar": {...}}``)
``POLARGS_KEEP_NATIVE``     ``1`` keeps the plug-in's copies of loss terms the trainer has natively
                            (they are off by default)
==========================  ======================================================================

The preset is built first, the trainer's native terms are switched off, then the file is applied,
so a term the file switches on explicitly stays on.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import TYPE_CHECKING, Mapping, Sequence

from polargs_plugin.io import PolarInputError
from polargs_plugin.service.configs import config_from_environment
from polargs_plugin.service.data import load_dataset

if TYPE_CHECKING:
    from polargs_plugin.config import PolarConfig
    from polargs_plugin.types import View

__all__ = ["ENV_DATA", "AdapterInputs", "adapter_inputs"]

ENV_DATA = "POLARGS_DATA"


@dataclass
class AdapterInputs:
    """The polarimetric views and the PolarGS settings of a patched trainer.

    Attributes:
        views: the views of ``POLARGS_DATA``, matched to the trainer's cameras by name.
        config: the PolarConfig of the environment.
        source: the dataset folder, for messages.
    """

    views: list["View"]
    config: "PolarConfig"
    source: str


def adapter_inputs(native_terms: Sequence[str] = (), environ: Mapping[str, str] | None = None) -> AdapterInputs:
    """Read the environment of a patched trainer (see the module docstring).

    Args:
        native_terms: PolarConfig.losses switches of terms the trainer computes itself.
        environ: the environment (default ``os.environ``).

    Raises:
        PolarInputError: naming the variable or file: no ``POLARGS_DATA``, an unknown preset,
            an unreadable settings file or dataset.
    """
    environ = os.environ if environ is None else environ
    data = environ.get(ENV_DATA)
    if not data:
        raise PolarInputError(ENV_DATA, "is not set: point it at the polarimetric dataset folder of this scene")
    config = config_from_environment(environ, native_terms)
    return AdapterInputs(load_dataset(data).views, config, data)

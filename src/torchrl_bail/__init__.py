"""torchrl_bail: BAIL, Progressive BAIL and the batch-RL baselines (BC, BCQ, BEAR, MARWIL) on TorchRL.

The package face defines nothing: ``torchrl_bail.config_dir``
(:func:`torchrl_bail.configuration.hydra_setup.config_dir`),
``torchrl_bail.load_policy`` (:func:`torchrl_bail.evaluation.policy.load_policy`) and
``torchrl_bail.fast_tensordict_outputs`` (:func:`torchrl_bail.modules.fast_tensordict_outputs`) load their modules on
first use, so that importing the package or one of its layers (``torchrl_bail.objectives``) imports nothing else.

The modules that moved into the layer packages keep their old names (``torchrl_bail.config``,
``torchrl_bail.policy``, ...): :data:`MOVED` maps each old name to its module, and an import of an old name (a
``from torchrl_bail.policy import load_policy``, or the unpickling of a policy file saved before the move) imports
the new module, lazily, and binds it under the old name too: the two names are the same module object.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import importlib.util
import sys

__version__ = "0.1.0"

#: what the package re-exports, each from the module that defines it, imported on first use
_EXPORTS = {"config_dir": "torchrl_bail.configuration.hydra_setup", "load_policy": "torchrl_bail.evaluation.policy",
            "fast_tensordict_outputs": "torchrl_bail.modules"}

#: the modules that moved into the layer packages: old name -> new name (old import paths keep working)
MOVED = {
    **{f"torchrl_bail.{name}": f"torchrl_bail.core.{name}"
       for name in ("io", "errors", "interrupts", "progress", "stacking")},
    **{f"torchrl_bail.{name}": f"torchrl_bail.configuration.{name}"
       for name in ("config", "config_builders", "hydra_setup", "algo_schemas", "batch_schemas", "schema_reader",
                    "run_dirs")},
    **{f"torchrl_bail.{name}": f"torchrl_bail.training.{name}" for name in ("trainer", "envelope", "resume")},
    **{f"torchrl_bail.{name}": f"torchrl_bail.evaluation.{name}" for name in ("simulator", "policy")},
    "torchrl_bail.plots": "torchrl_bail.reports.plots",
}


class _MovedModuleLoader(importlib.abc.Loader):
    """Loads an old module name as the module it moved to (imported on first use, the same object)."""

    def create_module(self, spec: importlib.machinery.ModuleSpec):
        return importlib.import_module(MOVED[spec.name])

    def exec_module(self, module) -> None:
        """Nothing to execute: :meth:`create_module` returned the module already executed under its new name."""


class _MovedModuleFinder(importlib.abc.MetaPathFinder):
    """Finds the old names of :data:`MOVED` (and nothing else)."""

    def find_spec(self, fullname: str, path=None, target=None):
        if fullname in MOVED:
            return importlib.util.spec_from_loader(fullname, _MovedModuleLoader())
        return None


if not any(isinstance(finder, _MovedModuleFinder) for finder in sys.meta_path):
    sys.meta_path.append(_MovedModuleFinder())


def __getattr__(name: str):
    """``torchrl_bail.config_dir``, ``torchrl_bail.load_policy`` and ``torchrl_bail.fast_tensordict_outputs`` without
    importing OmegaConf, torch or TorchRL when the package (or one of its layers) is imported."""
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'torchrl_bail' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *_EXPORTS])

"""torchrl_bail: BAIL, Progressive BAIL and the batch-RL baselines (BC, BCQ, BEAR, MARWIL) on TorchRL.

The package face defines nothing: ``torchrl_bail.config_dir`` (:func:`torchrl_bail.hydra_setup.config_dir`),
``torchrl_bail.load_policy`` (:func:`torchrl_bail.policy.load_policy`) and ``torchrl_bail.fast_tensordict_outputs``
(:func:`torchrl_bail.modules.fast_tensordict_outputs`) load their modules on first use, so that importing the package
or one of its layers (``torchrl_bail.objectives``) imports nothing else.
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

#: what the package re-exports, each from the module that defines it, imported on first use
_EXPORTS = {"config_dir": "torchrl_bail.hydra_setup", "load_policy": "torchrl_bail.policy",
            "fast_tensordict_outputs": "torchrl_bail.modules"}


def __getattr__(name: str):
    """``torchrl_bail.config_dir``, ``torchrl_bail.load_policy`` and ``torchrl_bail.fast_tensordict_outputs`` without
    importing OmegaConf, torch or TorchRL when the package (or one of its layers) is imported."""
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'torchrl_bail' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *_EXPORTS])

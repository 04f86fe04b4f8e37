"""torchrl_bail: BAIL, Progressive BAIL and the batch-RL baselines (BC, BCQ, BEAR, MARWIL) on TorchRL.

Heavy submodules are imported lazily so that ``python -m torchrl_bail.train --help`` starts fast;
``torchrl_bail.load_policy`` (:func:`torchrl_bail.policy.load_policy`) loads on first use.
"""

from __future__ import annotations

import importlib.util
import sys

__version__ = "0.1.0"

from torchrl_bail.config import config_dir  # noqa: E402, F401  (re-exported; light: Hydra/OmegaConf only)


def fast_tensordict_outputs() -> None:
    """Works around a per-call cost in tensordict 0.14: every ``TensorDictModule`` output goes through
    ``TensorDict.from_any``, which calls ``importlib.util.find_spec("pandas")`` -- a scan of ``sys.path`` (about
    0.2 ms, several times per update) when pandas is not installed. Registering pandas as absent in ``sys.modules``
    makes that lookup instant; ``import pandas`` fails exactly as before (``ImportError``). No-op when pandas is
    installed, and after the first call (one dictionary lookup).

    Not applied at import: every network builder of :mod:`torchrl_bail.modules` calls it (through
    :func:`~torchrl_bail.modules.mlp`), so the package's algorithms, behaviour agents and evaluation are fast
    without anything happening when :mod:`torchrl_bail` is merely imported. Call it yourself when you use the loss
    modules with networks of your own. The one visible effect: pandas installed *later in the same process* needs
    a restart to import.
    """
    if "pandas" not in sys.modules and importlib.util.find_spec("pandas") is None:
        sys.modules["pandas"] = None  # type: ignore[assignment]


def __getattr__(name: str):
    """``torchrl_bail.load_policy`` without importing torch and TorchRL when the package is imported."""
    if name == "load_policy":
        from torchrl_bail.policy import load_policy

        return load_policy
    raise AttributeError(f"module 'torchrl_bail' has no attribute {name!r}")

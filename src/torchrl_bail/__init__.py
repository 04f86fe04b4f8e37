"""torchrl_bail: BAIL, Progressive BAIL and the batch-RL baselines (BC, BCQ, BEAR, MARWIL) on TorchRL.

Heavy submodules are imported lazily so that ``python -m torchrl_bail.train --help`` starts fast;
``torchrl_bail.load_policy`` (:func:`torchrl_bail.policy.load_policy`) loads on first use.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

__version__ = "0.1.0"


def fast_tensordict_outputs() -> None:
    """Works around a per-call cost in tensordict 0.14: every ``TensorDictModule`` output goes through
    ``TensorDict.from_any``, which calls ``importlib.util.find_spec("pandas")`` -- a scan of ``sys.path`` (about
    0.2 ms, several times per update) when pandas is not installed. Registering pandas as absent in ``sys.modules``
    makes that lookup instant; ``import pandas`` fails exactly as before (``ImportError``). No-op when pandas is
    installed. Applied when ``torchrl_bail`` is imported, so the loss modules are fast in other people's loops too;
    the one visible effect is that pandas installed *later in the same process* needs a restart to import.
    """
    if "pandas" not in sys.modules and importlib.util.find_spec("pandas") is None:
        sys.modules["pandas"] = None  # type: ignore[assignment]


fast_tensordict_outputs()


def config_dir() -> Path:
    """Directory holding the Hydra configs.

    An installed wheel ships them as ``torchrl_bail/conf``; a source checkout (editable install) keeps
    them at the repository's top-level ``conf/``.
    """
    packaged = Path(__file__).resolve().parent / "conf"
    if packaged.is_dir():
        return packaged
    repo = Path(__file__).resolve().parents[2] / "conf"
    if repo.is_dir():
        return repo
    raise FileNotFoundError(
        f"torchrl_bail configs not found: looked in {packaged} and {repo}. Reinstall the package."
    )


def __getattr__(name: str):
    """``torchrl_bail.load_policy`` without importing torch and TorchRL when the package is imported."""
    if name == "load_policy":
        from torchrl_bail.policy import load_policy

        return load_policy
    raise AttributeError(f"module 'torchrl_bail' has no attribute {name!r}")

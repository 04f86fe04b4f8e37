"""torchrl_bail: BAIL, Progressive BAIL and the batch-RL baselines (BC, BCQ, BEAR, MARWIL) on TorchRL.

Heavy submodules are imported lazily so that ``python -m torchrl_bail.train --help`` starts fast.
"""

from __future__ import annotations

from pathlib import Path

__version__ = "0.1.0"


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

"""One file per algorithm; each contributes its update step and schedule to the one training loop."""

from __future__ import annotations

from torchrl_bail.algorithms.bail import BAIL
from torchrl_bail.algorithms.base import Algorithm, PrepareContext
from torchrl_bail.algorithms.bc import BehaviourCloning
from torchrl_bail.algorithms.bcq import BCQ
from torchrl_bail.algorithms.bear import BEAR
from torchrl_bail.algorithms.marwil import MARWIL
from torchrl_bail.algorithms.pbail import ProgressiveBAIL

__all__ = ["ALGORITHMS", "Algorithm", "BAIL", "BCQ", "BEAR", "BehaviourCloning", "MARWIL", "PrepareContext",
           "ProgressiveBAIL", "build_algorithm"]


#: ``algo.name`` -> the algorithm's class, built as ``cls(obs_dim, action_spec, algo_config, device)``
ALGORITHMS = {cls.name: cls for cls in (BAIL, ProgressiveBAIL, BehaviourCloning, MARWIL, BCQ, BEAR)}


def build_algorithm(cfg, obs_dim: int, action_spec, device) -> Algorithm:
    """Builds the algorithm named by ``cfg.name`` from its Hydra config group."""
    try:
        cls = ALGORITHMS[cfg.name]
    except KeyError:
        raise ValueError(f"unknown algo.name {cfg.name!r}; choose one of {sorted(ALGORITHMS)}") from None
    return cls(obs_dim, action_spec, cfg, device)

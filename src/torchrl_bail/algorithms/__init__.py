"""One file per algorithm; each contributes its update step and schedule to the one training loop.

An algorithm is registered where it is defined: a class that sets ``name`` enters
:data:`~torchrl_bail.algorithms.base.REGISTRY`, and importing this package imports every module in it, so a new
``algorithms/<name>.py`` needs no line here. :data:`ALGORITHMS` lists them in the order of their schemas
(:data:`torchrl_bail.configuration.algo_schemas.ALGO_SCHEMAS`, the order of the report's columns).
"""

from __future__ import annotations

import importlib
import pkgutil

from torchrl_bail.algorithms.bail import BAIL
from torchrl_bail.algorithms.base import REGISTRY, Algorithm, PrepareContext
from torchrl_bail.algorithms.bc import BehaviourCloning
from torchrl_bail.algorithms.bcq import BCQ
from torchrl_bail.algorithms.bear import BEAR
from torchrl_bail.algorithms.marwil import MARWIL
from torchrl_bail.algorithms.pbail import ProgressiveBAIL
from torchrl_bail.configuration.algo_schemas import ALGO_SCHEMAS

__all__ = ["ALGORITHMS", "Algorithm", "BAIL", "BCQ", "BEAR", "BehaviourCloning", "MARWIL", "PrepareContext",
           "ProgressiveBAIL", "build_algorithm"]

for _module in pkgutil.iter_modules(__path__):  # each algorithm file registers its class as it is defined
    importlib.import_module(f"{__name__}.{_module.name}")

#: ``algo.name`` -> the algorithm's class, built as ``cls(obs_dim, action_spec, algo_config, device)``; in the
#: schemas' order (an algorithm without a schema last: building it names the missing schema)
ALGORITHMS = dict(sorted(REGISTRY.items(), key=lambda item: (list(ALGO_SCHEMAS).index(item[0])
                                                             if item[0] in ALGO_SCHEMAS else len(ALGO_SCHEMAS))))


def build_algorithm(cfg, obs_dim: int, action_spec, device) -> Algorithm:
    """Builds the algorithm named by ``cfg.name`` from its Hydra config group."""
    try:
        cls = ALGORITHMS[cfg.name]
    except KeyError:
        raise ValueError(f"unknown algo.name {cfg.name!r}; choose one of {sorted(ALGORITHMS)}") from None
    return cls(obs_dim, action_spec, cfg, device)

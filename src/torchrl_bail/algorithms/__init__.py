"""One file per algorithm; each contributes its update step and schedule to the one training loop."""

from __future__ import annotations

from torchrl_bail.algorithms.bail import BAIL
from torchrl_bail.algorithms.base import Algorithm, PrepareContext
from torchrl_bail.algorithms.bc import BehaviourCloning
from torchrl_bail.algorithms.pbail import ProgressiveBAIL

__all__ = ["ALGORITHMS", "Algorithm", "BAIL", "BehaviourCloning", "PrepareContext", "ProgressiveBAIL",
           "build_algorithm"]


def _bc(cfg, obs_dim, action_spec, device):
    return BehaviourCloning(obs_dim=obs_dim, action_spec=action_spec, hidden=tuple(cfg.policy.hidden),
                            lr=cfg.policy.lr, batch_size=cfg.batch_size, epochs=cfg.epochs, device=device)


def _bail(cfg, obs_dim, action_spec, device):
    return BAIL(obs_dim=obs_dim, action_spec=action_spec, hidden=tuple(cfg.policy.hidden), lr=cfg.policy.lr,
                batch_size=cfg.batch_size, epochs=cfg.epochs, envelope=dict(cfg.envelope),
                percentile=cfg.selection.percentile, selection_by=cfg.selection.by,
                nonpositive_value=cfg.selection.nonpositive_value, device=device)


def _pbail(cfg, obs_dim, action_spec, device):
    return ProgressiveBAIL(obs_dim=obs_dim, action_spec=action_spec, hidden=tuple(cfg.policy.hidden),
                           lr=cfg.policy.lr, batch_size=cfg.batch_size, epochs=cfg.epochs,
                           envelope=dict(cfg.envelope), percentile=cfg.selection.percentile,
                           best_envelope=cfg.best_envelope, v_projection=cfg.v_projection,
                           validation=cfg.validation, device=device)


#: ``algo.name`` -> builder ``(algo_cfg, obs_dim, action_spec, device) -> Algorithm``
ALGORITHMS = {"bail": _bail, "pbail": _pbail, "bc": _bc}


def build_algorithm(cfg, obs_dim: int, action_spec, device) -> Algorithm:
    """Builds the algorithm named by ``cfg.name`` from its Hydra config group."""
    try:
        builder = ALGORITHMS[cfg.name]
    except KeyError:
        raise ValueError(f"unknown algo.name {cfg.name!r}; choose one of {sorted(ALGORITHMS)}") from None
    return builder(cfg, obs_dim, action_spec, device)

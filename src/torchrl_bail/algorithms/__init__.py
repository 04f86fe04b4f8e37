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
                           best_envelope=cfg.best_envelope, selection_envelope=cfg.selection_envelope,
                           v_projection=cfg.v_projection, validation=cfg.validation, device=device)


def _marwil(cfg, obs_dim, action_spec, device):
    return MARWIL(obs_dim=obs_dim, action_spec=action_spec, hidden=tuple(cfg.policy.hidden), lr=cfg.policy.lr,
                  value_hidden=tuple(cfg.value.hidden), value_lr=cfg.value.lr, beta=cfg.beta, c2_init=cfg.c2_init,
                  c2_rate=cfg.c2_rate, vf_coeff=cfg.vf_coeff, max_exponent=cfg.max_exponent, eps=cfg.eps,
                  batch_size=cfg.batch_size, epochs=cfg.epochs, device=device)


def _bcq(cfg, obs_dim, action_spec, device):
    return BCQ(obs_dim=obs_dim, action_spec=action_spec, vae=dict(cfg.vae), actor=dict(cfg.actor),
               critic=dict(cfg.critic), phi=cfg.phi, lmbda=cfg.lmbda, num_samples=cfg.num_samples,
               kl_weight=cfg.kl_weight, latent_clip=cfg.latent_clip, gamma=cfg.gamma, tau=cfg.tau,
               batch_size=cfg.batch_size, epochs=cfg.epochs, device=device)


def _bear(cfg, obs_dim, action_spec, device):
    return BEAR(obs_dim=obs_dim, action_spec=action_spec, vae=dict(cfg.vae), actor=dict(cfg.actor),
                critic=dict(cfg.critic), kernel_sigma=cfg.kernel_sigma, num_samples_match=cfg.num_samples_match,
                mmd_stabiliser=cfg.mmd_stabiliser, epsilon=cfg.epsilon, log_alpha_init=cfg.log_alpha_init,
                log_alpha_min=cfg.log_alpha_min, log_alpha_max=cfg.log_alpha_max, lagrange_lr=cfg.lagrange_lr,
                warm_start_updates=cfg.warm_start_updates, lmbda=cfg.lmbda, num_samples=cfg.num_samples,
                kl_weight=cfg.kl_weight, latent_clip=cfg.latent_clip, gamma=cfg.gamma, tau=cfg.tau,
                batch_size=cfg.batch_size, epochs=cfg.epochs, device=device)


#: ``algo.name`` -> builder ``(algo_cfg, obs_dim, action_spec, device) -> Algorithm``
ALGORITHMS = {"bail": _bail, "pbail": _pbail, "bc": _bc, "marwil": _marwil, "bcq": _bcq, "bear": _bear}


def build_algorithm(cfg, obs_dim: int, action_spec, device) -> Algorithm:
    """Builds the algorithm named by ``cfg.name`` from its Hydra config group."""
    try:
        builder = ALGORITHMS[cfg.name]
    except KeyError:
        raise ValueError(f"unknown algo.name {cfg.name!r}; choose one of {sorted(ALGORITHMS)}") from None
    return builder(cfg, obs_dim, action_spec, device)

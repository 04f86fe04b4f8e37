"""BEAR (spec 8.4), version 0 with the Laplacian kernel: one update = VAE step, critic step, actor and Lagrange
multiplier steps (from the same samples), ``log alpha`` clamp, warm-start clock, targets.

The actor is TorchRL's tanh-Gaussian :class:`~torchrl.modules.ProbabilisticActor` (the SAC actor of
:func:`~torchrl_bail.modules.make_sac_actor`) with the authors' unclamped log-std; the multiplier
``log alpha`` has its own Adam. The evaluation policy plays the best of ``num_samples`` (10) actor samples by
the first critic. With batch 100, one epoch (10^6 samples) is 10^4 updates.

Examples:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from torchrl_bail.modules import action_spec_from_bounds
    >>> small = {"hidden": (16, 16)}
    >>> algo = BEAR(obs_dim=4, action_spec=action_spec_from_bounds([-1.0] * 2, [1.0] * 2), vae=small, actor=small,
    ...             critic=small, warm_start_updates=1, batch_size=8, epochs=1)
    >>> batch = TensorDict({"observation": torch.randn(8, 4), "action": torch.rand(8, 2) * 2 - 1,
    ...                     "next": {"observation": torch.randn(8, 4), "reward": torch.randn(8, 1),
    ...                              "terminated": torch.zeros(8, 1, dtype=torch.bool)}}, [8])
    >>> [float(algo.update(batch)["warm_start"]) for _ in range(2)]
    [1.0, 0.0]
"""

from __future__ import annotations

import math
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.data import TensorSpec

from torchrl_bail.algorithms.twin_critic_vae import (
    CRITIC_DEFAULTS,
    NET_DEFAULTS,
    VAE_DEFAULTS,
    TwinCriticVAEAlgorithm,
    build_vae_and_critics,
    use_vmap,
)
from torchrl_bail.modules import make_sac_actor
from torchrl_bail.objectives.bear import BEARLoss

__all__ = ["BEAR"]

#: the authors' actor: BCQ's sizes, MMD noise clipped to +-0.5, log-std unclamped
ACTOR_DEFAULTS = {**NET_DEFAULTS, "noise_clip": 0.5, "log_std_min": -math.inf, "log_std_max": math.inf}


class BEAR(TwinCriticVAEAlgorithm):
    """BEAR on :class:`~torchrl_bail.objectives.bear.BEARLoss`.

    Keyword Args:
        obs_dim, action_spec, vae, critic, lmbda, num_samples, kl_weight, latent_clip, gamma, tau, batch_size,
            epochs, device: as in :class:`~torchrl_bail.algorithms.bcq.BCQ` (``num_samples`` counts the
            target actor's samples in the critic target and the candidates at action selection).
        actor (dict): ``hidden`` (400, 300), ``lr`` (1e-3), ``noise_clip`` (0.5), ``log_std_min`` /
            ``log_std_max`` (unclamped: -inf / inf).
        kernel_sigma (float): Laplacian kernel width. Defaults to ``10.0``.
        num_samples_match (int): samples per state for the MMD. Defaults to ``5``.
        mmd_stabiliser (float): added under the MMD's square root. Defaults to ``1e-6``.
        epsilon (float): MMD threshold. Defaults to ``0.05``.
        log_alpha_init (float, optional): initial ``log alpha``; ``None`` draws it from ``N(0, 1)``.
        log_alpha_min, log_alpha_max (float): clamp of ``log alpha`` after each step. Default ``-5`` and ``10``.
        lagrange_lr (float): Adam learning rate of ``log alpha``. Defaults to ``1e-3``.
        warm_start_updates (int): updates with the MMD-only actor loss. Defaults to ``100000``.
    """

    name = "bear"

    def __init__(
        self,
        *,
        obs_dim: int,
        action_spec: TensorSpec,
        vae: dict | None = None,
        actor: dict | None = None,
        critic: dict | None = None,
        kernel_sigma: float = 10.0,
        num_samples_match: int = 5,
        mmd_stabiliser: float = 1e-6,
        epsilon: float = 0.05,
        log_alpha_init: float | None = None,
        log_alpha_min: float = -5.0,
        log_alpha_max: float = 10.0,
        lagrange_lr: float = 1e-3,
        warm_start_updates: int = 100_000,
        lmbda: float = 0.75,
        num_samples: int = 10,
        kl_weight: float = 0.5,
        latent_clip: float = 0.5,
        gamma: float = 0.99,
        tau: float = 0.005,
        batch_size: int = 100,
        epochs: float = 100,
        device="cpu",
    ) -> None:
        vae = {**VAE_DEFAULTS, **(vae or {})}
        actor = {**ACTOR_DEFAULTS, **(actor or {})}
        critic = {**CRITIC_DEFAULTS, **(critic or {})}
        vae_net, critics = build_vae_and_critics(obs_dim, action_spec, vae, critic, latent_clip)
        policy_net = make_sac_actor(obs_dim, action_spec, tuple(actor["hidden"]),
                                    log_std_min=float(actor["log_std_min"]), log_std_max=float(actor["log_std_max"]))
        loss = BEARLoss(policy_net, critics, vae_net, action_spec=action_spec, num_samples=num_samples,
                        num_samples_match=num_samples_match, kernel_sigma=kernel_sigma, epsilon=epsilon,
                        noise_clip=actor["noise_clip"], mmd_stabiliser=mmd_stabiliser,
                        warm_start_updates=warm_start_updates, log_alpha_init=log_alpha_init,
                        log_alpha_min=log_alpha_min, log_alpha_max=log_alpha_max, lmbda=lmbda, gamma=gamma,
                        kl_weight=kl_weight, deactivate_vmap=not use_vmap(critic["vmap"], device))
        super().__init__(loss=loss, vae_lr=vae["lr"], critic_lr=critic["lr"], actor_lr=actor["lr"], tau=tau,
                         num_samples=num_samples, batch_size=batch_size, epochs=epochs, device=device)
        self.optimizers["alpha"] = torch.optim.Adam([self.loss.log_alpha], lr=lagrange_lr)

    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        metrics = self._update_vae_and_critics(batch)
        terms = self.loss.policy_terms(batch)
        loss_actor, meta_actor = self.loss.actor_loss(batch, terms)
        loss_alpha, meta_alpha = self.loss.alpha_loss(batch, terms)
        self._step("actor", loss_actor)
        self._step("alpha", loss_alpha)
        self.loss.clamp_log_alpha_()
        self.loss.count_update()
        self._finish_update()
        return {**metrics, "loss_actor": loss_actor.detach(), "loss_alpha": loss_alpha.detach(), **meta_actor,
                **meta_alpha}

    def summary(self) -> dict[str, Any]:
        return {"bear_final_log_alpha": float(self.loss.log_alpha.detach()),
                "bear_updates": int(self.loss.update_count)}

"""BEAR (supp. C.2, BEAR), version 0 with the Laplacian kernel: one update = VAE step, critic step, actor and Lagrange
multiplier steps (from the same samples), ``log alpha`` clamp, warm-start clock, targets.

The actor is TorchRL's tanh-Gaussian :class:`~torchrl.modules.ProbabilisticActor` (the SAC actor of
:func:`~torchrl_bail.modules.make_sac_actor`) with the authors' unclamped log-std; the multiplier
``log alpha`` has its own Adam. The evaluation policy plays the best of ``num_samples`` (10) actor samples by
the first critic. With batch 100, one epoch (10^6 samples) is 10^4 updates.

Examples:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from torchrl_bail.modules import action_spec_from_bounds
    >>> small = {"hidden": [16, 16]}  # the config: a mapping over conf/algo/bear.yaml's values
    >>> config = {"vae": small, "actor": small, "critic": small, "warm_start_updates": 1, "batch_size": 8}
    >>> algo = BEAR(4, action_spec_from_bounds([-1.0] * 2, [1.0] * 2), config)
    >>> batch = TensorDict({"observation": torch.randn(8, 4), "action": torch.rand(8, 2) * 2 - 1,
    ...                     "next": {"observation": torch.randn(8, 4), "reward": torch.randn(8, 1),
    ...                              "terminated": torch.zeros(8, 1, dtype=torch.bool)}}, [8])
    >>> [float(algo.update(batch)["warm_start"]) for _ in range(2)]
    [1.0, 0.0]
"""

from __future__ import annotations

from typing import Any, Optional

import torch
from omegaconf import MISSING
from tensordict import TensorDictBase
from torchrl.data import TensorSpec

from torchrl_bail.algorithms.twin_critic_vae import TwinCriticVAEAlgorithm, TwinCriticVAEConfig, adam
from torchrl_bail.configuration.algo_schemas import NetConfig, algo_schema, schema_block
from torchrl_bail.configuration.config import at_least, learning_rate, non_negative, positive
from torchrl_bail.modules import make_sac_actor
from torchrl_bail.objectives.bear import BEARLoss

__all__ = ["BEAR"]


# -- the schema (conf/algo/bear.yaml), read by torchrl_bail.configuration.algo_schemas without importing this module --


@schema_block
class BEARActorConfig(NetConfig):
    noise_clip: float = positive()
    log_std_min: float = MISSING
    log_std_max: float = MISSING


@algo_schema("bear")
class BEARConfig(TwinCriticVAEConfig):
    column = 6
    tiny = ("warm_start_updates=2",)
    description = ("BEAR v0 (arXiv:1906.00949): Laplacian MMD (σ = {kernel_sigma:g}, {num_samples_match} samples, "
                   "ε = {epsilon:g}), Lagrange α, warm start")
    losses = ("torchrl_bail.objectives.BEARLoss", "torchrl_bail.objectives.VAELoss")

    kernel_sigma: float = positive()
    num_samples_match: int = at_least(1)
    mmd_stabilizer: float = non_negative()
    epsilon: float = non_negative()
    log_alpha_init: Optional[float] = None
    log_alpha_min: float = MISSING
    log_alpha_max: float = MISSING
    lagrange_lr: float = learning_rate()
    warm_start_updates: int = at_least(0)
    actor: BEARActorConfig = MISSING

    def check(self) -> None:
        super().check()
        self._ordered("log_alpha_min", "log_alpha_max")


class BEAR(TwinCriticVAEAlgorithm):
    """BEAR on :class:`~torchrl_bail.objectives.bear.BEARLoss`, from ``conf/algo/bear.yaml``'s config (arguments as
    in :class:`~torchrl_bail.algorithms.base.Algorithm`).

    The config's ``actor`` block is the tanh-Gaussian actor (``hidden``, ``lr``, ``log_std_min`` /
    ``log_std_max``) and the clip of its MMD noise (``noise_clip``); ``lagrange_lr`` is the Adam rate of
    ``log alpha``; ``vae``, ``critic``, ``tau`` as in
    :class:`~torchrl_bail.algorithms.twin_critic_vae.TwinCriticVAEAlgorithm`; the other keys go to the loss
    (``num_samples`` counts the target actor's samples in the critic target and the candidates at action
    selection).
    """

    name = "bear"

    def __init__(self, obs_dim: int, action_spec: TensorSpec, config, device="cpu") -> None:
        super().__init__(obs_dim, action_spec, config, device)
        self.optimizers["alpha"] = adam([self.loss.log_alpha], self.config.lagrange_lr)

    def _make_loss(self, vae, critics, deactivate_vmap: bool) -> BEARLoss:
        cfg, spec = self.config, self.action_spec
        actor = make_sac_actor(self.obs_dim, spec, tuple(cfg.actor.hidden), log_std_min=float(cfg.actor.log_std_min),
                               log_std_max=float(cfg.actor.log_std_max))
        return BEARLoss(actor, critics, vae, action_spec=spec, num_samples=cfg.num_samples,
                        num_samples_match=cfg.num_samples_match, kernel_sigma=cfg.kernel_sigma, epsilon=cfg.epsilon,
                        noise_clip=cfg.actor.noise_clip, mmd_stabilizer=cfg.mmd_stabilizer,
                        warm_start_updates=cfg.warm_start_updates, log_alpha_init=cfg.log_alpha_init,
                        log_alpha_min=cfg.log_alpha_min, log_alpha_max=cfg.log_alpha_max, lmbda=cfg.lmbda,
                        gamma=cfg.gamma, kl_weight=cfg.kl_weight, deactivate_vmap=deactivate_vmap)

    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        metrics = self._update_vae_and_critics(batch)
        terms = self.loss.policy_terms(batch)
        loss_actor, meta_actor = self.loss.actor_loss(batch, terms)
        loss_alpha, meta_alpha = self.loss.alpha_loss(batch, terms)
        # one backward for both: each loss reaches only its own parameters (alpha is detached in the actor's loss,
        # MMD and Q in the multiplier's), and a compiled update computes both in one graph that backpropagates once
        self._step(("actor", "alpha"), loss_actor + loss_alpha)
        self.loss.clamp_log_alpha_()
        self.loss.count_update()
        self._finish_update()
        return {**metrics, "loss_actor": loss_actor.detach(), "loss_alpha": loss_alpha.detach(), **meta_actor,
                **meta_alpha}

    def summary(self) -> dict[str, Any]:
        return {"bear_final_log_alpha": float(self.loss.log_alpha.detach()),
                "bear_updates": int(self.loss.update_count)}

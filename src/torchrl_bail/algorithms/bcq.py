"""BCQ (supp. C.2, BCQ), the 2019 version the BAIL authors ran: one update = VAE step, critic step, actor step, targets.

The evaluation policy draws ``num_samples`` (10) VAE candidates per state, perturbs them with the actor and
plays the one the first critic values most. With batch 100, one epoch (10^6 samples) is 10^4 updates.

Examples:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from torchrl_bail.configuration.config_builders import algo_config
    >>> from torchrl_bail.modules import action_spec_from_bounds
    >>> small = {"hidden": [16, 16]}
    >>> config = algo_config("bcq", vae=small, actor=small, critic=small, batch_size=8)
    >>> algo = BCQ(4, action_spec_from_bounds([-1.0] * 2, [1.0] * 2), config)
    >>> batch = TensorDict({"observation": torch.randn(8, 4), "action": torch.rand(8, 2) * 2 - 1,
    ...                     "next": {"observation": torch.randn(8, 4), "reward": torch.randn(8, 1),
    ...                              "terminated": torch.zeros(8, 1, dtype=torch.bool)}}, [8])
    >>> sorted(k for k in algo.update(batch) if k.startswith("loss"))
    ['loss_actor', 'loss_qvalue', 'loss_vae']
    >>> algo.policy(TensorDict({"observation": torch.randn(3, 4)}, [3]))["action"].shape
    torch.Size([3, 2])
"""

from __future__ import annotations

import torch
from omegaconf import MISSING
from tensordict import TensorDictBase

from torchrl_bail.algorithms.twin_critic_vae import TwinCriticVAEAlgorithm, TwinCriticVAEConfig
from torchrl_bail.configuration.algo_schemas import NetConfig, algo_schema
from torchrl_bail.configuration.config import non_negative
from torchrl_bail.modules import make_perturbation_actor
from torchrl_bail.objectives.bcq import BCQLoss

__all__ = ["BCQ"]


# -- the schema (conf/algo/bcq.yaml), read by torchrl_bail.configuration.algo_schemas without importing this module --


@algo_schema("bcq")
class BCQConfig(TwinCriticVAEConfig):
    column = 5
    tiny = ()
    description = ("BCQ 2019 (arXiv:1812.02900): VAE + perturbation (Φ = {phi:g}) + soft clipped double Q, best of "
                   "{num_samples}")
    losses = ("torchrl_bail.objectives.BCQLoss", "torchrl_bail.objectives.VAELoss")

    phi: float = non_negative()
    actor: NetConfig = MISSING


class BCQ(TwinCriticVAEAlgorithm):
    """BCQ on :class:`~torchrl_bail.objectives.bcq.BCQLoss`, from ``conf/algo/bcq.yaml``'s config (arguments as in
    :class:`~torchrl_bail.algorithms.base.Algorithm`).

    The config's ``actor`` block is the perturbation model (``hidden``, ``lr``; it perturbs by up to ``phi`` times
    ``max_action``); ``vae``, ``critic``, ``tau`` as in
    :class:`~torchrl_bail.algorithms.twin_critic_vae.TwinCriticVAEAlgorithm`; ``num_samples``, ``lmbda``,
    ``gamma`` and ``kl_weight`` go to the loss (``num_samples`` VAE candidates in the critic target and at action
    selection).
    """

    name = "bcq"

    def _make_loss(self, vae, critics, deactivate_vmap: bool) -> BCQLoss:
        cfg = self.config
        actor = make_perturbation_actor(self.obs_dim, self.action_spec, tuple(cfg.actor.hidden), phi=cfg.phi)
        return BCQLoss(actor, critics, vae, num_samples=cfg.num_samples, lmbda=cfg.lmbda, gamma=cfg.gamma,
                       kl_weight=cfg.kl_weight, deactivate_vmap=deactivate_vmap)

    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        metrics = self._update_vae_and_critics(batch)
        loss_actor, meta_actor = self.loss.actor_loss(batch)
        self._step("actor", loss_actor)
        self._finish_update()
        return {**metrics, "loss_actor": loss_actor.detach(), **meta_actor}

"""BCQ (spec 8.3), the 2019 version the BAIL authors ran: one update = VAE step, critic step, actor step, targets.

The evaluation policy draws ``num_samples`` (10) VAE candidates per state, perturbs them with the actor and
plays the one the first critic values most. With batch 100, one epoch (10^6 samples) is 10^4 updates.

Examples:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from torchrl_bail.modules import action_spec_from_bounds
    >>> small = {"hidden": (16, 16)}
    >>> algo = BCQ(obs_dim=4, action_spec=action_spec_from_bounds([-1.0] * 2, [1.0] * 2), vae=small, actor=small,
    ...            critic=small, batch_size=8, epochs=1)
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
from torchrl_bail.modules import make_perturbation_actor
from torchrl_bail.objectives.bcq import BCQLoss

__all__ = ["BCQ"]


class BCQ(TwinCriticVAEAlgorithm):
    """BCQ on :class:`~torchrl_bail.objectives.bcq.BCQLoss`.

    Keyword Args:
        obs_dim (int): observation size.
        action_spec (TensorSpec): the bounded action spec.
        vae (dict): ``hidden`` (750, 750), ``lr`` (1e-3), ``latent_per_action`` (2: latent = 2 |A|),
            ``log_std_min`` (-4), ``log_std_max`` (15).
        actor (dict): the perturbation model's ``hidden`` (400, 300) and ``lr`` (1e-3).
        critic (dict): the critics' ``hidden`` (400, 300), ``lr`` (1e-3) and ``vmap`` (``"auto"``: the two critics
            run under ``torch.vmap`` on accelerators and one after the other on CPU, where that is faster).
        phi (float): perturbation range, times ``max_action``. Defaults to ``0.05``.
        lmbda (float): soft clipped double-Q weight of the minimum. Defaults to ``0.75``.
        num_samples (int): VAE candidates in the critic target and at action selection. Defaults to ``10``.
        kl_weight (float): KL weight of the VAE loss. Defaults to ``0.5``.
        latent_clip (float): prior latents are clipped to ``+-latent_clip`` when sampling. Defaults to ``0.5``.
        gamma (float): discount. Defaults to ``0.99``.
        tau (float): Polyak rate of the target actor and critics. Defaults to ``0.005``.
        batch_size (int): mini-batch size. Defaults to ``100``.
        epochs (float): length in epochs of 10^6 samples. Defaults to ``100``.
        device: training device. Defaults to ``"cpu"``.
    """

    name = "bcq"

    def __init__(
        self,
        *,
        obs_dim: int,
        action_spec: TensorSpec,
        vae: dict | None = None,
        actor: dict | None = None,
        critic: dict | None = None,
        phi: float = 0.05,
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
        actor = {**NET_DEFAULTS, **(actor or {})}
        critic = {**CRITIC_DEFAULTS, **(critic or {})}
        vae_net, critics = build_vae_and_critics(obs_dim, action_spec, vae, critic, latent_clip)
        loss = BCQLoss(make_perturbation_actor(obs_dim, action_spec, tuple(actor["hidden"]), phi=phi), critics,
                       vae_net, num_samples=num_samples, lmbda=lmbda, gamma=gamma, kl_weight=kl_weight,
                       deactivate_vmap=not use_vmap(critic["vmap"], device))
        super().__init__(loss=loss, vae_lr=vae["lr"], critic_lr=critic["lr"], actor_lr=actor["lr"], tau=tau,
                         num_samples=num_samples, batch_size=batch_size, epochs=epochs, device=device)

    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        metrics = self._update_vae_and_critics(batch)
        loss_actor, meta_actor = self.loss.actor_loss(batch)
        self._step("actor", loss_actor)
        self._finish_update()
        return {**metrics, "loss_actor": loss_actor.detach(), **meta_actor}

"""The conditional-VAE loss of BCQ and BEAR (supp. C.2, BCQ, 8.4): reconstruction MSE plus a weighted KL term.

The VAE (:class:`~torchrl_bail.modules.ConditionalVAE`) models the batch's actions given the state. BCQ samples
its candidate actions from it; BEAR compares the policy's actions with its samples (MMD). Both train it with

    loss = MSE(reconstruction, a) + kl_weight * KL,    KL = -0.5 * mean(1 + log sigma^2 - mu^2 - sigma^2)

where the MSE is a mean over batch x action dimensions and the KL a mean over batch x latent dimensions, as in
the authors' code (``kl_weight = 0.5``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import dispatch
from tensordict.utils import NestedKey
from torch import nn
from torchrl.objectives import LossModule

from torchrl_bail.objectives._shared import check_reduction, reduce_per_seed, required_entry

__all__ = ["VAELoss", "vae_loss_terms", "conditional_vae_loss"]


def vae_loss_terms(
    reconstruction: torch.Tensor, action: torch.Tensor, mean: torch.Tensor, log_std: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-sample ``(reconstruction MSE, KL)``, each averaged over its last dimension (actions, latents).

    ``KL = -0.5 * mean(1 + log sigma^2 - mu^2 - sigma^2)`` with ``log sigma^2 = 2 * log_std`` (the authors write
    ``log(std.pow(2))``: the same value, without the round trip through ``exp``). Averaging these per-sample
    terms over the batch gives exactly the authors' batch means.

    Examples:
        >>> # |recon - a| = 1 everywhere; mu = 1, sigma = 1: KL = -0.5 * (1 + 0 - 1 - 1) = 0.5
        >>> recon, kl = vae_loss_terms(torch.zeros(2, 3), torch.ones(2, 3), torch.ones(2, 4), torch.zeros(2, 4))
        >>> recon, kl
        (tensor([1., 1.]), tensor([0.5000, 0.5000]))
    """
    recon = (reconstruction - action).pow(2).mean(-1)
    kl = -0.5 * (1 + 2 * log_std - mean.pow(2) - (2 * log_std).exp()).mean(-1)
    return recon, kl


class VAELoss(LossModule):
    """The conditional-VAE loss of BCQ and BEAR: ``MSE(reconstruction, a) + kl_weight * KL``.

    Presented with BCQ in "Off-Policy Deep Reinforcement Learning without Exploration", Fujimoto et al.,
    ICML 2019, https://arxiv.org/abs/1812.02900, and reused by BEAR ("Stabilizing Off-Policy Q-Learning via
    Bootstrapping Error Reduction", Kumar et al., NeurIPS 2019, https://arxiv.org/abs/1906.00949); run as
    baselines in BAIL (Chen et al., NeurIPS 2020, https://arxiv.org/abs/1910.12179).

    :class:`~torchrl_bail.objectives.bcq.BCQLoss` and :class:`~torchrl_bail.objectives.bear.BEARLoss` compute
    the same term (``loss_vae``) with :func:`vae_loss_terms`; this class trains a VAE on its own.

    Args:
        vae_network (ConditionalVAE): the VAE (:class:`~torchrl_bail.modules.ConditionalVAE` or any module
            with ``forward(observation, action) -> (reconstruction, mu, log_sigma)``). Its parameters are the
            loss' parameters (shared, not copied).

    Keyword Args:
        kl_weight (float): weight of the KL term, registered as a buffer. Defaults to ``0.5``.
        reduction (str, optional): ``"none"`` | ``"mean"`` | ``"sum"``. Defaults to ``"mean"``. ``"none"``
            gives one loss per point (``[B]`` or ``[S, B]``); ``"mean"`` averages over the last batch dimension
            (one seed's points) and then over the leading ones.

    The output holds ``loss_vae`` and the detached diagnostics ``recon_loss`` and ``kl_loss`` (means over the
    last batch dimension: scalars for ``[B]``, ``[S]`` for ``[S, B]``). The reparameterised latent draws from
    torch's global random stream.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_bail.modules import ConditionalVAE
        >>> from torchrl_bail.objectives.vae import VAELoss
        >>> _ = torch.manual_seed(0)
        >>> loss = VAELoss(ConditionalVAE(11, 3, -1.0, 1.0, hidden=(32, 32), latent_dim=6))
        >>> data = TensorDict({"observation": torch.randn(8, 11), "action": torch.rand(8, 3) * 2 - 1}, [8])
        >>> out = loss(data)
        >>> sorted(out.keys())
        ['kl_loss', 'loss_vae', 'recon_loss']
        >>> out["loss_vae"].backward()

    Keyword calls work too (the keys are ``observation`` and ``action``):

        >>> _ = loss.select_out_keys("loss_vae")
        >>> loss(observation=torch.randn(8, 11), action=torch.rand(8, 3) * 2 - 1).shape
        torch.Size([])
    """

    @dataclass
    class _AcceptedKeys:
        """Maintains default values for all configurable tensordict keys.

        Attributes:
            observation (NestedKey): the state ``s``. Defaults to ``"observation"``.
            action (NestedKey): the batch's action ``a``. Defaults to ``"action"``.
        """

        observation: NestedKey = "observation"
        action: NestedKey = "action"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    #: coefficients a float may be assigned to (an in-place update of the buffer)
    _schedulable_buffers = frozenset({"kl_weight"})
    default_value_estimator = None
    out_keys = ["loss_vae", "recon_loss", "kl_loss"]

    vae_network: nn.Module
    vae_network_params: TensorDictParams
    target_vae_network_params: TensorDictParams

    def __init__(
        self,
        vae_network: nn.Module,
        *,
        kl_weight: float = 0.5,
        reduction: Literal["mean", "sum", "none"] | None = None,
    ) -> None:
        reduction = check_reduction(reduction)
        if not float(kl_weight) >= 0:
            raise ValueError(f"kl_weight must be >= 0, got {kl_weight}")
        super().__init__()
        self.convert_to_functional(vae_network, "vae_network")
        self.register_coeff_buffer("kl_weight", kl_weight)
        self.reduction = reduction

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    @property
    def in_keys(self) -> list[NestedKey]:
        return [self.tensor_keys.observation, self.tensor_keys.action]

    def vae_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """``(loss_vae, {"recon_loss", "kl_loss"})`` on a ``[B]`` or ``[S, B]`` batch."""
        return conditional_vae_loss(self, tensordict)

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Computes ``loss_vae`` and its two terms."""
        loss, metadata = self.vae_loss(tensordict)
        return TensorDict({"loss_vae": loss, **metadata})


def conditional_vae_loss(module: LossModule,
                         tensordict: TensorDictBase) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The VAE loss of any loss module holding ``vae_network`` (+ params), ``kl_weight`` and the two keys."""
    observation = required_entry(module, tensordict, module.tensor_keys.observation)
    action = required_entry(module, tensordict, module.tensor_keys.action)
    with module.vae_network_params.to_module(module.vae_network, preserve_module_state=False):
        reconstruction, mean, log_std = module.vae_network(observation, action)
    recon, kl = vae_loss_terms(reconstruction, action, mean, log_std)
    loss = reduce_per_seed(module, recon + module.kl_weight * kl, tensordict)
    return loss, {"recon_loss": recon.detach().mean(-1), "kl_loss": kl.detach().mean(-1)}

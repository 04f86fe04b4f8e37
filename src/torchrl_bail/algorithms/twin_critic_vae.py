"""The training side BCQ and BEAR share: their VAE and twin critics, the optimizers, the first two steps of an
update and the soft target update.

Each update runs the authors' order: the VAE's step, then the critics' step (their target already uses the
updated VAE in BCQ), then the algorithm's actor step(s) against the updated critics, then the Polyak update of the
target actor and critics (:class:`~torchrl.objectives.SoftUpdate` with ``tau``, fused into one ``lerp_``).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.data import TensorSpec

from torchrl_bail.algorithms.base import Algorithm
from torchrl_bail.modules import fused_soft_update, make_qvalue_network, make_vae
from torchrl_bail.objectives.common import BestOfNPolicy, TwinCriticVAELoss

__all__ = ["CRITIC_DEFAULTS", "NET_DEFAULTS", "VAE_DEFAULTS", "TwinCriticVAEAlgorithm", "adam",
           "build_vae_and_critics", "use_vmap"]

#: the authors' VAE (spec 8.3); a config's ``vae`` block overrides any of these
VAE_DEFAULTS = {"hidden": (750, 750), "lr": 1e-3, "latent_per_action": 2, "log_std_min": -4.0, "log_std_max": 15.0}
#: the authors' actor (400-300, Adam 1e-3)
NET_DEFAULTS = {"hidden": (400, 300), "lr": 1e-3}
#: the authors' critics; ``vmap``: run the two with ``torch.vmap`` (True), one after the other (False) or
#: ``"auto"``: vmap on accelerators, the loop on CPU (where two plain matmuls beat one batched matmul)
CRITIC_DEFAULTS = {**NET_DEFAULTS, "vmap": "auto"}


def use_vmap(setting, device: torch.device) -> bool:
    """Resolves a critic ``vmap`` setting (``True`` | ``False`` | ``"auto"``) for ``device``."""
    if setting == "auto":
        return torch.device(device).type != "cpu"
    if isinstance(setting, bool):
        return setting
    raise ValueError(f"algo.critic.vmap must be true, false or auto, got {setting!r}")


def build_vae_and_critics(obs_dim: int, action_spec: TensorSpec, vae: dict, critic: dict, latent_clip: float):
    """The conditional VAE and two independently initialised critics ``(s, a) -> hidden -> 1``."""
    act_dim = action_spec.shape[-1]
    net = make_vae(obs_dim, action_spec, tuple(vae["hidden"]), latent_dim=int(vae["latent_per_action"]) * act_dim,
                   log_std_min=vae["log_std_min"], log_std_max=vae["log_std_max"], latent_clip=latent_clip)
    critics = [make_qvalue_network(obs_dim, act_dim, tuple(critic["hidden"])) for _ in range(2)]
    return net, critics


def adam(params, lr: float) -> torch.optim.Adam:
    """``torch.optim.Adam`` with its fused kernel (one pass over each tensor; CPU and CUDA).

    At the paper's sizes the default per-tensor Adam takes about a tenth of a BCQ/BEAR update on one CPU thread;
    the fused kernel computes the same update with a different rounding order (parameters agree with the
    reference implementation to float32 precision, ``tests/test_twin_critic_vae_update.py``), so runs are
    reproducible seed for seed but not bit-identical to a run with ``torch.optim.Adam(params, lr)``.
    """
    return torch.optim.Adam(params, lr=lr, fused=True)


class TwinCriticVAEAlgorithm(Algorithm):
    """Base of :class:`~torchrl_bail.algorithms.bcq.BCQ` and :class:`~torchrl_bail.algorithms.bear.BEAR`.

    A subclass builds its loss (a :class:`~torchrl_bail.objectives.common.TwinCriticVAELoss`), passes it here
    with the three learning rates, and implements :meth:`update` from :meth:`_update_vae_and_critics`,
    :meth:`_step` and :meth:`_finish_update`. The loss is the one module checkpointed (every network, target
    and buffer); the evaluation policy is the loss' best-of-``num_samples`` policy.
    """

    def __init__(self, *, loss: TwinCriticVAELoss, vae_lr: float, critic_lr: float, actor_lr: float, tau: float,
                 num_samples: int, batch_size: int, epochs: float, device="cpu") -> None:
        super().__init__(batch_size=batch_size, epochs=epochs, device=device)
        if not 0.0 < float(tau) <= 1.0:
            raise ValueError(f"algo.tau must be in (0, 1], got {tau}")
        self.loss = loss.to(self.device)
        self.target_updater = fused_soft_update(self.loss, tau=float(tau))
        self.optimizers["vae"] = adam(self.loss.vae_network_params.parameters(), vae_lr)
        self.optimizers["critic"] = adam(self.loss.qvalue_network_params.parameters(), critic_lr)
        self.optimizers["actor"] = adam(self.loss.actor_network_params.parameters(), actor_lr)
        self.modules["loss"] = self.loss
        self._policy = BestOfNPolicy(self.loss, num_samples)

    @property
    def policy(self) -> BestOfNPolicy:
        return self._policy

    def _step(self, name: str, loss: torch.Tensor) -> None:
        optimizer = self.optimizers[name]
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()

    def _update_vae_and_critics(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        loss_vae, meta_vae = self.loss.vae_loss(batch)
        self._step("vae", loss_vae)
        loss_qvalue, meta_q = self.loss.qvalue_loss(batch)
        self._step("critic", loss_qvalue)
        return {"loss_vae": loss_vae.detach(), "loss_qvalue": loss_qvalue.detach(), **meta_vae, **meta_q}

    def _finish_update(self) -> None:
        self.target_updater.step()

"""The training side BCQ and BEAR share: their VAE and twin critics, the optimizers, the first two steps of an
update and the soft target update.

Each update runs the authors' order: the VAE's step, then the critics' step (their target already uses the
updated VAE in BCQ), then the algorithm's actor step(s) against the updated critics, then the Polyak update of the
target actor and critics (:class:`~torchrl.objectives.SoftUpdate` with ``tau``, fused into one ``lerp_``).
"""

from __future__ import annotations

from abc import abstractmethod

import torch
from omegaconf import MISSING
from tensordict import TensorDictBase
from torch import nn
from torchrl.data import TensorSpec

from torchrl_bail.algorithms.base import Algorithm
from torchrl_bail.configuration.algo_schemas import AlgoConfig, CriticConfig, NetConfig, schema_block
from torchrl_bail.configuration.config import at_least, discount, non_negative, positive, rule
from torchrl_bail.modules import fused_soft_update, make_qvalue_network, make_vae
from torchrl_bail.objectives.common import BestOfNPolicy, TwinCriticVAELoss

__all__ = ["TwinCriticVAEAlgorithm", "adam", "build_vae_and_critics", "use_vmap"]


# -- the schema BCQ's and BEAR's share, read by torchrl_bail.configuration.algo_schemas without importing this module --


@schema_block
class VAEConfig(NetConfig):
    latent_per_action: int = at_least(1)
    log_std_min: float = MISSING
    log_std_max: float = MISSING

    def check(self) -> None:
        self._ordered("log_std_min", "log_std_max")


@schema_block
class TwinCriticVAEConfig(AlgoConfig):
    """BCQ's and BEAR's shared keys; both are actor-critics the study runs on DDPG batches only (for cost), and
    both are in the paper-scale study."""

    cost = "offline_rl"
    study = "ddpg"
    paper_study = True

    lmbda: float = rule(lambda v: 0 <= v <= 1, "a weight in [0, 1]")
    num_samples: int = at_least(1)
    kl_weight: float = non_negative()
    latent_clip: float = positive()
    gamma: float = discount()
    tau: float = rule(lambda v: 0 < v <= 1, "a soft-update rate in (0, 1]")
    vae: VAEConfig = MISSING
    critic: CriticConfig = MISSING


def use_vmap(setting, device: torch.device) -> bool:
    """Resolves a critic ``vmap`` setting (``True`` | ``False`` | ``"auto"``: vmap on accelerators, the loop on CPU,
    where two plain matmuls beat one batched matmul) for ``device``."""
    if setting == "auto":
        return torch.device(device).type != "cpu"
    if isinstance(setting, bool):
        return setting
    raise ValueError(f"algo.critic.vmap must be true, false or auto, got {setting!r}")


def build_vae_and_critics(obs_dim: int, action_spec: TensorSpec, vae, critic, latent_clip: float):
    """The conditional VAE and two independently initialised critics ``(s, a) -> hidden -> 1`` from the config's
    ``vae`` and ``critic`` blocks."""
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

    Builds the VAE and the critics from the config's ``vae`` and ``critic`` blocks, asks the subclass'
    :meth:`_make_loss` for its loss (a :class:`~torchrl_bail.objectives.common.TwinCriticVAELoss` with its actor),
    and gives the VAE, the critics and the actor their Adam optimizers (``vae.lr``, ``critic.lr``, ``actor.lr``)
    and the targets their soft update (``tau``). A subclass implements :meth:`update` from
    :meth:`_update_vae_and_critics`, :meth:`_step` and :meth:`_finish_update`. The loss is the one module
    checkpointed (every network, target and buffer); the evaluation policy is the loss' best-of-``num_samples``
    policy. Arguments as in :class:`~torchrl_bail.algorithms.base.Algorithm`.
    """

    policy_samples = True

    def __init__(self, obs_dim: int, action_spec: TensorSpec, config, device="cpu") -> None:
        super().__init__(obs_dim, action_spec, config, device)
        cfg = self.config
        vae_net, critics = build_vae_and_critics(obs_dim, action_spec, cfg.vae, cfg.critic, cfg.latent_clip)
        loss = self._make_loss(vae_net, critics, deactivate_vmap=not use_vmap(cfg.critic.vmap, device))
        self.loss = loss.to(self.device)
        self.target_updater = fused_soft_update(self.loss, tau=float(cfg.tau))
        self.optimizers["vae"] = adam(self.loss.vae_network_params.parameters(), cfg.vae.lr)
        self.optimizers["critic"] = adam(self.loss.qvalue_network_params.parameters(), cfg.critic.lr)
        self.optimizers["actor"] = adam(self.loss.actor_network_params.parameters(), cfg.actor.lr)
        self.modules["loss"] = self.loss
        self._policy = BestOfNPolicy(self.loss, cfg.num_samples)

    @abstractmethod
    def _make_loss(self, vae: nn.Module, critics: list[nn.Module], deactivate_vmap: bool) -> TwinCriticVAELoss:
        """The algorithm's loss on its actor (built here from :attr:`config`), ``vae`` and ``critics``."""

    @property
    def policy(self) -> BestOfNPolicy:
        return self._policy

    def _step(self, names: str | tuple[str, ...], loss: torch.Tensor) -> None:
        """Backpropagates ``loss`` and steps the optimizer(s) ``names`` (whose gradients it fills)."""
        optimizers = [self.optimizers[name] for name in ((names,) if isinstance(names, str) else names)]
        for optimizer in optimizers:
            optimizer.zero_grad(set_to_none=True)
        loss.backward()
        for optimizer in optimizers:
            optimizer.step()

    def _update_vae_and_critics(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        loss_vae, meta_vae = self.loss.vae_loss(batch)
        self._step("vae", loss_vae)
        loss_qvalue, meta_q = self.loss.qvalue_loss(batch)
        self._step("critic", loss_qvalue)
        return {"loss_vae": loss_vae.detach(), "loss_qvalue": loss_qvalue.detach(), **meta_vae, **meta_q}

    def _finish_update(self) -> None:
        self.target_updater.step()

"""Bootstrapping Error Accumulation Reduction (BEAR), version 0 with the Laplacian kernel, as the BAIL authors ran
it (supp. C.2, BEAR)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, dispatch
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import TensorSpec

from torchrl_bail.objectives.common import BestOfNPolicy, TwinCriticVAELoss, expand_samples

__all__ = ["BEARLoss", "laplacian_mmd"]


def laplacian_mmd(x: torch.Tensor, y: torch.Tensor, sigma: torch.Tensor | float,
                  stabilizer: torch.Tensor | float = 1e-6) -> torch.Tensor:
    """Per-state MMD between two sample sets with the Laplacian kernel ``k(u, v) = exp(-|u - v|_1 / (2 sigma))``.

    ``MMD = sqrt(mean k(x, x') + mean k(y, y') - 2 mean k(x, y) + stabilizer)``, the means running over all
    pairs of the ``N`` (resp. ``M``) samples of one state, self-pairs included (the biased estimator of the
    authors' code). Identical sample sets give ``sqrt(stabilizer)``.

    Args:
        x (torch.Tensor): samples ``[*B, N, d]`` (BEAR: the VAE's pre-tanh actions).
        y (torch.Tensor): samples ``[*B, M, d]`` (BEAR: the actor's pre-tanh actions).
        sigma: the kernel width (10 in the BAIL runs).
        stabilizer: added under the square root. Defaults to ``1e-6``.

    Returns:
        ``[*B]``.

    Examples:
        >>> x = torch.tensor([[[0.0], [2.0]]])  # one state, two 1-d samples
        >>> y = torch.tensor([[[0.0], [0.0]]])
        >>> # sigma = 1/2: kxx = kxy = (2 + 2 e^-2) / 4, kyy = 1, so MMD = sqrt((1 - e^-2) / 2) = 0.6575
        >>> laplacian_mmd(x, y, 0.5, 0.0)
        tensor([0.6575])
        >>> laplacian_mmd(x, x, 1.0)
        tensor([0.0010])
    """

    def mean_kernel(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        distance = (u.unsqueeze(-2) - v.unsqueeze(-3)).abs().sum(-1)
        return torch.exp(-distance / (2 * sigma)).mean((-2, -1))

    return (mean_kernel(x, x) + mean_kernel(y, y) - 2 * mean_kernel(x, y) + stabilizer).sqrt()


def _stabilizer_renamed(state_dict: dict, prefix: str, *_) -> None:
    """Loads a state dict written when the buffer ``mmd_stabilizer`` was spelled ``mmd_stabiliser``."""
    old = f"{prefix}mmd_stabiliser"
    if old in state_dict:
        state_dict[f"{prefix}mmd_stabilizer"] = state_dict.pop(old)

class BEARLoss(TwinCriticVAELoss):
    """BEAR (version 0): a tanh-Gaussian actor kept on the batch's support by an MMD constraint, twin critics.

    Presented in "Stabilizing Off-Policy Q-Learning via Bootstrapping Error Reduction", Kumar, Fu, Tucker and
    Levine, NeurIPS 2019, https://arxiv.org/abs/1906.00949 (code: github.com/aviralkumar2907/BEAR, commit
    ``647ac13``), run as a baseline with the readme's Laplacian setting in "BAIL: Best-Action Imitation Learning
    for Batch Deep Reinforcement Learning", Chen et al., NeurIPS 2020, https://arxiv.org/abs/1910.12179.

    For a batch ``(s, a, r, s', terminated)``, with ``alpha = exp(log_alpha)`` a learned Lagrange multiplier:

    * ``loss_vae`` (VAE only): as in BCQ, ``MSE + kl_weight * KL``;
    * ``loss_qvalue`` (critics only): ``sum_j (Q_j(s, a) - y)^2``, ``y`` the soft clipped double-Q target
      (:func:`~torchrl_bail.objectives.common.soft_clipped_double_q_target`) over ``num_samples`` samples of the
      *target* actor at ``s'``;
    * ``loss_actor`` (actor only): with ``num_samples_match`` actor samples ``a_m = tanh(mu + sigma * eps_m)``
      (``eps`` clipped to ``+-noise_clip``) and as many VAE samples, ``MMD`` = :func:`laplacian_mmd` of their
      pre-tanh values and ``Q = min_j mean_m Q_j(s, a_m)`` (version 0, critics detached):
      ``alpha * MMD`` during the warm start (the first ``warm_start_updates`` updates), then
      ``-Q + alpha * MMD``; ``alpha`` is detached here;
    * ``loss_alpha`` (``log_alpha`` only): ``-(-Q + alpha * (MMD - epsilon))`` with ``Q`` and ``MMD`` detached,
      so ``log_alpha`` rises while ``MMD > epsilon``. After each step call :meth:`clamp_log_alpha_` (the
      authors clamp to ``[log_alpha_min, log_alpha_max]``) and :meth:`count_update` (the warm-start clock).

    :class:`~torchrl_bail.algorithms.bear.BEAR` runs them in the authors' order (VAE, critics, actor and
    multiplier from the same samples, targets with :class:`~torchrl.objectives.SoftUpdate`, ``tau = 0.005``).

    Args:
        actor_network (TensorDictModule): the tanh-Gaussian actor: it reads ``tensor_keys.observation`` and
            writes ``tensor_keys.loc`` and ``tensor_keys.scale`` (through ``get_dist_params`` when it is a
            :class:`~torchrl.modules.ProbabilisticActor`, e.g. the SAC actor of
            :func:`~torchrl_bail.modules.make_sac_actor` with an unclamped log-std). The loss samples from
            ``(loc, scale)`` itself; a target copy is made.
        qvalue_network (TensorDictModule or a list of two): the critics, as in
            :class:`~torchrl_bail.objectives.bcq.BCQLoss`.
        vae_network (ConditionalVAE): the VAE (:class:`~torchrl_bail.modules.ConditionalVAE`).

    Keyword Args:
        action_spec (TensorSpec, optional): the bounded action spec; defaults to the actor's
            ``spec["action"]``. Actions are ``loc + scale * tanh(.)`` over its bounds (``max_action * tanh``).
        num_samples (int): target-actor samples per next state in the critic target. Defaults to ``10``.
        num_samples_match (int): actor and VAE samples per state for the MMD. Defaults to ``5``.
        kernel_sigma (float): Laplacian kernel width. Defaults to ``10.0``.
        epsilon (float): the MMD threshold of the Lagrangian. Defaults to ``0.05``.
        noise_clip (float): the actor's MMD samples draw ``eps ~ N(0, I)`` clipped to ``+-noise_clip``.
            Defaults to ``0.5``.
        mmd_stabilizer (float): added under the MMD's square root. Defaults to ``1e-6``.
        warm_start_updates (int): updates during which the actor minimises ``alpha * MMD`` only.
            Defaults to ``100000`` (the authors' 20 ``train()`` calls of 5000 updates).
        log_alpha_init (float, optional): initial ``log_alpha``; ``None`` draws it from ``N(0, 1)`` with torch's
            global generator, as the authors do. Defaults to ``None``.
        log_alpha_min (float): lower clamp of ``log_alpha``. Defaults to ``-5.0``.
        log_alpha_max (float): upper clamp of ``log_alpha`` (``lagrange_thresh``). Defaults to ``10.0``.
        lmbda (float): as in :class:`~torchrl_bail.objectives.bcq.BCQLoss`.
        gamma (float): as in :class:`~torchrl_bail.objectives.bcq.BCQLoss`.
        kl_weight (float): as in :class:`~torchrl_bail.objectives.bcq.BCQLoss`.
        reduction (str): as in :class:`~torchrl_bail.objectives.bcq.BCQLoss`.
        deactivate_vmap (bool): as in :class:`~torchrl_bail.objectives.bcq.BCQLoss`.

    Choices where the paper is silent:

    * **Warm-start clock.** A buffer ``update_count`` (in the ``state_dict``) advanced by :meth:`count_update`;
      the actor objective switches with ``torch.where`` (no data-dependent branch) once
      ``update_count >= warm_start_updates``. The multiplier is trained during the warm start too (as coded).
    * **Which samples are clipped.** Only the actor's ``num_samples_match`` samples of the actor loss (they feed
      both the MMD and the Q term, as in the authors' ``sample_multiple``). The critic target's target-actor
      samples and the policy's candidates use unclipped noise (the authors' ``actor.forward``).
    * **One actor pass per state.** The authors repeat each state ``N`` times before the actor; the actor's
      ``(loc, scale)`` do not depend on the copy, so it runs once and ``N`` noises are drawn: the same law.
    * **log sigma is not clamped** (the authors' actor); ``(loc, scale)`` come from the actor's own mapping.
    * **No ensemble-variance term** (``use_ensemble_variance=False``: its coefficient multiplies zero) and only
      version 0 (min over the critics) are implemented.
    * **Gradients.** ``alpha`` is detached in ``loss_actor`` and ``Q``/``MMD`` in ``loss_alpha``, so each term
      reaches only its own parameters; the authors get the same effective updates through ``zero_grad`` calls.
    * gamma, the bootstrap mask, the bounds, random numbers and ``[S, B]`` batches: as in
      :class:`~torchrl_bail.objectives.bcq.BCQLoss`.

    Outputs of :meth:`forward`: ``loss_vae``, ``loss_qvalue``, ``loss_actor``, ``loss_alpha`` and the detached
    diagnostics ``recon_loss``, ``kl_loss``, ``q_mean``, ``target_value_mean``, ``mmd``, ``actor_q_mean``,
    ``alpha`` and ``warm_start`` (1.0 while the warm start lasts).

    Examples:
        >>> import math
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.objectives import SoftUpdate
        >>> from torchrl_bail.modules import make_sac_actor
        >>> from torchrl_bail.modules import action_spec_from_bounds, make_qvalue_network, make_vae
        >>> from torchrl_bail.objectives.bear import BEARLoss
        >>> _ = torch.manual_seed(0)
        >>> spec = action_spec_from_bounds([-1.0] * 3, [1.0] * 3)
        >>> actor = make_sac_actor(11, spec, (32, 32), log_std_min=-math.inf, log_std_max=math.inf)
        >>> loss = BEARLoss(actor, [make_qvalue_network(11, 3, (32, 32)) for _ in range(2)],
        ...                 make_vae(11, spec, (32, 32), latent_dim=6), warm_start_updates=20)
        >>> updater = SoftUpdate(loss, tau=0.005)
        >>> data = TensorDict({
        ...     "observation": torch.randn(8, 11), "action": torch.rand(8, 3) * 2 - 1,
        ...     "next": {"observation": torch.randn(8, 11), "reward": torch.randn(8, 1),
        ...              "terminated": torch.zeros(8, 1, dtype=torch.bool)},
        ... }, [8])
        >>> out = loss(data)
        >>> sorted(k for k in out.keys() if k.startswith("loss"))
        ['loss_actor', 'loss_alpha', 'loss_qvalue', 'loss_vae']
        >>> out["warm_start"]
        tensor(1.)
        >>> sum(out[k] for k in ("loss_vae", "loss_qvalue", "loss_actor", "loss_alpha")).backward()
        >>> loss.clamp_log_alpha_(); loss.count_update(); updater.step()
        >>> loss.policy(num_samples=10)(TensorDict({"observation": torch.randn(4, 11)}, [4]))["action"].shape
        torch.Size([4, 3])
    """

    @dataclass
    class _AcceptedKeys(TwinCriticVAELoss._AcceptedKeys):
        """Maintains default values for all configurable tensordict keys.

        Attributes:
            observation, action, reward, terminated, state_action_value: as in
                :class:`~torchrl_bail.objectives.common.TwinCriticVAELoss`.
            loc (NestedKey): where the actor writes the Gaussian's mean (pre-tanh). Defaults to ``"loc"``.
            scale (NestedKey): where the actor writes the Gaussian's standard deviation. Defaults to ``"scale"``.
        """

        loc: NestedKey = "loc"
        scale: NestedKey = "scale"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    #: coefficients a float may be assigned to, beside the shared ones (an in-place update of the buffer)
    _schedulable_buffers = frozenset({"kernel_sigma", "epsilon", "mmd_stabilizer", "log_alpha_min", "log_alpha_max"})
    out_keys = ["loss_vae", "loss_qvalue", "loss_actor", "loss_alpha", "recon_loss", "kl_loss", "q_mean",
                "target_value_mean", "mmd", "actor_q_mean", "alpha", "warm_start"]

    def __init__(
        self,
        actor_network: TensorDictModule,
        qvalue_network: TensorDictModule | Sequence[TensorDictModule],
        vae_network: nn.Module,
        *,
        action_spec: TensorSpec | None = None,
        num_samples: int = 10,
        num_samples_match: int = 5,
        kernel_sigma: float = 10.0,
        epsilon: float = 0.05,
        noise_clip: float = 0.5,
        mmd_stabilizer: float = 1e-6,
        warm_start_updates: int = 100_000,
        log_alpha_init: float | None = None,
        log_alpha_min: float = -5.0,
        log_alpha_max: float = 10.0,
        lmbda: float = 0.75,
        gamma: float = 0.99,
        kl_weight: float = 0.5,
        reduction: Literal["mean", "sum", "none"] | None = None,
        deactivate_vmap: bool = False,
    ) -> None:
        if action_spec is None:
            try:
                action_spec = actor_network.spec["action"]
            except (AttributeError, KeyError, TypeError):
                action_spec = None
            if action_spec is None or not hasattr(action_spec, "space"):
                raise ValueError("BEARLoss needs the action bounds: pass action_spec= (a Bounded spec) or an "
                                 "actor whose spec['action'] is bounded")
        if int(num_samples_match) < 1:
            raise ValueError(f"num_samples_match must be >= 1, got {num_samples_match}")
        if not float(kernel_sigma) > 0:
            raise ValueError(f"kernel_sigma must be > 0, got {kernel_sigma}")
        if not float(noise_clip) > 0:
            raise ValueError(f"noise_clip must be > 0, got {noise_clip}")
        if not float(log_alpha_min) <= float(log_alpha_max):
            raise ValueError(f"log_alpha_min ({log_alpha_min}) must be <= log_alpha_max ({log_alpha_max})")
        if int(warm_start_updates) < 0:
            raise ValueError(f"warm_start_updates must be >= 0, got {warm_start_updates}")
        super().__init__(actor_network, qvalue_network, vae_network, num_samples=num_samples, lmbda=lmbda,
                         gamma=gamma, kl_weight=kl_weight, reduction=reduction, deactivate_vmap=deactivate_vmap)
        self.num_samples_match = int(num_samples_match)
        self.noise_clip = float(noise_clip)
        low = torch.as_tensor(action_spec.space.low, dtype=torch.float32)
        high = torch.as_tensor(action_spec.space.high, dtype=torch.float32)
        self.register_buffer("action_loc", (high + low) / 2)
        self.register_buffer("action_scale", (high - low) / 2)
        self.register_coeff_buffer("kernel_sigma", kernel_sigma)
        self.register_coeff_buffer("epsilon", epsilon)
        self.register_coeff_buffer("mmd_stabilizer", mmd_stabilizer)
        self._register_load_state_dict_pre_hook(_stabilizer_renamed)  # checkpoints and policy files written before
        self.register_coeff_buffer("log_alpha_min", log_alpha_min)
        self.register_coeff_buffer("log_alpha_max", log_alpha_max)
        self.register_buffer("warm_start_updates", torch.tensor(int(warm_start_updates), dtype=torch.long))
        self.register_buffer("update_count", torch.zeros((), dtype=torch.long))
        init = torch.randn(()) if log_alpha_init is None else torch.tensor(float(log_alpha_init))
        self.log_alpha = nn.Parameter(init)
        self._actor_has_dist_params = getattr(actor_network, "get_dist_params", None) is not None

    # -- the actor's samples -----------------------------------------------------------------------
    def _loc_scale(self, observation: torch.Tensor, params: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        k = self.tensor_keys
        td = TensorDict({k.observation: observation}, batch_size=observation.shape[:-1])
        with params.to_module(self.actor_network, preserve_module_state=False):
            td = self.actor_network.get_dist_params(td) if self._actor_has_dist_params else self.actor_network(td)
        return td.get(k.loc), td.get(k.scale)

    def _actor_samples(self, observation: torch.Tensor, num_samples: int, params: TensorDictBase,
                       noise_clip: float | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``(actions, pre-tanh)``, each ``[*B, N, |A|]``: ``tanh(loc + scale * eps)`` on the bounds."""
        loc, scale = self._loc_scale(observation, params)
        noise = torch.randn(*loc.shape[:-1], num_samples, loc.shape[-1], device=loc.device, dtype=loc.dtype)
        if noise_clip is not None:
            noise = noise.clamp(-noise_clip, noise_clip)
        raw = loc.unsqueeze(-2) + scale.unsqueeze(-2) * noise
        return self.action_loc + self.action_scale * torch.tanh(raw), raw

    def _target_candidates(self, next_observation: torch.Tensor, num_samples: int) -> torch.Tensor:
        return self._actor_samples(next_observation, num_samples, self.target_actor_network_params)[0]

    def candidate_actions(self, observation: torch.Tensor, num_samples: int) -> torch.Tensor:
        """``num_samples`` samples of the current actor per state (unclipped noise): ``[*B, N, |A|]``."""
        return self._actor_samples(observation, num_samples, self.actor_network_params)[0]

    # -- losses ------------------------------------------------------------------------------------
    def policy_terms(self, tensordict: TensorDictBase) -> dict[str, torch.Tensor]:
        """The per-state ``mmd`` and version-0 ``policy_q`` shared by :meth:`actor_loss` and :meth:`alpha_loss`.

        Both carry the gradient to the actor (through its reparameterised samples) and to nothing else.
        """
        observation = tensordict.get(self.tensor_keys.observation)
        n = self.num_samples_match
        with torch.no_grad():
            _, vae_raw = self._vae_samples(observation, n)
        actions, raw = self._actor_samples(observation, n, self.actor_network_params, self.noise_clip)
        mmd = laplacian_mmd(vae_raw, raw, self.kernel_sigma, self.mmd_stabilizer)
        q = self._q_values(expand_samples(observation, n), actions, self._cached_detach_qvalue_network_params)
        return {"mmd": mmd, "policy_q": q.mean(-1).amin(0)}

    def actor_loss(self, tensordict: TensorDictBase,
                   terms: dict[str, torch.Tensor] | None = None) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """``(loss_actor, {"mmd", "actor_q_mean", "warm_start"})``: ``alpha * MMD`` during the warm start,
        ``-Q + alpha * MMD`` after it; actor only. ``terms`` (from :meth:`policy_terms`) avoids a second pass.
        """
        if terms is None:
            terms = self.policy_terms(tensordict)
        mmd, policy_q = terms["mmd"], terms["policy_q"]
        constraint = self._seed_log_alpha().detach().exp() * mmd
        warm = self.update_count < self.warm_start_updates
        loss = self._reduce(torch.where(warm, constraint, constraint - policy_q), tensordict)
        self._clear_weakrefs(tensordict, "actor_network_params", "qvalue_network_params", "vae_network_params")
        return loss, {"mmd": mmd.detach().mean(-1), "actor_q_mean": policy_q.detach().mean(-1),
                      "warm_start": warm.to(mmd.dtype)}

    def alpha_loss(self, tensordict: TensorDictBase,
                   terms: dict[str, torch.Tensor] | None = None) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """``(loss_alpha, {"alpha"})``: ``-(-Q + exp(log_alpha) * (MMD - epsilon))``, ``Q`` and ``MMD`` detached."""
        if terms is None:
            with torch.no_grad():
                terms = self.policy_terms(tensordict)
        mmd, policy_q = terms["mmd"].detach(), terms["policy_q"].detach()
        alpha = self._seed_log_alpha().exp()
        loss = self._reduce(policy_q - alpha * (mmd - self.epsilon), tensordict)
        return loss, {"alpha": alpha.detach().squeeze(-1) if alpha.ndim else alpha.detach()}

    def _seed_log_alpha(self) -> torch.Tensor:
        """``log_alpha`` shaped to multiply per-state terms: a scalar, or (one multiplier per seed, stacked by
        :class:`~torchrl_bail.core.stacking.SeedStack`) ``[S, 1]`` against ``[S, B]``."""
        return self.log_alpha.unsqueeze(-1) if self.log_alpha.ndim else self.log_alpha

    @torch.no_grad()
    def clamp_log_alpha_(self) -> None:
        """Clamps ``log_alpha`` to ``[log_alpha_min, log_alpha_max]`` in place (after each multiplier step)."""
        self.log_alpha.clamp_(self.log_alpha_min, self.log_alpha_max)

    @torch.no_grad()
    def count_update(self, n: int = 1) -> None:
        """Advances the warm-start clock by ``n`` updates."""
        self.update_count.add_(int(n))

    def policy(self, num_samples: int = 10) -> BestOfNPolicy:
        """The evaluation policy: the best of ``num_samples`` actor samples by ``Q_1`` (the authors use 10)."""
        return BestOfNPolicy(self, num_samples)

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Computes the four BEAR losses on the current parameters (the actor and multiplier terms from the same
        samples). Nothing is stepped or counted here.
        """
        loss_vae, meta_vae = self.vae_loss(tensordict)
        loss_qvalue, meta_q = self.qvalue_loss(tensordict)
        terms = self.policy_terms(tensordict)
        loss_actor, meta_actor = self.actor_loss(tensordict, terms)
        loss_alpha, meta_alpha = self.alpha_loss(tensordict, terms)
        return TensorDict({"loss_vae": loss_vae, "loss_qvalue": loss_qvalue, "loss_actor": loss_actor,
                           "loss_alpha": loss_alpha, **meta_vae, **meta_q, **meta_actor, **meta_alpha})

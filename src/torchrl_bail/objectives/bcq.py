"""Batch-Constrained deep Q-learning (BCQ), the 2019 version the BAIL authors ran as a baseline (supp. C.2, BCQ)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, dispatch
from torch import nn

from torchrl_bail.objectives.common import BestOfNPolicy, TwinCriticVAELoss, expand_samples

__all__ = ["BCQLoss"]


class BCQLoss(TwinCriticVAELoss):
    """BCQ for continuous actions: a VAE of the batch's actions, a perturbation actor and soft clipped twin critics.

    Presented in "Off-Policy Deep Reinforcement Learning without Exploration", Fujimoto, Meger and Precup,
    ICML 2019, https://arxiv.org/abs/1812.02900 (code: github.com/sfujim/BCQ, commit ``05c07fc``, the version
    run as a baseline in "BAIL: Best-Action Imitation Learning for Batch Deep Reinforcement Learning",
    Chen et al., NeurIPS 2020, https://arxiv.org/abs/1910.12179).

    For a batch ``(s, a, r, s', terminated)``:

    * ``loss_vae`` (VAE only): ``MSE(D(s, z), a) + kl_weight * KL(q(z | s, a) || N(0, I))`` with the
      reparameterised ``z ~ q(z | s, a)``;
    * ``loss_qvalue`` (critics only): ``sum_j (Q_j(s, a) - y)^2`` with
      ``y = r + gamma * (1 - terminated) * max_n [lmbda * min_j + (1 - lmbda) * max_j] Q'_j(s', xi'(s', a_n))``,
      ``a_n`` = ``num_samples`` VAE samples at ``s'`` (prior latents clipped to ``+-latent_clip``), ``xi'`` and
      ``Q'`` the target actor and critics (:func:`~torchrl_bail.objectives.common.soft_clipped_double_q_target`);
    * ``loss_actor`` (actor only): ``-Q_1(s, xi(s, a_vae))`` with one VAE sample ``a_vae`` per state and the
      first critic's parameters detached.

    The authors' update runs these in that order, each after the previous network's optimizer step, then moves
    the targets by Polyak averaging (:class:`~torchrl.objectives.SoftUpdate` with ``tau = 0.005``): see
    :class:`~torchrl_bail.algorithms.bcq.BCQ`. :meth:`forward` computes all three on the current parameters.

    Args:
        actor_network (TensorDictModule): the perturbation model ``xi``; it reads ``tensor_keys.observation`` and
            a candidate ``tensor_keys.action`` and writes the perturbed, clamped action under
            ``tensor_keys.action`` (:func:`~torchrl_bail.modules.make_perturbation_actor`). A target copy is made.
        qvalue_network (TensorDictModule or a list of two): the critic(s), reading ``observation`` and
            ``action`` and writing ``tensor_keys.state_action_value``. A list of two modules keeps their own
            initialisations (the authors' critics are two independently initialised nets); a single module is
            expanded to two copies, re-drawn as TorchRL does. The two are stacked and run with ``torch.vmap``;
            a target copy is made.
        vae_network (ConditionalVAE): the VAE (:class:`~torchrl_bail.modules.ConditionalVAE`); no target copy.

    Keyword Args:
        num_samples (int): VAE candidates per next state in the critic target. Defaults to ``10``.
        lmbda (float): weight of the minimum in the soft clipped double-Q. Defaults to ``0.75``.
        gamma (float): discount. Defaults to ``0.99``.
        kl_weight (float): weight of the KL term of ``loss_vae``. Defaults to ``0.5``.
        reduction (str, optional): ``"none"`` | ``"mean"`` | ``"sum"``. Defaults to ``"mean"``. ``"none"`` gives
            one value per transition (``[B]`` or ``[S, B]``); ``"mean"`` averages over the last batch dimension
            and then over the leading ones (seeds), which for ``[B]`` is the authors' batch mean.
        deactivate_vmap (bool): run the two critics in a Python loop instead of ``torch.vmap``.
            Defaults to ``False``.

    Choices where the paper is silent:

    * **gamma is a constructor argument** (a buffer), not a TorchRL value estimator: the target is a one-step
      maximum over sampled actions of a soft clipped double-Q, which no TD estimator computes, so
      ``default_value_estimator`` is ``None``.
    * **Bootstrap mask** = ``("next", "terminated")``; a missing entry raises instead of falling back on ``done``.
    * **Action bounds.** ``max_action * tanh`` of the authors is ``loc + scale * tanh`` over the action spec's bounds,
      identical for the symmetric MuJoCo bounds; the perturbation is ``phi * scale`` and the clamp uses the bounds.
    * **The next-state candidates** come from the *current* VAE (it has no target), as in the authors' code.
    * **Random numbers** (latents, reparameterisation) come from torch's global generator, so a run's seed fixes
      them (the authors used NumPy's).
    * **[S, B] batches.** All three losses (and the policy) take any leading batch shape; ``"mean"`` reduces per
      seed (last dimension first) and ``loss_mask_key`` masks are honoured per seed. Limitation: one set of
      weights serves all ``S`` slices; seed-ensembled networks are not supported (the VAE's sampling methods are
      not ensemble-aware), so independent seeds run as separate processes (Hydra multirun).
    * **Gradients.** The VAE samples of ``loss_actor`` and of the target are drawn without gradient and the
      critics' parameters are detached in ``loss_actor``, so each term reaches only its own network (the authors
      get the same effective updates through ``zero_grad``); one backward of the sum is then equivalent to three.
    * **Evaluation policy** (:class:`~torchrl_bail.objectives.common.BestOfNPolicy`): ``num_samples`` VAE
      samples perturbed by the *current* actor, argmax of the *current* ``Q_1``; it samples whatever the
      exploration type (this is the authors' deterministic test-time procedure) and works for any batch of envs.
    * **Twin critics** are stacked parameters (TorchRL's ``expand_dim`` idiom) run by ``torch.vmap``, or by a
      loop over the two slices with ``deactivate_vmap=True`` (faster on CPU: two matmuls beat one batched one);
      MLP critics then run straight from the stacked tensors (``F.linear``, no ``to_module``), bit-identically.
    * **No priority/TD-error output**: the batch is sampled uniformly.

    Outputs of :meth:`forward`: ``loss_vae``, ``loss_qvalue``, ``loss_actor`` and the detached diagnostics
    ``recon_loss``, ``kl_loss``, ``q_mean``, ``target_value_mean``, ``actor_q_mean`` (means over the last batch
    dimension). :meth:`policy` returns the evaluation policy (best of ``num_samples`` candidates by ``Q_1``).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.objectives import SoftUpdate
        >>> from torchrl_bail.modules import (action_spec_from_bounds, make_perturbation_actor,
        ...                                   make_qvalue_network, make_vae)
        >>> from torchrl_bail.objectives.bcq import BCQLoss
        >>> _ = torch.manual_seed(0)
        >>> spec = action_spec_from_bounds([-1.0] * 3, [1.0] * 3)
        >>> loss = BCQLoss(make_perturbation_actor(11, spec, (32, 32), phi=0.05),
        ...                [make_qvalue_network(11, 3, (32, 32)) for _ in range(2)],
        ...                make_vae(11, spec, (32, 32), latent_dim=6))
        >>> updater = SoftUpdate(loss, tau=0.005)
        >>> data = TensorDict({
        ...     "observation": torch.randn(8, 11), "action": torch.rand(8, 3) * 2 - 1,
        ...     "next": {"observation": torch.randn(8, 11), "reward": torch.randn(8, 1),
        ...              "terminated": torch.zeros(8, 1, dtype=torch.bool)},
        ... }, [8])
        >>> out = loss(data)
        >>> sorted(k for k in out.keys() if k.startswith("loss"))
        ['loss_actor', 'loss_qvalue', 'loss_vae']
        >>> (out["loss_vae"] + out["loss_qvalue"] + out["loss_actor"]).backward()
        >>> updater.step()
        >>> policy = loss.policy(num_samples=10)
        >>> policy(TensorDict({"observation": torch.randn(4, 11)}, [4]))["action"].shape
        torch.Size([4, 3])

    Keyword calls work too (nested keys are joined by ``_``):

        >>> _ = loss.select_out_keys("loss_qvalue")
        >>> loss(observation=torch.randn(8, 11), action=torch.rand(8, 3) * 2 - 1,
        ...      next_observation=torch.randn(8, 11), next_reward=torch.randn(8, 1),
        ...      next_terminated=torch.zeros(8, 1, dtype=torch.bool)).shape
        torch.Size([])
    """

    out_keys = ["loss_vae", "loss_qvalue", "loss_actor", "recon_loss", "kl_loss", "q_mean", "target_value_mean",
                "actor_q_mean"]

    def __init__(
        self,
        actor_network: TensorDictModule,
        qvalue_network: TensorDictModule | Sequence[TensorDictModule],
        vae_network: nn.Module,
        *,
        num_samples: int = 10,
        lmbda: float = 0.75,
        gamma: float = 0.99,
        kl_weight: float = 0.5,
        reduction: Literal["mean", "sum", "none"] | None = None,
        deactivate_vmap: bool = False,
    ) -> None:
        super().__init__(actor_network, qvalue_network, vae_network, num_samples=num_samples, lmbda=lmbda,
                         gamma=gamma, kl_weight=kl_weight, reduction=reduction, deactivate_vmap=deactivate_vmap)

    def _perturbed_vae_samples(self, observation: torch.Tensor, num_samples: int, params) -> torch.Tensor:
        """``xi(s, a_n)`` for ``num_samples`` VAE samples ``a_n`` per state: ``[*B, N, |A|]``."""
        with torch.no_grad():
            candidates, _ = self._vae_samples(observation, num_samples)
        return self._actor(expand_samples(observation, num_samples), candidates, params).get(self.tensor_keys.action)

    def _target_candidates(self, next_observation: torch.Tensor, num_samples: int) -> torch.Tensor:
        return self._perturbed_vae_samples(next_observation, num_samples, self.target_actor_network_params)

    def candidate_actions(self, observation: torch.Tensor, num_samples: int) -> torch.Tensor:
        """``num_samples`` VAE samples per state, perturbed by the current actor: ``[*B, N, |A|]``."""
        return self._perturbed_vae_samples(observation, num_samples, self.actor_network_params)

    def actor_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """``(loss_actor, {"actor_q_mean"})``: ``-Q_1(s, xi(s, a_vae))``; the gradient reaches the actor only."""
        observation = tensordict.get(self.tensor_keys.observation)
        with torch.no_grad(), self.vae_network_params.to_module(self.vae_network, preserve_module_state=False):
            sampled = self.vae_network.decode(observation)
        action = self._actor(observation, sampled, self.actor_network_params).get(self.tensor_keys.action)
        q1 = self.q1_value(observation, action)
        loss = self._reduce(-q1, tensordict)
        self._clear_weakrefs(tensordict, "actor_network_params", "qvalue_network_params", "vae_network_params")
        return loss, {"actor_q_mean": q1.detach().mean(-1)}

    def policy(self, num_samples: int = 10) -> BestOfNPolicy:
        """The evaluation policy: the best of ``num_samples`` perturbed VAE samples by ``Q_1`` (10 in 2019)."""
        return BestOfNPolicy(self, num_samples)

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Computes the three BCQ losses on the current parameters.

        Args:
            tensordict (TensorDictBase): ``observation``, ``action`` and ``("next", observation | reward |
                terminated)``, batch shape ``[B]`` or ``[S, B]``.

        Returns:
            A :class:`~tensordict.TensorDict` with ``loss_vae``, ``loss_qvalue``, ``loss_actor`` and diagnostics.
        """
        loss_vae, meta_vae = self.vae_loss(tensordict)
        loss_qvalue, meta_q = self.qvalue_loss(tensordict)
        loss_actor, meta_actor = self.actor_loss(tensordict)
        return TensorDict({"loss_vae": loss_vae, "loss_qvalue": loss_qvalue, "loss_actor": loss_actor,
                           **meta_vae, **meta_q, **meta_actor})

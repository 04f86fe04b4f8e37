"""MARWIL, monotonic advantage re-weighted imitation learning (supp. C.2, MARWIL), as the BAIL authors ran it.

A value net ``V_psi(s)`` regresses the Monte-Carlo returns ``G`` (the same augmented returns BAIL uses); the
policy imitates the batch's actions with per-sample weights ``exp(beta * A / c)`` where ``A = G - V(s)`` is the
advantage and ``c^2`` a slow running estimate of ``E[A^2]``. ``beta = 0`` is plain behaviour cloning.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictModule, dispatch
from tensordict.utils import NestedKey

from torchrl_bail.objectives._shared import LazyInKeysLoss, check_reduction, required_entry, value_and_return

__all__ = ["MARWILLoss"]


class MARWILLoss(LazyInKeysLoss):
    r"""MARWIL's advantage-weighted imitation loss for a deterministic actor, and its value regression.

    Presented in "Exponentially Weighted Imitation Learning for Batched Historical Data", Wang et al.,
    NeurIPS 2018,
    https://papers.nips.cc/paper/7866-exponentially-weighted-imitation-learning-for-batched-historical-data;
    run as a baseline in "BAIL: Best-Action Imitation Learning for Batch Deep Reinforcement Learning",
    Chen et al., NeurIPS 2020, https://arxiv.org/abs/1910.12179 (supp. C.2), with BAIL's augmented returns.

    For a batch of states ``s_i``, actions ``a_i`` and returns ``G_i``:

    * advantage ``A_i = G_i - V_psi(s_i)``;
    * running normaliser (training mode only, without gradient):
      ``c^2 <- c^2 + c2_rate * (mean_i(A_i^2) - c^2)``, started at ``c2_init``;
    * weights ``w_i = exp(min(beta * A_i / (sqrt(c^2) + eps), max_exponent))``, detached;
    * ``loss_actor`` per point: ``w_i * mean_a (pi(s_i) - a_i)^2`` (for a deterministic tanh actor the
      Gaussian log-likelihood of MARWIL is, up to constants, this weighted MSE);
    * ``loss_value`` per point: ``vf_coeff * 0.5 * A_i^2`` (RLlib's form; it only trains ``V_psi``).

    ``loss_actor`` back-propagates into the actor only (the weights are detached) and ``loss_value`` into the
    value net only, so the two can be stepped by separate optimizers from one ``backward`` of their sum.

    Args:
        actor_network (TensorDictModule): the deterministic policy ``pi``; it reads its ``in_keys``
            (``"observation"``) and writes ``tensor_keys.action``. It runs on a selection of its ``in_keys``,
            so the batch's own action under the same key is never overwritten.
        value_network (TensorDictModule): ``V_psi``; reads its ``in_keys`` and writes ``tensor_keys.value``
            (shape ``[*B, 1]`` or ``[*B]``). Both networks' parameters are the loss' parameters (shared).

    Keyword Args:
        beta (float): inverse temperature of the weights, ``>= 0``; ``0`` gives behaviour cloning.
            Defaults to ``1.0``.
        c2_init (float): start value of the running ``c^2``, ``> 0``. Defaults to ``100.0``.
        c2_rate (float): update rate of ``c^2``, in ``[0, 1]``. Defaults to ``1e-8``.
        vf_coeff (float): scale of the value loss, ``>= 0``. Defaults to ``1.0``.
        max_exponent (float): the weights' exponent is clamped at this value, so ``w <= exp(max_exponent)``
            and never overflows. Defaults to ``20.0``.
        eps (float): added to ``c = sqrt(c^2)`` in the weights' denominator. Defaults to ``1e-8``.
        reduction (str, optional): ``"none"`` | ``"mean"`` | ``"sum"``. Defaults to ``"mean"``.

            * ``"none"``: both losses have the batch shape of the input (``[B]`` or ``[S, B]``).
            * ``"mean"``: the mean over the last batch dimension (one seed's points), then over the leading
              ones (the seeds): a scalar.
            * ``"sum"``: the sum over every element.

    All coefficients and ``c^2`` are registered buffers: they follow ``.to()`` and the ``state_dict``.

    The output holds ``loss_actor`` and ``loss_value`` (the back-propagated terms) and detached diagnostics
    reduced over the last batch dimension (scalars for ``[B]`` batches, ``[S]`` for ``[S, B]``):
    ``advantage_mean``, ``value_mean``, ``weight_mean``, ``weight_max``, ``weight_share_max`` (the largest
    weight's share of the mini-batch's total weight: ``1/B`` for uniform weights, ``1`` when one point carries all
    of it), ``clamped_fraction`` (share of points whose exponent hit ``max_exponent``), ``squared_error_mean``
    (the unweighted ``mean_a (pi(s) - a)^2``: how well the actor imitates the batch, comparable with BC's
    ``loss_bc``) and ``c2`` (the normaliser the weights used).

    Choices made where the paper (supp. C.2) is silent:

    * **When c^2 moves.** Only in training mode (``loss.train()``, the default), under ``torch.no_grad``,
      once per call of :meth:`forward` or :meth:`actor_loss`, *before* the weights are computed, so a call
      uses the freshly updated ``c^2`` (RLlib's order). :meth:`value_loss` never touches it; in
      ``loss.eval()`` mode the loss is a pure function of its input.
    * **Precision of c^2.** ``c^2`` and ``c2_rate`` are float64 buffers: at ``c^2 = 100`` a float32 buffer
      cannot represent an increment below about ``4e-6``, so with ``c2_rate = 1e-8`` every update with
      ``|mean(A^2) - c^2| < 400`` would round away. The weights themselves are computed in the data's dtype.
    * **Seeds.** On ``[S, B]`` batches each seed keeps its own ``c^2`` (``mean(A^2)`` is taken over that
      seed's points): the buffer is a scalar until the first training call on an ``[S, B]`` batch, then
      becomes ``[S]`` (every seed starting from the scalar's value). A ``[S]`` state dict loads into a fresh
      loss. Feeding a batch whose leading shape differs from the buffer's raises a ``ValueError``.
    * **Clamping.** Only the exponent's upper side is clamped (at ``max_exponent``): very negative
      advantages give weights that underflow to ``0``, which is finite and means "do not imitate".
    * **Masks.** :attr:`~torchrl.objectives.LossModule.loss_mask_key` masks work as in every TorchRL loss;
      masked points are excluded from both losses (zero under ``"none"``), from the ``c^2`` update and from
      the diagnostics.
    * **Keys.** The predicted action is read from the actor's output under ``tensor_keys.action``, the key
      that also holds the batch's action (the TD3+BC convention).
    * **Training (:class:`~torchrl_bail.algorithms.marwil.MARWIL`).** The paper allows one total loss or two
      separately optimised networks; the algorithm does both at once: one forward, one ``backward`` of
      ``loss_actor + loss_value`` (the gradients do not mix), then one Adam step each (``algo.policy.lr``,
      ``algo.value.lr``). The value net is the upper envelope's architecture and init
      (:func:`~torchrl_bail.modules.make_value_network`: 128-128 ReLU, output layer default init x 0.1, bias 0),
      the paper leaving both open. Checkpoints carry this loss' buffers (``c^2`` included) beside the networks.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_bail.modules import action_spec_from_bounds, make_deterministic_actor, make_value_network
        >>> from torchrl_bail.objectives.marwil import MARWILLoss
        >>> _ = torch.manual_seed(0)
        >>> actor = make_deterministic_actor(11, action_spec_from_bounds([-1.0] * 3, [1.0] * 3), (64, 64))
        >>> loss = MARWILLoss(actor, make_value_network(11), beta=1.0, c2_init=100.0, c2_rate=1e-8)
        >>> data = TensorDict({"observation": torch.randn(32, 11), "action": torch.rand(32, 3) * 2 - 1,
        ...                    "return": torch.randn(32) * 10}, [32])
        >>> out = loss(data)
        >>> sorted(key for key in out.keys() if key.startswith("loss_"))
        ['loss_actor', 'loss_value']
        >>> sorted(key for key in out.keys() if not key.startswith("loss_"))  # doctest: +NORMALIZE_WHITESPACE
        ['advantage_mean', 'c2', 'clamped_fraction', 'squared_error_mean', 'value_mean', 'weight_max',
         'weight_mean', 'weight_share_max']
        >>> out["loss_actor"].shape, out["loss_value"].shape
        (torch.Size([]), torch.Size([]))
        >>> (out["loss_actor"] + out["loss_value"]).backward()

    This class is compatible with non-tensordict based calls too: the keyword arguments are the networks'
    ``in_keys``, the action and the return (``return``). ``select_out_keys`` picks what comes back.

    Examples:
        >>> import torch
        >>> from torchrl_bail.modules import action_spec_from_bounds, make_deterministic_actor, make_value_network
        >>> from torchrl_bail.objectives.marwil import MARWILLoss
        >>> actor = make_deterministic_actor(11, action_spec_from_bounds([-1.0] * 3, [1.0] * 3), (64, 64))
        >>> loss = MARWILLoss(actor, make_value_network(11))
        >>> _ = loss.select_out_keys("loss_actor", "loss_value")
        >>> loss_actor, loss_value = loss(observation=torch.randn(8, 11), action=torch.rand(8, 3) * 2 - 1,
        ...                               **{"return": torch.randn(8)})
        >>> loss_actor.shape, loss_value.shape
        (torch.Size([]), torch.Size([]))
    """

    @dataclass
    class _AcceptedKeys:
        """Maintains default values for all configurable tensordict keys.

        Attributes:
            action (NestedKey): the batch's action ``a`` (input) and the actor's prediction (actor output).
                Defaults to ``"action"``.
            value (NestedKey): where the value network writes ``V(s)``. Defaults to ``"state_value"``.
            value_target (NestedKey): the Monte-Carlo return ``G`` (shape ``[*B]`` or ``[*B, 1]``).
                Defaults to ``"return"``.
        """

        action: NestedKey = "action"
        value: NestedKey = "state_value"
        value_target: NestedKey = "return"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    default_value_estimator = None
    out_keys = ["loss_actor", "loss_value", "advantage_mean", "value_mean", "weight_mean", "weight_max",
                "weight_share_max", "clamped_fraction", "squared_error_mean", "c2"]
    #: coefficients a float may be assigned to (``loss.beta = 0.5``: an in-place update); not ``c2``, the running
    #: estimate the loss updates itself
    _schedulable_buffers = frozenset({"beta", "vf_coeff", "max_exponent", "eps", "c2_rate"})

    actor_network: TensorDictModule
    actor_network_params: TensorDictParams
    target_actor_network_params: TensorDictParams
    value_network: TensorDictModule
    value_network_params: TensorDictParams
    target_value_network_params: TensorDictParams

    def __init__(
        self,
        actor_network: TensorDictModule,
        value_network: TensorDictModule,
        *,
        beta: float = 1.0,
        c2_init: float = 100.0,
        c2_rate: float = 1e-8,
        vf_coeff: float = 1.0,
        max_exponent: float = 20.0,
        eps: float = 1e-8,
        reduction: Literal["mean", "sum", "none"] | None = None,
    ) -> None:
        reduction = check_reduction(reduction)
        for name, value, ok, expected in (
            ("beta", beta, float(beta) >= 0, ">= 0"),
            ("c2_init", c2_init, float(c2_init) > 0, "> 0"),
            ("c2_rate", c2_rate, 0 <= float(c2_rate) <= 1, "in [0, 1]"),
            ("vf_coeff", vf_coeff, float(vf_coeff) >= 0, ">= 0"),
            ("max_exponent", max_exponent, abs(float(max_exponent)) < float("inf"), "finite"),
            ("eps", eps, float(eps) > 0, "> 0"),
        ):
            if not ok:
                raise ValueError(f"MARWILLoss: {name} must be {expected}, got {value}")
        super().__init__()
        self.convert_to_functional(actor_network, "actor_network")
        self.convert_to_functional(value_network, "value_network")
        self.register_coeff_buffer("beta", float(beta))
        self.register_coeff_buffer("vf_coeff", float(vf_coeff))
        self.register_coeff_buffer("max_exponent", float(max_exponent))
        self.register_coeff_buffer("eps", float(eps))
        self.register_coeff_buffer("c2_rate", float(c2_rate), dtype=torch.float64)
        self.register_coeff_buffer("c2", float(c2_init), dtype=torch.float64)
        self.reduction = reduction

    def _in_key_list(self) -> list[NestedKey]:
        return [self.tensor_keys.action, self.tensor_keys.value_target, *self.actor_network.in_keys,
                *self.value_network.in_keys]

    # -- state dict: c2 may be per seed ------------------------------------------------------------------
    def _load_from_state_dict(self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys,
                              error_msgs) -> None:
        saved = state_dict.get(prefix + "c2")
        if isinstance(saved, torch.Tensor) and saved.shape != self.c2.shape:
            self.c2 = torch.empty(saved.shape, dtype=self.c2.dtype, device=self.c2.device)
        super()._load_from_state_dict(state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys,
                                      error_msgs)

    # -- pieces ------------------------------------------------------------------------------------------
    def _mask(self, tensordict: TensorDictBase, like: torch.Tensor) -> torch.Tensor | None:
        """The AND of the input's loss masks, broadcast to ``like`` (``[*B]``); ``None`` when there is none."""
        mask = None
        for key in self._loss_mask_keys():
            entry = tensordict.get(key, None)
            if entry is not None:
                entry = self._expand_loss_mask(entry, like)
                mask = entry if mask is None else mask & entry
        return mask

    @staticmethod
    def _mean_last(x: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
        """Mean over the last batch dimension (one seed's points), over unmasked points only."""
        if mask is None:
            return x.mean(-1)
        return torch.where(mask, x, torch.zeros_like(x)).sum(-1) / mask.sum(-1).clamp_min(1)

    def _reduce(self, loss: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
        """``reduction`` with per-seed means: the mean over ``B``, then over the seeds."""
        if self.reduction == "mean":
            # without a mask every seed has B points, so the mean of the per-seed means is the plain mean
            return loss.mean() if mask is None else self._mean_last(loss, mask).mean()
        if mask is not None:
            loss = torch.where(mask, loss, torch.zeros_like(loss))
        return loss.sum() if self.reduction == "sum" else loss

    def _advantage(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        """``(A, V)`` with shape ``[*B]``: ``A = G - V(s)`` carries ``V``'s graph."""
        value, target = value_and_return(self, tensordict)
        return target - value, value

    def _value_terms(self, advantage: torch.Tensor) -> torch.Tensor:
        """``vf_coeff * 0.5 * A^2`` per point (the coefficient is folded first: one graph node, not two)."""
        return advantage.square() * (0.5 * self.vf_coeff)

    @torch.compiler.disable  # torch 2.13's AOT autograd drops in-place updates of 0-dim float64 inputs
    @torch.no_grad()
    def _update_c2(self, advantage: torch.Tensor, mask: torch.Tensor | None) -> None:
        """``c^2 <- c^2 + rate * (mean(A^2) - c^2)``, per seed; in float64 (run eagerly in a compiled update)."""
        squared_mean = self._mean_last(advantage.square(), mask).to(self.c2.dtype)
        if self.c2.shape != squared_mean.shape:
            if self.c2.ndim != 0:
                raise ValueError(
                    f"MARWILLoss: c2 holds one normaliser per seed, shape {tuple(self.c2.shape)}, but the batch has "
                    f"leading shape {tuple(squared_mean.shape)}"
                )
            self.c2 = self.c2.expand(squared_mean.shape).clone()
        self.c2.add_(self.c2_rate * (squared_mean - self.c2))

    @torch.no_grad()
    def _weights(self, advantage: torch.Tensor, mask: torch.Tensor | None, *,
                 update_c2: bool | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``(w, clamped)``: the detached weights ``exp(min(beta A / (c + eps), max_exponent))``; ``c^2`` moves
        first when ``update_c2`` (default: in training mode)."""
        advantage = advantage.detach()
        if self.training if update_c2 is None else update_c2:
            self._update_c2(advantage, mask)
        c2 = self.c2
        if c2.ndim:
            if c2.shape != advantage.shape[:-1]:
                raise ValueError(
                    f"MARWILLoss: c2 has shape {tuple(c2.shape)} but the batch has leading shape "
                    f"{tuple(advantage.shape[:-1])}"
                )
            c2 = c2.unsqueeze(-1)
        scale = (c2.sqrt() + self.eps).to(advantage.dtype)
        exponent = self.beta * advantage / scale
        clamped = exponent >= self.max_exponent
        return exponent.clamp_max(self.max_exponent).exp(), clamped

    def _squared_error(self, tensordict: TensorDictBase) -> torch.Tensor:
        """``mean_a (pi(s) - a)^2``, shape ``[*B]``, carrying the actor's graph."""
        with self.actor_network_params.to_module(self.actor_network, preserve_module_state=False):
            predicted = self.actor_network(tensordict.select(*self.actor_network.in_keys)).get(self.tensor_keys.action)
        action = required_entry(self, tensordict, self.tensor_keys.action)
        if predicted.shape != action.shape:
            raise ValueError(
                f"MARWILLoss: the actor predicts {self.tensor_keys.action!r} with shape {tuple(predicted.shape)} "
                f"but the batch's action has shape {tuple(action.shape)}"
            )
        if action.dtype != predicted.dtype:
            action = action.to(predicted.dtype)
        return (predicted - action).square().mean(-1)

    def _diagnostics(self, advantage, value, weight, clamped, error, mask) -> dict[str, torch.Tensor]:
        dtype = advantage.dtype
        valid_weight = weight if mask is None else torch.where(mask, weight, torch.zeros_like(weight))
        weight_max = valid_weight.amax(-1)
        return {
            "advantage_mean": self._mean_last(advantage.detach(), mask),
            "value_mean": self._mean_last(value.detach(), mask),
            "weight_mean": self._mean_last(weight, mask),
            "weight_max": weight_max,
            "weight_share_max": weight_max / valid_weight.sum(-1).clamp_min(torch.finfo(dtype).tiny),
            "clamped_fraction": self._mean_last(clamped.to(dtype), mask),
            "squared_error_mean": self._mean_last(error.detach(), mask),
            "c2": self.c2.to(dtype, copy=True),
        }

    # -- public sub-losses -------------------------------------------------------------------------------
    @torch.no_grad()
    def advantage_weights(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(w, A, clamped)`` per point: the weights the actor loss gives these points now, their advantages
        ``G - V(s)`` and where the exponent hit ``max_exponent``, each of batch shape ``[B]`` or ``[S, B]``.

        Under the current value network and ``c^2``, which this never moves (in training mode too): for looking at
        the weights' distribution on held-out data without changing what the next update does.
        """
        advantage, _ = self._advantage(tensordict)
        mask = self._mask(tensordict, advantage)
        weight, clamped = self._weights(advantage, mask, update_c2=False)
        self._clear_weakrefs(tensordict, "value_network_params")
        return weight, advantage, clamped

    def value_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """``vf_coeff * 0.5 * (G - V(s))^2``, reduced; it never updates ``c^2``.

        Args:
            tensordict (TensorDictBase): input with the value network's ``in_keys`` and
                ``tensor_keys.value_target``, batch shape ``[B]`` or ``[S, B]``.

        Returns:
            ``(loss_value, metadata)`` where ``metadata`` holds the detached ``advantage_mean`` and
            ``value_mean`` reduced over the last batch dimension.
        """
        advantage, value = self._advantage(tensordict)
        mask = self._mask(tensordict, advantage)
        loss = self._reduce(self._value_terms(advantage), mask)
        metadata = {"advantage_mean": self._mean_last(advantage.detach(), mask),
                    "value_mean": self._mean_last(value.detach(), mask)}
        self._clear_weakrefs(tensordict, "value_network_params")
        return loss, metadata

    def actor_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """``w * mean_a (pi(s) - a)^2``, reduced; in training mode it advances ``c^2`` once.

        The value network runs without gradient here: the loss back-propagates into the actor only.

        Args:
            tensordict (TensorDictBase): input with both networks' ``in_keys``, ``tensor_keys.action`` and
                ``tensor_keys.value_target``, batch shape ``[B]`` or ``[S, B]``.

        Returns:
            ``(loss_actor, metadata)`` with the detached diagnostics listed in the class docstring.
        """
        with torch.no_grad():
            advantage, value = self._advantage(tensordict)
        mask = self._mask(tensordict, advantage)
        weight, clamped = self._weights(advantage, mask)
        error = self._squared_error(tensordict)
        loss = self._reduce(weight * error, mask)
        metadata = self._diagnostics(advantage, value, weight, clamped, error, mask)
        self._clear_weakrefs(tensordict, "actor_network_params", "value_network_params")
        return loss, metadata

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Computes both losses with one pass of each network.

        Args:
            tensordict (TensorDictBase): input with both networks' ``in_keys`` (``"observation"``), the action
                ``tensor_keys.action`` and the return ``tensor_keys.value_target`` (``"return"``).

        Returns:
            A :class:`~tensordict.TensorDict` with ``loss_actor``, ``loss_value`` and the diagnostics.
        """
        advantage, value = self._advantage(tensordict)
        mask = self._mask(tensordict, advantage)
        loss_value = self._reduce(self._value_terms(advantage), mask)
        weight, clamped = self._weights(advantage, mask)
        error = self._squared_error(tensordict)
        loss_actor = self._reduce(weight * error, mask)
        out = TensorDict({"loss_actor": loss_actor, "loss_value": loss_value,
                          **self._diagnostics(advantage, value, weight, clamped, error, mask)})
        self._clear_weakrefs(tensordict, out, "actor_network_params", "value_network_params")
        return out

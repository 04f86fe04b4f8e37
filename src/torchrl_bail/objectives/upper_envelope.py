"""The upper-envelope penalty loss of BAIL (paper Sec. 4; supp. Alg. 1, 3.3).

The envelope ``V`` is fitted to Monte-Carlo returns ``G`` with an asymmetric squared error: a point where the
envelope lies *below* its return costs ``K`` times more than the same gap above it. With ``K = 1000`` (the
authors' value) the fitted ``V`` lies above almost every return: an upper envelope.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictModule, dispatch
from tensordict.utils import NestedKey

from torchrl_bail.objectives._shared import LazyInKeysLoss, check_reduction, reduce_per_seed, value_and_return

__all__ = ["UpperEnvelopeLoss", "envelope_penalty"]


def envelope_penalty(value: torch.Tensor, target: torch.Tensor, penalty: torch.Tensor | float) -> torch.Tensor:
    """The elementwise upper-envelope penalty ``w * (V - G)^2``, ``w = 1 if V >= G else K``.

    The weight-1 branch includes ``V == G`` as in the authors' code (supp. Alg. 1); the paper writes ``V > G``,
    which makes no difference to the value (the gap is zero there) nor to the gradient.

    Args:
        value (torch.Tensor): the envelope ``V``.
        target (torch.Tensor): the returns ``G``, broadcastable with ``value``.
        penalty (torch.Tensor or float): ``K``, the weight of points where ``V < G``.

    Examples:
        >>> envelope_penalty(torch.tensor([3.0, 1.0, 2.0]), torch.tensor([2.0, 2.0, 2.0]), 1000.0)
        tensor([   1., 1000.,    0.])
    """
    return _penalised_gap(value - target, penalty)[0]


def _penalised_gap(gap: torch.Tensor, penalty: torch.Tensor | float) -> tuple[torch.Tensor, torch.Tensor]:
    """``(w * gap^2, gap < 0)`` for ``gap = V - G``: the one place where the penalty formula lives."""
    below = gap < 0
    squared = gap.square()
    return torch.where(below, squared * penalty, squared), below


class UpperEnvelopeLoss(LazyInKeysLoss):
    """BAIL's upper-envelope loss: an asymmetric squared error that pushes ``V(s)`` above the returns ``G``.

    Presented in "BAIL: Best-Action Imitation Learning for Batch Deep Reinforcement Learning",
    Chen et al., NeurIPS 2020, https://arxiv.org/abs/1910.12179.

    Per element the loss is ``(V - G)^2`` when ``V >= G`` and ``K * (V - G)^2`` when ``V < G`` (the
    authors' code puts ``V == G`` in the weight-1 branch). The regulariser ``lambda * ||phi||^2`` of the
    paper is *not* part of this loss: the authors implement it as coupled L2 in the optimizer,
    ``torch.optim.Adam(..., weight_decay=0.02)`` (see :func:`~torchrl_bail.training.envelope.fit_upper_envelope`).

    Args:
        value_network (TensorDictModule): the envelope ``V_phi``; it reads its ``in_keys`` (typically
            ``"observation"``) and writes ``tensor_keys.value`` (``"state_value"``, shape ``[*B, 1]``).
            Its parameters are the loss' parameters (they are shared, not copied).

    Keyword Args:
        penalty (float): ``K``, the weight of the points below the envelope. Registered as a buffer
            (it follows ``.to()`` and the ``state_dict``). Defaults to ``1000.0``.
        reduction (str, optional): ``"none"`` | ``"mean"`` | ``"sum"``. Defaults to ``"mean"``.

            * ``"none"``: ``loss_envelope`` has the batch shape of the input (``[B]`` or ``[S, B]``): one
              loss per point. Use it for per-seed losses: ``out["loss_envelope"].mean(-1)`` has shape ``[S]``.
            * ``"mean"``: the mean over the last batch dimension (the points of one seed), then the mean over
              the leading ones (the seeds): a scalar. Without masks this equals the mean over all elements.
            * ``"sum"``: the sum over every element.

            To train ``S`` independent envelopes exactly as ``S`` separate runs with coupled weight decay,
            back-propagate ``loss_envelope.mean(-1).sum()`` from ``reduction="none"``: the ``"mean"`` over
            seeds would scale each seed's gradient by ``1 / S`` relative to its weight decay.

    The output holds ``loss_envelope`` (the only back-propagated entry) and two detached diagnostics,
    reduced over the last batch dimension (scalars for ``[B]`` batches, ``[S]`` for ``[S, B]``):
    ``fraction_below`` (share of points with ``V < G``) and ``value_mean`` (mean of ``V``).

    Masks follow :attr:`~torchrl.objectives.LossModule.loss_mask_key` as in every TorchRL loss: masked points
    are excluded from ``loss_envelope`` (zero under ``"none"``), not from the diagnostics.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_bail.modules import make_value_network
        >>> from torchrl_bail.objectives.upper_envelope import UpperEnvelopeLoss
        >>> _ = torch.manual_seed(0)
        >>> value = make_value_network(11)
        >>> loss = UpperEnvelopeLoss(value, penalty=1000.0)
        >>> data = TensorDict({"observation": torch.randn(32, 11), "return": torch.rand(32)}, [32])
        >>> out = loss(data)
        >>> sorted(out.keys())
        ['fraction_below', 'loss_envelope', 'value_mean']
        >>> out["loss_envelope"].shape
        torch.Size([])
        >>> out["loss_envelope"].backward()

    This class is compatible with non-tensordict based calls too: the keyword arguments are the value
    network's ``in_keys`` plus the return key (``return``). ``select_out_keys`` picks what comes back.

    Examples:
        >>> import torch
        >>> from torchrl_bail.modules import make_value_network
        >>> from torchrl_bail.objectives.upper_envelope import UpperEnvelopeLoss
        >>> loss = UpperEnvelopeLoss(make_value_network(11))
        >>> _ = loss.select_out_keys("loss_envelope", "fraction_below")
        >>> loss_envelope, fraction_below = loss(observation=torch.randn(8, 11), **{"return": torch.rand(8)})
        >>> loss_envelope.shape, fraction_below.shape
        (torch.Size([]), torch.Size([]))
        >>> loss_envelope.backward()
    """

    @dataclass
    class _AcceptedKeys:
        """Maintains default values for all configurable tensordict keys.

        Attributes:
            value (NestedKey): where the value network writes ``V(s)``. Defaults to ``"state_value"``.
            value_target (NestedKey): the Monte-Carlo return ``G`` (shape ``[*B]`` or ``[*B, 1]``).
                Defaults to ``"return"``.
        """

        value: NestedKey = "state_value"
        value_target: NestedKey = "return"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    #: coefficients a float may be assigned to (``loss.penalty = 10.0``: an in-place update of the buffer)
    _schedulable_buffers = frozenset({"penalty"})
    default_value_estimator = None
    out_keys = ["loss_envelope", "fraction_below", "value_mean"]

    value_network: TensorDictModule
    value_network_params: TensorDictParams
    target_value_network_params: TensorDictParams

    def __init__(
        self,
        value_network: TensorDictModule,
        *,
        penalty: float = 1000.0,
        reduction: Literal["mean", "sum", "none"] | None = None,
    ) -> None:
        reduction = check_reduction(reduction)
        if not float(penalty) > 0:
            raise ValueError(f"penalty (K) must be > 0, got {penalty}")
        super().__init__()
        self.convert_to_functional(value_network, "value_network")
        self.register_coeff_buffer("penalty", penalty)
        self.reduction = reduction

    def _in_key_list(self) -> list[NestedKey]:
        return [self.tensor_keys.value_target, *self.value_network.in_keys]

    def envelope_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The reduced penalty loss and its diagnostics.

        Args:
            tensordict (TensorDictBase): input with the value network's ``in_keys`` and
                ``tensor_keys.value_target``, batch shape ``[B]`` or ``[S, B]``.

        Returns:
            ``(loss_envelope, metadata)`` where ``metadata`` holds the detached ``fraction_below`` and
            ``value_mean``, reduced over the last batch dimension.
        """
        value, target = value_and_return(self, tensordict)
        loss, below = _penalised_gap(value - target, self.penalty)
        loss = reduce_per_seed(self, loss, tensordict)
        metadata = {
            "fraction_below": below.to(value.dtype).mean(-1),
            "value_mean": value.detach().mean(-1),
        }
        self._clear_weakrefs(tensordict, "value_network_params")
        return loss, metadata

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Computes the upper-envelope loss.

        Args:
            tensordict (TensorDictBase): input with the value network's ``in_keys`` (``"observation"``) and
                the return ``tensor_keys.value_target`` (``"return"``).

        Returns:
            A :class:`~tensordict.TensorDict` with ``loss_envelope``, ``fraction_below`` and ``value_mean``.
        """
        loss, metadata = self.envelope_loss(tensordict)
        return TensorDict({"loss_envelope": loss, **metadata})

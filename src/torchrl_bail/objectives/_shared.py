"""What every loss of this package does the same way: reductions over ``[S, B]`` batches, lazily derived
``in_keys`` and reading a state value beside its Monte-Carlo return.

Not public API: only the losses of this package import it; users import the losses. (The fused target-network
updater the offline algorithms and the behaviour agents share is :class:`torchrl_bail.modules.FusedSoftUpdate`.)
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.objectives import LossModule

__all__ = ["check_reduction", "reduce_per_seed", "LazyInKeysLoss", "required_entry", "value_and_return"]


def check_reduction(reduction: str | None) -> str:
    """``reduction`` (``None`` means ``"mean"``) validated against ``"mean" | "sum" | "none"``."""
    reduction = "mean" if reduction is None else reduction
    if reduction not in ("mean", "sum", "none"):
        raise ValueError(f"reduction must be 'mean', 'sum' or 'none', got {reduction!r}")
    return reduction


def reduce_per_seed(loss_module: LossModule, loss: torch.Tensor, tensordict: TensorDictBase) -> torch.Tensor:
    """``loss_module._reduce_loss`` for ``[B]`` batches; for ``[S, B]`` under ``"mean"``: mean over ``B``, then ``S``.

    Masks (``loss_module.loss_mask_key``) exclude points from each seed's mean; a seed whose points are all masked
    contributes 0.
    """
    if loss_module.reduction != "mean" or loss.ndim <= 1:
        return loss_module._reduce_loss(loss, tensordict=tensordict)
    masked = loss_module._reduce_loss(loss, tensordict=tensordict, reduction="none")
    if masked is loss:  # no mask in the input
        return loss.mean(-1).mean()
    count = loss_module._reduce_loss(torch.ones_like(loss), tensordict=tensordict, reduction="none")
    return (masked.sum(-1) / count.sum(-1).clamp_min(1)).mean()


class LazyInKeysLoss(LossModule):
    """A :class:`~torchrl.objectives.LossModule` whose ``in_keys`` are derived on first use, and again after
    :meth:`set_keys`, from the subclass' ``_in_key_list()`` (its ``tensor_keys`` and its networks' own in-keys)."""

    _in_keys: list[NestedKey] | None = None

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        """No value estimator: the returns are precomputed Monte-Carlo returns."""

    @property
    def in_keys(self) -> list[NestedKey]:
        if self._in_keys is None:
            self._in_keys = list(dict.fromkeys(self._in_key_list()))
        return self._in_keys

    @in_keys.setter
    def in_keys(self, values) -> None:
        self._in_keys = values

    def set_keys(self, **kwargs) -> None:
        super().set_keys(**kwargs)
        self._in_keys = None


def required_entry(loss_module: LossModule, tensordict: TensorDictBase, key: NestedKey) -> torch.Tensor:
    """``tensordict[key]``, or a :class:`KeyError` naming the loss, the key and ``set_keys`` when it is missing."""
    entry = tensordict.get(key, None)
    if entry is None:
        raise KeyError(
            f"{type(loss_module).__name__}: the batch has no {key!r} entry; store it there or point set_keys(...) at "
            f"the key that holds it. Keys present: {sorted(map(str, tensordict.keys(True, True)))}"
        )
    return entry


def value_and_return(loss_module: LossModule, tensordict: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
    """``(V(s), G)`` with the batch shape ``[*B]``: ``loss_module.value_network`` (functional parameters) evaluated
    on ``tensordict`` and the return ``tensor_keys.value_target`` cast to V's dtype. A trailing dimension of 1 is
    dropped from either; any other shape is a clear error naming both keys."""
    keys = loss_module.tensor_keys
    network = loss_module.value_network
    with loss_module.value_network_params.to_module(network, preserve_module_state=False):
        value = network(tensordict.select(*network.in_keys)).get(keys.value)
    target = required_entry(loss_module, tensordict, keys.value_target)
    batch_shape = tensordict.batch_size
    if value.ndim == len(batch_shape) + 1 and value.shape[-1] == 1:
        value = value.squeeze(-1)
    if target.ndim == len(batch_shape) + 1 and target.shape[-1] == 1:
        target = target.squeeze(-1)
    if value.shape != batch_shape or target.shape != batch_shape:
        raise ValueError(
            f"{type(loss_module).__name__}: the value {keys.value!r} has shape {tuple(value.shape)} and the return "
            f"{keys.value_target!r} has shape {tuple(target.shape)}; expected both to be the batch shape "
            f"{tuple(batch_shape)} (optionally with a trailing 1)"
        )
    return value, target.to(value.dtype)

"""BAIL (static, spec 3-5): upper envelope -> best-action selection -> behaviour cloning.

:meth:`BAIL.prepare` fits the upper envelope ``V`` to the returns ``G`` with
:func:`~torchrl_bail.envelope.fit_upper_envelope`, then a
:class:`~torchrl_bail.transforms.BestActionFilter` keeps the pairs whose ``G / V`` ratio is in the top
``percentile``; the imitation that follows is :class:`~torchrl_bail.algorithms.bc.BehaviourCloning` on that
selected set (uniform mini-batches with replacement, as the paper does).

Ablations (supp D.1-D.3) are config switches: ``returns.augment=oracle`` (oracle returns),
``algo.selection.by=return`` (top-p by return, no envelope), ``algo.envelope.penalty=1`` (ordinary
regression instead of the envelope).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Literal

import torch
from tensordict import TensorDictBase
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer, TensorSpec

from torchrl_bail.algorithms.base import PrepareContext
from torchrl_bail.algorithms.bc import BehaviourCloning
from torchrl_bail.envelope import envelope_values, fit_upper_envelope, fraction_below, plot_envelope
from torchrl_bail.modules import make_value_network
from torchrl_bail.transforms.best_action import BestActionFilter

__all__ = ["BAIL"]


class BAIL(BehaviourCloning):
    """Static BAIL.

    Keyword Args:
        obs_dim, action_spec, hidden, lr, batch_size, epochs, device: as in
            :class:`~torchrl_bail.algorithms.bc.BehaviourCloning` (BAIL imitates for 50 epochs).
        envelope (dict): keyword arguments of :func:`~torchrl_bail.envelope.fit_upper_envelope` plus
            ``hidden`` and ``head_scale`` of the envelope network.
        percentile (float): share of the batch kept. Defaults to ``0.30``.
        selection_by (str): ``"envelope"`` (ratio ``G / V``) or ``"return"`` (top-p by ``G``; no envelope).
        nonpositive_value (str): how ``V <= 0`` enters the ratio, see
            :class:`~torchrl_bail.transforms.BestActionFilter`. Defaults to ``"raw"``.
    """

    name = "bail"
    #: what prepare measured (envelope fit, selection) for summary.json; the envelope weights are a module
    state_attributes = ("_summary",)

    def __init__(
        self,
        *,
        obs_dim: int,
        action_spec: TensorSpec,
        hidden: Sequence[int] = (400, 300),
        lr: float = 1e-3,
        batch_size: int = 1000,
        epochs: float = 50,
        envelope: dict | None = None,
        percentile: float = 0.30,
        selection_by: Literal["envelope", "return"] = "envelope",
        nonpositive_value: Literal["raw", "project", "error"] = "raw",
        device="cpu",
    ) -> None:
        super().__init__(obs_dim=obs_dim, action_spec=action_spec, hidden=hidden, lr=lr,
                         batch_size=batch_size, epochs=epochs, device=device)
        if selection_by not in ("envelope", "return"):
            raise ValueError(f"algo.selection.by must be 'envelope' or 'return', got {selection_by!r}")
        envelope = dict(envelope or {})
        self.envelope_kwargs = envelope
        self.value_network = make_value_network(
            obs_dim, envelope.pop("hidden", (128, 128)), head_scale=envelope.pop("head_scale", 0.1)
        ).to(self.device)
        self.modules["envelope"] = self.value_network
        self.selection_by = selection_by
        self.filter = BestActionFilter(percentile=percentile, nonpositive_value=nonpositive_value)
        self._summary: dict[str, Any] = {}

    def prepare(self, data: TensorDictBase, ctx: PrepareContext) -> TensorDictBase:
        observations, returns = data["observation"], data["return"]
        if self.selection_by == "envelope":
            fit = fit_upper_envelope(
                self.value_network, observations.to(self.device), returns.to(self.device),
                generator=ctx.generator, device=self.device, progress=ctx.progress, **self.envelope_kwargs,
            )
            for epoch, (tr, va) in enumerate(zip(fit.train_loss, fit.val_loss), start=1):
                ctx.log("envelope/train_loss", tr, step=epoch)
                ctx.log("envelope/val_loss", va, step=epoch)
            values = envelope_values(self.value_network, observations.to(self.device)).cpu()
            below = fraction_below(values, returns)
            self._summary.update(envelope_fraction_below=below, envelope_best_epoch=fit.best_epoch,
                                 envelope_median_gap=float((values - returns).median()))
            ctx.log("envelope/fraction_below", below)
            if ctx.run_dir is not None:
                plot_envelope(values, returns, ctx.run_dir / "envelope.png",
                              title=f"Upper envelope ({len(values)} states)")
        else:  # ablation D.2: rank by return alone
            values = torch.ones_like(returns)
            self._summary.update(envelope_fraction_below=None)
        return self._select(data, values, ctx)

    def restore_prepared(self, data: TensorDictBase, ctx: PrepareContext) -> TensorDictBase:
        """On resume: the checkpoint restored the fitted envelope, so only the (deterministic) selection reruns."""
        returns = data["return"]
        if self.selection_by == "envelope":
            values = envelope_values(self.value_network, data["observation"].to(self.device)).cpu()
        else:
            values = torch.ones_like(returns)
        return self._select(data, values, ctx)

    def _select(self, data: TensorDictBase, values: torch.Tensor, ctx: PrepareContext) -> TensorDictBase:
        """The best actions of ``data`` under the state values ``values`` (the filter's top ``percentile``)."""
        returns = data["return"]
        keyed = data.select("observation", "action", "return").clone(False)
        keyed.set("state_value", values.to(returns.dtype))
        selected_buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(len(data)), transform=self.filter)
        selected_buffer.extend(keyed)
        selected = selected_buffer.storage[: len(selected_buffer)]
        self._summary.update(selected_fraction=len(selected) / len(data), num_selected=len(selected),
                             selection_border=float(self.filter.border))
        ctx.log("selection/fraction", len(selected) / len(data))
        return selected

    def summary(self) -> dict[str, Any]:
        return dict(self._summary)

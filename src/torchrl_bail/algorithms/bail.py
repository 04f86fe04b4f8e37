"""BAIL (static, supp. Alg. 1, B.2): upper envelope -> best-action selection -> behaviour cloning.

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

from typing import Any

import torch
from omegaconf import OmegaConf
from tensordict import TensorDictBase
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer, TensorSpec

from torchrl_bail.algorithms.base import PrepareContext
from torchrl_bail.algorithms.bc import BehaviourCloning
from torchrl_bail.envelope import envelope_values, fit_upper_envelope, fraction_below, plot_envelope
from torchrl_bail.modules import make_value_network
from torchrl_bail.transforms.best_action import BestActionFilter

__all__ = ["BAIL"]


class BAIL(BehaviourCloning):
    """Static BAIL, from ``conf/algo/bail.yaml``'s config (arguments as in
    :class:`~torchrl_bail.algorithms.base.Algorithm`).

    The config's ``envelope`` block is the envelope network (``hidden``, ``head_scale``) and the keyword arguments
    of :func:`~torchrl_bail.envelope.fit_upper_envelope`; ``selection`` sets the
    :class:`~torchrl_bail.transforms.BestActionFilter` (``percentile``, ``nonpositive_value``) and what ranks
    (``by``: ``"envelope"``, the ratio ``G / V``, or ``"return"``, top-p by ``G`` with no envelope); ``policy``
    is the imitating actor.
    """

    name = "bail"
    #: what prepare measured (envelope fit, selection) for summary.json; the envelope weights are a module
    state_attributes = ("_summary",)

    def __init__(self, obs_dim: int, action_spec: TensorSpec, config, device="cpu") -> None:
        super().__init__(obs_dim, action_spec, config, device)
        envelope = OmegaConf.to_container(self.config.envelope)
        self.value_network = make_value_network(
            obs_dim, tuple(envelope.pop("hidden")), head_scale=envelope.pop("head_scale")
        ).to(self.device)
        #: the keyword arguments of fit_upper_envelope
        self.envelope_kwargs = envelope
        self.modules["envelope"] = self.value_network
        selection = self.config.selection
        self.selection_by = selection.by
        self.filter = BestActionFilter(percentile=selection.percentile, nonpositive_value=selection.nonpositive_value)
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

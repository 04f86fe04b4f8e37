"""BAIL (static, supp. Alg. 1, B.2): upper envelope -> best-action selection -> behaviour cloning.

:meth:`BAIL.prepare` fits the upper envelope ``V`` to the returns ``G`` with
:func:`~torchrl_bail.training.envelope.fit_upper_envelope`, then a
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
from omegaconf import MISSING, OmegaConf
from tensordict import TensorDictBase
from torchrl.data import LazyTensorStorage, TensorSpec

from torchrl_bail.algorithms.base import PrepareContext
from torchrl_bail.algorithms.bc import BehaviourCloning
from torchrl_bail.configuration.algo_schemas import (
    AlgoConfig,
    EnvelopeConfig,
    NetConfig,
    SelectionConfig,
    algo_schema,
    schema_block,
)
from torchrl_bail.configuration.config import at_least, one_of
from torchrl_bail.data.local_buffer import local_replay_buffer
from torchrl_bail.modules import make_value_network
from torchrl_bail.reports.plots import plot_envelope
from torchrl_bail.training.envelope import envelope_values, fit_upper_envelope, fraction_below
from torchrl_bail.transforms.best_action import BestActionFilter

__all__ = ["BAIL"]


# -- the schema (conf/algo/bail.yaml), read by torchrl_bail.configuration.algo_schemas without importing this module --


@schema_block
class BAILEnvelopeConfig(EnvelopeConfig):
    batch_size: int = at_least(1)
    epochs: int = at_least(1)
    early_stopping: str = one_of("paper", "as_coded")


@schema_block
class BAILSelectionConfig(SelectionConfig):
    by: str = one_of("envelope", "return")
    nonpositive_value: str = one_of("raw", "project", "error")


@algo_schema("bail")
class BAILConfig(AlgoConfig):
    column = 1
    study = "all"
    paper_study = True
    tiny = ("envelope.epochs=3", "envelope.batch_size=200")
    description = "BAIL (supp. Alg. 1): upper envelope → best {selection.percentile:.0%} by G/V → BC on them"
    losses = ("torchrl_bail.objectives.UpperEnvelopeLoss", "torchrl_bail.transforms.BestActionFilter",
              "torchrl.objectives.BCLoss")

    envelope: BAILEnvelopeConfig = MISSING
    selection: BAILSelectionConfig = MISSING
    policy: NetConfig = MISSING


class BAIL(BehaviourCloning):
    """Static BAIL, from ``conf/algo/bail.yaml``'s config (arguments as in
    :class:`~torchrl_bail.algorithms.base.Algorithm`).

    The config's ``envelope`` block is the envelope network (``hidden``, ``head_scale``) and the keyword arguments
    of :func:`~torchrl_bail.training.envelope.fit_upper_envelope`; ``selection`` sets the
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
        #: the filter of the last selection (each selection takes a new one: a filter selects once)
        self.filter = self._new_filter()
        self._summary: dict[str, Any] = {}

    def _new_filter(self) -> BestActionFilter:
        selection = self.config.selection
        return BestActionFilter(percentile=selection.percentile, nonpositive_value=selection.nonpositive_value)

    def prepare(self, data: TensorDictBase, ctx: PrepareContext) -> TensorDictBase:
        """Fits the envelope and selects the best actions: :meth:`prepare_seeds` of this one seed."""
        (selected,) = self.prepare_seeds([self], data, [ctx])
        return selected

    @staticmethod
    def prepare_seeds(algorithms: list[BAIL], data: TensorDictBase,
                      contexts: list[PrepareContext]) -> list[TensorDictBase]:
        """The prepared data of ``S >= 1`` seeds' BAIL (:func:`torchrl_bail.core.stacking.prepare_seeds`): their
        envelopes
        are fitted by one :func:`~torchrl_bail.training.envelope.fit_upper_envelope` of the ``S`` networks (stacked when
        ``S > 1``), each seed with its own split, shuffles, early stopping and best weights; then each seed selects
        its best actions under its envelope. Ranking by return (``selection.by="return"``) fits nothing."""
        first = algorithms[0]
        fits = [None] * len(algorithms)
        if first.selection_by == "envelope":
            fits = fit_upper_envelope(
                [algorithm.value_network for algorithm in algorithms], data["observation"].to(first.device),
                data["return"].to(first.device), generators=[ctx.generator for ctx in contexts], device=first.device,
                progress=contexts[0].progress, **first.envelope_kwargs,
            )
        return [algorithm._select_after_fit(data, fit, ctx)
                for algorithm, fit, ctx in zip(algorithms, fits, contexts, strict=True)]

    def _select_after_fit(self, data: TensorDictBase, fit, ctx: PrepareContext) -> TensorDictBase:
        """What :meth:`prepare` does after the envelope fit (``fit`` is ``None`` when ranking by return): log the
        fit, measure the envelope, plot it, select the best actions."""
        observations, returns = data["observation"], data["return"]
        if fit is not None:
            for epoch, (tr, va) in enumerate(zip(fit.train_loss, fit.val_loss, strict=True), start=1):
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
        self.filter = self._new_filter()
        selected_buffer = local_replay_buffer(LazyTensorStorage, len(data), transform=self.filter)
        selected_buffer.extend(keyed)
        selected = selected_buffer.storage[: len(selected_buffer)]
        self._summary.update(selected_fraction=len(selected) / len(data), num_selected=len(selected),
                             selection_border=float(self.filter.border))
        ctx.log("selection/fraction", len(selected) / len(data))
        return selected

    def summary(self) -> dict[str, Any]:
        return dict(self._summary)

"""Progressive BAIL (supp. Alg. 2): envelope, in-batch selection and imitation advance together, every iteration.

Each update samples a mini-batch from the whole batch, takes one envelope step on its non-validation rows,
selects the top ``percentile`` of the mini-batch by ``G / V`` under the *selection* envelope, and takes one
imitation step whose MSE is normalised by the full mini-batch (selected rows weigh 1, the others 0), as the
authors' code does. Every ``validate_every`` iterations the envelope's validation loss decides what the
selection envelope is.

Switches where the authors' code and the paper differ (where the paper and the authors' code differ):

* ``best_envelope="paper"`` (the yaml's default): ``phi'`` is a real copy of the lowest-validation weights, and the
  training envelope reverts to it after ``patience`` non-improving validations (the count then restarts: the rule
  of :class:`~torchrl_bail.training.envelope.EarlyStoppingTracker`, the same tracker static BAIL uses).
  ``"as_coded"``: the released code's aliasing: ``phi'`` is the live weights, no revert.
* ``selection_envelope="best"`` (the yaml's default): the separate selection network selects; it receives ``phi'``
  whenever ``phi'`` changes (``best_envelope="paper"``: a real copy at every improvement), or, with
  ``best_envelope="as_coded"``, the *current* weights at every non-improving validation, as the released code
  does (so it keeps its random init until the first validation increase).
  ``"training"``: Algorithm 2 of the supplementary material read literally: "select data point i if
  ``G_i > x V_phi(s_i)``" with the *training* envelope ``V_phi``; ``phi'`` only serves the reverts.
* ``v_projection=True`` (the yaml's default, as coded; not in the paper): ``V < 1`` is mapped to ``exp(V - 1)``
  before the ratio, which keeps early, near-zero envelopes from flipping the ranking.
* ``validation="split"`` (the yaml's default, the paper's 0.8/0.2 split) or ``"with_replacement"`` (the code's
  ``randint``: about 18 % unique validation points).

One epoch counts ``(1 - val_fraction) * batch_size`` samples per update, as the authors' logs do, so 100
epochs are 125k updates and an evaluation every 0.5 epoch is every 625 updates.
"""

from __future__ import annotations

from typing import Any

import torch
from omegaconf import MISSING
from tensordict import TensorDictBase
from torchrl.data import TensorSpec

from torchrl_bail.algorithms.base import PrepareContext
from torchrl_bail.algorithms.bc import DeterministicActorAlgorithm, make_bc_loss
from torchrl_bail.configuration.algo_schemas import (
    AlgoConfig,
    EnvelopeConfig,
    NetConfig,
    SelectionConfig,
    algo_schema,
    schema_block,
)
from torchrl_bail.configuration.config import at_least, one_of
from torchrl_bail.core.stacking import SeedSlice
from torchrl_bail.modules import make_value_network
from torchrl_bail.objectives.upper_envelope import UpperEnvelopeLoss
from torchrl_bail.training.envelope import EarlyStoppingTracker, validation_loss
from torchrl_bail.transforms.best_action import best_action_mask

__all__ = ["ProgressiveBAIL"]


# -- the schema (conf/algo/pbail.yaml), read by torchrl_bail.configuration.algo_schemas without importing this module --


@schema_block
class PBAILEnvelopeConfig(EnvelopeConfig):
    validate_every: int = at_least(1)


@algo_schema("pbail")
class PBAILConfig(AlgoConfig):
    column = 2
    study = "all"
    paper_study = True
    tiny = ("envelope.validate_every=2",)
    description = ("Progressive BAIL (supp. Alg. 2): envelope step + in-batch top {selection.percentile:.0%} + policy "
                   "step each iteration")
    losses = ("torchrl_bail.objectives.UpperEnvelopeLoss", "torchrl_bail.transforms.best_action_mask",
              "torchrl.objectives.BCLoss")

    envelope: PBAILEnvelopeConfig = MISSING
    selection: SelectionConfig = MISSING
    best_envelope: str = one_of("paper", "as_coded")
    selection_envelope: str = one_of("best", "training")
    v_projection: bool = MISSING
    validation: str = one_of("split", "with_replacement")
    policy: NetConfig = MISSING


VALIDATION_KEY = "envelope_validation"


class ProgressiveBAIL(DeterministicActorAlgorithm):
    """Progressive BAIL (Alg. 2 of the supplementary material), from ``conf/algo/pbail.yaml``'s config (arguments
    as in :class:`~torchrl_bail.algorithms.base.Algorithm`).

    The config's ``envelope`` block is the envelope network, its :class:`~torchrl_bail.objectives.UpperEnvelopeLoss`
    and Adam, its validation split and early stopping (``validate_every``, ``patience``); ``selection.percentile``
    is the share of each mini-batch imitated; ``best_envelope``, ``selection_envelope``, ``v_projection`` and
    ``validation`` are the switches of the module docstring; ``policy`` is the imitating actor.
    """

    name = "pbail"
    #: the update clock (validations happen every ``validate_every`` updates); the early-stopping state (best
    #: snapshot and loss, consecutive increases, reverts) travels as :meth:`state_dict`'s ``"early_stopping"``
    state_attributes = ("_iteration",)

    def __init__(self, obs_dim: int, action_spec: TensorSpec, config, device="cpu") -> None:
        super().__init__(obs_dim, action_spec, config, device)
        cfg = self.config
        env = cfg.envelope
        self.val_fraction = float(env.val_fraction)
        self.validate_every = int(env.validate_every)
        self.patience = int(env.patience)
        self.percentile = float(cfg.selection.percentile)
        self.best_envelope = cfg.best_envelope
        self.selection_envelope = cfg.selection_envelope
        self.v_projection = bool(cfg.v_projection)
        self.validation = cfg.validation
        self.samples_per_update = (1.0 - self.val_fraction) * self.batch_size

        hidden = tuple(env.hidden)
        self.value_network = make_value_network(obs_dim, hidden, head_scale=env.head_scale).to(self.device)
        # an independently initialised selection envelope, as in the authors' code
        self.selection_network = make_value_network(obs_dim, hidden, head_scale=env.head_scale).to(self.device)
        self.per_element_bc_loss = make_bc_loss(self.actor, reduction="none")
        self.envelope_loss = UpperEnvelopeLoss(self.value_network, penalty=env.penalty, reduction="none")
        self.modules.update(envelope=self.value_network, selection_envelope=self.selection_network)
        self.optimizers["envelope"] = torch.optim.Adam(self.envelope_loss.parameters(), lr=env.lr,
                                                       weight_decay=env.weight_decay)
        as_coded = self.best_envelope == "as_coded"
        self.early_stopping = EarlyStoppingTracker(self.value_network, patience=self.patience, revert=not as_coded,
                                                   copy_best=not as_coded)
        self._iteration = 0
        self._validation_data: TensorDictBase | None = None
        #: ``(early-stopping tracker, selection network)`` per seed: one pair here, one per seed when stacked
        self._seed_tracking = [(self.early_stopping, self.selection_network)]

    def prepare(self, data: TensorDictBase, ctx: PrepareContext) -> TensorDictBase:
        n = len(data)
        n_val = int(self.val_fraction * n)
        if self.validation == "split":
            val_index = torch.randperm(n, generator=ctx.generator)[:n_val]
        else:
            val_index = torch.randint(n, (n_val,), generator=ctx.generator)
        is_val = torch.zeros(n, dtype=torch.bool)
        is_val[val_index] = True
        self._validation_data = data.select("observation", "return")[val_index].to(self.device)
        keyed = data.select("observation", "action", "return").clone(False)
        keyed.set(VALIDATION_KEY, is_val)
        return keyed

    def _track_validation(self) -> None:
        """One validation of the training envelope; the tracker may revert it, then the selection network follows
        ``phi'`` (see the module docstring)."""
        val = self._validation_data
        if val is None or val.batch_size[-1] == 0:  # no validation set: no early stopping
            return
        losses = validation_loss(self.envelope_loss, val)
        for (tracker, selection), loss in zip(self._seed_tracking, losses, strict=True):
            event = tracker.observe(loss)
            if self.best_envelope == "paper" and event == "improved":
                tracker.best.load_into(selection)
            elif self.best_envelope == "as_coded" and event == "worse":
                tracker.best.load_into(selection)  # the aliased record: the current weights

    #: the validation clock and the early-stopping decisions stay in Python; the three steps are compiled
    compiled_method = "_steps"

    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        if self._iteration % self.validate_every == 0:
            self._track_validation()  # reads the validation loss back to the host: once every validate_every
        self._iteration += 1
        return self._steps(batch)

    def _steps(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        """The envelope step, the selection and the imitation step of one update (tensor work only)."""
        # 1. envelope step on the non-validation rows (per seed on [S, B] mini-batches, then their mean)
        train_rows = (~batch[VALIDATION_KEY]).to(torch.float32).reshape(batch.batch_size)
        per_row = self.envelope_loss(batch)["loss_envelope"].reshape(batch.batch_size)
        loss_envelope = (per_row * train_rows).sum(-1) / train_rows.sum(-1).clamp_min(1.0)
        opt = self.optimizers["envelope"]
        opt.zero_grad(set_to_none=True)
        loss_envelope.mean().backward()
        opt.step()
        # 2. selection inside the mini-batch (inside each seed's row) under the selection envelope
        with torch.no_grad():
            selector = self.value_network if self.selection_envelope == "training" else self.selection_network
            values = selector(batch.select("observation"))["state_value"].reshape(batch.batch_size)
            selected = best_action_mask(batch["return"].reshape(batch.batch_size), values, self.percentile,
                                        nonpositive_value="project" if self.v_projection else "raw")
        # 3. imitation step, normalised by the whole mini-batch
        weight = selected.to(torch.float32).unsqueeze(-1)
        loss_bc = (self.per_element_bc_loss(batch)["loss_bc"] * weight).mean()
        opt = self.optimizers["actor"]
        opt.zero_grad(set_to_none=True)
        loss_bc.backward()
        opt.step()
        return {"loss_envelope": loss_envelope.detach(), "loss_bc": loss_bc.detach(),
                "selected_fraction": selected.float().mean(-1)}

    # -- several seeds in one process (torchrl_bail.core.stacking.SeedStack)
    # --------------------------------------------
    def stack_attributes(self, algorithms: list[ProgressiveBAIL]) -> None:
        """On the stack's host: the seeds' validation sets ``[S, n_val]``, update clock and early-stopping states;
        each seed's tracker and selection network act on its slice of the stacked envelopes."""
        self._iteration = algorithms[0]._iteration
        if algorithms[0]._validation_data is not None:
            self._validation_data = torch.stack([a._validation_data for a in algorithms])
        as_coded = self.best_envelope == "as_coded"
        self._seed_tracking = []
        for s, algorithm in enumerate(algorithms):
            tracker = EarlyStoppingTracker(SeedSlice(self.value_network, s), patience=self.patience,
                                           revert=not as_coded, copy_best=not as_coded)
            tracker.load_state_dict(algorithm.early_stopping.state_dict())
            self._seed_tracking.append((tracker, SeedSlice(self.selection_network, s)))

    def unstack_attributes(self, algorithms: list[ProgressiveBAIL]) -> None:
        """Each seed's update clock and early-stopping state back into its own algorithm."""
        for algorithm, (tracker, _) in zip(algorithms, self._seed_tracking, strict=True):
            algorithm._iteration = self._iteration
            algorithm.early_stopping.load_state_dict(tracker.state_dict())

    def summary(self) -> dict[str, Any]:
        return {"envelope_best_val_loss": self.early_stopping.best_loss,
                "envelope_reverts": len(self.early_stopping.reverts), "percentile": self.percentile}

    # -- checkpoints: the early-stopping state and the iteration count travel with the weights ------------------
    def state_dict(self) -> dict[str, Any]:
        return {**super().state_dict(), "early_stopping": self.early_stopping.state_dict(),
                "iteration": self._iteration}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        self.early_stopping.load_state_dict(state["early_stopping"])
        self._iteration = int(state["iteration"])

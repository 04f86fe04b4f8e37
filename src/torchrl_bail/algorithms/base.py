"""What the one training loop needs from an algorithm.

An algorithm owns its networks, losses and optimizers and contributes three things to
:func:`torchrl_bail.trainer.train`: a :meth:`~Algorithm.prepare` stage that turns the batch (with its returns)
into the data the loop samples from (BAIL fits its envelope and keeps the best actions there), an
:meth:`~Algorithm.update` step on one mini-batch, and a deterministic :attr:`~Algorithm.policy` to evaluate.
Its schedule (mini-batch size and length in epochs of 10^6 samples) comes from its config.
"""

from __future__ import annotations

import copy
from abc import ABC, abstractmethod
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn

__all__ = ["Algorithm", "PrepareContext"]


class PrepareContext:
    """Where :meth:`Algorithm.prepare` may write artifacts (plots) and log scalars.

    Attributes:
        run_dir: the run directory (``None`` when nothing should be written).
        logger: a TorchRL logger or ``None``.
        generator: a seeded :class:`torch.Generator` for data splits.
        progress: whether to show progress bars.
    """

    def __init__(self, run_dir: Path | None = None, logger=None, generator: torch.Generator | None = None,
                 progress: bool = False) -> None:
        self.run_dir = None if run_dir is None else Path(run_dir)
        self.logger = logger
        self.generator = generator if generator is not None else torch.Generator().manual_seed(0)
        self.progress = progress

    def log(self, name: str, value: float, step: int = 0) -> None:
        if self.logger is not None:
            self.logger.log_scalar(name, float(value), step=step)


class Algorithm(ABC):
    """Base class: networks in :attr:`modules`, optimizers in :attr:`optimizers`, a schedule, a policy.

    Subclasses set ``name``, build their networks/losses/optimizers in ``__init__`` and implement
    :meth:`update`. The defaults of :meth:`prepare` (train on the whole batch) and :meth:`summary` (nothing
    to add) suit most baselines.
    """

    name: str = "algorithm"

    def __init__(self, *, batch_size: int, epochs: float, device: torch.device | str = "cpu") -> None:
        if int(batch_size) < 1:
            raise ValueError(f"algo.batch_size must be >= 1, got {batch_size}")
        if float(epochs) <= 0:
            raise ValueError(f"algo.epochs must be > 0, got {epochs}")
        self.batch_size = int(batch_size)
        self.epochs = float(epochs)
        #: samples one update counts towards an epoch (Progressive BAIL counts only its envelope's share)
        self.samples_per_update = float(batch_size)
        self.device = torch.device(device)
        self.modules: dict[str, nn.Module] = {}
        self.optimizers: dict[str, torch.optim.Optimizer] = {}

    # -- the three contributions to the training loop -------------------------------------------------
    def prepare(self, data: TensorDictBase, ctx: PrepareContext) -> TensorDictBase:
        """Returns the data the loop samples mini-batches from (default: the whole batch)."""
        return data

    def restore_prepared(self, data: TensorDictBase, ctx: PrepareContext) -> TensorDictBase:
        """On resume, after :meth:`load_state_dict`: the data :meth:`prepare` returned, without refitting.

        ``ctx`` carries the same generator state :meth:`prepare` saw and no logger or run directory (what prepare
        logged and plotted is already there). The default runs :meth:`prepare` again, which is exact and cheap
        when prepare fits nothing; an algorithm whose prepare fits a model (BAIL's envelope) overrides this to
        rebuild its output from the fitted state the checkpoint restored.
        """
        return self.prepare(data, ctx)

    @abstractmethod
    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        """One update on a mini-batch; returns detached scalars to log."""

    @property
    @abstractmethod
    def policy(self) -> TensorDictModuleBase:
        """The deterministic evaluation policy (reads ``"observation"``, writes ``"action"``)."""

    def summary(self) -> dict[str, Any]:
        """Extra fields for ``summary.json`` (e.g. BAIL's selected fraction)."""
        return {}

    # -- checkpoints -----------------------------------------------------------------------------------
    #: names of plain attributes (numbers, tensors, dicts of them) that change during training and belong in
    #: the checkpoint next to the modules and optimizers (early-stopping counters, prepare's summary, ...)
    state_attributes: tuple[str, ...] = ()

    def state_dict(self) -> dict[str, Any]:
        """Everything the rest of a run depends on: every module, every optimizer, the :attr:`state_attributes`.

        Loading it into a freshly built algorithm of the same config makes every later :meth:`update` produce
        the same numbers as the original object (given the same random streams).
        """
        return {
            "modules": {k: m.state_dict() for k, m in self.modules.items()},
            "optimizers": {k: o.state_dict() for k, o in self.optimizers.items()},
            "attributes": {k: copy.deepcopy(getattr(self, k)) for k in self.state_attributes if hasattr(self, k)},
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        for k, m in self.modules.items():
            m.load_state_dict(state["modules"][k])
        for k, o in self.optimizers.items():
            o.load_state_dict(state["optimizers"][k])
        for k, v in state.get("attributes", {}).items():
            setattr(self, k, copy.deepcopy(v))

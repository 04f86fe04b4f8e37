"""Behaviour cloning (spec 8.1): MSE imitation of the batch's actions with a deterministic tanh actor.

It is also BAIL's imitation step: :class:`~torchrl_bail.algorithms.bail.BAIL` is this class with a
:meth:`prepare` that keeps only the best actions.

Examples:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from torchrl_bail.modules import action_spec_from_bounds
    >>> algo = BehaviourCloning(obs_dim=4, action_spec=action_spec_from_bounds([-1.0] * 2, [1.0] * 2),
    ...                         hidden=(16,), batch_size=8, epochs=1)
    >>> batch = TensorDict({"observation": torch.randn(8, 4), "action": torch.rand(8, 2) * 2 - 1}, [8])
    >>> sorted(algo.update(batch))
    ['loss_bc']
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from torchrl.data import TensorSpec
from torchrl.objectives import BCLoss

from torchrl_bail.algorithms.base import Algorithm
from torchrl_bail.modules import make_deterministic_actor

__all__ = ["BehaviourCloning", "DeterministicActorAlgorithm", "make_bc_loss"]


def make_bc_loss(actor, reduction: str = "mean") -> BCLoss:
    """TorchRL's :class:`~torchrl.objectives.BCLoss` with MSE on a deterministic actor.

    With ``reduction="mean"`` its mean runs over batch x action dimensions, exactly the authors' imitation
    loss (spec 5); ``"none"`` gives the per-element squared errors ``[B, |A|]``. Several losses built on one
    actor share its parameters.
    """
    with warnings.catch_warnings():  # BCLoss lacks a target-params annotation and warns on construction
        warnings.filterwarnings("ignore", message=".*target_actor_network_params.*")
        return BCLoss(actor, loss_function="l2", reduction=reduction)


class DeterministicActorAlgorithm(Algorithm):
    """An algorithm whose policy is a deterministic tanh actor with its own Adam optimizer (BC, BAIL, MARWIL).

    Builds :attr:`actor` with :func:`~torchrl_bail.modules.make_deterministic_actor`, registers it as
    ``modules["actor"]`` with ``optimizers["actor"]`` and evaluates it as :attr:`policy`; subclasses add their
    losses and :meth:`update`. Keyword arguments as in :class:`BehaviourCloning`.
    """

    def __init__(
        self,
        *,
        obs_dim: int,
        action_spec: TensorSpec,
        hidden: Sequence[int] = (400, 300),
        lr: float = 1e-3,
        batch_size: int = 1000,
        epochs: float = 100,
        device="cpu",
    ) -> None:
        super().__init__(batch_size=batch_size, epochs=epochs, device=device)
        self.actor = make_deterministic_actor(obs_dim, action_spec.to(self.device), hidden).to(self.device)
        self.modules["actor"] = self.actor
        self.optimizers["actor"] = torch.optim.Adam(self.actor.parameters(), lr=lr)

    @property
    def policy(self):
        return self.actor


class BehaviourCloning(DeterministicActorAlgorithm):
    """BC on whatever :meth:`prepare` returns (the whole batch here).

    Keyword Args:
        obs_dim (int): observation size.
        action_spec (TensorSpec): bounded action spec; the actor outputs ``tanh`` scaled to it.
        hidden (sequence of int): actor hidden sizes. Defaults to ``(400, 300)``.
        lr (float): Adam learning rate. Defaults to ``1e-3``.
        batch_size (int): mini-batch size, sampled with replacement. Defaults to ``1000``.
        epochs (float): length in epochs of 10^6 samples. Defaults to ``100``.
        device: training device. Defaults to ``"cpu"``.
    """

    name = "bc"

    def __init__(
        self,
        *,
        obs_dim: int,
        action_spec: TensorSpec,
        hidden: Sequence[int] = (400, 300),
        lr: float = 1e-3,
        batch_size: int = 1000,
        epochs: float = 100,
        device="cpu",
    ) -> None:
        super().__init__(obs_dim=obs_dim, action_spec=action_spec, hidden=hidden, lr=lr, batch_size=batch_size,
                         epochs=epochs, device=device)
        self.bc_loss = make_bc_loss(self.actor)

    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        loss = self.bc_loss(batch)["loss_bc"]
        optimizer = self.optimizers["actor"]
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        return {"loss_bc": loss.detach()}

"""Behaviour cloning (supp. C.3): MSE imitation of the batch's actions with a deterministic tanh actor.

It is also BAIL's imitation step: :class:`~torchrl_bail.algorithms.bail.BAIL` is this class with a
:meth:`prepare` that keeps only the best actions.

Examples:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from torchrl_bail.configuration.config_builders import algo_config
    >>> from torchrl_bail.modules import action_spec_from_bounds
    >>> algo = BehaviourCloning(4, action_spec_from_bounds([-1.0] * 2, [1.0] * 2),
    ...                         algo_config("bc", batch_size=8, epochs=1, policy={"hidden": [16]}))
    >>> batch = TensorDict({"observation": torch.randn(8, 4), "action": torch.rand(8, 2) * 2 - 1}, [8])
    >>> sorted(algo.update(batch))
    ['loss_bc']
"""

from __future__ import annotations

import warnings

import torch
from omegaconf import MISSING
from tensordict import TensorDictBase
from torchrl.data import TensorSpec
from torchrl.objectives import BCLoss

from torchrl_bail.algorithms.base import Algorithm
from torchrl_bail.configuration.algo_schemas import AlgoConfig, NetConfig, algo_schema
from torchrl_bail.modules import make_deterministic_actor

__all__ = ["BehaviourCloning", "DeterministicActorAlgorithm", "make_bc_loss"]


# -- the schema (conf/algo/bc.yaml), read by torchrl_bail.configuration.algo_schemas without importing this module --


@algo_schema("bc")
class BCConfig(AlgoConfig):
    column = 3
    study = "all"
    paper_study = True
    tiny = ()
    description = "behaviour cloning on the whole batch"
    losses = ("torchrl.objectives.BCLoss",)

    policy: NetConfig = MISSING


def make_bc_loss(actor, reduction: str = "mean") -> BCLoss:
    """TorchRL's :class:`~torchrl.objectives.BCLoss` with MSE on a deterministic actor.

    With ``reduction="mean"`` its mean runs over batch x action dimensions, exactly the authors' imitation
    loss (supp. B.2, C.3); ``"none"`` gives the per-element squared errors ``[B, |A|]``. Several losses built on one
    actor share its parameters.
    """
    with warnings.catch_warnings():  # BCLoss lacks a target-params annotation and warns on construction
        warnings.filterwarnings("ignore", message=".*target_actor_network_params.*")
        loss = BCLoss(actor, loss_function="l2", reduction=reduction)
    _ = loss.in_keys  # resolved now, not lazily at the first call (a compiled update would recompile after it)
    return loss


class DeterministicActorAlgorithm(Algorithm):
    """An algorithm whose policy is a deterministic tanh actor with its own Adam optimizer (BC, BAIL, MARWIL).

    Builds :attr:`actor` with :func:`~torchrl_bail.modules.make_deterministic_actor` from the config's ``policy``
    block (``hidden``, ``lr``), registers it as ``modules["actor"]`` with ``optimizers["actor"]`` and evaluates it
    as :attr:`policy`; subclasses add their losses and :meth:`update`. Arguments as in
    :class:`~torchrl_bail.algorithms.base.Algorithm`.
    """

    def __init__(self, obs_dim: int, action_spec: TensorSpec, config, device="cpu") -> None:
        super().__init__(obs_dim, action_spec, config, device)
        policy = self.config.policy
        actor = make_deterministic_actor(obs_dim, action_spec.to(self.device), tuple(policy.hidden))
        self.actor = actor.to(self.device)
        self.modules["actor"] = self.actor
        self.optimizers["actor"] = torch.optim.Adam(self.actor.parameters(), lr=policy.lr)

    @property
    def policy(self):
        return self.actor

    @classmethod
    def rebuild_policy(cls, record, action_spec: TensorSpec, device):
        """The tanh actor alone, from the record's ``hidden["policy"]`` (nothing else of the algorithm is built)."""
        return make_deterministic_actor(record["obs_dim"], action_spec, tuple(record["hidden"]["policy"]))


class BehaviourCloning(DeterministicActorAlgorithm):
    """BC on whatever :meth:`prepare` returns (the whole batch here), from ``conf/algo/bc.yaml``'s config.

    Arguments as in :class:`~torchrl_bail.algorithms.base.Algorithm`; the config's ``policy`` block is the actor,
    its mini-batches are sampled with replacement.
    """

    name = "bc"

    def __init__(self, obs_dim: int, action_spec: TensorSpec, config, device="cpu") -> None:
        super().__init__(obs_dim, action_spec, config, device)
        self.bc_loss = make_bc_loss(self.actor)

    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        loss = self.bc_loss(batch)["loss_bc"]
        optimizer = self.optimizers["actor"]
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        return {"loss_bc": loss.detach()}

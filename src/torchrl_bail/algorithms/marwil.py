"""MARWIL (supp. C.2, MARWIL): advantage-weighted imitation with a value net fitted to BAIL's augmented returns.

Each update samples a mini-batch from the whole batch, computes :class:`~torchrl_bail.objectives.MARWILLoss`
once (one pass of each network) and steps the deterministic actor and the value net with their own Adam
optimizers. The actor is the evaluation policy; ``beta = 0`` reduces the algorithm to behaviour cloning.
The value net is built like BAIL's upper envelope (:func:`~torchrl_bail.modules.make_value_network`: output layer
default init x 0.1, bias 0); the running normaliser ``c^2`` is saved in :meth:`MARWIL.state_dict`.

Examples:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from torchrl_bail.configuration.config_builders import algo_config
    >>> from torchrl_bail.modules import action_spec_from_bounds
    >>> config = algo_config("marwil", batch_size=8, policy={"hidden": [16]}, value={"hidden": [16]})
    >>> algo = MARWIL(4, action_spec_from_bounds([-1.0] * 2, [1.0] * 2), config)
    >>> batch = TensorDict({"observation": torch.randn(8, 4), "action": torch.rand(8, 2) * 2 - 1,
    ...                     "return": torch.randn(8)}, [8])
    >>> sorted(algo.update(batch))  # doctest: +NORMALIZE_WHITESPACE
    ['advantage_mean', 'c2', 'clamped_fraction', 'loss_actor', 'loss_value', 'squared_error_mean', 'value_mean',
     'weight_max', 'weight_mean', 'weight_share_max']
"""

from __future__ import annotations

from typing import Any

import torch
from omegaconf import MISSING
from tensordict import TensorDictBase
from torchrl.data import TensorSpec

from torchrl_bail.algorithms.base import PrepareContext
from torchrl_bail.algorithms.bc import DeterministicActorAlgorithm
from torchrl_bail.configuration.algo_schemas import AlgoConfig, NetConfig, algo_schema
from torchrl_bail.configuration.config import at_least, fraction, non_negative, positive
from torchrl_bail.modules import make_value_network
from torchrl_bail.objectives.marwil import MARWILLoss

__all__ = ["MARWIL"]


# -- the schema (conf/algo/marwil.yaml), read by torchrl_bail.configuration.algo_schemas without importing this module
# --


@algo_schema("marwil")
class MARWILConfig(AlgoConfig):
    column = 4
    study = "all"
    paper_study = True
    tiny = ()
    description = "MARWIL (Wang et al., NeurIPS 2018): advantage-weighted imitation, β = {beta:g}, running c²"
    losses = ("torchrl_bail.objectives.MARWILLoss",)

    beta: float = non_negative()
    c2_init: float = positive()
    c2_rate: float = fraction()
    vf_coeff: float = non_negative()
    max_exponent: float = positive()
    eps: float = non_negative()
    value_warmup_updates: int = at_least(0)
    value: NetConfig = MISSING
    policy: NetConfig = MISSING


class MARWIL(DeterministicActorAlgorithm):
    """MARWIL with a deterministic tanh actor (weighted MSE) and a state-value net, from ``conf/algo/marwil.yaml``'s
    config (arguments as in :class:`~torchrl_bail.algorithms.base.Algorithm`).

    The config's ``policy`` block is the actor, ``value`` the value net (``hidden``, Adam ``lr``); ``beta``,
    ``c2_init``, ``c2_rate``, ``vf_coeff``, ``max_exponent`` and ``eps`` go to
    :class:`~torchrl_bail.objectives.MARWILLoss`.
    """

    name = "marwil"
    #: the tensor work of a joint update is what ``compile=`` compiles; :meth:`update` picks it or the warm-up step
    compiled_method = "_joint_update"
    state_attributes = ("updates_done",)

    def __init__(self, obs_dim: int, action_spec: TensorSpec, config, device="cpu") -> None:
        super().__init__(obs_dim, action_spec, config, device)
        cfg = self.config
        self.value_network = make_value_network(obs_dim, tuple(cfg.value.hidden)).to(self.device)
        self.loss = MARWILLoss(self.actor, self.value_network, beta=cfg.beta, c2_init=cfg.c2_init,
                               c2_rate=cfg.c2_rate, vf_coeff=cfg.vf_coeff, max_exponent=cfg.max_exponent,
                               eps=cfg.eps).to(self.device)
        self.modules["value"] = self.value_network
        self.optimizers["value"] = torch.optim.Adam(self.value_network.parameters(), lr=cfg.value.lr)
        self._optimizers = (self.optimizers["actor"], self.optimizers["value"])
        self.updates_done = 0

    def prepare(self, data: TensorDictBase, ctx: PrepareContext) -> TensorDictBase:
        """The whole batch, restricted to what the loss reads (``observation``, ``action``, ``return``)."""
        missing = [key for key in self.loss.in_keys if key not in data.keys(include_nested=True)]
        if missing:
            raise KeyError(f"MARWIL needs the batch entries {self.loss.in_keys}; missing {missing}")
        return data.select(*self.loss.in_keys)

    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        """One joint update of the actor and the value net; during the first ``value_warmup_updates`` (``0``, the
        paper's and RLlib's joint training, by default) only the value net is stepped and the actor's optimizer
        is left untouched, so the actor starts with a fresh Adam once V has been fitted (docs: Results, finding 4)."""
        self.updates_done += 1
        if self.updates_done <= self.config.value_warmup_updates:
            return self._value_update(batch)
        return self._joint_update(batch)

    def _value_update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        out = self.loss(batch)  # the same diagnostics (and the same c^2 schedule) as a joint update
        value_optimizer = self.optimizers["value"]
        value_optimizer.zero_grad(set_to_none=True)
        out.get("loss_value").backward()
        value_optimizer.step()
        return {key: value.detach() for key, value in out.items()}

    def _joint_update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        out = self.loss(batch)
        # the actor loss reaches only the actor and the value loss only the value net (the weights are
        # detached): one backward of the sum gives each optimizer exactly its own loss' gradient
        total = out.get("loss_actor") + out.get("loss_value")
        for optimizer in self._optimizers:
            optimizer.zero_grad(set_to_none=True)
        total.backward()
        for optimizer in self._optimizers:
            optimizer.step()
        return {key: value.detach() for key, value in out.items()}

    # -- seed stacks: one update clock for every seed (stacking.SeedStack's hooks) -------------------------------
    def stack_attributes(self, algorithms: list[MARWIL]) -> None:
        self.updates_done = algorithms[0].updates_done

    def unstack_attributes(self, algorithms: list[MARWIL]) -> None:
        for algorithm in algorithms:
            algorithm.updates_done = self.updates_done

    # -- checkpoints: the running normaliser c^2 lives in the loss ------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        state = super().state_dict()
        state["loss_buffers"] = {name: buf.clone() for name, buf in self.loss.named_buffers()
                                 if "." not in name}
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        self.loss.load_state_dict({**self.loss.state_dict(), **state["loss_buffers"]})

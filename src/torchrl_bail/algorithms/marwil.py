"""MARWIL (spec 8.2): advantage-weighted imitation with a value net fitted to BAIL's augmented returns.

Each update samples a mini-batch from the whole batch, computes :class:`~torchrl_bail.objectives.MARWILLoss`
once (one pass of each network) and steps the deterministic actor and the value net with their own Adam
optimizers. The actor is the evaluation policy; ``beta = 0`` reduces the algorithm to behaviour cloning.
The value net is built like BAIL's upper envelope (:func:`~torchrl_bail.modules.make_value_network`: output layer
default init x 0.1, bias 0); the running normaliser ``c^2`` is saved in :meth:`MARWIL.state_dict`.

Examples:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from torchrl_bail.modules import action_spec_from_bounds
    >>> algo = MARWIL(obs_dim=4, action_spec=action_spec_from_bounds([-1.0] * 2, [1.0] * 2), hidden=(16,),
    ...               value_hidden=(16,), batch_size=8, epochs=1)
    >>> batch = TensorDict({"observation": torch.randn(8, 4), "action": torch.rand(8, 2) * 2 - 1,
    ...                     "return": torch.randn(8)}, [8])
    >>> sorted(algo.update(batch))
    ['advantage_mean', 'c2', 'clamped_fraction', 'loss_actor', 'loss_value', 'value_mean', 'weight_max', 'weight_mean']
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.data import TensorSpec

from torchrl_bail.algorithms.base import PrepareContext
from torchrl_bail.algorithms.bc import DeterministicActorAlgorithm
from torchrl_bail.modules import make_value_network
from torchrl_bail.objectives.marwil import MARWILLoss

__all__ = ["MARWIL"]


class MARWIL(DeterministicActorAlgorithm):
    """MARWIL with a deterministic tanh actor (weighted MSE) and a state-value net.

    Keyword Args:
        obs_dim, action_spec, hidden, lr, batch_size, epochs, device: as in
            :class:`~torchrl_bail.algorithms.bc.BehaviourCloning` (``hidden``/``lr`` are the actor's).
        value_hidden (sequence of int): value-net hidden sizes. Defaults to ``(128, 128)``.
        value_lr (float): the value net's Adam learning rate. Defaults to ``1e-3``.
        beta, c2_init, c2_rate, vf_coeff, max_exponent, eps: see :class:`~torchrl_bail.objectives.MARWILLoss`.
    """

    name = "marwil"

    def __init__(
        self,
        *,
        obs_dim: int,
        action_spec: TensorSpec,
        hidden: Sequence[int] = (400, 300),
        lr: float = 1e-3,
        value_hidden: Sequence[int] = (128, 128),
        value_lr: float = 1e-3,
        beta: float = 1.0,
        c2_init: float = 100.0,
        c2_rate: float = 1e-8,
        vf_coeff: float = 1.0,
        max_exponent: float = 20.0,
        eps: float = 1e-8,
        batch_size: int = 1000,
        epochs: float = 100,
        device="cpu",
    ) -> None:
        super().__init__(obs_dim=obs_dim, action_spec=action_spec, hidden=hidden, lr=lr, batch_size=batch_size,
                         epochs=epochs, device=device)
        self.value_network = make_value_network(obs_dim, value_hidden).to(self.device)
        self.loss = MARWILLoss(self.actor, self.value_network, beta=beta, c2_init=c2_init, c2_rate=c2_rate,
                               vf_coeff=vf_coeff, max_exponent=max_exponent, eps=eps).to(self.device)
        self.modules["value"] = self.value_network
        self.optimizers["value"] = torch.optim.Adam(self.value_network.parameters(), lr=value_lr)
        self._optimizers = (self.optimizers["actor"], self.optimizers["value"])

    def prepare(self, data: TensorDictBase, ctx: PrepareContext) -> TensorDictBase:
        """The whole batch, restricted to what the loss reads (``observation``, ``action``, ``return``)."""
        missing = [key for key in self.loss.in_keys if key not in data.keys(include_nested=True)]
        if missing:
            raise KeyError(f"MARWIL needs the batch entries {self.loss.in_keys}; missing {missing}")
        return data.select(*self.loss.in_keys)

    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
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

    # -- checkpoints: the running normaliser c^2 lives in the loss ------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        state = super().state_dict()
        state["loss_buffers"] = {name: buf.clone() for name, buf in self.loss.named_buffers()
                                 if "." not in name}
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        self.loss.load_state_dict({**self.loss.state_dict(), **state["loss_buffers"]})

"""Network builders shared by every algorithm.

All networks are plain TorchRL modules reading TED keys (``"observation"``, ``"action"``) so that
they plug into TorchRL losses, replay buffers and environments without adapters.

Examples:
    >>> import torch
    >>> from torchrl.data import Bounded
    >>> from tensordict import TensorDict
    >>> spec = Bounded(-0.4, 0.4, shape=(3,))
    >>> actor = make_deterministic_actor(11, spec)
    >>> td = actor(TensorDict({"observation": torch.randn(5, 11)}, [5]))
    >>> td["action"].shape, bool(td["action"].abs().max() <= 0.4)
    (torch.Size([5, 3]), True)
    >>> value = make_value_network(11)
    >>> value(TensorDict({"observation": torch.randn(5, 11)}, [5]))["state_value"].shape
    torch.Size([5, 1])
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.data import Bounded, TensorSpec
from torchrl.modules import MLP, TanhModule, ValueOperator

__all__ = [
    "mlp",
    "action_spec_from_bounds",
    "make_deterministic_actor",
    "make_value_network",
    "make_qvalue_network",
]


def mlp(in_features: int, out_features: int, hidden: Sequence[int]) -> MLP:
    """A ReLU MLP ``in -> hidden... -> out`` with PyTorch's default init (never TorchRL's 1-layer default)."""
    return MLP(
        in_features=in_features,
        out_features=out_features,
        num_cells=list(hidden),
        activation_class=nn.ReLU,
    )


def action_spec_from_bounds(low, high, dtype: torch.dtype = torch.float32) -> Bounded:
    """A :class:`~torchrl.data.Bounded` action spec from per-dimension (or scalar) bounds."""
    low = torch.as_tensor(low, dtype=dtype)
    high = torch.as_tensor(high, dtype=dtype)
    return Bounded(low, high, shape=low.shape, dtype=dtype)


def make_deterministic_actor(
    obs_dim: int,
    action_spec: TensorSpec,
    hidden: Sequence[int] = (400, 300),
    *,
    observation_key="observation",
    action_key="action",
) -> TensorDictSequential:
    """Deterministic policy ``obs -> 400 -> 300 -> |A| -> tanh`` scaled to the spec bounds (BAIL §5).

    For Humanoid (bound 0.4) the output is ``0.4 * tanh(.)``.
    """
    act_dim = action_spec.shape[-1]
    body = TensorDictModule(mlp(obs_dim, act_dim, hidden), in_keys=[observation_key], out_keys=["param"])
    head = TanhModule(in_keys=["param"], out_keys=[action_key], spec=action_spec)
    return TensorDictSequential(body, head)


def make_value_network(
    obs_dim: int,
    hidden: Sequence[int] = (128, 128),
    *,
    head_scale: float = 0.1,
    observation_key="observation",
    out_key="state_value",
) -> ValueOperator:
    """State-value net ``obs -> 128 -> 128 -> 1`` (BAIL §3.2).

    Hidden layers keep PyTorch's default init; the output layer's weight is the default init times
    ``head_scale`` and its bias is zero, as in the authors' upper envelope.
    """
    net = mlp(obs_dim, 1, hidden)
    last = net[-1]
    with torch.no_grad():
        last.weight.mul_(head_scale)
        last.bias.zero_()
    return ValueOperator(net, in_keys=[observation_key], out_keys=[out_key])


def make_qvalue_network(
    obs_dim: int,
    act_dim: int,
    hidden: Sequence[int] = (400, 300),
    *,
    observation_key="observation",
    action_key="action",
    out_key="state_action_value",
) -> ValueOperator:
    """Action-value net ``(obs, action) -> 400 -> 300 -> 1`` (critics of BCQ, BEAR and DDPG)."""
    return ValueOperator(mlp(obs_dim + act_dim, 1, hidden), in_keys=[observation_key, action_key], out_keys=[out_key])

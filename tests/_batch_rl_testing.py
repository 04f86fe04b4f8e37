"""Test helpers shared by the contract suite and the BCQ/BEAR tests: tiny specs, batches, hand-made critics."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn

from torchrl_bail.modules import (
    action_spec_from_bounds,
    make_perturbation_actor,
    make_qvalue_network,
    make_sac_actor,
    make_vae,
)
from torchrl_bail.objectives.bcq import BCQLoss
from torchrl_bail.objectives.bear import BEARLoss

OBS, ACT, HIDDEN = 4, 2, (8, 8)
#: per-dimension bounds (the second like Humanoid's 0.4) so that scaling mistakes show
SPEC = action_spec_from_bounds([-1.0, -0.4], [1.0, 0.4])


def batch(shape=(6,), *, terminated=None, truncated=None, reward=None, seed=0) -> TensorDict:
    """A TED batch of random transitions; ``done = terminated | truncated`` as TorchRL stores it."""
    g = torch.Generator().manual_seed(seed)
    shape = tuple(shape)
    terminated = torch.zeros(*shape, 1, dtype=torch.bool) if terminated is None else terminated.view(*shape, 1)
    truncated = torch.zeros(*shape, 1, dtype=torch.bool) if truncated is None else truncated.view(*shape, 1)
    reward = torch.randn(*shape, 1, generator=g) if reward is None else reward.view(*shape, 1)
    low, high = SPEC.space.low, SPEC.space.high
    return TensorDict({
        "observation": torch.randn(*shape, OBS, generator=g),
        "action": low + (high - low) * torch.rand(*shape, ACT, generator=g),
        "next": {"observation": torch.randn(*shape, OBS, generator=g), "reward": reward,
                 "terminated": terminated, "truncated": truncated, "done": terminated | truncated},
    }, list(shape))


class LinearQ(nn.Module):
    """``Q(s, a) = k * a[..., 0] + b``: a critic whose values a test can compute by hand."""

    def __init__(self, k: float, b: float = 0.0) -> None:
        super().__init__()
        self.k = nn.Parameter(torch.tensor(float(k)))
        self.b = nn.Parameter(torch.tensor(float(b)))

    def forward(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.k * action[..., :1] + self.b + 0 * observation[..., :1]


class ObservationSlice(nn.Module):
    """``w * s[..., start:stop]`` with a trainable ``w = 1``: a network whose output the test writes into the
    observation (``ObservationSlice(0, 1)``: a value ``V(s) = s_0``; ``ObservationSlice(1)``: an action ``s_1:``)."""

    def __init__(self, start: int, stop: int | None = None) -> None:
        super().__init__()
        self.start, self.stop = start, stop
        self.w = nn.Parameter(torch.ones(()))

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return self.w * observation[..., self.start:self.stop]


def linear_critics(k=(1.0, 2.0), b=(0.0, 0.0)) -> list[TensorDictModule]:
    return [TensorDictModule(LinearQ(ki, bi), in_keys=["observation", "action"], out_keys=["state_action_value"])
            for ki, bi in zip(k, b, strict=True)]


def critics() -> list[TensorDictModule]:
    return [make_qvalue_network(OBS, ACT, HIDDEN) for _ in range(2)]


def vae():
    return make_vae(OBS, SPEC, HIDDEN, latent_dim=2 * ACT)


def bcq_loss(qvalue=None, **kwargs) -> BCQLoss:
    actor = make_perturbation_actor(OBS, SPEC, HIDDEN, phi=kwargs.pop("phi", 0.05))
    return BCQLoss(actor, critics() if qvalue is None else qvalue, vae(), **kwargs)


def bear_actor():
    return make_sac_actor(OBS, SPEC, HIDDEN, log_std_min=-math.inf, log_std_max=math.inf)


def bear_loss(qvalue=None, **kwargs) -> BEARLoss:
    return BEARLoss(bear_actor(), critics() if qvalue is None else qvalue, vae(), **kwargs)


def target_tensors(loss) -> dict:
    """Every target tensor, keyed by name, for before/after comparisons."""
    out = {}
    for name in ("target_actor_network_params", "target_qvalue_network_params"):
        for key, value in getattr(loss, name).items(True, True):
            out[(name, key)] = value
    return out


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """Tiny networks gain nothing from intra-op threads, and on a shared CPU the thread hand-offs dominate."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)

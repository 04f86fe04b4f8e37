"""The BCQ/BEAR update's fast paths compute what the plain paths compute: the critics run from plain tensors give
the same values and gradients bit for bit as ``to_module`` + TensorDict, and the fused Adam agrees with torch's
reference Adam to float32 precision over whole updates."""

from __future__ import annotations

import pytest
import torch
from _batch_rl_testing import (
    HIDDEN,
    OBS,
    SPEC,
    batch,
    bcq_loss,
    bear_loss,
    one_thread,  # noqa: F401 (autouse fixture)
)

from torchrl_bail.algorithms.bcq import BCQ
from torchrl_bail.algorithms.bear import BEAR
from torchrl_bail.configuration.config_builders import algo_config


def _critic_values_and_grads(loss, data, plain: bool):
    saved = loss._plain_critic
    if not plain:
        loss._plain_critic = None
    try:
        obs, act = data["observation"], data["action"]
        params = loss.qvalue_network_params
        q = loss._q_values(obs, act, params)
        target_q = loss._q_values(obs, act, loss.target_qvalue_network_params)
        q1 = loss.q1_value(obs, act.requires_grad_(True))
        (action_grad,) = torch.autograd.grad(q1.sum(), act)
        grads = torch.autograd.grad((q * torch.tensor([[1.0], [2.0]])).sum(), list(params.values(True, True)))
        return q.detach(), target_q, q1.detach(), action_grad, grads
    finally:
        loss._plain_critic = saved


@pytest.mark.parametrize("make_loss", [bcq_loss, bear_loss])
def test_plain_tensor_critics_match_the_tensordict_path_bit_for_bit(make_loss):
    torch.manual_seed(0)
    loss = make_loss(deactivate_vmap=True)
    assert loss._plain_critic is not None  # the MLP critics take the fast path
    data = batch((5,))
    fast = _critic_values_and_grads(loss, data.clone(), plain=True)
    slow = _critic_values_and_grads(loss, data.clone(), plain=False)
    for a, b in zip(fast[:4], slow[:4], strict=True):
        assert torch.equal(a, b)
    assert all(torch.equal(a, b) for a, b in zip(fast[4], slow[4], strict=True))
    assert fast[0].shape == (2, 5) and not torch.equal(fast[0][0], fast[0][1])


def test_critics_that_are_not_plain_mlps_keep_the_tensordict_path():
    from tensordict.nn import TensorDictModule
    from torch import nn

    class Critic(nn.Module):
        def __init__(self):
            super().__init__()
            self.net = nn.Linear(OBS + SPEC.shape[-1], 1)

        def forward(self, observation, action):
            return self.net(torch.cat([observation, action], -1)).tanh()

    critics = [TensorDictModule(Critic(), ["observation", "action"], ["state_action_value"]) for _ in range(2)]
    loss = bcq_loss(critics, deactivate_vmap=True)
    assert loss._plain_critic is None
    data = batch((3,))
    assert loss._q_values(data["observation"], data["action"], loss.qvalue_network_params).abs().max() <= 1


def _updates(cls, fused: bool, n: int = 6, **kwargs):
    small = {"hidden": HIDDEN}
    torch.manual_seed(0)
    algo = cls(OBS, SPEC, algo_config(cls.name, vae=small, actor=dict(small), critic=dict(small), batch_size=6,
                                      epochs=1, **kwargs))
    if not fused:  # torch's reference (single-tensor) Adam over the same parameters and learning rates
        for name, opt in algo.optimizers.items():
            algo.optimizers[name] = torch.optim.Adam(opt.param_groups[0]["params"], lr=opt.param_groups[0]["lr"],
                                                     foreach=False, fused=False)
    torch.manual_seed(1)
    metrics = [algo.update(batch((6,), seed=i)) for i in range(n)]
    return algo.loss.state_dict(), metrics


@pytest.mark.parametrize("cls, kwargs", [(BCQ, {}), (BEAR, {"warm_start_updates": 3})])
def test_fused_adam_agrees_with_the_reference_adam_to_float_precision(cls, kwargs):
    assert all(opt.defaults["fused"] for opt in _algo_optimizers(cls, kwargs))
    fused_state, fused_metrics = _updates(cls, True, **kwargs)
    ref_state, ref_metrics = _updates(cls, False, **kwargs)
    assert fused_state.keys() == ref_state.keys()
    for key, value in ref_state.items():
        torch.testing.assert_close(fused_state[key], value, rtol=1e-5, atol=1e-6, msg=key)
    for key, value in ref_metrics[-1].items():
        torch.testing.assert_close(fused_metrics[-1][key], value, rtol=1e-4, atol=1e-5, msg=key)
    # the parameters moved (the comparison is not between two untouched initialisations)
    assert not torch.equal(fused_state["qvalue_network_params.module.0.weight"],
                           _initial_state(cls, kwargs)["qvalue_network_params.module.0.weight"])


def _algo_optimizers(cls, kwargs):
    small = {"hidden": HIDDEN}
    algo = cls(OBS, SPEC, algo_config(cls.name, vae=small, actor=dict(small), critic=dict(small), batch_size=6,
                                      epochs=1, **kwargs))
    return list(algo.optimizers.values())


def _initial_state(cls, kwargs):
    return _updates(cls, True, n=0, **kwargs)[0]


def test_fused_adam_runs_are_reproducible_seed_for_seed():
    first, _ = _updates(BEAR, True, warm_start_updates=2)
    second, _ = _updates(BEAR, True, warm_start_updates=2)
    assert all(torch.equal(first[k], second[k]) for k in first)

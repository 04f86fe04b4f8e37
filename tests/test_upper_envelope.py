"""UpperEnvelopeLoss: the asymmetric penalty, its gradients, keys, reductions and [S, B] batches."""

from __future__ import annotations


import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import EnsembleModule, TensorDictModule
from torch import nn

from torchrl_bail.modules import make_value_network
from torchrl_bail.objectives.upper_envelope import UpperEnvelopeLoss, envelope_penalty


class _Constant(nn.Module):
    """V(s) = c for every state: lets a test put V exactly where it wants."""

    def __init__(self, value: float) -> None:
        super().__init__()
        self.c = nn.Parameter(torch.tensor(float(value)))

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return self.c.expand(*observation.shape[:-1], 1)


class _Identity(nn.Module):
    """V(s) = w * s[..., :1] with w = 1: V is whatever the first observation entry says."""

    def __init__(self) -> None:
        super().__init__()
        self.w = nn.Parameter(torch.ones(()))

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return self.w * observation[..., :1]


def _value_of(module: nn.Module) -> TensorDictModule:
    return TensorDictModule(module, in_keys=["observation"], out_keys=["state_value"])


def _batch(values, returns) -> TensorDict:
    """A batch whose identity envelope gives exactly ``values``."""
    values = torch.as_tensor(values, dtype=torch.float32)
    returns = torch.as_tensor(returns, dtype=torch.float32)
    return TensorDict({"observation": values.unsqueeze(-1), "return": returns}, batch_size=returns.shape)



def test_asymmetry_below_costs_k_times_above():
    loss = UpperEnvelopeLoss(_value_of(_Identity()), penalty=1000.0, reduction="none")
    above = loss(_batch([3.0], [1.0]))["loss_envelope"]  # V - G = +2
    below = loss(_batch([1.0], [3.0]))["loss_envelope"]  # V - G = -2
    torch.testing.assert_close(above, torch.tensor([4.0]))
    torch.testing.assert_close(below, torch.tensor([4000.0]))


def test_exact_value_hand_computed():
    # gaps V - G: +1, -0.5, 0, +2, -1 ; K = 10
    # per element: 1, 10 * 0.25, 0, 4, 10 * 1 -> sum 17.5, mean 3.5
    loss = UpperEnvelopeLoss(_value_of(_Identity()), penalty=10.0)
    out = loss(_batch([2.0, 1.0, 3.0, 4.0, 0.0], [1.0, 1.5, 3.0, 2.0, 1.0]))
    torch.testing.assert_close(out["loss_envelope"], torch.tensor(3.5))
    torch.testing.assert_close(out["fraction_below"], torch.tensor(0.4))
    torch.testing.assert_close(out["value_mean"], torch.tensor(2.0))
    torch.testing.assert_close(
        envelope_penalty(torch.tensor([2.0, 1.0, 3.0]), torch.tensor([1.0, 1.5, 3.0]), 10.0),
        torch.tensor([1.0, 2.5, 0.0]),
    )


def test_v_equal_g_is_weight_one_branch():
    # at V == G the loss and its derivative vanish; just above, the weight is 1 (not K)
    loss = UpperEnvelopeLoss(_value_of(_Constant(2.0)), penalty=1000.0)
    out = loss(_batch([0.0], [2.0]))
    assert out["loss_envelope"].item() == 0.0
    assert out["fraction_below"].item() == 0.0  # V == G is not "below"
    out["loss_envelope"].backward()
    assert loss.value_network_params.get(("module", "c")).grad.item() == 0.0
    eps = 1e-3
    loss2 = UpperEnvelopeLoss(_value_of(_Constant(2.0 + eps)), penalty=1000.0)
    torch.testing.assert_close(loss2(_batch([0.0], [2.0]))["loss_envelope"], torch.tensor(eps**2))


@pytest.mark.parametrize("value,target,expected_grad", [(3.0, 1.0, 2 * 2.0), (1.0, 3.0, 1000.0 * 2 * -2.0)])
def test_gradient_sign_and_size(value, target, expected_grad):
    # d/dV of w (V - G)^2 is 2 w (V - G): positive above (pushes V down), K-times larger and negative below
    module = _Constant(value)
    loss = UpperEnvelopeLoss(_value_of(module), penalty=1000.0)
    loss(_batch([0.0], [target]))["loss_envelope"].backward()
    torch.testing.assert_close(module.c.grad, torch.tensor(expected_grad))


def test_gradients_reach_only_value_params():
    torch.manual_seed(0)
    value = make_value_network(5)
    other = nn.Linear(3, 3)
    loss = UpperEnvelopeLoss(value)
    names = [name for name, _ in loss.named_parameters()]
    assert names and all(name.startswith("value_network_params") for name in names)
    td = TensorDict({"observation": torch.randn(16, 5), "return": torch.randn(16) * 10}, [16])
    out = loss(td)
    out["loss_envelope"].backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in value.parameters())
    assert all(p.grad is None for p in other.parameters())
    # diagnostics carry no graph
    assert not out["fraction_below"].requires_grad and not out["value_mean"].requires_grad
    # the loss shares the network's parameters (an optimizer over either trains the network)
    assert {id(p) for p in loss.parameters()} == {id(p) for p in value.parameters()}


def test_set_keys_and_unknown_key():
    loss = UpperEnvelopeLoss(_value_of(_Identity()))
    assert set(loss.in_keys) == {"observation", "return"}
    loss.set_keys(value_target="mc_return")
    assert set(loss.in_keys) == {"observation", "mc_return"}
    td = TensorDict({"observation": torch.tensor([[1.0]]), "mc_return": torch.tensor([3.0])}, [1])
    torch.testing.assert_close(loss(td)["loss_envelope"], torch.tensor(4000.0))
    with pytest.raises(ValueError):
        loss.set_keys(bogus="x")
    loss.set_keys(value_target=None)  # back to the default
    assert loss.tensor_keys.value_target == "return"


def test_reductions_none_mean_sum():
    values, returns = [2.0, 1.0, 3.0, 4.0], [1.0, 2.0, 3.0, 2.0]  # per element K=10: 1, 10, 0, 4
    per_element = torch.tensor([1.0, 10.0, 0.0, 4.0])
    outs = {r: UpperEnvelopeLoss(_value_of(_Identity()), penalty=10.0, reduction=r)(_batch(values, returns))
            for r in ("none", "mean", "sum")}
    torch.testing.assert_close(outs["none"]["loss_envelope"], per_element)
    torch.testing.assert_close(outs["mean"]["loss_envelope"], per_element.mean())
    torch.testing.assert_close(outs["sum"]["loss_envelope"], per_element.sum())
    with pytest.raises(ValueError):
        UpperEnvelopeLoss(_value_of(_Identity()), reduction="max")


def test_return_with_trailing_singleton_and_shape_error():
    loss = UpperEnvelopeLoss(_value_of(_Identity()), penalty=10.0, reduction="none")
    td = TensorDict({"observation": torch.tensor([[2.0], [1.0]]), "return": torch.tensor([[1.0], [2.0]])}, [2])
    torch.testing.assert_close(loss(td)["loss_envelope"], torch.tensor([1.0, 10.0]))
    bad = TensorDict({"observation": torch.tensor([[2.0], [1.0]]), "return": torch.zeros(2, 3)}, [2])
    with pytest.raises(ValueError, match="shape"):
        loss(bad)


def test_seed_batch_per_seed_reduction():
    # S = 2 seeds, B = 3 points; the identity envelope makes every per-element loss explicit (K = 10)
    values = [[2.0, 1.0, 3.0], [0.0, 0.0, 5.0]]
    returns = [[1.0, 2.0, 3.0], [1.0, 1.0, 1.0]]
    per_element = torch.tensor([[1.0, 10.0, 0.0], [10.0, 10.0, 16.0]])
    td = _batch(values, returns)
    none = UpperEnvelopeLoss(_value_of(_Identity()), penalty=10.0, reduction="none")(td)
    torch.testing.assert_close(none["loss_envelope"], per_element)
    torch.testing.assert_close(none["fraction_below"], torch.tensor([1 / 3, 2 / 3]))
    torch.testing.assert_close(none["value_mean"], torch.tensor([2.0, 5 / 3]))
    mean = UpperEnvelopeLoss(_value_of(_Identity()), penalty=10.0)(td)
    torch.testing.assert_close(mean["loss_envelope"], per_element.mean(-1).mean())
    # with a mask, each seed's mean runs over its own unmasked points
    masked_loss = UpperEnvelopeLoss(_value_of(_Identity()), penalty=10.0)
    masked_loss.loss_mask_key = "valid"
    td["valid"] = torch.tensor([[True, True, False], [True, False, False]])
    torch.testing.assert_close(masked_loss(td)["loss_envelope"], torch.tensor(((1.0 + 10.0) / 2 + 10.0) / 2))


def test_seed_ensemble_gradients_are_per_seed():
    torch.manual_seed(0)
    seeds = 3
    ensemble = EnsembleModule(make_value_network(4), num_copies=seeds, expand_input=False)
    loss = UpperEnvelopeLoss(ensemble, reduction="none")
    td = TensorDict({"observation": torch.randn(seeds, 20, 4), "return": torch.randn(seeds, 20)}, [seeds, 20])
    out = loss(td)
    assert out["loss_envelope"].shape == (seeds, 20)
    assert out["fraction_below"].shape == (seeds,)
    per_seed = out["loss_envelope"].mean(-1)
    per_seed[1].backward()  # only seed 1's parameters receive gradient
    stacked = [p for p in loss.parameters() if p.grad is not None]
    assert stacked and all(p.shape[0] == seeds for p in stacked)
    for p in stacked:
        assert p.grad[0].abs().sum() == 0 and p.grad[2].abs().sum() == 0 and p.grad[1].abs().sum() > 0


def test_state_dict_round_trip_keeps_penalty():
    loss = UpperEnvelopeLoss(make_value_network(3), penalty=123.0)
    state = loss.state_dict()
    assert state["penalty"].item() == 123.0
    other = UpperEnvelopeLoss(make_value_network(3), penalty=1.0)
    other.load_state_dict(state)
    assert other.penalty.item() == 123.0
    for key, value in state.items():
        torch.testing.assert_close(other.state_dict()[key], value)
    with pytest.raises(ValueError):
        UpperEnvelopeLoss(make_value_network(3), penalty=0.0)


def test_kwargs_dispatch_matches_tensordict_path():
    torch.manual_seed(0)
    loss = UpperEnvelopeLoss(make_value_network(6))
    obs, ret = torch.randn(12, 6), torch.randn(12)
    td_out = loss(TensorDict({"observation": obs, "return": ret}, [12]))
    loss.select_out_keys("loss_envelope", "fraction_below", "value_mean")
    loss_envelope, below, mean = loss(observation=obs, **{"return": ret})
    torch.testing.assert_close(loss_envelope, td_out["loss_envelope"])
    torch.testing.assert_close(below, td_out["fraction_below"])
    torch.testing.assert_close(mean, td_out["value_mean"])

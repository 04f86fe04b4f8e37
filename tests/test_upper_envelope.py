"""What only UpperEnvelopeLoss does: the asymmetric penalty by hand, the V == G branch, the gradient's sign and size,
shapes and per-seed values (the contract suite in test_contract.py covers keys, reductions and the rest)."""

from __future__ import annotations

import pytest
import torch
from _batch_rl_testing import ObservationSlice
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
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


def _value_of(module: nn.Module) -> TensorDictModule:
    return TensorDictModule(module, in_keys=["observation"], out_keys=["state_value"])


def _batch(values, returns) -> TensorDict:
    """A batch whose identity envelope gives exactly ``values``."""
    values = torch.as_tensor(values, dtype=torch.float32)
    returns = torch.as_tensor(returns, dtype=torch.float32)
    return TensorDict({"observation": values.unsqueeze(-1), "return": returns}, batch_size=returns.shape)



def test_asymmetry_below_costs_k_times_above():
    loss = UpperEnvelopeLoss(_value_of(ObservationSlice(0, 1)), penalty=1000.0, reduction="none")
    above = loss(_batch([3.0], [1.0]))["loss_envelope"]  # V - G = +2
    below = loss(_batch([1.0], [3.0]))["loss_envelope"]  # V - G = -2
    torch.testing.assert_close(above, torch.tensor([4.0]))
    torch.testing.assert_close(below, torch.tensor([4000.0]))


def test_exact_value_hand_computed():
    # gaps V - G: +1, -0.5, 0, +2, -1 ; K = 10
    # per element: 1, 10 * 0.25, 0, 4, 10 * 1 -> sum 17.5, mean 3.5
    loss = UpperEnvelopeLoss(_value_of(ObservationSlice(0, 1)), penalty=10.0)
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


def test_return_with_trailing_singleton_and_shape_error():
    loss = UpperEnvelopeLoss(_value_of(ObservationSlice(0, 1)), penalty=10.0, reduction="none")
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
    none = UpperEnvelopeLoss(_value_of(ObservationSlice(0, 1)), penalty=10.0, reduction="none")(td)
    torch.testing.assert_close(none["loss_envelope"], per_element)
    torch.testing.assert_close(none["fraction_below"], torch.tensor([1 / 3, 2 / 3]))
    torch.testing.assert_close(none["value_mean"], torch.tensor([2.0, 5 / 3]))
    mean = UpperEnvelopeLoss(_value_of(ObservationSlice(0, 1)), penalty=10.0)(td)
    torch.testing.assert_close(mean["loss_envelope"], per_element.mean(-1).mean())


def test_penalty_is_a_checked_buffer():
    loss = UpperEnvelopeLoss(make_value_network(3), penalty=123.0)
    assert loss.state_dict()["penalty"].item() == 123.0
    with pytest.raises(ValueError, match="penalty"):
        UpperEnvelopeLoss(make_value_network(3), penalty=0.0)

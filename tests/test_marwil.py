"""MARWILLoss and the MARWIL algorithm: hand-computed weights, gradients, keys, reductions, seeds, checkpoints."""

from __future__ import annotations

import math

import pytest
import torch
from hydra import compose, initialize_config_dir
from tensordict import TensorDict
from tensordict.nn import EnsembleModule, TensorDictModule
from torch import nn

from torchrl_bail import config_dir
from torchrl_bail.algorithms import ALGORITHMS, MARWIL, BehaviourCloning, build_algorithm
from torchrl_bail.algorithms.bc import make_bc_loss
from torchrl_bail.modules import action_spec_from_bounds, make_deterministic_actor, make_value_network
from torchrl_bail.objectives import MARWILLoss


class _FirstEntry(nn.Module):
    """V(s) = w * s[..., :1], w = 1: the value is whatever the first observation entry says."""

    def __init__(self) -> None:
        super().__init__()
        self.w = nn.Parameter(torch.ones(()))

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return self.w * observation[..., :1]


class _Tail(nn.Module):
    """pi(s) = w * s[..., 1:], w = 1: the predicted action is the rest of the observation."""

    def __init__(self) -> None:
        super().__init__()
        self.w = nn.Parameter(torch.ones(()))

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return self.w * observation[..., 1:]


def _nets():
    actor = TensorDictModule(_Tail(), in_keys=["observation"], out_keys=["action"])
    value = TensorDictModule(_FirstEntry(), in_keys=["observation"], out_keys=["state_value"])
    return actor, value


# a tiny batch: V = [1, 2, 3], G = [11, 2, -7] -> A = [10, 0, -10], mean(A^2) = 200 / 3
VALUES = [1.0, 2.0, 3.0]
RETURNS = [11.0, 2.0, -7.0]
PREDICTED = [[0.5, -0.5], [0.0, 0.0], [1.0, 1.0]]
ACTIONS = [[0.0, 0.0], [0.0, 1.0], [1.0, 0.0]]
SQUARED_ERRORS = [0.25, 0.5, 0.5]  # mean over the action dims of (pi - a)^2


def _batch(values=VALUES, returns=RETURNS, predicted=PREDICTED, actions=ACTIONS) -> TensorDict:
    values = torch.as_tensor(values, dtype=torch.float32)
    obs = torch.cat([values.unsqueeze(-1), torch.as_tensor(predicted, dtype=torch.float32)], -1)
    returns = torch.as_tensor(returns, dtype=torch.float32)
    return TensorDict({"observation": obs, "action": torch.as_tensor(actions, dtype=torch.float32),
                       "return": returns}, batch_size=returns.shape)


def _expected(beta: float, c2_init: float, rate: float, max_exponent: float = 20.0):
    """The spec's formulas in plain Python floats."""
    adv = [g - v for g, v in zip(RETURNS, VALUES)]
    c2 = c2_init + rate * (sum(a * a for a in adv) / len(adv) - c2_init)
    exponents = [beta * a / (math.sqrt(c2) + 1e-8) for a in adv]
    weights = [math.exp(min(e, max_exponent)) for e in exponents]
    per_point = [w * se for w, se in zip(weights, SQUARED_ERRORS)]
    return adv, c2, weights, per_point, [e >= max_exponent for e in exponents]


def _real_nets(obs_dim=5, act_dim=2):
    actor = make_deterministic_actor(obs_dim, action_spec_from_bounds([-1.0] * act_dim, [1.0] * act_dim), (16, 16))
    return actor, make_value_network(obs_dim, (16,))


def _random_batch(batch_size=(16,), obs_dim=5, act_dim=2, scale=10.0) -> TensorDict:
    return TensorDict({"observation": torch.randn(*batch_size, obs_dim),
                       "action": torch.rand(*batch_size, act_dim) * 2 - 1,
                       "return": torch.randn(*batch_size) * scale}, list(batch_size))



def test_weights_and_losses_by_hand():
    adv, c2, weights, per_point, _ = _expected(beta=1.0, c2_init=100.0, rate=0.5)
    loss = MARWILLoss(*_nets(), beta=1.0, c2_init=100.0, c2_rate=0.5, vf_coeff=2.0, reduction="none")
    out = loss(_batch())
    assert c2 == pytest.approx(100.0 + 0.5 * (200.0 / 3.0 - 100.0))
    torch.testing.assert_close(loss.c2, torch.tensor(c2, dtype=torch.float64))
    torch.testing.assert_close(out["c2"], torch.tensor(c2))
    torch.testing.assert_close(out["loss_actor"], torch.tensor(per_point))
    torch.testing.assert_close(out["loss_value"], 2.0 * 0.5 * torch.tensor(adv) ** 2)
    torch.testing.assert_close(out["weight_mean"], torch.tensor(sum(weights) / 3))
    torch.testing.assert_close(out["weight_max"], torch.tensor(max(weights)))
    torch.testing.assert_close(out["advantage_mean"], torch.tensor(0.0))
    torch.testing.assert_close(out["value_mean"], torch.tensor(2.0))
    assert out["clamped_fraction"].item() == 0.0
    # a second training call uses (and moves) the updated normaliser
    loss(_batch())
    assert loss.c2.item() == pytest.approx(c2 + 0.5 * (200.0 / 3.0 - c2))


def test_c2_moves_only_in_training_and_keeps_tiny_updates():
    loss = MARWILLoss(*_nets(), c2_init=100.0, c2_rate=1e-8)
    loss(_batch())
    # the increment 1e-8 * (66.7 - 100) = -3.3e-7 is below a float32 ulp at 100; the float64 buffer keeps it
    expected = 100.0 + 1e-8 * (200.0 / 3.0 - 100.0)
    assert loss.c2.dtype == torch.float64 and loss.c2.item() != 100.0
    assert loss.c2.item() == pytest.approx(expected, rel=1e-12)
    loss.eval()
    before = loss.c2.clone()
    out = loss(_batch())
    loss.actor_loss(_batch())
    torch.testing.assert_close(loss.c2, before)
    torch.testing.assert_close(out["c2"], before.float())
    loss.train()
    loss.value_loss(_batch())  # the value loss never moves c2
    torch.testing.assert_close(loss.c2, before)
    loss.actor_loss(_batch())
    assert loss.c2.item() != before.item()


def test_exponent_is_clamped_and_weights_never_overflow():
    _, _, weights, per_point, clamped = _expected(beta=1.0, c2_init=1.0, rate=0.0, max_exponent=5.0)
    loss = MARWILLoss(*_nets(), beta=1.0, c2_init=1.0, c2_rate=0.0, max_exponent=5.0, reduction="none")
    out = loss(_batch())
    assert clamped == [True, False, False] and weights[0] == pytest.approx(math.exp(5.0))
    torch.testing.assert_close(out["loss_actor"], torch.tensor(per_point))
    torch.testing.assert_close(out["clamped_fraction"], torch.tensor(1 / 3))
    # an absurd advantage: exp(1e6) would be inf; the clamp keeps every weight <= exp(max_exponent)
    huge = MARWILLoss(*_nets(), c2_init=1.0, max_exponent=20.0)
    out = huge(_batch(returns=[1e6, 2.0, -1e6]))
    assert torch.isfinite(out["loss_actor"]) and out["weight_max"].item() == pytest.approx(math.exp(20.0), rel=1e-5)
    assert math.isfinite(huge.c2.item())


def test_reductions_none_mean_sum():
    *_, per_point, _ = _expected(beta=1.0, c2_init=100.0, rate=0.0)
    value_terms = torch.tensor([50.0, 0.0, 50.0])
    outs = {r: MARWILLoss(*_nets(), c2_rate=0.0, reduction=r)(_batch()) for r in ("none", "mean", "sum")}
    torch.testing.assert_close(outs["none"]["loss_actor"], torch.tensor(per_point))
    torch.testing.assert_close(outs["mean"]["loss_actor"], torch.tensor(sum(per_point) / 3))
    torch.testing.assert_close(outs["sum"]["loss_actor"], torch.tensor(sum(per_point)))
    torch.testing.assert_close(outs["none"]["loss_value"], value_terms)
    torch.testing.assert_close(outs["mean"]["loss_value"], value_terms.mean())
    torch.testing.assert_close(outs["sum"]["loss_value"], value_terms.sum())
    with pytest.raises(ValueError, match="reduction"):
        MARWILLoss(*_nets(), reduction="max")


@pytest.mark.parametrize("kwargs", [{"beta": -1.0}, {"c2_init": 0.0}, {"c2_rate": 2.0}, {"vf_coeff": -1.0},
                                    {"max_exponent": float("inf")}, {"eps": 0.0}])
def test_bad_coefficients_are_named(kwargs):
    with pytest.raises(ValueError, match=next(iter(kwargs))):
        MARWILLoss(*_nets(), **kwargs)


def test_shape_errors_name_the_keys():
    loss = MARWILLoss(*_nets())
    td = TensorDict({"observation": _batch()["observation"], "action": _batch()["action"],
                     "return": torch.zeros(3, 2)}, [3])
    with pytest.raises(ValueError, match="return"):
        loss(td)
    td = TensorDict({"observation": _batch()["observation"], "action": torch.zeros(3, 5),
                     "return": torch.zeros(3)}, [3])
    with pytest.raises(ValueError, match="action"):
        loss(td)
    # a [3, 1] return is accepted like [3]
    td = _batch()
    td.set("return", td["return"].unsqueeze(-1))
    torch.testing.assert_close(loss(td)["loss_value"], loss(_batch())["loss_value"])


def test_gradients_reach_only_their_own_network():
    torch.manual_seed(0)
    actor, value = _real_nets()
    loss = MARWILLoss(actor, value)
    assert {id(p) for p in loss.parameters()} == {id(p) for p in [*actor.parameters(), *value.parameters()]}
    td = _random_batch()
    out = loss(td)
    for key in ("advantage_mean", "value_mean", "weight_mean", "weight_max", "clamped_fraction", "c2"):
        assert not out[key].requires_grad, key
    out["loss_actor"].backward(retain_graph=True)
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in actor.parameters())
    assert all(p.grad is None for p in value.parameters())
    for p in actor.parameters():
        p.grad = None
    out["loss_value"].backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in value.parameters())
    assert all(p.grad is None for p in actor.parameters())
    # the sub-loss methods keep the same separation
    for p in value.parameters():
        p.grad = None
    loss.actor_loss(td)[0].backward()
    assert all(p.grad is None for p in value.parameters())
    for p in actor.parameters():
        p.grad = None
    loss.value_loss(td)[0].backward()
    assert all(p.grad is None for p in actor.parameters())


def test_forward_equals_sub_losses():
    torch.manual_seed(0)
    loss = MARWILLoss(*_real_nets())
    loss.eval()  # keep c2 fixed so the three calls see the same normaliser
    td = _random_batch()
    out = loss(td)
    actor_loss, actor_meta = loss.actor_loss(td)
    value_loss, value_meta = loss.value_loss(td)
    torch.testing.assert_close(out["loss_actor"], actor_loss)
    torch.testing.assert_close(out["loss_value"], value_loss)
    for key, value in {**actor_meta, **value_meta}.items():
        torch.testing.assert_close(out[key], value)


def test_set_keys_and_unknown_key():
    # the actor writes tensor_keys.action (the key contract), so this one writes the renamed key
    actor = TensorDictModule(_Tail(), in_keys=["observation"], out_keys=["expert_action"])
    value = TensorDictModule(_FirstEntry(), in_keys=["observation"], out_keys=["state_value"])
    loss = MARWILLoss(actor, value, c2_rate=0.0, reduction="none")
    assert set(loss.in_keys) == {"observation", "action", "return"}
    loss.set_keys(value_target="mc_return", action="expert_action")
    assert set(loss.in_keys) == {"observation", "expert_action", "mc_return"}
    base = _batch()
    td = TensorDict({"observation": base["observation"], "expert_action": base["action"],
                     "mc_return": base["return"]}, [3])
    *_, per_point, _ = _expected(beta=1.0, c2_init=100.0, rate=0.0)
    torch.testing.assert_close(loss(td)["loss_actor"], torch.tensor(per_point))
    with pytest.raises(ValueError):
        loss.set_keys(bogus="x")
    loss.set_keys(value_target=None)
    assert loss.tensor_keys.value_target == "return"


def test_beta_is_schedulable_in_place():
    loss = MARWILLoss(*_nets())
    buffer = loss.beta
    loss.beta = 0.5
    assert loss.beta is buffer and loss.beta.item() == 0.5


def test_seed_batch_per_seed_reduction_and_per_seed_c2():
    # seed 0: the tiny batch; seed 1: the tiny batch with returns scaled so that mean(A^2) differs
    s0, s1 = _batch(), _batch(returns=[21.0, 2.0, -17.0])  # A = [20, 0, -20] -> mean(A^2) = 800 / 3
    td = torch.stack([s0, s1])
    rate = 0.5
    loss = MARWILLoss(*_nets(), c2_init=100.0, c2_rate=rate, reduction="none")
    out = loss(td)
    assert out["loss_actor"].shape == out["loss_value"].shape == (2, 3)
    expected_c2 = torch.tensor([100 + rate * (200 / 3 - 100), 100 + rate * (800 / 3 - 100)], dtype=torch.float64)
    torch.testing.assert_close(loss.c2, expected_c2)
    for key in ("advantage_mean", "value_mean", "weight_mean", "weight_max", "clamped_fraction", "c2"):
        assert out[key].shape == (2,), key
    # each seed's weights use its own normaliser: seed 0 equals the [B] computation
    single = MARWILLoss(*_nets(), c2_init=100.0, c2_rate=rate, reduction="none")(s0)
    torch.testing.assert_close(out["loss_actor"][0], single["loss_actor"])
    # "mean": per-seed means, then the mean over seeds; with a mask, each seed's mean over its own points
    mean_loss = MARWILLoss(*_nets(), c2_init=100.0, c2_rate=0.0)
    none_loss = MARWILLoss(*_nets(), c2_init=100.0, c2_rate=0.0, reduction="none")
    per_point = none_loss(td)["loss_actor"]
    torch.testing.assert_close(mean_loss(td)["loss_actor"], per_point.mean(-1).mean())
    mean_loss.loss_mask_key = "valid"
    td["valid"] = torch.tensor([[True, True, False], [True, False, False]])
    expected = ((per_point[0, 0] + per_point[0, 1]) / 2 + per_point[1, 0]) / 2
    torch.testing.assert_close(mean_loss(td)["loss_actor"], expected)
    # a per-seed normaliser refuses a batch of another leading shape
    with pytest.raises(ValueError, match="c2"):
        loss(s0)


def test_seed_ensemble_gradients_are_per_seed():
    torch.manual_seed(0)
    seeds = 3
    actor, value = _real_nets()
    loss = MARWILLoss(EnsembleModule(actor, num_copies=seeds, expand_input=False),
                      EnsembleModule(value, num_copies=seeds, expand_input=False), reduction="none")
    out = loss(_random_batch((seeds, 20)))
    assert out["loss_actor"].shape == (seeds, 20) and loss.c2.shape == (seeds,)
    (out["loss_actor"].mean(-1)[1] + out["loss_value"].mean(-1)[1]).backward()
    # EnsembleModule also lists its (unused) template; the stacked [S, ...] copies are under params_td
    stacked = [p for name, p in loss.named_parameters() if "params_td" in name and name.endswith(("weight", "bias"))]
    assert len(stacked) == 10
    for p in stacked:
        assert p.shape[0] == seeds
        assert p.grad[0].abs().sum() == 0 and p.grad[2].abs().sum() == 0 and p.grad[1].abs().sum() > 0


def test_state_dict_round_trip_keeps_c2_and_coefficients():
    torch.manual_seed(0)
    loss = MARWILLoss(*_real_nets(), beta=0.7, c2_init=100.0, c2_rate=0.1, vf_coeff=0.3, max_exponent=7.0)
    loss(_random_batch())
    state = loss.state_dict()
    assert state["c2"].item() != 100.0 and state["beta"].item() == pytest.approx(0.7)
    other = MARWILLoss(*_real_nets())
    other.load_state_dict(state)
    for key, value in state.items():
        torch.testing.assert_close(other.state_dict()[key], value)
    other.eval(), loss.eval()
    td = _random_batch()
    torch.testing.assert_close(other(td)["loss_actor"], loss(td)["loss_actor"])
    # a per-seed normaliser [S] loads into a fresh loss whose c2 is still a scalar
    seeded = MARWILLoss(*_nets(), c2_rate=0.5)
    seeded(torch.stack([_batch(), _batch(returns=[21.0, 2.0, -17.0])]))
    fresh = MARWILLoss(*_nets())
    fresh.load_state_dict(seeded.state_dict())
    torch.testing.assert_close(fresh.c2, seeded.c2)


def test_kwargs_dispatch_matches_tensordict_path():
    torch.manual_seed(0)
    loss = MARWILLoss(*_real_nets())
    loss.eval()
    td = _random_batch()
    td_out = loss(td)
    loss.select_out_keys("loss_actor", "loss_value", "weight_mean")
    loss_actor, loss_value, weight_mean = loss(observation=td["observation"], action=td["action"],
                                               **{"return": td["return"]})
    torch.testing.assert_close(loss_actor, td_out["loss_actor"])
    torch.testing.assert_close(loss_value, td_out["loss_value"])
    torch.testing.assert_close(weight_mean, td_out["weight_mean"])


def test_beta_zero_is_behaviour_cloning():
    torch.manual_seed(0)
    actor, value = _real_nets()
    td = _random_batch(scale=1000.0)
    out = MARWILLoss(actor, value, beta=0.0)(td)
    assert out["weight_mean"].item() == 1.0 and out["weight_max"].item() == 1.0
    torch.testing.assert_close(out["loss_actor"], make_bc_loss(actor)(td)["loss_bc"])
    # and as algorithms: same seed, same batches -> the same actor after a few Adam steps
    spec = action_spec_from_bounds([-1.0] * 2, [1.0] * 2)
    torch.manual_seed(1)
    marwil = MARWIL(obs_dim=5, action_spec=spec, hidden=(16,), value_hidden=(8,), beta=0.0, batch_size=16,
                    epochs=1)
    torch.manual_seed(1)
    bc = BehaviourCloning(obs_dim=5, action_spec=spec, hidden=(16,), batch_size=16, epochs=1)
    for _ in range(5):
        batch = _random_batch(scale=1000.0)
        torch.testing.assert_close(marwil.update(batch)["loss_actor"], bc.update(batch)["loss_bc"])
    for p, q in zip(marwil.actor.parameters(), bc.actor.parameters()):
        torch.testing.assert_close(p, q)


def _run_algo(seed: int, updates: int = 3) -> tuple[list[dict], MARWIL]:
    torch.manual_seed(seed)
    algo = MARWIL(obs_dim=5, action_spec=action_spec_from_bounds([-1.0] * 2, [1.0] * 2), hidden=(16, 16),
                  value_hidden=(16,), c2_rate=0.01, batch_size=16, epochs=1)
    g = torch.Generator().manual_seed(seed)
    metrics = []
    for _ in range(updates):
        batch = TensorDict({"observation": torch.randn(16, 5, generator=g),
                            "action": torch.rand(16, 2, generator=g) * 2 - 1,
                            "return": torch.randn(16, generator=g) * 10}, [16])
        metrics.append(algo.update(batch))
    return metrics, algo


def test_same_seed_same_numbers_and_both_networks_step():
    (m1, a1), (m2, a2), (m3, _) = _run_algo(0), _run_algo(0), _run_algo(1)
    for x, y in zip(m1, m2):
        assert x.keys() == y.keys()
        for key in x:
            assert torch.equal(x[key], y[key]), key
    assert not torch.equal(m1[-1]["loss_actor"], m3[-1]["loss_actor"])
    for name in ("actor", "value"):
        for p, q in zip(a1.modules[name].parameters(), a2.modules[name].parameters()):
            assert torch.equal(p, q)
    # both optimizers took steps: a fresh algorithm with the same seed has other weights
    torch.manual_seed(0)
    fresh = MARWIL(obs_dim=5, action_spec=action_spec_from_bounds([-1.0] * 2, [1.0] * 2), hidden=(16, 16),
                   value_hidden=(16,), batch_size=16, epochs=1)
    for name in ("actor", "value"):
        assert any(not torch.equal(p, q) for p, q in zip(fresh.modules[name].parameters(),
                                                           a1.modules[name].parameters())), name
    assert set(a1.optimizers) == {"actor", "value"}
    assert all(len(o.state) > 0 for o in a1.optimizers.values())


def test_algorithm_checkpoint_restores_c2_and_continues_identically():
    _, algo = _run_algo(0)
    state = algo.state_dict()
    assert state["loss_buffers"]["c2"].item() != 100.0
    torch.manual_seed(5)
    other = MARWIL(obs_dim=5, action_spec=action_spec_from_bounds([-1.0] * 2, [1.0] * 2), hidden=(16, 16),
                   value_hidden=(16,), c2_rate=0.01, batch_size=16, epochs=1)
    other.load_state_dict(state)
    assert other.loss.c2.item() == algo.loss.c2.item()
    batch = _random_batch()
    a, b = algo.update(batch), other.update(batch)
    for key in a:
        torch.testing.assert_close(a[key], b[key])


def test_prepare_keeps_what_the_loss_reads_and_names_missing_keys():
    _, algo = _run_algo(0, updates=0)
    data = _random_batch()
    data["episode"] = torch.zeros(16, dtype=torch.int64)
    prepared = algo.prepare(data, None)
    assert set(prepared.keys()) == {"observation", "action", "return"}
    with pytest.raises(KeyError, match="return"):
        algo.prepare(data.exclude("return"), None)


def test_registry_builds_marwil_from_its_config():
    assert "marwil" in ALGORITHMS
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("config", overrides=["+exp=hopper_ddpg05", "algo=marwil", "algo.policy.hidden=[8]",
                                           "algo.value.hidden=[8]"])
    algo = build_algorithm(cfg.algo, 11, action_spec_from_bounds([-1.0] * 3, [1.0] * 3), "cpu")
    assert isinstance(algo, MARWIL) and algo.name == "marwil"
    assert algo.loss.beta.item() == cfg.algo.beta
    assert algo.loss.c2.item() == cfg.algo.c2_init
    assert algo.loss.c2_rate.item() == cfg.algo.c2_rate
    assert algo.loss.vf_coeff.item() == cfg.algo.vf_coeff
    assert algo.loss.max_exponent.item() == cfg.algo.max_exponent
    assert (algo.batch_size, algo.epochs) == (cfg.algo.batch_size, cfg.algo.epochs)
    assert algo.optimizers["actor"].param_groups[0]["lr"] == cfg.algo.policy.lr
    assert algo.optimizers["value"].param_groups[0]["lr"] == cfg.algo.value.lr
    assert algo.policy is algo.actor

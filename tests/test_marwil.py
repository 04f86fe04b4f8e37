"""What only MARWIL does: weights and losses by hand, the running normaliser c^2 (training only, float64, per
seed), the clamp, beta = 0 as BC, and its config (the contract suite in test_contract.py covers the rest)."""

from __future__ import annotations

import copy
import math

import pytest
import torch
from _batch_rl_testing import ObservationSlice
from hydra import compose, initialize_config_dir
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from torchrl_bail import config_dir
from torchrl_bail.algorithms import ALGORITHMS, MARWIL, BehaviourCloning, build_algorithm
from torchrl_bail.algorithms.bc import make_bc_loss
from torchrl_bail.configuration.config_builders import algo_config
from torchrl_bail.modules import action_spec_from_bounds, make_deterministic_actor, make_value_network
from torchrl_bail.objectives import MARWILLoss


def _nets():
    actor = TensorDictModule(ObservationSlice(1), in_keys=["observation"], out_keys=["action"])
    value = TensorDictModule(ObservationSlice(0, 1), in_keys=["observation"], out_keys=["state_value"])
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
    """MARWIL's formulas in plain Python floats."""
    adv = [g - v for g, v in zip(RETURNS, VALUES, strict=True)]
    c2 = c2_init + rate * (sum(a * a for a in adv) / len(adv) - c2_init)
    exponents = [beta * a / (math.sqrt(c2) + 1e-8) for a in adv]
    weights = [math.exp(min(e, max_exponent)) for e in exponents]
    per_point = [w * se for w, se in zip(weights, SQUARED_ERRORS, strict=True)]
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
    torch.testing.assert_close(out["weight_share_max"], torch.tensor(max(weights) / sum(weights)))
    torch.testing.assert_close(out["squared_error_mean"], torch.tensor(sum(SQUARED_ERRORS) / 3))
    torch.testing.assert_close(out["advantage_mean"], torch.tensor(0.0))
    torch.testing.assert_close(out["value_mean"], torch.tensor(2.0))
    assert out["clamped_fraction"].item() == 0.0
    # a second training call uses (and moves) the updated normaliser
    loss(_batch())
    assert loss.c2.item() == pytest.approx(c2 + 0.5 * (200.0 / 3.0 - c2))


def test_advantage_weights_are_the_next_updates_weights_and_move_nothing():
    # c2 stays at its initial 100 (rate 0.5 would move it in any training-mode loss call)
    beta, c2 = 1.0, 100.0
    loss = MARWILLoss(*_nets(), beta=beta, c2_init=c2, c2_rate=0.5, max_exponent=0.5, reduction="none")
    weight, advantage, clamped = loss.advantage_weights(_batch())
    adv = [g - v for g, v in zip(RETURNS, VALUES, strict=True)]
    exponents = [beta * a / (math.sqrt(c2) + 1e-8) for a in adv]  # [1, 0, -1]: the first above max_exponent 0.5
    torch.testing.assert_close(advantage, torch.tensor(adv))
    torch.testing.assert_close(weight, torch.tensor([math.exp(min(e, 0.5)) for e in exponents]))
    assert clamped.tolist() == [True, False, False]
    assert loss.training and loss.c2.item() == c2, "looking at the weights never moves c^2"
    assert not weight.requires_grad and not advantage.requires_grad


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


def test_renamed_action_is_both_the_target_and_the_actor_output():
    # the actor writes tensor_keys.action (the key contract), so this one writes the renamed key
    actor = TensorDictModule(ObservationSlice(1), in_keys=["observation"], out_keys=["expert_action"])
    value = TensorDictModule(ObservationSlice(0, 1), in_keys=["observation"], out_keys=["state_value"])
    loss = MARWILLoss(actor, value, c2_rate=0.0, reduction="none")
    assert set(loss.in_keys) == {"observation", "action", "return"}
    loss.set_keys(value_target="mc_return", action="expert_action")
    assert set(loss.in_keys) == {"observation", "expert_action", "mc_return"}
    base = _batch()
    td = TensorDict({"observation": base["observation"], "expert_action": base["action"],
                     "mc_return": base["return"]}, [3])
    *_, per_point, _ = _expected(beta=1.0, c2_init=100.0, rate=0.0)
    torch.testing.assert_close(loss(td)["loss_actor"], torch.tensor(per_point))


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
    for key in ("advantage_mean", "value_mean", "weight_mean", "weight_max", "weight_share_max", "clamped_fraction",
                "squared_error_mean", "c2"):
        assert out[key].shape == (2,), key
    # each seed's weights use its own normaliser: seed 0 equals the [B] computation
    single = MARWILLoss(*_nets(), c2_init=100.0, c2_rate=rate, reduction="none")(s0)
    torch.testing.assert_close(out["loss_actor"][0], single["loss_actor"])
    # a per-seed normaliser refuses a batch of another leading shape
    with pytest.raises(ValueError, match="c2"):
        loss(s0)


def test_per_seed_normaliser_loads_into_a_fresh_loss():
    # a per-seed normaliser [S] loads into a fresh loss whose c2 is still a scalar
    seeded = MARWILLoss(*_nets(), c2_rate=0.5)
    seeded(torch.stack([_batch(), _batch(returns=[21.0, 2.0, -17.0])]))
    fresh = MARWILLoss(*_nets())
    fresh.load_state_dict(seeded.state_dict())
    torch.testing.assert_close(fresh.c2, seeded.c2)


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
    policy = {"policy": {"hidden": [16]}, "batch_size": 16}
    marwil = MARWIL(5, spec, algo_config("marwil", value={"hidden": [8]}, beta=0.0, **policy))
    torch.manual_seed(1)
    bc = BehaviourCloning(5, spec, algo_config("bc", **policy))
    for _ in range(5):
        batch = _random_batch(scale=1000.0)
        torch.testing.assert_close(marwil.update(batch)["loss_actor"], bc.update(batch)["loss_bc"])
    for p, q in zip(marwil.actor.parameters(), bc.actor.parameters(), strict=True):
        torch.testing.assert_close(p, q)


def _run_algo(seed: int, updates: int = 3) -> tuple[list[dict], MARWIL]:
    torch.manual_seed(seed)
    config = algo_config("marwil", policy={"hidden": [16, 16]}, value={"hidden": [16]}, c2_rate=0.01, batch_size=16)
    algo = MARWIL(5, action_spec_from_bounds([-1.0] * 2, [1.0] * 2), config)
    g = torch.Generator().manual_seed(seed)
    metrics = []
    for _ in range(updates):
        batch = TensorDict({"observation": torch.randn(16, 5, generator=g),
                            "action": torch.rand(16, 2, generator=g) * 2 - 1,
                            "return": torch.randn(16, generator=g) * 10}, [16])
        metrics.append(algo.update(batch))
    return metrics, algo


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


def test_value_warmup_fits_v_alone_then_starts_the_actor_with_a_fresh_adam():
    spec = action_spec_from_bounds([-1.0] * 2, [1.0] * 2)
    config = algo_config("marwil", policy={"hidden": [16]}, value={"hidden": [8]}, batch_size=16,
                         value_warmup_updates=3)
    torch.manual_seed(2)
    algo = MARWIL(5, spec, config)
    actor_before = [p.detach().clone() for p in algo.actor.parameters()]
    value_before = [p.detach().clone() for p in algo.value_network.parameters()]
    batches = [_random_batch(scale=100.0) for _ in range(5)]
    for batch in batches[:3]:
        out = algo.update(batch)
        assert "loss_actor" in out and "squared_error_mean" in out  # the same logged columns as a joint update
    assert all(torch.equal(p, q) for p, q in zip(algo.actor.parameters(), actor_before, strict=True))
    assert not any(torch.equal(p, q) for p, q in zip(algo.value_network.parameters(), value_before, strict=True))
    assert algo.optimizers["actor"].state_dict()["state"] == {}, "the actor's Adam has seen no gradient yet"
    resumed = MARWIL(5, spec, config)
    resumed.load_state_dict(copy.deepcopy(algo.state_dict()))  # a copy, as a checkpoint on disk is
    assert resumed.updates_done == 3
    for batch in batches[3:]:
        torch.testing.assert_close(algo.update(batch)["loss_actor"], resumed.update(batch)["loss_actor"])
    assert not any(torch.equal(p, q) for p, q in zip(algo.actor.parameters(), actor_before, strict=True))
    # the actor's Adam has counted only the two joint updates: its bias correction starts afresh after the warm-up
    assert {int(state["step"]) for state in algo.optimizers["actor"].state_dict()["state"].values()} == {2}
    assert {int(state["step"]) for state in algo.optimizers["value"].state_dict()["state"].values()} == {5}

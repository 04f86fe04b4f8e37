"""BCQLoss and the BCQ algorithm: gradient isolation, targets, keys, the critic target by hand, the policy,
state_dict, seeds, [S, B] batches, and the update order."""

from __future__ import annotations

import io

import pytest
import torch
from _batch_rl_testing import (
    ACT,
    HIDDEN,
    OBS,
    SPEC,
    batch,
    bcq_loss,
    groups_with_grad,
    linear_critics,
    one_thread,  # noqa: F401 (autouse fixture)
    target_tensors,
    zero_grads,
)
from tensordict import TensorDict
from torchrl.objectives import SoftUpdate

from torchrl_bail.algorithms.bcq import BCQ
from torchrl_bail.objectives.common import soft_clipped_double_q_target
from torchrl_bail.trainer import train



def test_outputs_are_scalars_and_diagnostics_carry_no_graph():
    torch.manual_seed(0)
    out = bcq_loss()(batch())
    assert set(out.keys()) == {"loss_vae", "loss_qvalue", "loss_actor", "recon_loss", "kl_loss", "q_mean",
                               "target_value_mean", "actor_q_mean"}
    for key, value in out.items():
        assert value.shape == ()
        assert value.requires_grad == key.startswith("loss"), key


@pytest.mark.parametrize("term,group", [("loss_vae", "vae_network_params"), ("loss_qvalue", "qvalue_network_params"),
                                        ("loss_actor", "actor_network_params")])
@pytest.mark.parametrize("vmap", [True, False])
def test_each_loss_reaches_only_its_network(term, group, vmap):
    torch.manual_seed(0)
    loss = bcq_loss(deactivate_vmap=not vmap)
    SoftUpdate(loss, tau=0.005)
    zero_grads(loss)
    loss(batch())[term].backward()
    assert groups_with_grad(loss) == {group}
    for name, target in target_tensors(loss).items():
        assert not target.requires_grad and target.grad is None, name


def test_every_parameter_is_trained_and_none_is_listed_twice():
    torch.manual_seed(0)
    loss = bcq_loss()
    params = list(loss.parameters())
    assert len({id(p) for p in params}) == len(params)
    out = loss(batch())
    (out["loss_vae"] + out["loss_qvalue"] + out["loss_actor"]).backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in params)
    assert not any(name.startswith("_target") for name, _ in loss.named_parameters())


def test_soft_update_moves_targets_by_exactly_tau():
    torch.manual_seed(0)
    loss = bcq_loss()
    tau = 0.1
    updater = SoftUpdate(loss, tau=tau)
    with torch.no_grad():  # move every source away from its target
        for p in loss.parameters():
            p.add_(torch.randn_like(p))
    before = {k: v.clone() for k, v in target_tensors(loss).items()}
    sources = {}
    for name in ("actor_network_params", "qvalue_network_params"):
        for key, value in getattr(loss, name).items(True, True):
            sources[("target_" + name, key)] = value.detach().clone()
    updater.step()
    after = target_tensors(loss)
    moved = 0
    for k, old in before.items():
        torch.testing.assert_close(after[k], old + tau * (sources[k] - old))
        moved += int(not torch.equal(after[k], old))
    assert moved > 0


def test_set_keys_renames_what_the_loss_reads():
    torch.manual_seed(0)
    loss = bcq_loss()
    assert ("next", "terminated") in loss.in_keys and ("next", "done") not in loss.in_keys
    td = batch()
    td["next", "true_end"] = td["next", "terminated"]
    del td["next", "terminated"]
    with pytest.raises(KeyError, match="terminated"):
        loss(td)
    loss.set_keys(terminated="true_end")
    assert ("next", "true_end") in loss.in_keys
    loss(td)
    with pytest.raises(ValueError):
        loss.set_keys(bogus="x")
    loss.set_keys(terminated=None)
    assert loss.tensor_keys.terminated == "terminated"


def test_target_bootstraps_a_truncation_but_not_a_termination():
    # constant critics Q1 = 1, Q2 = 3: every sample's soft clipped value is 0.75 * 1 + 0.25 * 3 = 1.5
    loss = bcq_loss(qvalue=linear_critics(k=(0.0, 0.0), b=(1.0, 3.0)), gamma=0.9, reduction="none")
    td = batch((3,), terminated=torch.tensor([False, False, True]), truncated=torch.tensor([False, True, False]),
               reward=torch.tensor([0.5, 0.5, 0.5]))
    assert td["next", "done"].squeeze(-1).tolist() == [False, True, True]
    y = torch.tensor([0.5 + 0.9 * 1.5, 0.5 + 0.9 * 1.5, 0.5])  # the truncated row bootstraps like a plain one
    loss_qvalue, meta = loss.qvalue_loss(td)
    torch.testing.assert_close(loss_qvalue, (1.0 - y) ** 2 + (3.0 - y) ** 2)
    torch.testing.assert_close(meta["target_value_mean"], y.mean())


def test_target_is_the_max_over_samples_of_the_soft_clipped_double_q():
    # Q_j(s, a) = k_j * a_0 with k = (1, 2); three fixed candidates a_0 in {-0.5, 0.2, 0.9}:
    # soft clipped values 0.75 * min + 0.25 * max = -0.875, 0.25, 1.125 -> max 1.125; y = 1 + 0.5 * 1.125
    loss = bcq_loss(qvalue=linear_critics(k=(1.0, 2.0)), gamma=0.5, num_samples=3, reduction="none")
    seen = {}

    def fixed_candidates(next_observation, num_samples):
        seen["shape"], seen["n"] = tuple(next_observation.shape), num_samples
        a0 = torch.tensor([-0.5, 0.2, 0.9]).expand(*next_observation.shape[:-1], 3)
        return torch.stack([a0, torch.zeros_like(a0)], -1)

    loss._target_candidates = fixed_candidates
    td = batch((2,), reward=torch.tensor([1.0, 1.0]))
    _, meta = loss.qvalue_loss(td)
    torch.testing.assert_close(meta["target_value_mean"], torch.tensor(1.0 + 0.5 * 1.125))
    assert seen == {"shape": (2, OBS), "n": 3}
    # the shared function on the same numbers
    q = torch.tensor([[-0.5, 0.2, 0.9], [-1.0, 0.4, 1.8]]).unsqueeze(1)  # [J=2, B=1, N=3]
    torch.testing.assert_close(
        soft_clipped_double_q_target(q, torch.tensor([[1.0]]), torch.tensor([[False]]), gamma=0.5, lmbda=0.75),
        torch.tensor([1.5625]),
    )


def test_actor_loss_is_minus_q1_of_the_perturbed_vae_sample():
    # Q1 = 2 * a_0 + 1 (Q2 must not matter): loss_actor = -(2 * mean a_0 + 1) over the perturbed samples
    loss = bcq_loss(qvalue=linear_critics(k=(2.0, -7.0), b=(1.0, 5.0)))
    td = batch()
    torch.manual_seed(5)
    loss_actor, meta = loss.actor_loss(td)
    torch.manual_seed(5)
    with torch.no_grad():
        sampled = loss.vae_network.decode(td["observation"])
        perturbed = loss.actor_network(TensorDict({"observation": td["observation"], "action": sampled}, [6]))
    expected = -(2 * perturbed["action"][:, 0] + 1).mean()
    torch.testing.assert_close(loss_actor, expected)
    torch.testing.assert_close(meta["actor_q_mean"], -expected)


def test_policy_plays_the_argmax_q1_candidate_within_bounds():
    # Q1 = -a_0, Q2 = +a_0: the policy must pick the candidate with the *smallest* first coordinate
    loss = bcq_loss(qvalue=linear_critics(k=(-1.0, 1.0)), phi=0.5)
    policy = loss.policy(num_samples=10)
    observation = torch.randn(5, OBS)
    torch.manual_seed(3)
    with torch.no_grad():
        candidates = loss.candidate_actions(observation, 10)
    expected = candidates[torch.arange(5), candidates[..., 0].argmin(-1)]
    torch.manual_seed(3)
    action = policy(TensorDict({"observation": observation}, [5]))["action"]
    torch.testing.assert_close(action, expected)
    assert action.shape == (5, ACT) and not action.requires_grad
    low, high = SPEC.space.low, SPEC.space.high
    assert ((candidates >= low) & (candidates <= high)).all()
    single = policy(TensorDict({"observation": torch.randn(OBS)}, []))["action"]
    assert single.shape == (ACT,) and ((single >= low) & (single <= high)).all()


def test_perturbation_stays_within_phi_and_the_bounds():
    loss = bcq_loss(phi=0.05)
    candidate = SPEC.space.high.expand(7, ACT).clone()  # at the upper bound: only a downward move is allowed
    candidate[:3] = SPEC.space.low
    out = loss.actor_network(TensorDict({"observation": torch.randn(7, OBS), "action": candidate}, [7]))["action"]
    scale = (SPEC.space.high - SPEC.space.low) / 2
    assert ((out - candidate).abs() <= 0.05 * scale + 1e-6).all()
    assert ((out >= SPEC.space.low) & (out <= SPEC.space.high)).all()


def test_state_dict_round_trip():
    torch.manual_seed(0)
    loss = bcq_loss(gamma=0.9)
    SoftUpdate(loss, tau=0.005)
    with torch.no_grad():
        for p in loss.parameters():
            p.add_(0.1)
    state = loss.state_dict()
    assert any(k.startswith("target_qvalue_network_params") for k in state) and state["gamma"] == 0.9
    torch.manual_seed(1)
    other = bcq_loss(gamma=0.99)
    SoftUpdate(other, tau=0.005)
    other.load_state_dict(state)
    for key, value in state.items():
        torch.testing.assert_close(other.state_dict()[key], value)
    td = batch()
    torch.manual_seed(7)
    a = loss(td)
    torch.manual_seed(7)
    b = other(td)
    for key, value in a.items():
        torch.testing.assert_close(value, b[key])


def test_same_seed_same_numbers():
    def run(seed):
        torch.manual_seed(seed)
        algo = BCQ(obs_dim=OBS, action_spec=SPEC, vae={"hidden": HIDDEN}, actor={"hidden": HIDDEN},
                   critic={"hidden": HIDDEN}, batch_size=6, epochs=1)
        metrics = [algo.update(batch(seed=i)) for i in range(3)]
        action = algo.policy(TensorDict({"observation": torch.ones(2, OBS)}, [2]))["action"]
        return metrics, action

    (m1, a1), (m2, a2), (m3, _) = run(11), run(11), run(12)
    for x, y in zip(m1, m2):
        for key in x:
            assert torch.equal(x[key], y[key]), key
    assert torch.equal(a1, a2)
    assert not torch.equal(m1[-1]["loss_qvalue"], m3[-1]["loss_qvalue"])


@pytest.mark.parametrize("vmap", [True, False])
def test_seed_batches_reduce_per_seed(vmap):
    torch.manual_seed(0)
    loss = bcq_loss(reduction="none", deactivate_vmap=not vmap)
    td = batch((3, 4))
    flat = td.reshape(-1)
    for method in ("vae_loss", "qvalue_loss", "actor_loss"):
        torch.manual_seed(1)
        seeded, meta = getattr(loss, method)(td)
        torch.manual_seed(1)
        flat_loss, _ = getattr(loss, method)(flat)
        assert seeded.shape == (3, 4), method
        assert all(v.shape == (3,) for v in meta.values()), method
        torch.testing.assert_close(seeded.reshape(-1), flat_loss)
        loss.reduction = "mean"
        torch.manual_seed(1)
        mean, _ = getattr(loss, method)(td)
        torch.testing.assert_close(mean, seeded.mean(-1).mean())
        loss.reduction = "none"


def test_vmap_and_loop_critics_agree():
    torch.manual_seed(0)
    loss = bcq_loss()
    td = batch((5,))
    torch.manual_seed(2)
    vmapped = loss.qvalue_loss(td)[0]
    loss.deactivate_vmap = True
    torch.manual_seed(2)
    looped = loss.qvalue_loss(td)[0]
    torch.testing.assert_close(vmapped, looped)


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="reduction"):
        bcq_loss(reduction="max")
    with pytest.raises(ValueError, match="lmbda"):
        bcq_loss(lmbda=1.5)
    with pytest.raises(ValueError, match="critics"):
        bcq_loss(qvalue=linear_critics(k=(1.0, 1.0)) + linear_critics(k=(1.0,), b=(0.0,)))


def test_update_runs_in_the_authors_order_and_counts_samples():
    torch.manual_seed(0)
    small = {"hidden": HIDDEN}
    algo = BCQ(obs_dim=OBS, action_spec=SPEC, vae=small, actor=small, critic=small, batch_size=100,
               epochs=300 / 1e6)
    calls = []
    for name in ("vae_loss", "qvalue_loss", "actor_loss"):
        method = getattr(algo.loss, name)
        setattr(algo.loss, name, lambda td, _m=method, _n=name: calls.append(_n) or _m(td))
    step, target_step = algo._step, algo.target_updater.step
    algo._step = lambda name, loss: calls.append(f"step {name}") or step(name, loss)
    algo.target_updater.step = lambda: calls.append("targets") or target_step()
    algo.update(batch())
    assert calls == ["vae_loss", "step vae", "qvalue_loss", "step critic", "actor_loss", "step actor", "targets"]
    assert isinstance(algo.target_updater, SoftUpdate) and algo.target_updater.eps == pytest.approx(0.995)
    # one epoch is 10^6 samples: 10^4 updates of 100; 300 samples -> 3 updates
    assert algo.samples_per_update == 100
    history = train(algo, batch((50,)), progress=False)
    assert history.iterations == 3


def test_algorithm_checkpoint_round_trip_resumes_identically():
    small = {"hidden": HIDDEN}

    def make(seed):
        torch.manual_seed(seed)
        return BCQ(obs_dim=OBS, action_spec=SPEC, vae=small, actor=small, critic=small, batch_size=6, epochs=1)

    a = make(0)
    for i in range(2):
        a.update(batch(seed=i))
    buffer = io.BytesIO()  # through bytes, as the trainer's checkpoint file (a live state_dict aliases tensors)
    torch.save(a.state_dict(), buffer)
    buffer.seek(0)
    b = make(1)
    b.load_state_dict(torch.load(buffer))
    for algo in (a, b):  # optimizers, targets and the fused target updater all follow the restored tensors
        torch.manual_seed(3)
        algo.metrics = [algo.update(batch(seed=10 + i)) for i in range(2)]
    for x, y in zip(a.metrics, b.metrics):
        for key in x:
            torch.testing.assert_close(x[key], y[key])
    for key, value in a.loss.state_dict().items():
        torch.testing.assert_close(b.loss.state_dict()[key], value)


def test_loss_mask_reduces_each_seed_over_its_own_points():
    torch.manual_seed(0)
    loss = bcq_loss(reduction="none")
    loss.loss_mask_key = "valid"
    td = batch((2, 3))
    td["valid"] = torch.tensor([[True, True, False], [True, False, False]])
    torch.manual_seed(1)
    none, _ = loss.qvalue_loss(td)
    assert none[0, 2] == 0 and (none[1, 1:] == 0).all() and (none[td["valid"]] > 0).all()
    loss.reduction = "mean"
    torch.manual_seed(1)
    mean, _ = loss.qvalue_loss(td)
    torch.testing.assert_close(mean, ((none[0, 0] + none[0, 1]) / 2 + none[1, 0]) / 2)

"""What only BCQ does: the soft target update, the critic target's maximum over perturbed VAE samples and the
actor loss by hand, the perturbation's range, argument checks and the update order (the contract suite in
test_contract.py covers gradients, keys, reductions, [S, B] batches, checkpoints and seeds)."""

from __future__ import annotations

import pytest
import torch
from _batch_rl_testing import (
    ACT,
    HIDDEN,
    OBS,
    SPEC,
    batch,
    bcq_loss,
    linear_critics,
    one_thread,  # noqa: F401 (autouse fixture)
    target_tensors,
)
from tensordict import TensorDict
from torchrl.objectives import SoftUpdate

from torchrl_bail.algorithms.bcq import BCQ
from torchrl_bail.configuration.config_builders import algo_config
from torchrl_bail.objectives.common import soft_clipped_double_q_target
from torchrl_bail.training.trainer import make_trainee, train


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


def test_perturbation_stays_within_phi_and_the_bounds():
    loss = bcq_loss(phi=0.05)
    candidate = SPEC.space.high.expand(7, ACT).clone()  # at the upper bound: only a downward move is allowed
    candidate[:3] = SPEC.space.low
    out = loss.actor_network(TensorDict({"observation": torch.randn(7, OBS), "action": candidate}, [7]))["action"]
    scale = (SPEC.space.high - SPEC.space.low) / 2
    assert ((out - candidate).abs() <= 0.05 * scale + 1e-6).all()
    assert ((out >= SPEC.space.low) & (out <= SPEC.space.high)).all()


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="lmbda"):
        bcq_loss(lmbda=1.5)
    with pytest.raises(ValueError, match="critics"):
        bcq_loss(qvalue=linear_critics(k=(1.0, 1.0)) + linear_critics(k=(1.0,), b=(0.0,)))


def test_update_runs_in_the_authors_order_and_counts_samples():
    torch.manual_seed(0)
    small = {"hidden": list(HIDDEN)}
    algo = BCQ(OBS, SPEC, algo_config("bcq", vae=small, actor=small, critic=small, batch_size=100, epochs=300 / 1e6))
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
    (history,) = train(make_trainee([algo], [batch((50,))]), progress=False)
    assert history.iterations == 3



"""What only BEAR does: the Laplacian MMD and the policy terms by hand, the multiplier's loss and clamp, the warm
start, the target actor's candidates, the action bounds and the update order (the contract suite in
test_contract.py covers gradients, keys, reductions, [S, B] batches, checkpoints and seeds)."""

from __future__ import annotations

import math

import pytest
import torch
from _batch_rl_testing import (
    ACT,
    HIDDEN,
    OBS,
    SPEC,
    batch,
    bear_loss,
    linear_critics,
    one_thread,  # noqa: F401 (autouse fixture)
)
from torchrl.objectives import SoftUpdate

from torchrl_bail.algorithms.bear import BEAR
from torchrl_bail.configuration.config_builders import algo_config
from torchrl_bail.objectives.bear import laplacian_mmd


def _algo(**overrides) -> BEAR:
    small = {"hidden": list(HIDDEN)}
    return BEAR(OBS, SPEC, algo_config("bear", vae=small, actor=small, critic=small, batch_size=6, **overrides))



def test_laplacian_mmd_by_hand():
    x = torch.tensor([[[0.0, 1.0], [2.0, -1.0]]])  # one state: N = 2 samples in 2-d
    y = torch.tensor([[[1.0, 1.0]]])  # M = 1 sample
    sigma = 2.0

    def k(u, v):
        return math.exp(-sum(abs(a - b) for a, b in zip(u, v, strict=True)) / (2 * sigma))

    xs, ys = x[0].tolist(), y[0].tolist()
    kxx = sum(k(u, v) for u in xs for v in xs) / 4
    kyy = 1.0
    kxy = sum(k(u, v) for u in xs for v in ys) / 2
    expected = math.sqrt(kxx + kyy - 2 * kxy + 1e-6)
    torch.testing.assert_close(laplacian_mmd(x, y, sigma), torch.tensor([expected]))
    # identical sample sets: only the stabilizer is left; a batch of states keeps its shape
    same = torch.randn(3, 4, 5, ACT)
    torch.testing.assert_close(laplacian_mmd(same, same.clone(), 10.0), torch.full((3, 4), 1e-3))
    assert (laplacian_mmd(torch.randn(7, 5, ACT), torch.randn(7, 5, ACT), 10.0) > 1e-3).all()


def test_policy_terms_use_pre_tanh_samples_clipped_noise_and_the_min_of_mean_qs():
    # Q1 = 2 a_0, Q2 = -a_0 + 1 (version 0: min over critics of the per-critic mean over samples)
    loss = bear_loss(qvalue=linear_critics(k=(2.0, -1.0), b=(0.0, 1.0)), kernel_sigma=10.0, num_samples_match=5)
    td = batch()
    obs = td["observation"]
    torch.manual_seed(4)
    terms = loss.policy_terms(td)
    torch.manual_seed(4)
    with torch.no_grad():
        _, vae_raw = loss.vae_network.sample(obs, 5)
        loc, scale = loss._loc_scale(obs, loss.actor_network_params)
        noise = torch.randn(6, 5, ACT).clamp(-0.5, 0.5)
    raw = loc.unsqueeze(-2) + scale.unsqueeze(-2) * noise
    actions = SPEC.space.low + (SPEC.space.high - SPEC.space.low) * (torch.tanh(raw) + 1) / 2
    torch.testing.assert_close(terms["mmd"], laplacian_mmd(vae_raw, raw, 10.0))
    expected_q = torch.minimum(2 * actions[..., 0].mean(-1), 1 - actions[..., 0].mean(-1))
    torch.testing.assert_close(terms["policy_q"], expected_q)
    # the noise clip bounds the raw samples around the mean
    _, raw_samples = loss._actor_samples(obs, 50, loss.actor_network_params, noise_clip=0.5)
    assert ((raw_samples - loc.unsqueeze(-2)).abs() <= 0.5 * scale.unsqueeze(-2) + 1e-6).all()


def test_alpha_loss_by_hand_and_its_gradient():
    torch.manual_seed(0)
    loss = bear_loss(log_alpha_init=0.3, epsilon=0.05)
    terms = {"mmd": torch.tensor([0.2, 0.01]), "policy_q": torch.tensor([1.0, -3.0])}
    alpha = math.exp(0.3)
    loss_alpha, meta = loss.alpha_loss(batch((2,)), terms)
    torch.testing.assert_close(loss_alpha, torch.tensor(((1.0 - alpha * 0.15) + (-3.0 + alpha * 0.04)) / 2))
    torch.testing.assert_close(meta["alpha"], torch.tensor(alpha))
    loss_alpha.backward()
    # d/dlog_alpha = -alpha * mean(mmd - epsilon): log alpha rises while the MMD exceeds epsilon on average
    torch.testing.assert_close(loss.log_alpha.grad, torch.tensor(-alpha * (0.15 - 0.04) / 2))


def test_log_alpha_is_clamped():
    loss = bear_loss(log_alpha_init=0.0, log_alpha_min=-5.0, log_alpha_max=10.0)
    for value, expected in [(20.0, 10.0), (-20.0, -5.0), (3.0, 3.0)]:
        with torch.no_grad():
            loss.log_alpha.fill_(value)
        loss.clamp_log_alpha_()
        assert loss.log_alpha.item() == expected
    algo = _algo(log_alpha_init=50.0, log_alpha_max=10.0)
    algo.update(batch())
    assert algo.loss.log_alpha.item() == 10.0


def test_warm_start_switches_the_actor_objective_after_n_updates():
    torch.manual_seed(0)
    loss = bear_loss(warm_start_updates=2, log_alpha_init=0.5)
    td = batch()
    terms = {k: v.detach() for k, v in loss.policy_terms(td).items()}
    alpha = math.exp(0.5)
    warm = (alpha * terms["mmd"]).mean()
    full = (alpha * terms["mmd"] - terms["policy_q"]).mean()
    for count, expected, flag in [(0, warm, 1.0), (1, warm, 1.0), (2, full, 0.0), (3, full, 0.0)]:
        assert loss.update_count.item() == count
        loss_actor, meta = loss.actor_loss(td, terms)
        torch.testing.assert_close(loss_actor, expected)
        assert meta["warm_start"].item() == flag
        loss.count_update()
    algo = _algo(warm_start_updates=1)
    flags = [algo.update(batch(seed=i))["warm_start"].item() for i in range(3)]
    assert flags == [1.0, 0.0, 0.0] and algo.loss.update_count.item() == 3


def test_target_candidates_come_from_the_target_actor():
    torch.manual_seed(0)
    loss = bear_loss()
    SoftUpdate(loss, tau=0.005)
    obs = torch.randn(4, OBS)
    with torch.no_grad():
        for p in loss.actor_network_params.parameters():
            p.add_(1.0)  # the current actor moves, its target does not

    def draw(fn):
        torch.manual_seed(9)
        with torch.no_grad():
            return fn(obs, 10)

    target = draw(loss._target_candidates)
    assert target.shape == (4, 10, ACT)
    target_samples = draw(lambda o, n: loss._actor_samples(o, n, loss.target_actor_network_params)[0])
    torch.testing.assert_close(target, target_samples)
    assert not torch.allclose(target, draw(loss.candidate_actions))


def test_action_bounds_come_from_the_actor_spec_or_fail_clearly():
    loss = bear_loss()
    torch.testing.assert_close(loss.action_scale, torch.tensor([1.0, 0.4]))
    from torchrl_bail.modules import make_qvalue_network, make_vae
    from torchrl_bail.objectives.bear import BEARLoss

    bare_actor = torch.nn.Linear(OBS, 2 * ACT)
    with pytest.raises(ValueError, match="action_spec"):
        BEARLoss(bare_actor, [make_qvalue_network(OBS, ACT, HIDDEN)] * 2, make_vae(OBS, SPEC, HIDDEN, latent_dim=4))


def test_update_runs_in_the_authors_order():
    torch.manual_seed(0)
    algo = _algo()
    calls = []
    for name in ("vae_loss", "qvalue_loss", "policy_terms", "actor_loss", "alpha_loss", "clamp_log_alpha_",
                 "count_update"):
        method = getattr(algo.loss, name)
        setattr(algo.loss, name, lambda *a, _m=method, _n=name: calls.append(_n) or _m(*a))
    step, target_step = algo._step, algo.target_updater.step
    def logged_step(names, loss):
        calls.append(f"step {'+'.join([names] if isinstance(names, str) else names)}")
        return step(names, loss)

    algo._step = logged_step
    algo.target_updater.step = lambda: calls.append("targets") or target_step()
    algo.update(batch())
    assert calls == ["vae_loss", "step vae", "qvalue_loss", "step critic", "policy_terms", "actor_loss",
                     "alpha_loss", "step actor+alpha", "clamp_log_alpha_", "count_update", "targets"]
    assert sorted(algo.optimizers) == ["actor", "alpha", "critic", "vae"]
    assert algo.optimizers["alpha"].param_groups[0]["params"] == [algo.loss.log_alpha]


def test_state_written_with_the_old_spelling_still_loads(tmp_path):
    """Checkpoints and BEAR policy files from before the one spelling (``mmd_stabiliser``) load, and the config of
    such a run still compares equal for resume and groups alike in the report."""
    from torchrl_bail.report import _read_config
    from torchrl_bail.training.resume import _comparable

    algo = _algo()
    state = algo.state_dict()
    old = {("mmd_stabiliser" if k == "mmd_stabilizer" else k): v for k, v in state["modules"]["loss"].items()}
    assert "mmd_stabiliser" in old
    fresh = _algo(mmd_stabilizer=0.5)
    fresh.load_state_dict({**state, "modules": {"loss": old}})
    assert float(fresh.loss.mmd_stabilizer) == float(algo.loss.mmd_stabilizer)
    assert _comparable({"algo": {"name": "bear", "mmd_stabiliser": 1e-6}}) == \
        {"algo": {"name": "bear", "mmd_stabilizer": 1e-6}}
    (tmp_path / "config.yaml").write_text("algo:\n  name: bear\n  mmd_stabiliser: 1.0e-06\n")
    assert _read_config(tmp_path)["algo.mmd_stabilizer"] == 1e-6 and "algo.mmd_stabiliser" not in _read_config(tmp_path)

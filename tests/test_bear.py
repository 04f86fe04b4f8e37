"""BEARLoss and the BEAR algorithm: gradient isolation (log alpha included), the Laplacian MMD by hand, the
multiplier's loss and clamp, the warm start, targets, the policy, state_dict, seeds, [S, B] batches, update order."""

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
    groups_with_grad,
    linear_critics,
    one_thread,  # noqa: F401 (autouse fixture)
    target_tensors,
    zero_grads,
)
from tensordict import TensorDict
from torchrl.objectives import SoftUpdate

from torchrl_bail.algorithms.bear import BEAR
from torchrl_bail.objectives.bear import laplacian_mmd

LOSS_KEYS = ("loss_vae", "loss_qvalue", "loss_actor", "loss_alpha")


def _algo(**kwargs) -> BEAR:
    small = {"hidden": HIDDEN}
    return BEAR(obs_dim=OBS, action_spec=SPEC, vae=small, actor=dict(small), critic=small, batch_size=6, epochs=1,
                **kwargs)



def test_outputs_are_scalars_and_diagnostics_carry_no_graph():
    torch.manual_seed(0)
    out = bear_loss()(batch())
    assert set(out.keys()) == {*LOSS_KEYS, "recon_loss", "kl_loss", "q_mean", "target_value_mean", "mmd",
                               "actor_q_mean", "alpha", "warm_start"}
    for key, value in out.items():
        assert value.shape == ()
        assert value.requires_grad == key.startswith("loss"), key


@pytest.mark.parametrize("warm", [True, False])
@pytest.mark.parametrize("term,group", [("loss_vae", "vae_network_params"), ("loss_qvalue", "qvalue_network_params"),
                                        ("loss_actor", "actor_network_params"), ("loss_alpha", "log_alpha")])
def test_each_loss_reaches_only_its_parameters(term, group, warm):
    torch.manual_seed(0)
    loss = bear_loss(warm_start_updates=1 if warm else 0)
    SoftUpdate(loss, tau=0.005)
    zero_grads(loss)
    out = loss(batch())
    assert out["warm_start"].item() == float(warm)
    out[term].backward()
    assert groups_with_grad(loss) == {group}
    for name, target in target_tensors(loss).items():
        assert not target.requires_grad and target.grad is None, name


def test_laplacian_mmd_by_hand():
    x = torch.tensor([[[0.0, 1.0], [2.0, -1.0]]])  # one state: N = 2 samples in 2-d
    y = torch.tensor([[[1.0, 1.0]]])  # M = 1 sample
    sigma = 2.0

    def k(u, v):
        return math.exp(-sum(abs(a - b) for a, b in zip(u, v)) / (2 * sigma))

    xs, ys = x[0].tolist(), y[0].tolist()
    kxx = sum(k(u, v) for u in xs for v in xs) / 4
    kyy = 1.0
    kxy = sum(k(u, v) for u in xs for v in ys) / 2
    expected = math.sqrt(kxx + kyy - 2 * kxy + 1e-6)
    torch.testing.assert_close(laplacian_mmd(x, y, sigma), torch.tensor([expected]))
    # identical sample sets: only the stabiliser is left; a batch of states keeps its shape
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


def test_target_bootstraps_a_truncation_but_not_a_termination():
    loss = bear_loss(qvalue=linear_critics(k=(0.0, 0.0), b=(1.0, 3.0)), gamma=0.9, reduction="none")
    td = batch((3,), terminated=torch.tensor([False, False, True]), truncated=torch.tensor([False, True, False]),
               reward=torch.tensor([0.5, 0.5, 0.5]))
    y = torch.tensor([0.5 + 0.9 * 1.5, 0.5 + 0.9 * 1.5, 0.5])
    loss_qvalue, _ = loss.qvalue_loss(td)
    torch.testing.assert_close(loss_qvalue, (1.0 - y) ** 2 + (3.0 - y) ** 2)


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
    torch.testing.assert_close(target, draw(lambda o, n: loss._actor_samples(o, n, loss.target_actor_network_params)[0]))
    assert not torch.allclose(target, draw(loss.candidate_actions))


def test_policy_plays_the_argmax_q1_actor_sample_within_bounds():
    loss = bear_loss(qvalue=linear_critics(k=(-1.0, 1.0)))
    policy = loss.policy(num_samples=10)
    observation = torch.randn(5, OBS)
    torch.manual_seed(3)
    with torch.no_grad():
        candidates = loss.candidate_actions(observation, 10)
    expected = candidates[torch.arange(5), candidates[..., 0].argmin(-1)]
    torch.manual_seed(3)
    action = policy(TensorDict({"observation": observation}, [5]))["action"]
    torch.testing.assert_close(action, expected)
    low, high = SPEC.space.low, SPEC.space.high
    assert ((action >= low) & (action <= high)).all() and action.shape == (5, ACT)
    assert policy(TensorDict({"observation": torch.randn(OBS)}, []))["action"].shape == (ACT,)


def test_state_dict_round_trip_keeps_multiplier_and_clock():
    torch.manual_seed(0)
    loss = bear_loss(warm_start_updates=7)
    SoftUpdate(loss, tau=0.005)
    loss.count_update(3)
    with torch.no_grad():
        loss.log_alpha.fill_(1.25)
        for p in loss.parameters():
            p.add_(0.1)
    state = loss.state_dict()
    assert state["update_count"].item() == 3 and state["warm_start_updates"].item() == 7
    torch.manual_seed(1)
    other = bear_loss(warm_start_updates=100)
    SoftUpdate(other, tau=0.005)
    other.load_state_dict(state)
    assert other.log_alpha.item() == pytest.approx(1.35) and other.update_count.item() == 3
    td = batch()
    torch.manual_seed(7)
    a = loss(td)
    torch.manual_seed(7)
    b = other(td)
    for key, value in a.items():
        torch.testing.assert_close(value, b[key])


def test_same_seed_same_numbers_including_the_multiplier_init():
    def run(seed):
        torch.manual_seed(seed)
        algo = _algo(warm_start_updates=1)
        log_alpha = algo.loss.log_alpha.item()
        metrics = [algo.update(batch(seed=i)) for i in range(3)]
        return log_alpha, metrics

    (la1, m1), (la2, m2), (la3, m3) = run(5), run(5), run(6)
    assert la1 == la2 != la3
    for x, y in zip(m1, m2):
        for key in x:
            assert torch.equal(x[key], y[key]), key
    assert not torch.equal(m1[-1]["loss_actor"], m3[-1]["loss_actor"])


def test_seed_batches_reduce_per_seed():
    torch.manual_seed(0)
    loss = bear_loss(reduction="none", warm_start_updates=0)
    td = batch((3, 4))
    flat = td.reshape(-1)
    torch.manual_seed(1)
    seeded = loss(td)
    torch.manual_seed(1)
    flat_out = loss(flat)
    for key in LOSS_KEYS:
        assert seeded[key].shape == (3, 4), key
        torch.testing.assert_close(seeded[key].reshape(-1), flat_out[key])
    assert seeded["mmd"].shape == (3,)
    loss.reduction = "mean"
    torch.manual_seed(1)
    mean = loss(td)
    for key in LOSS_KEYS:
        torch.testing.assert_close(mean[key], seeded[key].mean(-1).mean())


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
    algo._step = lambda name, loss: calls.append(f"step {name}") or step(name, loss)
    algo.target_updater.step = lambda: calls.append("targets") or target_step()
    algo.update(batch())
    assert calls == ["vae_loss", "step vae", "qvalue_loss", "step critic", "policy_terms", "actor_loss",
                     "alpha_loss", "step actor", "step alpha", "clamp_log_alpha_", "count_update", "targets"]
    assert sorted(algo.optimizers) == ["actor", "alpha", "critic", "vae"]
    assert algo.optimizers["alpha"].param_groups[0]["params"] == [algo.loss.log_alpha]

"""The behaviour agents. SAC: log-probabilities on the unscaled tanh output (as sac_adapt), bound-1 envs unchanged,
the soft-Q target, the actor and alpha losses with hand-computed values, the recipe hashes. SAC and DDPG: the
updates' plain-tensor losses are TorchRL's SACLoss / DDPGLoss numbers."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from torch.distributions import Normal
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import TanhNormal

from torchrl_bail.behaviour.ddpg import DDPGAgent
from torchrl_bail.behaviour.sac import SACAgent
from torchrl_bail.data.cache import sac_identity
from torchrl_bail.modules import action_spec_from_bounds, make_sac_actor

OBS, ACT, N = 5, 3, 16


def _spec(bound: float):
    return action_spec_from_bounds([-bound] * ACT, [bound] * ACT)


def _batch(bound: float, seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    return TensorDict({
        "observation": torch.randn(N, OBS, generator=g),
        "action": (torch.rand(N, ACT, generator=g) * 2 - 1) * bound,
        "next": {"observation": torch.randn(N, OBS, generator=g), "reward": torch.randn(N, 1, generator=g),
                 "done": torch.zeros(N, 1, dtype=torch.bool),
                 "terminated": torch.tensor([[i % 5 == 0] for i in range(N)]),
                 "truncated": torch.zeros(N, 1, dtype=torch.bool)},
    }, [N])


def _agent(bound: float, log_prob_on: str = "tanh", seed: int = 0) -> SACAgent:
    torch.manual_seed(seed)
    return SACAgent(OBS, _spec(bound), actor_hidden=(16, 16), critic_hidden=(16, 16), log_prob_on=log_prob_on)


def _dist(actor, observation):
    with set_exploration_type(ExplorationType.RANDOM):
        return actor.get_dist(TensorDict({"observation": observation}, [observation.shape[0]]))


def test_log_prob_of_scaled_action_is_the_unscaled_tanh_log_prob():
    torch.manual_seed(1)
    actor = make_sac_actor(OBS, _spec(0.4), (16, 16), log_prob_on="tanh")
    obs = torch.randn(N, OBS)
    dist = _dist(actor, obs)
    unscaled = TanhNormal(dist.loc, dist.scale)  # the authors' policy on [-1, 1]
    torch.manual_seed(7)
    action, log_prob = dist.rsample_and_log_prob()
    torch.manual_seed(7)
    unit, unit_log_prob = unscaled.rsample_and_log_prob()
    assert torch.equal(action, 0.4 * unit) and action.abs().max() <= 0.4
    assert torch.equal(log_prob, unit_log_prob)  # same draw, same numbers
    torch.testing.assert_close(dist.log_prob(action), unscaled.log_prob(unit), rtol=1e-5, atol=1e-4)
    # TorchRL's density of the scaled action differs by exactly sum(log 0.4) (the term this agent drops)
    scaled = TanhNormal(dist.loc, dist.scale, low=-0.4, high=0.4)
    torch.testing.assert_close(scaled.log_prob(action), unit_log_prob - ACT * math.log(0.4), rtol=1e-5, atol=1e-4)


def test_bound_one_agent_gives_the_same_numbers_either_way():
    """Hopper, Walker2d, HalfCheetah, Ant: ``log_prob_on`` changes nothing (same losses, same weights)."""
    agents = [_agent(1.0, on) for on in ("tanh", "action")]
    assert agents[0].target_entropy == agents[1].target_entropy == -float(ACT)
    outs = []
    for agent in agents:
        torch.manual_seed(3)
        outs.append([{k: float(v) for k, v in agent.update(_batch(1.0, seed=j)).items()} for j in range(3)])
    assert outs[0] == outs[1]
    for (k, a), (_, b) in zip(agents[0].loss.state_dict().items(), agents[1].loss.state_dict().items(), strict=True):
        assert torch.equal(a, b), k


def test_target_entropy_is_minus_action_dim_on_the_tanh_output():
    assert _agent(0.4).target_entropy == -float(ACT)
    assert _agent(0.4, "action").target_entropy == pytest.approx(-ACT + ACT * math.log(0.4))


def _q(agent, index, obs, action, target=False):
    params = agent.loss.target_qvalue_network_params if target else agent.loss.qvalue_network_params
    with params[index].to_module(agent.qvalue):
        td = agent.qvalue(TensorDict({"observation": obs, "action": action}, [obs.shape[0]]))
    return td["state_action_value"].squeeze(-1)


def _hand_sample(agent, obs):
    """A draw as the authors' SAC makes it: u ~ N(mu, sigma), y = tanh(u), log pi(y), action 0.4 * y."""
    dist = _dist(agent.actor, obs)
    u = Normal(dist.loc, dist.scale).rsample()
    y = torch.tanh(u)
    log_pi = Normal(dist.loc, dist.scale).log_prob(u).sum(-1) - torch.log1p(-y.pow(2)).sum(-1)
    return 0.4 * y, log_pi


@pytest.mark.parametrize("log_prob_on", ["tanh", "action"])
def test_sac_loss_uses_the_unscaled_log_prob_in_target_actor_and_alpha(log_prob_on):
    agent = _agent(0.4, log_prob_on)
    with torch.no_grad():
        agent.loss.log_alpha.fill_(math.log(0.7))
    batch = _batch(0.4)
    torch.manual_seed(11)
    out = agent.loss(batch.clone())
    torch.manual_seed(11)  # SACLoss draws the next-state action first, then the actor-loss action
    with torch.no_grad():
        next_action, next_log_pi = _hand_sample(agent, batch["next", "observation"])
        action, log_pi = _hand_sample(agent, batch["observation"])
    alpha = 0.7
    s2 = batch["next", "observation"]
    soft_v = torch.min(_q(agent, 0, s2, next_action, True), _q(agent, 1, s2, next_action, True)) - alpha * next_log_pi
    target = batch["next", "reward"].squeeze(-1) + 0.99 * (~batch["next", "terminated"].squeeze(-1)) * soft_v
    s, a = batch["observation"], batch["action"]
    loss_q = ((_q(agent, 0, s, a) - target).pow(2) + (_q(agent, 1, s, a) - target).pow(2)).mean()
    loss_actor = (alpha * log_pi - torch.min(_q(agent, 0, s, action), _q(agent, 1, s, action))).mean()
    loss_alpha = (-math.log(0.7) * (log_pi + agent.target_entropy)).mean()
    matches = [torch.allclose(out[k].detach(), v.detach(), rtol=1e-4, atol=1e-4)
               for k, v in (("loss_qvalue", loss_q), ("loss_actor", loss_actor), ("loss_alpha", loss_alpha))]
    # the faithful agent matches the hand-computed sac_adapt losses; TorchRL's scaled density does not
    assert matches == ([True] * 3 if log_prob_on == "tanh" else [False] * 3)


def test_log_prob_on_is_hashed_only_where_the_bound_is_not_one():
    block = {"gamma": 0.99, "log_prob_on": "tanh"}
    assert sac_identity(block, "Hopper-v5") == sac_identity({**block, "log_prob_on": "action"}, "Hopper-v5")
    assert sac_identity(block, "Hopper-v5") == {"gamma": 0.99}  # the hash it had before the key existed
    assert sac_identity(block, "Humanoid-v5") != sac_identity({**block, "log_prob_on": "action"}, "Humanoid-v5")
    assert sac_identity({"gamma": 0.99}, "Humanoid-v5") == block  # absent means tanh, the default


def test_unknown_log_prob_on_is_one_clear_error():
    with pytest.raises(ValueError, match="log_prob_on"):
        make_sac_actor(OBS, _spec(0.4), (16, 16), log_prob_on="scaled")


@pytest.mark.parametrize("bound", [1.0, 0.4])
def test_fast_losses_are_sac_loss_numbers_and_gradients(bound):
    """``SACAgent.losses`` (the update's plain-tensor path) == TorchRL's ``SACLoss`` forward, values and gradients."""
    agent = _agent(bound)
    with torch.no_grad():
        agent.loss.log_alpha.fill_(math.log(0.7))
    batch = _batch(bound)
    results = []
    for compute in (agent.losses, agent.loss):
        torch.manual_seed(5)
        out = compute(batch.clone())
        agent.loss.zero_grad(set_to_none=True)
        (out["loss_qvalue"] + out["loss_actor"] + out["loss_alpha"]).backward()
        grads = [p.grad.clone() for p in agent.loss.parameters() if p.grad is not None]
        results.append(([out[k].detach() for k in ("loss_qvalue", "loss_actor", "loss_alpha", "alpha")], grads))
    (fast, fast_grads), (ref, ref_grads) = results
    assert len(fast_grads) == len(ref_grads) > 0
    for a, b in zip(fast + fast_grads, ref + ref_grads, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)


def test_update_steps_match_a_sac_loss_update():
    """Five updates of the agent == five updates driven by ``SACLoss`` itself (same optimizers and target step)."""
    agents = [_agent(0.4), _agent(0.4)]
    reference = agents[1]
    reference.losses = reference.loss  # the plain TorchRL forward
    for agent in agents:
        torch.manual_seed(9)
        for k in range(5):
            out = agent.update(_batch(0.4, seed=k))
        assert set(out) == {"loss_qvalue", "loss_actor", "alpha"} and all(v.dim() == 0 for v in out.values())
    for (key, a), (_, b) in zip(agents[0].loss.state_dict().items(), agents[1].loss.state_dict().items(), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6, msg=key)


@pytest.mark.parametrize("bound,arch", [(1.0, "late_action"), (0.4, "concat")])
def test_ddpg_updates_are_ddpg_loss_updates(bound, arch):
    """``DDPGAgent.update`` (plain-tensor losses) == the same steps on TorchRL's ``DDPGLoss``, over several updates
    (so the target copies follow the soft updates)."""

    def agent():
        torch.manual_seed(0)
        return DDPGAgent(OBS, _spec(bound), actor_hidden=(16, 16), critic_hidden=(16, 12), critic_arch=arch)

    fast, reference = agent(), agent()
    reference.loss_value = lambda batch: reference.loss.loss_value(batch)[0]
    reference.loss_actor = lambda batch: reference.loss.loss_actor(batch)[0]
    outs = []
    for a in (fast, reference):
        outs.append([a.update(_batch(bound, seed=k)) for k in range(4)])
    for x, y in zip(outs[0], outs[1], strict=True):
        torch.testing.assert_close(x, y, rtol=1e-5, atol=1e-6)
    for (key, a), (_, b) in zip(fast.loss.state_dict().items(), reference.loss.state_dict().items(), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6, msg=key)
    assert not torch.equal(fast.loss.target_value_network_params["module", "l3" if arch == "late_action" else "4",
                                                                   "weight"],
                           fast.critic.module.state_dict()["l3.weight" if arch == "late_action" else "4.weight"])


@pytest.mark.parametrize("deterministic", [False, True])
def test_sac_act_is_the_actor_module_action(deterministic):
    agent = _agent(0.4)
    obs = torch.randn(OBS)
    mode = ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM
    torch.manual_seed(2)
    action = agent.act(obs, deterministic=deterministic)
    torch.manual_seed(2)
    with torch.no_grad(), set_exploration_type(mode):
        expected = agent.actor(TensorDict({"observation": obs}, []))["action"]
    assert torch.equal(action, expected) and action.abs().max() <= 0.4


@pytest.mark.parametrize("bound", [1.0, 0.4])
def test_ddpg_act_is_the_actor_module_action(bound):
    torch.manual_seed(0)
    agent = DDPGAgent(OBS, _spec(bound), actor_hidden=(16, 16), critic_hidden=(16, 12))
    obs = torch.randn(4, OBS)
    with torch.no_grad():
        expected = agent.actor(TensorDict({"observation": obs}, [4]))["action"]
    assert torch.equal(agent.act(obs), expected)


def test_episode_store_sample_is_the_replay_buffer_sample(tmp_path):
    """The agents' fast mini-batches: the rows TorchRL's RandomSampler would give, the same RNG draws after."""
    from torchrl_bail.behaviour.buffers import EpisodeStore

    store = EpisodeStore(64, tmp_path, batch_size=7)
    with pytest.raises(RuntimeError, match="empty"):
        store.sample()
    data = _batch(1.0).set("episode", torch.zeros(N, dtype=torch.int64))
    store.extend(data)
    store.extend(_batch(1.0, seed=1).set("episode", torch.ones(N, dtype=torch.int64)))
    for size in (None, 11):
        torch.manual_seed(5)
        expected = store.rb.sample() if size is None else store.rb.sample(size)
        after_expected = torch.rand(3)
        torch.manual_seed(5)
        got = store.sample(size)
        assert torch.equal(torch.rand(3), after_expected)
        assert got.batch_size == expected.batch_size == torch.Size([size or 7])
        assert set(got.keys(True, True)) == set(expected.exclude("index").keys(True, True))
        assert (got == expected.exclude("index")).all()
        assert type(got["next", "observation"]) is torch.Tensor  # gathered from views, not memmap tensors

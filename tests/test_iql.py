"""IQL: the paper's three losses by hand, the update's order, the locomotion reward scale (and that a resumed run
keeps it), the actor's cosine learning rate over the run (and across a resume), the clip the schema allows, a tiny
run from the command line with its export, and the one-line refusal of ``seeds=``.

The contract suite (tests/_contract.py) covers what every algorithm keeps (optimizers, bounds, same seed -> same
numbers, checkpoints, deep copies, a tiny run through the config and its policy.pt).
"""

from __future__ import annotations

import copy
import io
import json
import math
import subprocess
import sys

import pytest
import torch
from _batch_rl_testing import OBS, SPEC, one_thread  # noqa: F401 (autouse fixture)
from _contract import ALGO_CASES, TINY_RUN, equal_trees, loss_batch, refusal_line
from tensordict import TensorDict

from torchrl_bail.algorithms import PrepareContext
from torchrl_bail.algorithms.iql import IQL, episode_returns
from torchrl_bail.configuration.config import ConfigError
from torchrl_bail.configuration.config_builders import algo_config
from torchrl_bail.training.trainer import make_trainee, train

SMALL = {"actor": {"hidden": [8]}, "critic": {"hidden": [8]}, "value": {"hidden": [8]}, "batch_size": 16}
LR = 3e-4


def _algo(seed: int = 0, **overrides) -> IQL:
    torch.manual_seed(seed)
    return IQL(OBS, SPEC, algo_config("iql", **{**SMALL, **overrides}))


def _batch(seed: int = 1) -> TensorDict:
    """16 transitions: three terminal, two more truncated (done but not terminated: the TD target bootstraps)."""
    td = loss_batch((16,), seed=seed)
    td["next", "terminated"][:3] = True
    td["next", "truncated"][3:5] = True
    td["next", "done"] = td["next", "terminated"] | td["next", "truncated"]
    return td


def _episodes(rewards: list[float], episode: list[int]) -> TensorDict:
    """A batch of ``len(rewards)`` transitions with the given rewards and episode ids (the last row of each episode
    done)."""
    n = len(rewards)
    td = loss_batch((n,), seed=2)
    ids = torch.tensor(episode)
    done = torch.cat([ids[1:] != ids[:-1], torch.tensor([True])]).unsqueeze(-1)
    td["episode"] = ids
    td["next", "reward"] = torch.tensor(rewards).unsqueeze(-1)
    td["next", "terminated"], td["next", "truncated"], td["next", "done"] = done, torch.zeros_like(done), done
    return td


def _critic(algo: IQL, i: int, observation, action, target: bool = False) -> torch.Tensor:
    params = (algo.loss.target_qvalue_network_params if target else algo.loss.qvalue_network_params)[i]
    with params.to_module(algo.loss.qvalue_network):
        td = algo.loss.qvalue_network(TensorDict({"observation": observation, "action": action}, observation.shape[:1]))
    return td["state_action_value"].squeeze(-1)


def _value(algo: IQL, observation) -> torch.Tensor:
    with algo.loss.value_network_params.to_module(algo.loss.value_network):
        td = algo.loss.value_network(TensorDict({"observation": observation}, observation.shape[:1]))
    return td["state_value"].squeeze(-1)


def _log_prob(algo: IQL, observation, action) -> torch.Tensor:
    """log N(a; c + h tanh(MLP(s)), h exp(log_std)), summed over the action's dimensions, from the actor's weights."""
    params = algo.loss.actor_network_params
    net = algo.loss.actor_network.module[0].module  # GaussianActorParams: its weights come from ``params``
    with params.to_module(algo.loss.actor_network):
        hidden = net.net(observation)
        log_std = net.log_std.clamp(-5.0, 2.0)
    centre, half = (SPEC.space.high + SPEC.space.low) / 2, (SPEC.space.high - SPEC.space.low) / 2
    normal = torch.distributions.Normal(centre + half * torch.tanh(hidden), half * log_std.exp())
    return normal.log_prob(action).sum(-1)


@torch.no_grad()
def test_the_three_losses_are_the_papers_computed_by_hand():
    algo, batch = _algo(), _batch()
    obs, action, next_obs = batch["observation"], batch["action"], batch["next", "observation"]
    reward, terminated = batch["next", "reward"].squeeze(-1), batch["next", "terminated"].squeeze(-1).float()
    min_q = torch.minimum(*(_critic(algo, i, obs, action, target=True) for i in range(2)))
    bias = algo.loss.value_network_params.get(("module", "2", "bias"))  # the value MLP's last layer
    # V shifted twice: advantages of both signs around 0 (the expectile's two weights), then around log(100) / 3,
    # where about half the advantage weights exp(3 A) exceed the clip
    for centre in (0.0, math.log(100.0) / 3.0):
        bias.add_((min_q - _value(algo, obs)).median() - centre)
        advantage = min_q - _value(algo, obs)
        weights = torch.exp(3.0 * advantage)
        if centre == 0.0:
            assert (advantage > 0).any() and (advantage < 0).any()
        else:
            assert (weights > 100).any() and (weights < 100).any(), "the clip is not exercised"
        # value: the expectile loss |0.7 - 1(u < 0)| u^2, u = min Q'(s, a) - V(s)
        expected_value = torch.where(advantage > 0, 0.7, 0.3) * advantage**2
        torch.testing.assert_close(algo.loss.value_loss(batch.clone())[0], expected_value.mean())
        # actor: -min(exp(beta A), 100) log pi(a | s)
        expected_actor = -(weights.clamp(max=100.0) * _log_prob(algo, obs, action))
        torch.testing.assert_close(algo.loss.actor_loss(batch.clone())[0], expected_actor.mean())
    # critics: sum_i mean (Q_i(s, a) - y)^2, y = r + gamma (1 - terminated) V(s') (a truncated row bootstraps)
    target = reward + 0.99 * (1 - terminated) * _value(algo, next_obs)
    expected_critic = sum(((_critic(algo, i, obs, action) - target) ** 2).mean() for i in range(2))
    torch.testing.assert_close(algo.loss.qvalue_loss(batch.clone())[0], expected_critic)


def test_one_update_steps_value_then_actor_then_critics_then_the_targets():
    """The actor's and the critics' losses of an update read the value network after its step (the authors'
    order; the actor's and the critics' steps commute, as both read the target critics, which move last, by tau
    towards the stepped critics)."""
    algo, batch = _algo(), _batch()
    with torch.no_grad():  # targets away from the critics, so that tau shows in one update
        for target in algo.loss.target_qvalue_network_params.values(True, True):
            target.add_(torch.randn(target.shape, generator=torch.Generator().manual_seed(target.numel())))
    before = copy.deepcopy(algo)
    metrics = algo.update(batch.clone())
    assert sorted(metrics) == ["actor_lr", "loss_actor", "loss_qvalue", "loss_value"]
    torch.testing.assert_close(metrics["loss_value"], before.loss.value_loss(batch.clone())[0].detach())
    stepped_value = copy.deepcopy(before)
    stepped_value.loss.value_network_params.data.copy_(algo.loss.value_network_params.data)
    for name in ("loss_actor", "loss_qvalue"):
        method = {"loss_actor": "actor_loss", "loss_qvalue": "qvalue_loss"}[name]
        got, old_v = metrics[name], getattr(before.loss, method)(batch.clone())[0].detach()
        torch.testing.assert_close(got, getattr(stepped_value.loss, method)(batch.clone())[0].detach())
        assert not torch.allclose(got, old_v), f"{name} read the value network before its step"
    critics, targets = algo.loss.qvalue_network_params.data, algo.loss.target_qvalue_network_params.data
    old_targets = before.loss.target_qvalue_network_params.data
    assert (critics != before.loss.qvalue_network_params.data).any()
    torch.testing.assert_close(targets, old_targets + 0.005 * (critics - old_targets))


def test_locomotion_reward_scale_is_computed_from_the_episodes_and_kept_by_a_resume():
    # episodes 0 and 1: returns 1 + 2 + 3 = 6 and 4 + 10 = 14: rewards times 1000 / (14 - 6) = 125
    data = _episodes([1.0, 2.0, 3.0, 4.0, 10.0], [0, 0, 0, 1, 1])
    raw = data.clone()
    algo = _algo()
    prepared = algo.prepare(data, PrepareContext())
    assert algo.reward_factor == 125.0 and algo.summary() == {"reward_factor": 125.0}
    torch.testing.assert_close(prepared["next", "reward"], raw["next", "reward"] * 125.0)
    assert (data == raw).all(), "the caller's batch was changed"
    without_ids = data.exclude("episode")  # the episodes then come from ("next", "done")
    assert episode_returns(without_ids).tolist() == episode_returns(data).tolist() == [6.0, 14.0]
    # a resumed run applies the checkpoint's factor to the data it is given, without computing it again
    buffer = io.BytesIO()
    torch.save(algo.state_dict(), buffer)
    resumed = _algo(seed=3)
    resumed.load_state_dict(torch.load(io.BytesIO(buffer.getvalue()), weights_only=False))
    other = _episodes([1.0, 2.0, 3.0, 4.0, 100.0], [0, 0, 0, 1, 1])
    restored = resumed.restore_prepared(other, PrepareContext())
    torch.testing.assert_close(restored["next", "reward"], other["next", "reward"] * 125.0)
    plain = _algo(reward_scale="none")
    torch.testing.assert_close(plain.prepare(data, PrepareContext())["next", "reward"], raw["next", "reward"])
    with pytest.raises(ValueError, match="reward_scale=none"):
        _algo().prepare(_episodes([1.0, 2.0], [0, 0]), PrepareContext())


def _cosine(t: int, total: int) -> float:
    return LR * 0.5 * (1 + math.cos(math.pi * t / total))


def test_the_actors_learning_rate_follows_a_cosine_over_the_runs_updates():
    algo, batch = _algo(), _batch()
    algo.plan_updates(10)
    lrs = [float(algo.update(batch)["actor_lr"]) for _ in range(10)]
    assert lrs[0] == pytest.approx(LR) and lrs[5] == pytest.approx(LR / 2)  # start, middle
    assert lrs[-1] == pytest.approx(_cosine(9, 10)) and lrs[-1] < 0.03 * LR  # the last update: nearly 0
    assert lrs == pytest.approx([_cosine(t, 10) for t in range(10)])
    assert float(algo.optimizers["value"].param_groups[0]["lr"]) == pytest.approx(LR)  # only the actor's decays
    assert float(algo.optimizers["critic"].param_groups[0]["lr"]) == pytest.approx(LR)
    constant = _algo(actor={"hidden": [8], "lr_schedule": "constant"})
    constant.plan_updates(10)
    assert [float(constant.update(batch)["actor_lr"]) for _ in range(3)] == pytest.approx([LR] * 3)


def _loop_data() -> TensorDict:
    data = _episodes([float(r) for r in range(40)], [i // 10 for i in range(40)])
    return _algo().prepare(data, PrepareContext())


class _Stop(Exception):
    pass


def test_the_training_loop_sets_the_schedule_and_a_resumed_run_continues_it_exactly(tmp_path):
    """8 updates of 16 samples, evaluated every 2: a run killed in its second evaluation resumes from the
    checkpoint of the first and ends with the uninterrupted run's learning rates and weights."""
    data, epochs, per_epoch = _loop_data(), 8 * 16 / 100, 100

    def run(evaluate, resume_from=None, seed=0):
        algo = _algo(seed=seed, epochs=epochs)
        if resume_from is not None:
            algo.load_state_dict(resume_from["algorithm"])
        prepared = algo.restore_prepared(data, PrepareContext()) if resume_from else data
        lrs = []
        update = algo.update
        algo.update = lambda batch: lrs.append(float((out := update(batch))["actor_lr"])) or out
        torch.manual_seed(7)
        train(make_trainee([algo], [prepared]), evaluate=lambda policy: [evaluate(policy)], samples_per_epoch=per_epoch,
              eval_every_epochs=2 * 16 / 100, checkpoint_paths=[tmp_path / "checkpoint.pt"],
              resume_from=None if resume_from is None else [resume_from], progress=False)
        return algo, lrs

    full, full_lrs = run(lambda policy: 0.0)
    assert full.total_updates == 8 and full_lrs == pytest.approx([_cosine(t, 8) for t in range(8)])
    calls = []

    def killed(policy):
        calls.append(1)
        if len(calls) == 2:
            raise _Stop
        return 0.0

    with pytest.raises(_Stop):
        run(killed)
    checkpoint = torch.load(tmp_path / "checkpoint.pt", weights_only=False)
    assert checkpoint["iteration"] == 2 and checkpoint["algorithm"]["attributes"]["updates"] == 2
    resumed, resumed_lrs = run(lambda policy: 0.0, resume_from=checkpoint, seed=5)
    assert resumed_lrs == full_lrs[2:]
    equal_trees(resumed.state_dict(), full.state_dict())


def test_only_torchrls_clip_of_the_advantage_weights_is_accepted():
    with pytest.raises(ConfigError, match=r"algo\.max_weight = 50\.0: expected 100"):
        algo_config("iql", max_weight=50.0)


def test_a_tiny_run_from_the_command_line_and_its_export(tiny_run_data_dir, tmp_path):
    run_dir = tmp_path / "run"
    cmd = [sys.executable, "-m", "torchrl_bail.train", *TINY_RUN, "algo=iql", *ALGO_CASES["iql"].cli,
           f"data_dir={tiny_run_data_dir}", f"hydra.run.dir={run_dir}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["algo"] == "iql" and math.isfinite(summary["final_return"])
    assert summary["reward_factor"] > 0  # the tiny batch's episodes, scaled as the paper's locomotion runs
    out = tmp_path / "policy.pt2"
    proc = subprocess.run([sys.executable, "-m", "torchrl_bail.evaluate", str(run_dir), "--export", "pt2",
                           "--out", str(out)], capture_output=True, text=True, timeout=600, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    from torchrl_bail.evaluation.policy import load_policy, policy_actions

    policy = load_policy(run_dir)
    obs = torch.randn(5, policy.record["obs_dim"])
    expected = policy_actions(policy, obs)
    torch.testing.assert_close(torch.export.load(str(out)).module()(obs), expected, atol=1e-5, rtol=1e-5)


def test_seeds_are_refused_in_one_line():
    line = refusal_line("algo=iql", "seeds=[1,2]")
    assert "seeds = [1, 2]" in line and "algo=iql" in line and "log std" in line, line

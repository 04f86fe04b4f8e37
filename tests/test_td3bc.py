"""TD3+BC: the paper's losses by hand, the actor's delay, the batch's standardisation carried by the policy into
policy.pt and its exports, compiled updates (with ``TORCHRL_BAIL_FULL_COMPILE_TESTS=1``), and the one-line refusal
of ``seeds=``.

The contract suite (tests/_contract.py) covers what every algorithm keeps (optimizers, bounds, same seed -> same
numbers, checkpoints, deep copies, a tiny run through the config and its policy.pt).
"""

from __future__ import annotations

import io
import os

import pytest
import torch
import torch.nn.functional as F
from _batch_rl_testing import OBS, one_thread  # noqa: F401 (autouse fixture)
from _contract import loss_batch, refusal_line
from tensordict import TensorDict

from torchrl_bail.algorithms import PrepareContext
from torchrl_bail.algorithms.td3bc import TD3BC
from torchrl_bail.configuration.config_builders import algo_config
from torchrl_bail.modules import action_spec_from_bounds

#: bounds +-2: the target policy's noise is 0.2 * 2 with a clip of 0.5 * 2
SPEC = action_spec_from_bounds([-2.0, -2.0], [2.0, 2.0])
SMALL = {"actor": {"hidden": [8]}, "critic": {"hidden": [8]}, "batch_size": 16}


def _algo(seed: int = 0, **overrides) -> TD3BC:
    torch.manual_seed(seed)
    return TD3BC(OBS, SPEC, algo_config("td3bc", **{**SMALL, **overrides}))


def _batch(seed: int = 1) -> TensorDict:
    td = loss_batch((16,), seed=seed)
    td["action"] = td["action"].clamp(-1, 1) * 2
    td["next", "terminated"][:3] = True
    td["next", "done"] = td["next", "terminated"] | td["next", "truncated"]
    return td


def _critic(algo: TD3BC, i: int, observation, action, target: bool = False) -> torch.Tensor:
    params = (algo.loss.target_qvalue_network_params if target else algo.loss.qvalue_network_params)[i]
    with params.to_module(algo.loss.qvalue_network):
        td = algo.loss.qvalue_network(TensorDict({"observation": observation, "action": action}, observation.shape[:1]))
    return td["state_action_value"].squeeze(-1)


def _actor(algo: TD3BC, observation, target: bool = False) -> torch.Tensor:
    params = algo.loss.target_actor_network_params if target else algo.loss.actor_network_params
    with params.to_module(algo.loss.actor_network):
        return algo.loss.actor_network(TensorDict({"observation": observation}, observation.shape[:1]))["action"]


@torch.no_grad()
def test_critic_and_actor_losses_are_the_papers_computed_by_hand():
    algo, batch = _algo(), _batch()
    obs, action, next_obs = batch["observation"], batch["action"], batch["next", "observation"]
    reward, terminated = batch["next", "reward"].squeeze(-1), batch["next", "terminated"].squeeze(-1).float()
    torch.manual_seed(3)
    noise = (torch.randn_like(action) * 0.2 * 2).clamp(-0.5 * 2, 0.5 * 2)  # times max_action = 2
    next_action = (_actor(algo, next_obs, target=True) + noise).clamp(-2, 2)
    next_q = torch.minimum(*(_critic(algo, i, next_obs, next_action, target=True) for i in range(2)))
    target = reward + 0.99 * (1 - terminated) * next_q
    expected = sum(F.mse_loss(_critic(algo, i, obs, action), target) for i in range(2))
    torch.manual_seed(3)
    with torch.enable_grad():
        got = algo.loss.qvalue_loss(batch)[0]
    torch.testing.assert_close(got, expected)
    pi = _actor(algo, obs)
    q = _critic(algo, 0, obs, pi)
    expected_actor = -(2.5 / q.abs().mean()) * q.mean() + F.mse_loss(pi, action)
    torch.testing.assert_close(algo.loss.actor_loss(batch)[0], expected_actor)


def test_the_actor_and_the_targets_move_every_second_update_and_the_count_is_checkpointed():
    algo, batch = _algo(), _batch()

    def snapshot():
        loss = algo.loss
        return {name: params.clone() for name, params in [
            ("actor", loss.actor_network_params), ("critic", loss.qvalue_network_params),
            ("targets", loss.target_actor_network_params.clone().update(loss.target_qvalue_network_params))]}

    before = snapshot()
    steps = []
    for update in range(1, 5):
        metrics = algo.update(batch)
        after = snapshot()
        moved = {name: not (after[name] == before[name]).all() for name in before}
        assert moved == {"actor": update % 2 == 0, "critic": True, "targets": update % 2 == 0}, update
        steps.append(float(metrics["actor_step"]))
        assert sorted(metrics) == ["actor_step", "bc_loss", "lmbd", "loss_actor", "loss_qvalue", "q_actor",
                                   "target_value"]
        before = after
    assert steps == [0.0, 1.0, 0.0, 1.0]
    algo.update(batch)  # the fifth: a critic step; a checkpoint taken now resumes with the actor's step next
    buffer = io.BytesIO()  # through bytes, as a checkpoint: the fused Adam's step counts are not shared then
    torch.save(algo.state_dict(), buffer)
    resumed = _algo(seed=9)
    resumed.load_state_dict(torch.load(io.BytesIO(buffer.getvalue()), weights_only=False))
    torch.manual_seed(4)
    expected = algo.update(batch)
    torch.manual_seed(4)
    got = resumed.update(batch)
    assert float(got["actor_step"]) == 1.0 and all(torch.equal(got[k], expected[k]) for k in expected)


def test_prepare_standardises_with_the_batch_statistics_and_the_policy_acts_on_raw_observations():
    algo = _algo()
    data = _batch()
    data["observation"] = data["observation"] * 5 + 3
    raw = data.clone()
    prepared = algo.prepare(data, PrepareContext())
    loc = raw["observation"].mean(0)
    scale = raw["observation"].std(0, correction=0) + 1e-3
    torch.testing.assert_close(prepared["observation"], (raw["observation"] - loc) / scale)
    torch.testing.assert_close(prepared["next", "observation"], (raw["next", "observation"] - loc) / scale)
    assert (data == raw).all(), "the caller's batch was changed"
    with torch.no_grad():
        acted = algo.policy(TensorDict({"observation": raw["observation"]}, [16]))
        on_standardised = algo.loss.actor_network(TensorDict({"observation": prepared["observation"]}, [16]))
    torch.testing.assert_close(acted["action"], on_standardised["action"])
    torch.testing.assert_close(acted["observation"], raw["observation"])  # the input's observation is kept
    plain = _algo(normalize_observations=False)
    assert torch.equal(plain.prepare(data, PrepareContext())["observation"], raw["observation"])


@pytest.mark.parametrize("fmt", ["pt2", "onnx"])
def test_policy_file_and_its_exports_carry_the_standardisation(tmp_path, fmt):
    from omegaconf import OmegaConf

    from torchrl_bail.evaluate import main as evaluate_main
    from torchrl_bail.evaluation.policy import load_policy, policy_actions, save_policy

    if fmt == "onnx":
        pytest.importorskip("onnxruntime")
    algo = _algo()
    data = _batch()
    data["observation"] = data["observation"] * 5 + 3
    algo.prepare(data, PrepareContext())
    cfg = {"seed": 0, "env": {"id": "Hopper-v5"}, "algo": OmegaConf.to_container(algo.config)}
    path = save_policy(tmp_path / "policy.pt", algo, cfg, obs_dim=OBS, action_spec=SPEC)
    obs = data["observation"][:5]
    expected = policy_actions(algo.policy, obs)
    assert torch.equal(policy_actions(load_policy(path), obs), expected)
    out = tmp_path / f"policy.{fmt}"
    assert evaluate_main([str(path), "--export", fmt, "--out", str(out)]) == 0
    if fmt == "pt2":
        got = torch.export.load(str(out)).module()(obs)
    else:
        import onnxruntime

        got = torch.from_numpy(onnxruntime.InferenceSession(str(out)).run(None, {"observation": obs.numpy()})[0])
    torch.testing.assert_close(got, expected, atol=1e-5, rtol=1e-5)


@pytest.mark.skipif(os.environ.get("TORCHRL_BAIL_FULL_COMPILE_TESTS") != "1",
                    reason="about 2 minutes of Dynamo tracing on 2 cores (tests/test_compile.py's docstring); "
                           "TORCHRL_BAIL_FULL_COMPILE_TESTS=1 runs it")
def test_compiled_updates_agree_with_eager_across_the_delay():
    """Both compiled updates (the critic's alone, and with the actor's), through aot_eager's graphs."""
    batches = [_batch(seed) for seed in range(4)]
    eager, compiled = _algo(), _algo()
    compiled.compile(backend="aot_eager", cudagraphs=False)
    for batch in batches:
        torch.manual_seed(5)
        expected = eager.update(batch)
        torch.manual_seed(5)
        got = compiled.update(batch)
        for key in expected:
            torch.testing.assert_close(got[key], expected[key], rtol=1e-4, atol=1e-5, msg=key)
    for a, b in zip(compiled.loss.parameters(), eager.loss.parameters(), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)


def test_seeds_are_refused_in_one_line():
    line = refusal_line("algo=td3bc", "seeds=[1,2]")
    assert "seeds = [1, 2]" in line and "algo=td3bc" in line and "-m seed=1,2" in line, line

"""Evaluation reads each episode's true return, scores failures 0, and keeps going."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict

from torchrl_bail.evaluation import EvalResult, Evaluator, _read_episodes
from torchrl_bail.modules import make_deterministic_actor


def _rollout(rewards: torch.Tensor, done_at: list[int | None], obs_dim: int = 2) -> TensorDict:
    """A [n, T] rollout like break_when_all_done produces: finished envs repeat their last entries."""
    n, horizon = rewards.shape
    done = torch.zeros(n, horizon, 1, dtype=torch.bool)
    episode_reward = torch.zeros(n, horizon, 1)
    step_count = torch.zeros(n, horizon, 1, dtype=torch.int64)
    for i, d in enumerate(done_at):
        running = 0.0
        for t in range(horizon):
            last = d if d is not None else horizon - 1
            if t <= last:
                running += float(rewards[i, t])
            step_count[i, t] = min(t, last) + 1
            episode_reward[i, t] = running
            if d is not None and t >= d:
                done[i, t] = True
    return TensorDict({"next": {"done": done, "reward": rewards.unsqueeze(-1), "episode_reward": episode_reward,
                                "step_count": step_count, "observation": torch.zeros(n, horizon, obs_dim)}},
                      [n, horizon])


def test_returns_read_at_each_episodes_first_done():
    rewards = torch.tensor([[1.0, 2.0, 3.0, 4.0], [5.0, -7.0, -7.0, -7.0], [1.0, 1.0, 1.0, 1.0]])
    res = _read_episodes(_rollout(rewards, [3, 0, None]))
    assert res.returns == [10.0, 5.0, 4.0]  # the repeated -7 rewards after env 1's done are not counted
    assert res.lengths == [4, 1, 4]
    assert res.failures == 0


def test_non_finite_state_scores_zero_and_is_counted():
    rewards = torch.ones(3, 4)
    ro = _rollout(rewards, [3, 3, 1])
    ro["next", "observation"][0, 2, 1] = float("nan")  # env 0 diverges before its done: a failure
    ro["next", "observation"][2, 3, 0] = float("inf")  # env 2 diverges after its done: ignored
    res = _read_episodes(ro)
    assert res.returns == [0.0, 4.0, 2.0]
    assert res.failures == 1 and res.failed_episodes == [0]


def test_eval_result_statistics():
    res = EvalResult([1.0, 3.0], [5, 5])
    assert res.mean_return == 2.0 and math.isclose(res.std_return, 1.0)


def test_simulator_exception_scores_only_failing_episodes_zero(monkeypatch):
    evaluator = Evaluator("Hopper-v5", episodes=2, seed=0, max_steps=5)
    actor = make_deterministic_actor(evaluator.obs_dim, evaluator.action_spec, hidden=(4,))

    def broken_rollout(*args, **kwargs):
        raise RuntimeError("mujoco exploded")

    monkeypatch.setattr(evaluator.env, "rollout", broken_rollout)
    calls = {"n": 0}
    real_make_env = __import__("torchrl_bail.evaluation", fromlist=["make_env"]).make_env

    def flaky_make_env(*args, **kwargs):
        calls["n"] += 1
        env = real_make_env(*args, **kwargs)
        if calls["n"] == 1:  # the first replayed episode fails too
            monkeypatch.setattr(env, "rollout", broken_rollout)
        return env

    monkeypatch.setattr("torchrl_bail.evaluation.make_env", flaky_make_env)
    res = evaluator(actor)
    evaluator.close()
    assert res.failures == 1 and res.failed_episodes == [0]
    assert res.returns[0] == 0.0 and res.returns[1] != 0.0


def test_real_hopper_episode_returns_are_whole():
    """Batched evaluation equals running each seeded env alone (no truncation by the other episodes)."""
    evaluator = Evaluator("Hopper-v5", episodes=3, seed=3, max_steps=200)
    torch.manual_seed(0)
    actor = make_deterministic_actor(evaluator.obs_dim, evaluator.action_spec, hidden=(8,))
    res = evaluator(actor)
    evaluator.close()
    assert len(res.returns) == 3 and all(math.isfinite(r) for r in res.returns)
    assert all(1 <= length <= 200 for length in res.lengths)
    # the episodes end at different steps: none was cut at another episode's end
    assert len(set(res.lengths)) > 1, res.lengths


def test_bad_settings_are_rejected():
    with pytest.raises(ValueError, match="eval.episodes"):
        Evaluator("Hopper-v5", episodes=0)

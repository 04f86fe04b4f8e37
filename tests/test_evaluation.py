"""Evaluation reads each episode's true return, scores simulator failures 0, and keeps going; an evaluator plays a list
of seeds (one seed: a list of one, its policy unstacked) and returns one result per seed."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
import torch
from tensordict.nn import TensorDictModule
from torchrl.envs import DoubleToFloat, GymEnv, GymWrapper, TransformedEnv

from torchrl_bail.evaluation import EvalResult, Evaluator, episode_seed
from torchrl_bail.evaluation.simulator import SimulatorGuard, make_guarded_env


def _policy(hook=None):
    """A deterministic policy computed element by element, so its outputs never depend on the batch shape."""
    shapes = []

    def act(obs):
        shapes.append(tuple(obs.shape))
        if hook is not None:
            hook(len(shapes))
        return (3 * obs[..., 5:8]).clamp(-1, 1)  # exactly rounded ops: no SIMD-dependent bits

    module = TensorDictModule(act, in_keys=["observation"], out_keys=["action"])
    module.shapes = shapes
    return module


def _one_episode(env_id, seed, policy, max_steps, **make_kwargs):
    """Reference: one gymnasium env alone, run to its first done (or max_steps); (return, length)."""
    env = gym.make(env_id, **make_kwargs)
    obs, _ = env.reset(seed=seed)
    ret, length = 0.0, 0
    for _ in range(max_steps):
        action = policy.module(torch.as_tensor(obs, dtype=torch.float32).unsqueeze(0))[0].numpy()
        obs, r, terminated, truncated, _ = env.step(action)
        ret, length = ret + r, length + 1
        if terminated or truncated:
            break
    env.close()
    return ret, length


def test_each_episode_runs_to_its_own_first_done():
    """Batched evaluation equals running each seeded episode alone: none is cut at another's end or padded."""
    with Evaluator("Hopper-v5", episodes=3, seeds=[3], max_steps=300) as evaluator:
        policy = _policy()
        (res,) = evaluator.evaluate(policy)
    assert policy.shapes[0] == (3, 11)  # one call per step on the float32 observations (one seed: no seed dim)
    reference = [_one_episode("Hopper-v5", episode_seed(3, 0, i), _policy(), 300) for i in range(3)]
    assert res.returns == [r for r, _ in reference]
    assert res.lengths == [n for _, n in reference]
    assert len(set(res.lengths)) > 1 and max(res.lengths) < 300, res.lengths  # Hopper fell, each at its own step
    assert res.failures == 0


def test_same_seed_same_returns_new_start_states_each_evaluation():
    a = Evaluator("Hopper-v5", episodes=2, seeds=[1], max_steps=30)
    b = Evaluator("Hopper-v5", episodes=2, seeds=[1], max_steps=30)
    (first,), (again,) = a.evaluate(_policy()), b.evaluate(_policy())
    assert first.returns == again.returns
    (second,) = a.evaluate(_policy())
    assert second.returns != first.returns  # the next evaluation starts from new states
    a.evaluations = 0  # resuming the stream reproduces the first evaluation
    assert a.evaluate(_policy())[0].returns == first.returns
    a.close()
    b.close()


def test_time_limit_and_step_budget_end_episodes():
    kwargs = {"terminate_when_unhealthy": False}
    with Evaluator("Hopper-v5", episodes=2, max_steps=50, max_episode_steps=7, env_kwargs=kwargs) as ev:
        assert ev.evaluate(_policy())[0].lengths == [7, 7]
    with Evaluator("Hopper-v5", episodes=2, max_steps=5, env_kwargs=kwargs) as ev:
        assert ev.evaluate(_policy())[0].lengths == [5, 5]


def test_guard_ends_the_episode_mujoco_would_silently_reset():
    raw = gym.make("Hopper-v5")
    raw.reset(seed=0)
    raw.unwrapped.data.qvel[:] = 1e20
    obs, reward, terminated, _, _ = raw.step(np.zeros(3))
    # MuJoCo >= 3 raises nothing: it resets the simulation and the episode goes on from the initial state
    assert not terminated and np.isfinite(obs).all() and math.isfinite(reward)
    raw.close()

    env = make_guarded_env("Hopper-v5")
    _, info = env.reset(seed=0)
    assert info["simulator_unstable"] is False
    _, _, terminated, _, info = env.step(np.zeros(3))
    assert not terminated and info["simulator_unstable"] is False
    env.unwrapped.data.qpos[2] = float("nan")
    _, _, terminated, _, info = env.step(np.zeros(3))
    assert terminated and info["simulator_unstable"] is True and env.unstable_episodes == 1
    _, info = env.reset(seed=1)  # a reset clears MuJoCo's counters: the next episode is healthy again
    _, _, terminated, _, info = env.step(np.zeros(3))
    assert not terminated and info["simulator_unstable"] is False
    assert isinstance(env, SimulatorGuard)
    env.close()


def test_unstable_simulator_scores_zero_and_is_counted():
    evaluator = Evaluator("Hopper-v5", episodes=3, seeds=[0], max_steps=200)

    def diverge(call):  # before the 4th step, episode 1's simulation blows up
        if call == 4:
            evaluator.envs[1].unwrapped.data.qvel[:] = 1e20

    (res,) = evaluator.evaluate(_policy(diverge))
    assert res.failures == 1 and res.failed_episodes == [1]
    assert res.returns[1] == 0.0 and res.lengths[1] == 4
    assert res.returns[0] != 0.0 and res.returns[2] != 0.0 and min(res.lengths[0], res.lengths[2]) > 4
    # the next evaluation is healthy again
    assert evaluator.evaluate(_policy())[0].failures == 0
    evaluator.close()


def test_simulator_exception_scores_only_that_episode_zero(monkeypatch):
    evaluator = Evaluator("Hopper-v5", episodes=2, seeds=[0], max_steps=20)

    def broken_step(action):
        raise RuntimeError("mujoco exploded")

    monkeypatch.setattr(evaluator.envs[0], "step", broken_step)
    (res,) = evaluator.evaluate(_policy())
    evaluator.close()
    assert res.failures == 1 and res.failed_episodes == [0]
    assert res.returns[0] == 0.0 and res.returns[1] != 0.0 and res.lengths[1] > 0


def test_several_seeds_in_one_step_loop_equal_separate_evaluations():
    policy = _policy()
    with Evaluator("Hopper-v5", episodes=2, seeds=[3, 4], max_steps=40) as ev:
        together = ev.evaluate(policy)
    assert policy.shapes[0] == (2, 2, 11)  # [seeds, episodes, obs]
    separate = []
    for s in (3, 4):
        with Evaluator("Hopper-v5", episodes=2, seeds=[s], max_steps=40) as ev:
            separate.extend(ev.evaluate(_policy()))
    assert [r.returns for r in together] == [r.returns for r in separate]
    assert [r.lengths for r in together] == [r.lengths for r in separate]


def test_seed_is_shorthand_for_a_list_of_one():
    """``seed=s`` is ``seeds=[s]``: the same unstacked ``[episodes]`` batch and the same episodes."""
    with Evaluator("Hopper-v5", episodes=2, seed=3, max_steps=40) as ev, \
            Evaluator("Hopper-v5", episodes=2, seeds=[3], max_steps=40) as listed:
        assert ev.seeds == listed.seeds == [3] and ev.batch_shape == listed.batch_shape == (2,)
        (result,) = ev.evaluate(_policy())
        (expected,) = listed.evaluate(_policy())
    assert (result.returns, result.lengths) == (expected.returns, expected.lengths)


def test_eval_result_statistics():
    res = EvalResult([1.0, 3.0], [5, 5])
    assert res.mean_return == 2.0 and math.isclose(res.std_return, 1.0)


def test_bad_settings_are_rejected():
    with pytest.raises(ValueError, match="eval.episodes"):
        Evaluator("Hopper-v5", episodes=0)
    with pytest.raises(ValueError, match="eval.max_steps"):
        Evaluator("Hopper-v5", max_steps=0)


def test_guard_is_a_drop_in_for_torchrl_collection_envs():
    """``GymWrapper(make_guarded_env(id))`` steps exactly like ``GymEnv(id)`` and ends an unstable episode."""
    plain = TransformedEnv(GymEnv("Hopper-v5"), DoubleToFloat())
    guard = make_guarded_env("Hopper-v5")
    guarded = TransformedEnv(GymWrapper(guard), DoubleToFloat())
    rollouts = []
    for env in (plain, guarded):
        env.set_seed(5)
        torch.manual_seed(1)
        rollouts.append(env.rollout(80, break_when_any_done=False))  # random actions, resets after done
    assert rollouts[0]["next", "done"].any()
    assert (rollouts[0] == rollouts[1]).all()
    td = guarded.reset()
    guard.unwrapped.data.qvel[:] = 1e20
    td = guarded.step(td.set("action", torch.zeros(3)))
    assert td["next", "terminated"].item() and td["next", "done"].item() and guard.unstable_episodes == 1
    plain.close()
    guarded.close()


class _KnownRewards(gym.Env):
    """Rewards ``1, 2, 3, ...`` (step ``t`` pays ``t + 1``), terminated after ``length`` steps; the action is unused."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def __init__(self, length: int = 5):
        self.length, self.t = length, 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return np.zeros(2, np.float32), {}

    def step(self, action):
        self.t += 1
        return np.zeros(2, np.float32), float(self.t), self.t >= self.length, False, {}


gym.register("KnownRewards-v0", entry_point=_KnownRewards)


def _zero_policy():
    return TensorDictModule(lambda obs: torch.zeros(*obs.shape[:-1], 1), in_keys=["observation"], out_keys=["action"])


def test_the_discounted_return_is_recorded_beside_the_return():
    """Each episode's discounted return from its start, sum_t gamma^t r_t, at the gamma FQE estimates (its default
    FQESettings.gamma, one constant) or another, beside the undiscounted return; a failed episode scores 0 in both."""
    from torchrl_bail.ope import FQESettings

    rewards = [1.0, 2.0, 3.0, 4.0, 5.0]
    with Evaluator("KnownRewards-v0", episodes=2, seeds=[0], max_steps=50, env_kwargs={"length": 5}) as ev:
        assert ev.gamma == FQESettings.gamma == 0.99
        (res,) = ev.evaluate(_zero_policy())
    assert res.returns == [15.0, 15.0] and res.lengths == [5, 5] and res.gamma == 0.99
    expected = sum(0.99 ** t * r for t, r in enumerate(rewards))
    assert all(math.isclose(d, expected, rel_tol=1e-12) for d in res.discounted_returns), res.discounted_returns
    assert math.isclose(res.mean_discounted_return, expected, rel_tol=1e-12)

    with Evaluator("KnownRewards-v0", episodes=1, seeds=[1, 2], max_steps=3, gamma=0.5,
                   env_kwargs={"length": 5}) as ev:  # two seeds; the step budget cuts the episodes at 3 steps
        results = ev.evaluate(_zero_policy())
    assert [r.discounted_returns for r in results] == [[1.0 + 0.5 * 2.0 + 0.25 * 3.0]] * 2
    assert [r.returns for r in results] == [[6.0]] * 2

    evaluator = Evaluator("KnownRewards-v0", episodes=2, seeds=[0], max_steps=10, env_kwargs={"length": 5})

    def broken_step(action):
        raise RuntimeError("the simulator exploded")

    evaluator.envs[0].step = broken_step
    (res,) = evaluator.evaluate(_zero_policy())
    evaluator.close()
    assert res.failed_episodes == [0] and res.returns[0] == res.discounted_returns[0] == 0.0
    assert math.isclose(res.discounted_returns[1], expected, rel_tol=1e-12)
    with pytest.raises(ValueError, match="gamma"):
        Evaluator("KnownRewards-v0", gamma=1.5)

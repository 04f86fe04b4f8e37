"""Behaviour-data collection on tiny budgets: flags, terminal observations, noise, training schedule, caching."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from torchrl_bail import config_dir
from torchrl_bail.behaviour import catalogue
from torchrl_bail.behaviour.catalogue import ensure_batch
from torchrl_bail.behaviour.ddpg import DDPGAgent, collect_ddpg
from torchrl_bail.configuration.config import ConfigError
from torchrl_bail.configuration.config_builders import collection_config
from torchrl_bail.data.cache import batch_name, batch_path, behaviour_seed

#: short enough that a random or barely trained Hopper outlives it now and then
LIMIT = 20
TINY_DDPG = [
    "batch.steps=400", "batch.start_steps=100", f"env.max_episode_steps={LIMIT}",
    "batch.agent.actor_hidden=[32,32]", "batch.agent.critic_hidden=[32,32]", "batch.agent.batch_size=16",
]


def _compose(*overrides: str):
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        return compose("config", overrides=list(overrides))


def _tiny(*extra: str, exp: str = "hopper_ddpg05"):
    return _compose(f"+exp={exp}", *TINY_DDPG, *extra)


def _episode_spans(episode: torch.Tensor) -> list[tuple[int, int]]:
    ids = episode.tolist()
    spans, start = [], 0
    for i in range(1, len(ids) + 1):
        if i == len(ids) or ids[i] != ids[start]:
            spans.append((start, i))
            start = i
    return spans


@pytest.fixture(scope="module")
def ddpg_run(tmp_path_factory):
    """One tiny DDPG batch, with every gradient-step call recorded as (stored transitions, number of updates)."""
    data_dir = tmp_path_factory.mktemp("ddpg")
    cfg = _tiny()
    calls = []
    original = DDPGAgent.train

    def spy(self, replay, num_updates):
        calls.append((len(replay), int(num_updates)))
        return original(self, replay, num_updates)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(DDPGAgent, "train", spy)
        batch = ensure_batch(cfg, progress=False, data_dir=data_dir)
    return cfg, batch, calls, data_dir


def test_ddpg_batch_loads_with_ted_layout_and_metadata(ddpg_run):
    from torchrl_bail.data.batch import load_batch

    cfg, batch, _, data_dir = ddpg_run
    assert batch.path == batch_path(cfg, data_dir)
    again = load_batch(batch.path)
    assert again.num_transitions == 400 and again.obs_dim == 11 and again.act_dim == 3
    data = again.data
    assert data["observation"].dtype == torch.float32 and data["action"].dtype == torch.float32
    assert data["next", "reward"].shape == (400, 1)
    meta = again.metadata
    assert meta["env_id"] == "Hopper-v5" and meta["seed"] == 1 and meta["recipe"]["sigma"] == 0.5
    assert meta["action_low"] == [-1.0] * 3 and meta["action_high"] == [1.0] * 3
    assert meta["gradient_steps"] == sum(n for _, n in ddpg_run[2])
    spans = _episode_spans(data["episode"])
    assert [data["episode"][s].item() for s, _ in spans] == list(range(len(spans)))


def test_terminated_and_truncated_flags(ddpg_run):
    _, batch, _, _ = ddpg_run
    data = batch.data
    term, trunc, done = (data["next", k].squeeze(-1) for k in ("terminated", "truncated", "done"))
    assert torch.equal(done, term | trunc)
    assert not (term & trunc).any()
    spans = _episode_spans(data["episode"])
    assert trunc.any(), f"a {LIMIT}-step time limit must truncate some episodes in 400 steps"
    for k, (s, e) in enumerate(spans):
        assert not done[s:e - 1].any(), "done only on the last step of an episode"
        if k < len(spans) - 1:
            assert done[e - 1], "every episode but the last ends with done"
            assert bool(trunc[e - 1]) == (e - s == LIMIT and not bool(term[e - 1]))
        assert e - s <= LIMIT


def test_observations_match_a_raw_gymnasium_replay(ddpg_run):
    """Replaying the stored actions in plain gymnasium reproduces every obs, reward, flag and terminal next-obs."""
    cfg, batch, _, _ = ddpg_run
    data = batch.data
    env = gym.make("Hopper-v5", max_episode_steps=LIMIT)
    env.reset(seed=behaviour_seed(cfg))  # GymEnv.set_seed resets with the seed ...
    obs, _ = env.reset()                   # ... and the first episode starts from the next reset
    n_terminal = 0
    for i in range(data.shape[0]):
        np.testing.assert_array_equal(data["observation"][i].numpy(), obs.astype(np.float32))
        nxt, reward, terminated, truncated, _ = env.step(data["action"][i].numpy())
        np.testing.assert_array_equal(data["next", "observation"][i].numpy(), nxt.astype(np.float32))
        assert data["next", "reward"][i, 0].item() == pytest.approx(reward, rel=1e-6, abs=1e-6)
        assert bool(data["next", "terminated"][i]) == terminated and bool(data["next", "truncated"][i]) == truncated
        if terminated or truncated:
            n_terminal += 1
            assert data["next", "observation"][i].abs().sum() > 0, "terminal next-obs must be real, not zeros"
            if i + 1 < data.shape[0]:
                assert not torch.equal(data["next", "observation"][i], data["observation"][i + 1])
            obs, _ = env.reset()
        else:
            obs = nxt
    assert n_terminal >= 5


def test_random_phase_is_uniform_in_bounds(ddpg_run):
    _, batch, _, _ = ddpg_run
    a = batch.data["action"][:100]
    assert a.min() >= -1 and a.max() <= 1
    assert a.min() < -0.85 and a.max() > 0.85
    assert abs(a.mean().item()) < 0.15 and abs(a.std().item() - (1 / 3) ** 0.5) < 0.1


def test_gradient_steps_happen_at_episode_ends(ddpg_run):
    _, batch, calls, _ = ddpg_run
    spans = _episode_spans(batch.data["episode"])
    done = batch.data["next", "done"].squeeze(-1)
    finished = [(s, e) for s, e in spans if done[e - 1]]
    if finished and finished[-1][1] == batch.num_transitions:
        finished = finished[:-1]  # the batch is full: no training after its last episode (as the BCQ repo)
    assert calls == [(e, e - s) for s, e in finished]  # episode_length updates, right after that episode


def test_noise_is_absolute_and_clipped(tmp_path):
    """InvertedPendulum's bound is 3: an absolute sigma=2 gives interior residuals of std ~2 (not 6) and clips."""
    cfg = _compose("env=hopper", "batch=ddpg05", "env.id=InvertedPendulum-v5", "env.name=pendulum",
                   "batch.steps=600", "batch.start_steps=0", "batch.sigma=2.0", "env.max_episode_steps=100",
                   "batch.agent.actor_hidden=[16]", "batch.agent.critic_hidden=[16,16]",
                   "batch.agent.batch_size=8", "batch.agent.actor_lr=1e-12")
    agents = []
    data, extra = collect_ddpg(cfg, scratch=tmp_path, progress=False, agent_hook=agents.append)
    a = data["action"].clone()
    mu = agents[0].act(data["observation"].clone())
    assert a.abs().max() <= 3.0
    at_bound = a.abs() == 3.0
    assert 0.03 < at_bound.float().mean() < 0.4
    residual = (a - mu)[~at_bound]
    assert 1.3 < residual.std().item() < 2.3
    assert extra["action_high"] == [3.0]


def test_same_seed_same_batch_and_index_changes_it(tmp_path):
    b1 = ensure_batch(_tiny("batch.steps=150"), progress=False, data_dir=tmp_path / "a")
    b1_again = ensure_batch(_tiny("batch.steps=150"), progress=False, data_dir=tmp_path / "b")
    b2 = ensure_batch(_tiny("batch.steps=150", "batch.index=2"), progress=False, data_dir=tmp_path / "a")
    for key in ("observation", "action", ("next", "reward"), ("next", "observation"), ("next", "terminated")):
        assert torch.equal(b1.data[key], b1_again.data[key]), key
    assert b1.path.name.split("-")[0] == "hopper_ddpg05_b1" and b2.path.name.split("-")[0] == "hopper_ddpg05_b2"
    assert not torch.equal(b1.data["observation"], b2.data["observation"])


def test_second_call_is_a_cache_hit(ddpg_run, monkeypatch):
    cfg, batch, _, data_dir = ddpg_run

    def boom(*args, **kwargs):
        raise AssertionError("the cached batch must not be collected again")

    monkeypatch.setattr(catalogue, "collect_batch", boom)
    again = ensure_batch(cfg, progress=False, data_dir=data_dir)
    assert again.path == batch.path and again.num_transitions == batch.num_transitions


def test_names_and_hashes():
    paper = _compose("+exp=hopper_ddpg05")
    quick = _compose("+exp=hopper_ddpg05", "preset=quick")
    other_seed = _compose("+exp=hopper_ddpg05", "seed=7")
    assert batch_name(paper) == batch_name(quick) == "hopper_ddpg05_b1"
    assert batch_path(paper, "/d") != batch_path(quick, "/d")
    assert batch_path(paper, "/d") == batch_path(other_seed, "/d"), "the training seed must not change the batch"
    assert batch_path(paper, "/d").parent.as_posix() == "/d"
    assert behaviour_seed(_compose("+exp=hopper_ddpg05", "batch.index=2")) == 2
    assert behaviour_seed(_compose("+exp=hopper_ddpg05", "batch.index=2", "batch.seed=11")) == 11
    ddpg01 = _compose("+exp=hopper_ddpg01")
    assert batch_path(paper, "/d") != batch_path(ddpg01, "/d")


@pytest.mark.parametrize("override, key", [
    ("batch.recipe=ppo", "batch.recipe"),
    ("batch.steps=0", "batch.steps"),
    ("batch.sigma=-0.1", "batch.sigma"),
    ("batch.start_steps=-1", "batch.start_steps"),
    ("batch.agent.actor_lr=0", "batch.agent.actor_lr"),
    ("batch.agent.critic_hidden=[0]", "batch.agent.critic_hidden"),
    ("batch.index=0", "batch.index"),
    ("env.max_episode_steps=0", "env.max_episode_steps"),
])
def test_bad_recipes_are_named(override, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        collection_config(_compose("+exp=hopper_ddpg05", override))


def test_cli_collects_then_reports_cached_then_lists(tmp_path):
    """... with the ``threads`` config key applied (torch's own default would be the machine's cores) and recorded in
    the batch's metadata."""
    env = {**os.environ, "RL_WARNINGS": "0", "HYDRA_FULL_ERROR": "1", "PYTHONPATH": os.pathsep.join(
        [os.path.join(os.path.dirname(__file__), "..", "src"), os.environ.get("PYTHONPATH", "")])}
    base = [sys.executable, "-m", "torchrl_bail.collect", "+exp=hopper_ddpg01", *TINY_DDPG, "batch.steps=120",
            f"data_dir={tmp_path / 'data'}", "progress=false", f"hydra.run.dir={tmp_path / 'run'}", "threads=3"]
    first = subprocess.run(base, capture_output=True, text=True, env=env, timeout=300)
    assert first.returncode == 0, first.stderr[-3000:]
    assert "hopper_ddpg01_b1: collected" in first.stdout and "120 transitions" in first.stdout
    listing = subprocess.run([sys.executable, "-m", "torchrl_bail.collect", "--list", "--data-dir",
                              str(tmp_path / "data")], capture_output=True, text=True, env=env, timeout=300)
    assert listing.returncode == 0, listing.stderr[-3000:]
    assert "hopper_ddpg01_b1-" in listing.stdout and "ddpg steps=120" in listing.stdout
    meta = json.loads(next((tmp_path / "data").glob("hopper_ddpg01_b1-*/metadata.json")).read_text())
    assert meta["recipe"]["sigma"] == 0.1
    assert meta["collection_threads"] == 3


def test_collection_env_ends_an_episode_on_a_simulator_instability():
    """MuJoCo >= 3 only warns and resets; the collection env's SimulatorGuard ends the episode and counts it."""
    from torchrl_bail.behaviour.loop import BehaviourRun, make_collection_env

    env = make_collection_env("Hopper-v5", max_episode_steps=50, seed=0)
    try:
        runner = BehaviourRun(env, lambda obs, t: torch.zeros(3))
        td = env.reset()
        td.set("action", torch.zeros(3))
        assert not bool(env.step(td)["next", "terminated"])  # healthy: goes on
        env.simulator_guard.unwrapped.data.qvel[:] = 1e20
        out = env.step(td)
        assert bool(out["next", "terminated"]) and bool(out["next", "done"])
        assert runner.unstable_episodes == 1
    finally:
        env.close()

"""Collection resume: a crashed or SIGKILLed collection continues from its last checkpoint and makes the same bytes
as an uninterrupted one; checkpoints are atomic and removed once the batch is saved."""

from __future__ import annotations

import random
import sys
import time
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from torchrl_bail import config_dir
from torchrl_bail.behaviour import ensure_batch
from torchrl_bail.behaviour.checkpoint import CollectionCheckpoint
from torchrl_bail.behaviour.ddpg import DDPGAgent
from torchrl_bail.behaviour.sac import SACAgent
from torchrl_bail.data.cache import batch_path
from torchrl_bail.data.locks import PARTIAL

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from _collection_drill import collection_trial  # noqa: E402

TINY_DDPG = ["+exp=hopper_ddpg05", "batch.steps=400", "batch.start_steps=60", "env.max_episode_steps=30",
             "batch.agent.actor_hidden=[16,16]", "batch.agent.critic_hidden=[16,16]", "batch.agent.batch_size=16",
             "batch.checkpoint_every_steps=50"]
TINY_SAC = ["+exp=hopper_sac", "batch.steps=400", "env.max_episode_steps=40", "batch.sac.start_steps=100",
            "batch.sac.eval_every=150", "batch.sac.eval_episodes=2", "batch.sac.actor_hidden=[16,16]",
            "batch.sac.critic_hidden=[16,16]", "batch.sac.batch_size=16", "batch.checkpoint_every_steps=50"]


def _compose(overrides: list[str]):
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        return compose("config", overrides=list(overrides))


def _files(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


class Crash(Exception):
    """Stands for a kill: raised from the agent's training once a checkpoint exists."""


def _crash_once_checkpointed(monkeypatch, agent_cls, data_dir: Path, after_rows: int) -> None:
    original = agent_cls.train

    def train(self, replay, n):
        if len(replay) >= after_rows and list((data_dir / PARTIAL).glob("*/state.pt")):
            raise Crash
        return original(self, replay, n)

    monkeypatch.setattr(agent_cls, "train", train)


@pytest.mark.parametrize("overrides,agent_cls", [(TINY_DDPG, DDPGAgent), (TINY_SAC, SACAgent)], ids=["ddpg", "sac"])
def test_a_crashed_collection_resumes_to_the_same_bytes(tmp_path, monkeypatch, overrides, agent_cls):
    cfg = _compose(overrides)
    reference = ensure_batch(cfg, progress=False, data_dir=tmp_path / "reference")
    assert reference.metadata["resumed_from_step"] is None
    assert reference.metadata["simulator_unstable_episodes"] == 0
    data_dir = tmp_path / "crashed"
    with monkeypatch.context() as mp:
        _crash_once_checkpointed(mp, agent_cls, data_dir, after_rows=230)
        with pytest.raises(Crash):
            ensure_batch(cfg, progress=False, data_dir=data_dir)
    assert not batch_path(cfg, data_dir).exists(), "a half-collected batch never appears under its final name"
    (partial,) = list((data_dir / PARTIAL).iterdir())
    assert {"segments", "state.pt"} <= {p.name for p in partial.iterdir()}
    state = torch.load(partial / "state.pt", weights_only=True)
    assert state["wall_time_s"] > 0
    # the transitions kept and the batch's size, which run_study.py --status reads for its progress and time left
    assert 0 < state["buffers"]["kept"] < state["buffers"]["steps"] == reference.num_transitions
    torch.save({**state, "wall_time_s": 1e6}, partial / "state.pt")  # as if the first part had taken 10^6 s
    start = time.perf_counter()
    resumed = ensure_batch(cfg, progress=False, data_dir=data_dir)
    last_part = time.perf_counter() - start
    step = resumed.metadata["resumed_from_step"]
    assert step is not None and 100 <= step <= 400
    assert 1e6 < resumed.metadata["collection_wall_time_s"] < 1e6 + last_part, "the time of both parts"
    assert resumed.metadata["collection_timed_from_step"] == reference.metadata["collection_timed_from_step"] == 0
    for key in reference.data.keys(True, True):
        assert torch.equal(reference.data[key], resumed.data[key]), key
    assert _files(reference.path / "data") == _files(resumed.path / "data"), "every data file, byte for byte"
    assert list((data_dir / PARTIAL).iterdir()) == [], "the checkpoint is removed once the batch is saved"


def test_checkpoints_are_due_by_steps_or_seconds_and_an_incomplete_one_is_ignored(tmp_path):
    by_steps = CollectionCheckpoint(tmp_path / "a", every_s=None, every_steps=100)
    assert not by_steps.due(99) and by_steps.due(100)
    by_time = CollectionCheckpoint(tmp_path / "b", every_s=0.0, every_steps=None)
    assert by_time.due(1)
    never = CollectionCheckpoint(tmp_path / "c", every_s=None, every_steps=None)
    assert not never.due(10**9)
    # a state.pt naming a segment that is not there (or not readable) is not a checkpoint: start over
    broken = tmp_path / "d"
    broken.mkdir()
    torch.save({"format": 2, "segments": {"batch": ["segments/batch_0_10.pt"]}, "saved_rows": {"batch": 10},
                "loop": {"t": 10}}, broken / "state.pt")
    assert CollectionCheckpoint(broken).load() is None
    (broken / "state.pt").write_bytes(b"half a pickle")
    assert CollectionCheckpoint(broken).load() is None


def test_a_checkpoint_carries_the_collections_time_and_an_older_one_says_it_kept_none(tmp_path):
    """A resumed collection's clock starts from the time its checkpoint carried; a checkpoint written before
    checkpoints kept the time (no ``wall_time_s``) counts from its own env step, which the batch's metadata says."""
    first = CollectionCheckpoint(tmp_path / "k", every_s=None, every_steps=1)
    first.earlier_wall_time_s = 100.0  # as if 100 s of earlier parts were restored
    first.save({"loop": {"t": 7}}, {})
    state = first.load()
    assert state["wall_time_s"] >= 100.0 and state["timed_from_step"] == 0
    second = CollectionCheckpoint(tmp_path / "k")
    second.restore_stores(state, {})
    assert second.timed_from_step == 0 and second.wall_time_s >= state["wall_time_s"]

    older = {k: v for k, v in state.items() if k not in ("wall_time_s", "timed_from_step")}
    third = CollectionCheckpoint(tmp_path / "k")
    third.restore_stores(older, {})
    assert third.timed_from_step == 7 and third.wall_time_s < 100.0


@pytest.mark.parametrize("recipe,overrides", [("ddpg", TINY_DDPG), ("sac", TINY_SAC)])
def test_a_sigkilled_collection_resumes_to_the_same_bytes(tmp_path, recipe, overrides):
    """The kill drill's trial: SIGKILL after >= 1 checkpoint, resume in a new process, compare every data byte."""
    lines = []
    assert collection_trial(random.Random(0), tmp_path, recipe=recipe, overrides=overrides, max_delay_s=0.5,
                            log=lines.append), lines
    assert "resumed from step None" not in lines[0] or "finished before the kill" in lines[0]


def test_the_env_step_rate_counts_the_steps_its_time_covers(tmp_path):
    """``env_steps_per_s`` divides by the collection's time the steps that time covers: every step, or, resumed from
    an older version's checkpoint (its steps' time unknown), those after that checkpoint's step."""
    from types import SimpleNamespace

    from torchrl_bail.behaviour.loop import env_steps_per_s

    runner = SimpleNamespace(t=1000)
    assert env_steps_per_s(runner, 10.0) == 100.0
    checkpoint = CollectionCheckpoint(tmp_path / "k", every_s=None, every_steps=1)
    assert env_steps_per_s(runner, 10.0, SimpleNamespace(checkpoint=checkpoint)) == 100.0  # timed from step 0
    checkpoint.restore_stores({"loop": {"t": 400}, "segments": {}, "saved_rows": {}}, {})  # an older version's
    assert checkpoint.timed_from_step == 400
    assert env_steps_per_s(runner, 10.0, SimpleNamespace(checkpoint=checkpoint)) == 60.0

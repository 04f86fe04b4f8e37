"""A killed run continues from its checkpoint and ends exactly where an uninterrupted run ends.

Unit level: every algorithm's ``state_dict`` is complete (a fresh object loaded from it makes the same updates
bit for bit), and the training loop resumed from its checkpoint reproduces the uninterrupted loop. Run level
(in process, on a tiny generated batch): runs of BAIL, BCQ and TD3+BC "killed" at random points (an exception escaping
the update or the envelope fit leaves the disk as SIGKILL would) and restarted match the reference run's summary,
scalar logs and weights; a changed config is refused; a finished run is reported, not retrained. The SIGKILL
version of the drill with real processes is ``benchmarks/kill_drill.py``.
"""

from __future__ import annotations

import copy
import io
import json
import os
import random
import threading
import time

import pytest
import torch
from _contract import ALGO_CASES
from hydra import compose, initialize_config_dir
from tensordict import TensorDict

import torchrl_bail.algorithms as algorithms_module
import torchrl_bail.training.envelope as envelope_module
import torchrl_bail.training.resume as resume_module
import torchrl_bail.training.trainer as trainer_module
from torchrl_bail import config_dir
from torchrl_bail.algorithms import BehaviourCloning, PrepareContext
from torchrl_bail.configuration.config_builders import algo_config
from torchrl_bail.data.locks import host_name, process_table_identity
from torchrl_bail.modules import action_spec_from_bounds
from torchrl_bail.training.resume import RUN_LOCK, ResumeError, Resumption
from torchrl_bail.training.trainer import make_trainee, train

SPEC = action_spec_from_bounds([-1.0, -0.5], [1.0, 0.5])
POLICY = {"policy": {"hidden": [16]}, "batch_size": 16, "epochs": 1}


def _data(n: int = 300, seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(n, 4, generator=g)
    return TensorDict({
        "observation": obs, "action": torch.rand(n, 2, generator=g) * 2 - 1,
        "return": obs[:, 0] * 3 + torch.rand(n, generator=g),
        "next": {"observation": torch.randn(n, 4, generator=g), "reward": torch.randn(n, 1, generator=g),
                 "terminated": (end := torch.rand(n, 1, generator=g) < 0.05), "done": end},
    }, [n])


#: beyond the contract's tiny configs: the 13 updates compared cross Progressive BAIL's early stop and BEAR's warm
#: start
SWITCHES = {"pbail": {"envelope.patience": 2}, "bear": {"warm_start_updates": 5}}
ALGOS = {name: lambda case=case: case.build(**SWITCHES.get(case.name, {})) for name, case in ALGO_CASES.items()}


def _updates(algo, data, n: int, seed: int) -> list[dict]:
    torch.manual_seed(seed)
    out = []
    for _ in range(n):
        batch = data[torch.randint(len(data), (algo.batch_size,))]
        out.append({k: v.clone() for k, v in algo.update(batch).items()})
    return out


def _tensors(state, prefix="") -> dict:
    if isinstance(state, dict):
        return {k: v for key, sub in state.items() for k, v in _tensors(sub, f"{prefix}/{key}").items()}
    if isinstance(state, (list, tuple)):
        return {k: v for i, sub in enumerate(state) for k, v in _tensors(sub, f"{prefix}/{i}").items()}
    return {prefix: state}


def _assert_same(a, b) -> None:
    ta, tb = _tensors(a), _tensors(b)
    assert ta.keys() == tb.keys()
    for k in ta:
        if torch.is_tensor(ta[k]):
            assert torch.equal(ta[k], tb[k]), k
        else:
            assert ta[k] == tb[k] or (ta[k] != ta[k] and tb[k] != tb[k]), k  # NaN == NaN here


@pytest.mark.parametrize("name", sorted(ALGOS))
def test_checkpoint_round_trip_continues_bit_for_bit(name):
    """Save mid-training, load into a freshly built algorithm, continue both: identical updates and states."""
    data = _data()
    torch.manual_seed(0)
    original = ALGOS[name]()
    train_data = original.prepare(data, PrepareContext(generator=torch.Generator().manual_seed(5)))
    _updates(original, train_data, 7, seed=1)
    buffer = io.BytesIO()
    torch.save(original.state_dict(), buffer)
    torch.manual_seed(123)  # a different initialisation that the checkpoint must overwrite
    restored = ALGOS[name]()
    restored.load_state_dict(torch.load(io.BytesIO(buffer.getvalue()), weights_only=False))
    restored_data = restored.restore_prepared(data, PrepareContext(generator=torch.Generator().manual_seed(5)))
    _assert_same(restored_data.to_dict(), train_data.to_dict())
    _assert_same(_updates(restored, restored_data, 6, seed=2), _updates(original, train_data, 6, seed=2))
    _assert_same(restored.state_dict(), original.state_dict())
    _assert_same(restored.summary(), original.summary())


@pytest.mark.parametrize("name", sorted(ALGOS))
def test_a_state_loaded_from_a_live_algorithm_shares_nothing_with_it(name):
    """``b.load_state_dict(a.state_dict())`` without a trip through disk: torch's ``Optimizer.load_state_dict`` keeps
    the given moment tensors, so without a copy ``a``'s later updates would move ``b``'s Adam moments too."""
    data = _data()
    torch.manual_seed(0)
    original = ALGOS[name]()
    train_data = original.prepare(data, PrepareContext(generator=torch.Generator().manual_seed(5)))
    _updates(original, train_data, 7, seed=1)
    loaded = ALGOS[name]()
    loaded.load_state_dict(original.state_dict())
    snapshot = copy.deepcopy(loaded.state_dict())
    _updates(original, train_data, 3, seed=2)
    _assert_same(loaded.state_dict(), snapshot)


class _Kill(BaseException):
    """Stands in for SIGKILL: raised mid-run, caught by nothing, leaves the disk as it is."""


def _killing(algo, at: int):
    update, calls = algo.update, [0]

    def dying_update(batch):
        calls[0] += 1
        if calls[0] == at:
            raise _Kill
        return update(batch)

    algo.update = dying_update
    return algo


def test_training_loop_resumed_from_its_checkpoint_equals_the_uninterrupted_loop(tmp_path):
    data = _data(200)
    kwargs = dict(evaluate=lambda policy: [float(policy(data[:5].select("observation"))["action"].sum())],
                  eval_every_epochs=40 / 1e6, log_every=3, progress=False)

    def fresh():
        torch.manual_seed(0)
        return BehaviourCloning(4, SPEC, algo_config("bc", **{**POLICY, "batch_size": 8, "epochs": 200 / 1e6}))

    reference_algo = fresh()
    (reference,) = train(make_trainee([reference_algo], [data]), **kwargs)
    path = tmp_path / "checkpoint.pt"
    with pytest.raises(_Kill):
        train(make_trainee([_killing(fresh(), at=13)], [data]), checkpoint_paths=[path], checkpoint_every_s=0.0,
              **kwargs)
    state = torch.load(path, weights_only=False)
    assert state["iteration"] == 12  # checkpoint_every_s=0: one after every update
    resumed_algo = fresh()
    resumed_algo.load_state_dict(state["algorithm"])
    torch.manual_seed(99)  # the checkpoint's random streams replace whatever the process has
    (resumed,) = train(make_trainee([resumed_algo], [data]), checkpoint_paths=[path], resume_from=[state], **kwargs)
    assert resumed.evaluations == reference.evaluations and resumed.iterations == reference.iterations
    _assert_same(resumed_algo.state_dict(), reference_algo.state_dict())


# -- whole runs, in process, on a tiny generated batch --------------------------------------------------------------
TINY = ["+exp=hopper_ddpg05", "preset=quick", "batch.steps=1000", "batch.start_steps=200",
        "batch.agent.actor_hidden=[32,32]", "batch.agent.critic_hidden=[32,32]", "env.max_episode_steps=50",
        "eval.episodes=2", "eval.max_steps=50", "returns.horizon=50", "progress=false"]
RUN = {
    "bail": ["algo.epochs=0.012", "eval.every_epochs=0.004", "algo.envelope.epochs=3", "algo.envelope.batch_size=100",
             "algo.batch_size=100"],
    "bcq": ["algo=bcq", "algo.epochs=0.004", "eval.every_epochs=0.001", "algo.vae.hidden=[16,16]",
            "algo.actor.hidden=[16,16]", "algo.critic.hidden=[16,16]", "algo.batch_size=50"],
    # killed after odd and even updates: the actor's delay counts on from the checkpoint
    "td3bc": ["algo=td3bc", "algo.epochs=0.004", "eval.every_epochs=0.001", "algo.actor.hidden=[16,16]",
              "algo.critic.hidden=[16,16]", "algo.batch_size=50"],
}


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("batches")


def _cfg(data_dir, *overrides):
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        return compose("config", overrides=[*TINY, f"data_dir={data_dir}", *overrides])


def _outputs(run_dir) -> dict:
    summary = json.loads((run_dir / "summary.json").read_text())
    for volatile in ("wall_time_s", "run_dir", "batch_path", "resumed_from_iteration"):
        summary.pop(volatile)
    logs = {p.relative_to(run_dir).as_posix(): p.read_text() for p in (run_dir / "logs").rglob("*.csv")}
    weights = torch.load(run_dir / "checkpoint.pt", weights_only=False)["algorithm"]["modules"]
    return {"summary": summary, "logs": logs, "weights": weights}


@pytest.mark.parametrize("algo", list(RUN))
def test_runs_killed_at_random_points_resume_to_the_reference(tmp_path, data_dir, monkeypatch, algo):
    from torchrl_bail import train as train_module

    cfg = _cfg(data_dir, *RUN[algo])
    train_module.run(cfg, tmp_path / "reference")
    reference = _outputs(tmp_path / "reference")
    assert reference["logs"]  # scalars were logged
    total = json.loads((tmp_path / "reference" / "summary.json").read_text())["iterations"]
    build, one_epoch = algorithms_module.build_algorithm, envelope_module.train_one_epoch
    rng = random.Random(algo)
    first = rng.randint(2, total // 2)
    kills = [first, rng.randint(first + 1, total - 1)]  # killed at these iterations, then a clean finish
    if algo == "bail":  # and once during the envelope fit, before the first checkpoint
        kills.insert(0, 0)
    run_dir = tmp_path / "killed"
    for kill in kills:
        checkpoint = run_dir / "checkpoint.pt"
        done = torch.load(checkpoint, weights_only=False)["iteration"] if checkpoint.exists() else 0
        at = kill - done  # the update of this process that dies

        def dying_build(*args, at=at, **kwargs):
            return _killing(build(*args, **kwargs), at)

        def dying_epoch(*args, epochs=[0], **kwargs):  # noqa: B006 - the count of this process' envelope epochs
            epochs[0] += 1
            if epochs[0] == 2:  # in the envelope fit's second epoch
                raise _Kill
            return one_epoch(*args, **kwargs)

        if at == 0:
            monkeypatch.setattr(envelope_module, "train_one_epoch", dying_epoch)
        else:
            monkeypatch.setattr(algorithms_module, "build_algorithm", dying_build)
        with pytest.raises(_Kill):
            train_module.run(cfg, run_dir)
        monkeypatch.setattr(envelope_module, "train_one_epoch", one_epoch)
    monkeypatch.setattr(algorithms_module, "build_algorithm", build)
    (summary,) = train_module.run(cfg, run_dir)
    assert summary["resumed_from_iteration"], "the last start resumed from a checkpoint"
    resumed = _outputs(run_dir)
    assert resumed["summary"] == reference["summary"]
    assert resumed["logs"] == reference["logs"]
    _assert_same(resumed["weights"], reference["weights"])


def test_finished_run_is_reported_and_changed_config_refused(tmp_path, data_dir, monkeypatch, caplog):
    from torchrl_bail import train as train_module

    run_dir = tmp_path / "run"
    cfg = _cfg(data_dir, "algo=bc", "algo.epochs=0.002", "eval.every_epochs=0.001")
    (first,) = train_module.run(cfg, run_dir)
    monkeypatch.setattr(trainer_module, "train", lambda *a, **k: pytest.fail("a finished run was trained again"))
    with caplog.at_level("INFO", logger="torchrl_bail"):
        (again,) = train_module.run(cfg, run_dir)
    assert again == first and again["resumed_from_iteration"] == []
    assert "already complete" in caplog.text and "summary.json" in caplog.text
    # run-only keys may change; anything else is refused, naming the key
    train_module.run(_cfg(data_dir, "algo=bc", "algo.epochs=0.002", "eval.every_epochs=0.001", "logger.backend=csv",
                          "progress=true"), run_dir)
    with pytest.raises(ResumeError, match=r"algo\.epochs: 0\.002 -> 0\.004"):
        train_module.run(_cfg(data_dir, "algo=bc", "algo.epochs=0.004", "eval.every_epochs=0.001"), run_dir)
    monkeypatch.undo()
    (restarted,) = train_module.run(_cfg(data_dir, "algo=bc", "algo.epochs=0.004", "eval.every_epochs=0.001",
                                      "resume=false"), run_dir)
    assert restarted["iterations"] == 2 * first["iterations"]


def test_checkpoints_written_before_a_key_existed_still_resume(tmp_path, data_dir, monkeypatch):
    """``compile`` and ``seeds`` came after runs were made: an older checkpoint lacks them (and one of the first
    ``seeds`` version stored ``seeds: None``); at their defaults both resume, another value is refused."""
    from torchrl_bail import train as train_module
    from torchrl_bail.training.resume import ADDED_KEYS

    run_dir = tmp_path / "run"
    cfg = _cfg(data_dir, "algo=bc", "algo.epochs=0.002", "eval.every_epochs=0.001")
    (first,) = train_module.run(cfg, run_dir)
    monkeypatch.setattr(trainer_module, "train", lambda *a, **k: pytest.fail("a finished run was trained again"))
    path = run_dir / "checkpoint.pt"
    checkpoint = torch.load(path, weights_only=False)
    assert not set(ADDED_KEYS) & set(checkpoint["config"])  # written at the defaults: left out
    for old_layout in ({}, {"seeds": None}, {"seeds": None, "compile": False}):
        torch.save({**checkpoint, "config": {**checkpoint["config"], **old_layout}}, path)
        assert train_module.run(cfg, run_dir) == [first]
    torch.save({**checkpoint, "config": {**checkpoint["config"], "compile": True}}, path)
    with pytest.raises(ResumeError, match=r"compile: True -> \(absent\)"):
        train_module.run(cfg, run_dir)


def test_resume_from_another_run_dir_and_the_lock(tmp_path, data_dir):
    from torchrl_bail import train as train_module

    cfg = _cfg(data_dir, "algo=bc", "algo.epochs=0.002", "eval.every_epochs=0.001")
    source = tmp_path / "old_run"
    (expected,) = train_module.run(cfg, source)
    (moved,) = train_module.run(_cfg(data_dir, "algo=bc", "algo.epochs=0.002", "eval.every_epochs=0.001",
                                  f"resume={source}"), tmp_path / "new_run")
    assert moved["final_return"] == expected["final_return"] and moved["resumed_from_iteration"] == [2]
    assert (tmp_path / "new_run" / "logs" / "scalars" / "eval" / "return.csv").read_text() == \
        (source / "logs" / "scalars" / "eval" / "return.csv").read_text()
    with Resumption(cfg, tmp_path / "busy"):
        with pytest.raises(ResumeError, match=rf"in use by another process \({host_name()}:{os.getpid()}\)"):
            with Resumption(cfg, tmp_path / "busy"):
                pass
    assert not (tmp_path / "busy" / RUN_LOCK).exists(), "the lock is released with the run"


def _foreign_lock(run_dir, **extra):
    run_dir.mkdir(parents=True, exist_ok=True)
    owner = {"host": "otherhost-that-is-not-us", "pid": 4242, "start_time": 1, "token": "theirs", **extra}
    (run_dir / RUN_LOCK).write_text(json.dumps(owner))
    return run_dir / RUN_LOCK


def test_the_run_directory_lock_is_the_batches_owner_file_lock(tmp_path, data_dir, monkeypatch, caplog):
    """Another host's live run (its heartbeat moves) is refused; a killed one's lock (no heartbeat for
    RUN_LOCK_STALE_AFTER_S, a Slurm job requeued on another node) is taken over; a dead local pid's at once."""
    cfg = _cfg(data_dir, "algo=bc")
    monkeypatch.setattr(resume_module, "RUN_LOCK_STALE_AFTER_S", 3.0)
    lock = _foreign_lock(tmp_path / "live")
    beating = threading.Event()

    def heartbeat():
        while not beating.wait(0.1):
            os.utime(lock, None)

    beater = threading.Thread(target=heartbeat, daemon=True)
    beater.start()
    try:
        with pytest.raises(ResumeError, match=r"in use by another process \(otherhost-that-is-not-us:4242\)"):
            with Resumption(cfg, tmp_path / "live"):
                pass
    finally:
        beating.set()
        beater.join()
    assert json.loads(lock.read_text())["token"] == "theirs", "a live owner's lock is left alone"

    caplog.set_level("INFO", logger="torchrl_bail")
    old = time.time() - 2.0
    os.utime(lock, (old, old))  # killed two seconds ago: no heartbeat comes
    start = time.monotonic()
    with Resumption(cfg, tmp_path / "live"):
        taken_at = time.time()  # the clock of the lock's mtime
        assert json.loads(lock.read_text())["host"] == host_name()
    assert taken_at - old >= 3.0, "taken over once its heartbeat is RUN_LOCK_STALE_AFTER_S old, not before"
    assert time.monotonic() - start < 10, "and not much later"
    assert "taking it over if none comes" in caplog.text and "taking over the lock .lock" in caplog.text

    monkeypatch.setattr(resume_module, "RUN_LOCK_STALE_AFTER_S", 600.0)
    _foreign_lock(tmp_path / "killed_here", host=host_name(), pid=999_999_999, **process_table_identity())
    start = time.monotonic()
    with Resumption(cfg, tmp_path / "killed_here"):
        pass
    assert time.monotonic() - start < 5, "a dead pid of this host: taken over at once, whatever the heartbeat"

    (tmp_path / "flock_era").mkdir()
    (tmp_path / "flock_era" / RUN_LOCK).write_text("12345")  # what the flock-based versions left behind
    with Resumption(cfg, tmp_path / "flock_era"):
        assert json.loads((tmp_path / "flock_era" / RUN_LOCK).read_text())["pid"] == os.getpid()


def test_a_run_whose_directory_was_taken_over_stops_before_its_next_checkpoint(tmp_path, data_dir):
    cfg = _cfg(data_dir, "algo=bc")
    with Resumption(cfg, tmp_path / "run") as resumption:
        resumption.checkpoint_extra()  # ours: fine
        _foreign_lock(tmp_path / "run")  # a job elsewhere took it over while this one was suspended
        with pytest.raises(ResumeError, match="was taken over by another job .* stopping without writing"):
            resumption.checkpoint_extra()
    assert json.loads((tmp_path / "run" / RUN_LOCK).read_text())["token"] == "theirs", "the new owner's is kept"


def test_run_dirs_are_derived_from_the_config_and_slurm_requeues():
    from hydra.core.hydra_config import HydraConfig

    def dirs(*overrides):
        with initialize_config_dir(str(config_dir()), version_base="1.3"):
            cfg = compose("config", overrides=list(overrides), return_hydra_config=True)
        HydraConfig.instance().set_config(cfg)
        return cfg.hydra.run.dir, f"{cfg.hydra.sweep.dir}/{cfg.hydra.sweep.subdir}"

    run, sweep = dirs("+exp=hopper_ddpg05", "seed=2")
    assert run == sweep == "outputs/hopper_ddpg05_b1/bail/seed2"  # no clock: a rerun finds its own directory
    assert dirs("+exp=hopper_ddpg05", "algo=bc", "preset=quick", "progress=false")[0] == \
        "outputs/hopper_ddpg05_b1/bc/seed1,preset=quick"
    assert dirs("+exp=hopper_ddpg05", "algo.epochs=3", "preset=quick") == \
        dirs("+exp=hopper_ddpg05", "preset=quick", "algo.epochs=3")  # order does not matter
    assert dirs("+exp=hopper_ddpg05", "algo.epochs=3")[0] != dirs("+exp=hopper_ddpg05", "algo.epochs=4")[0]
    # a dataset= run is filed under its dataset's name, not under the batch group it never reads
    run, sweep = dirs("dataset=/data/hopper_medium-v2.hdf5", "env=hopper", "algo=bc")
    assert run == sweep == "outputs/hopper_medium-v2/bc/seed1"
    other = dirs("dataset=/data/hopper_expert-v2.hdf5", "env=hopper", "algo=bc")[0]
    assert other == "outputs/hopper_expert-v2/bc/seed1", "two datasets, two directories"
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("config", overrides=["+exp=hopper_ddpg05", "hydra/launcher=slurm"], return_hydra_config=True)
    assert cfg.hydra.launcher.max_num_timeout > 0  # a timed-out job is requeued, and resumes


def test_a_dataset_run_records_and_groups_by_its_dataset_not_the_unread_batch(tmp_path):
    from omegaconf import OmegaConf

    from torchrl_bail.training.resume import _comparable, comparable_config, diff_configs, record_config

    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        generated = compose("config", overrides=["+exp=hopper_ddpg05"])
        imported = compose("config", overrides=["dataset=/data/hopper_medium-v2.hdf5", "env=hopper", "algo=bc"])
    assert (generated.logger.group, imported.logger.group) == ("hopper_ddpg05_b1", "hopper_medium-v2")
    record_config(imported, tmp_path / "config.yaml")
    recorded = OmegaConf.to_container(OmegaConf.load(tmp_path / "config.yaml"))
    assert "batch" not in recorded and recorded["dataset"] == "/data/hopper_medium-v2.hdf5"
    assert "batch" not in comparable_config(imported)
    # a checkpoint of an older dataset run, which recorded the batch group, still resumes
    older = {**OmegaConf.to_container(imported, resolve=True), "batch": {"kind": "ddpg05"}}
    assert diff_configs(_comparable(older), comparable_config(imported)) == []
    # a generated batch's run records exactly what it recorded before
    record_config(generated, tmp_path / "generated.yaml")
    OmegaConf.save(generated, tmp_path / "saved.yaml", resolve=True)
    assert (tmp_path / "generated.yaml").read_text() == (tmp_path / "saved.yaml").read_text()

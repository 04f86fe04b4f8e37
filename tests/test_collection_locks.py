"""Many machines, one data directory: owner files with host, pid and start time; heartbeats; another host's live
lock or scratch directory is never removed, a stale one is taken over; two jobs wanting one batch make it once."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

from torchrl_bail.data.locks import (
    LOCKS,
    OWNER_FILE,
    SCRATCH,
    clean_stale,
    file_lock,
    host_name,
    owned_name,
    owner_alive,
    owner_record,
    scratch_directory,
)

SRC = str(Path(__file__).resolve().parents[1] / "src")
OTHER = "otherhost-that-is-not-us"


def _age(path: Path, seconds: float) -> None:
    """Makes ``path``'s heartbeat (mtime) ``seconds`` old."""
    t = time.time() - seconds
    os.utime(path, (t, t))


def _foreign_owner(**extra) -> dict:
    return {"host": OTHER, "pid": os.getpid(), "start_time": 1, "created": time.time(), **extra}


def _dead_name(stem: str) -> str:
    """A private name of a dead process of this host, boot and pid namespace (:func:`owned_name`'s format)."""
    return owned_name(stem).replace(f".{os.getpid()}.", ".999999999.", 1)


def test_owner_records_name_host_pid_and_start_time():
    me = owner_record()
    assert me["host"] == host_name() and me["pid"] == os.getpid()
    assert owner_alive(me, heartbeat_age_s=10**6, stale_after_s=1), "a live local process is alive, heartbeat or not"
    assert not owner_alive({**me, "pid": 999_999_999}, 0.0, 600), "a dead local pid is gone at once"
    if me["start_time"] is not None:
        assert not owner_alive({**me, "start_time": me["start_time"] + 1}, 0.0, 600), "a recycled pid is not it"
    foreign = _foreign_owner()
    assert owner_alive(foreign, 599.0, 600) and not owner_alive(foreign, 601.0, 600)


def test_another_hosts_lock_is_waited_for_while_its_heartbeat_is_fresh_then_taken_over(tmp_path, caplog):
    lock = tmp_path / LOCKS / "b.lock"
    lock.parent.mkdir()
    lock.write_text(json.dumps(_foreign_owner(token="theirs", what="hopper_ddpg05_b1-xxxx")))
    got = threading.Event()

    def take():
        with file_lock(lock, stale_after_s=5.0, heartbeat_every_s=0.1, poll_s=0.05):
            got.set()
            time.sleep(0.3)

    caplog.set_level("INFO", logger="torchrl_bail")
    worker = threading.Thread(target=take, daemon=True)
    worker.start()
    time.sleep(1.0)
    assert not got.is_set(), "a fresh heartbeat from another host means: wait"
    assert json.loads(lock.read_text())["token"] == "theirs", "another host's live lock is never removed"
    assert f"waiting for {OTHER}:{os.getpid()}, which is making hopper_ddpg05_b1-xxxx" in caplog.text
    _age(lock, 60)  # its heartbeat stops
    assert got.wait(10), "a stale lock is taken over"
    worker.join(10)
    assert not lock.exists(), "our own lock is released on exit"
    assert "taking over the lock b.lock" in caplog.text


def test_the_heartbeat_keeps_our_lock_and_scratch_fresh(tmp_path):
    lock = tmp_path / LOCKS / "b.lock"
    with file_lock(lock, heartbeat_every_s=0.05), scratch_directory(tmp_path, "b", heartbeat_every_s=0.05) as scratch:
        owner = json.loads((scratch / OWNER_FILE).read_text())
        assert owner["host"] == host_name() and owner["pid"] == os.getpid()
        assert scratch.name.split(".")[1:3] == [host_name(), str(os.getpid())]
        _age(lock, 100)
        _age(scratch / OWNER_FILE, 100)
        time.sleep(0.5)
        assert time.time() - lock.stat().st_mtime < 5
        assert time.time() - (scratch / OWNER_FILE).stat().st_mtime < 5
    assert not scratch.exists() and not lock.exists()


def test_scratch_of_another_host_is_kept_while_fresh_and_removed_when_stale(tmp_path):
    theirs = tmp_path / SCRATCH / f"b.{OTHER}.{os.getpid()}.abcd1234"
    theirs.mkdir(parents=True)
    (theirs / OWNER_FILE).write_text(json.dumps(_foreign_owner()))
    dead_here = tmp_path / SCRATCH / _dead_name("c")
    dead_here.mkdir()
    legacy = tmp_path / SCRATCH / "d.999999999.abcd1234"  # old name, no host: judged by age only
    legacy.mkdir()
    # an older version's name (host and pid, no namespace): maybe a container's of this host name, so judged by age
    older = tmp_path / SCRATCH / f"e.{host_name()}.999999999.abcd1234"
    older.mkdir()
    assert clean_stale(tmp_path, stale_after_s=60) == [dead_here]
    assert theirs.exists() and legacy.exists() and older.exists(), \
        "another host's (or an unknown) owner is presumed alive while fresh"
    _age(theirs / OWNER_FILE, 120)
    _age(legacy, 120)
    _age(older, 120)
    assert sorted(clean_stale(tmp_path, stale_after_s=60)) == sorted([theirs, legacy, older])


def _child(data_dir: Path, overrides: list[str]) -> str:
    return textwrap.dedent(f"""
        import logging, sys
        sys.path.insert(0, {SRC!r})
        from hydra import compose, initialize_config_dir
        from torchrl_bail import config_dir
        from torchrl_bail.behaviour import catalogue
        logging.basicConfig(level=logging.INFO, format="%(message)s")
        original = catalogue.collect_batch
        def collect_batch(*args, **kwargs):
            print("COLLECTING", flush=True)
            return original(*args, **kwargs)
        catalogue.collect_batch = collect_batch
        with initialize_config_dir(str(config_dir()), version_base="1.3"):
            cfg = compose("config", overrides={overrides!r})
        batch = catalogue.ensure_batch(cfg, progress=False, data_dir={str(data_dir)!r})
        print("BATCH", batch.path, batch.num_transitions, flush=True)
    """)


def test_two_jobs_asking_for_the_same_batch_make_it_once(tmp_path):
    overrides = ["+exp=hopper_ddpg05", "batch.steps=300", "batch.start_steps=300", "env.max_episode_steps=30",
                 "batch.agent.actor_hidden=[8]", "batch.agent.critic_hidden=[8,8]"]
    env = {**os.environ, "RL_WARNINGS": "0", "OMP_NUM_THREADS": "1"}
    procs = [subprocess.Popen([sys.executable, "-c", _child(tmp_path, overrides)], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True, env=env) for _ in range(2)]
    outs = [p.communicate(timeout=300) for p in procs]
    assert all(p.returncode == 0 for p in procs), [err[-2000:] for _, err in outs]
    assert sum(out.count("COLLECTING") for out, _ in outs) == 1, "the batch is collected once"
    paths = {line.split()[1] for out, _ in outs for line in out.splitlines() if line.startswith("BATCH")}
    assert len(paths) == 1
    assert all(line.split()[2] == "300" for out, _ in outs for line in out.splitlines() if line.startswith("BATCH"))


def test_a_job_whose_lock_was_taken_over_stops_before_writing(tmp_path):
    from torchrl_bail.data.locks import HEARTBEAT, LockLost

    lock = tmp_path / LOCKS / "b.lock"
    with file_lock(lock, heartbeat_every_s=60):
        HEARTBEAT.check()  # ours: fine
        lock.write_text(json.dumps(_foreign_owner(token="theirs")))  # another host took it over
        try:
            HEARTBEAT.check()
        except LockLost:
            pass
        else:
            raise AssertionError("a lost lock must stop the job before it writes")
    assert json.loads(lock.read_text())["token"] == "theirs", "the new owner's lock is left alone"
    HEARTBEAT.check()  # released: nothing lost any more


def test_a_cached_batch_clears_the_scratch_a_dead_collector_left_behind(tiny_run_data_dir):
    """A collector killed between saving its batch and removing its scratch directory leaves the scratch behind; the
    next job that finds the batch cached removes it (its owner is a dead process of this host) and keeps a live
    one's."""
    from _contract import TINY_RUN
    from hydra import compose, initialize_config_dir

    from torchrl_bail import config_dir
    from torchrl_bail.behaviour.catalogue import ensure_batch

    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("config", overrides=[*TINY_RUN, f"data_dir={tiny_run_data_dir}"])
    made = ensure_batch(cfg, progress=False, data_dir=tiny_run_data_dir)  # made here or by an earlier test
    dead = tiny_run_data_dir / SCRATCH / _dead_name(made.path.name)
    dead.mkdir(parents=True)
    (dead / "data.bin").write_bytes(b"\0" * 1024)
    with scratch_directory(tiny_run_data_dir, "live") as live:
        assert ensure_batch(cfg, progress=False, data_dir=tiny_run_data_dir).path == made.path
        assert not dead.exists() and live.exists()

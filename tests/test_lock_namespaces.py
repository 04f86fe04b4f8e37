"""Lock owners told apart where host names collide, and stale owners fenced (issue 54, item 2).

Containers of one node often share a host name (Docker ``--hostname``, Slurm jobs in containers, pods on a node's
network) but not a pid namespace: a waiter must not look up such an owner's pid in its own process table. The
``unshare`` tests run real jobs in fresh pid namespaces on this host (each one is pid 1 there, with our host name);
they are skipped where ``unshare --pid --fork --mount-proc`` cannot run (CI runs as root). The fencing tests take a
lock over from a stale owner and check that the old owner can publish no checkpoint and no batch any more.

The module imports only what older versions of :mod:`torchrl_bail.data.locks` had too, so that the ``unshare``
take-over test also runs against them (it failed there: the second job took the first one's live lock over).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

from torchrl_bail.data import locks
from torchrl_bail.data.locks import LOCKS, LockLost, file_lock, host_name, partial_directory

SRC = Path(__file__).resolve().parents[1] / "src"
_ENV = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "RL_WARNINGS": "0"}


def _unshare_problem() -> str | None:
    """Why a job cannot be started in a fresh pid namespace here (``None``: it can)."""
    if not sys.platform.startswith("linux"):
        return "pid namespaces are Linux's"
    if shutil.which("unshare") is None:
        return "no unshare(1) on this machine"
    try:
        probe = subprocess.run(["unshare", "--pid", "--fork", "--mount-proc", "true"], capture_output=True,
                               text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired) as err:
        return f"unshare --pid --fork --mount-proc true failed: {err}"
    if probe.returncode != 0:
        return (f"unshare --pid --fork --mount-proc true exited {probe.returncode} (needs root or user namespaces): "
                f"{probe.stderr.strip()[:200]}")
    return None


UNSHARE_PROBLEM = _unshare_problem()
needs_unshare = pytest.mark.skipif(UNSHARE_PROBLEM is not None, reason=str(UNSHARE_PROBLEM))

#: what every job of these tests runs first: ``torchrl_bail.data.locks`` without ``torchrl_bail.data``'s
#: ``__init__`` (which imports torch), logging to stderr, and a journal of its critical sections written inside the
#: lock (epoch ns, event, pid as the job sees it, role)
_PRELUDE = """
import logging, os, sys, time, types
from pathlib import Path
sys.path.insert(0, {src!r})
import torchrl_bail
package = types.ModuleType("torchrl_bail.data")
package.__path__ = [os.path.join({src!r}, "torchrl_bail", "data")]
sys.modules["torchrl_bail.data"] = package
from torchrl_bail.data.locks import HEARTBEAT, LockLost, file_lock
logging.basicConfig(level=logging.INFO, format="[%(levelname)s] %(message)s")
JOURNAL, ROLE = {journal!r}, {role!r}

def note(event):
    fd = os.open(JOURNAL, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        os.write(fd, f"{{time.time_ns()}} {{event}} {{os.getpid()}} {{ROLE}}\\n".encode())
    finally:
        os.close(fd)
"""

#: a job that holds the lock for ``hold_s`` seconds, checking all along that it still owns it
_HOLDER = _PRELUDE + """
lock = Path({lock!r})
with file_lock(lock, stale_after_s={stale_after_s}, heartbeat_every_s={heartbeat_every_s}, poll_s=0.05):
    note("enter")
    until = time.monotonic() + {hold_s}
    try:
        while time.monotonic() < until:
            HEARTBEAT.check(lock)
            time.sleep(0.05)
    except LockLost as err:
        note("LOST")
        print("LOST:", err, file=sys.stderr, flush=True)
    note("exit")
"""


def _job(tmp_path: Path, role: str, **params) -> subprocess.Popen:
    """Starts a holder job in a fresh pid namespace (pid 1 there, our host name), in its own process group."""
    code = textwrap.dedent(_HOLDER).format(src=str(SRC), journal=str(tmp_path / "journal"), role=role,
                                           lock=str(tmp_path / LOCKS / "b.lock"), **params)
    log = open(tmp_path / f"{role}.log", "w")  # noqa: SIM115 -- closed when the test reads it
    return subprocess.Popen(["unshare", "--pid", "--fork", "--mount-proc", sys.executable, "-c", code],
                            stdout=log, stderr=subprocess.STDOUT, env=_ENV, start_new_session=True)


def _journal(tmp_path: Path) -> list[tuple[int, str, int, str]]:
    path = tmp_path / "journal"
    if not path.exists():
        return []
    rows = (line.split() for line in path.read_text().splitlines())
    return sorted((int(r[0]), r[1], int(r[2]), r[3]) for r in rows if len(r) == 4)


def _wait_for(tmp_path: Path, event: str, role: str, timeout: float = 60.0) -> int:
    """The time (epoch ns) of ``role``'s first ``event`` in the journal, waiting for it."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        found = [t for t, e, _, r in _journal(tmp_path) if e == event and r == role]
        if found:
            return found[0]
        time.sleep(0.02)
    raise AssertionError(f"{role} never logged {event!r}: {_journal(tmp_path)}")


@needs_unshare
def test_a_same_named_container_never_takes_over_a_live_lock(tmp_path):
    """Two jobs with one host name, each in its own pid namespace (two containers of one node): A holds the lock
    for 5 s; B, started once A holds it, waits with a 2 s staleness timeout. A's pid (1) names another process in
    B's namespace, so B must judge A by its heartbeat, which keeps moving: B waits for A to release the lock,
    neither logs an error and the critical sections do not overlap. (Before the fix B logged "taking over the lock
    b.lock of <host>:1 (process gone)" at once, and A "[ERROR] lock ... was taken over by another job".)"""
    (tmp_path / LOCKS).mkdir()
    a = _job(tmp_path, "A", stale_after_s=2.0, heartbeat_every_s=0.2, hold_s=5.0)
    try:
        _wait_for(tmp_path, "enter", "A")
        b = _job(tmp_path, "B", stale_after_s=2.0, heartbeat_every_s=0.2, hold_s=0.2)
        try:
            assert b.wait(60) == 0 and a.wait(60) == 0
        finally:
            b.kill()
    finally:
        a.kill()
    logs = {role: (tmp_path / f"{role}.log").read_text() for role in ("A", "B")}
    rows = _journal(tmp_path)
    where = f"journal {rows}\nA's log:\n{logs['A']}\nB's log:\n{logs['B']}"
    assert {pid for _, _, pid, _ in rows} == {1}, "each job is pid 1 of its own namespace: " + where
    assert "taking over" not in logs["B"], "B took over the live lock of A: " + where
    assert "[ERROR]" not in logs["A"] and "LOST" not in logs["A"], "A lost its live lock: " + where
    (a_in, a_out), (b_in, _) = ([t for t, e, _, r in rows if r == role and e in ("enter", "exit")] for role in "AB")
    assert b_in >= a_out, f"B entered {(a_out - b_in) / 1e9:.2f} s before A left: " + where
    assert (a_out - a_in) / 1e9 >= 4.5, "A held the lock to the end: " + where
    assert "waiting for" in logs["B"] and f"{host_name()}:1" in logs["B"], where


@needs_unshare
def test_a_killed_owner_in_another_pid_namespace_is_taken_over_by_its_heartbeat(tmp_path, caplog):
    """A job in another pid namespace with our host name that is SIGKILLed leaves its lock; a job here cannot see
    its process, so it takes the lock over once its heartbeat is ``stale_after_s`` old -- not at once, not never."""
    (tmp_path / LOCKS).mkdir()
    a = _job(tmp_path, "A", stale_after_s=1.5, heartbeat_every_s=0.2, hold_s=120.0)
    try:
        _wait_for(tmp_path, "enter", "A")
        time.sleep(0.5)  # a few heartbeats
        os.killpg(a.pid, signal.SIGKILL)
        a.wait(30)
        killed = time.time()
    finally:
        a.kill()
    caplog.set_level("INFO", logger="torchrl_bail")
    lock = tmp_path / LOCKS / "b.lock"
    assert json.loads(lock.read_text())["pid"] == 1, "the killed job's lock is left behind"
    with file_lock(lock, stale_after_s=1.5, heartbeat_every_s=0.2, poll_s=0.05):
        took = time.time()
        assert json.loads(lock.read_text())["pid"] == os.getpid()
    assert took - killed >= 1.5 - 0.2 - 0.1, f"taken over {took - killed:.2f} s after the kill: before a missed beat"
    assert took - killed < 15
    assert f"taking over the lock b.lock of {host_name()}:1 (no heartbeat for" in caplog.text, caplog.text


def test_owner_identity_separates_pid_namespaces_and_boots(monkeypatch):
    """Only an owner of this host name, boot and pid namespace is judged by its pid; another namespace's, another
    boot's and an older version's (host and pid only) are judged by their heartbeat."""
    me = locks.owner_record()
    assert me["host"] == host_name() and me["pid"] == os.getpid()
    if me["boot_id"] is None or me["pid_ns"] is None:
        pytest.skip("no /proc here: every owner is judged by its heartbeat")
    assert me["pid_ns"] == os.readlink("/proc/self/ns/pid")
    assert me["boot_id"] == Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    dead = {**me, "pid": 999_999_999}
    assert locks.sees_process_table(me) and not locks.owner_alive(dead, 0.0, 600), "a dead pid here: gone at once"
    container = {**dead, "pid_ns": "pid:[1]"}  # another container of this node, same host name
    rebooted = {**dead, "boot_id": "00000000-0000-0000-0000-000000000000"}
    older = {"host": host_name(), "pid": 999_999_999, "start_time": 1}  # an older version's owner file
    for owner in (container, rebooted, older):
        assert not locks.sees_process_table(owner)
        assert locks.owner_alive(owner, 599.0, 600), f"not provably gone while its heartbeat is fresh: {owner}"
        assert not locks.owner_alive(owner, 601.0, 600), f"gone once its heartbeat is stale: {owner}"
    live_elsewhere = {**me, "pid_ns": "pid:[1]", "start_time": -1}  # our pid and host name, another namespace
    assert not locks.owner_alive(live_elsewhere, 601.0, 600), "our pid here says nothing about its process"
    name = locks.owned_name("b")
    assert name.split(".")[1:3] == [host_name(), str(os.getpid())] and name.split(".")[3].startswith("ns")
    monkeypatch.setattr(locks, "process_table_identity", lambda: {"boot_id": None, "pid_ns": None})
    assert not locks.sees_process_table(me), "where this process's own namespace is unknown, nothing is judged here"


def test_an_older_versions_lock_on_this_host_name_waits_for_its_heartbeat(tmp_path, caplog):
    """A lock written by an older version (host and pid only) with our host name and a dead pid may be another
    container's: it is taken over once its heartbeat is ``stale_after_s`` old, not at once."""
    lock = tmp_path / LOCKS / "b.lock"
    lock.parent.mkdir()
    lock.write_text(json.dumps({"host": host_name(), "pid": 999_999_999, "start_time": 1, "token": "old",
                                "created": time.time(), "what": "b"}))
    got = threading.Event()

    def take():
        with file_lock(lock, stale_after_s=1.0, poll_s=0.02):
            got.set()

    caplog.set_level("INFO", logger="torchrl_bail")
    worker = threading.Thread(target=take, daemon=True)
    worker.start()
    time.sleep(0.5)
    assert not got.is_set() and json.loads(lock.read_text())["token"] == "old", "not provably gone: wait"
    assert got.wait(10)
    worker.join(10)
    assert f"taking over the lock b.lock of {host_name()}:999999999 (no heartbeat for" in caplog.text


# -- fencing -------------------------------------------------------------------------------------------------------
class _Store:
    """A stand-in for an :class:`~torchrl_bail.behaviour.buffers.EpisodeStore`: ``len`` and ``data()``."""

    def __init__(self, rows: int, value: float, before_data=None):
        self.td = TensorDict({"x": torch.full((rows, 2), value)}, [rows])
        self.before_data = before_data

    def __len__(self) -> int:
        return self.td.shape[0]

    def data(self) -> TensorDict:
        if self.before_data is not None:
            self.before_data()
        return self.td


def _files(directory: Path) -> dict[str, bytes]:
    return {p.relative_to(directory).as_posix(): p.read_bytes() for p in sorted(directory.rglob("*")) if p.is_file()}


def _tiny_batch(n: int = 6) -> TensorDict:
    done = torch.zeros(n, 1, dtype=torch.bool)
    done[n // 2 - 1] = done[-1] = True
    return TensorDict({"observation": torch.zeros(n, 3), "action": torch.zeros(n, 2),
                       "episode": torch.tensor([0] * (n // 2) + [1] * (n - n // 2)),
                       "next": {"observation": torch.zeros(n, 3), "reward": torch.ones(n, 1), "done": done,
                                "terminated": done.clone(), "truncated": torch.zeros(n, 1, dtype=torch.bool)}},
                      [n])


class _Successor:
    """The job that takes the lock over from a stale owner (in a thread: a context of its own), saves its own
    checkpoint there and holds the lock until told to release it."""

    def __init__(self, lock: Path, directory: Path):
        from torchrl_bail.behaviour.checkpoint import CollectionCheckpoint

        self.lock, self.checkpoint = lock, CollectionCheckpoint(directory, every_s=None, every_steps=1)
        self.saved, self.release = threading.Event(), threading.Event()
        self.errors: list[BaseException] = []
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        try:
            with file_lock(self.lock, stale_after_s=1.0, heartbeat_every_s=0.05, poll_s=0.02) as held:
                self.token = held.token
                self.checkpoint.save({"loop": {"t": 100}, "who": "successor"}, {"x": _Store(8, 2.0)})
                self.saved.set()
                assert self.release.wait(30)
        except BaseException as err:  # noqa: BLE001 -- reported by the test
            self.errors.append(err)
            self.saved.set()


def _stale_owner(lock: Path, monkeypatch):
    """This thread takes ``lock`` as if it lived in another pid namespace of our host name (so that a waiter
    judges it by its heartbeat), then stops beating (suspended) with a heartbeat 1000 s old. Returns the open
    ``file_lock`` context."""
    with monkeypatch.context() as patch:
        patch.setattr(locks, "process_table_identity", lambda: {"boot_id": "another-boot", "pid_ns": "pid:[1]"})
        context = file_lock(lock, heartbeat_every_s=100.0)
        held = context.__enter__()
    assert json.loads(lock.read_text())["pid_ns"] == "pid:[1]"
    return context, held


def _suspend(lock: Path, held) -> None:
    locks.HEARTBEAT.unregister(lock, held.token)  # its heartbeat stops ...
    old = time.time() - 1000
    for _ in range(20):  # ... and is now far older than any grace (a beat under way when it stopped: again)
        os.utime(lock, (old, old))
        time.sleep(0.05)
        if lock.stat().st_mtime == old:
            break


def test_a_fenced_owner_cannot_publish_a_checkpoint_or_a_batch(tmp_path, monkeypatch, caplog):
    """A stale owner (suspended past the grace, in another pid namespace of our host name) is taken over; the new
    owner saves its checkpoint; then the old owner wakes up and saves: its checkpoint save raises ``LockLost``
    before publishing anything, so is its batch, and the new owner's files are intact."""
    from torchrl_bail.behaviour.checkpoint import CollectionCheckpoint
    from torchrl_bail.data.batch import save_batch

    lock, directory = tmp_path / LOCKS / "b.lock", partial_directory(tmp_path, "b")
    old = CollectionCheckpoint(directory, every_s=None, every_steps=1)
    successor = _Successor(lock, directory)
    context, held = _stale_owner(lock, monkeypatch)
    try:
        old.save({"loop": {"t": 1}, "who": "stale owner"}, {"x": _Store(4, 1.0)})  # still its lock: published
        _suspend(lock, held)
        caplog.set_level("INFO", logger="torchrl_bail")
        successor.thread.start()
        assert successor.saved.wait(30) and not successor.errors, successor.errors
        assert "taking over the lock b.lock" in caplog.text and "(no heartbeat for" in caplog.text
        theirs = _files(directory)
        with pytest.raises(LockLost, match=r"taken over by another job .*refusing to rename its checkpoint"):
            old.save({"loop": {"t": 2}, "who": "stale owner"}, {"x": _Store(8, 1.0)})
        with pytest.raises(LockLost, match="taken over by another job"):
            save_batch(_tiny_batch(), tmp_path / "batch", {"env_id": "Toy-v0"})
        assert _files(directory) == theirs, "the new owner's checkpoint is intact, nothing of the old one's added"
        assert not (tmp_path / "batch").exists() and not list(tmp_path.glob("batch.tmp-*"))
        state = torch.load(directory / "state.pt", weights_only=True)
        assert state["who"] == "successor" and state["loop"]["t"] == 100
        assert json.loads(lock.read_text())["token"] == successor.token, "the new owner keeps its lock"
    finally:
        successor.release.set()
        if successor.thread.is_alive():
            successor.thread.join(30)
        context.__exit__(None, None, None)
    assert not successor.errors, successor.errors
    assert not lock.exists(), "released by the new owner; the old owner removed nothing of it"


def test_a_take_over_during_a_save_fences_the_rename(tmp_path, monkeypatch):
    """The lock is taken over while the stale owner is in the middle of its checkpoint save (after the check at its
    start): the rename of its segment is refused, its temporary file removed, and the new owner's files kept."""
    from torchrl_bail.behaviour.checkpoint import CollectionCheckpoint

    lock, directory = tmp_path / LOCKS / "b.lock", partial_directory(tmp_path, "b")
    old = CollectionCheckpoint(directory, every_s=None, every_steps=1)
    successor = _Successor(lock, directory)
    context, held = _stale_owner(lock, monkeypatch)
    try:
        old.save({"loop": {"t": 1}, "who": "stale owner"}, {"x": _Store(4, 1.0)})

        def taken_over_now():  # the owner is suspended right here, and taken over
            _suspend(lock, held)
            successor.thread.start()
            assert successor.saved.wait(30) and not successor.errors, successor.errors

        with pytest.raises(LockLost, match="taken over by another job"):
            old.save({"loop": {"t": 2}, "who": "stale owner"}, {"x": _Store(8, 1.0, before_data=taken_over_now)})
        theirs = _files(successor.checkpoint.directory)
        assert sorted(theirs) == ["segments/x_000000000000_000000000004.pt",
                                  "segments/x_000000000000_000000000008.pt", "state.pt"], sorted(theirs)
        state = torch.load(directory / "state.pt", weights_only=True)
        assert state["who"] == "successor" and state["loop"]["t"] == 100
        segment = torch.load(directory / "segments/x_000000000000_000000000008.pt", weights_only=True)
        assert torch.equal(segment["x"], torch.full((8, 2), 2.0)), "the new owner's segment"
        assert not list(directory.rglob(".*")), "no temporary file of the refused save is left"
    finally:
        successor.release.set()
        if successor.thread.is_alive():
            successor.thread.join(30)
        context.__exit__(None, None, None)
    assert not successor.errors, successor.errors


def test_file_lock_yields_its_token_and_the_fence_follows_the_thread(tmp_path):
    """Each acquisition has a fresh token, written in the lock file; the fence checks the locks of the thread that
    holds them, and passes while they are ours."""
    lock = tmp_path / LOCKS / "b.lock"
    tokens = []
    for _ in range(2):
        with file_lock(lock) as held:
            assert json.loads(lock.read_text())["token"] == held.token and held.holds()
            assert locks.held_locks() == (held,)
            locks.check_fence()
            tokens.append(held.token)
        assert locks.held_locks() == ()
    assert tokens[0] != tokens[1]


def test_a_fenced_training_run_cannot_overwrite_its_successors_checkpoint(tmp_path):
    """A training run's checkpoint (:func:`torchrl_bail.training.trainer.save_checkpoint`) is fenced as a collection's
    is: once
    the run directory's lock carries another job's token, the save raises ``LockLost`` before its rename, the
    successor's ``checkpoint.pt`` is untouched and no temporary file is left."""
    from torchrl_bail.training.trainer import save_checkpoint

    lock, target = tmp_path / "run.lock", tmp_path / "checkpoint.pt"
    with file_lock(lock, heartbeat_every_s=100.0) as held:
        save_checkpoint(target, {"who": "owner"})  # its own lock: published
        record = json.loads(lock.read_text())
        assert record["token"] == held.token
        lock.write_text(json.dumps({**record, "token": "the-successors-token"}))  # taken over meanwhile
        torch.save({"who": "successor"}, target)
        theirs = target.read_bytes()
        with pytest.raises(LockLost, match="taken over by another job"):
            save_checkpoint(target, {"who": "owner, woken up"})
        assert target.read_bytes() == theirs and sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint.pt",
                                                                                                 "run.lock"]
        lock.write_text(json.dumps(record))  # back to its own token, so that the context releases it cleanly

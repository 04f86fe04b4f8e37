"""Collecting a batch safely when several jobs -- on several hosts -- share one ``data_dir``: owner records,
heartbeats, locks, scratch and partial directories. Training runs lock their run directories with the same
:func:`file_lock` (``wait=False``: :mod:`torchrl_bail.training.resume`).

Interruption: nothing is ever written under a batch's final name until it is complete (``save_batch`` writes to a
temporary directory and renames it). Work in progress lives in a scratch directory
``<data_dir>/.scratch/<name>-<hash>.<host>.<pid>.ns<tag>.<random>`` (:func:`scratch_directory`) removed on exit (Ctrl-C
included), and checkpoints in ``<data_dir>/.partial/<name>-<hash>`` (:func:`partial_directory`, written by
:mod:`torchrl_bail.behaviour.checkpoint`) from which a killed collection resumes.

Several hosts, one ``data_dir``: a lock (:func:`file_lock`) is an owner file created atomically, and a scratch
directory has an ``owner.json``; both record host name, boot id, pid namespace, pid and process start time
(:func:`owner_record`), and the owner's :data:`HEARTBEAT` thread touches them every ``heartbeat_every_s``.
:func:`owner_alive` decides, by this identity rule:

* *Same process table* -- same host name, same boot (``/proc/sys/kernel/random/boot_id``) and same pid namespace
  (``os.readlink("/proc/self/ns/pid")``), all known on both sides (:func:`sees_process_table`): the owner is gone
  when its pid does not exist or has another start time. Exact, and at once.
* *Anything else* is judged by its heartbeat only: presumed alive until the heartbeat is older than
  ``stale_after_s`` (:func:`liveness_settings`; compared on the file server's clock). That covers other hosts, but
  also containers of one node that share a host name (Docker ``--hostname``, Slurm jobs in containers, pods on a
  node's network): each has its own pid namespace, where a pid of ours names another process or none, so a live
  owner there would look "gone" (issue 54: two such jobs took over each other's live lock). It also covers the
  owner files of older versions, which record host and pid only: on the same host name such an owner is *not
  provably gone* (it may live in another pid namespace), so its lock or scratch directory waits for its heartbeat
  to age, once (``stale_after_s``, 600 s by default; a run directory's 60 s). Private names
  (:func:`owned_name`) carry a hash of boot and pid namespace for the same purpose.

:func:`clean_stale` removes only what a gone owner left; a waiter takes over a gone owner's lock and logs whom it
waited for.

How a lock is taken over (the design; it uses only what is atomic on NFS as on a local disk: creating a name by
``link()`` of a file written aside (a link count of 2 confirming an ``EEXIST`` that NFS may answer to a retried
``link()``), or ``O_EXCL`` where there are no hard links, ``unlink()``, reads and ``utime``; no ``fcntl``/``flock``):

1. *Judge.* A waiter opens the lock once and reads owner record and heartbeat (mtime) from that one open file, so
   it never judges one owner by the heartbeat of the next. The owner is gone when :func:`owner_alive` says so (the
   identity rule above), with a grace of ``max(stale_after_s, 3 x the heartbeat period the owner recorded in its
   file)``.
2. *Claim.* The waiter creates, the same atomic way, a take-over claim ``.<lock>.takeover.<instance>.<n>`` where
   ``<instance>`` names the judged lock (a hash of its random token). One job at a time holds the claim of an
   instance; the others wait for it. A claim whose holder is gone (killed mid-take-over; judged like a lock's owner)
   is superseded by creating claim ``n + 1``, never removed by another job, so there is nothing to race on there
   either.
3. *Verify, then remove.* The claim holder reads the lock again and unlinks it only if it still carries the judged
   token; then it removes its claims and, like every waiter, races to create the lock: exactly one create wins.

Nothing moves a lock aside and puts it back. (The mechanism before did: a waiter that had read a gone owner's
record moved the lock aside -- by then a live job's lock -- and linked it back when it saw another token; in between
a third job could create the lock, and the live owner's heartbeat found its lock missing: two owners, or a live
owner told it lost its lock. Issue 37.)

Guarantees, as long as no live owner is judged gone: at most one job holds a lock at any moment, and an owner keeps
its lock until it releases it. A token is never reused, so once the judged lock is gone no claim of it can remove
anything; while it is there only its (gone) owner or the one live claim holder could. Within one process table the
judgement is exact (pid and start time; no heartbeat, load or clock is involved); anywhere else it holds while a
live owner's heartbeat is never older than the grace (600 s against a 30 s heartbeat by default). A job stopped for
longer than that (a suspended job, an NFS client cut off past the grace: the one way to be misjudged) is fenced.

Fencing. Each acquisition writes a fresh random token in the lock file (:class:`HeldLock`, what :func:`file_lock`
yields; :func:`held_locks`). Whoever publishes what a lock guards -- the rename of a checkpoint file into
``.partial/`` (:mod:`torchrl_bail.behaviour.checkpoint`), of a batch into its final name
(:func:`~torchrl_bail.data.batch.save_batch`), of a SAC run into ``policies/`` -- first calls :func:`check_fence`
(in the thread that holds the lock), immediately before the rename: unless the lock file still carries its token,
it raises :class:`LockLost` and the file stays unpublished (its temporary copy is removed), so a fenced owner never
overwrites its successor's checkpoint or batch. Its heartbeat also notices, logs one error and stops touching the
lock. What the fence cannot close (no ``fcntl`` lease on NFS) is the moment between its check and the rename: a
take-over must land within that one ``fsync`` and rename.

The private files of a killed taker (claims, files being written) are removed by the lock's next owner. The
``batch`` keys that tune this and the checkpoints (:data:`~torchrl_bail.data.cache.OPERATIONAL_KEYS`) are outside
the recipe hash.
"""

from __future__ import annotations

import contextlib
import contextvars
import errno
import hashlib
import json
import logging
import os
import re
import secrets
import shutil
import socket
import threading
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from torchrl_bail.core.interrupts import stop_if_requested

__all__ = [
    "SCRATCH",
    "LOCKS",
    "PARTIAL",
    "HEARTBEAT",
    "LockHeld",
    "LockLost",
    "HeldLock",
    "host_name",
    "process_table_identity",
    "sees_process_table",
    "process_start_time",
    "owner_record",
    "pid_alive",
    "owner_alive",
    "held_locks",
    "check_fence",
    "liveness_settings",
    "owned_name",
    "clean_stale",
    "scratch_directory",
    "partial_directory",
    "file_lock",
]

log = logging.getLogger("torchrl_bail")

SCRATCH = ".scratch"
LOCKS = ".locks"
PARTIAL = ".partial"
OWNER_FILE = "owner.json"
STALE_ENV = "TORCHRL_BAIL_LOCK_STALE_AFTER_S"
#: another host's lock or scratch directory is presumed alive until its heartbeat is this old (seconds)
STALE_AFTER_S = 600.0
#: how often a job touches the owner files of its locks and scratch directories (seconds)
HEARTBEAT_EVERY_S = 30.0
BOOT_ID_FILE = "/proc/sys/kernel/random/boot_id"
PID_NAMESPACE_LINK = "/proc/self/ns/pid"
#: ``.ns<tag>`` in a private name: the owner's boot and pid namespace (:func:`owned_name`)
_NS = r"(?:\.ns(?P<ns>[0-9a-f]{10}))?"
_OWNED_NAME = re.compile(rf"^\.?(?P<stem>.+)\.(?P<host>[A-Za-z0-9-]+)\.(?P<pid>\d+){_NS}\.(?P<rand>[0-9a-f]{{8}})$")
_LEGACY_NAME = re.compile(r"^\.?.+\.\d+\.[0-9a-f]{8}$")


# --------------------------------------------------------------------------------------------------------------
# owners, heartbeats, locks, scratch and partial directories (safe when several hosts share data_dir)
# --------------------------------------------------------------------------------------------------------------


def host_name() -> str:
    """This host's name as it appears in owner files and scratch names (``[A-Za-z0-9-]`` only)."""
    return re.sub(r"[^A-Za-z0-9-]", "-", socket.gethostname()) or "localhost"


def _read_boot_id() -> str | None:
    try:
        return Path(BOOT_ID_FILE).read_text().strip() or None
    except OSError:
        return None


def _read_pid_namespace() -> str | None:
    try:
        return os.readlink(PID_NAMESPACE_LINK)  # e.g. "pid:[4026531836]"
    except OSError:
        pass
    try:
        return f"pid:[{os.stat(PID_NAMESPACE_LINK).st_ino}]"
    except OSError:
        return None


def _proc_is_ours() -> bool:
    """Whether ``/proc`` shows this process's own pid namespace (not so where a process in a new pid namespace kept
    its parent's ``/proc``, e.g. ``unshare --pid --fork`` without ``--mount-proc``)."""
    try:
        return os.readlink("/proc/self") == str(os.getpid())
    except OSError:
        return False


def process_table_identity() -> dict[str, str | None]:
    """Which process table this process lives in: ``boot_id`` (the kernel's boot, ``/proc/sys/kernel/random/boot_id``:
    one per machine or VM and boot, shared by the containers of one node) and ``pid_ns`` (the pid namespace,
    ``os.readlink("/proc/self/ns/pid")``, e.g. ``pid:[4026531836]``: one per container that has its own pids).
    ``None`` where unknown (no ``/proc``: another OS, a sandbox; or a ``/proc`` of another pid namespace)."""
    known = _proc_is_ours()
    return {"boot_id": _read_boot_id() if known else None, "pid_ns": _read_pid_namespace() if known else None}


def _namespace_tag(owner: Mapping[str, Any] | None) -> str | None:
    """A short hash of an owner's boot and pid namespace (``ns`` where it came from a private name), ``None``
    where either is unknown (an owner file of an older version: host and pid only)."""
    if not owner:
        return None
    tag = owner.get("ns")
    if isinstance(tag, str) and tag:
        return tag
    boot, ns = owner.get("boot_id"), owner.get("pid_ns")
    if not (isinstance(boot, str) and boot and isinstance(ns, str) and ns):
        return None
    return hashlib.sha1(f"{boot}\0{ns}".encode()).hexdigest()[:10]


def sees_process_table(owner: Mapping[str, Any] | None) -> bool:
    """Whether this process sees the process table of ``owner`` (an owner record, or what a private name says):
    the same host name, the same boot and the same pid namespace, all known. Only then may its pid be looked up
    here; a container with its own pid namespace (or a VM) that shares our host name is another host for this
    purpose, and so is an owner whose record lacks boot or namespace (an older version's: host and pid only)."""
    if not owner or owner.get("host") != host_name() or not isinstance(owner.get("pid"), int):
        return False
    mine = _namespace_tag(process_table_identity())
    return mine is not None and _namespace_tag(owner) == mine


def process_start_time(pid: int) -> int | None:
    """The start time of process ``pid`` in clock ticks since boot (``/proc``), ``None`` where unknown.

    Together with host, boot, pid namespace and pid it names a process uniquely: a recycled pid has another start
    time. ``None`` too where ``/proc`` shows another pid namespace than this process's.
    """
    if not _proc_is_ours():
        return None
    try:
        stat = Path(f"/proc/{int(pid)}/stat").read_text()
    except OSError:
        return None
    try:
        return int(stat[stat.rindex(")") + 2:].split()[19])
    except (ValueError, IndexError):
        return None


def owner_record() -> dict[str, Any]:
    """Who owns a lock or scratch directory: ``host``, ``pid``, process ``start_time``, ``boot_id`` and ``pid_ns``
    (:func:`process_table_identity`), ``created`` (epoch s)."""
    return {"host": host_name(), "pid": os.getpid(), "start_time": process_start_time(os.getpid()),
            **process_table_identity(), "created": time.time()}


def pid_alive(pid: int) -> bool:
    """Whether a process with id ``pid`` exists on this host (one owned by another user counts)."""
    try:
        os.kill(pid, 0)
    except OSError as err:
        return err.errno == errno.EPERM
    return True


def liveness_settings(cfg=None) -> tuple[float, float]:
    """``(stale_after_s, heartbeat_every_s)``: ``batch.lock_stale_after_s`` / ``batch.heartbeat_every_s`` of
    ``cfg``, else ``$TORCHRL_BAIL_LOCK_STALE_AFTER_S`` / :data:`STALE_AFTER_S`, and :data:`HEARTBEAT_EVERY_S`."""
    stale = cfg.batch.lock_stale_after_s if cfg is not None else None
    beat = cfg.batch.heartbeat_every_s if cfg is not None else None
    if stale is None:
        stale = float(os.environ.get(STALE_ENV, STALE_AFTER_S))
    return float(stale), float(HEARTBEAT_EVERY_S if beat is None else beat)


def _fs_now(directory: Path) -> float:
    """The file system's clock: the mtime of a probe file just touched in ``directory`` (hosts' clocks differ;
    heartbeats are compared on the clock of the file server that stamps them)."""
    probe = directory / owned_name(".clock")
    try:
        probe.touch()
        return probe.stat().st_mtime
    except OSError:
        return time.time()
    finally:
        with contextlib.suppress(OSError):
            probe.unlink()


def owner_alive(owner: Mapping[str, Any] | None, heartbeat_age_s: float, stale_after_s: float) -> bool:
    """Whether the owner of a lock or scratch directory may still be working.

    Where this process sees the owner's process table (:func:`sees_process_table`: same host name, boot and pid
    namespace): its pid exists with the recorded start time. Anywhere else -- another host, a container of this
    node with its own pid namespace that has the same host name, an owner record of an older version (host and pid
    only, so not provably gone even on this host name), an unknown owner -- it is presumed alive until its
    heartbeat -- the mtime of its owner file, touched every ``heartbeat_every_s`` -- is older than
    ``stale_after_s``.
    """
    if sees_process_table(owner):
        if not pid_alive(owner["pid"]):
            return False
        recorded, now = owner.get("start_time"), process_start_time(owner["pid"])
        return recorded is None or now is None or recorded == now
    return heartbeat_age_s < stale_after_s


def lock_is_held(path: Path, stale_after_s: float) -> bool:
    """Whether the lock file ``path`` has an owner that may still be working (:func:`owner_alive`, its heartbeat
    aged on the file system's clock): how another process tells a running job from a stopped one (``python -m
    torchrl_bail.study status``)."""
    found = _read_lock(path)
    if found is None:
        return False
    owner, st = found
    return owner_alive(owner, _fs_now(path.parent) - st.st_mtime, stale_after_s)


class LockLost(RuntimeError):
    """Another job took over a lock this process held (its heartbeat stopped for too long): it must publish nothing
    more (:func:`check_fence`)."""


class LockHeld(RuntimeError):
    """A lock taken with ``file_lock(..., wait=False)`` is held by an owner that is alive.

    Attributes:
        path: the lock file.
        owner: its owner record (``host``, ``pid``, ``what``; empty where the file could not be read).
    """

    def __init__(self, path: Path, owner: Mapping[str, Any]):
        self.path, self.owner = Path(path), dict(owner)
        super().__init__(f"{self.path} is held by {self.holder}")

    @property
    def holder(self) -> str:
        """``host:pid`` of the owner (``?`` for what is unknown)."""
        return f"{self.owner.get('host', '?')}:{self.owner.get('pid', '?')}"


class Heartbeat:
    """A daemon thread that touches the owner files of this process's locks and scratch directories.

    :meth:`register` a path (and, for a lock, the token written in it); every ``interval`` seconds its mtime is
    set to now, so that jobs on other hosts sharing ``data_dir`` see the owner is alive. A lock whose file no
    longer carries our token was taken over (our heartbeat stopped for longer than the staleness timeout): that
    is logged as an error once and the path is no longer touched.
    """

    def __init__(self):
        self._paths: dict[Path, tuple[str | None, float]] = {}
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._thread: threading.Thread | None = None
        self._thread_pid = -1
        self.lost: set[Path] = set()

    def register(self, path: Path, *, interval: float, token: str | None = None) -> None:
        with self._lock:
            self._paths[Path(path)] = (token, float(interval))
            if self._thread is None or not self._thread.is_alive() or self._thread_pid != os.getpid():
                self._thread_pid = os.getpid()
                self._thread = threading.Thread(target=self._run, name="torchrl_bail-heartbeat", daemon=True)
                self._thread.start()
        self._wake.set()

    def unregister(self, path: Path, token: str | None = None) -> None:
        """Stops touching ``path``; given a ``token``, only while ``path`` is registered with that token (two
        acquisitions of one lock in one process -- a fenced owner and its successor -- leave each other's alone)."""
        with self._lock:
            if token is None or self._paths.get(Path(path), (None,))[0] == token:
                self._paths.pop(Path(path), None)

    def mark_lost(self, path: Path, token: str) -> None:
        """Records that the acquisition ``token`` of the lock ``path`` was taken over (if it is the one registered)."""
        with self._lock:
            ours = self._paths.get(Path(path), (None,))[0] == token
            if ours:
                self._paths.pop(Path(path), None)
        if ours:
            self.lost.add(Path(path))

    def beat(self) -> None:
        """Touches every registered path once now (a lock only while it still carries our token)."""
        with self._lock:
            items = list(self._paths.items())
        for path, (token, _) in items:
            if token is None:
                with contextlib.suppress(OSError):
                    os.utime(path, None)
            elif _touch_if_ours(path, token) is False:
                log.error("lock %s was taken over by another job (this job was judged gone: its heartbeat was "
                          "older than the staleness timeout); this job no longer owns it", path)
                self.mark_lost(path, token)

    def check(self, path: Path | None = None) -> None:
        """Raises :class:`LockLost` if a lock of this process (or the lock ``path``) was taken over (e.g. the job
        was suspended for longer than the staleness timeout): it must not write what the new owner now writes."""
        with self._lock:
            items = [(p, v) for p, v in self._paths.items() if path is None or p == Path(path)]
        for lock, (token, _) in items:
            if token is not None and _holds(lock, token) is False:
                self.mark_lost(lock, token)
        lost = sorted(str(p) for p in self.lost if path is None or p == Path(path))
        if lost:
            raise LockLost(f"lock {lost[0]} was taken over by another job; stopping here "
                           "(its heartbeat was older than the staleness timeout)")

    def _run(self) -> None:
        while True:
            with self._lock:
                interval = min((i for _, i in self._paths.values()), default=HEARTBEAT_EVERY_S)
            self._wake.wait(interval)
            self._wake.clear()
            self.beat()


#: the process-wide heartbeat (one thread for every lock and scratch directory of this process)
HEARTBEAT = Heartbeat()

#: how long a fence check retries a lock file it cannot read just now (a passing file-server error), in seconds
FENCE_RETRY_S = 1.0


class HeldLock:
    """One acquisition of a lock, as :func:`file_lock` yields it: the lock file ``path`` and the random ``token``
    written in it (fresh for each acquisition, never reused). The token is the fence: :meth:`check` before
    publishing anything the lock guards."""

    def __init__(self, path: Path, token: str):
        self.path, self.token = Path(path), token

    def __repr__(self) -> str:
        return f"HeldLock({str(self.path)!r}, token={self.token!r})"

    def holds(self) -> bool | None:
        """Whether the lock file still carries this acquisition's token (``None``: it cannot be read just now)."""
        return _holds(self.path, self.token)

    def check(self) -> None:
        """Raises :class:`LockLost` unless the lock file still carries this acquisition's token: another job took
        the lock over (this one was judged gone), so what this job would publish now is refused. A lock file that
        cannot be read is retried for :data:`FENCE_RETRY_S`, then refused too (nothing proves it is still ours)."""
        deadline = time.monotonic() + FENCE_RETRY_S
        holds = self.holds()
        while holds is None and time.monotonic() < deadline:
            time.sleep(0.05)
            holds = self.holds()
        if holds:
            return
        if holds is None:
            raise LockLost(f"cannot read the lock {self.path} to confirm that this job still holds it; refusing to "
                           "publish (a checkpoint or batch is renamed into place only under its lock)")
        HEARTBEAT.mark_lost(self.path, self.token)
        owner = _read_owner(self.path)
        now = f"now held by {owner.get('host', '?')}:{owner.get('pid', '?')}" if owner else "now released"
        raise LockLost(f"lock {self.path} was taken over by another job ({now}); this job was judged gone (its "
                       "heartbeat was older than the staleness timeout) and may publish nothing more: refusing to "
                       "rename its checkpoint or batch into place")


#: the locks the current thread (context) holds, innermost last: what :func:`check_fence` checks
_HELD: contextvars.ContextVar[tuple[HeldLock, ...]] = contextvars.ContextVar("torchrl_bail_held_locks", default=())


def held_locks() -> tuple[HeldLock, ...]:
    """The locks taken with :func:`file_lock` by the current thread (context) and not yet released."""
    return _HELD.get()


def check_fence() -> None:
    """The fence: raises :class:`LockLost` if a lock of this job was taken over. Call it immediately before
    publishing -- the atomic rename of a checkpoint or a batch into place -- so that a stale owner (suspended, or
    cut off from the file server, past the grace; then taken over) cannot overwrite what the new owner writes.

    Checks each lock this thread holds (:func:`held_locks`: the lock file must still carry that acquisition's
    token) and every lock this process's heartbeat knows lost (:meth:`Heartbeat.check`)."""
    HEARTBEAT.check()
    for held in held_locks():
        held.check()


def _read_owner(path: Path) -> dict[str, Any]:
    try:
        owner = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return {}
    return owner if isinstance(owner, dict) else {}


def _owner_of_entry(path: Path) -> tuple[dict[str, Any], Path]:
    """The owner of a scratch-like entry and the file whose mtime is its heartbeat: ``owner.json`` inside it
    when there is one, else host, pid (and namespace) from its name (:func:`owned_name`), else unknown."""
    owner_file = path / OWNER_FILE
    if owner_file.is_file():
        return _read_owner(owner_file), owner_file
    m = _OWNED_NAME.match(path.name)
    return (_owner_of_name(m) if m else {}), path


def _owner_of_name(m: re.Match) -> dict[str, Any]:
    """The owner a private name tells (``host``, ``pid``, and ``ns``, its namespace tag, where the name has one)."""
    return {"host": m["host"], "pid": int(m["pid"]), **({"ns": m["ns"]} if m["ns"] else {})}


def owned_name(stem: str) -> str:
    """``<stem>.<host>.<pid>.ns<tag>.<random>``: a private name whose owner :func:`clean_stale` can tell (``tag``:
    a hash of the boot and pid namespace, :func:`process_table_identity`; left out where they are unknown, and in
    older versions' names: such an owner is judged by age only)."""
    tag = _namespace_tag(process_table_identity())
    return f"{stem}.{host_name()}.{os.getpid()}{f'.ns{tag}' if tag else ''}.{secrets.token_hex(4)}"


def clean_stale(data_dir: str | os.PathLike, *, stale_after_s: float | None = None) -> list[Path]:
    """Removes scratch directories (and temporary run directories) whose owner is gone (:func:`owner_alive`):
    a dead process of this host at once, another host's only once its heartbeat is older than
    ``stale_after_s``. Checkpoints (``.partial``) and locks are never touched here."""
    data_dir = Path(data_dir)
    stale_after_s = liveness_settings()[0] if stale_after_s is None else float(stale_after_s)
    removed = []
    candidates = list((data_dir / SCRATCH).glob("*")) if (data_dir / SCRATCH).is_dir() else []
    candidates += [p for p in data_dir.glob(".*") if p.is_dir() and p.name not in (SCRATCH, LOCKS, PARTIAL)]
    candidates += list((data_dir / "policies").glob(".*")) if (data_dir / "policies").is_dir() else []
    now = None
    for path in candidates:
        if not path.is_dir():
            continue
        owner, beat_file = _owner_of_entry(path)
        if not owner and not _OWNED_NAME.match(path.name) and not _LEGACY_NAME.match(path.name):
            continue  # not ours to judge
        now = _fs_now(data_dir / SCRATCH if (data_dir / SCRATCH).is_dir() else data_dir) if now is None else now
        try:
            age = now - beat_file.stat().st_mtime
        except OSError:
            continue
        if owner_alive(owner, age, stale_after_s):
            continue
        shutil.rmtree(path, ignore_errors=True)
        removed.append(path)
    return removed


@contextlib.contextmanager
def scratch_directory(data_dir: Path, stem: str, *, heartbeat_every_s: float | None = None) -> Iterator[Path]:
    """A private directory ``<data_dir>/.scratch/<stem>.<host>.<pid>.ns<tag>.<random>`` (:func:`owned_name`) with an
    ``owner.json`` that the :data:`HEARTBEAT` keeps fresh; removed on exit (exceptions and Ctrl-C included)."""
    path = data_dir / SCRATCH / owned_name(stem)
    path.mkdir(parents=True)
    owner_file = path / OWNER_FILE
    owner_file.write_text(json.dumps(owner_record()))
    HEARTBEAT.register(owner_file, interval=liveness_settings()[1] if heartbeat_every_s is None else heartbeat_every_s)
    try:
        yield path
    finally:
        HEARTBEAT.unregister(owner_file)
        shutil.rmtree(path, ignore_errors=True)


def partial_directory(data_dir: str | os.PathLike, key: str) -> Path:
    """``<data_dir>/.partial/<key>``: where an unfinished collection keeps its checkpoint (``key`` is the batch's
    or the SAC run's directory name, hash included); written only under the lock of that batch or run."""
    return Path(data_dir) / PARTIAL / key


def _create_exclusively(path: Path, text: str) -> bool:
    """Creates ``path`` holding ``text`` unless it exists (written aside, then hard-linked: atomic on NFS too)."""
    tmp = path.with_name(f".{path.name}.{owned_name('new')}")
    tmp.write_text(text)
    try:
        os.link(tmp, path)
        return True
    except FileExistsError:  # NFS: a retransmitted link() that had succeeded answers EEXIST; the link count tells
        try:
            return os.stat(tmp).st_nlink == 2
        except OSError:
            return False
    except OSError:  # no hard links here: O_EXCL create (readers skip an empty file while it is written)
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            return False
        with os.fdopen(fd, "w") as f:
            f.write(text)
        return True
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink()


def _read_lock(path: Path) -> tuple[dict[str, Any], os.stat_result] | None:
    """Owner record and ``stat`` of the lock file ``path``, both from one open file (one instance of the lock:
    never the record of one and the heartbeat of the next); ``None`` when there is no lock. A record that cannot be
    read or parsed is ``{}``."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        return None
    except OSError:
        try:
            return {}, os.stat(path)
        except FileNotFoundError:
            return None
    try:
        st = os.fstat(fd)
        chunks = []
        with contextlib.suppress(OSError):  # a file server's read error: an unreadable record
            while chunk := os.read(fd, 1 << 16):
                chunks.append(chunk)
    except OSError:
        return None  # e.g. a stale NFS handle: the lock was replaced; judge again
    finally:
        os.close(fd)
    try:
        owner = json.loads(b"".join(chunks))
    except ValueError:
        owner = {}
    return (owner if isinstance(owner, dict) else {}), st


def _holds(path: Path, token: str) -> bool | None:
    """Whether the lock ``path`` still carries ``token``: ``False`` when it is gone or carries another token,
    ``None`` when it could not be read just now (a passing file-server error is not a lost lock)."""
    try:
        raw = Path(path).read_bytes()
    except FileNotFoundError:
        return False
    except OSError:
        return None
    try:
        owner = json.loads(raw)
    except ValueError:
        return None
    return isinstance(owner, dict) and owner.get("token") == token


def _touch_if_ours(path: Path, token: str) -> bool | None:
    """The heartbeat of a lock: sets the mtime of ``path`` to now if (and only if, on that very file) it carries
    ``token``. Returns :func:`_holds`'s answer."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        return False
    except OSError:
        return None
    try:
        chunks = []
        while chunk := os.read(fd, 1 << 16):
            chunks.append(chunk)
        try:
            owner = json.loads(b"".join(chunks))
        except ValueError:
            return None
        if not (isinstance(owner, dict) and owner.get("token") == token):
            return False
        with contextlib.suppress(OSError):
            os.utime(fd if os.utime in os.supports_fd else path, None)
        return True
    except OSError:
        return None
    finally:
        os.close(fd)


def _grace(owner: Mapping[str, Any], stale_after_s: float) -> float:
    """How old another host's heartbeat must be before its owner is gone: ``stale_after_s``, but at least three of
    the heartbeat periods the owner recorded (a waiter with a shorter timeout than the owner's heartbeat would
    otherwise judge a live owner gone between two beats)."""
    beat = owner.get("heartbeat_every_s")
    return max(stale_after_s, 3.0 * beat) if isinstance(beat, (int, float)) and beat > 0 else stale_after_s


def _instance(owner: Mapping[str, Any], st: os.stat_result) -> str:
    """A name for one instance of a lock file: a hash of its token (never reused), or for a lock without one (an
    unreadable file, an older version's) of its inode and mtime."""
    token = owner.get("token")
    ident = f"token:{token}" if isinstance(token, str) and token else f"inode:{st.st_dev}:{st.st_ino}:{st.st_mtime_ns}"
    return hashlib.sha1(ident.encode()).hexdigest()[:16]


def _claim(path: Path, instance: str, generation: int) -> Path:
    """The take-over claim number ``generation`` of the lock instance ``instance`` of ``path``."""
    return path.with_name(f".{path.name}.takeover.{instance}.{generation}")


#: test hook: called by a take-over between holding its claim and removing the judged lock
_BEFORE_REMOVING = None


def _take_over(path: Path, instance: str, stale_after_s: float) -> bool | None:
    """Removes the lock ``path`` if it still is the instance ``instance`` that was judged gone, holding that
    instance's take-over claim (module docstring). Returns ``True`` when this job removed it, ``False`` when it is
    not there any more (taken over by another job, or released), ``None`` when another live job is taking it over
    (wait a moment and judge again)."""
    generation = 1
    while not _create_exclusively(_claim(path, instance, generation), json.dumps(owner_record())):
        state = _read_lock(_claim(path, instance, generation))
        if state is None:
            continue  # its holder just finished: try the same claim again
        holder, st = state
        if owner_alive(holder, _fs_now(path.parent) - st.st_mtime, stale_after_s):
            return None
        generation += 1  # its holder was killed mid-take-over: supersede its claim (never remove another's)
    try:
        if _claim(path, instance, generation + 1).exists():
            return None  # somebody judged *us* gone meanwhile (suspended?): it goes on, we step back
        if _BEFORE_REMOVING is not None:
            _BEFORE_REMOVING(path)
        state = _read_lock(path)
        if state is None or _instance(*state) != instance:
            return False  # gone, or a new lock: not the one judged
        try:
            os.unlink(path)
        except FileNotFoundError:
            return False
        return True
    finally:
        for n in range(generation, 0, -1):  # ours, then any superseded claim of a killed taker
            with contextlib.suppress(OSError):
                os.unlink(_claim(path, instance, n))


def _sweep_debris(path: Path, stale_after_s: float) -> None:
    """Removes what killed jobs left next to the lock ``path``: take-over claims, files being written (``.new.``),
    an older version's moved-aside locks (``.stale.``) and clock probes, each only when its owner is gone."""
    name = re.escape(path.name)
    owned = rf"(?P<host>[A-Za-z0-9-]+)\.(?P<pid>\d+){_NS}"
    claims = r"(?:\.takeover\.[0-9a-f]{16}\.\d+)?"
    private = [re.compile(rf"^\.{{1,2}}{name}{claims}\.(?:new|stale)\.{owned}\.[0-9a-f]{{8}}$"),
               re.compile(rf"^\.clock\.{owned}(?:\.[0-9a-f]{{8}})?$")]
    claim = re.compile(rf"^\.{name}\.takeover\.[0-9a-f]{{16}}\.\d+$")
    try:
        entries = list(os.scandir(path.parent))
    except OSError:
        return
    now = None
    for entry in entries:
        m = next((m for m in (p.match(entry.name) for p in private) if m), None)
        if m:
            owner = _owner_of_name(m)
        elif claim.match(entry.name):
            state = _read_lock(Path(entry.path))
            if state is None:
                continue
            owner = state[0]
        else:
            continue
        now = _fs_now(path.parent) if now is None else now
        try:
            age = now - entry.stat(follow_symlinks=False).st_mtime
        except OSError:
            continue
        if not owner_alive(owner, age, stale_after_s):
            with contextlib.suppress(OSError):
                os.unlink(entry.path)


@contextlib.contextmanager
def file_lock(path: Path, *, stale_after_s: float | None = None, heartbeat_every_s: float | None = None,
              what: str | None = None, poll_s: float = 0.2, wait: bool = True) -> Iterator[HeldLock]:
    """An exclusive lock across processes *and hosts* sharing ``data_dir``: concurrent jobs wanting the same
    batch collect it once; the others wait (logging ``waiting for <host>:<pid>``) and then reuse it.

    The lock is an owner file (host, boot, pid namespace, pid, process start time, heartbeat period, a random
    token) created atomically; its owner's :data:`HEARTBEAT` touches it every ``heartbeat_every_s``. A waiter takes
    it over when the owner is gone (:func:`owner_alive`: a dead pid at once where the waiter sees the owner's
    process table -- same host name, boot and pid namespace; anywhere else, a same-named container included, once
    the heartbeat is older than ``stale_after_s``, default :func:`liveness_settings`, and than three of the owner's
    heartbeat periods), through a take-over claim that serializes take-overs and removes only the very lock that
    was judged (module docstring). A killed owner leaves the file behind; its next owner removes what killed jobs
    left around it.

    Yields the :class:`HeldLock` (path and this acquisition's token), also listed by :func:`held_locks` while it is
    held: :func:`check_fence` before publishing what the lock guards refuses once the lock was taken over.

    ``wait=False`` (a run directory's lock) does not wait for a live owner to finish: it raises
    :class:`LockHeld` as soon as the owner is known to be alive -- at once for a live process whose process table
    the waiter sees, when its heartbeat moves for any other -- while a gone owner's lock is still taken over
    (another host's once its heartbeat is ``stale_after_s`` old: a job requeued on another node after its
    predecessor was killed waits at most that long).
    """
    stale, beat = liveness_settings()
    stale_after_s = stale if stale_after_s is None else float(stale_after_s)
    heartbeat_every_s = beat if heartbeat_every_s is None else float(heartbeat_every_s)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    token = secrets.token_hex(8)
    record = json.dumps({**owner_record(), "token": token, "heartbeat_every_s": heartbeat_every_s,
                         "what": what or path.stem})
    waited_since = None
    first_beat = None
    last_log = 0.0
    delay = poll_s
    while not _create_exclusively(path, record):
        state = _read_lock(path)
        if state is None:
            continue  # released meanwhile: try again
        owner, st = state
        beat = st.st_mtime
        age = _fs_now(path.parent) - beat
        grace = _grace(owner, stale_after_s)
        if not owner_alive(owner, age, grace) and (owner or age >= grace):
            took = _take_over(path, _instance(owner, st), grace)
            if took:
                log.warning("taking over the lock %s of %s:%s (%s)", path.name, owner.get("host", "?"),
                            owner.get("pid", "?"), "process gone" if sees_process_table(owner)
                            else f"no heartbeat for {age:.0f} s")
            if took is not None:
                continue
            stop_if_requested(None)
            time.sleep(poll_s)  # another job is taking it over this very moment
            continue
        first_beat = beat if first_beat is None else first_beat
        if not wait and (beat > first_beat or sees_process_table(owner)):
            raise LockHeld(path, owner)
        now = time.monotonic()
        waited_since = now if waited_since is None else waited_since
        if now - last_log >= 60 or last_log == 0.0:
            if wait:
                log.info("waiting for %s:%s, which is making %s (waited %.0f s, its heartbeat %.0f s ago)",
                         owner.get("host", "?"), owner.get("pid", "?"), owner.get("what", path.stem),
                         now - waited_since, age)
            else:
                log.info("%s is locked by %s:%s, whose last heartbeat was %.0f s ago: taking it over if none comes "
                         "within %.0f s (a killed job's lock), stopping if one does", owner.get("what", path.stem),
                         owner.get("host", "?"), owner.get("pid", "?"), age, grace - age)
            last_log = now
        stop_if_requested(None)  # Ctrl-C/SIGTERM (an entry point's request) while waiting: stop now, nothing to save
        time.sleep(delay)
        delay = min(delay * 1.5, 5.0)
    held = HeldLock(path, token)
    HEARTBEAT.lost.discard(path)
    HEARTBEAT.register(path, interval=heartbeat_every_s, token=token)
    _HELD.set((*_HELD.get(), held))
    try:
        with contextlib.suppress(OSError):
            _sweep_debris(path, stale_after_s)
        yield held
    finally:
        _HELD.set(tuple(h for h in _HELD.get() if h is not held))
        HEARTBEAT.unregister(path, token)
        HEARTBEAT.lost.discard(path)
        if _holds(path, token):
            with contextlib.suppress(FileNotFoundError):
                os.unlink(path)

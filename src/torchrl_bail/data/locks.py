"""Collecting a batch safely when several jobs -- on several hosts -- share one ``data_dir``: owner records,
heartbeats, locks, scratch and partial directories. Training runs lock their run directories with the same
:func:`file_lock` (``wait=False``: :mod:`torchrl_bail.resume`).

Interruption: nothing is ever written under a batch's final name until it is complete (``save_batch`` writes to a
temporary directory and renames it). Work in progress lives in a scratch directory
``<data_dir>/.scratch/<name>-<hash>.<host>.<pid>.<random>`` (:func:`scratch_directory`) removed on exit (Ctrl-C
included), and checkpoints in ``<data_dir>/.partial/<name>-<hash>`` (:func:`partial_directory`, written by
:mod:`torchrl_bail.behaviour.checkpoint`) from which a killed collection resumes.

Several hosts, one ``data_dir``: a lock (:func:`file_lock`) is an owner file created atomically, and a scratch
directory has an ``owner.json``; both record host, pid and process start time (:func:`owner_record`), and the
owner's :data:`HEARTBEAT` thread touches them every ``heartbeat_every_s``. :func:`owner_alive` decides: on this host
the process must exist with the same start time; another host's owner is presumed alive until its heartbeat is
older than ``stale_after_s`` (:func:`liveness_settings`; compared on the file server's clock). :func:`clean_stale`
removes only what a gone owner left; a waiter takes over a gone owner's lock and logs whom it waited for.

How a lock is taken over (the design; it uses only what is atomic on NFS as on a local disk: creating a name by
``link()`` of a file written aside (a link count of 2 confirming an ``EEXIST`` that NFS may answer to a retried
``link()``), or ``O_EXCL`` where there are no hard links, ``unlink()``, reads and ``utime``; no ``fcntl``/``flock``):

1. *Judge.* A waiter opens the lock once and reads owner record and heartbeat (mtime) from that one open file, so
   it never judges one owner by the heartbeat of the next. The owner is gone when :func:`owner_alive` says so, with
   a grace of ``max(stale_after_s, 3 x the heartbeat period the owner recorded in its file)``.
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
anything; while it is there only its (gone) owner or the one live claim holder could. On one host the judgement is
exact (pid and start time; no heartbeat, load or clock is involved); between hosts it holds while a live owner's
heartbeat is never older than the grace (600 s against a 30 s heartbeat by default). A job stopped for longer than
that (a suspended job: the one way to be misjudged) learns it from its heartbeat (:class:`LockLost`) and writes
nothing more. The private files of a killed taker (claims, files being written) are removed by the lock's next owner.
The ``batch`` keys that tune this and the checkpoints (:data:`~torchrl_bail.data.cache.OPERATIONAL_KEYS`) are outside
the recipe hash.
"""

from __future__ import annotations

import contextlib
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

from torchrl_bail.interrupts import stop_if_requested

__all__ = [
    "SCRATCH",
    "LOCKS",
    "PARTIAL",
    "HEARTBEAT",
    "LockHeld",
    "LockLost",
    "host_name",
    "process_start_time",
    "owner_record",
    "pid_alive",
    "owner_alive",
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
_OWNED_NAME = re.compile(r"^\.?(?P<stem>.+)\.(?P<host>[A-Za-z0-9-]+)\.(?P<pid>\d+)\.(?P<rand>[0-9a-f]{8})$")
_LEGACY_NAME = re.compile(r"^\.?.+\.\d+\.[0-9a-f]{8}$")


# --------------------------------------------------------------------------------------------------------------
# owners, heartbeats, locks, scratch and partial directories (safe when several hosts share data_dir)
# --------------------------------------------------------------------------------------------------------------


def host_name() -> str:
    """This host's name as it appears in owner files and scratch names (``[A-Za-z0-9-]`` only)."""
    return re.sub(r"[^A-Za-z0-9-]", "-", socket.gethostname()) or "localhost"


def process_start_time(pid: int) -> int | None:
    """The start time of process ``pid`` in clock ticks since boot (``/proc``), ``None`` where unknown.

    Together with host and pid it names a process uniquely: a recycled pid has another start time.
    """
    try:
        stat = Path(f"/proc/{int(pid)}/stat").read_text()
    except OSError:
        return None
    try:
        return int(stat[stat.rindex(")") + 2:].split()[19])
    except (ValueError, IndexError):
        return None


def owner_record() -> dict[str, Any]:
    """Who owns a lock or scratch directory: ``host``, ``pid``, process ``start_time``, ``created`` (epoch s)."""
    return {"host": host_name(), "pid": os.getpid(), "start_time": process_start_time(os.getpid()),
            "created": time.time()}


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

    On this host: its pid exists with the recorded start time. On another host (or an unknown owner) it is
    presumed alive until its heartbeat -- the mtime of its owner file, touched every ``heartbeat_every_s`` --
    is older than ``stale_after_s``.
    """
    if owner and owner.get("host") == host_name() and isinstance(owner.get("pid"), int):
        if not pid_alive(owner["pid"]):
            return False
        recorded, now = owner.get("start_time"), process_start_time(owner["pid"])
        return recorded is None or now is None or recorded == now
    return heartbeat_age_s < stale_after_s


class LockLost(RuntimeError):
    """Another job took over a lock this process held (its heartbeat stopped for too long)."""


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

    def unregister(self, path: Path) -> None:
        with self._lock:
            self._paths.pop(Path(path), None)

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
                self.unregister(path)
                self.lost.add(path)

    def check(self, path: Path | None = None) -> None:
        """Raises :class:`LockLost` if a lock of this process (or the lock ``path``) was taken over (e.g. the job
        was suspended for longer than the staleness timeout): it must not write what the new owner now writes."""
        with self._lock:
            items = [(p, v) for p, v in self._paths.items() if path is None or p == Path(path)]
        for lock, (token, _) in items:
            if token is not None and _holds(lock, token) is False:
                self.unregister(lock)
                self.lost.add(lock)
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


def _read_owner(path: Path) -> dict[str, Any]:
    try:
        owner = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return {}
    return owner if isinstance(owner, dict) else {}


def _owner_of_entry(path: Path) -> tuple[dict[str, Any], Path]:
    """The owner of a scratch-like entry and the file whose mtime is its heartbeat: ``owner.json`` inside it
    when there is one, else host and pid from its name ``<stem>.<host>.<pid>.<hex>``, else unknown."""
    owner_file = path / OWNER_FILE
    if owner_file.is_file():
        return _read_owner(owner_file), owner_file
    m = _OWNED_NAME.match(path.name)
    return ({"host": m["host"], "pid": int(m["pid"])} if m else {}), path


def owned_name(stem: str) -> str:
    """``<stem>.<host>.<pid>.<random>``: a private name whose owner :func:`clean_stale` can tell."""
    return f"{stem}.{host_name()}.{os.getpid()}.{secrets.token_hex(4)}"


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
    """A private directory ``<data_dir>/.scratch/<stem>.<host>.<pid>.<random>`` with an ``owner.json`` that the
    :data:`HEARTBEAT` keeps fresh; removed on exit (exceptions and Ctrl-C included)."""
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
    owned = r"(?P<host>[A-Za-z0-9-]+)\.(?P<pid>\d+)"
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
            owner: dict[str, Any] = {"host": m["host"], "pid": int(m["pid"])}
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
              what: str | None = None, poll_s: float = 0.2, wait: bool = True) -> Iterator[None]:
    """An exclusive lock across processes *and hosts* sharing ``data_dir``: concurrent jobs wanting the same
    batch collect it once; the others wait (logging ``waiting for <host>:<pid>``) and then reuse it.

    The lock is an owner file (host, pid, process start time, heartbeat period, a random token) created atomically;
    its owner's :data:`HEARTBEAT` touches it every ``heartbeat_every_s``. A waiter takes it over when the owner is
    gone (:func:`owner_alive`: a dead pid on this host at once; on another host once the heartbeat is older than
    ``stale_after_s``, default :func:`liveness_settings`, and than three of the owner's heartbeat periods), through
    a take-over claim that serializes take-overs and removes only the very lock that was judged (module docstring).
    A killed owner leaves the file behind; its next owner removes what killed jobs left around it.

    ``wait=False`` (a run directory's lock) does not wait for a live owner to finish: it raises
    :class:`LockHeld` as soon as the owner is known to be alive -- at once for a live process of this host, when
    its heartbeat moves for another host's -- while a gone owner's lock is still taken over (another host's once
    its heartbeat is ``stale_after_s`` old: a job requeued on another node after its predecessor was killed waits
    at most that long).
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
                            owner.get("pid", "?"), "process gone" if owner.get("host") == host_name()
                            else f"no heartbeat for {age:.0f} s")
            if took is not None:
                continue
            stop_if_requested(None)
            time.sleep(poll_s)  # another job is taking it over this very moment
            continue
        first_beat = beat if first_beat is None else first_beat
        if not wait and (owner.get("host") == host_name() or beat > first_beat):
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
    HEARTBEAT.lost.discard(path)
    HEARTBEAT.register(path, interval=heartbeat_every_s, token=token)
    try:
        with contextlib.suppress(OSError):
            _sweep_debris(path, stale_after_s)
        yield
    finally:
        HEARTBEAT.unregister(path)
        HEARTBEAT.lost.discard(path)
        if _holds(path, token):
            with contextlib.suppress(FileNotFoundError):
                os.unlink(path)

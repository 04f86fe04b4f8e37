"""The on-disk batch cache: where batches live, what names and hashes they get, locks and scratch directories.

Every batch is cached as an :class:`~torchrl_bail.data.batch.OfflineBatch` under

``<data_dir>/<env>_<kind>[_oracle]_b<index>-<hash>/``  (``data/`` memmap + ``metadata.json``)

The 8-hex ``hash`` covers everything that determines the data (:func:`recipe_identity`: the env id and time limit,
every field of ``cfg.batch`` except the cosmetic ``kind``, the behaviour seed and, for mediocre-policy batches, the
env's ``mediocre_threshold``), so a quick-preset batch (``batch.steps=50000``) never collides with the paper-scale
one and a changed hyper-parameter never silently reuses stale data.

Seeds: the behaviour seed is ``batch.seed`` or, when that is ``null``, ``batch.index`` -- B1 and B2 differ and the
training seed ``cfg.seed`` never changes a batch.

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
The ``batch`` keys that tune this and the checkpoints (:data:`OPERATIONAL_KEYS`) are outside the recipe hash.

This module reads configs (an OmegaConf ``DictConfig`` or a plain nested ``dict``) but never produces data: the
behaviour agents that fill the cache live in :mod:`torchrl_bail.behaviour`.

Examples:
    >>> cfg = {"env": {"name": "hopper", "id": "Hopper-v5", "max_episode_steps": 1000},
    ...        "batch": {"kind": "ddpg05", "recipe": "ddpg", "index": 2, "steps": 1000,
    ...                  "sigma": 0.5, "start_steps": 100}}
    >>> batch_name(cfg), behaviour_seed(cfg), config_value(cfg, "batch.sigma")
    ('hopper_ddpg05_b2', 2, 0.5)
    >>> len(recipe_hash(cfg))
    8
"""

from __future__ import annotations

import contextlib
import errno
import functools
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

from omegaconf import DictConfig, OmegaConf

from torchrl_bail.data.batch import BatchValidationError, load_batch

__all__ = [
    "DATA_DIR_ENV",
    "SCRATCH",
    "LOCKS",
    "default_data_dir",
    "data_dir_of",
    "plain",
    "config_value",
    "oracle_settings",
    "behaviour_seed",
    "batch_name",
    "episode_limit",
    "recipe_identity",
    "sac_identity",
    "stable_hash",
    "recipe_hash",
    "batch_path",
    "batch_metadata",
    "PARTIAL",
    "OPERATIONAL_KEYS",
    "HEARTBEAT",
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
    "load_cached_batch",
    "list_batches",
    "format_bytes",
]

log = logging.getLogger("torchrl_bail")

DATA_DIR_ENV = "TORCHRL_BAIL_DATA_DIR"
SCRATCH = ".scratch"
LOCKS = ".locks"
PARTIAL = ".partial"
OWNER_FILE = "owner.json"
STALE_ENV = "TORCHRL_BAIL_LOCK_STALE_AFTER_S"
#: another host's lock or scratch directory is presumed alive until its heartbeat is this old (seconds)
STALE_AFTER_S = 600.0
#: how often a job touches the owner files of its locks and scratch directories (seconds)
HEARTBEAT_EVERY_S = 30.0
#: ``batch`` keys that say how a batch is collected (checkpoints, locks), not what it holds: outside its hash
OPERATIONAL_KEYS = ("checkpoint_every_s", "checkpoint_every_steps", "lock_stale_after_s", "heartbeat_every_s")
_OWNED_NAME = re.compile(r"^\.?(?P<stem>.+)\.(?P<host>[A-Za-z0-9-]+)\.(?P<pid>\d+)\.(?P<rand>[0-9a-f]{8})$")
_LEGACY_NAME = re.compile(r"^\.?.+\.\d+\.[0-9a-f]{8}$")


def default_data_dir() -> Path:
    """``$TORCHRL_BAIL_DATA_DIR`` if set, else ``~/.cache/torchrl_bail``."""
    env = os.environ.get(DATA_DIR_ENV)
    return Path(env).expanduser() if env else Path.home() / ".cache" / "torchrl_bail"


# --------------------------------------------------------------------------------------------------------------
# reading configs, names, identities, paths
# --------------------------------------------------------------------------------------------------------------


def plain(node: Any) -> Any:
    """``node`` as plain Python containers (an OmegaConf node is resolved and converted; anything else as is)."""
    if isinstance(node, DictConfig) or OmegaConf.is_config(node):
        return OmegaConf.to_container(node, resolve=True)
    return node


def config_value(cfg: Any, dotted: str, default: Any = None) -> Any:
    """The value at ``dotted`` (e.g. ``"batch.agent.tau"``) of a ``DictConfig`` or a nested ``dict``, as plain
    Python (see :func:`plain`); ``default`` when a key on the way is missing."""
    if OmegaConf.is_config(cfg):
        value = OmegaConf.select(cfg, dotted, default=default)
        return plain(value)
    node = cfg
    for part in dotted.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return default
        node = node[part]
    return node


def oracle_settings(cfg) -> dict | None:
    """The resolved ``batch.oracle`` block when oracle mode is on, else ``None``."""
    oracle = config_value(cfg, "batch.oracle")
    if not oracle or not oracle.get("enabled", False):
        return None
    return {"horizon": 2000, "keep": 1000, "gamma": 0.99, **oracle}


def behaviour_seed(cfg) -> int:
    """``batch.seed`` when set, else ``batch.index``: B1 and B2 differ; the training ``seed`` is not used."""
    seed = config_value(cfg, "batch.seed")
    return int(config_value(cfg, "batch.index") if seed is None else seed)


def batch_name(cfg) -> str:
    """``<env.name>_<batch.kind>_b<batch.index>`` (``_oracle`` before ``_b`` in oracle mode)."""
    oracle = "_oracle" if oracle_settings(cfg) else ""
    env, kind, index = config_value(cfg, "env.name"), config_value(cfg, "batch.kind"), config_value(cfg, "batch.index")
    return f"{env}_{kind}{oracle}_b{int(index)}"


def episode_limit(cfg) -> int:
    """The collection env's time limit: ``env.max_episode_steps`` (``oracle.horizon`` in oracle mode)."""
    oracle = oracle_settings(cfg)
    if oracle:
        return int(oracle["horizon"])
    limit = config_value(cfg, "env.max_episode_steps")
    return 1000 if limit is None else int(limit)


def recipe_identity(cfg) -> dict:
    """Everything that determines a batch's content, as plain JSON-able data (hashed by :func:`recipe_hash`)."""
    batch = dict(plain(config_value(cfg, "batch")))
    batch.pop("kind", None)  # cosmetic: it is part of the batch's name
    for key in OPERATIONAL_KEYS:  # how to collect (checkpoints, locks), never what
        batch.pop(key, None)
    if not (batch.get("oracle") or {}).get("enabled", False):
        batch.pop("oracle", None)  # off == absent, so adding the block never changes existing hashes
    batch["seed"] = behaviour_seed(cfg)
    if isinstance(batch.get("sac"), Mapping):
        batch["sac"] = sac_identity(batch["sac"], config_value(cfg, "env.id"))
    identity = {"env_id": config_value(cfg, "env.id"), "max_episode_steps": episode_limit(cfg), "batch": batch}
    if batch.get("recipe") == "sac_exec" and batch.get("policy") == "mediocre":
        identity["mediocre_threshold"] = config_value(cfg, "env.mediocre_threshold")
    return identity


@functools.cache
def unit_action_bounds(env_id: str) -> bool:
    """Whether every action dimension of ``env_id`` lies in ``[-1, 1]`` (the env is made once per process to look)."""
    try:
        import gymnasium

        env = gymnasium.make(env_id)
    except Exception:  # noqa: BLE001 - an unknown id (gymnasium raises several kinds): bounds unknown, not unit
        return False
    try:
        space = env.action_space
        return bool((space.low == -1).all() and (space.high == 1).all())
    finally:
        env.close()


def sac_identity(sac: Mapping, env_id: str) -> dict:
    """The ``batch.sac`` block as hashed: ``log_prob_on`` counts only when ``env_id``'s action bound is not 1.

    With bounds ``+-1`` the unscaled and the scaled log-probabilities are the same numbers, so Hopper, Walker2d,
    HalfCheetah and Ant keep the hashes they had before the key existed; Humanoid (bound 0.4) hashes it (absent
    means ``tanh``, the default).

    Examples:
        >>> sac_identity({"gamma": 0.99, "log_prob_on": "tanh"}, "Hopper-v5")
        {'gamma': 0.99}
        >>> sac_identity({"gamma": 0.99}, "Humanoid-v5")
        {'gamma': 0.99, 'log_prob_on': 'tanh'}
    """
    sac = dict(sac)
    log_prob_on = sac.pop("log_prob_on", "tanh")
    if env_id is None or not unit_action_bounds(str(env_id)):
        sac["log_prob_on"] = log_prob_on
    return sac


def stable_hash(obj: Any) -> str:
    """8 hex digits of the SHA-256 of ``obj`` as canonical JSON (sorted keys, no spaces)."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, separators=(",", ":")).encode()).hexdigest()[:8]


def recipe_hash(cfg) -> str:
    """8 hex digits of the SHA-256 of :func:`recipe_identity`."""
    return stable_hash(recipe_identity(cfg))


def data_dir_of(cfg=None, data_dir: str | os.PathLike | None = None) -> Path:
    """``data_dir`` argument, else ``cfg.data_dir``, else :func:`default_data_dir`."""
    if data_dir is None and cfg is not None:
        data_dir = config_value(cfg, "data_dir")
    if data_dir is None:
        data_dir = default_data_dir()
    return Path(os.path.expanduser(str(data_dir))).absolute()


def batch_path(cfg, data_dir: str | os.PathLike | None = None) -> Path:
    """``<data_dir>/<batch_name>-<recipe_hash>``."""
    return data_dir_of(cfg, data_dir) / f"{batch_name(cfg)}-{recipe_hash(cfg)}"


def batch_metadata(cfg, extra: Mapping[str, Any], *, wall_time_s: float) -> dict:
    """The metadata every collected batch carries (``save_batch`` adds stats and versions)."""
    identity = recipe_identity(cfg)
    low, high = extra.pop("action_low"), extra.pop("action_high")
    return {
        "name": batch_name(cfg),
        "env_id": config_value(cfg, "env.id"),
        "env_name": config_value(cfg, "env.name"),
        "kind": config_value(cfg, "batch.kind"),
        "index": int(config_value(cfg, "batch.index")),
        "recipe": {**plain(config_value(cfg, "batch")), "env": config_value(cfg, "env.name"),
                   "env_id": config_value(cfg, "env.id"), "max_episode_steps": episode_limit(cfg)},
        "recipe_hash": recipe_hash(cfg),
        "identity": identity,
        "seed": behaviour_seed(cfg),
        "action_low": [float(x) for x in low],
        "action_high": [float(x) for x in high],
        "oracle": oracle_settings(cfg) is not None,
        "collection_wall_time_s": float(wall_time_s),
        **extra,
    }


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
    stale = config_value(cfg, "batch.lock_stale_after_s") if cfg is not None else None
    beat = config_value(cfg, "batch.heartbeat_every_s") if cfg is not None else None
    if stale is None:
        stale = float(os.environ.get(STALE_ENV, STALE_AFTER_S))
    return float(stale), float(HEARTBEAT_EVERY_S if beat is None else beat)


def _fs_now(directory: Path) -> float:
    """The file system's clock: the mtime of a probe file just touched in ``directory`` (hosts' clocks differ;
    heartbeats are compared on the clock of the file server that stamps them)."""
    probe = directory / f".clock.{host_name()}.{os.getpid()}"
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
        """Touches every registered path once now."""
        with self._lock:
            items = list(self._paths.items())
        for path, (token, _) in items:
            try:
                if token is not None and _read_owner(path).get("token") != token:
                    log.error("lock %s was taken over by another job (our heartbeat was late); "
                              "this job no longer owns it", path)
                    self.unregister(path)
                    self.lost.add(path)
                    continue
                os.utime(path, None)
            except OSError:
                pass

    def check(self) -> None:
        """Raises :class:`LockLost` if a lock of this process was taken over (e.g. the job was suspended for
        longer than the staleness timeout): it must not write what the new owner now writes."""
        with self._lock:
            items = list(self._paths.items())
        for path, (token, _) in items:
            if token is not None and _read_owner(path).get("token") != token:
                self.unregister(path)
                self.lost.add(path)
        if self.lost:
            raise LockLost(f"lock {sorted(map(str, self.lost))[0]} was taken over by another job; stopping here "
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
    except FileExistsError:
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


def _take_over(path: Path, stale_token: str | None) -> None:
    """Moves a stale lock aside; puts it back if it turns out to be a fresh one created meanwhile."""
    aside = path.with_name(f".{path.name}.{owned_name('stale')}")
    try:
        os.rename(path, aside)
    except FileNotFoundError:
        return
    if _read_owner(aside).get("token") != stale_token:  # somebody else took it over first: restore theirs
        with contextlib.suppress(OSError):
            os.link(aside, path)
    with contextlib.suppress(OSError):
        aside.unlink()


@contextlib.contextmanager
def file_lock(path: Path, *, stale_after_s: float | None = None, heartbeat_every_s: float | None = None,
              what: str | None = None, poll_s: float = 0.2) -> Iterator[None]:
    """An exclusive lock across processes *and hosts* sharing ``data_dir``: concurrent jobs wanting the same
    batch collect it once; the others wait (logging ``waiting for <host>:<pid>``) and then reuse it.

    The lock is an owner file (host, pid, process start time, a random token) created atomically; its owner's
    :data:`HEARTBEAT` touches it every ``heartbeat_every_s``. A waiter takes it over when the owner is gone
    (:func:`owner_alive`: a dead pid on this host at once; on another host once the heartbeat is older than
    ``stale_after_s``, default :func:`liveness_settings`). A killed owner leaves the file behind; nothing else
    needs cleaning.
    """
    stale, beat = liveness_settings()
    stale_after_s = stale if stale_after_s is None else float(stale_after_s)
    heartbeat_every_s = beat if heartbeat_every_s is None else float(heartbeat_every_s)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    token = secrets.token_hex(8)
    record = json.dumps({**owner_record(), "token": token, "what": what or path.stem})
    waited_since = None
    last_log = 0.0
    delay = poll_s
    while not _create_exclusively(path, record):
        owner = _read_owner(path)
        try:
            age = _fs_now(path.parent) - path.stat().st_mtime
        except FileNotFoundError:
            continue
        if not owner_alive(owner, age, stale_after_s) and (owner or age >= stale_after_s):
            log.warning("taking over the lock %s of %s:%s (%s)", path.name, owner.get("host", "?"),
                        owner.get("pid", "?"), "process gone" if owner.get("host") == host_name()
                        else f"no heartbeat for {age:.0f} s")
            _take_over(path, owner.get("token"))
            continue
        now = time.monotonic()
        waited_since = now if waited_since is None else waited_since
        if now - last_log >= 60 or last_log == 0.0:
            log.info("waiting for %s:%s, which is making %s (waited %.0f s, its heartbeat %.0f s ago)",
                     owner.get("host", "?"), owner.get("pid", "?"), owner.get("what", path.stem), now - waited_since,
                     age)
            last_log = now
        time.sleep(delay)
        delay = min(delay * 1.5, 5.0)
    HEARTBEAT.lost.discard(path)
    HEARTBEAT.register(path, interval=heartbeat_every_s, token=token)
    try:
        yield
    finally:
        HEARTBEAT.unregister(path)
        HEARTBEAT.lost.discard(path)
        if _read_owner(path).get("token") == token:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(path)


def load_cached_batch(path: Path, *, remedy: str = "it will be collected again"):
    """The cached batch at ``path``, or ``None`` when there is none (a broken one is reported, with what happens
    instead, ``remedy``, and ignored)."""
    if not path.exists():
        return None
    try:
        return load_batch(path)
    except (BatchValidationError, OSError, ValueError, KeyError) as err:
        log.warning("ignoring unreadable cached batch %s (%s); %s", path, err, remedy)
        return None


# --------------------------------------------------------------------------------------------------------------
# listing
# --------------------------------------------------------------------------------------------------------------


def _du(path: Path) -> int:
    total = 0
    for root, _, files in os.walk(path):
        for f in files:
            with contextlib.suppress(OSError):
                total += os.stat(os.path.join(root, f)).st_blocks * 512
    return total


def _recipe_summary(meta: Mapping[str, Any]) -> str:
    recipe = meta.get("recipe") or {}
    kind = recipe.get("recipe", "?")
    parts = [f"{kind}", f"steps={recipe.get('steps')}", f"seed={meta.get('seed')}"]
    if kind == "ddpg":
        parts.append(f"sigma={recipe.get('sigma')}")
    elif kind == "sac_exec":
        parts.append(f"{recipe.get('policy')}/{'stoch' if recipe.get('stochastic') else 'det'}")
        if meta.get("behaviour_return") is not None:
            parts.append(f"policy_return={meta['behaviour_return']:.0f}")
    if meta.get("oracle"):
        parts.append("oracle")
    return " ".join(parts)


def list_batches(data_dir: str | os.PathLike | None = None) -> list[dict[str, Any]]:
    """One row per cached batch in ``data_dir``: name, path, bytes on disk, sizes, episode-return stats, recipe."""
    data_dir = data_dir_of(None, data_dir)
    rows = []
    if not data_dir.is_dir():
        return rows
    for meta_path in sorted(data_dir.glob("*/metadata.json")):
        path = meta_path.parent
        if path.name.startswith("."):
            continue
        try:
            meta = json.loads(meta_path.read_text())
        except (OSError, ValueError):
            continue
        row = {"name": path.name, "path": str(path), "bytes": _du(path), "env_id": meta.get("env_id"),
               "recipe": _recipe_summary(meta)}
        stats = _episode_stats(path, meta)
        row.update(stats)
        rows.append(row)
    return rows


def _episode_stats(path: Path, meta: Mapping[str, Any]) -> dict[str, Any]:
    stats = meta.get("stats") or {}
    out = {
        "transitions": stats.get("num_transitions", meta.get("num_transitions")),
        "episodes": stats.get("num_episodes", meta.get("num_episodes")),
        "mean_return": stats.get("episode_return_mean", stats.get("mean_episode_return")),
        "max_return": stats.get("episode_return_max", stats.get("max_episode_return")),
    }
    if any(v is None for v in out.values()):
        with contextlib.suppress(Exception):
            batch = load_batch(path)
            rets = batch.episode_returns()
            out = {"transitions": int(batch.num_transitions), "episodes": int(batch.num_episodes),
                   "mean_return": float(rets.mean()), "max_return": float(rets.max())}
    return out


def format_bytes(n: int) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if n < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return str(n)

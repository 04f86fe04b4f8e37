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
``<data_dir>/.scratch/<name>-<hash>.<pid>.<random>`` (:func:`scratch_directory`) removed on exit (Ctrl-C included);
a run killed outright leaves it behind and :func:`clean_stale` removes every scratch directory whose process is
gone. :func:`file_lock` makes concurrent jobs wanting the same batch produce it once.

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
import fcntl
import functools
import hashlib
import json
import logging
import os
import secrets
import shutil
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
    "pid_alive",
    "clean_stale",
    "scratch_directory",
    "file_lock",
    "load_cached_batch",
    "list_batches",
    "format_bytes",
]

log = logging.getLogger("torchrl_bail")

DATA_DIR_ENV = "TORCHRL_BAIL_DATA_DIR"
SCRATCH = ".scratch"
LOCKS = ".locks"


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
    if not (batch.get("oracle") or {}).get("enabled", False):
        batch.pop("oracle", None)  # off == absent, so adding the block never changes existing hashes
    batch["seed"] = behaviour_seed(cfg)
    if isinstance(batch.get("sac"), Mapping):
        batch["sac"] = sac_identity(batch["sac"], config_value(cfg, "env.id"))
    identity = {"env_id": config_value(cfg, "env.id"), "max_episode_steps": episode_limit(cfg), "batch": batch}
    if batch.get("recipe") == "sac_exec" and batch.get("policy") == "mediocre":
        identity["mediocre_threshold"] = config_value(cfg, "env.mediocre_threshold")
    return identity


@functools.lru_cache(maxsize=None)
def unit_action_bounds(env_id: str) -> bool:
    """Whether every action dimension of ``env_id`` lies in ``[-1, 1]`` (the env is made once per process to look)."""
    try:
        import gymnasium

        env = gymnasium.make(env_id)
    except Exception:  # an unknown id: treat the bounds as unknown (not unit)
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
# locks, scratch directories, stale files
# --------------------------------------------------------------------------------------------------------------


def pid_alive(pid: int) -> bool:
    """Whether a process with id ``pid`` exists (one owned by another user counts)."""
    try:
        os.kill(pid, 0)
    except OSError as err:
        return err.errno == errno.EPERM
    return True


def clean_stale(data_dir: str | os.PathLike) -> list[Path]:
    """Removes scratch directories (and ``save_batch`` temp dirs) left by processes that no longer exist."""
    data_dir = Path(data_dir)
    removed = []
    candidates = list((data_dir / SCRATCH).glob("*")) if (data_dir / SCRATCH).is_dir() else []
    candidates += [p for p in data_dir.glob(".*") if p.is_dir() and p.name not in (SCRATCH, LOCKS)]
    candidates += list((data_dir / "policies").glob(".*")) if (data_dir / "policies").is_dir() else []
    for path in candidates:
        pid = _pid_in_name(path.name)
        if pid is None or pid_alive(pid):
            continue
        shutil.rmtree(path, ignore_errors=True)
        removed.append(path)
    return removed


def _pid_in_name(name: str) -> int | None:
    """Scratch names are ``<stem>.<pid>.<random>``; ``None`` when the name carries no pid."""
    parts = name.split(".")
    for part in reversed(parts[:-1] if len(parts) > 2 else []):
        if part.isdigit():
            return int(part)
    return None


@contextlib.contextmanager
def scratch_directory(data_dir: Path, stem: str) -> Iterator[Path]:
    """A private directory under ``<data_dir>/.scratch``, removed on exit (exceptions and Ctrl-C included)."""
    path = data_dir / SCRATCH / f"{stem}.{os.getpid()}.{secrets.token_hex(4)}"
    path.mkdir(parents=True)
    try:
        yield path
    finally:
        shutil.rmtree(path, ignore_errors=True)


@contextlib.contextmanager
def file_lock(path: Path) -> Iterator[None]:
    """An exclusive advisory lock (``flock``): concurrent jobs wanting the same batch collect it once."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a+") as f:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)


def load_cached_batch(path: Path):
    """The cached batch at ``path``, or ``None`` when there is none (a broken one is reported and ignored)."""
    if not path.exists():
        return None
    try:
        return load_batch(path)
    except (BatchValidationError, OSError, ValueError, KeyError) as err:
        log.warning("ignoring unreadable cached batch %s (%s); it will be collected again", path, err)
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

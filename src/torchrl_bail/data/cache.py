"""The on-disk batch cache: where batches live and what names and hashes they get.

Every batch is cached as an :class:`~torchrl_bail.data.batch.OfflineBatch` under

``<data_dir>/<env>_<kind>[_oracle]_b<index>-<hash>/``  (``data/`` memmap + ``metadata.json``)

The 8-hex ``hash`` covers everything that determines the data (:func:`recipe_identity`: the env id and time limit,
every field of ``cfg.batch`` except the cosmetic ``kind``, the behaviour seed and, for mediocre-policy batches, the
env's ``mediocre_threshold``), so a quick-preset batch (``batch.steps=50000``) never collides with the paper-scale
one and a changed hyper-parameter never silently reuses stale data.

Seeds: the behaviour seed is ``batch.seed`` or, when that is ``null``, ``batch.index`` -- B1 and B2 differ and the
training seed ``cfg.seed`` never changes a batch.

Collecting a batch safely (scratch and partial directories, locks shared by several hosts) is
:mod:`torchrl_bail.data.locks`; listing the cache is :mod:`torchrl_bail.data.listing`.

The functions that name and hash a batch read a typed collection config (``cfg.env``, ``cfg.batch``,
``cfg.data_dir``: a :class:`torchrl_bail.configuration.config_builders.CollectionConfig`, whose schemas checked every
value), but
never produce data: the behaviour agents that fill the cache live in :mod:`torchrl_bail.behaviour`.

Examples:
    >>> from types import SimpleNamespace as Node
    >>> cfg = Node(env=Node(name="hopper", id="Hopper-v5", max_episode_steps=1000),
    ...            batch=Node(kind="ddpg05", recipe="ddpg", index=2, seed=None, steps=1000, sigma=0.5,
    ...                       oracle=Node(enabled=False)))
    >>> batch_name(cfg), behaviour_seed(cfg), episode_limit(cfg)
    ('hopper_ddpg05_b2', 2, 1000)
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import logging
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from torchrl_bail.data.batch import BatchValidationError, load_batch

__all__ = [
    "DATA_DIR_ENV",
    "default_data_dir",
    "data_dir_of",
    "plain",
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
    "OPERATIONAL_KEYS",
    "load_cached_batch",
]

log = logging.getLogger("torchrl_bail")

DATA_DIR_ENV = "TORCHRL_BAIL_DATA_DIR"
#: ``batch`` keys that say how a batch is collected (checkpoints, locks), not what it holds: outside its hash
OPERATIONAL_KEYS = ("checkpoint_every_s", "checkpoint_every_steps", "lock_stale_after_s", "heartbeat_every_s")


def default_data_dir() -> Path:
    """``$TORCHRL_BAIL_DATA_DIR`` if set, else ``~/.cache/torchrl_bail``."""
    env = os.environ.get(DATA_DIR_ENV)
    return Path(env).expanduser() if env else Path.home() / ".cache" / "torchrl_bail"


# --------------------------------------------------------------------------------------------------------------
# reading configs, names, identities, paths
# --------------------------------------------------------------------------------------------------------------


def plain(node: Any) -> Any:
    """``node`` as plain Python containers (an OmegaConf node is resolved and converted, a dataclass -- a typed
    config -- becomes a dict; anything else as is)."""
    if isinstance(node, DictConfig) or OmegaConf.is_config(node):
        return OmegaConf.to_container(node, resolve=True)
    if dataclasses.is_dataclass(node) and not isinstance(node, type):
        return dataclasses.asdict(node)
    return node


def oracle_settings(cfg) -> dict | None:
    """The ``batch.oracle`` block (``enabled``, ``horizon``, ``keep``, ``gamma``) when oracle mode is on, else
    ``None``."""
    oracle = cfg.batch.oracle
    return plain(oracle) if oracle.enabled else None


def behaviour_seed(cfg) -> int:
    """``batch.seed`` when set, else ``batch.index``: B1 and B2 differ; the training ``seed`` is not used."""
    seed = cfg.batch.seed
    return int(cfg.batch.index if seed is None else seed)


def batch_name(cfg) -> str:
    """``<env.name>_<batch.kind>_b<batch.index>`` (``_oracle`` before ``_b`` in oracle mode)."""
    oracle = "_oracle" if oracle_settings(cfg) else ""
    return f"{cfg.env.name}_{cfg.batch.kind}{oracle}_b{int(cfg.batch.index)}"


def episode_limit(cfg) -> int:
    """The collection env's time limit: ``env.max_episode_steps`` (``oracle.horizon`` in oracle mode; the
    gymnasium default of the MuJoCo envs, 1000, for ``null``)."""
    oracle = oracle_settings(cfg)
    if oracle:
        return int(oracle["horizon"])
    limit = cfg.env.max_episode_steps
    return 1000 if limit is None else int(limit)


def recipe_identity(cfg) -> dict:
    """Everything that determines a batch's content, as plain JSON-able data (hashed by :func:`recipe_hash`)."""
    batch = dict(plain(cfg.batch))
    batch.pop("kind", None)  # cosmetic: it is part of the batch's name
    for key in OPERATIONAL_KEYS:  # how to collect (checkpoints, locks), never what
        batch.pop(key, None)
    if not (batch.get("oracle") or {}).get("enabled", False):
        batch.pop("oracle", None)  # off == absent, so adding the block never changes existing hashes
    batch["seed"] = behaviour_seed(cfg)
    if isinstance(batch.get("sac"), Mapping):
        batch["sac"] = sac_identity(batch["sac"], cfg.env.id)
    identity = {"env_id": cfg.env.id, "max_episode_steps": episode_limit(cfg), "batch": batch}
    if batch.get("policy") == "mediocre":  # a batch of the env's mediocre policy (sac_exec): its threshold counts
        identity["mediocre_threshold"] = cfg.env.mediocre_threshold
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
        data_dir = cfg.data_dir
    if data_dir is None:
        data_dir = default_data_dir()
    return Path(os.path.expanduser(str(data_dir))).absolute()


def batch_path(cfg, data_dir: str | os.PathLike | None = None) -> Path:
    """``<data_dir>/<batch_name>-<recipe_hash>``."""
    return data_dir_of(cfg, data_dir) / f"{batch_name(cfg)}-{recipe_hash(cfg)}"


def batch_metadata(cfg, extra: Mapping[str, Any], *, wall_time_s: float, timed_from_step: int = 0) -> dict:
    """The metadata every collected batch carries (``save_batch`` adds stats and versions).

    ``wall_time_s`` is the collection's, summed over the processes of a collection resumed from its checkpoint;
    ``timed_from_step`` the env step it counts from (``0``; a resume from an older version's checkpoint, which kept no
    time, counts from that checkpoint's step); ``collection_threads`` is torch's thread count while it ran (the
    ``threads`` config key, :func:`~torchrl_bail.cli.use_job_threads`), which its time depends on."""
    import torch

    identity = recipe_identity(cfg)
    low, high = extra.pop("action_low"), extra.pop("action_high")
    return {
        "name": batch_name(cfg),
        "env_id": cfg.env.id,
        "env_name": cfg.env.name,
        "kind": cfg.batch.kind,
        "index": int(cfg.batch.index),
        "recipe": {**plain(cfg.batch), "env": cfg.env.name, "env_id": cfg.env.id,
                   "max_episode_steps": episode_limit(cfg)},
        "recipe_hash": recipe_hash(cfg),
        "identity": identity,
        "seed": behaviour_seed(cfg),
        "action_low": [float(x) for x in low],
        "action_high": [float(x) for x in high],
        "oracle": oracle_settings(cfg) is not None,
        "collection_wall_time_s": float(wall_time_s),
        "collection_timed_from_step": int(timed_from_step),
        "collection_threads": torch.get_num_threads(),
        **extra,
    }


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

"""Behaviour-data catalogue: names, cache paths, recipe validation, dispatch, and the shared collection loop.

Every batch the paper uses is produced on demand by an online behaviour agent (spec section 9) and cached on disk
as an :class:`~torchrl_bail.data.batch.OfflineBatch`:

``<data_dir>/<env>_<kind>[_oracle]_b<index>-<hash>/``  (``data/`` memmap + ``metadata.json``)

The 8-hex ``hash`` covers everything that determines the data (:func:`recipe_identity`: the env id and time limit,
every field of ``cfg.batch`` except the cosmetic ``kind``, the behaviour seed and, for mediocre-policy batches, the
env's ``mediocre_threshold``), so a quick-preset batch (``batch.steps=50000``) never collides with the paper-scale
one and a changed hyper-parameter never silently reuses stale data.

Recipes (``cfg.batch.recipe``):

* ``ddpg`` -- :mod:`torchrl_bail.data.ddpg`: the whole replay buffer of an online DDPG run with N(0, sigma^2)
  exploration noise (spec 9.1).
* ``sac`` -- :mod:`torchrl_bail.data.sac`: the first ``steps`` transitions of an online SAC run (spec 9.2).
* ``sac_exec`` -- :mod:`torchrl_bail.data.sac`: ``steps`` transitions of a frozen SAC policy (mediocre or
  optimal, deterministic or stochastic; spec 9.3). The SAC run behind it is shared with the ``sac`` batch.

Any recipe can be collected in *oracle* mode (``batch.oracle.enabled=true``, spec 2.5): episodes run for
``oracle.horizon`` (2000) steps, the batch keeps the first ``oracle.keep`` (1000) steps of each with
``truncated=True`` at ``t = keep - 1``, and stores ``oracle_return`` [N], the plain discounted return over the
*real* continuation of the episode.

Seeds: the behaviour seed is ``batch.seed`` or, when that is ``null``, ``batch.index`` -- B1 and B2 differ and the
training seed ``cfg.seed`` never changes a batch.

Interruption: nothing is ever written under a batch's final name until it is complete (``save_batch`` writes to a
temporary directory and renames it). The agent's replay buffer lives in a scratch directory
``<data_dir>/.scratch/<name>-<hash>.<pid>.<random>`` that is removed on exit (Ctrl-C included); a run killed
outright leaves it behind and the next :func:`ensure_batch` removes every scratch directory whose process is gone.
An interrupted collection restarts from scratch (no agent checkpoints): the cost is the lost run, never bad data.

Examples:
    >>> from omegaconf import OmegaConf
    >>> cfg = OmegaConf.create({"env": {"name": "hopper", "id": "Hopper-v5", "max_episode_steps": 1000},
    ...                         "batch": {"kind": "ddpg05", "recipe": "ddpg", "index": 2, "steps": 1000,
    ...                                   "sigma": 0.5, "start_steps": 100}})
    >>> batch_name(cfg), behaviour_seed(cfg)
    ('hopper_ddpg05_b2', 2)
    >>> len(recipe_hash(cfg))
    8
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import json
import logging
import math
import os
import secrets
import shutil
import time
from collections import deque
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase

from torchrl_bail.data.returns import discounted_returns

__all__ = [
    "RECIPES",
    "CollectionConfigError",
    "batch_name",
    "batch_path",
    "behaviour_seed",
    "recipe_identity",
    "recipe_hash",
    "validate_recipe",
    "ensure_batch",
    "collect_batch",
    "list_batches",
    "clean_stale",
    "seed_all",
    "make_collection_env",
    "BehaviourRun",
    "BehaviourBuffers",
    "TRANSITION_KEYS",
]

log = logging.getLogger("torchrl_bail")

RECIPES = ("ddpg", "sac", "sac_exec")
EXEC_POLICIES = ("mediocre", "optimal")
SCRATCH = ".scratch"
LOCKS = ".locks"

#: the keys one stored transition carries (TED layout); ``episode`` (and ``oracle_return``) are added per episode
TRANSITION_KEYS = (
    "observation",
    "action",
    ("next", "observation"),
    ("next", "reward"),
    ("next", "done"),
    ("next", "terminated"),
    ("next", "truncated"),
)


class CollectionConfigError(ValueError):
    """A behaviour-data recipe value is missing or out of range; the message names the config key."""


# --------------------------------------------------------------------------------------------------------------
# names, identities, paths
# --------------------------------------------------------------------------------------------------------------


def _container(node: Any) -> Any:
    if isinstance(node, DictConfig) or OmegaConf.is_config(node):
        return OmegaConf.to_container(node, resolve=True)
    return node


def _get(cfg: Any, dotted: str, default: Any = None) -> Any:
    if OmegaConf.is_config(cfg):
        value = OmegaConf.select(cfg, dotted, default=default)
        return _container(value)
    node = cfg
    for part in dotted.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return default
        node = node[part]
    return node


def oracle_settings(cfg) -> dict | None:
    """The resolved ``batch.oracle`` block when oracle mode is on, else ``None``."""
    oracle = _get(cfg, "batch.oracle")
    if not oracle or not oracle.get("enabled", False):
        return None
    return {"horizon": 2000, "keep": 1000, "gamma": 0.99, **oracle}


def behaviour_seed(cfg) -> int:
    """``batch.seed`` when set, else ``batch.index``: B1 and B2 differ; the training ``seed`` is not used."""
    seed = _get(cfg, "batch.seed")
    return int(_get(cfg, "batch.index") if seed is None else seed)


def batch_name(cfg) -> str:
    """``<env.name>_<batch.kind>_b<batch.index>`` (``_oracle`` before ``_b`` in oracle mode)."""
    oracle = "_oracle" if oracle_settings(cfg) else ""
    return f"{_get(cfg, 'env.name')}_{_get(cfg, 'batch.kind')}{oracle}_b{int(_get(cfg, 'batch.index'))}"


def episode_limit(cfg) -> int:
    """The collection env's time limit: ``env.max_episode_steps`` (``oracle.horizon`` in oracle mode)."""
    oracle = oracle_settings(cfg)
    if oracle:
        return int(oracle["horizon"])
    limit = _get(cfg, "env.max_episode_steps")
    return 1000 if limit is None else int(limit)


def recipe_identity(cfg) -> dict:
    """Everything that determines a batch's content, as plain JSON-able data (hashed by :func:`recipe_hash`)."""
    batch = dict(_container(_get(cfg, "batch")))
    batch.pop("kind", None)  # cosmetic: it is part of the batch's name
    if not (batch.get("oracle") or {}).get("enabled", False):
        batch.pop("oracle", None)  # off == absent, so adding the block never changes existing hashes
    batch["seed"] = behaviour_seed(cfg)
    identity = {"env_id": _get(cfg, "env.id"), "max_episode_steps": episode_limit(cfg), "batch": batch}
    if batch.get("recipe") == "sac_exec" and batch.get("policy") == "mediocre":
        identity["mediocre_threshold"] = _get(cfg, "env.mediocre_threshold")
    return identity


def _hash(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, separators=(",", ":")).encode()).hexdigest()[:8]


def recipe_hash(cfg) -> str:
    """8 hex digits of the SHA-256 of :func:`recipe_identity`."""
    return _hash(recipe_identity(cfg))


def data_dir_of(cfg=None, data_dir: str | os.PathLike | None = None) -> Path:
    """``data_dir`` argument, else ``cfg.data_dir``, else :func:`~torchrl_bail.data.batch.default_data_dir`."""
    if data_dir is None and cfg is not None:
        data_dir = _get(cfg, "data_dir")
    if data_dir is None:
        from torchrl_bail.data.batch import default_data_dir

        data_dir = default_data_dir()
    return Path(os.path.expanduser(str(data_dir))).absolute()


def batch_path(cfg, data_dir: str | os.PathLike | None = None) -> Path:
    """``<data_dir>/<batch_name>-<recipe_hash>``."""
    return data_dir_of(cfg, data_dir) / f"{batch_name(cfg)}-{recipe_hash(cfg)}"


# --------------------------------------------------------------------------------------------------------------
# validation
# --------------------------------------------------------------------------------------------------------------


def validate_recipe(cfg) -> None:
    """Checks ``cfg.env`` / ``cfg.batch`` before any work starts; raises :class:`CollectionConfigError`."""

    def need(cond: bool, key: str, expected: str) -> None:
        if not cond:
            raise CollectionConfigError(f"config key {key} = {_get(cfg, key)!r}: expected {expected}")

    def number(key: str) -> bool:
        v = _get(cfg, key)
        return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)

    def integer(key: str) -> bool:
        v = _get(cfg, key)
        return isinstance(v, int) and not isinstance(v, bool)

    def hidden(key: str) -> None:
        v = _get(cfg, key)
        need(isinstance(v, list) and all(isinstance(h, int) and h > 0 for h in v), key,
             "a list of positive layer widths, e.g. [400, 300]")

    need(isinstance(_get(cfg, "env.id"), str), "env.id", "a gymnasium id such as Hopper-v5")
    need(isinstance(_get(cfg, "env.name"), str), "env.name", "a short env name such as hopper")
    limit = _get(cfg, "env.max_episode_steps")
    need(limit is None or (integer("env.max_episode_steps") and limit >= 1), "env.max_episode_steps",
         "a positive integer (or null for the env's default)")
    need(isinstance(_get(cfg, "batch.kind"), str), "batch.kind", "a string such as ddpg05")
    recipe = _get(cfg, "batch.recipe")
    need(recipe in RECIPES, "batch.recipe", f"one of {', '.join(RECIPES)}")
    need(integer("batch.index") and _get(cfg, "batch.index") >= 1, "batch.index", "an integer >= 1 (B1, B2, ...)")
    need(_get(cfg, "batch.seed") is None or integer("batch.seed"), "batch.seed", "null or an integer")
    need(integer("batch.steps") and _get(cfg, "batch.steps") > 0, "batch.steps", "a positive number of transitions")

    oracle = _get(cfg, "batch.oracle")
    if oracle is not None:
        need(isinstance(oracle, dict) and isinstance(oracle.get("enabled", False), bool), "batch.oracle.enabled",
             "true or false")
    if oracle_settings(cfg):
        need(integer("batch.oracle.keep") and _get(cfg, "batch.oracle.keep") >= 1, "batch.oracle.keep",
             "a positive number of steps kept per episode")
        need(integer("batch.oracle.horizon") and _get(cfg, "batch.oracle.horizon") > _get(cfg, "batch.oracle.keep"),
             "batch.oracle.horizon", "an episode length larger than batch.oracle.keep")
        need(number("batch.oracle.gamma") and 0 < _get(cfg, "batch.oracle.gamma") <= 1, "batch.oracle.gamma",
             "a discount in (0, 1]")

    if recipe == "ddpg":
        need(number("batch.sigma") and _get(cfg, "batch.sigma") >= 0, "batch.sigma",
             "a non-negative noise std (absolute, not scaled by the action bound)")
        need(integer("batch.start_steps") and _get(cfg, "batch.start_steps") >= 0, "batch.start_steps",
             "a non-negative number of uniformly random steps")
        hidden("batch.agent.actor_hidden")
        hidden("batch.agent.critic_hidden")
        for key in ("actor_lr", "critic_lr"):
            need(number(f"batch.agent.{key}") and _get(cfg, f"batch.agent.{key}") > 0, f"batch.agent.{key}",
                 "a positive learning rate")
        need(number("batch.agent.critic_weight_decay") and _get(cfg, "batch.agent.critic_weight_decay") >= 0,
             "batch.agent.critic_weight_decay", "a non-negative L2 coefficient")
        need(number("batch.agent.gamma") and 0 < _get(cfg, "batch.agent.gamma") <= 1, "batch.agent.gamma",
             "a discount in (0, 1]")
        need(number("batch.agent.tau") and 0 < _get(cfg, "batch.agent.tau") <= 1, "batch.agent.tau",
             "a soft-update rate in (0, 1]")
        need(integer("batch.agent.batch_size") and _get(cfg, "batch.agent.batch_size") >= 1,
             "batch.agent.batch_size", "a positive mini-batch size")
        arch = _get(cfg, "batch.agent.critic_arch", "late_action")
        need(arch in ("late_action", "concat"), "batch.agent.critic_arch", "late_action | concat")
    else:
        _validate_sac_block(cfg, need, number, integer, hidden)
        if recipe == "sac":
            need(_get(cfg, "batch.steps") <= _get(cfg, "batch.sac.train_steps"), "batch.steps",
                 f"at most batch.sac.train_steps = {_get(cfg, 'batch.sac.train_steps')} (the batch is the first "
                 "batch.steps transitions of the SAC run)")
        if recipe == "sac_exec":
            need(_get(cfg, "batch.policy") in EXEC_POLICIES, "batch.policy", "mediocre | optimal")
            need(isinstance(_get(cfg, "batch.stochastic"), bool), "batch.stochastic",
                 "false (sigma=0: max_action*tanh(mu)) or true (sigma=sigma(s))")
            if _get(cfg, "batch.policy") == "mediocre":
                need(number("env.mediocre_threshold"), "env.mediocre_threshold",
                     "the return at which the mediocre SAC policy is frozen")


def _validate_sac_block(cfg, need, number, integer, hidden) -> None:
    need(isinstance(_get(cfg, "batch.sac"), dict), "batch.sac", "the SAC agent block (see conf/batch/sac.yaml)")
    hidden("batch.sac.actor_hidden")
    hidden("batch.sac.critic_hidden")
    for key in ("actor_lr", "critic_lr", "alpha_lr"):
        need(number(f"batch.sac.{key}") and _get(cfg, f"batch.sac.{key}") > 0, f"batch.sac.{key}",
             "a positive learning rate")
    need(number("batch.sac.gamma") and 0 < _get(cfg, "batch.sac.gamma") <= 1, "batch.sac.gamma", "a discount in (0, 1]")
    need(number("batch.sac.polyak") and 0 <= _get(cfg, "batch.sac.polyak") < 1, "batch.sac.polyak",
         "a target-network decay in [0, 1) (0.995)")
    need(number("batch.sac.alpha_init") and _get(cfg, "batch.sac.alpha_init") > 0, "batch.sac.alpha_init",
         "a positive initial entropy coefficient")
    te = _get(cfg, "batch.sac.target_entropy")
    need(te == "auto" or number("batch.sac.target_entropy"), "batch.sac.target_entropy", "auto or a number")
    need(number("batch.sac.log_std_min") and number("batch.sac.log_std_max")
         and _get(cfg, "batch.sac.log_std_min") < _get(cfg, "batch.sac.log_std_max"), "batch.sac.log_std_min",
         "log_std_min < log_std_max")
    for key, lo in (("batch_size", 1), ("start_steps", 0), ("train_steps", 1), ("eval_every", 1),
                    ("eval_episodes", 1)):
        need(integer(f"batch.sac.{key}") and _get(cfg, f"batch.sac.{key}") >= lo, f"batch.sac.{key}",
             f"an integer >= {lo}")
    need(_get(cfg, "batch.sac.loss_function") in ("l2", "smooth_l1", "l1"), "batch.sac.loss_function",
         "l2 | smooth_l1 | l1")


# --------------------------------------------------------------------------------------------------------------
# cache, locks, stale files
# --------------------------------------------------------------------------------------------------------------


def _pid_alive(pid: int) -> bool:
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
        if pid is None or _pid_alive(pid):
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


def _try_load(path: Path):
    """The cached batch at ``path``, or ``None`` when there is none (a broken one is reported and ignored)."""
    from torchrl_bail.data.batch import BatchValidationError, load_batch

    if not path.exists():
        return None
    try:
        return load_batch(path)
    except (BatchValidationError, OSError, ValueError, KeyError) as err:
        log.warning("ignoring unreadable cached batch %s (%s); it will be collected again", path, err)
        return None


def ensure_batch(cfg, *, progress: bool = True, data_dir: str | os.PathLike | None = None):
    """Loads the cached batch for ``cfg.env`` x ``cfg.batch``, collecting it first when it is not there yet.

    Returns:
        the :class:`~torchrl_bail.data.batch.OfflineBatch`.
    """
    validate_recipe(cfg)
    path = batch_path(cfg, data_dir)
    batch = _try_load(path)
    if batch is not None:
        log.info("using cached batch %s", path)
        return batch
    root = path.parent
    root.mkdir(parents=True, exist_ok=True)
    clean_stale(root)
    with file_lock(root / LOCKS / f"{path.name}.lock"):
        batch = _try_load(path)  # another job may have made it while we waited
        if batch is not None:
            return batch
        if path.exists():  # unreadable leftovers under the final name: move them aside, never delete silently
            aside = path.with_name(f"{path.name}.broken-{time.strftime('%Y%m%d-%H%M%S')}")
            os.replace(path, aside)
            log.warning("moved unreadable batch directory %s to %s", path, aside)
        return collect_batch(cfg, path, progress=progress)


def collect_batch(cfg, path: str | os.PathLike, *, progress: bool = True):
    """Runs the behaviour recipe of ``cfg.batch`` and saves the result at ``path`` (atomically)."""
    validate_recipe(cfg)
    path = Path(path)
    recipe = _get(cfg, "batch.recipe")
    start = time.perf_counter()
    log.info("collecting %s (%s, %d transitions) into %s", batch_name(cfg), recipe, _get(cfg, "batch.steps"), path)
    with scratch_directory(path.parent, path.name) as scratch:
        if recipe == "ddpg":
            from torchrl_bail.data.ddpg import collect_ddpg

            data, extra = collect_ddpg(cfg, scratch=scratch, progress=progress)
        elif recipe == "sac":
            from torchrl_bail.data.sac import collect_sac

            data, extra = collect_sac(cfg, scratch=scratch, progress=progress, data_dir=path.parent)
        else:
            from torchrl_bail.data.sac import collect_sac_exec

            data, extra = collect_sac_exec(cfg, scratch=scratch, progress=progress, data_dir=path.parent)
        metadata = batch_metadata(cfg, extra, wall_time_s=time.perf_counter() - start)
        from torchrl_bail.data.batch import save_batch

        batch = save_batch(data, path, metadata)
    return batch


def batch_metadata(cfg, extra: Mapping[str, Any], *, wall_time_s: float) -> dict:
    """The metadata every collected batch carries (``save_batch`` adds stats and versions)."""
    identity = recipe_identity(cfg)
    low, high = extra.pop("action_low"), extra.pop("action_high")
    return {
        "name": batch_name(cfg),
        "env_id": _get(cfg, "env.id"),
        "env_name": _get(cfg, "env.name"),
        "kind": _get(cfg, "batch.kind"),
        "index": int(_get(cfg, "batch.index")),
        "recipe": {**_container(_get(cfg, "batch")), "env": _get(cfg, "env.name"), "env_id": _get(cfg, "env.id"),
                   "max_episode_steps": episode_limit(cfg)},
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
            from torchrl_bail.data.batch import load_batch

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


# --------------------------------------------------------------------------------------------------------------
# the shared collection loop
# --------------------------------------------------------------------------------------------------------------


def seed_all(seed: int) -> None:
    """Seeds Python, NumPy and torch from the behaviour seed."""
    import random

    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def make_collection_env(env_id: str, *, max_episode_steps: int | None, seed: int):
    """One gymnasium env (``GymEnv`` + ``DoubleToFloat``), seeded; never ``num_envs`` (zero terminal obs).

    ``GymEnv.set_seed`` resets the env with ``seed``; the first episode starts from the reset after that.
    """
    from torchrl.envs import DoubleToFloat, GymEnv, TransformedEnv

    kwargs = {} if max_episode_steps is None else {"max_episode_steps": int(max_episode_steps)}
    env = TransformedEnv(GymEnv(env_id, **kwargs), DoubleToFloat())
    env.set_seed(int(seed))
    return env


class EpisodeStore:
    """A preallocated memmap store of ``capacity`` transitions (the batch), filled one episode at a time.

    Backed by a TorchRL :class:`~torchrl.data.LazyMemmapStorage` in ``scratch`` so that 10^6 Humanoid-size rows
    live on disk (page cache), never twice in RAM; :meth:`sample` draws uniformly from what is stored so far.
    """

    def __init__(self, capacity: int, scratch: Path, *, batch_size: int | None = None):
        from torchrl.data import LazyMemmapStorage, TensorDictReplayBuffer

        self.capacity = int(capacity)
        self.rb = TensorDictReplayBuffer(
            storage=LazyMemmapStorage(self.capacity, scratch_dir=scratch, auto_cleanup=False),
            batch_size=batch_size,
        )

    def __len__(self) -> int:
        return len(self.rb)

    def extend(self, episode: TensorDictBase) -> None:
        n = episode.shape[0]
        if len(self) + n > self.capacity:
            raise RuntimeError(f"episode store overflow: {len(self)} + {n} > {self.capacity}")
        self.rb.extend(episode)

    def sample(self, batch_size: int | None = None) -> TensorDictBase:
        return self.rb.sample() if batch_size is None else self.rb.sample(batch_size)

    def data(self) -> TensorDictBase:
        """The stored rows as a memmapped TensorDict (no copy), without the buffer's bookkeeping ``index``."""
        storage = self.rb.storage._storage  # the memmap TensorDict LazyMemmapStorage allocated
        td = storage[: len(self)] if len(self) < self.capacity else storage
        return td.exclude("index")


class BatchSink:
    """Where finished episodes go: every transition (plain mode) or the oracle cut (spec 2.5).

    Plain mode: the store holds exactly ``steps`` transitions; the final episode may be unfinished.

    Oracle mode: each episode (up to ``horizon`` steps) contributes its first ``keep`` steps, with
    ``truncated=done=True`` at ``t = keep - 1`` when the episode went on, and ``oracle_return`` = the plain discounted
    return over the whole real episode. Once ``steps`` transitions are kept, the open episode is run to its end
    (for the returns) and only its rows up to the budget are kept -- that last episode is unfinished.
    """

    def __init__(self, store: EpisodeStore, steps: int, oracle: dict | None = None):
        self.store = store
        self.steps = int(steps)
        self.oracle = oracle
        self.episode_id = 0
        self.kept = 0

    @property
    def budget_reached(self) -> bool:
        """No more transitions are needed (oracle mode: the open episode still has to finish)."""
        return self.kept >= self.steps

    def add_episode(self, episode: TensorDictBase) -> None:
        """``episode``: the TED rows of one episode (finished, or cut by the budget in plain mode)."""
        n = episode.shape[0]
        if self.oracle is None:
            keep = min(n, self.steps - self.kept)
            rows = episode[:keep]
        else:
            g = discounted_returns(episode["next", "reward"], torch.zeros(n, dtype=torch.int64),
                                   float(self.oracle["gamma"])).float()
            keep_ep = min(n, int(self.oracle["keep"]))
            rows = episode[:keep_ep].clone()
            rows.set("oracle_return", g[:keep_ep])
            if n > keep_ep:  # the episode went on past `keep`: the kept part ends in a time-limit truncation
                rows["next", "truncated"][-1] = True
                rows["next", "done"][-1] = True
            keep = min(keep_ep, self.steps - self.kept)
            rows = rows[:keep]
        if keep <= 0:
            return
        rows.set("episode", torch.full((keep,), self.episode_id, dtype=torch.int64))
        self.store.extend(rows)
        self.kept += keep
        self.episode_id += 1


class ReturnTracker:
    """tqdm progress (env steps/s, mean return of the last 10 episodes) and per-episode bookkeeping."""

    def __init__(self, total: int, *, desc: str, progress: bool, window: int = 10):
        self.returns: deque[float] = deque(maxlen=window)
        self.all_returns: list[float] = []
        self.lengths: list[int] = []
        self.bar = None
        self.postfix: dict[str, Any] = {}
        if progress:
            from tqdm.auto import tqdm

            self.bar = tqdm(total=total, desc=desc, unit="step", dynamic_ncols=True, mininterval=0.5, smoothing=0.05)
        self._pending = 0

    def step(self, n: int = 1) -> None:
        if self.bar is not None:
            self._pending += n
            if self._pending >= 100:
                self.bar.update(self._pending)
                self._pending = 0

    def episode(self, ret: float, length: int) -> None:
        self.returns.append(ret)
        self.all_returns.append(ret)
        self.lengths.append(length)
        if self.bar is not None:
            self.postfix["ret10"] = f"{self.mean_recent:.1f}"
            self.postfix["ep"] = len(self.all_returns)
            self.bar.set_postfix(self.postfix, refresh=False)

    def note(self, **kv: Any) -> None:
        if self.bar is not None:
            self.postfix.update(kv)
            self.bar.set_postfix(self.postfix, refresh=False)

    @property
    def mean_recent(self) -> float:
        return float(np.mean(self.returns)) if self.returns else float("nan")

    def close(self) -> None:
        if self.bar is not None:
            self.bar.update(self._pending)
            self._pending = 0
            self.bar.close()


class BehaviourRun:
    """The step loop every recipe shares: act, step one env, record, and call hooks at episode ends.

    Args:
        env: a seeded TorchRL env from :func:`make_collection_env`.
        act: ``act(observation [obs_dim], t) -> action [act_dim]`` (``t`` = env steps taken so far).

    Keyword Args:
        on_episode_end: ``f(length, episode_return, t)`` after an episode ends (DDPG/SAC train here).
        on_step: ``f(t)`` after every env step (SAC evaluates here).
        tracker: a :class:`ReturnTracker` (progress bar, recent returns).
    """

    def __init__(self, env, act: Callable[[torch.Tensor, int], torch.Tensor], *,
                 on_episode_end: Callable[[int, float, int], None] | None = None,
                 on_step: Callable[[int], None] | None = None,
                 tracker: ReturnTracker | None = None):
        self.env = env
        self.act = act
        self.on_episode_end = on_episode_end
        self.on_step = on_step
        self.tracker = tracker
        self.t = 0
        self.episodes = 0

    def run(self, sinks: list, *, until: Callable[[int], bool], finish_open_episode: bool = False) -> None:
        """Steps until ``until(rows_in_open_episode)`` holds.

        When it holds mid-episode the open episode is handed to the sinks unfinished, or, with
        ``finish_open_episode`` (oracle continuation), first run to its end with no more hooks called.
        """
        env = self.env
        td = env.reset()
        rows: list[TensorDictBase] = []
        ep_ret = 0.0
        finishing = False
        while True:
            if not finishing and until(len(rows)):
                if rows and finish_open_episode:
                    finishing = True
                else:
                    break
            td.set("action", self.act(td["observation"], self.t))
            step_td, td = env.step_and_maybe_reset(td)
            rows.append(step_td.select(*TRANSITION_KEYS))
            ep_ret += float(step_td["next", "reward"])
            self.t += 1
            if self.tracker is not None:
                self.tracker.step()
            if bool(step_td["next", "done"]):
                length = len(rows)
                self._flush(rows, sinks)
                rows = []
                self.episodes += 1
                if self.tracker is not None:
                    self.tracker.episode(ep_ret, length)
                if finishing:
                    break
                if self.on_episode_end is not None and not until(0):  # no learning once the batch is full
                    self.on_episode_end(length, ep_ret, self.t)
                ep_ret = 0.0
            if not finishing and self.on_step is not None:
                self.on_step(self.t)
        if rows:
            self._flush(rows, sinks)

    @staticmethod
    def _flush(rows: list[TensorDictBase], sinks) -> None:
        episode = torch.stack(rows)
        for sink in sinks:
            if isinstance(sink, BatchSink):
                sink.add_episode(episode)
            else:
                sink.extend(episode)


class BehaviourBuffers:
    """The agent's replay buffer and the batch, for plain or oracle collection of ``steps`` transitions.

    Plain mode: one memmap store is both the agent's replay buffer and the batch (the paper's "the batch IS the
    replay buffer"). Oracle mode: the agent replays every transition it saw (up to 2000-step episodes) from its
    own store; the batch keeps the oracle cut (:class:`BatchSink`).

    Args:
        steps: transitions in the batch.
        scratch: a scratch directory (removed by the caller).

    Keyword Args:
        oracle: :func:`oracle_settings` or ``None``.
        replay_batch_size: mini-batch size the agent samples (``None``: no agent, e.g. policy execution).
    """

    def __init__(self, steps: int, scratch: Path, *, oracle: dict | None, replay_batch_size: int | None):
        self.steps = int(steps)
        self.oracle = oracle
        self.batch_store = EpisodeStore(self.steps, scratch / "batch",
                                        batch_size=replay_batch_size if oracle is None else None)
        self.sink = BatchSink(self.batch_store, self.steps, oracle=oracle)
        self.replay: EpisodeStore | None = None
        if replay_batch_size is not None:
            if oracle is None:
                self.replay = self.batch_store
            else:
                ratio = math.ceil(int(oracle["horizon"]) / int(oracle["keep"]))
                self.replay = EpisodeStore(ratio * self.steps + int(oracle["horizon"]), scratch / "replay",
                                           batch_size=replay_batch_size)

    @property
    def sinks(self) -> list:
        return [self.sink] + ([self.replay] if self.replay is not None and self.replay is not self.batch_store else [])

    def until(self, open_rows: int) -> bool:
        if self.oracle is None:
            return self.sink.kept + open_rows >= self.steps
        return self.sink.kept + min(open_rows, int(self.oracle["keep"])) >= self.steps

    def collect(self, runner: BehaviourRun) -> TensorDictBase:
        """Runs ``runner`` until the batch is full; returns the batch (memmapped, no copy)."""
        runner.run(self.sinks, until=self.until, finish_open_episode=self.oracle is not None)
        if self.sink.kept != self.steps:
            raise RuntimeError(f"collected {self.sink.kept} transitions, expected {self.steps}")
        return self.batch_store.data()


def env_bounds(env) -> tuple[torch.Tensor, torch.Tensor]:
    spec = env.action_spec
    space = getattr(spec, "space", None)
    low = space.low if space is not None else spec.low
    high = space.high if space is not None else spec.high
    return low.detach().clone().float(), high.detach().clone().float()

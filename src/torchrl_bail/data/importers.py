"""Import datasets users already have on disk (their normalised scores: :mod:`torchrl_bail.data.scores`).

:func:`import_dataset` accepts three kinds of path and returns an :class:`~torchrl_bail.data.batch.OfflineBatch`:

* a **D4RL-layout HDF5 file** (``.hdf5`` / ``.h5``): flat arrays ``observations [N, obs]``, ``actions [N, act]``,
  ``rewards [N]``, ``terminals [N]``, ``timeouts [N]`` and optionally ``next_observations [N, obs]``; other keys
  (``infos/*``, ``metadata/*``) are ignored. Read with h5py; neither ``d4rl`` nor mujoco-py is needed.
* a **local Minari dataset**: ``<root>/<dataset_id>/`` or its ``data/`` folder, holding ``metadata.json`` and
  ``main_data.hdf5`` (groups ``episode_<i>`` with ``observations [T+1, obs]``, ``actions``, ``rewards``,
  ``terminations``, ``truncations``). The HDF5 layout is parsed directly with h5py; only Minari's other storage
  formats (``data_format`` ``arrow``/``parquet``) need the optional ``minari`` package
  (``pip install -e ".[minari]"``).
* a **native batch directory** (``data/`` + ``metadata.json``, see :mod:`torchrl_bail.data.batch`): loaded as is.

How a file becomes a batch (TED layout, ``float32`` observations, actions and rewards, converted once):

* Episode boundaries come from ``terminals | timeouts`` only (never from comparing observations).
  ``terminated`` = ``terminals``, ``truncated`` = ``timeouts``, ``done`` = either; ``episode`` ids count from 0.
* ``next/observation`` is ``next_observations`` when the file has them. Otherwise it is the next row's
  observation within the episode, and the last row of an episode has no known next observation:

  - an episode ending in a **timeout**: its last row is dropped (a truncated transition needs its real next state
    for bootstrapping, and that state is not in the file -- ``d4rl.qlearning_dataset`` drops these rows too). The
    row before it becomes the episode's last one, flagged ``truncated`` (the episode is cut one step earlier),
    and keeps its genuine next observation (the dropped row's observation). Such episodes are one step shorter:
    with ``returns.horizon=1000`` a 1000-step Hopper episode becomes 999 steps and is no longer "time-limited"
    for the gain augmentation (set ``returns.horizon=999`` for such files, or use files with
    ``next_observations``, as every D4RL v2 MuJoCo file has);
  - an episode ending in a **terminal**: the row is kept (its reward and the termination are real and the next
    state is never bootstrapped from, every TD target multiplies it by ``1 - terminated``); ``next/observation``
    holds a copy of ``observation`` as a finite placeholder, counted in the metadata as
    ``placeholder_next_observation_rows``;
  - a **trailing unfinished episode** (the file ends without a terminal or timeout): its last row is dropped (its
    next observation is unknown); the rest stays the batch's final, unfinished episode.

  Every dropped row is counted in the metadata (``dropped_rows``).
* A trailing unfinished episode in a file *with* ``next_observations`` is kept whole as the batch's final unfinished
  episode (the batch format allows exactly one, at the end).
* Minari episodes carry their final observation, so nothing is dropped; an episode whose last step has neither
  ``terminations`` nor ``truncations`` set (a recording stopped by its collector) is flagged ``truncated``, except
  the last episode of a dataset this package exported from a batch whose final episode was still running
  (metadata ``torchrl_bail.unfinished_final_episode``): it stays the batch's final unfinished episode. Such
  exports also keep a step flagged both terminated and truncated as it is (the batch held gymnasium's flags as
  they came); every other dataset gets the "a true terminal wins" rule below.

Every check happens at the edge and raises :class:`DatasetImportError` (a
:class:`~torchrl_bail.data.batch.BatchValidationError`) naming the file, the key and what was expected: a missing
key, ragged lengths, non-2-D arrays, non-0/1 flags, NaN/inf, an observation/action size that differs from the env's
(``env_id`` given: the sizes come from ``gymnasium.make(env_id)``'s spaces), an empty file. A row with both
``terminals`` and ``timeouts`` set (gymnasium allows a step to be both: a fall on the time limit's last step) is a
true terminal: ``terminated=True``, ``truncated=False``, since its next state must not be bootstrapped from; the
metadata counts such rows (``terminal_and_timeout_rows``).

The converted batch is cached in the data directory (``data_dir``, else ``$TORCHRL_BAIL_DATA_DIR``, else
``~/.cache/torchrl_bail``) as ``import_<name>-<hash>/``, written atomically by
:func:`~torchrl_bail.data.batch.save_batch`; ``hash`` covers the source's absolute path, size and modification time
(every file of a Minari dataset), so a second import of the same file is a cache hit and a changed file is
converted again (the stale conversion stays on disk until removed; ``python -m torchrl_bail.collect --list`` shows it).

Each format is one module of :mod:`torchrl_bail.data.formats` that registers itself
(:func:`~torchrl_bail.data.formats.base.register_format`); this module never names one. A path no registered format
claims is one :class:`DatasetImportError` listing what each format expects.

Examples:
    >>> import tempfile, h5py, numpy as np
    >>> d = tempfile.mkdtemp()
    >>> with h5py.File(f"{d}/toy.hdf5", "w") as f:
    ...     f["observations"] = np.arange(12, dtype=np.float64).reshape(6, 2)
    ...     f["actions"] = np.zeros((6, 1))
    ...     f["rewards"] = np.ones(6)
    ...     f["terminals"] = np.array([0, 0, 1, 0, 0, 0], dtype=bool)
    ...     f["timeouts"] = np.array([0, 0, 0, 0, 1, 0], dtype=bool)
    >>> batch = import_dataset(f"{d}/toy.hdf5", data_dir=f"{d}/cache")
    >>> batch.data["episode"].tolist(), batch.metadata["dropped_rows"]
    ([0, 0, 0, 1], 2)
    >>> batch.data["next", "truncated"].flatten().tolist()
    [False, False, False, True]
    >>> batch.data["observation"].dtype
    torch.float32
"""

from __future__ import annotations

import functools
import json
import logging
import os
import re
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

from torchrl_bail.data.batch import OfflineBatch, save_batch
from torchrl_bail.data.cache import data_dir_of, load_cached_batch, stable_hash
from torchrl_bail.data.formats import (
    Checker,
    DatasetFormat,
    DatasetImportError,
    find_format,
)
from torchrl_bail.data.formats.d4rl import D4RL_KEYS
from torchrl_bail.data.formats.minari import EXPORT_KEY, MINARI_INSTALL
from torchrl_bail.data.locks import LOCKS, file_lock

__all__ = [
    "D4RL_KEYS",
    "EXPORT_KEY",
    "IMPORT_PREFIX",
    "MINARI_INSTALL",
    "DatasetImportError",
    "describe_import",
    "detect_format",
    "env_sizes",
    "import_cache_path",
    "import_dataset",
    "iter_imported",
]

log = logging.getLogger("torchrl_bail")

#: bumped whenever the conversion changes, so that old cached conversions are not reused
IMPORTER_VERSION = 1
#: cached conversions are ``<data_dir>/import_<name>-<hash>``
IMPORT_PREFIX = "import_"


# --------------------------------------------------------------------------------------------------------------
# formats and cache paths
# --------------------------------------------------------------------------------------------------------------


def _find(path: str | os.PathLike) -> tuple[DatasetFormat, Path]:
    path = Path(path).expanduser()
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such dataset file or directory")
    return find_format(path)


def detect_format(path: str | os.PathLike) -> tuple[str, Path]:
    """``(format name, location)`` for a dataset path (``"d4rl"``, ``"minari"``, ``"native"`` or a registered
    format's name); one :class:`DatasetImportError` naming every known format when none claims it.

    ``location`` is the HDF5 file (D4RL), the Minari ``data/`` folder, or the batch directory (native).
    """
    fmt, location = _find(path)
    return fmt.name, location


def _safe_name(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._") or "dataset"


def _source_identity(fmt: str, location: Path) -> dict[str, Any]:
    """What the cache key covers: absolute path, size and modification time of every source file."""
    files = [location] if location.is_file() else sorted(p for p in location.rglob("*") if p.is_file())
    entries = []
    for f in files:
        st = f.stat()
        entries.append([str(f.relative_to(location)) if f != location else "", st.st_size, st.st_mtime_ns])
    return {"format": fmt, "path": str(location), "files": entries, "importer_version": IMPORTER_VERSION}


def _cache_path(fmt: DatasetFormat, location: Path, data_dir: str | os.PathLike | None) -> Path:
    identity = _source_identity(fmt.name, location)
    name = _safe_name(fmt.source_name(location))
    return data_dir_of(None, data_dir) / f"{IMPORT_PREFIX}{name}-{stable_hash(identity)}"


def import_cache_path(path: str | os.PathLike, data_dir: str | os.PathLike | None = None) -> Path | None:
    """Where :func:`import_dataset` caches the conversion of ``path``; ``None`` for a native batch directory (a
    format loaded in place)."""
    fmt, location = _find(Path(path).expanduser().resolve())
    return None if fmt.in_place else _cache_path(fmt, location, data_dir)


def describe_import(metadata: Mapping[str, Any]) -> str | None:
    """One line for ``collect --list`` when ``metadata`` belongs to an imported batch, else ``None``."""
    source = metadata.get("source")
    if not isinstance(source, Mapping) or "format" not in source:
        return None
    parts = [f"import {source['format']}", str(source.get("path", "?"))]
    if metadata.get("dropped_rows"):
        parts.append(f"dropped={metadata['dropped_rows']}")
    return " ".join(parts)


# --------------------------------------------------------------------------------------------------------------
# env sizes
# --------------------------------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=16)
def _env_spaces(env_id: str) -> tuple[int, int, tuple[float, ...], tuple[float, ...]]:
    import gymnasium as gym

    env = gym.make(env_id)
    try:
        obs_space, act_space = env.observation_space, env.action_space
        if len(obs_space.shape or ()) != 1 or len(act_space.shape or ()) != 1:
            raise ValueError(f"spaces {obs_space} / {act_space} are not flat Boxes")
        return (int(obs_space.shape[0]), int(act_space.shape[0]),
                tuple(float(x) for x in act_space.low), tuple(float(x) for x in act_space.high))
    finally:
        env.close()


def env_sizes(env_id: str, *, source: str) -> tuple[int, int, tuple[float, ...], tuple[float, ...]]:
    """``(obs_dim, act_dim, action_low, action_high)`` of ``gymnasium.make(env_id)``; a clear error if it fails."""
    try:
        return _env_spaces(str(env_id))
    except Exception as err:  # noqa: BLE001 - any failure to build the env is reported against the dataset
        raise DatasetImportError(
            f"{source}: cannot check the data's sizes against env {env_id!r}: {type(err).__name__}: {err}"
        ) from None


# --------------------------------------------------------------------------------------------------------------
# the entry point
# --------------------------------------------------------------------------------------------------------------


def _check_loaded_sizes(batch: OfflineBatch, source: Path, obs_dim: int | None, act_dim: int | None,
                        env_id: str | None) -> None:
    check = Checker(str(source), obs_dim, act_dim, env_id)
    check.sizes("observations", batch.obs_dim, "actions", batch.act_dim)


def import_dataset(path: str | os.PathLike, *, env_id: str | None = None,
                   data_dir: str | os.PathLike | None = None) -> OfflineBatch:
    """Imports a D4RL HDF5 file, a local Minari dataset or a native batch directory (see the module doc), or a path
    of any other registered format (:mod:`torchrl_bail.data.formats`).

    Args:
        path: the ``.hdf5`` / ``.h5`` file, the Minari dataset folder (or its ``data/``), or a batch directory.
        env_id: a gymnasium id (e.g. ``Hopper-v5``); when given, the data's observation and action sizes must match
            its spaces, and the batch records its action bounds. Without it the sizes are not checked and the
            batch's ``env_id`` is the Minari dataset's env (or ``None``).
        data_dir: where conversions are cached (default: ``$TORCHRL_BAIL_DATA_DIR`` or ``~/.cache/torchrl_bail``).

    Returns:
        the memory-mapped :class:`~torchrl_bail.data.batch.OfflineBatch` (the cached conversion, or the native
        batch itself).

    Raises:
        FileNotFoundError: ``path`` does not exist.
        DatasetImportError: no registered format claims ``path``, or the data breaks its format; the message names
            the file, the key and the expectation.
    """
    fmt, location = _find(Path(path).expanduser().resolve())
    fmt.check(location)
    obs_dim = act_dim = None
    low = high = None
    if env_id:
        obs_dim, act_dim, low, high = env_sizes(env_id, source=str(location))
    if fmt.in_place:
        batch = fmt.load(location)
        _check_loaded_sizes(batch, location, obs_dim, act_dim, env_id)
        return batch

    cache = _cache_path(fmt, location, data_dir)
    batch = load_cached_batch(cache, remedy="converting again")
    if batch is None:
        cache.parent.mkdir(parents=True, exist_ok=True)
        with file_lock(cache.parent / LOCKS / f"{cache.name}.lock"):
            # another job may have converted it while we waited
            batch = load_cached_batch(cache, remedy="converting again")
            if batch is None:
                batch = _convert_and_save(fmt, location, cache, env_id, obs_dim, act_dim, low, high)
                log.info("imported %s -> %s (%d transitions, %d episodes)", location, cache,
                         batch.num_transitions, batch.num_episodes)
                return batch
    _check_loaded_sizes(batch, location, obs_dim, act_dim, env_id)
    if env_id and batch.metadata.get("env_id") not in (None, env_id):
        log.warning("cached import %s was converted for env %s; using it for %s (same sizes)", cache,
                    batch.metadata.get("env_id"), env_id)
    log.info("using cached import %s of %s", cache, location)
    return batch


def _convert_and_save(fmt: DatasetFormat, location: Path, cache: Path, env_id: str | None, obs_dim: int | None,
                      act_dim: int | None, low, high) -> OfflineBatch:
    conversion = fmt.convert(location, Checker(str(location), obs_dim, act_dim, env_id))
    td, info = conversion.data, conversion.info
    meta: dict[str, Any] = {
        "name": fmt.source_name(location),
        "env_id": env_id or conversion.env_id,
        "kind": "import",
        "source": {**_source_identity(fmt.name, location), "format": fmt.label or fmt.name},
        **info,
    }
    if low is not None:
        meta["action_low"], meta["action_high"] = list(low), list(high)
    elif conversion.action_low is not None and len(conversion.action_low) == td.get("action").shape[-1]:
        meta["action_low"], meta["action_high"] = list(conversion.action_low), list(conversion.action_high)
    return save_batch(td, cache, meta, overwrite=True)


def iter_imported(rows: Iterable[Mapping[str, Any]]) -> Iterator[tuple[Mapping[str, Any], str]]:
    """``(row, description)`` for each ``list_batches`` row that is an imported batch (for ``collect --list``)."""
    for row in rows:
        try:
            meta = json.loads((Path(row["path"]) / "metadata.json").read_text())
        except (OSError, ValueError, KeyError):
            continue
        desc = describe_import(meta)
        if desc is not None:
            yield row, desc

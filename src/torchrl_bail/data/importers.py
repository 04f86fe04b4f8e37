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

import numpy as np
import torch
from tensordict import TensorDict

from torchrl_bail.data.batch import (
    BatchValidationError,
    OfflineBatch,
    load_batch,
    save_batch,
)
from torchrl_bail.data.cache import data_dir_of, load_cached_batch, stable_hash
from torchrl_bail.data.locks import LOCKS, file_lock

__all__ = [
    "D4RL_KEYS",
    "IMPORT_PREFIX",
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
#: the metadata block this package writes into the Minari datasets it exports (:mod:`torchrl_bail.data.minari_export`)
EXPORT_KEY = "torchrl_bail"
#: the keys a D4RL-layout file must hold (``next_observations`` is optional)
D4RL_KEYS = ("observations", "actions", "rewards", "terminals", "timeouts")
HDF5_SUFFIXES = (".hdf5", ".h5")
MINARI_INSTALL = 'pip install -e ".[minari]"'

class DatasetImportError(BatchValidationError):
    """An external dataset cannot be imported; the message names the file, the key and what was expected."""


# --------------------------------------------------------------------------------------------------------------
# formats and cache paths
# --------------------------------------------------------------------------------------------------------------


def _is_native(path: Path) -> bool:
    return path.is_dir() and (path / "metadata.json").is_file() and (path / "data").is_dir()


def _minari_data_dir(path: Path) -> Path | None:
    """The Minari ``data/`` folder for ``path`` (the dataset folder, its ``data/``, or ``main_data.hdf5``)."""
    if path.is_file() and path.name == "main_data.hdf5" and (path.parent / "metadata.json").is_file():
        return path.parent
    if path.is_dir():
        for candidate in (path / "data", path):
            meta = candidate / "metadata.json"
            if meta.is_file() and (
                (candidate / "main_data.hdf5").is_file() or _json_has(meta, "data_format")
            ):
                return candidate
    return None


def _json_has(path: Path, key: str) -> bool:
    try:
        return key in json.loads(path.read_text())
    except (OSError, ValueError):
        return False


def detect_format(path: str | os.PathLike) -> tuple[str, Path]:
    """``("d4rl" | "minari" | "native", location)`` for a dataset path; clear errors otherwise.

    ``location`` is the HDF5 file (D4RL), the Minari ``data/`` folder, or the batch directory (native).
    """
    path = Path(path).expanduser()
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such dataset file or directory")
    if _is_native(path):
        return "native", path
    minari_dir = _minari_data_dir(path)
    if minari_dir is not None:
        return "minari", minari_dir
    if path.is_file():
        if path.suffix.lower() in HDF5_SUFFIXES:
            return "d4rl", path
        raise DatasetImportError(
            f"{path}: expected a D4RL-layout HDF5 file (*.hdf5 or *.h5), a Minari dataset directory or a native "
            f"batch directory, found a file with suffix {path.suffix!r}"
        )
    raise DatasetImportError(
        f"{path}: expected a Minari dataset directory (data/metadata.json + data/main_data.hdf5) or a native batch "
        f"directory (metadata.json + data/), found a directory with {sorted(p.name for p in path.iterdir())[:10]}"
    )


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


def _source_name(fmt: str, location: Path) -> str:
    if fmt == "minari":
        try:
            dataset_id = json.loads((location / "metadata.json").read_text()).get("dataset_id")
        except (OSError, ValueError):
            dataset_id = None
        return str(dataset_id) if dataset_id else (location.parent.name if location.name == "data" else location.name)
    return location.stem


def import_cache_path(path: str | os.PathLike, data_dir: str | os.PathLike | None = None) -> Path | None:
    """Where :func:`import_dataset` caches the conversion of ``path``; ``None`` for a native batch directory."""
    fmt, location = detect_format(Path(path).expanduser().resolve())
    if fmt == "native":
        return None
    identity = _source_identity(fmt, location)
    name = _safe_name(_source_name(fmt, location))
    return data_dir_of(None, data_dir) / f"{IMPORT_PREFIX}{name}-{stable_hash(identity)}"


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
# checks shared by both readers
# --------------------------------------------------------------------------------------------------------------


class _Checker:
    """Raises :class:`DatasetImportError` with ``<file>: key '<key>': expected ..., found ...``."""

    def __init__(self, source: str, obs_dim: int | None, act_dim: int | None, env_id: str | None):
        self.source, self.obs_dim, self.act_dim, self.env_id = source, obs_dim, act_dim, env_id

    def fail(self, key: str | None, expected: str, found: str) -> None:
        where = f" key {key!r}:" if key is not None else ""
        raise DatasetImportError(f"{self.source}:{where} expected {expected}, found {found}")

    def numeric(self, key: str, value: np.ndarray) -> None:
        if not (np.issubdtype(value.dtype, np.number) or value.dtype == np.bool_):
            self.fail(key, "numeric values", f"dtype {value.dtype}")

    def matrix(self, key: str, value: np.ndarray) -> np.ndarray:
        self.numeric(key, value)
        if value.ndim != 2:
            self.fail(key, "a 2-D array [steps, features]", f"shape {tuple(value.shape)}")
        return value

    def vector(self, key: str, value: np.ndarray) -> np.ndarray:
        self.numeric(key, value)
        if value.ndim == 2 and value.shape[1] == 1:
            value = value[:, 0]
        if value.ndim != 1:
            self.fail(key, "a 1-D array [steps]", f"shape {tuple(value.shape)}")
        return value

    def flags(self, key: str, value: np.ndarray) -> np.ndarray:
        value = self.vector(key, value)
        if value.dtype != np.bool_:
            bad = ~np.isin(value, (0, 1))
            if bad.any():
                i = int(np.flatnonzero(bad)[0])
                self.fail(key, "boolean flags (0/1)", f"{value[i].item()!r} at row {i}")
        return value.astype(bool)

    def rows(self, key: str, value: np.ndarray, n: int, reference: str) -> None:
        if value.shape[0] != n:
            self.fail(key, f"{n} rows (as many as {reference!r})", f"{value.shape[0]} rows (ragged lengths)")

    def finite32(self, key: str, value: np.ndarray, offset: int = 0) -> np.ndarray:
        """The float32 copy of ``value`` (made once), after checking every entry is finite."""
        out = np.asarray(value, dtype=np.float32)
        finite = np.isfinite(out.reshape(out.shape[0], -1)).all(axis=1)
        if not finite.all():
            i = int(np.flatnonzero(~finite)[0])
            kind = "NaN" if np.isnan(np.asarray(value[i], dtype=np.float64)).any() else "inf (or beyond float32)"
            self.fail(key, "finite values", f"{kind} at row {i + offset}")
        return out

    def sizes(self, obs_key: str, obs_dim: int, act_key: str, act_dim: int) -> None:
        env = f" of env {self.env_id}" if self.env_id else ""
        if self.obs_dim is not None and obs_dim != self.obs_dim:
            self.fail(obs_key, f"{self.obs_dim} observation features (the observation size{env})", f"{obs_dim}")
        if self.act_dim is not None and act_dim != self.act_dim:
            self.fail(act_key, f"{self.act_dim} action dimensions (the action size{env})", f"{act_dim}")


def _terminal_wins(term: np.ndarray, trunc: np.ndarray) -> tuple[np.ndarray, int]:
    """``truncated`` with rows that are also terminal cleared (a true terminal wins), and how many there were."""
    both = term & trunc
    return trunc & ~both, int(both.sum())


def _episode_ids(done: np.ndarray) -> np.ndarray:
    """Episode id of each row: 0 for the first episode, +1 after every ``done`` row."""
    ids = np.zeros(done.shape[0], dtype=np.int64)
    if done.shape[0] > 1:
        ids[1:] = np.cumsum(done[:-1], dtype=np.int64)
    return ids


def _ted(obs, act, next_obs, rew, term, trunc) -> TensorDict:
    n = obs.shape[0]
    term_t = torch.from_numpy(np.ascontiguousarray(term, dtype=bool)).unsqueeze(-1)
    trunc_t = torch.from_numpy(np.ascontiguousarray(trunc, dtype=bool)).unsqueeze(-1)
    return TensorDict({
        "observation": torch.from_numpy(np.ascontiguousarray(obs)),
        "action": torch.from_numpy(np.ascontiguousarray(act)),
        "episode": torch.from_numpy(_episode_ids(term | trunc)),
        "next": {
            "observation": torch.from_numpy(np.ascontiguousarray(next_obs)),
            "reward": torch.from_numpy(np.ascontiguousarray(rew, dtype=np.float32)).reshape(n, 1),
            "terminated": term_t,
            "truncated": trunc_t,
            "done": term_t | trunc_t,
        },
    }, [n])


# --------------------------------------------------------------------------------------------------------------
# D4RL HDF5
# --------------------------------------------------------------------------------------------------------------


def _open_hdf5(path: Path):
    import h5py

    try:
        return h5py.File(path, "r")
    except OSError as err:
        raise DatasetImportError(f"{path}: expected a readable HDF5 file, found unreadable data ({err})") from None


def _read_dataset(f, key: str, check: _Checker) -> np.ndarray:
    import h5py

    node = f[key]
    if not isinstance(node, h5py.Dataset):
        check.fail(key, "an array (HDF5 dataset)", f"a {type(node).__name__}")
    return node[()]


def _d4rl_is_minari(path: Path) -> bool:
    """A ``.hdf5`` with ``episode_<i>`` groups and no ``observations``: Minari's ``main_data.hdf5`` layout."""
    with _open_hdf5(path) as f:
        keys = list(f.keys())
    return "observations" not in keys and bool(keys) and all(k.startswith("episode_") for k in keys)


def _convert_d4rl(path: Path, check: _Checker) -> tuple[TensorDict, dict[str, Any]]:
    with _open_hdf5(path) as f:
        keys = sorted(f.keys())
        if not keys:
            check.fail(None, f"a D4RL dataset with keys {list(D4RL_KEYS)}", "an empty HDF5 file (no keys)")
        for key in D4RL_KEYS:
            if key not in f:
                extra = (" (timeouts mark time-limit truncations; without them the episode boundaries are unknown)"
                         if key == "timeouts" else "")
                check.fail(key, f"this key to be present{extra}", f"keys {keys}")
        raw = {key: _read_dataset(f, key, check) for key in D4RL_KEYS}
        has_next = "next_observations" in f
        if has_next:
            raw["next_observations"] = _read_dataset(f, "next_observations", check)
    ignored = [k for k in keys if k not in raw]

    obs = check.matrix("observations", raw["observations"])
    n = obs.shape[0]
    if n == 0:
        check.fail("observations", "at least one transition", "0 rows (an empty dataset)")
    act = check.matrix("actions", raw["actions"])
    rew = check.vector("rewards", raw["rewards"])
    for key, value in (("actions", act), ("rewards", rew), ("terminals", raw["terminals"]),
                       ("timeouts", raw["timeouts"])):
        check.rows(key, value, n, "observations")
    term = check.flags("terminals", raw["terminals"])
    trunc = check.flags("timeouts", raw["timeouts"])
    if has_next:
        nxt = check.matrix("next_observations", raw["next_observations"])
        check.rows("next_observations", nxt, n, "observations")
        if nxt.shape[1] != obs.shape[1]:
            check.fail("next_observations", f"{obs.shape[1]} features (as many as 'observations')",
                       f"{nxt.shape[1]}")
    check.sizes("observations", obs.shape[1], "actions", act.shape[1])
    trunc, both = _terminal_wins(term, trunc)
    obs = check.finite32("observations", obs)
    act = check.finite32("actions", act)
    rew = check.finite32("rewards", rew)

    done = term | trunc
    info: dict[str, Any] = {"rows_in_file": int(n), "ignored_keys": ignored, "terminal_and_timeout_rows": both,
                            "unfinished_final_episode": not bool(done[-1])}
    if has_next:
        nxt = check.finite32("next_observations", nxt)
        info.update(next_observation="next_observations", dropped_rows=0, placeholder_next_observation_rows=0)
        return _ted(obs, act, nxt, rew, term, trunc), info

    # no next_observations: the next row's observation within the episode (see the module doc for episode ends)
    nxt = np.empty_like(obs)
    nxt[:-1] = obs[1:]
    nxt[-1] = obs[-1]
    nxt[term] = obs[term]  # placeholder: a terminal's next state is never bootstrapped from
    drop = trunc.copy()
    drop[-1] |= not done[-1]  # the trailing unfinished episode's last row: its next observation is unknown
    new_trunc = np.zeros(n, dtype=bool)
    new_trunc[:-1] = trunc[1:] & ~done[:-1]  # the row before a dropped timeout row ends its (shortened) episode
    keep = ~drop
    if not keep.any():
        check.fail(None, "at least one transition with a known next observation (the file has no "
                         "'next_observations')", f"{n} rows, every one the last step of a timeout episode")
    info.update(next_observation="shifted observations", dropped_rows=int(drop.sum()),
                placeholder_next_observation_rows=int(term.sum()))
    td = _ted(obs[keep], act[keep], nxt[keep], rew[keep], term[keep], new_trunc[keep])
    return td, info


# --------------------------------------------------------------------------------------------------------------
# Minari
# --------------------------------------------------------------------------------------------------------------


def _minari_metadata(data_dir: Path) -> dict[str, Any]:
    meta_file = data_dir / "metadata.json"
    try:
        meta = json.loads(meta_file.read_text())
    except ValueError as err:
        raise DatasetImportError(f"{meta_file}: expected valid JSON (Minari dataset metadata), found {err}") from None
    if not isinstance(meta, dict):
        raise DatasetImportError(f"{meta_file}: expected a JSON object, found {type(meta).__name__}")
    return meta


def _space(meta: Mapping[str, Any], key: str) -> dict | None:
    value = meta.get(key)
    if isinstance(value, str):
        try:
            value = json.loads(value)
        except ValueError:
            return None
    return value if isinstance(value, dict) else None


def _minari_env_id(meta: Mapping[str, Any]) -> str | None:
    spec = meta.get("env_spec")
    if isinstance(spec, str):
        try:
            spec = json.loads(spec)
        except ValueError:
            return None
    return spec.get("id") if isinstance(spec, dict) else None


def _minari_hdf5_episodes(data_dir: Path, check: _Checker) -> Iterator[tuple[str, dict[str, Any]]]:
    import h5py

    main = data_dir / "main_data.hdf5"
    if not main.is_file():
        check.fail(None, "main_data.hdf5 beside metadata.json (Minari's HDF5 storage)", "no such file")
    with _open_hdf5(main) as f:
        names = [k for k in f if re.fullmatch(r"episode_\d+", k)]
        if not names:
            check.fail(None, "groups episode_<i> (Minari's HDF5 layout)", f"keys {sorted(f)[:10]}")
        for name in sorted(names, key=lambda k: int(k.split("_")[1])):
            group = f[name]
            episode: dict[str, Any] = {}
            for key in ("observations", "actions", "rewards", "terminations", "truncations"):
                if key not in group:
                    check.fail(f"{name}/{key}", "this key to be present", f"keys {sorted(group.keys())}")
                node = group[key]
                if not isinstance(node, h5py.Dataset):
                    check.fail(f"{name}/{key}", "a flat array (Box observation/action spaces only)",
                               f"a group with keys {sorted(node.keys())[:10]} (a Dict/Tuple space)")
                episode[key] = node[()]
            yield name, episode


def _minari_package_episodes(data_dir: Path, fmt: str) -> Iterator[tuple[str, dict[str, Any]]]:
    try:
        import minari
    except ImportError:
        raise DatasetImportError(
            f"{data_dir}: this Minari dataset is stored as {fmt!r}; reading it needs the optional minari package: "
            f"{MINARI_INSTALL} (HDF5-format Minari datasets are read without it)"
        ) from None
    dataset = minari.MinariDataset(data_dir)
    for episode in dataset.iterate_episodes():
        yield f"episode_{episode.id}", {key: getattr(episode, key) for key in
                                        ("observations", "actions", "rewards", "terminations", "truncations")}


def _convert_minari(data_dir: Path, check: _Checker) -> tuple[TensorDict, dict[str, Any]]:
    meta = _minari_metadata(data_dir)
    fmt = str(meta.get("data_format", "hdf5"))
    source = data_dir / "main_data.hdf5" if fmt == "hdf5" else data_dir
    check.source = str(source)
    episodes = _minari_hdf5_episodes(data_dir, check) if fmt == "hdf5" else _minari_package_episodes(data_dir, fmt)
    parts: dict[str, list[np.ndarray]] = {k: [] for k in ("obs", "act", "next", "rew", "term", "trunc")}
    export = meta.get(EXPORT_KEY) if isinstance(meta.get(EXPORT_KEY), Mapping) else {}
    rows = empty = unflagged = 0
    last_unflagged = False
    sizes: tuple[int, int] | None = None
    for name, ep in episodes:
        obs, act, rew, term, trunc = _minari_episode_arrays(name, ep, check)
        sizes = _check_minari_sizes(name, obs, act, sizes, check)
        steps = rew.shape[0]
        if steps == 0:
            empty += 1
            continue
        trunc, last_unflagged = _minari_episode_end(name, term, trunc, bool(export), check)
        unflagged += last_unflagged
        obs32 = check.finite32(f"{name}/observations", obs)
        parts["obs"].append(obs32[:-1])
        parts["next"].append(obs32[1:])
        parts["act"].append(check.finite32(f"{name}/actions", act))
        parts["rew"].append(check.finite32(f"{name}/rewards", rew))
        parts["term"].append(term)
        parts["trunc"].append(trunc)
        rows += steps
    if rows == 0:
        check.fail(None, "at least one transition", f"no steps in any episode ({empty} empty episodes)")
    unfinished = bool(export.get("unfinished_final_episode")) and last_unflagged
    if unfinished:  # exported from a batch whose last episode was still running: it stays unfinished
        parts["trunc"][-1][-1] = False
        unflagged -= 1
    cat = {k: np.concatenate(v) for k, v in parts.items()}
    td = _ted(cat["obs"], cat["act"], cat["next"], cat["rew"], cat["term"], cat["trunc"])
    info: dict[str, Any] = {
        "rows_in_file": int(rows), "dropped_rows": 0, "placeholder_next_observation_rows": 0,
        "next_observation": "episode observations[t + 1]", "empty_episodes_skipped": empty,
        "episodes_without_end_flag": unflagged, "minari_data_format": fmt,
        "unfinished_final_episode": unfinished,
    }
    info.update(_minari_info(meta))
    return td, info


def _minari_episode_arrays(name: str, ep: Mapping[str, Any], check: _Checker) -> tuple[np.ndarray, ...]:
    """One Minari episode's ``(observations, actions, rewards, terminations, truncations)``, checked: flat arrays,
    ``steps + 1`` observations and ``steps`` of everything else, boolean flags."""
    for key in ("observations", "actions"):
        if not isinstance(ep[key], np.ndarray):
            check.fail(f"{name}/{key}", "a flat array (Box observation/action spaces only)",
                       f"{type(ep[key]).__name__} (a Dict/Tuple space)")
    obs = check.matrix(f"{name}/observations", np.asarray(ep["observations"]))
    act = check.matrix(f"{name}/actions", np.asarray(ep["actions"]))
    rew = check.vector(f"{name}/rewards", np.asarray(ep["rewards"]))
    steps = rew.shape[0]
    check.rows(f"{name}/observations", obs, steps + 1, f"{name}/rewards' plus the final observation")
    for key, value in (("actions", act), ("terminations", ep["terminations"]),
                       ("truncations", ep["truncations"])):
        check.rows(f"{name}/{key}", np.asarray(value), steps, f"{name}/rewards")
    term = check.flags(f"{name}/terminations", np.asarray(ep["terminations"]))
    trunc = check.flags(f"{name}/truncations", np.asarray(ep["truncations"]))
    return obs, act, rew, term, trunc


def _check_minari_sizes(name: str, obs: np.ndarray, act: np.ndarray, sizes: tuple[int, int] | None,
                        check: _Checker) -> tuple[int, int]:
    """The first episode's observation and action sizes (checked against the env's, when given); every later
    episode must have the same. Returns them."""
    if sizes is None:
        check.sizes(f"{name}/observations", obs.shape[1], f"{name}/actions", act.shape[1])
        return obs.shape[1], act.shape[1]
    if (obs.shape[1], act.shape[1]) != sizes:
        check.fail(f"{name}/observations", f"the sizes of the first episode ({sizes[0]} observation features, "
                   f"{sizes[1]} action dimensions)", f"({obs.shape[1]}, {act.shape[1]})")
    return sizes


def _minari_episode_end(name: str, term: np.ndarray, trunc: np.ndarray, exported: bool,
                        check: _Checker) -> tuple[np.ndarray, bool]:
    """A non-empty episode's end flags: a flag on its last step only; one recorded without any gets a truncation.
    Returns ``(truncations, whether the last step had no flag)``."""
    if not exported:  # this package's own exports keep the batch's flags as recorded (gymnasium's, both may be set)
        trunc, _ = _terminal_wins(term, trunc)
    early = (term | trunc)[:-1]
    if early.any():
        key = f"{name}/terminations" if term[:-1].any() else f"{name}/truncations"
        check.fail(key, "a flag only on an episode's last step", f"one at step {int(np.flatnonzero(early)[0])} "
                   f"of {term.shape[0]}")
    unflagged = not (term[-1] or trunc[-1])
    if unflagged:
        trunc = trunc.copy()
        trunc[-1] = True  # the recording stopped here: a truncation (the final observation is known)
    return trunc, unflagged


def _minari_info(meta: Mapping[str, Any]) -> dict[str, Any]:
    """What the batch records of the Minari dataset's metadata: its id, reference scores, algorithm, version, env
    and Box action bounds (the keys it has)."""
    info: dict[str, Any] = {}
    for key in ("dataset_id", "ref_min_score", "ref_max_score", "algorithm_name", "minari_version"):
        if meta.get(key) is not None:
            info[key] = meta[key]
    env_id = _minari_env_id(meta)
    if env_id:
        info["minari_env_id"] = env_id
    space = _space(meta, "action_space")
    if space and space.get("type") == "Box" and "low" in space and "high" in space:
        info["minari_action_low"] = [float(x) for x in np.ravel(space["low"])]
        info["minari_action_high"] = [float(x) for x in np.ravel(space["high"])]
    return info


# --------------------------------------------------------------------------------------------------------------
# the entry point
# --------------------------------------------------------------------------------------------------------------


def _check_loaded_sizes(batch: OfflineBatch, source: Path, obs_dim: int | None, act_dim: int | None,
                        env_id: str | None) -> None:
    check = _Checker(str(source), obs_dim, act_dim, env_id)
    check.sizes("observations", batch.obs_dim, "actions", batch.act_dim)


def import_dataset(path: str | os.PathLike, *, env_id: str | None = None,
                   data_dir: str | os.PathLike | None = None) -> OfflineBatch:
    """Imports a D4RL HDF5 file, a local Minari dataset or a native batch directory (see the module doc).

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
        DatasetImportError: the data breaks the format; the message names the file, the key and the expectation.
    """
    location = Path(path).expanduser().resolve()
    fmt, location = detect_format(location)
    if fmt == "d4rl" and _d4rl_is_minari(location):
        raise DatasetImportError(
            f"{location}: expected D4RL keys {list(D4RL_KEYS)}, found Minari episode_<i> groups; pass the Minari "
            "dataset folder (the one holding data/metadata.json and data/main_data.hdf5) instead"
        )
    obs_dim = act_dim = None
    low = high = None
    if env_id:
        obs_dim, act_dim, low, high = env_sizes(env_id, source=str(location))
    if fmt == "native":
        batch = load_batch(location)
        _check_loaded_sizes(batch, location, obs_dim, act_dim, env_id)
        return batch

    cache = import_cache_path(location, data_dir)
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


def _convert_and_save(fmt: str, location: Path, cache: Path, env_id: str | None, obs_dim: int | None,
                      act_dim: int | None, low, high) -> OfflineBatch:
    check = _Checker(str(location), obs_dim, act_dim, env_id)
    if fmt == "d4rl":
        td, info = _convert_d4rl(location, check)
        label = "d4rl_hdf5"
    else:
        td, info = _convert_minari(location, check)
        label = "minari"
    name = _source_name(fmt, location)
    meta: dict[str, Any] = {
        "name": name,
        "env_id": env_id or info.get("minari_env_id"),
        "kind": "import",
        "source": {**_source_identity(fmt, location), "format": label},
        **info,
    }
    if low is not None:
        meta["action_low"], meta["action_high"] = list(low), list(high)
    elif "minari_action_low" in info and len(info["minari_action_low"]) == td.get("action").shape[-1]:
        meta["action_low"], meta["action_high"] = info["minari_action_low"], info["minari_action_high"]
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

"""The offline batch format: a TED TensorDict ``[N]`` memory-mapped on disk, plus ``metadata.json``.

Layout of a batch directory::

    <batch_dir>/data/           tensordict memmap (TensorDict.memmap / load_memmap)
    <batch_dir>/metadata.json   env id, recipe and its parameters, seed, sizes, behaviour return statistics,
                                library versions, creation time

Keys (TED): ``observation`` ``[N, obs]`` float32, ``action`` ``[N, act]`` float32,
``("next", "observation")`` ``[N, obs]`` float32, ``("next", "reward")`` ``[N, 1]`` float32,
``("next", "done" | "terminated" | "truncated")`` ``[N, 1]`` bool, ``episode`` ``[N]`` int64. Extra keys (e.g.
``oracle_return``) are kept.

Writes are atomic: the batch is written into a sibling temporary directory and renamed into place, so an
interrupted write never leaves anything that loads as a batch. Loading validates everything and every
violation raises :class:`BatchValidationError` naming the file, the key and what was expected.

Examples:
    >>> import tempfile, torch
    >>> from tensordict import TensorDict
    >>> n = 5
    >>> done = torch.tensor([False, True, False, False, False]).unsqueeze(-1)
    >>> td = TensorDict({"observation": torch.zeros(n, 3), "action": torch.zeros(n, 2),
    ...                  "episode": torch.tensor([0, 0, 1, 1, 1]),
    ...                  "next": {"observation": torch.zeros(n, 3), "reward": torch.ones(n, 1),
    ...                           "done": done, "terminated": done, "truncated": torch.zeros(n, 1, dtype=torch.bool)}},
    ...                 [n])
    >>> batch = save_batch(td, tempfile.mkdtemp() + "/tiny", {"env_id": "Toy-v0"})
    >>> batch.num_transitions, batch.num_episodes, batch.episode_returns().tolist()
    (5, 2, [2.0, 3.0])
    >>> load_batch(batch.path).metadata["num_episodes"]
    2
"""

from __future__ import annotations

import datetime as _dt
import importlib.metadata
import json
import os
import shutil
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase

from torchrl_bail.core.errors import BatchValidationError
from torchrl_bail.core.io import write_json_atomic
from torchrl_bail.data.locks import check_fence

__all__ = [
    "BatchValidationError",
    "OfflineBatch",
    "REQUIRED_KEYS",
    "FORMAT_VERSION",
    "validate_batch",
    "batch_statistics",
    "STATISTICS_KEYS",
    "save_batch",
    "load_batch",
    "cpu_model",
    "library_versions",
    "source_revision",
    "platform_record",
    "write_json_atomic",
]

FORMAT_VERSION = 1
FLOAT_KEYS = ("observation", "action", ("next", "observation"), ("next", "reward"))
BOOL_KEYS = (("next", "done"), ("next", "terminated"), ("next", "truncated"))
REQUIRED_KEYS = (*FLOAT_KEYS, *BOOL_KEYS, "episode")


def _name(key) -> str:
    return key if isinstance(key, str) else "/".join(key)


def library_versions() -> dict[str, str]:
    versions = {}
    for pkg in ("torch", "torchrl", "tensordict", "gymnasium", "mujoco", "numpy", "torchrl_bail"):
        try:
            versions[pkg] = importlib.metadata.version(pkg)
        except importlib.metadata.PackageNotFoundError:
            versions[pkg] = None
    return versions


def source_revision(package: Path | None = None) -> dict[str, Any] | None:
    """The git commit of the checkout this package (or the package folder ``package``) runs from, an editable
    install's ``src/torchrl_bail``, and whether the checkout's tracked files under ``src/`` and ``conf/`` differ from
    it; ``None`` for an installed package (even one inside another repository), or where git is missing. The package
    version alone does not tell two states of the code apart.

    Examples:
        >>> revision = source_revision()
        >>> revision is None or (len(revision["commit"]) == 40 and isinstance(revision["modified"], bool))
        True
    """
    import subprocess

    package = Path(package or Path(__file__).parents[1]).resolve()

    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(package), *args], capture_output=True, text=True, timeout=30,
                              check=True).stdout.strip()

    try:
        root = Path(git("rev-parse", "--show-toplevel")).resolve()
        if root / "src" / package.name != package:  # the package lies in someone else's repository (a venv in it)
            return None
        return {"commit": git("rev-parse", "HEAD"),
                "modified": bool(git("status", "--porcelain", "--untracked-files=no", "--", str(root / "src"),
                                     str(root / "conf")))}
    except (OSError, subprocess.SubprocessError):
        return None


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``), or the platform's processor string."""
    import platform

    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def platform_record() -> dict:
    """What a run's numbers depend on beyond its config and seed: the library versions (:func:`library_versions`),
    the code's own git revision (:func:`source_revision`), Python's version, the CPU's model name (:func:`cpu_model`)
    and the SIMD level torch's CPU kernels use. Two runs of one config and seed that agree here must give the same
    numbers on the CPU; runs that differ here may differ in the last digits (another CPU kind rounds matrix products
    otherwise), and the difference grows over training; or more, where the code changed between the revisions.

    Examples:
        >>> sorted(platform_record())
        ['cpu', 'cpu_capability', 'python', 'source', 'versions']
    """
    import platform

    return {"versions": library_versions(), "source": source_revision(), "python": platform.python_version(),
            "cpu": cpu_model(), "cpu_capability": torch.backends.cpu.get_cpu_capability()}


def _episode_boundaries(episode: torch.Tensor) -> torch.Tensor:
    """Boolean ``[N]``: True at the last row of each episode block."""
    last = torch.ones_like(episode, dtype=torch.bool)
    last[:-1] = episode[1:] != episode[:-1]
    return last


def validate_batch(
    td: TensorDictBase,
    metadata: dict | None = None,
    *,
    source: str = "<memory>",
    obs_dim: int | None = None,
    act_dim: int | None = None,
) -> None:
    """Raises :class:`BatchValidationError` at the first violation of the batch format (see module doc)."""
    keys = _check_layout(td, source)
    _check_shapes(td, source)
    _check_dtypes(td, source)
    _check_finite(td, keys, source)
    _check_env_sizes(td, source, obs_dim, act_dim)
    _check_episodes(td, source)
    if metadata is not None:
        _check_metadata(td, metadata, source)


def _fail(source: str, key, expected: str, found: str) -> None:
    """Raises the one-line :class:`BatchValidationError` of a violation: ``<source>: key '<key>' expected ...``."""
    where = f" key {_name(key)!r}" if key is not None else ""
    raise BatchValidationError(f"{source}:{where} expected {expected}, found {found}")


def _check_layout(td: TensorDictBase, source: str) -> set:
    """One batch dimension, at least one row, every required key; returns the batch's leaf keys."""
    if td.batch_dims != 1:
        _fail(source, None, "a TensorDict with one batch dimension [N]", f"batch size {tuple(td.batch_size)}")
    if td.batch_size[0] == 0:
        _fail(source, None, "at least one transition", "an empty batch")
    keys = set(td.keys(include_nested=True, leaves_only=True))
    for key in REQUIRED_KEYS:
        if key not in keys:
            _fail(source, key, "this key to be present", f"keys {sorted(_name(k) for k in keys)}")
    return keys


def _check_shapes(td: TensorDictBase, source: str) -> None:
    """Every required key's shape: ``[N, obs_dim]``, ``[N, act_dim]``, ``[N, 1]`` rewards and flags, ``[N]`` ids."""
    n = td.batch_size[0]
    obs_features, act_features = td.get("observation").shape[-1], td.get("action").shape[-1]
    expected_shapes = {
        "observation": (n, obs_features), ("next", "observation"): (n, obs_features),
        "action": (n, act_features), ("next", "reward"): (n, 1), "episode": (n,),
        **{k: (n, 1) for k in BOOL_KEYS},
    }
    for key, shape in expected_shapes.items():
        value = td.get(key)
        if tuple(value.shape) != shape:
            _fail(source, key, f"shape {shape}", f"shape {tuple(value.shape)}")


def _check_dtypes(td: TensorDictBase, source: str) -> None:
    """float32 values, bool flags, int64 episode ids."""
    for key in FLOAT_KEYS:
        if td.get(key).dtype != torch.float32:
            _fail(source, key, "dtype float32", f"{td.get(key).dtype}")
    for key in BOOL_KEYS:
        if td.get(key).dtype != torch.bool:
            _fail(source, key, "dtype bool", f"{td.get(key).dtype}")
    if td.get("episode").dtype != torch.int64:
        _fail(source, "episode", "dtype int64", f"{td.get('episode').dtype}")


def _check_finite(td: TensorDictBase, keys: set, source: str) -> None:
    """No NaN or infinity in any floating-point key (the first bad row is named)."""
    n = td.batch_size[0]
    for key in sorted(keys, key=_name):
        value = td.get(key)
        if value.is_floating_point():
            finite = torch.isfinite(value.reshape(n, -1)).all(-1)
            if not bool(finite.all()):
                _fail(source, key, "finite values", f"a non-finite value at index {int((~finite).nonzero()[0])}")


def _check_env_sizes(td: TensorDictBase, source: str, obs_dim: int | None, act_dim: int | None) -> None:
    """The observation and action sizes are the env's, when they are given."""
    obs_features, act_features = td.get("observation").shape[-1], td.get("action").shape[-1]
    if obs_dim is not None and obs_features != obs_dim:
        _fail(source, "observation", f"{obs_dim} features (the env's observation size)", f"{obs_features}")
    if act_dim is not None and act_features != act_dim:
        _fail(source, "action", f"{act_dim} dimensions (the env's action size)", f"{act_features}")


def _check_episodes(td: TensorDictBase, source: str) -> None:
    """``done == terminated | truncated``; contiguous episode ids; ``done`` on each episode's last row only, and
    on every episode's but the batch's last."""
    done, term, trunc = (td.get(k).squeeze(-1) for k in BOOL_KEYS)
    bad = done != (term | trunc)
    if bool(bad.any()):
        _fail(source, ("next", "done"), "done == terminated | truncated",
              f"a mismatch at index {int(bad.nonzero()[0])}")
    episode = td.get("episode")
    steps = episode[1:] - episode[:-1]
    bad = (steps != 0) & (steps != 1)
    if bool(bad.any()):
        i = int(bad.nonzero()[0])
        _fail(source, "episode", "ids that stay or increase by exactly 1 (contiguous episodes)",
              f"{int(episode[i])} followed by {int(episode[i + 1])} at index {i + 1}")
    last = _episode_boundaries(episode)
    early = done & ~last
    if bool(early.any()):
        _fail(source, ("next", "done"), "done only on the last transition of an episode",
              f"done inside episode {int(episode[early.nonzero()[0]])} at index {int(early.nonzero()[0])}")
    unfinished = last[:-1] & ~done[:-1]
    if bool(unfinished.any()):
        i = int(unfinished.nonzero()[0])
        _fail(source, ("next", "done"), "every episode but the batch's last to end with done=True",
              f"episode {int(episode[i])} ends at index {i} without done")


def _check_metadata(td: TensorDictBase, metadata: dict, source: str) -> None:
    """The metadata names an env and agrees with the data on its row count and sizes."""
    n = td.batch_size[0]
    if "env_id" not in metadata:
        _fail(source, None, "metadata with an 'env_id'", f"metadata keys {sorted(metadata)}")
    if metadata.get("num_transitions", n) != n:
        _fail(source, None, f"metadata num_transitions == {n} rows", f"{metadata['num_transitions']}")
    sizes = (("observation_dim", td.get("observation").shape[-1]), ("action_dim", td.get("action").shape[-1]))
    for key, size in sizes:
        if metadata.get(key, size) != size:
            _fail(source, None, f"metadata {key} == {size} (the data's size)", f"{metadata[key]}")


def _episode_sums(td: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
    episode = td.get("episode")
    ids = episode - episode[0]
    count = int(ids[-1]) + 1
    rewards = td.get(("next", "reward")).reshape(-1).double()
    sums = torch.zeros(count, dtype=torch.float64).index_add_(0, ids, rewards)
    lengths = torch.zeros(count, dtype=torch.int64).index_add_(0, ids, torch.ones_like(ids))
    return sums, lengths


#: the keys of :func:`batch_statistics`, which every batch's ``metadata.json`` holds: what the data say of
#: themselves. Two copies of one batch agree on each; a batch made again from its recipe on another kind of CPU or
#: with other library versions differs, while its provenance (when, how long) differs on any remaking.
STATISTICS_KEYS = ("num_transitions", "num_episodes", "episode_return_mean", "episode_return_std",
                   "episode_return_min", "episode_return_max", "episode_length_mean")


def batch_statistics(td: TensorDictBase) -> dict[str, Any]:
    """Sizes and behaviour episode-return statistics (undiscounted), JSON-serialisable: :data:`STATISTICS_KEYS`."""
    sums, lengths = _episode_sums(td)
    values = (int(td.batch_size[0]), int(sums.numel()), float(sums.mean()), float(sums.std(unbiased=False)),
              float(sums.min()), float(sums.max()), float(lengths.double().mean()))
    return dict(zip(STATISTICS_KEYS, values, strict=True))


@dataclass
class OfflineBatch:
    """A validated batch: ``data`` (TED TensorDict ``[N]``, memory-mapped when loaded), its metadata, its path."""

    data: TensorDictBase
    metadata: dict
    path: Path | None = None

    @property
    def num_transitions(self) -> int:
        return int(self.data.batch_size[0])

    @property
    def num_episodes(self) -> int:
        ep = self.data.get("episode")
        return int(ep[-1] - ep[0]) + 1

    @property
    def obs_dim(self) -> int:
        return int(self.data.get("observation").shape[-1])

    @property
    def act_dim(self) -> int:
        return int(self.data.get("action").shape[-1])

    @property
    def env_id(self) -> str:
        return self.metadata["env_id"]

    @property
    def action_low(self) -> torch.Tensor:
        return torch.as_tensor(self.metadata.get("action_low", [-1.0] * self.act_dim), dtype=torch.float32)

    @property
    def action_high(self) -> torch.Tensor:
        return torch.as_tensor(self.metadata.get("action_high", [1.0] * self.act_dim), dtype=torch.float32)

    def episode_returns(self) -> torch.Tensor:
        """Undiscounted return of each episode, ``[num_episodes]`` (the last one may be unfinished)."""
        return _episode_sums(self.data)[0]


def _to_format(td: TensorDictBase) -> TensorDictBase:
    """Converts float64 observations/actions/rewards to float32 once, at the edge."""
    out = td.copy() if not td.is_locked else td.clone(False)
    for key in FLOAT_KEYS:
        if key in out.keys(include_nested=True) and out.get(key).dtype == torch.float64:
            out.set(key, out.get(key).to(torch.float32))
    return out


def save_batch(td: TensorDictBase, path, metadata: dict, *, overwrite: bool = False) -> OfflineBatch:
    """Validates ``td`` and writes it atomically to ``path`` (a directory); returns the memory-mapped batch.

    ``metadata`` must name ``env_id``; sizes, return statistics, library versions and the creation time are
    filled in (fields the caller gave are kept). float64 observations, actions and rewards are converted to
    float32. An existing ``path`` raises :class:`FileExistsError` unless ``overwrite=True``, in which case the
    old batch is replaced only once the new one is complete. Called under a lock
    (:func:`~torchrl_bail.data.locks.file_lock`, in this thread), it is fenced: once that lock was taken over, it
    raises :class:`~torchrl_bail.data.locks.LockLost` instead of renaming the batch into place.
    """
    path = Path(path)
    td = _to_format(td)
    validate_batch(td, None, source=str(path))
    if "env_id" not in metadata:
        raise BatchValidationError(f"{path}: metadata must name the 'env_id' of the batch")
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} already exists; pass overwrite=True to replace it")
    meta = {
        "format_version": FORMAT_VERSION,
        "observation_dim": int(td.get("observation").shape[-1]),
        "action_dim": int(td.get("action").shape[-1]),
        **batch_statistics(td),
        "library_versions": library_versions(),
        "created_at": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
    }
    meta.update(metadata)
    meta.update(num_transitions=int(td.batch_size[0]))
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}")
    old = None
    try:
        td.memmap(tmp / "data", num_threads=0, copy_existing=True)
        write_json_atomic(tmp / "metadata.json", meta)
        check_fence()  # a job whose lock was taken over publishes nothing (locks: fencing)
        if path.exists():
            old = path.with_name(f"{path.name}.old-{os.getpid()}-{uuid.uuid4().hex[:8]}")
            os.replace(path, old)
        os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        if old is not None and not path.exists():
            os.replace(old, path)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    return load_batch(path)


def load_batch(path, *, obs_dim: int | None = None, act_dim: int | None = None) -> OfflineBatch:
    """Loads and validates the batch in directory ``path`` (memory-mapped: nothing is copied into RAM)."""
    path = Path(path)
    if ".tmp-" in path.name or ".old-" in path.name:
        raise BatchValidationError(f"{path}: an incomplete (interrupted) write, not a batch")
    if not path.is_dir():
        raise FileNotFoundError(f"{path}: no batch directory here")
    meta_file = path / "metadata.json"
    if not meta_file.is_file() or not (path / "data").is_dir():
        raise BatchValidationError(
            f"{path}: incomplete batch (expected data/ and metadata.json); delete it and collect it again"
        )
    try:
        metadata = json.loads(meta_file.read_text())
    except json.JSONDecodeError as err:
        raise BatchValidationError(f"{meta_file}: not valid JSON ({err})") from None
    try:
        data = TensorDict.load_memmap(path / "data")
    except Exception as err:  # noqa: BLE001 - a corrupt memmap must read as a clear error
        raise BatchValidationError(f"{path / 'data'}: unreadable tensordict memmap ({err})") from None
    validate_batch(data, metadata, source=str(path), obs_dim=obs_dim, act_dim=act_dim)
    return OfflineBatch(data, metadata, path)

"""The dataset-format registry of :func:`~torchrl_bail.data.importers.import_dataset`, and what formats share.

A format is one :class:`DatasetFormat` subclass in one module that ends with ``register_format(TheFormat())``;
:mod:`torchrl_bail.data.formats` imports the built-in ones (:mod:`~torchrl_bail.data.formats.native`,
:mod:`~torchrl_bail.data.formats.minari`, :mod:`~torchrl_bail.data.formats.d4rl`). The importer never names a
format: it asks the registry which format claims a path (:func:`find_format`, lowest ``priority`` first), and a path
no format claims is one :class:`DatasetImportError` listing what every registered format expects
(:func:`unknown_format_error`). Converting formats hand back a :class:`Conversion` built with :func:`transitions`
and checked with a :class:`Checker`; the importer caches it. An ``in_place`` format loads a batch as it is.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
import torch
from tensordict import TensorDict

from torchrl_bail.data.batch import BatchValidationError

if TYPE_CHECKING:
    from torchrl_bail.data.batch import OfflineBatch

__all__ = [
    "FORMATS",
    "Checker",
    "Conversion",
    "DatasetFormat",
    "DatasetImportError",
    "find_format",
    "open_hdf5",
    "register_format",
    "terminal_wins",
    "transitions",
    "unknown_format_error",
]


class DatasetImportError(BatchValidationError):
    """An external dataset cannot be imported; the message names the file, the key and what was expected."""


@dataclass
class Conversion:
    """What a converting format makes of its source: the TED ``data`` (:func:`transitions`), the ``info`` the
    batch's metadata records, and the env id and Box action bounds the source itself names (used when the import
    is given no ``env_id``; bounds only when their length matches the actions')."""

    data: TensorDict
    info: dict[str, Any]
    env_id: str | None = None
    action_low: list[float] | None = None
    action_high: list[float] | None = None


class DatasetFormat(ABC):
    """One on-disk dataset format. Subclass it, set the class attributes, implement :meth:`locate` and either
    :meth:`convert` or (``in_place = True``) :meth:`load`, and call :func:`register_format` on an instance.

    Attributes:
        name: the registry key; it is part of a conversion's cache key (renaming a format moves its cache).
        label: ``metadata["source"]["format"]`` of a batch converted from it (default: ``name``).
        expects: what a path of this format is, as the unknown-format error lists it
            (``"a D4RL-layout HDF5 file (*.hdf5 or *.h5)"``).
        priority: formats are tried lowest first (the built-ins: native 0, Minari 10, D4RL 20; default 50).
        in_place: loaded as is (:meth:`load`), never converted nor cached.
    """

    name: ClassVar[str]
    label: ClassVar[str | None] = None
    expects: ClassVar[str]
    priority: ClassVar[int] = 50
    in_place: ClassVar[bool] = False

    @abstractmethod
    def locate(self, path: Path) -> Path | None:
        """Where the data of ``path`` (existing, absolute) is if it is of this format (the location the cache key
        and :meth:`convert` use), else ``None``. Cheap: no reading beyond a small metadata file."""

    def check(self, location: Path) -> None:
        """Raises :class:`DatasetImportError` when ``location`` cannot be of this format after all, before anything
        else is done with it (no env is made, no cache looked at). Default: nothing."""
        return None

    def source_name(self, location: Path) -> str:
        """The name of the converted batch (and of its cache folder). Default: the file or folder's stem."""
        return location.stem

    def convert(self, location: Path, check: Checker) -> Conversion:
        """The source as a :class:`Conversion`, every value checked (``check.fail`` for what breaks the format)."""
        raise NotImplementedError(f"the {self.name} format sets in_place = {self.in_place} but defines no convert()")

    def load(self, location: Path) -> OfflineBatch:
        """An ``in_place`` format's batch, as it is."""
        raise NotImplementedError(f"the {self.name} format sets in_place = {self.in_place} but defines no load()")


#: the registered formats by name, in registration order (the unknown-format error lists them in this order)
FORMATS: dict[str, DatasetFormat] = {}


def register_format(fmt: DatasetFormat, *, replace: bool = False) -> DatasetFormat:
    """Adds ``fmt`` to :data:`FORMATS` (a second format of the same name is an error unless ``replace``)."""
    if fmt.name in FORMATS and not replace:
        raise ValueError(f"dataset format {fmt.name!r} is already registered ({type(FORMATS[fmt.name]).__name__})")
    FORMATS[fmt.name] = fmt
    return fmt


def find_format(path: Path) -> tuple[DatasetFormat, Path]:
    """``(format, location)`` of the first registered format (lowest ``priority``) that claims the existing
    ``path``; :func:`unknown_format_error` when none does."""
    for fmt in sorted(FORMATS.values(), key=lambda f: f.priority):
        location = fmt.locate(path)
        if location is not None:
            return fmt, location
    raise unknown_format_error(path)


def unknown_format_error(path: Path) -> DatasetImportError:
    """The one error for a path no registered format claims: every format's ``expects``, and what was found."""
    expected = [fmt.expects for fmt in FORMATS.values()]
    listed = ", ".join(expected[:-1]) + f" or {expected[-1]}" if len(expected) > 1 else "".join(expected)
    if path.is_file():
        found = f"a file with suffix {path.suffix!r}"
    else:
        found = f"a directory with {sorted(p.name for p in path.iterdir())[:10]}"
    return DatasetImportError(f"{path}: expected {listed}, found {found}")


# --------------------------------------------------------------------------------------------------------------
# what the formats share: checks at the edge, the TED layout, HDF5
# --------------------------------------------------------------------------------------------------------------


class Checker:
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


def terminal_wins(term: np.ndarray, trunc: np.ndarray) -> tuple[np.ndarray, int]:
    """``truncated`` with rows that are also terminal cleared (a true terminal wins), and how many there were."""
    both = term & trunc
    return trunc & ~both, int(both.sum())


def _episode_ids(done: np.ndarray) -> np.ndarray:
    """Episode id of each row: 0 for the first episode, +1 after every ``done`` row."""
    ids = np.zeros(done.shape[0], dtype=np.int64)
    if done.shape[0] > 1:
        ids[1:] = np.cumsum(done[:-1], dtype=np.int64)
    return ids


def transitions(obs, act, next_obs, rew, term, trunc) -> TensorDict:
    """The TED TensorDict of ``n`` transitions (float32 observations, actions and rewards; ``episode`` ids from the
    ``term | trunc`` flags; ``done`` = either)."""
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


def open_hdf5(path: Path):
    import h5py

    try:
        return h5py.File(path, "r")
    except OSError as err:
        raise DatasetImportError(f"{path}: expected a readable HDF5 file, found unreadable data ({err})") from None

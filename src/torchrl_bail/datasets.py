"""A ``bail:`` source in TorchRL's dataset registry: a catalogue batch as a TorchRL replay buffer in one line.

Importing this module registers the source (:func:`torchrl.data.datasets.register_dataset`, TorchRL >= 0.14)::

    import torchrl_bail.datasets  # noqa: F401  (registers "bail:")
    from torchrl.data.datasets import load_dataset

    buffer = load_dataset("bail:hopper_ddpg05_b1", batch_size=256)            # the paper-scale Hopper DDPG-0.5 B1
    buffer = load_dataset("bail:walker_sac_b2", batch_size=256, overrides=["preset=quick"])
    buffer = load_dataset("bail:/path/to/batch_dir_or_minari_dir_or.hdf5", batch_size=256)
    sample = buffer.sample()  # TED keys: observation, action, ("next", "observation" | "reward" | "done" | ...)

A name is ``<env>_<kind>_b<index>`` (``<env>_<kind>_oracle_b<index>`` for an oracle batch), the batch names of
``python -m torchrl_bail.collect --list``; ``overrides`` are the collect command's other overrides (a preset,
``batch.steps=...``), because they change the batch's recipe hash and so which cached batch is meant. Anything
that is an existing path is read by :func:`~torchrl_bail.data.importers.import_dataset` (native batch, Minari
dataset folder, D4RL-layout HDF5). Nothing is collected here: a batch not in the cache raises
:class:`FileNotFoundError` with the ``collect`` command that makes it. The buffer is read-only (TorchRL's
``ImmutableDatasetWriter``) and memory-mapped: the batch is not copied.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable, Sequence
from pathlib import Path

from hydra import compose, initialize_config_dir
from torchrl.data.datasets import register_dataset
from torchrl.data.datasets.common import BaseDatasetExperienceReplay
from torchrl.data.replay_buffers.samplers import Sampler
from torchrl.data.replay_buffers.storages import TensorStorage
from torchrl.data.replay_buffers.writers import ImmutableDatasetWriter, Writer

from torchrl_bail.configuration.config import validate_config
from torchrl_bail.configuration.config_builders import collection_config
from torchrl_bail.configuration.hydra_setup import config_dir
from torchrl_bail.data.batch import OfflineBatch
from torchrl_bail.data.cache import batch_path, load_cached_batch
from torchrl_bail.data.importers import import_dataset

__all__ = ["SOURCE", "BailExperienceReplay", "resolve_batch"]

#: the prefix of this package's datasets in TorchRL's registry
SOURCE = "bail"
_NAME = re.compile(r"^(?P<exp>[a-z0-9]+_[a-z0-9_]+?)(?P<oracle>_oracle)?_b(?P<index>\d+)$")


def resolve_batch(dataset_id: str, *, overrides: Sequence[str] = (),
                  data_dir: str | os.PathLike | None = None) -> OfflineBatch:
    """The cached batch a ``bail:`` id names (see the module doc)."""
    path = Path(dataset_id).expanduser()
    if path.exists():
        return import_dataset(path, data_dir=data_dir)
    match = _NAME.match(dataset_id)
    experiments = sorted(p.stem for p in (config_dir() / "exp").glob("*.yaml"))
    if match is None or match["exp"] not in experiments:
        raise ValueError(f"bail:{dataset_id}: expected an existing path or a batch name <env>_<kind>_b<index> "
                         f"with <env>_<kind> one of {', '.join(experiments)} (e.g. bail:hopper_ddpg05_b1)")
    command = [f"+exp={match['exp']}", f"batch.index={match['index']}", *overrides]
    if match["oracle"]:
        command.append("batch.oracle.enabled=true")
    if data_dir is not None:
        command.append(f"data_dir={data_dir}")
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("config", overrides=command)
    validate_config(cfg)
    location = batch_path(collection_config(cfg))
    batch = load_cached_batch(location)
    if batch is None:
        raise FileNotFoundError(f"bail:{dataset_id}: not collected yet (no batch at {location}); make it with "
                                f"python -m torchrl_bail.collect {' '.join(command)}")
    return batch


class BailExperienceReplay(BaseDatasetExperienceReplay):
    """A batch of this package as a read-only TorchRL replay buffer (what ``load_dataset("bail:...")`` returns).

    Args:
        dataset_id: a batch name (``hopper_ddpg05_b1``) or a path (see the module doc).
        batch_size: the sample size of :meth:`sample`.

    Keyword Args:
        overrides: the ``collect`` overrides the batch was made with beyond ``+exp`` and ``batch.index``.
        data_dir: the batch cache (default ``$TORCHRL_BAIL_DATA_DIR`` or ``~/.cache/torchrl_bail``).
        sampler (Sampler, optional): as for :class:`~torchrl.data.TensorDictReplayBuffer`.
        writer (Writer, optional): as for :class:`~torchrl.data.TensorDictReplayBuffer`.
        collate_fn (callable, optional): as for :class:`~torchrl.data.TensorDictReplayBuffer`.
        pin_memory (bool): as for :class:`~torchrl.data.TensorDictReplayBuffer`.
        prefetch (int, optional): as for :class:`~torchrl.data.TensorDictReplayBuffer`.
        transform (Transform, optional): as for :class:`~torchrl.data.TensorDictReplayBuffer`.

    Attributes:
        batch: the :class:`~torchrl_bail.data.batch.OfflineBatch` (its ``metadata``: recipe, hash, statistics).
    """

    def __init__(self, dataset_id: str, batch_size: int, *, overrides: Sequence[str] = (),
                 data_dir: str | os.PathLike | None = None, sampler: Sampler | None = None,
                 writer: Writer | None = None, collate_fn: Callable | None = None, pin_memory: bool = False,
                 prefetch: int | None = None, transform=None) -> None:
        self.dataset_id = dataset_id
        self.batch = resolve_batch(dataset_id, overrides=overrides, data_dir=data_dir)
        self.root = Path(self.batch.path).parent
        super().__init__(storage=TensorStorage(self.batch.data), sampler=sampler,
                         writer=ImmutableDatasetWriter() if writer is None else writer, collate_fn=collate_fn,
                         pin_memory=pin_memory, prefetch=prefetch, batch_size=batch_size, transform=transform)

    @property
    def data_path(self) -> Path:
        return Path(self.batch.path)

    @property
    def data_path_root(self) -> Path:
        return Path(self.batch.path)

    @property
    def metadata(self) -> dict:
        return self.batch.metadata

    def _is_downloaded(self) -> bool:
        return True


register_dataset(SOURCE, BailExperienceReplay, replace=True)

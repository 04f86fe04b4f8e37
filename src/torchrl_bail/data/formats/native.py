"""This package's own batch directory (``data/`` + ``metadata.json``, :mod:`torchrl_bail.data.batch`): loaded in
place, never converted nor cached."""

from __future__ import annotations

from pathlib import Path

from torchrl_bail.data.batch import OfflineBatch, load_batch
from torchrl_bail.data.formats.base import DatasetFormat, register_format

__all__ = ["NativeFormat"]


class NativeFormat(DatasetFormat):
    """A batch directory written by :func:`~torchrl_bail.data.batch.save_batch`."""

    name = "native"
    expects = "a native batch directory (metadata.json + data/)"
    priority = 0
    in_place = True

    def locate(self, path: Path) -> Path | None:
        is_batch = path.is_dir() and (path / "metadata.json").is_file() and (path / "data").is_dir()
        return path if is_batch else None

    def load(self, location: Path) -> OfflineBatch:
        return load_batch(location)


register_format(NativeFormat())

"""Dataset formats :func:`~torchrl_bail.data.importers.import_dataset` reads, each one module that registers itself
(:mod:`~torchrl_bail.data.formats.base` holds the registry). Importing this package registers the built-ins, in the
order the unknown-format error lists them: D4RL HDF5, Minari, native. A new format is one module (or one class)
ending with ``register_format(MyFormat())``, imported before the import it serves."""

from torchrl_bail.data.formats import d4rl, minari, native  # noqa: F401  (each registers its format)
from torchrl_bail.data.formats.base import (
    FORMATS,
    Checker,
    Conversion,
    DatasetFormat,
    DatasetImportError,
    find_format,
    register_format,
    transitions,
    unknown_format_error,
)

__all__ = [
    "FORMATS",
    "Checker",
    "Conversion",
    "DatasetFormat",
    "DatasetImportError",
    "find_format",
    "register_format",
    "transitions",
    "unknown_format_error",
]

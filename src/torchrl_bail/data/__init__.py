"""Offline batches: the on-disk format, Monte-Carlo returns, importers and behaviour-data generation."""

from torchrl_bail.data.batch import (
    BatchValidationError,
    OfflineBatch,
    batch_statistics,
    default_data_dir,
    library_versions,
    load_batch,
    save_batch,
    validate_batch,
    write_json_atomic,
)
from torchrl_bail.data.returns import discounted_returns, monte_carlo_returns

__all__ = [
    "BatchValidationError",
    "OfflineBatch",
    "batch_statistics",
    "default_data_dir",
    "discounted_returns",
    "library_versions",
    "load_batch",
    "monte_carlo_returns",
    "save_batch",
    "validate_batch",
    "write_json_atomic",
]

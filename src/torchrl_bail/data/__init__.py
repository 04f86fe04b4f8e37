"""The bottom layer: the offline batch format, Monte-Carlo returns, dataset importers, the on-disk cache (names and
hashes: ``cache``; multi-host locks: ``locks``; listing: ``listing``) and normalised scores.

Nothing here imports the rest of :mod:`torchrl_bail` (only :mod:`torchrl_bail.core.io`, the atomic writes, and
:mod:`torchrl_bail.core.errors`): the online behaviour agents that *produce* batches live in
:mod:`torchrl_bail.behaviour`, the learners that consume them in :mod:`torchrl_bail.algorithms`.
"""

from torchrl_bail.data.batch import (
    BatchValidationError,
    OfflineBatch,
    batch_statistics,
    library_versions,
    load_batch,
    save_batch,
    source_revision,
    validate_batch,
    write_json_atomic,
)
from torchrl_bail.data.cache import default_data_dir
from torchrl_bail.data.returns import discounted_returns, monte_carlo_returns

__all__ = [
    "BatchValidationError",
    "OfflineBatch",
    "batch_statistics",
    "default_data_dir",
    "discounted_returns",
    "library_versions",
    "source_revision",
    "load_batch",
    "monte_carlo_returns",
    "save_batch",
    "validate_batch",
    "write_json_atomic",
]

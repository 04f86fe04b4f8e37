"""``ensure_batch``: the cached batch for ``cfg.env`` x ``cfg.batch``, collected first when it is not there yet.

The cache layout, names and hashes are :mod:`torchrl_bail.data.cache`'s; the recipes are listed in
:mod:`torchrl_bail.behaviour.recipes`. Interruption: the agent's replay buffer lives in a scratch directory removed
on exit; an interrupted collection restarts from scratch (no agent checkpoints): the cost is the lost run, never
bad data.
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

from torchrl_bail.behaviour.ddpg import collect_ddpg
from torchrl_bail.behaviour.execution import collect_sac_exec
from torchrl_bail.behaviour.recipes import validate_recipe
from torchrl_bail.behaviour.sac import collect_sac
from torchrl_bail.data.batch import save_batch
from torchrl_bail.data.cache import (
    LOCKS,
    batch_metadata,
    batch_name,
    batch_path,
    clean_stale,
    config_value,
    file_lock,
    load_cached_batch,
    scratch_directory,
)

__all__ = ["ensure_batch", "collect_batch"]

log = logging.getLogger("torchrl_bail")


def ensure_batch(cfg, *, progress: bool = True, data_dir: str | os.PathLike | None = None):
    """Loads the cached batch for ``cfg.env`` x ``cfg.batch``, collecting it first when it is not there yet.

    Returns:
        the :class:`~torchrl_bail.data.batch.OfflineBatch`.
    """
    validate_recipe(cfg)
    path = batch_path(cfg, data_dir)
    batch = load_cached_batch(path)
    if batch is not None:
        log.info("using cached batch %s", path)
        return batch
    root = path.parent
    root.mkdir(parents=True, exist_ok=True)
    clean_stale(root)
    with file_lock(root / LOCKS / f"{path.name}.lock"):
        batch = load_cached_batch(path)  # another job may have made it while we waited
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
    recipe = config_value(cfg, "batch.recipe")
    start = time.perf_counter()
    log.info("collecting %s (%s, %d transitions) into %s", batch_name(cfg), recipe, config_value(cfg, "batch.steps"), path)
    with scratch_directory(path.parent, path.name) as scratch:
        if recipe == "ddpg":
            data, extra = collect_ddpg(cfg, scratch=scratch, progress=progress)
        elif recipe == "sac":
            data, extra = collect_sac(cfg, scratch=scratch, progress=progress, data_dir=path.parent)
        else:
            data, extra = collect_sac_exec(cfg, scratch=scratch, progress=progress, data_dir=path.parent)
        metadata = batch_metadata(cfg, extra, wall_time_s=time.perf_counter() - start)
        batch = save_batch(data, path, metadata)
    return batch


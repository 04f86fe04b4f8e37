"""``ensure_batch``: the cached batch for ``cfg.env`` x ``cfg.batch``, collected first when it is not there yet.

The cache layout, names and hashes are :mod:`torchrl_bail.data.cache`'s; the recipes register themselves in
:mod:`torchrl_bail.behaviour.recipes`, and :func:`collect_batch` runs them through it. Interruption: the agent's
replay buffer lives in a scratch directory removed on exit; the run checkpoints in ``<data_dir>/.partial/``
(:mod:`~torchrl_bail.behaviour.checkpoint`) and a killed collection resumes from its last checkpoint, producing the
same batch; nothing half-written ever loads.
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

from torchrl_bail.behaviour import ddpg, execution, sac_run  # noqa: F401  (each registers its recipe)
from torchrl_bail.behaviour.recipes import recipe_of
from torchrl_bail.configuration.config_builders import collection_config
from torchrl_bail.core import interrupts
from torchrl_bail.data.batch import OfflineBatch, save_batch
from torchrl_bail.data.cache import batch_metadata, batch_name, batch_path, load_cached_batch
from torchrl_bail.data.locks import HEARTBEAT, LOCKS, clean_stale, file_lock, liveness_settings, scratch_directory

__all__ = ["ensure_batch", "collect_batch"]

log = logging.getLogger("torchrl_bail")


def ensure_batch(cfg, *, progress: bool = True, data_dir: str | os.PathLike | None = None) -> OfflineBatch:
    """Loads the cached batch for ``cfg.env`` x ``cfg.batch``, collecting it first when it is not there yet.

    ``cfg``: a composed config (or its ``env``/``batch``/``data_dir``), typed and checked first
    (:func:`~torchrl_bail.configuration.config_builders.collection_config`).

    Returns:
        the :class:`~torchrl_bail.data.batch.OfflineBatch`.
    """
    cfg = collection_config(cfg)
    path = batch_path(cfg, data_dir)
    root = path.parent
    stale, beat = liveness_settings(cfg)
    batch = load_cached_batch(path)
    if batch is not None:
        log.info("using cached batch %s", path)
        # what a collector killed between saving its batch and removing its scratch left behind
        clean_stale(root, stale_after_s=stale)
        return batch
    root.mkdir(parents=True, exist_ok=True)
    clean_stale(root, stale_after_s=stale)
    with file_lock(root / LOCKS / f"{path.name}.lock", stale_after_s=stale, heartbeat_every_s=beat,
                   what=path.name):
        batch = load_cached_batch(path)  # another job (on any host) may have made it while we waited
        if batch is not None:
            log.info("using batch %s, made by another job meanwhile", path)
            return batch
        if path.exists():  # unreadable leftovers under the final name: move them aside, never delete silently
            aside = path.with_name(f"{path.name}.broken-{time.strftime('%Y%m%d-%H%M%S')}")
            os.replace(path, aside)
            log.warning("moved unreadable batch directory %s to %s", path, aside)
        return collect_batch(cfg, path, progress=progress)


def collect_batch(cfg, path: str | os.PathLike, *, progress: bool = True):
    """Runs the behaviour recipe of ``cfg.batch`` and saves the result at ``path`` (atomically).

    The run checkpoints as it goes (:mod:`torchrl_bail.behaviour.checkpoint`) and resumes from the last
    checkpoint of a killed attempt; the checkpoint is removed once the batch is saved. Call it under the batch's
    lock (:func:`ensure_batch` does).
    """
    cfg = collection_config(cfg)
    path = Path(path)
    root = path.parent
    recipe = recipe_of(cfg)
    log.info("collecting %s (%s, %d transitions) into %s", batch_name(cfg), recipe.name, cfg.batch.steps,
             path)
    beat = liveness_settings(cfg)[1]
    checkpoint = recipe.checkpoint(cfg, root, path.name)
    # Ctrl-C/SIGTERM (interrupts): the loop checkpoints at its next episode end and stops; a signal that comes after
    # the last one waits for the batch to be saved
    with interrupts.safe_points():
        with scratch_directory(root, path.name, heartbeat_every_s=beat) as scratch:
            data, extra = recipe.collect(cfg, scratch=scratch, progress=progress, data_dir=root,
                                         checkpoint=checkpoint)
            metadata = batch_metadata(cfg, extra, wall_time_s=checkpoint.wall_time_s,
                                      timed_from_step=checkpoint.timed_from_step)
            HEARTBEAT.check()  # our lock was taken over (a suspended job?): the new owner makes this batch
            batch = save_batch(data, path, metadata)
        recipe.remove_checkpoint(cfg, root, checkpoint)  # the shared SAC run's: under its lock
        interrupts.stop_if_requested(f"the finished batch {path}")
    return batch

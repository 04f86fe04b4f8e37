"""Run-directory naming: which keys a run directory's name leaves out (:data:`RUN_ONLY_KEYS`, :data:`RUN_DIR_KEYS`,
:func:`run_dir_excluded_keys`) and the ``run_dir_suffix`` / ``batch_label`` resolvers of ``conf/config.yaml``
(registered by :func:`torchrl_bail.configuration.hydra_setup.config_dir`). Torch-free.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import typing
from pathlib import Path

from torchrl_bail.configuration.config import Config

__all__ = ["RUN_DIR_KEYS", "RUN_ONLY_KEYS", "batch_label", "run_dir_excluded_keys", "run_dir_suffix"]



#: the top-level keys marked :func:`run_only` in :class:`Config`: a checkpoint resumes across them
#: (:mod:`torchrl_bail.training.resume`), the report never separates runs by them, run directories leave them out of
# their names
RUN_ONLY_KEYS = tuple(f.name for f in dataclasses.fields(Config) if f.metadata.get("run_only"))
#: the other keys a run directory's name leaves out: those already in its path (``conf/config.yaml``'s
#: ``hydra.run.dir``; ``seeds=``: one directory per seed) and ``dataset`` (a path)
RUN_DIR_KEYS = ("exp", "env", "batch", "batch.index", "algo", "seed", "seeds", "dataset")
#: longest override suffix kept verbatim in a directory name (file systems allow 255 bytes per component)
_MAX_SUFFIX = 120


def run_dir_excluded_keys() -> list[str]:
    """The overrides a run directory's name leaves out (Hydra's ``override_dirname.exclude_keys`` in
    ``conf/config.yaml``, which a test ties to this): :data:`RUN_DIR_KEYS` and every key under :data:`RUN_ONLY_KEYS`.

    Examples:
        >>> [k for k in run_dir_excluded_keys() if k.startswith("logger.")]
        ['logger.backend', 'logger.project', 'logger.group', 'logger.name']
    """
    keys = list(RUN_DIR_KEYS)
    for f in dataclasses.fields(Config):
        if f.metadata.get("run_only"):
            schema = typing.get_type_hints(Config)[f.name]
            nested = dataclasses.is_dataclass(schema)
            keys += [f"{f.name}.{leaf.name}" for leaf in dataclasses.fields(schema)] if nested else [f.name]
    return keys


def run_dir_suffix(override_dirname: str) -> str:
    """``",<overrides>"`` for a non-empty Hydra ``override_dirname`` (``/`` -> ``%``; long ones shortened with a
    hash), else ``""``: registered as the ``run_dir_suffix`` resolver of ``conf/config.yaml``'s run dirs.

    Examples:
        >>> run_dir_suffix("")
        ''
        >>> run_dir_suffix("algo.epochs=3,preset=quick")
        ',algo.epochs=3,preset=quick'
        >>> run_dir_suffix("dataset=/data/hopper.hdf5")
        ',dataset=%data%hopper.hdf5'
    """
    text = str(override_dirname or "").replace(os.sep, "%")
    if not text:
        return ""
    if len(text) > _MAX_SUFFIX:
        digest = hashlib.sha1(text.encode()).hexdigest()[:10]
        text = f"{text[:_MAX_SUFFIX - 11]}~{digest}"
    return "," + text


def batch_label(env: str, kind: str, index: int, dataset: str | None) -> str:
    """What a run trained on, for its logger group (``conf/config.yaml``'s ``batch_label`` resolver):
    ``<env>_<kind>_b<index>`` for a generated batch; for a ``dataset=`` run, whose ``batch`` group is not read, the
    dataset's name (a file's stem, a Minari folder's name), prefixed with the env unless it starts with it.

    Examples:
        >>> batch_label("hopper", "ddpg05", 1, None), batch_label("hopper", "ddpg05", 1, "/data/hopper_medium-v2.hdf5")
        ('hopper_ddpg05_b1', 'hopper_medium-v2')
        >>> batch_label("hopper", "ddpg05", 1, "~/.minari/datasets/mujoco/hopper/expert-v0/data")
        'hopper_expert-v0'
    """
    if not dataset:
        return f"{env}_{kind}_b{index}"
    path = Path(str(dataset))
    name = path.parent.name if path.name == "data" else (path.stem if path.suffix in (".hdf5", ".h5") else path.name)
    return name if name.startswith(str(env)) else f"{env}_{name}"

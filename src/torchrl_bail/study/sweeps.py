"""A study's step as a Hydra multirun: the command line of each step, and what the study sweeper launches.

``python -m torchrl_bail.study run`` runs each step as::

    python -m torchrl_bail.<command> -m hydra/sweeper=study hydra.sweeper.study=<study> hydra.sweeper.step=<i>
        hydra.sweep.dir=<workdir>/outputs data_dir=<data dir> progress=false [the user's overrides]

(:func:`step_command`). The sweeper (``hydra_plugins.torchrl_bail_study``) composes each job of the step with the
command line's overrides, leaves out the jobs already done (:func:`finished`: a training run's ``summary.json``, a
batch in the data dir) and hands the others, in the study's order, to the launcher the command line names: Hydra's
basic launcher by default (one job after another, in the sweeper's process), ``hydra/launcher=joblib``,
``hydra/launcher=slurm``. A training job's directory is ``<workdir>/outputs/<batch>/<algo>/seed<s>[,<overrides>]``
(``conf/config.yaml``'s ``hydra.sweep.subdir``, derived from the config), so a job stopped anywhere (a killed
process, a Slurm time limit, a session's end) continues from its checkpoint when the step runs again; a
collection continues from its partial collection in the data dir.
"""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path

from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

from torchrl_bail.configuration.config_builders import collection_config
from torchrl_bail.configuration.hydra_setup import config_dir
from torchrl_bail.data.cache import batch_path
from torchrl_bail.study.declaration import Step, Study, StudyJob

#: where a collect step's Hydra files go, under the sweep dir: one folder per batch
COLLECT_SUBDIR = "${env.name}_${batch.kind}_b${batch.index}"


def step_command(study: str | Path, step: int, command: str, workdir: Path, data_dir: Path,
                 overrides: list[str]) -> list[str]:
    """The command line that runs step ``step`` (from 1) of ``study`` (:mod:`torchrl_bail.study.sweeps`)."""
    return [sys.executable, "-m", f"torchrl_bail.{command}", "-m", "hydra/sweeper=study",
            f"hydra.sweeper.study={study}", f"hydra.sweeper.step={step}", *where_overrides(command, workdir, data_dir),
            "progress=false", *overrides]


def where_overrides(command: str, workdir: Path, data_dir: Path) -> list[str]:
    """Where a step's jobs write: run directories under ``<workdir>/outputs`` (a collection's Hydra files under
    ``outputs/collect/<batch>``), batches in ``data_dir``."""
    outputs = workdir / "outputs"
    where = ([f"hydra.sweep.dir={outputs / 'collect'}", f"hydra.sweep.subdir={COLLECT_SUBDIR}"]
             if command == "collect" else [f"hydra.sweep.dir={outputs}"])
    return [*where, f"data_dir={data_dir}"]


def job_configs(study: Study, workdir: Path, data_dir: Path, command: str | None = None
                ) -> Iterator[tuple[Step, StudyJob, DictConfig]]:
    """Each job of ``study`` (of its ``command`` steps only, if given) with its config as ``run`` composes it in
    ``workdir`` with batches in ``data_dir`` (the ``hydra`` node included: :func:`job_dir`)."""
    for step in study.steps:
        if command is not None and step.command != command:
            continue
        with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3", job_name=step.command):
            for job in step.jobs:
                yield step, job, compose("config", overrides=[*job.args, *where_overrides(step.command, workdir,
                                                                                           data_dir)],
                                         return_hydra_config=True)


def job_batch(cfg: DictConfig) -> Path:
    """Where the batch of a composed collect job lies (:func:`~torchrl_bail.data.cache.batch_path` of its recipe)."""
    return batch_path(collection_config(cfg))


def job_dir(cfg: DictConfig) -> Path:
    """The directory of a composed job of a sweep (``hydra.sweep.dir`` / ``hydra.sweep.subdir``)."""
    return Path(str(cfg.hydra.sweep.dir)) / str(cfg.hydra.sweep.subdir)


def finished(command: str, cfg: DictConfig) -> bool:
    """Whether the job of the composed ``cfg`` is done: a training run whose ``summary.json`` is written (last, so
    it marks the run complete), or a batch already in the data dir (written whole or not at all)."""
    if command == "collect":
        return job_batch(cfg).exists()
    return (job_dir(cfg) / "summary.json").is_file()

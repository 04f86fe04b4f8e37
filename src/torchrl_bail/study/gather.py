"""What a study keeps of its runs: each finished run's summary, config and logs, and each batch's metadata, gathered
from the work dir into the study's results directory, where every report reads them.

A study's results directory (``results/paper_batches``, ...) holds ``runs/<batch>/<algo>/seed<s>[,<overrides>]``
(the work dir's ``outputs`` layout, never a checkpoint) and ``batches/<entry>.metadata.json`` (the batch's
statistics: episode returns, the behaviour agent's final return, collection time), so that the reports rebuild once
the work dir and the data dir are gone (:func:`gather`). A batch made again with the same data is recorded beside the
kept one (``<entry>.remakes.json``); one with other data is refused (:class:`BatchMismatch`), since runs on it would
not compare with the kept ones.

:func:`gather_study` gathers what ``python -m torchrl_bail.study run`` made (its batches found in the data dir by
their recipe); :func:`gather` and :func:`keep_batch_metadata` what ``results/run_study.py`` made (a collect job's
batch named by its log in the work dir). The functions take a study's jobs
(:class:`~torchrl_bail.study.declaration.StudyJob`, or any job with its ``name``, ``args``, ``module`` and
``overrides``).
"""

from __future__ import annotations

import json
import re
import shutil
from collections.abc import Iterable
from pathlib import Path

from torchrl_bail.core.io import write_json_atomic
from torchrl_bail.data.batch import STATISTICS_KEYS
from torchrl_bail.study.declaration import Study, StudyJob
from torchrl_bail.study.sweeps import job_batch, job_configs

#: what a collect job prints once its batch is in the cache (``torchrl_bail.collect``): the batch's cache entry
CACHED_AT = re.compile(r"^\S+: (?:collected|already cached) at (.+)$", re.MULTILINE)


class BatchMismatch(RuntimeError):
    """A batch made again (its data dir lost, say) holds other data than the one whose metadata and runs are kept."""


def batch_label(job: StudyJob) -> str:
    """The label of a job's batch, ``<experiment>_b<batch.index>`` (e.g. ``hopper_ddpg05_b2``): the first part of its
    run directories and of its partial collection's name in the data dir. Coarser than the batch's recipe hash: a
    preset or another ``batch.*`` override makes another batch under the same label."""
    named = job.overrides
    return f"{named['+exp']}_b{named.get('batch.index', 1)}"


def label_recipe(label: str) -> str:
    """The experiment (recipe) of a :func:`batch_label`, ``hopper_ddpg05_b2`` -> ``hopper_ddpg05``: batches of one
    recipe differ only in their behaviour seed (``batch.index``)."""
    return label.rsplit("_b", 1)[0]


def run_dir_of(job: StudyJob, runs: Path) -> Path | None:
    """The run directory of a training job under ``runs`` (the workdir's ``outputs``, or the results' ``runs``, which
    keeps the same layout: ``<batch>_b1/<algo>/seed<s>[,<overrides>]``)."""
    named = job.overrides
    extra = sorted(arg for arg in job.args if not arg.startswith(("+exp=", "algo=", "seed=", "batch.index=")))
    for run in sorted((runs / batch_label(job) / named["algo"]).glob(f"seed{named['seed']}*")):
        if run.name.split(",")[0] == f"seed{named['seed']}" and sorted(run.name.split(",")[1:]) == extra:
            return run
    return None


def collected_batch(job: StudyJob, workdir: Path) -> Path | None:
    """The batch directory (in the data dir) that a collect job's log in ``workdir/logs`` names last, when that
    batch's ``metadata.json`` is there; else ``None``."""
    log = workdir / "logs" / (job.name.replace("/", "__") + ".log")
    if job.module != "torchrl_bail.collect" or not log.is_file():
        return None
    entries = CACHED_AT.findall(log.read_text(errors="replace"))
    batch = Path(entries[-1].strip()) if entries else None
    return batch if batch is not None and (batch / "metadata.json").is_file() else None


def remakes_file(metadata: Path) -> Path:
    """``<entry>.remakes.json`` beside a kept ``<entry>.metadata.json``: the batch's remakings with the same data."""
    return metadata.with_name(metadata.name.replace(".metadata.json", ".remakes.json"))


def _record_remake(path: Path, remade: dict, same: tuple[str, ...]) -> bool:
    """Adds ``remade`` (a remaking's metadata fields that differ from the kept batch's) to the ``remakes`` of the
    JSON file at ``path``, beside ``same`` (the statistics found equal), unless it is already there or empty;
    returns whether the file changed."""
    record = json.loads(path.read_text()) if path.is_file() else {"same": list(same), "remakes": []}
    if not remade or remade in record["remakes"]:
        return False
    record["remakes"].append(remade)
    write_json_atomic(path, record)
    return True


def keep_batch(batch: Path, results: Path) -> list[Path]:
    """Keeps the ``metadata.json`` of the batch directory ``batch`` (a cache entry in the data dir) as
    ``results/batches/<entry>.metadata.json``; returns the files written. A batch whose metadata is already kept was
    made again, its cache lost: with the same data (:data:`~torchrl_bail.data.batch.STATISTICS_KEYS`, to every digit)
    the kept copy stays, the record of the collection the kept runs trained on, and ``<entry>.remakes.json`` lists
    each remaking's own record (the fields in which its metadata differ: when, how long, on which versions), the
    evidence that the recipe makes the same batch again; with other data it raises :class:`BatchMismatch`, since runs
    on the new copy would not compare with the kept ones."""
    source = batch / "metadata.json"
    target = results / "batches" / f"{batch.name}.metadata.json"
    if target.is_file():
        made, before = json.loads(source.read_text()), json.loads(target.read_text())
        differ = [k for k in STATISTICS_KEYS if made.get(k) != before.get(k)]
        if differ:
            raise BatchMismatch(
                f"{batch} holds other data than the batch kept in {target}: "
                + "; ".join(f"{k} {made.get(k)!r} here, {before.get(k)!r} kept" for k in differ)
                + ". Runs on it would not compare with the kept runs of its cells: put the original batch in the "
                "data dir, or move that batch's kept runs and metadata aside to make its cells again")
        remakes = remakes_file(target)
        return [remakes] if _record_remake(remakes, {k: v for k, v in made.items() if v != before.get(k)},
                                           STATISTICS_KEYS) else []
    target.parent.mkdir(parents=True, exist_ok=True)
    shutil.copy2(source, target)
    return [target]


def keep_batch_metadata(workdir: Path, results: Path, jobs: Iterable[StudyJob]) -> list[Path]:
    """Keeps the metadata of each batch a collect job of ``jobs`` has in the cache (the entry its log in
    ``workdir/logs`` names, in the data dir: :func:`collected_batch`) in ``results/batches``
    (:func:`keep_batch`): the batch's statistics (episode returns, the behaviour agent's final return, collection
    time) stay with the results once the data dir is gone; returns the files written. Raises
    :class:`BatchMismatch` for a batch made again with other data than the kept one's."""
    kept = []
    for job in jobs:
        batch = collected_batch(job, workdir)
        if batch is not None:
            kept += keep_batch(batch, results)
    return kept


def gather(workdir: Path, results: Path, jobs: Iterable[StudyJob] = (), policies: bool = False) -> list[Path]:
    """Copies every finished run's summary, config and logs from ``workdir/outputs`` into ``results/runs``, and the
    metadata of the batches the collect jobs of ``jobs`` made (:func:`keep_batch_metadata`). With ``policies`` (the
    paper-scale studies) also each run's final ``policy.pt`` (about 0.5 MB), so that later analyses of the policies
    (off-policy evaluation: ``python -m torchrl_bail.ope``) never need to train them again; never checkpoints (nor
    policy snapshots). A run's FQE records (``ope.json``, ``snapshots/ope_*.json``) come with it where it has
    them."""
    keep_batch_metadata(workdir, results, list(jobs))
    copied = []
    for summary in sorted((workdir / "outputs").glob("*/*/*/summary.json")):
        run = summary.parent
        target = results / "runs" / run.relative_to(workdir / "outputs")
        target.mkdir(parents=True, exist_ok=True)
        for name in ("summary.json", "config.yaml", *(("policy.pt",) if policies else ())):
            if name != "policy.pt" or (run / name).is_file():
                shutil.copy2(run / name, target / name)
        if (run / "logs").is_dir():
            shutil.copytree(run / "logs", target / "logs", dirs_exist_ok=True)
        for record in [run / "ope.json", *sorted(run.glob("snapshots/ope_*.json"))]:
            if record.is_file():
                (target / record.relative_to(run)).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(record, target / record.relative_to(run))
        copied.append(target)
    return copied


def study_batches(study: Study, workdir: Path, data_dir: Path) -> list[Path]:
    """The batch directory in ``data_dir`` of each collect job of ``study`` whose batch is there (its
    ``metadata.json`` written), as ``python -m torchrl_bail.study run`` in ``workdir`` makes it
    (:func:`~torchrl_bail.study.sweeps.job_configs`, :func:`~torchrl_bail.study.sweeps.job_batch`)."""
    batches = []
    for _, _, cfg in job_configs(study, workdir, data_dir, "collect"):
        path = job_batch(cfg)
        if (path / "metadata.json").is_file():
            batches.append(path)
    return batches


def gather_study(study: Study, workdir: Path, results: Path, data_dir: Path) -> list[Path]:
    """Gathers into ``results`` what ``python -m torchrl_bail.study run`` made of ``study`` in ``workdir`` (batches
    in ``data_dir``): each finished run with its final policy (:func:`gather`, ``policies``) and each batch's metadata
    (:func:`study_batches`, :func:`keep_batch`); returns the runs copied. Raises :class:`BatchMismatch` before
    copying any run when a batch was made again with other data than the kept one's."""
    for batch in study_batches(study, workdir, data_dir):
        keep_batch(batch, results)
    return gather(workdir, results, policies=True)

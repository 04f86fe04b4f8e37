"""Reruns the results study of the docs ("Results"), or any row of it, from scratch.

    python results/run_study.py                              # everything: 11 batches, every algorithm, reports (hours)
    python results/run_study.py --only hopper_ddpg05/bail/seed  # one row: its batch and 3 seeds, then the reports
    python results/run_study.py --list                       # the jobs, in the order they run
    python results/run_study.py --study paper_hopper --jobs 2 --pin  # paper scale (days of CPU), a core per job
    python results/run_study.py --study paper_hopper --status   # where its jobs stand: done, running, left

Every job is one ``python -m torchrl_bail.train ... preset=study`` command (or ``torchrl_bail.collect`` for a
batch), run in ``--workdir`` (its ``outputs/`` holds the run directories) with ``threads=1``, ``--jobs`` at a
time. Jobs resume: a finished run is reported, not trained again, and a killed one continues from its
checkpoint, so rerunning this script after an interruption only does what is left. The batches are cached in
``--data-dir`` (default: ``$TORCHRL_BAIL_DATA_DIR`` or ``~/.cache/torchrl_bail``); a fresh directory reproduces
a row from scratch, collection included.

When the runs are done, ``--results`` (default: ``results/study`` beside this script) receives each finished
run's ``summary.json``, resolved ``config.yaml`` and ``logs/`` (evaluation and training scalars; never checkpoints,
policies or batches), ``timings.json`` (every job's wall seconds, torch threads, CPUs, CPU model and the load averages
at its start and end; older entries hold the wall seconds alone) and the two reports of ``torchrl_bail.report``:
``study.*`` (every batch x algorithm) and ``ablations.*`` (supp. D.1-D.3 on Hopper DDPG sigma=0.5), each as
``.md``, ``.csv``, ``.json`` and figures, and ``curves.{md,json}``: whether each learning curve has flattened
over the second half of training (:func:`curve_check`).

The study (supp. C and E, arXiv:1910.12179): Hopper-v5 and Walker2d-v5; batches ddpg01, ddpg05, sac, med_stoch,
opt_det (B1, 50k transitions); every registered algorithm (:data:`torchrl_bail.configuration.algo_schemas.ALGO_SCHEMAS`:
BAIL,
Progressive BAIL, BC, MARWIL, ...) with seeds 1-3 on each (BAIL and BC on Hopper's DDPG batches,
:data:`FIVE_SEED_CELLS`: seeds 1-5), except BCQ and BEAR (:data:`DDPG_ONLY`), with seeds 1-3 on
the two DDPG batches of each env; on Hopper ddpg05 the ablations D.1 (BAIL with oracle vs augmented
returns, on the oracle batch of 2000-step episodes), D.2 (selection by return, no envelope) and D.3 (ordinary
regression, penalty K = 1), seeds 1-3.

``--study paper_hopper`` (results in ``results/paper_hopper``): Hopper-v5 at the paper's batch size (10^6
transitions, ``preset=paper``), in the order that lands what matters most first (:func:`paper_hopper_jobs`).
Its ``cell.{md,json}`` (:func:`paper_cell_report`) sets the DDPG σ = 0.5 cell beside the published figures, gives a
verdict per claim of the paper and the measured cost of every run. A job whose summary is already kept in
``--results`` is done: it neither runs again nor needs the workdir that made it.
``--study paper_batches`` (results in ``results/paper_batches``): three more 10^6-transition batches
(:data:`PAPER_BATCHES`, :func:`paper_batches_jobs`). Beside its own ``study.*`` it writes ``cross_batch.{md,json}``
and ``curves_<batch>.png`` (:func:`cross_batch_report`): these batches and the headline one (read from
``--headline``, default ``results/paper_hopper``) side by side, a verdict per claim per batch, and rliable's IQM and
probabilities of improvement over all of them, each batch's final returns min-max normalised by its own episodes
(:func:`normalised_return`), with intervals from a hierarchical bootstrap over batches, then seeds within each
(:func:`hierarchical_interval`), and each batch made by another batch's recipe with another behaviour seed set beside
it (:func:`same_recipe_comparisons`: how much of a verdict is the batch drawn). Every collect job's batch metadata is
kept in ``<results>/batches`` (:func:`keep_batch_metadata`); ``--report-only`` rebuilds everything from what is kept,
with zero, some or all runs.
``--study paper_exec`` (results in ``results/paper_exec``, :func:`paper_exec_jobs`): per env, the 10^6-step SAC run's
training batch and its four execution batches, BAIL, BCQ, BC and MARWIL on each. Beside its ``study.*`` it writes
``table2.{md,json}`` and ``curves_<batch>.png`` (:func:`exec_table_report`): a supp. Table 2 row per execution batch
(and a Table 1 row per SAC batch) with the batch's mean episode return, its behaviour policy's return and the
paper's figure beside each cell, a verdict per claim of Table 2, the rows each algorithm wins and how each row orders
the algorithms against the paper's (Kendall's tau).
``--status`` lists every job of a study as done, running (its log was written in the last 10 minutes) or left,
with the checkpoint's progress (updates done / scheduled, or a collection's transitions kept / wanted) where one
exists and the time the rest takes at the job's pace so far; its last lines price what is left in hours of one core
(:func:`work_left`) and in wall hours with ``--jobs`` workers (:func:`queue_wall_seconds`).

The gathering and the reports of paper_batches and paper_exec are the package's (:mod:`torchrl_bail.study`:
``gather``, ``tables``, ``cross_batch``, ``exec_table``, ``reports``), which this script imports; so is the
``study.*``/``curves.*`` part of every study's report (:func:`torchrl_bail.study.reports.report_runs`,
:func:`~torchrl_bail.study.reports.curve_check`).
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import queue
import re
import shutil
import subprocess
import sys
import threading
import time
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from torchrl_bail.configuration.algo_schemas import ALGO_SCHEMAS, study_algorithms
from torchrl_bail.ope import ranking_quality, spearman_interval
from torchrl_bail.reports.plots import read_scalar_csv
from torchrl_bail.study.cross_batch import PAPER_BATCH_CELLS, PAPER_BATCH_EXTRA_CELLS, PAPER_BATCHES, cross_batch_report
from torchrl_bail.study.exec_table import PAPER_EXEC_CELLS, PAPER_EXEC_ENVS, PAPER_EXEC_KINDS, exec_table_report
from torchrl_bail.study.gather import (
    BatchMismatch,
    batch_label,
    collected_batch,
    gather,
    keep_batch_metadata,
    run_dir_of,
)
from torchrl_bail.study.reports import curve_check, report_runs
from torchrl_bail.study.tables import MIN_SEEDS_FOR_VERDICT, PAPER_ANCHORS, PAPER_CLAIMS, claim_verdict, shown_path

HERE = Path(__file__).resolve().parent
SEEDS = (1, 2, 3)
ENVS = ("hopper", "walker")
KINDS = ("ddpg01", "ddpg05", "sac", "med_stoch", "opt_det")
#: the study's cost rule, read from the registry (each schema's ``study`` line,
# :mod:`torchrl_bail.configuration.algo_schemas`): a
#: BCQ or BEAR run costs ~10x an imitation run on a 2-core CPU, so these run on the two DDPG batches of each env only;
#: the algorithms registered for every batch run on every batch, and the others not at all
DDPG_ONLY = tuple(study_algorithms("ddpg"))
EVERY_BATCH = tuple(study_algorithms("all"))
#: supp. D.1-D.3 on Hopper ddpg05: name -> overrides (D.1 runs on the oracle batch, with both kinds of returns)
ABLATIONS = {
    "D1_oracle": ["batch.oracle.enabled=true", "returns.augment=oracle"],
    "D1_augmented": ["batch.oracle.enabled=true"],
    "D2_select_by_return": ["algo.selection.by=return"],
    "D3_regression": ["algo.envelope.penalty=1"],
}

#: MARWIL with V fitted alone for its first 200 of 2000 updates (README "MARWIL"), on Hopper's batches where MARWIL
#: is below BC
MARWIL_WARMUP = ["algo.value_warmup_updates=200"]
MARWIL_WARMUP_KINDS = ("sac", "med_stoch", "opt_det")
#: the paper's headline pair (BAIL vs BC, arXiv:1910.12179 Table 1): the one comparison both studies give more
#: seeds and run first; named here because it is a finding about these two, not a property of an algorithm
HEADLINE_PAIR = ("bail", "bc")
#: the cells the study's first finding rests on (the pair on Hopper's DDPG batches) run 5 seeds, so that their
#: IQM intervals are bootstrap intervals, not the range of 3 seeds; seeds 4 and 5 run after everything else
FIVE_SEEDS = (1, 2, 3, 4, 5)
FIVE_SEED_CELLS = [("hopper", kind, algo) for algo in HEADLINE_PAIR for kind in ("ddpg01", "ddpg05")]


#: what a finished training run logs last (torchrl_bail.train)
FINISHED = re.compile(r"final_return [-0-9.]+ \(best")


@dataclass
class Job:
    name: str                                   # <env>_<kind>/<algo>[/<ablation>]/seed<s>, or collect/<env>_<kind>...
    args: list[str] = field(default_factory=list)
    module: str = "torchrl_bail.train"

    @property
    def row(self) -> str:
        return self.name.rsplit("/seed", 1)[0]

    @property
    def overrides(self) -> dict[str, str]:
        """The job's ``key=value`` arguments as a mapping (``{"+exp": "hopper_ddpg05", "algo": "bail", ...}``)."""
        return dict(arg.split("=", 1) for arg in self.args)


def study_jobs() -> list[Job]:
    """Every job in the order it runs: batches first, then Hopper, the ablations, BCQ/BEAR, Walker2d and its
    BCQ/BEAR (the BCQ/BEAR cells seed 1 first, so a partial run already covers every cell)."""
    batches = [(env, kind, []) for kind in ("sac", "ddpg05", "ddpg01", "med_stoch", "opt_det") for env in ENVS]
    batches.append(("hopper", "ddpg05", ABLATIONS["D1_oracle"][:1]))
    jobs = [Job(f"collect/{env}_{kind}" + ("_oracle" if extra else ""), [f"+exp={env}_{kind}", "preset=study", *extra],
                "torchrl_bail.collect") for env, kind, extra in batches]

    def train(env, kind, algo, extra=(), tag="", seeds=SEEDS):
        return [Job(f"{env}_{kind}/{algo}{tag}/seed{s}", [f"+exp={env}_{kind}", f"algo={algo}", f"seed={s}",
                                                           "preset=study", *extra]) for s in seeds]

    for env in ENVS:
        jobs += [j for kind in KINDS for algo in EVERY_BATCH for j in train(env, kind, algo)]
        if env == "hopper":
            jobs += [j for name, extra in ABLATIONS.items() for j in train(env, "ddpg05", "bail", extra, "/" + name)]
            jobs += [j for kind in MARWIL_WARMUP_KINDS
                     for j in train(env, kind, "marwil", MARWIL_WARMUP, "/value_warmup")]
        bcq_bear = [train(env, kind, algo) for kind in ("ddpg05", "ddpg01") for algo in DDPG_ONLY]
        jobs += [cell[i] for i in range(len(SEEDS)) for cell in bcq_bear]  # seed 1 of every cell first
    more_seeds = tuple(s for s in FIVE_SEEDS if s not in SEEDS)
    jobs += [j for env, kind, algo in FIVE_SEED_CELLS for j in train(env, kind, algo, seeds=more_seeds)]
    return jobs


#: the paper-scale schedule of an actor-critic (``cost = "offline_rl"``): 10^5 updates, 10 % of the 10^6 of BCQ's,
#: BEAR's and TD3+BC's papers, with 20 evaluations (see :func:`paper_schedule`)
OFFLINE_RL_UPDATES, OFFLINE_RL_EVALUATIONS = 10**5, 20


def paper_schedule(algo: str) -> list[str]:
    """The overrides of ``algo``'s paper-scale jobs. Imitation and BAIL's envelope run the paper's own schedules
    (``preset=paper``, nothing overridden: 50 envelope passes over the 0.8 training split with the C = 4 revert rule,
    supp. B.1 Alg. 1, which changes the weights but never ends a fit, so the 50-epoch cap always does; the imitation
    epochs of conf/algo). An actor-critic runs :data:`OFFLINE_RL_UPDATES` updates of its own batch size, in epochs of
    10^6 samples: ``algo.epochs=10`` for BCQ and BEAR (batches of 100), ``algo.epochs=25.6`` for TD3+BC (256), so
    that every actor-critic of the cell has had as many updates."""
    return list(_paper_schedule(algo, ALGO_SCHEMAS[algo].cost))


@functools.cache
def _paper_schedule(algo: str, cost: str) -> tuple[str, ...]:
    """:func:`paper_schedule`, computed once per algorithm (composing its yaml takes most of a second)."""
    from torchrl_bail.configuration.config_builders import run_length_overrides

    if cost == "imitation":
        return ()
    return tuple(run_length_overrides(algo, OFFLINE_RL_UPDATES, OFFLINE_RL_EVALUATIONS))


#: the paper-scale study's design (which algorithms: each schema's ``paper_study`` line): :data:`HEADLINE_PAIR` runs
#: first on each batch, with 5 seeds on the DDPG sigma=0.5 and SAC batches, every other algorithm 3; MARWIL also runs
#: with V fitted first; BCQ also runs on opt_det. A newly registered algorithm lands after the pair with 3 seeds
PAPER_FIVE_SEED_KINDS = ("ddpg05", "sac")
PAPER_VARIANTS = {"marwil": (["algo.value_warmup_updates=1000"], "/value_warmup")}
PAPER_EXTRA_CELLS = [("opt_det", "bcq", 3)]
#: algorithms outside the paper run on the headline batch as reference points, right after the paper's cell
PAPER_REFERENCE_CELLS = [("ddpg05", "td3bc", 3)]


def paper_hopper_jobs() -> list[Job]:
    """The paper-scale Hopper study, most important first: (a) the DDPG sigma=0.5 final buffer with BAIL and BC x 5
    seeds, Progressive BAIL, MARWIL and MARWIL with V fitted first x 3, BCQ and BEAR x 3, then TD3+BC x 3 as a
    reference point outside the paper (:data:`PAPER_REFERENCE_CELLS`); (b) the 10^6-step SAC
    run's training batch and its execution batches opt_det and med_stoch (BAIL and BC x 5 on sac, x 3 elsewhere);
    (c) med_det, opt_stoch, ddpg01, and BCQ on opt_det."""
    def collect(kind):
        return Job(f"collect/hopper_{kind}", [f"+exp=hopper_{kind}"], "torchrl_bail.collect")

    def train(kind, algo, seeds, extra=(), tag=""):
        schedule = paper_schedule(algo)
        return [Job(f"hopper_{kind}/{algo}{tag}/seed{s}", [f"+exp=hopper_{kind}", f"algo={algo}", f"seed={s}",
                                                            *schedule, *extra]) for s in range(1, seeds + 1)]

    def cells(kind, batches, variants=True):
        paper = [name for name, schema in ALGO_SCHEMAS.items() if schema.paper_study and schema.study in batches]
        if variants:  # the priority order of phases (a) and (b)
            paper.sort(key=lambda name: name not in HEADLINE_PAIR)
        jobs = []
        for algo in paper:
            jobs += train(kind, algo, 5 if algo in HEADLINE_PAIR and kind in PAPER_FIVE_SEED_KINDS else 3)
            if variants and algo in PAPER_VARIANTS:
                jobs += train(kind, algo, 3, *PAPER_VARIANTS[algo])
        return jobs

    jobs = [collect("ddpg05"), *cells("ddpg05", ("all", "ddpg"))]
    jobs += [j for kind, algo, seeds in PAPER_REFERENCE_CELLS for j in train(kind, algo, seeds)]
    jobs += [collect("sac"), collect("opt_det"), collect("med_stoch")]
    for kind in ("sac", "opt_det", "med_stoch"):
        jobs += cells(kind, ("all",))
    for kind in ("med_det", "opt_stoch", "ddpg01"):
        jobs += [collect(kind), *cells(kind, ("all",), variants=False)]
    return jobs + [j for kind, algo, seeds in PAPER_EXTRA_CELLS for j in train(kind, algo, seeds)]


def batch_args(exp: str, index: int) -> list[str]:
    """The overrides that name a batch: its experiment and, past B1, its index."""
    return [f"+exp={exp}"] + ([f"batch.index={index}"] if index != 1 else [])


def paper_batches_jobs() -> list[Job]:
    """The cross-batch study at the paper's scale (results in ``results/paper_batches``): for each of
    :data:`PAPER_BATCHES` in turn, its collection (``collect``, 10^6 env steps) and then :data:`PAPER_BATCH_CELLS`
    (BAIL and BC x 5 seeds, BCQ x 3 at the paper-scale actor-critic schedule of :func:`paper_schedule`, Progressive
    BAIL x 3); then :data:`PAPER_BATCH_EXTRA_CELLS` on every batch, seed 1 of every cell first. Job names carry the
    batch label (``walker_ddpg05_b1/bail/seed1``)."""
    def train(exp, index, algo, seeds):
        return [Job(f"{exp}_b{index}/{algo}/seed{s}", [*batch_args(exp, index), f"algo={algo}", f"seed={s}",
                                                        *paper_schedule(algo)]) for s in seeds]

    jobs = []
    for exp, index, _ in PAPER_BATCHES:
        jobs.append(Job(f"collect/{exp}_b{index}", batch_args(exp, index), "torchrl_bail.collect"))
        jobs += [j for algo, seeds in PAPER_BATCH_CELLS for j in train(exp, index, algo, range(1, seeds + 1))]
    extra = [train(exp, index, algo, range(1, seeds + 1)) for algo, seeds in PAPER_BATCH_EXTRA_CELLS
             for exp, index, _ in PAPER_BATCHES]
    return jobs + [cell[i] for i in range(max(len(c) for c in extra)) for cell in extra if i < len(cell)]


#: the off-policy-evaluation study (``--study ope_headline``): policies trained again on the headline batch (Hopper
#: DDPG sigma=0.5 B1, 10^6 transitions, at the paper_hopper study's own schedules and seeds, so each final policy is
#: that study's run, kept this time), as ``(algo, seeds)``: 20 final policies over every algorithm of the headline
#: cell; the imitation learners and TD3+BC first, one seed of each per round, then one BCQ and one BEAR (80 and 70
#: minutes a run on one core, against 12-37 for the others)
OPE_CELLS = [("bail", 5), ("bc", 5), ("td3bc", 3), ("marwil", 3), ("pbail", 2)]
OPE_COSTLY_CELLS = [("bcq", 1), ("bear", 1)]
#: the runs that keep policy snapshots for FQE to choose from (``eval.snapshots``: the final policy and 4 earlier)
OPE_SNAPSHOTS = {"bail": ["eval.snapshots=5"]}
#: what every FQE job passes to ``torchrl_bail.ope`` beside its run directory (its defaults otherwise: FQESettings)
OPE_FLAGS = ["--no-progress", "--threads", "1"]


def ope_headline_jobs() -> list[Job]:
    """Issue 38's study (results in ``results/ope_headline``): each policy of :data:`OPE_CELLS` and
    :data:`OPE_COSTLY_CELLS` trained on the headline batch, then at once its FQE fit (``ope/<training job>``:
    ``python -m torchrl_bail.ope <its run>``, which also fits and ranks a BAIL run's snapshots), seed 1 of every
    cell first. The training jobs are the ``paper_hopper`` study's (same overrides, seeds and schedule; BAIL with
    :data:`OPE_SNAPSHOTS`, which changes no number of the run), so their summaries must equal that study's kept
    ones: :func:`ope_headline_report` checks it."""
    def pair(algo, seed):
        train = Job(f"hopper_ddpg05/{algo}/seed{seed}", ["+exp=hopper_ddpg05", f"algo={algo}", f"seed={seed}",
                                                         *paper_schedule(algo), *OPE_SNAPSHOTS.get(algo, [])])
        return [train, Job(f"ope/{train.name}", train.args, "torchrl_bail.ope")]

    jobs = []
    for cells in (OPE_CELLS, OPE_COSTLY_CELLS):
        for seed in range(1, max(seeds for _, seeds in cells) + 1):
            jobs += [j for algo, seeds in cells if seed <= seeds for j in pair(algo, seed)]
    return jobs


#: when both envs are complete: BEAR on Hopper's execution batches (supp. Table 2's BEAR often scores 0)
PAPER_EXEC_EXTRA_CELLS = [("hopper", kind, "bear", 3) for kind in PAPER_EXEC_KINDS[1:]]


def paper_exec_jobs() -> list[Job]:
    """The paper's SAC-made half at its scale (results in ``results/paper_exec``): for each of :data:`PAPER_EXEC_ENVS`,
    the collection of each of :data:`PAPER_EXEC_KINDS` (the first, ``sac``, trains the shared SAC run that the
    execution batches reuse), then :data:`PAPER_EXEC_CELLS` on each batch, seed 1 of every cell first; then
    :data:`PAPER_EXEC_EXTRA_CELLS`."""
    def train(exp, algo, seed):
        return Job(f"{exp}_b1/{algo}/seed{seed}", [*batch_args(exp, 1), f"algo={algo}", f"seed={seed}",
                                                   *paper_schedule(algo)])

    jobs = []
    for env in PAPER_EXEC_ENVS:
        exps = [f"{env}_{kind}" for kind in PAPER_EXEC_KINDS]
        jobs += [Job(f"collect/{exp}_b1", batch_args(exp, 1), "torchrl_bail.collect") for exp in exps]
        jobs += [train(exp, algo, seed) for seed in range(1, max(n for _, n in PAPER_EXEC_CELLS) + 1)
                 for exp in exps for algo, n in PAPER_EXEC_CELLS if seed <= n]
    return jobs + [train(f"{env}_{kind}", algo, seed) for seed in range(1, 4)
                   for env, kind, algo, n in PAPER_EXEC_EXTRA_CELLS if seed <= n]


STUDIES = {"study": study_jobs, "paper_hopper": paper_hopper_jobs, "paper_batches": paper_batches_jobs,
           "ope_headline": ope_headline_jobs, "paper_exec": paper_exec_jobs}


def _is_running(log: Path) -> bool:
    """Whether the job of ``log`` runs now: its ``.pid`` file (written by :func:`run_job`) names a live process, or,
    for a runner that wrote none, its log was written in the last 10 minutes."""
    pid_file = log.with_suffix(".pid")
    if pid_file.is_file():
        try:
            os.kill(int(pid_file.read_text()), 0)
            return True
        except (ValueError, ProcessLookupError, PermissionError):
            return False
    return log.is_file() and time.time() - log.stat().st_mtime < 600


def _running_since(log: Path) -> float | None:
    """When the job of ``log`` started, if it runs now (:func:`_is_running`): its ``.pid`` file's time (written as
    its process started), or 0 for a runner that wrote none (its start unknown); ``None`` if it does not run."""
    if not _is_running(log):
        return None
    pid_file = log.with_suffix(".pid")
    try:
        return pid_file.stat().st_mtime
    except OSError:
        return 0.0


@dataclass(frozen=True)
class JobState:
    """Where one job stands (:func:`job_status`); ``str()`` gives it as ``--status`` prints it, e.g. ``running
    (2500/10000 updates, about 25 min left)``."""

    state: str                                #: ``done``, ``running`` or ``left``
    updates: tuple[int, int] | None = None    #: a training run's checkpoint: updates done, scheduled
    seconds_left: float | None = None         #: what the updates or transitions left take at the job's pace so far
    transitions: tuple[int, int] | None = None  #: a partial collection's last checkpoint: transitions kept, wanted
    steps_collected: int | None = None        #: the same from an older checkpoint, which names no size: env steps
    detail: str = ""                          #: any other progress (an FQE job's fits)

    def __str__(self) -> str:
        left = "" if self.seconds_left is None else f", about {self.seconds_left / 60:.0f} min left"
        if self.updates is not None:
            detail = f"{self.updates[0]}/{self.updates[1]} updates{left}"
        elif self.transitions is not None:
            detail = f"{self.transitions[0]}/{self.transitions[1]} transitions{left}"
        elif self.steps_collected is not None:
            detail = f"{self.steps_collected} steps collected"
        else:
            detail = self.detail
        return self.state + (f" ({detail})" if detail else "")


def _collection_state(job: Job, data_dir: Path | None, running_since: float | None) -> JobState:
    """An unfinished collect job with the last checkpoint of its batch's partial collection, if any: the transitions
    kept out of the batch's size and the time the rest takes at the collection's pace so far (less what a running
    job has done since: ``running_since`` is :func:`_running_since`), or, from an older checkpoint that names no
    size, its env steps."""
    from torchrl_bail.behaviour.checkpoint import STATE_FILE, CollectionCheckpoint
    from torchrl_bail.data.cache import default_data_dir
    from torchrl_bail.data.locks import PARTIAL

    unfinished = "left" if running_since is None else "running"
    partials = (Path(data_dir or default_data_dir()) / PARTIAL).glob(f"{batch_label(job)}-*")
    found = [(state, p) for p in partials if (state := CollectionCheckpoint(p, every_s=None).load()) is not None]
    if not found:
        return JobState(unfinished)
    state, partial = max(found, key=lambda f: int(f[0]["loop"]["t"]))
    kept, size = state["buffers"]["kept"], state["buffers"].get("steps")
    if size is None:
        return JobState(unfinished, steps_collected=int(state["loop"]["t"]))
    wall = None if state.get("timed_from_step") else state.get("wall_time_s")  # else its first steps are untimed
    return JobState(unfinished, transitions=(int(kept), int(size)),
                    seconds_left=_seconds_left(kept, size, wall, partial / STATE_FILE, running_since))


def landed(job: Job, results: Path | None) -> bool:
    """Whether a training job's ``summary.json`` is already kept in ``results/runs`` (gathered by an earlier call,
    maybe on another machine whose workdir is gone): such a job is done and does not run again."""
    if results is None or job.module not in ("torchrl_bail.train", "torchrl_bail.ope"):
        return False
    run = run_dir_of(job, results / "runs")
    if job.module == "torchrl_bail.ope":
        return run is not None and ope_finished(run)
    return run is not None and (run / "summary.json").is_file()


def finished_ope(run: Path) -> dict | None:
    """An FQE job's finished ``ope.json`` in ``run``: one with the estimate and, for a run with policy snapshots,
    FQE's choice among them (``fqe_selected``, written last); else ``None``."""
    try:
        ope = json.loads((run / "ope.json").read_text())
        summary = json.loads((run / "summary.json").read_text())
    except (OSError, ValueError):
        return None
    return ope if "estimate" in ope and (not summary.get("snapshots") or "fqe_selected" in ope) else None


def ope_finished(run: Path) -> bool:
    """Whether an FQE job's run holds its finished ``ope.json`` (:func:`finished_ope`)."""
    return finished_ope(run) is not None


def job_status(job: Job, workdir: Path, data_dir: Path | None = None, results: Path | None = None) -> JobState:
    """``done``, ``running`` or ``left``, with the progress of its checkpoint (updates done / scheduled) or of its
    partial collection (transitions kept / wanted), and the time the rest takes, where there is one. A job whose
    summary is kept in ``results`` is done."""
    done = JobState("done")
    if landed(job, results):
        return done
    log = workdir / "logs" / (job.name.replace("/", "__") + ".log")
    running_since = _running_since(log)
    unfinished = "left" if running_since is None else "running"
    if job.module == "torchrl_bail.ope":
        run = run_dir_of(job, workdir / "outputs")
        if run is not None and ope_finished(run):
            return done
        return JobState(unfinished, detail="" if run is None else _ope_progress(run))
    if job.module != "torchrl_bail.train":
        text = log.read_text(errors="replace") if log.is_file() else ""
        if re.search(r": (collected|already cached) at ", text):
            return done
        return _collection_state(job, data_dir, running_since)
    run = run_dir_of(job, workdir / "outputs")
    if run is not None and (run / "summary.json").is_file():
        return done
    if run is None or not (run / "checkpoint.pt").is_file():
        return JobState(unfinished)
    import torch

    state = torch.load(run / "checkpoint.pt", map_location="cpu", weights_only=False)
    return JobState(unfinished, (state["iteration"], state["iterations"]),
                    _seconds_left(state["iteration"], state["iterations"], state.get("wall_time_s"),
                                  run / "checkpoint.pt", running_since))


def _ope_progress(run: Path) -> str:
    """``k of n fits, u/U updates``: an FQE job's finished fits (``ope.json``, then one per snapshot but the
    last, which has the final policy's weights) and the progress of the fit it checkpointed, if any; empty before
    its training has finished."""
    try:
        snapshots = json.loads((run / "summary.json").read_text()).get("snapshots") or []
    except (OSError, ValueError):
        return ""
    fits = max(1, len(snapshots))
    done = (run / "ope.json").is_file() + len(list(run.glob("snapshots/ope_*.json")))
    progress = f"{min(done, fits)} of {fits} fit{'s' if fits != 1 else ''}"
    checkpoints = sorted([*run.glob("*_checkpoint.pt"), *run.glob("snapshots/*_checkpoint.pt")],
                         key=lambda p: p.stat().st_mtime)
    if checkpoints:
        import torch

        state = torch.load(checkpoints[-1], map_location="cpu", weights_only=False)
        progress += f", {state['update']}/{state['identity']['settings']['updates']} updates"
    return progress


def _seconds_left(done: int, total: int, wall: float | None, checkpoint: Path,
                  running_since: float | None) -> float | None:
    """The seconds the ``total - done`` units left (updates, transitions) take at the job's own pace so far (the
    ``wall`` seconds its ``checkpoint`` records for the ``done`` ones: a run's evaluations included), less what a
    job running since ``running_since`` (:func:`_running_since`) has done since that checkpoint or since it
    started, whichever is later: one resumed from an older checkpoint has not run in between; ``None`` before any,
    or where the checkpoint records no time."""
    if not done or not wall:
        return None
    left = (total - done) * wall / done
    if running_since is not None:
        left -= time.time() - max(checkpoint.stat().st_mtime, running_since)
    return max(left, 0.0)


#: the studies whose jobs run at a study's scale (``preset=paper``, the same schedules), so whose recorded costs price
#: its jobs of a kind it has not recorded yet (``--status``'s estimate of the work left)
COST_PEERS = {"paper_batches": ("paper_hopper",), "paper_hopper": ("paper_batches",),
              "paper_exec": ("paper_batches", "paper_hopper")}


#: a collect job's batch kind -> how it is made, which sets its cost: a DDPG run, the shared SAC run (10^6 steps of
#: SAC updates), or an execution batch (a frozen SAC policy acting, no update)
COLLECTION_KINDS = (("_sac", "sac run"), ("_med_", "execution"), ("_opt_", "execution"))


def collection_kind(name: str) -> str:
    """How the batch of the collect job ``name`` is made (:data:`COLLECTION_KINDS`; ``"ddpg"`` otherwise):
    ``collect/hopper_sac_b1`` -> ``"sac run"``, ``collect/walker_med_det_b1`` -> ``"execution"``."""
    return next((kind for token, kind in COLLECTION_KINDS if token in name), "ddpg")


def _recorded_cost(name: str, timings: dict, elsewhere: dict) -> float | None:
    """What ``name`` should cost: the median recorded seconds of the jobs of its kind in ``timings`` (its study's
    ``timings.json``) on its batch (``<batch>/<algo>/seed…`` without the seed; ``collect/…``: any collection made the
    same way, :func:`collection_kind`), else of its algorithm on the study's other batches, else in ``elsewhere`` (the
    records of its :data:`COST_PEERS`); ``None`` where nothing of its kind is recorded."""
    parts = name.split("/")

    def same_algo(records: dict) -> list[str]:
        if parts[0] == "collect":
            return [k for k in records if k.startswith("collect/") and collection_kind(k) == collection_kind(name)]
        return [k for k in records if k.split("/")[-2:-1] == parts[-2:-1]
                and k.startswith("ope/") == name.startswith("ope/")]

    prefix = "/".join(parts[:-1]) + "/"
    tiers = [(timings, [k for k in timings if k.startswith(prefix) and parts[0] != "collect"]),
             (timings, same_algo(timings)), (elsewhere, same_algo(elsewhere))]
    for records, keys in tiers:
        costs = [wall_seconds(records[k]) for k in keys]
        if costs:
            return float(np.median(costs))
    return None


def job_seconds_left(name: str, state: JobState, timings: dict, elsewhere: dict) -> float | None:
    """What the unfinished job ``name`` should still take: the time left its ``state`` gives, else its kind's
    recorded cost (:func:`_recorded_cost`) scaled by the share of updates or transitions its checkpoint has left (a
    partial collection whose older checkpoint names no batch size, at its whole cost); ``None`` where nothing of its
    kind is recorded."""
    if state.seconds_left is not None:
        return state.seconds_left
    cost = _recorded_cost(name, timings, elsewhere)
    if cost is None:
        return None
    progress = state.updates or state.transitions
    return cost * (1 - progress[0] / progress[1] if progress else 1)


def seconds_left(states: list[tuple[str, JobState]], timings: dict, elsewhere: dict | None = None
                 ) -> dict[str, float | None]:
    """Each unfinished job of ``states`` (``(name, job_status)``) with what it should still take
    (:func:`job_seconds_left`; ``None``: a kind nothing has recorded yet)."""
    return {name: job_seconds_left(name, state, timings, elsewhere or {})
            for name, state in states if state.state != "done"}


def work_left(states: list[tuple[str, JobState]], seconds: dict[str, float | None]) -> str:
    """One line on what the unfinished jobs of ``states`` (``(name, job_status)``) still cost, in hours of one core,
    from their ``seconds`` left (:func:`seconds_left`). Jobs of a kind nothing has recorded yet are counted apart."""
    unfinished = [(n, s) for n, s in states if s.state != "done"]
    if not unfinished:
        return "nothing left to run"
    known = [seconds[name] for name, _ in unfinished if seconds[name] is not None]
    unknown = len(unfinished) - len(known)
    collecting = sum(state.steps_collected is not None for _, state in unfinished)
    return (f"left to run: about {sum(known) / 3600:.1f} h of one core for {len(known)} of the "
            f"{len(unfinished)} unfinished jobs (a running job at its own pace, any other at the median recorded "
            "cost of its algorithm: on its batch, else on the study's others, else in its peer study's records)"
            + (f"; {unknown} of a kind with no recorded cost" if unknown else "")
            + (f"; {collecting} partial collection{'s' if collecting > 1 else ''} priced whole" if collecting else ""))


def queue_wall_seconds(jobs: list[Job], states: dict[str, JobState], seconds: dict[str, float], workers: int) -> float:
    """How long the unfinished jobs of the queue ``jobs`` take on ``workers`` workers when :func:`run_queue`
    dispatches them: a running job holds a worker for its time left, and each free worker takes the first pending job
    that :func:`next_ready` allows (so a batch's jobs wait for its collection). Each job takes its ``seconds``
    (:func:`job_seconds_left`); a job without an estimate is left out."""
    by_name = {job.name: job for job in jobs}
    ends = {name: seconds[name] for name, state in states.items() if state.state == "running" and name in seconds}
    pending = [job for job in jobs if states[job.name].state == "left" and job.name in seconds]
    now = 0.0
    while ends or pending:
        while len(ends) < workers and (job := next_ready(pending, [by_name[name] for name in ends])):
            pending.remove(job)
            ends[job.name] = now + seconds[job.name]
        name = min(ends, key=ends.__getitem__)  # never empty here: with nothing running, next_ready takes a job
        now = ends.pop(name)
    return now


def conditions() -> dict:
    """What the machine was doing as a job started or ended: the 1/5/15-minute load averages and the UTC time."""
    return {"load": [round(x, 2) for x in os.getloadavg()], "utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}


def run_job(job: Job, workdir: Path, data_dir: Path | None, results: Path | None = None,
            stop: threading.Event | None = None, cpus: queue.SimpleQueue | None = None
            ) -> tuple[Job, int | None, float, dict]:
    """Runs ``job`` (its output appended to ``workdir/logs/<job>.log``); returns its exit code (``None``: it had
    finished in an earlier call, its log or its kept summary in ``results`` says so, or ``stop`` is set, and nothing
    ran), wall seconds and the job's record for ``timings.json``: wall seconds, torch threads, the CPUs the job may run
    on, the load averages at its start and end (a load near the job's own threads is a quiet machine), the CPU.

    ``cpus`` (``--pin``): the free CPUs of the queue; the job takes one for its whole run (``taskset -c``), alone on
    it, and gives it back when it ends; without, it may run on any CPU of the runner's.

    A collect job's batch metadata goes to ``results`` as soon as it ends (:func:`keep_batch_metadata`), before the
    next job can start: a batch unlike the kept one sets ``stop`` (no job of the queue starts after it; running ones
    go on) and raises :class:`BatchMismatch`."""
    if stop is not None and stop.is_set():
        return job, None, 0.0, {}
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    if data_dir is not None:
        env["TORCHRL_BAIL_DATA_DIR"] = str(data_dir)
    log = workdir / "logs" / (job.name.replace("/", "__") + ".log")
    log.parent.mkdir(parents=True, exist_ok=True)
    if landed(job, results) or (job.module == "torchrl_bail.train" and log.is_file()
                                and FINISHED.search(log.read_text(errors="replace"))):
        return job, None, 0.0, {}
    args = job.args
    from torchrl_bail.data.batch import cpu_model

    if job.module == "torchrl_bail.ope":  # its arguments name the training job whose run it scores
        run = run_dir_of(job, workdir / "outputs")
        if run is not None and ope_finished(run):
            return job, None, 0.0, {}
        if run is None or not (run / "summary.json").is_file():
            with open(log, "a") as out:
                out.write(f"{job.name}: its training run has not finished in {workdir / 'outputs'}\n")
            return job, 1, 0.0, {}
        args, extra = [str(run.relative_to(workdir))], OPE_FLAGS
    else:
        extra = ["progress=false", "threads=1"]
    cpu = None if cpus is None else cpus.get()
    try:
        pinned = [] if cpu is None else ["taskset", "-c", str(cpu)]
        record = {"threads": 1,
                  "cpus": sorted(os.sched_getaffinity(0)) if cpu is None else [cpu], "cpu": cpu_model(),
                  "start": conditions()}
        start = time.perf_counter()
        pid_file = log.with_suffix(".pid")  # while it exists and names a live process, --status says "running"
        with open(log, "a") as out:
            proc = subprocess.Popen([*pinned, sys.executable, "-m", job.module, *args, *extra], cwd=workdir, env=env,
                                    stdout=out, stderr=subprocess.STDOUT)
            pid_file.write_text(f"{proc.pid}\n")
            try:
                rc = proc.wait()
            finally:
                pid_file.unlink(missing_ok=True)
        seconds = time.perf_counter() - start
    finally:
        if cpu is not None:
            cpus.put(cpu)
    if rc == 0 and results is not None and job.module == "torchrl_bail.collect":
        try:
            keep_batch_metadata(workdir, results, [job])
        except BatchMismatch:
            if stop is not None:
                stop.set()
            raise
    return job, rc, seconds, {"wall_s": seconds, **record, "end": conditions()}


def whole_job_record(job: Job, record: dict, workdir: Path) -> dict:
    """The ``timings.json`` record of a job that just finished. A run resumed from its checkpoint (an earlier call
    was interrupted: a killed process, a session's end) is charged its accumulated training time, the summary's
    ``wall_time_s`` (the checkpoint carries it across resumes; the minutes between the last checkpoint and a kill are
    lost, and so is each start-up), not this call's last part alone, which ``last_part_s`` keeps with the iterations
    it resumed from; ``start`` is then the last part's. A resumed collection is charged likewise its batch's
    ``collection_wall_time_s``, the time of all its parts (from env step ``collection_timed_from_step`` on)."""
    if job.module == "torchrl_bail.collect":
        batch = collected_batch(job, workdir)
        meta = json.loads((batch / "metadata.json").read_text()) if batch is not None else {}
        if meta.get("resumed_from_step") is None:
            return record
        return {**record, "wall_s": float(meta["collection_wall_time_s"]), "last_part_s": record["wall_s"],
                "resumed_from_step": meta["resumed_from_step"],
                "timed_from_step": meta.get("collection_timed_from_step", 0)}
    run = run_dir_of(job, workdir / "outputs") if job.module == "torchrl_bail.train" else None
    summary_path = run / "summary.json" if run is not None else None
    summary = json.loads(summary_path.read_text()) if summary_path is not None and summary_path.is_file() else {}
    if not summary.get("resumed_from_iteration"):
        return record
    return {**record, "wall_s": float(summary["wall_time_s"]), "last_part_s": record["wall_s"],
            "resumed_from_iteration": summary["resumed_from_iteration"]}


def wall_seconds(entry: float | dict) -> float:
    """A ``timings.json`` entry's wall seconds: the bare number of older entries, or a record's ``wall_s``."""
    return float(entry["wall_s"] if isinstance(entry, dict) else entry)


def cell_label(row: dict) -> str:
    """A report row's name in the cell: its algorithm, and the overrides that set it apart from its yaml's values
    (the paper preset's). The report names a key for every group of an algorithm once one group overrides it, so
    the faithful MARWIL beside the one with V fitted first is ``marwil``, not ``marwil (value_warmup_updates=0)``
    (which left the claim "MARWIL above BC" without its group)."""
    from torchrl_bail.configuration.config_builders import algo_config

    yaml = OmegaConf.create({"algo": algo_config(row["algo"])})
    extra = ", ".join(f"{k.rsplit('.', 1)[-1]}={v}" for k, v in sorted(row["overrides"].items())
                      if v is not None and OmegaConf.select(yaml, k) != v)
    return f"{row['algo']} ({extra})" if extra else row["algo"]


def cost_rows(results: Path, jobs: list[Job]) -> list[dict]:
    """One row per training job with a kept run: wall seconds (``timings.json``, else the summary's
    ``wall_time_s``), torch threads, updates and updates per wall second (evaluations included), and the load
    averages at the job's start and end."""
    timings_path = results / "timings.json"
    timings = json.loads(timings_path.read_text()) if timings_path.is_file() else {}
    rows = []
    for job in jobs:
        run = run_dir_of(job, results / "runs") if job.module == "torchrl_bail.train" else None
        if run is None or not (run / "summary.json").is_file():
            continue
        summary = json.loads((run / "summary.json").read_text())
        entry = timings.get(job.name)
        wall = wall_seconds(entry) if entry is not None else float(summary["wall_time_s"])
        record = entry if isinstance(entry, dict) else {}
        threads = record.get("threads")
        if threads is None and (run / "config.yaml").is_file():
            threads = OmegaConf.load(run / "config.yaml").get("threads")
        updates = summary.get("iterations")
        rows.append({"job": job.name, "wall_s": wall, "threads": threads, "updates": updates,
                     "updates_per_s": updates / wall if updates else None,
                     "load_start": record.get("start", {}).get("load"), "load_end": record.get("end", {}).get("load"),
                     "cpu": record.get("cpu"), "recorded": "timings.json" if entry is not None else "summary.json"})
    return rows


def envelope_fits(results: Path) -> list[dict]:
    """Every kept upper-envelope fit (a run whose summary has ``envelope_best_epoch``): its best validation epoch
    against the fit's epoch cap, the share of returns left above the envelope (``envelope_fraction_below``: the
    share with V < G) and the median of V - G, and its Fig. 13-style plot where the run kept one."""
    fits = []
    for summary_path in sorted((results / "runs").glob("*/*/*/summary.json")):
        summary = json.loads(summary_path.read_text())
        if summary.get("envelope_best_epoch") is None:
            continue
        run = summary_path.parent
        cap = OmegaConf.load(run / "config.yaml").algo.envelope.epochs if (run / "config.yaml").is_file() else None
        fits.append({"run": str(run.relative_to(results / "runs")), "best_epoch": summary["envelope_best_epoch"],
                     "epochs": cap, "uncovered": summary.get("envelope_fraction_below"),
                     "median_gap": summary.get("envelope_median_gap"),
                     "plot": str((run / "envelope.png").relative_to(results)) if (run / "envelope.png").is_file()
                     else None})
    return fits


def load_change(cost: dict) -> str:
    """``start → end`` of a cost row's 1-minute load average, or nothing where the job's record has none."""
    if cost["load_start"] is None or cost["load_end"] is None:
        return ""
    return f"{cost['load_start'][0]} → {cost['load_end'][0]}"


def paper_cell_report(results: Path, jobs: list[Job]) -> str:
    """``cell.{md,json}`` of the paper-scale study: every group of the cell (per-seed final returns, mean ± std, IQM
    with its 95 % bootstrap interval, best evaluation) beside :data:`PAPER_ANCHORS`, a verdict per claim of
    :data:`PAPER_CLAIMS` (:func:`claim_verdict`), and the cost of every kept run (:func:`cost_rows`). Reads the
    report's ``study.json``; returns the markdown."""
    from torchrl_bail.core.io import write_json_atomic, write_text_atomic

    study = json.loads((results / "study.json").read_text()) if (results / "study.json").is_file() else {"groups": []}
    rows = {cell_label(row): row for row in study["groups"]}
    if len(rows) != len(study["groups"]):  # two groups under one name: a claim would read either
        labels = [cell_label(row) for row in study["groups"]]
        raise ValueError(f"report groups share a cell label: {sorted({x for x in labels if labels.count(x) > 1})}")
    for row in rows.values():  # run_dirs are relative to the repository (report), or absolute
        row["per_seed"] = [json.loads((HERE.parent / d / "summary.json").read_text())["final_return"]
                           for d in row["run_dirs"]]
    claims = [{"claim": claim, "a": a, "b": b, "verdict": claim_verdict(rows.get(a), rows.get(b), kind)}
              for claim, a, b, kind in PAPER_CLAIMS]
    costs = cost_rows(results, jobs)

    def fmt(x, digits=1):
        return "" if x is None else f"{x:.{digits}f}"

    lines = ["| algorithm | seeds | final return per seed | mean ± std | IQM [95 % CI] | best evaluation (mean) "
             "| published (gym v2) |", "|---|---|---|---|---|---|---|"]
    for label, row in rows.items():
        anchor = PAPER_ANCHORS.get(label, ("", ""))[0]
        std = row["final_return_std"]
        lines.append(f"| {label} | {row['seeds']} | {' / '.join(fmt(x) for x in row['per_seed'])} | "
                     f"{fmt(row['final_return_mean'])}{' ± ' + fmt(std) if std is not None else ''} | "
                     f"{fmt(row['final_return_iqm'])} [{fmt(row['final_return_iqm_ci_low'])}, "
                     f"{fmt(row['final_return_iqm_ci_high'])}] | {fmt(row['best_return_mean'])} | {anchor} |")
    lines += ["", "Published figures: " + "; ".join(f"{algo}: {value}, {source}"
                                                    for algo, (value, source) in PAPER_ANCHORS.items()) + ".",
              "They come from gym's -v2 Hopper; these runs use Gymnasium's -v5, whose simulator and rewards differ, "
              "so a level is a ballpark and the ordering of the algorithms is what compares.", "",
              "| claim | verdict |", "|---|---|"]
    lines += [f"| {c['claim']} | {c['verdict']} |" for c in claims]
    lines += ["", f"A verdict needs {MIN_SEEDS_FOR_VERDICT} seeds on both sides; 'holds' for a ≫ claim means the "
              "first group's IQM interval lies wholly above the second's; for a ≈ claim that the intervals overlap "
              "(no difference shown, which is not proof of equality).", "",
              "| job | wall time (s) | threads | updates | updates/s (evaluations included) | load at start → end "
              "| recorded in |", "|---|---|---|---|---|---|---|"]
    lines += [f"| {c['job']} | {c['wall_s']:.0f} | {c['threads'] if c['threads'] is not None else ''} | "
              f"{c['updates'] if c['updates'] is not None else ''} | {fmt(c['updates_per_s'])} | "
              f"{load_change(c)} | {c['recorded']} |" for c in costs]
    fits = envelope_fits(results)
    lines += ["", "| envelope fit | best epoch of cap | returns above the envelope (V < G) | median V - G | plot |",
              "|---|---|---|---|---|"]
    lines += [f"| {f['run']} | {f['best_epoch']} of {f['epochs']} | {fmt(100 * f['uncovered'], 2)} % | "
              f"{fmt(f['median_gap'])} | {f['plot'] or ''} |" for f in fits]
    lines += ["", "Load: the 1-minute load average as the job started and ended (a job on one thread alone on the "
              "machine reads about 1)."]
    text = "\n".join(lines) + "\n"
    write_text_atomic(results / "cell.md", text)
    write_json_atomic(results / "cell.json", {"groups": rows, "anchors": PAPER_ANCHORS, "claims": claims,
                                              "costs": costs, "envelope_fits": fits})
    return text


# ---------------------------------------------------------------------------------------------------------------
# the off-policy-evaluation report (``--study ope_headline``): how well FQE ranks the headline batch's policies
# ---------------------------------------------------------------------------------------------------------------

#: the bootstrap of the rank correlation's interval: replications (policies drawn with replacement) and numpy seed
OPE_REPS, OPE_SEED = 2_000, 0


def _last_evaluation(run: Path) -> float | None:
    """The return of a run's final policy (``policy.pt``) as training measured it: its last evaluation's mean return
    (``logs/scalars/eval/return.csv``, the value ``policy.pt`` records)."""
    csv = run / "logs" / "scalars" / "eval" / "return.csv"
    if not csv.is_file():
        return None
    returns = read_scalar_csv(csv)
    return float(returns[max(returns)]) if returns else None


def _read_json(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _ope_policy(job: Job, results: Path, headline: Path) -> dict:
    """One policy of the OPE study: its kept run, FQE estimate, true return and the paper_hopper study's summary of
    the same job (the reference its numbers must equal)."""
    named = job.overrides
    entry = {"job": job.name, "algo": named["algo"], "seed": int(named["seed"]), "run": None, "estimate": None,
             "true_return": None, "final_return": None, "best_return": None, "reference_final_return": None,
             "reproduces": None, "action_gap": None}
    reference_job = Job(job.name, [a for a in job.args if a not in OPE_SNAPSHOTS.get(named["algo"], [])])
    reference = run_dir_of(reference_job, headline / "runs")
    ref_summary = None if reference is None else _read_json(reference / "summary.json")
    if ref_summary is not None:
        entry["reference_run"] = shown_path(reference)
        entry["reference_final_return"] = ref_summary["final_return"]
    run = run_dir_of(job, results / "runs")
    summary = None if run is None else _read_json(run / "summary.json")
    if summary is None:
        return entry
    entry.update(run=shown_path(run), final_return=summary["final_return"], best_return=summary["best_return"],
                 true_return=_last_evaluation(run))
    if ref_summary is not None:
        entry["reproduces"] = all(summary.get(k) == ref_summary.get(k) for k in ("final_return", "best_return"))
        entry["platforms"] = _compare_records(summary, ref_summary, lambda p: {k: v for k, v in p.items()
                                                                                 if k != "source"})
        entry["sources"] = _compare_records(summary, ref_summary, lambda p: p.get("source"))
    ope = finished_ope(run)
    if ope is not None:
        entry["estimate"], entry["action_gap"] = ope["estimate"], ope.get("action_gap")
        if ope.get("fqe_selected"):
            candidates = ope["snapshots"]
            entry["snapshots"] = {
                "candidates": [{k: c[k] for k in ("iteration", "eval_return", "fqe_estimate", "rank")}
                               for c in candidates],
                "fqe_selected": ope["fqe_selected"],
                "best_candidate_return": max(c["eval_return"] for c in candidates),
                "spearman": (ranking_quality([c["fqe_estimate"] for c in candidates],
                                             [c["eval_return"] for c in candidates])["spearman"]
                             if len(candidates) > 1 else None)}
    return entry


def _compare_records(summary: dict, reference: dict, part) -> str:
    """Whether ``part`` of two summaries' ``platform`` records agrees: ``same``, ``different`` or ``unrecorded``
    (either summary lacks it)."""
    mine, theirs = (part(s["platform"]) if s.get("platform") else None for s in (summary, reference))
    return "unrecorded" if mine is None or theirs is None else "same" if mine == theirs else "different"


def _why_not_the_same_run(policy: dict) -> str:
    """The "same run" cell of a retrained run that differs from the kept one: whether its platform, or only the code,
    differs (else a bug, in bold), or is unrecorded."""
    if policy.get("platforms") == "same" and policy.get("sources") == "different":
        return "no (another code revision)"
    return {"same": "**no** (same platform)", "different": "no (another platform)",
            "unrecorded": "no (a platform unrecorded)"}.get(policy.get("platforms"))


def _gap_overrating(scored: list[dict]) -> dict | None:
    """Spearman's rho between the scored policies' action gaps and FQE's overrating of each (its rank by estimate
    minus its rank by true return, ranks ascending, ties averaged), or ``None`` below 3 policies with a gap."""
    from scipy.stats import rankdata, spearmanr

    with_gap = [p for p in scored if p["action_gap"] is not None]
    if len(with_gap) < 3:
        return None
    overrating = (rankdata([p["estimate"] for p in with_gap]) - rankdata([p["true_return"] for p in with_gap]))
    rho = spearmanr([p["action_gap"] for p in with_gap], overrating).statistic
    return {"n": len(with_gap), "spearman": None if np.isnan(rho) else float(rho)}


def plot_ope(policies: list[dict], path: Path) -> Path:
    """``ope.png``: left, each scored final policy's FQE estimate against its true return, one marker per algorithm;
    right, each BAIL run's snapshots (estimate against evaluation return, one colour per seed, each labelled with its
    iteration), FQE's choice circled. Before any policy is scored, both panels say so (the docs show the file at every
    stage)."""
    from torchrl_bail.reports.plots import new_figure, save_figure

    scored = [p for p in policies if p["estimate"] is not None and p["true_return"] is not None]
    fig = new_figure(figsize=(11.0, 4.6), layout="constrained")
    left, right = fig.subplots(1, 2)
    algos = list(dict.fromkeys(p["algo"] for p in scored))
    for i, algo in enumerate(algos):
        mine = [p for p in scored if p["algo"] == algo]
        left.scatter([p["estimate"] for p in mine], [p["true_return"] for p in mine], color=f"C{i}",
                     marker="osD^v<>"[i % 7], s=42, label=f"{algo} ({len(mine)})")
    left.set_xlabel("FQE estimate (discounted value, gamma 0.99)")
    left.set_ylabel("true return (the policy's own evaluation, 10 episodes)")
    left.set_title(f"final policies on the headline batch ({len(scored)})")
    left.grid(alpha=0.3)
    if scored:
        left.legend(fontsize="small")
    else:
        left.text(0.5, 0.5, "no policy scored yet", transform=left.transAxes, ha="center", color="gray")
    for i, p in enumerate(p for p in policies if p.get("snapshots")):
        c = p["snapshots"]["candidates"]
        right.scatter([x["fqe_estimate"] for x in c], [x["eval_return"] for x in c], color=f"C{i}", s=24,
                      label=f"seed {p['seed']}")
        for x in c:  # each snapshot's iteration, in thousands
            right.annotate(f"{x['iteration'] // 1000}k", (x["fqe_estimate"], x["eval_return"]), fontsize=7,
                           color=f"C{i}", xytext=(4, 3), textcoords="offset points")
        chosen = p["snapshots"]["fqe_selected"]
        right.scatter([chosen["fqe_estimate"]], [chosen["online_return"]], s=140, facecolors="none",
                      edgecolors=f"C{i}", linewidths=1.6)
    right.set_xlabel("FQE estimate")
    right.set_ylabel("evaluation return of the snapshot")
    right.set_title("BAIL snapshots along training (circled: FQE's choice)")
    right.grid(alpha=0.3)
    if right.collections:
        right.legend(fontsize="small")
    else:
        right.text(0.5, 0.5, "no BAIL snapshots ranked yet", transform=right.transAxes, ha="center", color="gray")
    return save_figure(fig, path)


def ope_headline_report(results: Path, headline: Path | None = None) -> dict:
    """``results/ope.{md,json}`` and ``results/ope.png``: how well FQE (``torchrl_bail.ope``, its default settings)
    ranks the policies of :func:`ope_headline_jobs`, from kept files alone. Each policy's true return is its own
    evaluation in training (the last evaluation's mean over 10 test episodes: the return of exactly the policy FQE
    scored); ``final_return`` (the mean of the last 10 evaluations) is shown beside it, and each run is checked
    against the paper_hopper study's kept summary of the same job (``headline``, default ``results/paper_hopper``).
    Over the scored policies: Spearman's rank correlation with a bootstrap interval and the regret of deploying
    FQE's top policy (:func:`torchrl_bail.ope.ranking_quality`); per algorithm, the same on the algorithms' means; per
    BAIL run, the online return of the snapshot FQE selects beside ``final_return`` and ``best_return``. Returns the
    JSON written."""
    from torchrl_bail.core.io import write_json_atomic, write_text_atomic

    headline = headline if headline is not None else HERE / "paper_hopper"
    trains = [j for j in ope_headline_jobs() if j.module == "torchrl_bail.train"]
    policies = [_ope_policy(job, results, headline) for job in trains]
    scored = [p for p in policies if p["estimate"] is not None and p["true_return"] is not None]
    trained = [p for p in policies if p["run"] is not None]
    checked = [p for p in trained if p["reproduces"] is not None]
    ranking = None
    if len(scored) >= 2:
        q = ranking_quality([p["estimate"] for p in scored], [p["true_return"] for p in scored])
        low, high = spearman_interval([p["estimate"] for p in scored], [p["true_return"] for p in scored],
                                      reps=OPE_REPS, seed=OPE_SEED)
        ranking = {**q, "spearman_ci": [low, high], "selected": scored[q["selected"]]["job"],
                   "best": scored[q["best"]]["job"], "selected_return": scored[q["selected"]]["true_return"],
                   "best_return": scored[q["best"]]["true_return"],
                   "regret_fraction": q["regret"] / scored[q["best"]]["true_return"]}
    by_algo = {}
    for p in scored:
        by_algo.setdefault(p["algo"], []).append(p)
    algorithms = [{"algo": a, "policies": len(ps), "mean_estimate": float(np.mean([p["estimate"] for p in ps])),
                   "mean_true_return": float(np.mean([p["true_return"] for p in ps])),
                   "mean_action_gap": (None if any(p["action_gap"] is None for p in ps) else
                                       float(np.mean([p["action_gap"] for p in ps])))} for a, ps in by_algo.items()]
    gap_overrating = _gap_overrating(scored)
    algo_ranking = None
    if len(algorithms) >= 2:
        q = ranking_quality([a["mean_estimate"] for a in algorithms], [a["mean_true_return"] for a in algorithms])
        algo_ranking = {**q, "selected": algorithms[q["selected"]]["algo"], "best": algorithms[q["best"]]["algo"]}
    selections = [p for p in policies if p.get("snapshots")]
    selection_means = None if not selections else {
        key: float(np.mean([f(p) for p in selections])) for key, f in (
            ("fqe_selected_return", lambda p: p["snapshots"]["fqe_selected"]["online_return"]),
            ("final_return", lambda p: p["final_return"]), ("best_return", lambda p: p["best_return"]),
            ("final_policy_return", lambda p: p["true_return"]),
            ("best_candidate_return", lambda p: p["snapshots"]["best_candidate_return"]))}
    planned_snapshots = sum(1 for j in trains if OPE_SNAPSHOTS.get(j.name.split("/")[1]))
    status = (f"Policies scored by FQE: {len(scored)} of {len(policies)} planned (trained: {len(trained)}); BAIL runs "
              f"with their snapshots ranked: {len(selections)} of {planned_snapshots}. Retrained runs equal to the "
              f"paper_hopper study's kept run of the same job (final and best return): "
              f"{sum(bool(p['reproduces']) for p in checked)} of {len(checked)}. "
              + ("Every policy is scored." if len(scored) == len(policies) else
                 f"The readings below are preliminary until all {len(policies)} are scored."))
    figure = plot_ope(policies, results / "ope.png")
    out = {"status": status, "policies": policies, "ranking": ranking, "algorithms": algorithms,
           "algorithm_ranking": algo_ranking, "gap_overrating": gap_overrating, "snapshot_selection": selection_means,
           "bootstrap": {"reps": OPE_REPS, "seed": OPE_SEED}, "figure": figure.name}

    def num(x, digits=1):
        return "pending" if x is None else f"{x:.{digits}f}"

    lines = [status, "", "| policy | FQE estimate | action gap | true return | final_return | paper_hopper's "
             "final_return | same run |", "|---|---|---|---|---|---|---|"]
    for p in policies:
        same = {None: "pending", True: "yes", False: _why_not_the_same_run(p)}[p["reproduces"]]
        lines.append(f"| {p['algo']} seed {p['seed']} | {num(p['estimate'], 2)} | {num(p['action_gap'], 2)} | "
                     f"{num(p['true_return'])} | "
                     f"{num(p['final_return'])} | {num(p['reference_final_return'])} | {same} |")
    lines += ["", "FQE estimate: `python -m torchrl_bail.ope` at its defaults (d3rlpy's FQE settings, 10^5 updates; a "
              "discounted value, gamma 0.99, so not on the return's scale). True return: the policy's own evaluation "
              "in training, the mean over 10 test episodes of exactly the policy FQE scored (its last evaluation); "
              "final_return, the mean of the last 10 evaluations, is the figure the other reports use. Same run: "
              "the retrained run's final and best return equal those the paper_hopper study kept for the same job, "
              "to the last digit. Where they do not, the summaries' `platform` records (library versions, CPU model, "
              "SIMD level, the code's git revision) tell a bug (the same platform and code) from another machine's "
              "rounding, which grows over training, or from a change of the code; the paper_hopper runs were made "
              "before summaries recorded it. Action gap: how far the policy acts from the batch, the root mean "
              "square of its action minus the batch's over all 10^6 transitions, per half action range "
              "(`torchrl_bail.ope.action_gap`; 0: the batch's own actions); the further it is, the more of FQE's "
              "estimate is extrapolation.", ""]
    if ranking is None:
        lines.append("Ranking: pending (fewer than 2 scored policies).")
    else:
        lines += ["| policies | Spearman's rho [95 % bootstrap CI] | FQE's top policy (true return) | best policy "
                  "(true return) | regret |", "|---|---|---|---|---|",
                  f"| {ranking['n']} | {num(ranking['spearman'], 2)} [{num(ranking['spearman_ci'][0], 2)}, "
                  f"{num(ranking['spearman_ci'][1], 2)}] | {ranking['selected']} ({num(ranking['selected_return'])}) "
                  f"| {ranking['best']} ({num(ranking['best_return'])}) | {num(ranking['regret'])} "
                  f"({100 * ranking['regret_fraction']:.0f} % of the best) |", "",
                  f"Spearman's rank correlation between the FQE estimates and the true returns of the scored final "
                  f"policies (its interval: the policies bootstrapped, {OPE_REPS} replications); regret: the best "
                  f"true return minus that of the policy with the highest estimate, the return a user who deploys "
                  f"FQE's choice gives up."]
    if gap_overrating is not None:
        lines += ["", f"Does FQE overrate the policies that act furthest from the batch? Spearman's rho between the "
                  f"action gap and FQE's overrating (a policy's rank by estimate above its rank by true return) over "
                  f"the {gap_overrating['n']} scored policies: {num(gap_overrating['spearman'], 2)} (positive: the "
                  f"more FQE overrates a policy, the further that policy acts from the batch)."]
    if algo_ranking is not None:
        lines += ["", "| algorithm | policies | mean FQE estimate | mean action gap | mean true return |",
                  "|---|---|---|---|---|"]
        lines += [f"| {a['algo']} | {a['policies']} | {num(a['mean_estimate'], 2)} | {num(a['mean_action_gap'], 2)} "
                  f"| {num(a['mean_true_return'])} |" for a in algorithms]
        lines += ["", f"Choosing an algorithm by its mean estimate: FQE ranks **{algo_ranking['selected']}** first, "
                  f"the true returns **{algo_ranking['best']}** (Spearman's rho over the {algo_ranking['n']} "
                  f"algorithms {num(algo_ranking['spearman'], 2)}; regret {num(algo_ranking['regret'])})."]
    if selections:
        lines += ["", "| BAIL run | snapshots | FQE's choice: iteration | its online return | final policy's return "
                  "| final_return | best_return | best snapshot's return | rho over snapshots |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for p in selections:
            snap = p["snapshots"]
            lines.append(f"| seed {p['seed']} | {len(snap['candidates'])} | {snap['fqe_selected']['iteration']} | "
                         f"{num(snap['fqe_selected']['online_return'])} | {num(p['true_return'])} | "
                         f"{num(p['final_return'])} | {num(p['best_return'])} | {num(snap['best_candidate_return'])} "
                         f"| {num(snap['spearman'], 2)} |")
        m = selection_means
        lines.append(f"| mean of {len(selections)} | | | {num(m['fqe_selected_return'])} | "
                     f"{num(m['final_policy_return'])} | {num(m['final_return'])} | {num(m['best_return'])} | "
                     f"{num(m['best_candidate_return'])} | |")
        lines += ["", "A BAIL run keeps 5 policies evenly along training (`eval.snapshots=5`, the last one the final "
                  "policy); FQE fits each and picks the highest estimate. Its online return is the snapshot's own "
                  "evaluation in training (10 episodes), what a user without a simulator deploying FQE's choice "
                  "gets; best_return is the best of all 100 evaluations, a choice only the simulator can make."]
    text = "\n".join(lines) + "\n"
    write_text_atomic(results / "ope.md", text)
    write_json_atomic(results / "ope.json", out)
    return out


def write_reports(study: str, results: Path, headline: Path) -> str:
    """Every report of ``study`` from the runs kept in ``results`` (``headline``: the headline batch's kept results,
    which the cross-batch and OPE reports read); returns the names of its reports."""
    report_runs(results, ablations=study == "study")
    curve_check(results)
    if study == "paper_hopper":
        paper_cell_report(results, STUDIES[study]())
    if study == "paper_batches":
        cross_batch_report(results, headline, headline_jobs=paper_hopper_jobs())
    if study == "ope_headline":
        ope_headline_report(results, headline)
    if study == "paper_exec":
        exec_table_report(results)
    return {"study": "study.md, ablations.md", "paper_hopper": "study.md, cell.md",
            "paper_batches": "study.md, cross_batch.md", "ope_headline": "study.md, ope.md",
            "paper_exec": "study.md, table2.md"}[study]


def pin_cpus(parallel: int) -> queue.SimpleQueue:
    """The CPUs ``--pin`` gives the queue's jobs: the first ``parallel`` of the runner's own (``os.sched_getaffinity``,
    so ``taskset -c 2,3 python results/run_study.py --jobs 2 --pin`` uses CPUs 2 and 3). A clear error where there are
    fewer CPUs than jobs or no ``taskset`` (util-linux) to pin with."""
    allowed = sorted(os.sched_getaffinity(0))
    if parallel > len(allowed):
        raise ValueError(f"--pin runs each job alone on a CPU: --jobs {parallel} needs {parallel} CPUs, this process "
                         f"may use {len(allowed)} ({allowed})")
    if shutil.which("taskset") is None:
        raise ValueError("--pin starts each job under taskset (util-linux), which is not on PATH")
    cpus = queue.SimpleQueue()
    for cpu in allowed[:max(1, parallel)]:
        cpus.put(cpu)
    return cpus


def batch_key(job: Job) -> tuple[str, ...]:
    """What names a job's batch among its arguments (experiment, ``batch.*`` overrides, preset): a collect job and the
    jobs that train on its batch share it."""
    return tuple(sorted(a for a in job.args if a.startswith(("+exp=", "batch.", "preset="))))


def next_ready(pending: list[Job], running: list[Job]) -> Job | None:
    """The first of ``pending`` whose batch no running collect job is making (it would only wait on the batch's lock,
    holding a worker and its CPU), or ``None`` if every one would wait."""
    collecting = {batch_key(j) for j in running if j.module == "torchrl_bail.collect"}
    return next((j for j in pending if batch_key(j) not in collecting), None)


def run_queue(jobs: list[Job], workdir: Path, data_dir: Path | None, results: Path, parallel: int,
              cpus: queue.SimpleQueue | None = None) -> list[str]:
    """Runs ``jobs`` in order, ``parallel`` at a time (:func:`run_job`), printing ``[k/N] <job>: ok in S s`` as each
    ends and recording its cost in ``results/timings.json``; returns the names of the jobs that failed. One queue,
    batches first: training starts while the last batches are still being collected. A free worker takes the first
    job whose batch is not being collected by a running job (:func:`next_ready`), so while one core makes a batch the
    other goes on with jobs on other batches instead of waiting on its lock. ``cpus`` (``--pin``, :func:`pin_cpus`):
    each job runs alone on one of them, so that its recorded cost is one core's whatever runs beside it."""
    failed, pending, running, done = [], list(jobs), {}, 0
    stop, workers = threading.Event(), max(1, parallel)
    with ThreadPoolExecutor(max_workers=workers) as pool:
        while pending or running:
            while len(running) < workers and (job := next_ready(pending, list(running.values()))):
                pending.remove(job)
                running[pool.submit(run_job, job, workdir.resolve(), data_dir, results, stop, cpus)] = job
            finished, _ = wait(running, return_when=FIRST_COMPLETED)
            for future in finished:
                job, done = running.pop(future), done + 1
                if not record_job_end(future, job, f"[{done}/{len(jobs)}]", workdir, results):
                    failed.append(job.name)
    return failed


def record_job_end(future: Future, job: Job, counter: str, workdir: Path, results: Path) -> bool:
    """Prints how ``job`` (``future``'s :func:`run_job`) ended and records its cost in ``results/timings.json``;
    whether it did not fail."""
    from torchrl_bail.core.io import write_text_atomic

    try:
        _, rc, seconds, record = future.result()
    except BatchMismatch as err:
        print(f"{counter} {job.name}: FAILED ({err}); no other job starts", flush=True)
        return False
    if rc is None:
        return True  # finished in an earlier call
    print(f"{counter} {job.name}: {'ok' if rc == 0 else f'FAILED (exit {rc})'} in {seconds:.0f} s", flush=True)
    # read again before each write: another runner (another CPU's job) may have recorded since
    timings_path = results / "timings.json"
    timings = json.loads(timings_path.read_text()) if timings_path.exists() else {}
    if rc == 0 and job.name not in timings:  # the first record stays (a batch made again keeps its remakes.json)
        timings[job.name] = whole_job_record(job, record, workdir)
        write_text_atomic(timings_path, json.dumps(timings, indent=1, sort_keys=True) + "\n")
    return rc == 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--study", choices=sorted(STUDIES), default="study",
                        help="study: the 50k-transition study (docs: Results); paper_hopper: Hopper at paper scale; "
                             "paper_batches: three more 10^6 batches, reported beside paper_hopper's (cross_batch.md)")
    parser.add_argument("--only", help="run only the jobs whose name matches this regex (e.g. hopper_ddpg05/bail)")
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="jobs at a time (default: cores)")
    parser.add_argument("--pin", action="store_true",
                        help="run each job alone on one CPU of this process's (taskset -c): --jobs N uses the first N")
    parser.add_argument("--workdir", type=Path, help="where outputs/ and logs/ go (default: <study>_work)")
    parser.add_argument("--data-dir", type=Path, help="batch cache (default: TORCHRL_BAIL_DATA_DIR or ~/.cache)")
    parser.add_argument("--results", type=Path, help="where the kept files and reports go (default: results/<study>)")
    parser.add_argument("--list", action="store_true", help="print the jobs and exit")
    parser.add_argument("--status", action="store_true", help="print each job's state (done, running, left)")
    parser.add_argument("--report-only", action="store_true", help="only gather the finished runs and report")
    parser.add_argument("--headline", type=Path, default=HERE / "paper_hopper",
                        help="paper_batches, ope_headline: the headline batch's kept results (default: "
                             "results/paper_hopper)")
    args = parser.parse_args(argv)
    if args.jobs < 1:
        parser.error(f"--jobs must be at least 1, got {args.jobs}")
    args.workdir = args.workdir or Path(f"{args.study}_work")
    args.results = args.results or HERE / args.study

    jobs = STUDIES[args.study]()
    if args.only:  # a row's batch is collected by its first training job (the others wait on its lock)
        jobs = [j for j in jobs if re.search(args.only, j.name)]
    if args.list:
        print("\n".join(f"{j.name}: python -m {j.module} {' '.join(j.args)}" if j.module != "torchrl_bail.ope" else
                        f"{j.name}: python -m {j.module} <the run of {j.name[len('ope/'):]}> {' '.join(OPE_FLAGS)}"
                        for j in jobs))
        return 0
    if args.status:
        states = [(j.name, job_status(j, args.workdir, args.data_dir, args.results)) for j in jobs]
        width = max(len(str(state)) for _, state in states)
        print("\n".join(f"{str(state):<{width}}  {name}" for name, state in states))
        counts = {k: sum(state.state == k for _, state in states) for k in ("done", "running", "left")}
        print(", ".join(f"{v} {k}" for k, v in counts.items()) + f" of {len(states)} jobs")
        own, elsewhere = args.results / "timings.json", {}
        for peer in COST_PEERS.get(args.study, ()):
            path = args.results.parent / peer / "timings.json"
            elsewhere.update(json.loads(path.read_text()) if path.exists() else {})
        timings = json.loads(own.read_text()) if own.exists() else {}
        seconds = seconds_left(states, timings, elsewhere)
        print(work_left(states, seconds))
        if known := {name: left for name, left in seconds.items() if left is not None}:
            wall = queue_wall_seconds(jobs, dict(states), known, args.jobs)
            print(f"with --jobs {args.jobs}, as the queue dispatches them (a batch's jobs after its collection): "
                  f"about {wall / 3600:.1f} h of wall time for those jobs")
        return 0
    cpus = None
    if args.pin and not args.report_only:
        try:
            cpus = pin_cpus(args.jobs)
        except ValueError as err:
            parser.error(str(err))
    args.workdir.mkdir(parents=True, exist_ok=True)
    args.results.mkdir(parents=True, exist_ok=True)
    failed = [] if args.report_only else run_queue(jobs, args.workdir, args.data_dir, args.results, args.jobs, cpus)
    try:
        copied = gather(args.workdir, args.results, STUDIES[args.study](), policies=args.study != "study")
    except BatchMismatch as err:
        print(f"run_study: {err}; nothing gathered, no report written", file=sys.stderr)
        return 1
    reports = write_reports(args.study, args.results, args.headline)
    kept = len(list((args.results / "runs").glob("*/*/*/summary.json")))
    print(f"{len(copied)} runs copied from {args.workdir / 'outputs'}; {kept} runs in {args.results / 'runs'}; "
          f"reports in {args.results}: {reports}")
    if failed:
        print("failed (see their logs in " f"{args.workdir / 'logs'}): " + ", ".join(failed), file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

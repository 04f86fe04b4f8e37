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
from torchrl_bail.ope import ranking_quality, spearman_interval  # loads no torch

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


#: the cross-batch study (``--study paper_batches``): three more 10^6-transition training batches, in the order they
#: run, each as (exp, batch index, the BAIL authors' published figure on it: their repository's README table, gym -v2
#: envs, mean ± std over seeds). Hopper DDPG sigma=0.5 B2 is the headline batch's recipe with another seed: how much of
#: a verdict is the batch itself
PAPER_BATCHES = [("walker_ddpg05", 1, "2522 ± 51"), ("hopper_ddpg01", 1, "2173 ± 291"),
                 ("hopper_ddpg05", 2, "2623 ± 282")]
#: the central algorithms of the cross-batch study, with their seeds, in the order they run on each batch
PAPER_BATCH_CELLS = [("bail", 5), ("bc", 5), ("bcq", 3), ("pbail", 3)]
#: when every batch has its central cells: the paper's other actor-critic and two modern reference points (no claim
#: rests on these)
PAPER_BATCH_EXTRA_CELLS = [("bear", 3), ("td3bc", 3), ("iql", 3)]


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


#: the execution-batch study (``--study paper_exec``, issue 51): per env in turn, the 10^6-step SAC run (its ``sac``
#: training batch) and its four execution batches of supp. Table 2 (B1, 10^6 transitions each), then on each of those
#: five batches :data:`PAPER_EXEC_CELLS` at the paper-scale schedules; Hopper's batches complete before Walker2d's start
PAPER_EXEC_ENVS = ("hopper", "walker")
PAPER_EXEC_KINDS = ("sac", "med_det", "med_stoch", "opt_det", "opt_stoch")
PAPER_EXEC_CELLS = [("bail", 3), ("bc", 3), ("marwil", 3), ("bcq", 3)]
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


def batch_label(job: Job) -> str:
    """The label of a job's batch, ``<experiment>_b<batch.index>`` (e.g. ``hopper_ddpg05_b2``): the first part of its
    run directories and of its partial collection's name in the data dir. Coarser than :func:`batch_key`: a preset
    or another ``batch.*`` override makes another batch under the same label."""
    named = job.overrides
    return f"{named['+exp']}_b{named.get('batch.index', 1)}"


def label_recipe(label: str) -> str:
    """The experiment (recipe) of a :func:`batch_label`, ``hopper_ddpg05_b2`` -> ``hopper_ddpg05``: batches of one
    recipe differ only in their behaviour seed (``batch.index``)."""
    return label.rsplit("_b", 1)[0]


def run_dir_of(job: Job, runs: Path) -> Path | None:
    """The run directory of a training job under ``runs`` (the workdir's ``outputs``, or the results' ``runs``, which
    keeps the same layout: ``<batch>_b1/<algo>/seed<s>[,<overrides>]``)."""
    named = job.overrides
    extra = sorted(arg for arg in job.args if not arg.startswith(("+exp=", "algo=", "seed=", "batch.index=")))
    for run in sorted((runs / batch_label(job) / named["algo"]).glob(f"seed{named['seed']}*")):
        if run.name.split(",")[0] == f"seed{named['seed']}" and sorted(run.name.split(",")[1:]) == extra:
            return run
    return None


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
    from torchrl_bail.data.batch import cpu_model  # loads torch: not at the script's start (--list, --status)

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


#: what a collect job prints once its batch is in the cache (``torchrl_bail.collect``): the batch's cache entry
CACHED_AT = re.compile(r"^\S+: (?:collected|already cached) at (.+)$", re.MULTILINE)


def collected_batch(job: Job, workdir: Path) -> Path | None:
    """The batch directory (in the data dir) that a collect job's log in ``workdir/logs`` names last, when that
    batch's ``metadata.json`` is there; else ``None``."""
    log = workdir / "logs" / (job.name.replace("/", "__") + ".log")
    if job.module != "torchrl_bail.collect" or not log.is_file():
        return None
    entries = CACHED_AT.findall(log.read_text(errors="replace"))
    batch = Path(entries[-1].strip()) if entries else None
    return batch if batch is not None and (batch / "metadata.json").is_file() else None


class BatchMismatch(RuntimeError):
    """A batch made again (its data dir lost, say) holds other data than the one whose metadata and runs are kept."""


def remakes_file(metadata: Path) -> Path:
    """``<entry>.remakes.json`` beside a kept ``<entry>.metadata.json``: the batch's remakings with the same data."""
    return metadata.with_name(metadata.name.replace(".metadata.json", ".remakes.json"))


def _record_remake(path: Path, remade: dict, same: tuple[str, ...]) -> bool:
    """Adds ``remade`` (a remaking's metadata fields that differ from the kept batch's) to the ``remakes`` of the
    JSON file at ``path``, beside ``same`` (the statistics found equal), unless it is already there or empty;
    returns whether the file changed."""
    from torchrl_bail.core.io import write_json_atomic

    record = json.loads(path.read_text()) if path.is_file() else {"same": list(same), "remakes": []}
    if not remade or remade in record["remakes"]:
        return False
    record["remakes"].append(remade)
    write_json_atomic(path, record)
    return True


def keep_batch_metadata(workdir: Path, results: Path, jobs: list[Job]) -> list[Path]:
    """Copies the ``metadata.json`` of each batch a collect job of ``jobs`` has in the cache (the entry its log in
    ``workdir/logs`` names, in the data dir) to ``results/batches/<entry>.metadata.json``: the batch's statistics
    (episode returns, the behaviour agent's final return, collection time) stay with the results once the data dir
    is gone; returns the files written. A batch whose metadata is already kept was made again, its cache lost: with
    the same data (:data:`~torchrl_bail.data.batch.STATISTICS_KEYS`, to every digit) the kept copy stays, the record
    of the collection the kept runs trained on, and ``<entry>.remakes.json`` lists each remaking's own record (the
    fields in which its metadata differ: when, how long, on which versions), the evidence that the recipe makes the
    same batch again; with other data it raises :class:`BatchMismatch`, since runs on the new copy would not compare
    with the kept ones."""
    from torchrl_bail.data.batch import STATISTICS_KEYS

    kept = []
    for job in jobs:
        batch = collected_batch(job, workdir)
        if batch is None:
            continue
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
            if _record_remake(remakes, {k: v for k, v in made.items() if v != before.get(k)}, STATISTICS_KEYS):
                kept.append(remakes)
            continue
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(source, target)
        kept.append(target)
    return kept


def gather(workdir: Path, results: Path, jobs: list[Job] = (), policies: bool = False) -> list[Path]:
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


def report(results: Path, ablations: bool = True) -> None:
    """``study.*`` (every kept run but the ablations) and, with ``ablations``, ``ablations.*`` (supp. D on Hopper
    DDPG σ = 0.5) through ``torchrl_bail.report``."""
    runs = results / "runs"
    ablation = re.compile(r"selection\.by=|envelope\.penalty=|oracle|augment")
    main_runs = [p for p in sorted(runs.glob("*/*/*")) if not ablation.search(p.name)]
    bail_ddpg05 = sorted(runs.glob("hopper_ddpg05_b1/bail/*")) + sorted(runs.glob("hopper_ddpg05_oracle*/bail/*"))
    repo = HERE.parent  # the report records its run directories relative to the repository, on any machine

    def shown(path: Path) -> str:
        path = path.resolve()
        return str(path.relative_to(repo)) if path.is_relative_to(repo) else str(path)

    for prefix, paths in (("study", main_runs), ("ablations", bail_ddpg05 if ablations else [])):
        if paths:
            subprocess.check_call([sys.executable, "-m", "torchrl_bail.report", *map(shown, paths),
                                   "--out", shown(results / prefix), "--plot"], cwd=repo, stdout=subprocess.DEVNULL)


def curve_check(results: Path) -> list[dict]:
    """Has each learning curve flattened? Per group (batch x algorithm x overrides): the mean curve over seeds,
    and over its second half (evaluations ``n // 2`` to ``n``, the ones ``final_return`` averages) its mean, the
    change a least-squares line fits across it and the spread of the points around that line. ``still_moving``
    marks a change larger than twice the spread and than 5 % of the mean. Groups whose second half holds fewer than
    3 evaluations are left out.

    For the algorithms that fit an upper envelope (their ``summary.json`` has ``envelope_best_epoch``) each group
    also lists every seed's best validation epoch against the fit's cap ``algo.envelope.epochs``, and whether early
    stopping ended every fit: ``envelope_settled`` when each best epoch is at least ``algo.envelope.patience``
    epochs before the cap (the validation loss then stopped improving for that long), not when a fit was still
    improving as the cap stopped it. Written to ``results/curves.{md,json}``."""
    import numpy as np

    from torchrl_bail.core.io import write_json_atomic, write_text_atomic
    from torchrl_bail.reports.plots import read_eval_curve

    groups: dict[tuple[str, str, str], list] = {}
    envelopes: dict[tuple[str, str, str], list] = {}
    for run in sorted((results / "runs").glob("*/*/*")):
        curve = read_eval_curve(run)
        if curve is not None:
            key = (run.parent.parent.name, run.parent.name,
                   ",".join(o for o in run.name.split(",")[1:] if o != "preset=study"))
            groups.setdefault(key, []).append(np.asarray(curve[1]))
            summary = json.loads((run / "summary.json").read_text()) if (run / "summary.json").is_file() else {}
            if summary.get("envelope_best_epoch") is not None:
                fit = OmegaConf.load(run / "config.yaml").algo.envelope
                envelopes.setdefault(key, []).append((int(summary["envelope_best_epoch"]), int(fit.epochs),
                                                      int(fit.patience)))
    rows = []
    for key, curves in groups.items():
        n = min(len(c) for c in curves)
        if n - n // 2 < 3:  # a line through a second half of fewer than 3 evaluations says nothing
            continue
        y = np.mean([c[:n] for c in curves], axis=0)[n // 2:]
        dx = np.arange(n // 2, n) - (n // 2 + n - 1) / 2  # evaluation index about the half's centre
        # least squares in closed form, not np.polyfit: LAPACK's kernels differ by CPU, these sums do not
        slope = float((dx * (y - y.mean())).sum() / (dx * dx).sum())
        spread = float(np.std(y - (y.mean() + slope * dx), ddof=2))
        change, level = slope * float(dx[-1] - dx[0]), float(y.mean())
        row = {"batch": key[0], "algo": key[1], "overrides": key[2], "seeds": len(curves), "evaluations": n,
               "second_half_mean": level, "second_half_change": change, "residual_spread": spread,
               "still_moving": bool(abs(change) > max(2 * spread, 0.05 * abs(level)))}
        if key in envelopes:
            at_cap = sum(best > cap - patience for best, cap, patience in envelopes[key])
            row.update(envelope_best_epochs=[best for best, _, _ in envelopes[key]],
                       envelope_epochs=max(cap for _, cap, _ in envelopes[key]),
                       envelope_fits_at_cap=at_cap, envelope_settled=at_cap == 0)
        rows.append(row)

    def envelope_cell(row: dict) -> str:
        if "envelope_best_epochs" not in row:
            return ""
        verdict = "stopped early" if row["envelope_settled"] else "**at the cap**"
        return f"{', '.join(map(str, row['envelope_best_epochs']))} of {row['envelope_epochs']}: {verdict}"

    lines = ["| batch | algo | overrides | 2nd-half mean | change over it | spread | still moving "
             "| envelope best epoch |", "|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['batch']} | {r['algo']} | {r['overrides']} | {r['second_half_mean']:.1f} | "
              f"{r['second_half_change']:+.1f} | {r['residual_spread']:.1f} | "
              f"{('**rising**' if r['second_half_change'] > 0 else '**falling**') if r['still_moving'] else 'no'} | "
              f"{envelope_cell(r)} |" for r in rows]
    fits = [r for r in rows if "envelope_best_epochs" in r]
    at_cap = sum(r["envelope_fits_at_cap"] for r in fits)
    lines += ["", "2nd-half mean: the seed-mean curve over the evaluations final_return averages; change: what a "
              "least-squares line through them rises or falls across that half; spread: the points' standard "
              "deviation around the line; still moving: |change| > 2 x spread and > 5 % of the mean. Envelope "
              "best epoch: each seed's best validation epoch of the upper-envelope fit, of the fit's epoch cap; "
              "stopped early: every best epoch is at least the patience (algo.envelope.patience) epochs before the "
              "cap; at the cap: a "
              "fit was still improving when the cap stopped it"
              + (f" ({at_cap} of {sum(len(r['envelope_best_epochs']) for r in fits)} fits here)." if fits else ".")]
    write_text_atomic(results / "curves.md", "\n".join(lines) + "\n")
    write_json_atomic(results / "curves.json", rows)
    return rows


#: published figures the paper-scale cell is read beside: raw returns of gym's -v2 Hopper, where these runs use
#: Gymnasium's -v5 (its simulator and rewards changed), so a level is a ballpark and the ordering is what compares
PAPER_ANCHORS = {
    "bail": ("2054 ± 158", "BAIL's authors, Hopper DDPG σ = 0.5 B1, 10^6 transitions (arXiv:1910.12179, Table 1)"),
    "bcq": ("curve only", "BCQ paper Fig. 2a, Hopper final buffer (arXiv:1812.02900): no table, so no number is "
                          "quoted; supp. C.2 of the BAIL paper says its BCQ runs agree with that figure"),
}
#: the paper's claims on this cell, each a comparison of two groups' IQM intervals: (claim, a, b, kind); kind
#: "above": a's interval lies above b's; "similar": the two intervals overlap (no difference shown)
PAPER_CLAIMS = [
    ("BAIL ≫ BC", "bail", "bc", "above"),
    ("BAIL above BCQ (BCQ at 10^5 of the paper's 10^6 updates)", "bail", "bcq", "above"),
    ("BAIL above BEAR (BEAR at 10^5 of the paper's 10^6 updates)", "bail", "bear", "above"),
    ("Progressive BAIL ≈ BAIL", "pbail", "bail", "similar"),
    ("MARWIL above BC", "marwil", "bc", "above"),
    ("MARWIL with V fitted first above BC", "marwil (value_warmup_updates=1000)", "bc", "above"),
]
#: fewer seeds than this and a claim's verdict is "pending"
MIN_SEEDS_FOR_VERDICT = 3


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


def interval_order(a: dict | None, b: dict | None) -> str:
    """Where group ``a`` lies against group ``b`` from their report rows (IQM and its 95 % bootstrap interval):
    "above" or "below" where the intervals are disjoint, "no difference shown" where they overlap, "pending" while
    either side has fewer than :data:`MIN_SEEDS_FOR_VERDICT` seeds. A row marked ``"reference": True`` is a fixed
    figure, not a group of runs (a behaviour policy's return: :func:`reference_row`), and needs no seeds."""
    seeds = [0 if row is None else row["seeds"] for row in (a, b) if row is None or not row.get("reference")]
    if seeds and min(seeds) < MIN_SEEDS_FOR_VERDICT:
        return f"pending (seeds so far: {' and '.join(map(str, seeds))}; {MIN_SEEDS_FOR_VERDICT} each needed)"
    lo_a, hi_a = a["final_return_iqm_ci_low"], a["final_return_iqm_ci_high"]
    lo_b, hi_b = b["final_return_iqm_ci_low"], b["final_return_iqm_ci_high"]
    if lo_a > hi_b:
        return "above: the IQM intervals are disjoint"
    if lo_b > hi_a:
        return "below: the IQM intervals are disjoint"
    return "no difference shown: the IQM intervals overlap"


def reference_row(value: float) -> dict:
    """A fixed figure (a behaviour policy's measured return) as a report row that :func:`interval_order` reads: its
    interval is the one point, and it needs no seeds."""
    return {"reference": True, "seeds": None, "final_return_iqm": float(value),
            "final_return_iqm_ci_low": float(value), "final_return_iqm_ci_high": float(value)}


def claim_verdict(a: dict | None, b: dict | None, kind: str) -> str:
    """The verdict on one claim from the two groups' report rows (:func:`interval_order`): an "above" claim holds
    where ``a``'s interval lies wholly above ``b``'s, a "below" claim where it lies wholly below, an "≈" claim
    ("similar") where the intervals overlap."""
    order = interval_order(a, b)
    if order.startswith("pending"):
        return order
    holds = order.startswith(kind) if kind in ("above", "below") else order.startswith("no difference")
    return f"{'holds' if holds else 'does not hold'} ({order})"


def same_recipe_comparisons(batches: list[dict], algos: list[str]) -> list[dict]:
    """Batches made by one recipe with another behaviour seed (``<exp>_b1``, ``<exp>_b2``, ...: the same env, agent
    and noise, ``batch.index`` apart), each set beside the recipe's first batch: how much of a score, and of a
    verdict, is the batch drawn rather than the algorithm. Per algorithm, where the later batch's IQM interval lies
    against the first's (:func:`interval_order`); per claim, the verdict on each batch and whether they agree."""
    by_recipe: dict[str, list[dict]] = {}
    for b in batches:
        by_recipe.setdefault(label_recipe(b["batch"]), []).append(b)
    out = []
    for recipe, group in by_recipe.items():
        first = group[0]
        for other in group[1:]:
            claims = []
            for i, claim in enumerate(first["claims"]):
                verdicts = [claim["verdict"], other["claims"][i]["verdict"]]
                heads = [v.split(" (")[0] for v in verdicts]
                reading = ("pending" if "pending" in heads else "the same verdict" if heads[0] == heads[1]
                           else "the verdicts differ")
                claims.append({"claim": claim["claim"], "verdicts": verdicts, "reading": reading})
            out.append({"recipe": recipe, "batches": [first["batch"], other["batch"]],
                        "algorithms": {a: interval_order(other["cells"].get(a), first["cells"].get(a))
                                       for a in algos},
                        "claims": claims})
    return out


def _same_recipe_lines(comparisons: list[dict], batches: list[dict]) -> list[str]:
    """The cross-batch report's "Same recipe, another behaviour seed" section, as Markdown lines."""
    meta = {b["batch"]: b["metadata"] or {} for b in batches}
    cells = {b["batch"]: b["cells"] for b in batches}
    lines = []
    for c in comparisons:
        first, other = c["batches"]
        data = "; ".join(f"{label}: data {_fmt(meta[label].get('episode_return_mean')) or 'pending'}, behaviour "
                         f"agent {_fmt(meta[label].get('behaviour_final_return_mean10')) or 'pending'}"
                         for label in c["batches"])
        lines += ["", f"**Same recipe, another behaviour seed: {first} and {other}.** One recipe ({c['recipe']}: env, "
                  f"behaviour agent, its noise and the batch's size), a behaviour seed apart (`batch.index`), so what "
                  f"differs between the two rows is the batch drawn, not the algorithm ({data}). Each algorithm's "
                  f"IQM [95 % CI] on both, and where {other}'s interval lies against {first}'s:", "",
                  f"| algorithm | {first} | {other} | {other} against {first} |", "|---|---|---|---|"]
        lines += [f"| {a} | {_iqm_cell(cells[first].get(a))} | {_iqm_cell(cells[other].get(a))} | "
                  f"{'pending' if order.startswith('pending') else order} |" for a, order in c["algorithms"].items()]
        lines += ["", f"| claim | {first} | {other} | reading |", "|---|---|---|---|"]
        lines += [f"| {k['claim']} | {k['verdicts'][0]} | {k['verdicts'][1]} | {k['reading']} |"
                  for k in c["claims"]]
    return lines


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
# the cross-batch report (``--study paper_batches``): the headline batch and PAPER_BATCHES side by side
# ---------------------------------------------------------------------------------------------------------------

#: the cross-batch report's columns, in the registry's order: the central cells of every batch, then the reference
#: points (shown once any batch has a run of them)
CROSS_BATCH_CENTRAL = tuple(a for a in ALGO_SCHEMAS if a in dict(PAPER_BATCH_CELLS))
CROSS_BATCH_EXTRA = tuple(a for a in ALGO_SCHEMAS if a in dict(PAPER_BATCH_EXTRA_CELLS))
#: the claims read on every batch: the paper cell's own (:data:`PAPER_CLAIMS`) whose groups every batch runs
CROSS_BATCH_CLAIMS = [c for c in PAPER_CLAIMS if (c[1], c[2]) in {("bail", "bc"), ("bail", "bcq"), ("pbail", "bail")}]
#: the probabilities of improvement over all batches: P(first > second)
CROSS_BATCH_PAIRS = [("bail", "bcq"), ("bail", "bc")]
#: bootstrap replications and numpy seed of every interval of the cross-batch report (the report's defaults)
CROSS_BATCH_REPS, CROSS_BATCH_SEED = 2_000, 0
#: how a final return is put on one scale across batches (:func:`normalised_return`)
NORMALISATION = ("min-max by the batch's own episodes: (final return - the batch's worst episode return) / (its "
                 "best - its worst), from the batch's metadata (episode_return_min, episode_return_max); 0 = the "
                 "batch's worst episode, 1 = its best")


def cross_batches() -> list[tuple[str, int, str, str]]:
    """The cross-batch report's rows, as ``(exp, batch index, the BAIL authors' published figure, the study whose
    results hold its runs)``: the headline batch (Hopper DDPG sigma=0.5 B1, ``results/paper_hopper``), then
    :data:`PAPER_BATCHES` (``results/paper_batches``)."""
    return [("hopper_ddpg05", 1, PAPER_ANCHORS["bail"][0], "paper_hopper"),
            *((exp, index, published, "paper_batches") for exp, index, published in PAPER_BATCHES)]


def normalised_return(final_return: float, metadata: dict) -> float:
    """A final return on its batch's min-max scale (:data:`NORMALISATION`): 0 = the batch's worst episode, 1 = its
    best. Min-max by the batch itself, not by reference scores: every batch's metadata has both bounds (the
    random-policy scores of ``results/reference_scores.json`` have no expert end yet), the four batches differ in
    env and behaviour quality, and the question BAIL asks is how much of the batch's best behaviour a policy
    recovers. The map is increasing, so within a batch it changes no ordering; it sets the weight of each batch in
    the aggregate."""
    low, high = float(metadata["episode_return_min"]), float(metadata["episode_return_max"])
    return (float(final_return) - low) / (high - low)


def kept_metadata(results: Path, label: str, recipe_hashes: set[str]) -> tuple[Path | None, dict | None]:
    """The batch's ``metadata.json`` kept in ``results/batches`` (``<label>-<recipe hash>.metadata.json``, copied
    there by :func:`keep_batch_metadata`): the one whose recipe hash the runs name, or the only one."""
    files = sorted((results / "batches").glob(f"{label}-*.metadata.json"))
    if recipe_hashes:
        files = [f for f in files if f.name[len(label) + 1:].split(".")[0] in recipe_hashes]
    if len(files) != 1:
        return None, None
    return files[0], json.loads(files[0].read_text())


def _train_cell(job: Job) -> tuple[str, str, int] | None:
    """``(batch label, algorithm, seed)`` of a training job without a variant tag, else ``None``."""
    if job.module != "torchrl_bail.train" or len(job.name.split("/")) != 3:
        return None
    named = job.overrides
    return batch_label(job), named["algo"], int(named["seed"])


def batch_cells(results: Path, jobs: list[Job], label: str, algos: tuple[str, ...] | None = None) -> dict[str, dict]:
    """``algo -> {"scheduled": seeds the study runs, "runs": kept run directories}`` of batch ``label``, for the
    columns ``algos`` (default: the cross-batch report's)."""
    algos = CROSS_BATCH_CENTRAL + CROSS_BATCH_EXTRA if algos is None else algos
    cells: dict[str, dict] = {}
    for job in jobs:
        cell = _train_cell(job)
        if cell is None or cell[0] != label or cell[1] not in algos:
            continue
        entry = cells.setdefault(cell[1], {"scheduled": 0, "runs": []})
        entry["scheduled"] += 1
        run = run_dir_of(job, results / "runs")
        if run is not None and (run / "summary.json").is_file():
            entry["runs"].append(run)
    return cells


def batch_rows(root: Path, jobs: list[Job], label: str, algos: tuple[str, ...]
               ) -> tuple[dict[str, dict], Path | None, dict | None, dict[str, dict]]:
    """Batch ``label`` of a study (``jobs``, its kept results in ``root``) as a report row reads it: its cells
    (:func:`batch_cells` over ``algos``), its kept metadata (:func:`kept_metadata`, the one whose recipe hash the
    runs name) with that file's path, and per algorithm its :func:`_cell_row` with the seeds scheduled (``{"seeds":
    0}`` and the seeds scheduled while no run is kept)."""
    cells = batch_cells(root, jobs, label, algos)
    hashes = set()
    for cell in cells.values():
        for run in cell["runs"]:
            path = json.loads((run / "summary.json").read_text()).get("batch_path") or ""
            if "-" in Path(path).name:
                hashes.add(Path(path).name.rsplit("-", 1)[1])
    meta_path, metadata = kept_metadata(root, label, hashes)
    rows = {}
    for algo, cell in cells.items():
        row = _cell_row(label, algo, cell["runs"], metadata) if cell["runs"] else {"seeds": 0}
        rows[algo] = {"scheduled": cell["scheduled"], **row}
    return cells, meta_path, metadata, rows


def _shown(path: Path) -> str:
    """A path relative to the repository where it lies inside it (the kept reports hold no machine's paths)."""
    path = Path(path).resolve()
    return str(path.relative_to(HERE.parent)) if path.is_relative_to(HERE.parent) else str(path)


def _cell_row(label: str, algo: str, runs: list[Path], metadata: dict | None) -> dict:
    """One algorithm's row on one batch: :func:`torchrl_bail.report.summarise` over its kept runs (mean, sample std,
    IQM with its 95 % stratified-bootstrap interval), its per-seed final returns in seed order and, where the
    batch's metadata is kept, their normalised values."""
    import math

    from torchrl_bail.report import Group, find_runs, summarise

    found = sorted(find_runs(runs), key=lambda r: int(r.summary["seed"]))
    row = summarise([Group((label, None), algo, (), algo, "", found)], reps=CROSS_BATCH_REPS,
                    seed=CROSS_BATCH_SEED)[0]
    row = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in row.items()
           if k not in ("label", "variant", "overrides", "recipe_hash", "batch")}
    row["run_dirs"] = [_shown(r.run_dir) for r in found]
    row["seed_ids"] = [int(r.summary["seed"]) for r in found]
    row["per_seed"] = [float(r.summary["final_return"]) for r in found]
    row["per_seed_normalised"] = (None if metadata is None else
                                  [normalised_return(x, metadata) for x in row["per_seed"]])
    return row


#: the learning-curve figures' window: each seed's evaluations averaged per this many updates (the actor-critics'
#: evaluation interval at the paper schedule, so every algorithm lands on one grid)
CURVE_WINDOW_UPDATES = 5000


def _windowed_curve(run: Path):
    """``(window ends, mean evaluation return per window)`` of a kept run, windows of :data:`CURVE_WINDOW_UPDATES`
    updates (the trainer logs each evaluation at its update count: the step of ``eval/return.csv``); ``None``
    without CSV evaluation logs."""
    from torchrl_bail.reports.plots import _read_scalar_csv, read_eval_curve

    if read_eval_curve(run) is None:
        return None
    returns = _read_scalar_csv(run / "logs" / "scalars" / "eval" / "return.csv")
    windows: dict[int, list[float]] = {}
    for step, value in returns.items():
        windows.setdefault(-(-step // CURVE_WINDOW_UPDATES), []).append(value)
    ends = sorted(windows)
    return np.array(ends) * CURVE_WINDOW_UPDATES, np.array([np.mean(windows[w]) for w in ends])


def plot_batch_curves(label: str, cells: dict[str, dict], metadata: dict | None, path: Path,
                      algos: tuple[str, ...] | None = None) -> Path | None:
    """``curves_<batch>.png``: every algorithm's evaluation return against updates on a linear axis (every schedule
    of the study ends between 5 x 10^4 and 1.25 x 10^5 updates, where its epochs of 10^6 samples run from 10 to 100),
    each seed averaged per :data:`CURVE_WINDOW_UPDATES` updates; the mean over seeds as a line, the lowest to the
    highest seed as a band; the batch's mean episode return dashed. ``algos``: the algorithms, in the order that
    gives each its colour (default: the cross-batch report's)."""
    from torchrl_bail.reports.plots import new_figure, read_eval_curve, save_figure

    lines = []
    for i, algo in enumerate(CROSS_BATCH_CENTRAL + CROSS_BATCH_EXTRA if algos is None else algos):
        runs = cells.get(algo, {}).get("runs", [])
        curves = [c for c in map(_windowed_curve, runs) if c is not None and len(c[0])]
        if not curves:
            continue
        n = min(len(x) for x, _ in curves)
        ys = np.stack([y[:n] for _, y in curves])
        epochs = max(read_eval_curve(r)[0][-1] for r in runs if read_eval_curve(r) is not None)
        lines.append((algo, f"C{i}", len(curves), f"{epochs:g}", curves[0][0][:n] / 1000, ys))
    if not lines:
        return None
    fig = new_figure(figsize=(8.0, 4.8), layout="constrained")
    ax = fig.subplots()
    for algo, color, n, epochs, x, ys in lines:
        ax.plot(x, ys.mean(0), color=color, linewidth=1.8,
                label=f"{algo} ({n} seed{'s' if n != 1 else ''}, {epochs} epochs)")
        ax.fill_between(x, ys.min(0), ys.max(0), color=color, alpha=0.12, linewidth=0)
    if metadata is not None:
        ax.axhline(metadata["episode_return_mean"], color="gray", linestyle="--", label="batch mean episode return")
    ax.set_title(f"{label}: evaluation return, mean over seeds (band: lowest to highest seed)")
    ax.set_xlabel(f"updates (thousands; each seed's evaluations averaged per {CURVE_WINDOW_UPDATES} updates)")
    ax.set_ylabel("evaluation return")
    ax.set_xlim(left=0)
    ax.grid(alpha=0.3)
    ax.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize="small")
    return save_figure(fig, path)


def _seeded_interval(scores, func) -> tuple[float, float, float]:
    """``(point, low, high)`` of rliable's stratified bootstrap over ``scores`` (a runs x batches matrix, or a pair
    of them), under the report's seeded numpy stream (:func:`torchrl_bail.report.numpy_seed`): seeds resampled within
    each batch, the batches themselves fixed. Kept beside each aggregate as ``seeds_only`` to show what the batches
    add: where every batch is perfectly separated it is a single point."""
    from rliable import library

    from torchrl_bail.report import numpy_seed

    with numpy_seed(CROSS_BATCH_SEED):
        point, interval = library.get_interval_estimates({"x": scores}, func, reps=CROSS_BATCH_REPS)
    return float(np.ravel(point["x"])[0]), float(np.ravel(interval["x"][0])[0]), float(np.ravel(interval["x"][1])[0])


#: how every aggregate over batches gets its interval (:func:`hierarchical_interval`), as the reports say it
HIERARCHICAL_BOOTSTRAP = ("a hierarchical bootstrap: each replication draws the batches with replacement, then the "
                          "seeds of each drawn batch with replacement (each algorithm's on its own), so the interval "
                          "covers which batches were drawn as well as which seeds")


def hierarchical_interval(matrices: list[np.ndarray], func, reps: int | None = None,
                          seed: int | None = None) -> tuple[float, float, float]:
    """``(point, low, high)`` of ``func(*matrices)`` (each a runs x batches matrix over the same batches, in the same
    column order; the runs may differ between matrices) with its 95 % percentile interval from
    :data:`HIERARCHICAL_BOOTSTRAP`: ``reps`` replications (default :data:`CROSS_BATCH_REPS`) of a numpy generator
    seeded with ``seed`` (default :data:`CROSS_BATCH_SEED`), so a rerun gives the same numbers. Each replication
    draws the batch columns with replacement, one draw shared by every matrix (a comparison stays within a batch),
    then resamples each drawn column's rows with replacement, for each matrix apart (a batch drawn twice gets two
    independent draws of its seeds). With one batch it is the bootstrap over seeds alone."""
    reps = CROSS_BATCH_REPS if reps is None else reps
    rng = np.random.default_rng(CROSS_BATCH_SEED if seed is None else seed)
    matrices = [np.asarray(m, dtype=float) for m in matrices]
    n_batches = matrices[0].shape[1]
    if any(m.shape[1] != n_batches for m in matrices):
        raise ValueError(f"every matrix needs the same batches (columns): {[m.shape for m in matrices]}")
    columns = np.arange(n_batches)
    stats = np.empty(reps)
    for i in range(reps):
        drawn = rng.integers(0, n_batches, n_batches)
        stats[i] = float(np.ravel(func(*(m[:, drawn][rng.integers(0, m.shape[0], (m.shape[0], n_batches)), columns]
                                         for m in matrices)))[0])
    low, high = np.percentile(stats, [2.5, 97.5])
    return float(np.ravel(func(*matrices))[0]), float(low), float(high)


def _matrix(batches: list[dict], algo: str, entered: list[str], key: str = "per_seed_normalised") -> np.ndarray:
    """``runs x batches`` of ``algo``'s final returns (``key``: normalised, or ``per_seed`` for the raw ones) on the
    batches ``entered``: each batch's first ``n`` seeds in seed order, ``n`` the fewest seeds any of them has (rliable
    needs a full matrix)."""
    columns = [b["cells"][algo][key] for b in batches if b["batch"] in entered]
    n = min(len(c) for c in columns)
    return np.array([c[:n] for c in columns]).T


def _against(row: dict, side: str) -> str:
    """The batches that go the other way of an across-batch reading (their own probability of improvement on
    ``side`` of 0.5), as a clause to append to it; "" when none does."""
    against = [batch for batch, p in row["per_batch"].items() if (p < 0.5 if side == "below" else p > 0.5)]
    return f", though {side} 0.5 on {', '.join(against)}" if against else ""


def _ready(batch: dict, algo: str, normalised: bool = True) -> bool:
    """Whether ``algo`` enters an aggregate on ``batch``: :data:`MIN_SEEDS_FOR_VERDICT` seeds there and, on the
    normalised scale, the batch's metadata kept."""
    cell = batch["cells"].get(algo)
    return ((batch["metadata"] is not None or not normalised) and cell is not None
            and cell.get("seeds", 0) >= MIN_SEEDS_FOR_VERDICT)


def aggregate_iqm(batches: list[dict], algo: str) -> dict | None:
    """``algo``'s IQM of normalised final returns over the batches where it has :data:`MIN_SEEDS_FOR_VERDICT` seeds,
    with its :func:`hierarchical_interval` (and, as ``seeds_only``, the interval over seeds alone); ``None`` where
    no batch is entered."""
    from rliable import metrics

    entered = [b["batch"] for b in batches if _ready(b, algo)]
    if not entered:
        return None
    m = _matrix(batches, algo, entered)
    point, low, high = hierarchical_interval([m], metrics.aggregate_iqm)
    seeds_only = _seeded_interval(m, lambda x: np.array([metrics.aggregate_iqm(x)]))[1:]
    return {"batches": entered, "n_batches": len(entered), "seeds_per_batch": int(m.shape[0]), "iqm": point,
            "ci_low": low, "ci_high": high, "seeds_only": list(seeds_only)}


def improvement(batches: list[dict], a: str, b: str, normalised: bool = True) -> dict:
    """P(``a`` > ``b``) (rliable's probability of improvement: a run of ``a`` ends above a run of ``b`` on the same
    batch, averaged over batches) over the batches where both have :data:`MIN_SEEDS_FOR_VERDICT` seeds, with its
    :func:`hierarchical_interval` (``seeds_only``: the interval over seeds alone) and each batch's own value
    (``per_batch``), and the reading: pending until every batch is entered, then above or below 0.5 where the whole
    interval is, naming the batches that go the other way. ``normalised``: read the normalised final returns (the
    same ordering within a batch; a batch without metadata enters nothing) or the raw ones."""
    from rliable import metrics

    key = "per_seed_normalised" if normalised else "per_seed"
    entered = [x["batch"] for x in batches if _ready(x, a, normalised) and _ready(x, b, normalised)]
    row = {"a": a, "b": b, "batches": entered, "n_batches": len(entered), "p": None, "ci_low": None,
           "ci_high": None, "seeds_only": None, "seeds": None, "per_batch": {}}
    if entered:
        x, y = _matrix(batches, a, entered, key), _matrix(batches, b, entered, key)
        row["p"], row["ci_low"], row["ci_high"] = hierarchical_interval([x, y], metrics.probability_of_improvement)
        row["seeds_only"] = list(_seeded_interval([x, y], metrics.probability_of_improvement)[1:])
        row["seeds"] = [int(x.shape[0]), int(y.shape[0])]
        row["per_batch"] = {batch: float(metrics.probability_of_improvement(x[:, [i]], y[:, [i]]))
                            for i, batch in enumerate(entered)}
    if len(entered) < len(batches):
        row["reading"] = (f"pending ({len(entered)} of {len(batches)} batches entered; the reading needs every batch "
                          f"with {MIN_SEEDS_FOR_VERDICT} seeds of both)")
    elif row["ci_low"] > 0.5:
        row["reading"] = f"{a} above {b} across batches (the interval lies above 0.5)" + _against(row, "below")
    elif row["ci_high"] < 0.5:
        row["reading"] = f"{a} below {b} across batches (the interval lies below 0.5)" + _against(row, "above")
    else:
        row["reading"] = "no difference shown (the interval contains 0.5)"
    return row


def cross_batch_aggregate(batches: list[dict]) -> dict:
    """Over all batches, on the normalised scale (:data:`NORMALISATION`): each algorithm's IQM with its 95 % interval
    over the batches where it has :data:`MIN_SEEDS_FOR_VERDICT` seeds (:func:`aggregate_iqm`), and each of
    :data:`CROSS_BATCH_PAIRS`'s probability of improvement over the batches where both have them
    (:func:`improvement`), with each batch's own value beside it. Every interval is :data:`HIERARCHICAL_BOOTSTRAP`'s
    (:func:`hierarchical_interval`): with four batches drawn, most of its width is which batches they were. A batch
    without kept metadata enters nothing. Unequal seeds: each batch gives its first ``n`` seeds, ``n`` the fewest of
    the batches entered (so 5-seed BAIL stays 5 where every batch has 5)."""
    iqm = {algo: row for algo in CROSS_BATCH_CENTRAL + CROSS_BATCH_EXTRA
           if (row := aggregate_iqm(batches, algo)) is not None}
    pairs = [improvement(batches, a, b) for a, b in CROSS_BATCH_PAIRS]
    return {"normalisation": NORMALISATION, "bootstrap": HIERARCHICAL_BOOTSTRAP, "iqm": iqm,
            "probability_of_improvement": pairs}


#: the markers that tell the batches apart in the aggregate figure, in :func:`cross_batches` order
BATCH_MARKERS = ("o", "s", "^", "D")


def plot_cross_batch_aggregate(batches: list[dict], aggregate: dict, path: Path) -> Path | None:
    """Saves :func:`cross_batch_aggregate_figure` to ``path``; ``None`` (nothing written) while it has nothing to
    show."""
    from torchrl_bail.reports.plots import save_figure

    fig = cross_batch_aggregate_figure(batches, aggregate)
    return None if fig is None else save_figure(fig, path)


def cross_batch_aggregate_figure(batches: list[dict], aggregate: dict):
    """The figure ``cross_batch_aggregate.png``: the aggregate of :func:`cross_batch_aggregate` with each batch
    beside it. Left, per algorithm, its IQM of the normalised final return over the batches entered with its 95 %
    interval (black), and on each batch where it has :data:`MIN_SEEDS_FOR_VERDICT` seeds the IQM of that batch's
    normalised final returns alone (a marker per batch); right, the same for each probability of improvement. Where
    the batches' markers fall on both sides of an aggregate, the batches disagree, and the interval (over batches and
    seeds: :func:`hierarchical_interval`) widens with it. ``None`` while no algorithm has entered a batch."""
    from rliable import metrics

    from torchrl_bail.reports.plots import new_figure

    algos = [a for a in CROSS_BATCH_CENTRAL + CROSS_BATCH_EXTRA if a in aggregate["iqm"]]
    pairs = [p for p in aggregate["probability_of_improvement"] if p["p"] is not None]
    if not algos:
        return None
    markers = {b["batch"]: BATCH_MARKERS[i % len(BATCH_MARKERS)] for i, b in enumerate(batches)}
    fig = new_figure(figsize=(10.0, 0.45 * max(len(algos), 4) + 1.6), layout="constrained")
    left, right = fig.subplots(1, 2, gridspec_kw={"width_ratios": [3, 2]})
    seen = set()

    def batch_point(ax, x: float, y: float, batch: str) -> None:
        ax.plot(x, y, linestyle="none", marker=markers[batch], markersize=6, markerfacecolor="none",
                color=f"C{list(markers).index(batch)}", label=None if batch in seen else batch)
        seen.add(batch)

    for y, algo in enumerate(algos):
        row = aggregate["iqm"][algo]
        left.errorbar(row["iqm"], y, xerr=[[row["iqm"] - row["ci_low"]], [row["ci_high"] - row["iqm"]]],
                      fmt="|", color="black", markersize=14, capsize=4, linewidth=2)
        for b in batches:
            if b["batch"] in row["batches"]:
                batch_point(left, float(metrics.aggregate_iqm(np.array(b["cells"][algo]["per_seed_normalised"]))),
                            y, b["batch"])
    left.set_yticks(range(len(algos)), algos)
    left.invert_yaxis()
    left.set_xlabel("normalised final return (0: the batch's worst episode, 1: its best)")
    left.set_title("IQM over the batches entered [95 % CI], and per batch", fontsize="medium")
    left.grid(axis="x", alpha=0.3)
    for y, p in enumerate(pairs):
        right.errorbar(p["p"], y, xerr=[[p["p"] - p["ci_low"]], [p["ci_high"] - p["p"]]], fmt="|", color="black",
                       markersize=14, capsize=4, linewidth=2)
        for batch, value in p["per_batch"].items():
            batch_point(right, value, y, batch)
    right.set_yticks(range(len(pairs)), [f"P({p['a']} > {p['b']})" for p in pairs])
    right.set_ylim(-0.5, max(len(pairs), 1) - 0.5)
    right.invert_yaxis()
    right.axvline(0.5, color="gray", linestyle="--", linewidth=1)
    right.set_xlim(-0.05, 1.05)
    right.set_xlabel("probability that a run of the first ends above a run of the second")
    right.set_title("Probability of improvement [95 % CI], and per batch", fontsize="medium")
    right.grid(axis="x", alpha=0.3)
    fig.legend(loc="outside lower center", ncol=len(seen), fontsize="small", title="batch (hollow markers)")
    fig.suptitle("Across batches: interval over batches and seeds (black), each batch on its own (markers)")
    return fig


def _fmt(x: float | None, digits: int = 1) -> str:
    return "" if x is None else f"{x:.{digits}f}"


def _mean_cell(cell: dict | None) -> str:
    if cell is None:
        return "not run"
    seeds, scheduled = cell.get("seeds", 0), cell["scheduled"]
    if seeds == 0:
        return f"pending (0 of {scheduled} seeds)"
    std = cell["final_return_std"]
    text = _fmt(cell["final_return_mean"]) + ("" if std is None else f" ± {_fmt(std)}")
    return text + (f" ({seeds} of {scheduled} seeds)" if seeds < scheduled else "")


def _iqm_cell(cell: dict | None) -> str:
    if cell is None:
        return "not run"
    seeds, scheduled = cell.get("seeds", 0), cell["scheduled"]
    if seeds < MIN_SEEDS_FOR_VERDICT:
        return f"pending ({seeds} of {scheduled} seeds)"
    text = (f"{_fmt(cell['final_return_iqm'])} [{_fmt(cell['final_return_iqm_ci_low'])}, "
            f"{_fmt(cell['final_return_iqm_ci_high'])}]")
    return text + (f" ({seeds} of {scheduled} seeds)" if seeds < scheduled else "")


def _iqm_table(batches: list[dict], algos: list[str], names: list[str] | None = None) -> list[str]:
    """A report's table of each batch's per-algorithm IQM interval (:func:`_iqm_cell`), headed by ``names`` (default:
    the algorithms' own), and its caption."""
    return ["| batch | " + " | ".join(names or algos) + " |", "|---|" + "---|" * len(algos),
            *(f"| {b['batch']} | " + " | ".join(_iqm_cell(b["cells"].get(a)) for a in algos) + " |" for b in batches),
            "", f"Interquartile mean of the final return over seeds [95 % stratified-bootstrap interval] (rliable, "
            f"{CROSS_BATCH_REPS} replications); pending below {MIN_SEEDS_FOR_VERDICT} seeds."]


def _bootstrap_sentence(n_batches: int) -> str:
    """What every interval over batches is, for the reports' text."""
    return (f"Intervals: 95 %, {HIERARCHICAL_BOOTSTRAP} ({CROSS_BATCH_REPS} replications, numpy seed "
            f"{CROSS_BATCH_SEED}, the same numbers on every rerun). With {n_batches} batches to draw from, these "
            "intervals are coarse. '[over seeds alone]': rliable's stratified bootstrap, the seeds drawn "
            "within each batch and the batches fixed, which cannot show batches that disagree.")


def _improvement_lines(pairs: list[dict], n_batches: int) -> list[str]:
    """The table of :func:`improvement` rows and what they mean, as Markdown lines."""
    lines = ["| comparison | batches entered | seeds (first, second) | probability of improvement [95 % CI] "
             "| [over seeds alone] | per batch | reading |", "|---|---|---|---|---|---|---|"]
    for p in pairs:
        entered = f"{', '.join(p['batches'])} ({len(p['batches'])} of {n_batches})" if p["batches"] else "none"
        value = "" if p["p"] is None else f"{_fmt(p['p'], 3)} [{_fmt(p['ci_low'], 3)}, {_fmt(p['ci_high'], 3)}]"
        alone = "" if p["seeds_only"] is None else f"[{_fmt(p['seeds_only'][0], 3)}, {_fmt(p['seeds_only'][1], 3)}]"
        seeds = "" if p["seeds"] is None else f"{p['seeds'][0]}, {p['seeds'][1]}"
        per_batch = ", ".join(f"{batch} {_fmt(v, 2)}" for batch, v in p["per_batch"].items())
        lines.append(f"| P({p['a']} > {p['b']}) | {entered} | {seeds} | {value} | {alone} | {per_batch} | "
                     f"{p['reading']} |")
    return lines + ["", "Probability of improvement (rliable): the chance that a run of the first algorithm ends above "
                    "a run of the second on the same batch, averaged over the batches entered; the reading needs all "
                    f"{n_batches} batches, and then says 'above' when the whole interval lies above 0.5, naming any "
                    "batch whose own value lies on the other side, and 'no difference shown' when the interval "
                    "contains 0.5. A batch where every run of one algorithm ends above every run of the other gives 1 "
                    "(or 0) whatever seeds are drawn, so over seeds alone batches that disagree that cleanly give a "
                    "one-point interval; drawing the batches too shows the disagreement as width. Read it with the "
                    "per-batch column."]


def _aggregate_lines(aggregate: dict, algos: list[str], n_batches: int, figure: Path | None) -> list[str]:
    """The cross-batch report's "Over all batches" section (:func:`cross_batch_aggregate`'s tables, and the figure
    of :func:`plot_cross_batch_aggregate` where there is one), as Markdown lines."""
    lines = [f"**Over all batches.** Normalisation: {NORMALISATION}. Min-max by the batch itself because every "
             "batch's metadata carries both bounds (the v5 reference scores have no expert end yet) and the four "
             "batches differ in env and behaviour quality; it changes no ordering within a batch. A batch enters "
             f"an algorithm's IQM when the algorithm has {MIN_SEEDS_FOR_VERDICT} seeds there, and a comparison "
             f"when both sides have; each batch gives its first n seeds (seed order), n the fewest of the batches "
             f"entered. {_bootstrap_sentence(n_batches)}", "",
             "| algorithm | batches entered | seeds per batch | IQM of normalised final return [95 % CI] "
             "| [over seeds alone] |", "|---|---|---|---|---|"]
    for algo in algos:
        row = aggregate["iqm"].get(algo)
        lines.append(f"| {algo} | pending (no batch with {MIN_SEEDS_FOR_VERDICT} seeds) |  |  |  |" if row is None else
                     f"| {algo} | {', '.join(row['batches'])} ({len(row['batches'])} of {n_batches}) | "
                     f"{row['seeds_per_batch']} | {_fmt(row['iqm'], 3)} [{_fmt(row['ci_low'], 3)}, "
                     f"{_fmt(row['ci_high'], 3)}] | [{_fmt(row['seeds_only'][0], 3)}, "
                     f"{_fmt(row['seeds_only'][1], 3)}] |")
    lines += ["", *_improvement_lines(aggregate["probability_of_improvement"], n_batches)]
    if figure is not None:
        lines += ["", "Both tables at a glance, with each batch on its own beside the aggregate: "
                  f"`{_shown(figure)}`."]
    return lines


def cross_batch_report(results: Path, headline: Path | None = None) -> dict:
    """``results/cross_batch.{md,json}`` and ``results/curves_<batch>.png``: the headline batch (its kept runs and
    metadata in ``headline``, default ``results/paper_hopper``) and :data:`PAPER_BATCHES` (in ``results``) side by
    side, Table-1 style — per batch its own mean episode return, its behaviour agent's final evaluation return
    (``behaviour_final_return_mean10``) and collection time (``collection_wall_time_s``) from its kept metadata, each
    algorithm's mean ± std and IQM [95 % CI] over seeds, the BAIL authors' published figure; a verdict per claim of
    :data:`CROSS_BATCH_CLAIMS` per batch (:func:`claim_verdict`); over all batches :func:`cross_batch_aggregate`.
    Reads kept runs only (no workdir, no batch); a cell without runs, a batch without metadata, reads "pending".
    Returns the JSON written."""
    from torchrl_bail.core.io import write_json_atomic, write_text_atomic

    headline = headline if headline is not None else HERE / "paper_hopper"
    sources = {"paper_hopper": (headline, paper_hopper_jobs()), "paper_batches": (results, paper_batches_jobs())}
    batches = []
    for exp, index, published, study in cross_batches():
        label = f"{exp}_b{index}"
        root, jobs = sources[study]
        cells, meta_path, metadata, rows = batch_rows(root, jobs, label, CROSS_BATCH_CENTRAL + CROSS_BATCH_EXTRA)
        claims = [{"claim": claim, "a": a, "b": b, "verdict": claim_verdict(rows.get(a), rows.get(b), kind)}
                  for claim, a, b, kind in CROSS_BATCH_CLAIMS]
        complete = all(rows.get(a, {}).get("seeds", 0) >= rows[a]["scheduled"] for a in CROSS_BATCH_CENTRAL
                       if a in rows) and metadata is not None
        figure = plot_batch_curves(label, cells, metadata, results / f"curves_{label}.png",
                                   CROSS_BATCH_CENTRAL + CROSS_BATCH_EXTRA)
        keys = ("episode_return_mean", "episode_return_min", "episode_return_max", "behaviour_final_return_mean10",
                "collection_wall_time_s", "collection_timed_from_step", "num_transitions", "num_episodes", "env_id",
                "recipe_hash")
        remakes = [] if meta_path is None or not remakes_file(meta_path).is_file() else [
            {k: r.get(k) for k in ("created_at", "collection_wall_time_s", "collection_timed_from_step")}
            for r in json.loads(remakes_file(meta_path).read_text())["remakes"]]
        batches.append({
            "batch": label, "results": _shown(root), "published_bail": published, "complete": complete,
            "metadata_file": None if meta_path is None else _shown(meta_path),
            "metadata": None if metadata is None else {k: metadata.get(k) for k in keys}, "remakes": remakes,
            "cells": rows, "claims": claims, "figure": None if figure is None else figure.name})
    aggregate = cross_batch_aggregate(batches)
    aggregate_figure = plot_cross_batch_aggregate(batches, aggregate, results / "cross_batch_aggregate.png")
    across = []
    for claim, *_ in CROSS_BATCH_CLAIMS:
        verdicts = [next(c["verdict"] for c in b["claims"] if c["claim"] == claim) for b in batches]
        across.append({"claim": claim, **{k: sum(v.startswith(k + " ") or v == k for v in verdicts)
                                          for k in ("holds", "does not hold", "pending")}})
    done = [b["batch"] for b in batches if b["complete"]]
    status = ("Batches complete (every central cell at its seeds: "
              + ", ".join(f"{a} x {dict(PAPER_BATCH_CELLS)[a]}" for a in CROSS_BATCH_CENTRAL)
              + f"; the batch's metadata kept): {len(done)} of {len(batches)}"
              + (f" ({', '.join(done)})" if done else "") + ". "
              + ("The cross-batch reading is pending until every batch is complete."
                 if len(done) < len(batches) else "Every batch is complete."))
    shown_extra = [a for a in CROSS_BATCH_EXTRA if any(b["cells"].get(a, {}).get("seeds") for b in batches)]
    algos = [*CROSS_BATCH_CENTRAL, *shown_extra]
    same_recipe = same_recipe_comparisons(batches, algos)
    out = {"status": status, "complete_batches": done, "min_seeds_for_verdict": MIN_SEEDS_FOR_VERDICT,
           "batches": batches, "claims_across_batches": across, "same_recipe": same_recipe, "aggregate": aggregate,
           "aggregate_figure": None if aggregate_figure is None else aggregate_figure.name,
           "bootstrap": {"reps": CROSS_BATCH_REPS, "seed": CROSS_BATCH_SEED}}

    def meta(b, key, fmt):
        return "pending" if b["metadata"] is None or b["metadata"].get(key) is None else fmt(b["metadata"][key])

    def collection_time(b) -> str:  # a part of a resumed collection may not have been timed
        timed_from = (b["metadata"] or {}).get("collection_timed_from_step")
        again = [f"{r['collection_wall_time_s'] / 3600:.1f} h" for r in b["remakes"]
                 if r["collection_wall_time_s"] is not None and not r["collection_timed_from_step"]]
        return (meta(b, "collection_wall_time_s", lambda s: f"{s / 3600:.1f} h")
                + (f" (env steps {timed_from:,} on)" if timed_from else "")
                + (f"; made again: {', '.join(again)}" if again else ""))

    lines = [status, "",
             "| batch | data: mean episode return | behaviour agent's final return | collection time | "
             + " | ".join(algos) + " | published BAIL (gym -v2) |", "|---|---|---|---|" + "---|" * len(algos) + "---|"]
    for b in batches:
        lines.append(f"| {b['batch']} | {meta(b, 'episode_return_mean', _fmt)} | "
                     f"{meta(b, 'behaviour_final_return_mean10', _fmt)} | "
                     f"{collection_time(b)} | "
                     + " | ".join(_mean_cell(b["cells"].get(a)) for a in algos) + f" | {b['published_bail']} |")
    lines += ["", "Final return (the mean of a run's last evaluations), mean ± sample std over seeds. Data: the "
              "batch's mean episode return; behaviour agent's final return: the mean of its last 10 evaluations as "
              "collection ended; collection time: wall time of the 10^6-step collection, summed over its parts "
              "when it was resumed from its checkpoint (\"env steps N on\": an older version's checkpoint, "
              "which kept no time, held the steps before N) (all from the batch's kept metadata.json); made again: the "
              "time of each later collection of the same batch from scratch, its cache lost, that made the same data "
              "to every digit (its remakes.json). "
              "Published BAIL: the authors' figures, mean ± std over seeds, on gym's -v2 "
              "envs — for the three added batches from their repository's README table, for hopper_ddpg05_b1 the "
              "paper's Table 1. These runs use Gymnasium's -v5 (simulator and rewards changed), so the levels "
              "differ and the ordering of the algorithms is what compares.", "", *_iqm_table(batches, algos), "",
              "| batch | " + " | ".join(c[0] for c in CROSS_BATCH_CLAIMS) + " |",
              "|---|" + "---|" * len(CROSS_BATCH_CLAIMS)]
    lines += [f"| {b['batch']} | " + " | ".join(c["verdict"] for c in b["claims"]) + " |" for b in batches]
    lines.append("| across batches | " + " | ".join(
        f"holds on {c['holds']}, does not hold on {c['does not hold']}, pending on {c['pending']} of {len(batches)}"
        for c in across) + " |")
    lines += ["", f"A verdict needs {MIN_SEEDS_FOR_VERDICT} seeds on both sides (the paper cell's rule: 'holds' for "
              "an 'above' claim means the first group's IQM interval lies wholly above the second's; for ≈ that the "
              "intervals overlap, no difference shown, which is not proof of equality).",
              *_same_recipe_lines(same_recipe, batches), "",
              *_aggregate_lines(aggregate, algos, len(batches), aggregate_figure)]
    figures = ", ".join(f"`{_shown(results / b['figure'])}`" for b in batches if b["figure"]) or "none yet"
    lines += ["", f"Learning curves, one figure per batch (updates on a linear axis, each seed's "
              f"evaluations averaged per {CURVE_WINDOW_UPDATES} updates; the mean over seeds, a band from the lowest "
              f"to the highest seed): {figures}."]
    text = "\n".join(lines) + "\n"
    write_text_atomic(results / "cross_batch.md", text)
    write_json_atomic(results / "cross_batch.json", out)
    return out


# ---------------------------------------------------------------------------------------------------------------
# the execution-batch report (``--study paper_exec``): supp. Table 2's rows at the paper's scale
# ---------------------------------------------------------------------------------------------------------------

#: supp. Table 2, arXiv:1910.12179: the authors' final returns on the 40 SAC execution batches (gym -v2 envs, mean ±
#: std over seeds), as ``(env, kind, batch index, *cells)``, the cells in :data:`PAPER_TABLE2_COLUMNS`' order (the
#: table's own); kinds as this package names the batches: med_det = M σ = 0, med_stoch = M σ = σ(s), opt_det = O
#: σ = 0, opt_stoch = O σ = σ(s) (:data:`EXEC_KINDS`)
PAPER_TABLE2_COLUMNS = ("bail", "bcq", "bear", "bc", "marwil")
_PAPER_TABLE2_ROWS = [
    ("hopper", "med_det", 1, (1026, 0), (901, 132), (4, 1), (1026, 0), (1026, 0)),
    ("hopper", "med_det", 2, (696, 233), (805, 312), (19, 23), (977, 0), (977, 1)),
    ("walker", "med_det", 1, (437, 20), (525, 45), (380, 194), (444, 16), (439, 17)),
    ("walker", "med_det", 2, (500, 12), (554, 29), (546, 28), (489, 15), (504, 4)),
    ("halfcheetah", "med_det", 1, (4057, 69), (4255, 150), (4470, 96), (4032, 72), (4073, 55)),
    ("halfcheetah", "med_det", 2, (4013, 12), (4438, 25), (4395, 31), (3998, 4), (3999, 6)),
    ("ant", "med_det", 1, (753, 9), (996, 52), (734, 43), (730, 7), (732, 11)),
    ("ant", "med_det", 2, (738, 4), (994, 12), (988, 30), (708, 11), (725, 7)),
    ("humanoid", "med_det", 1, (4313, 139), (3108, 510), (0, 0), (4507, 481), (4521, 156)),
    ("humanoid", "med_det", 2, (4053, 252), (2906, 226), (0, 0), (3994, 530), (3940, 165)),
    ("hopper", "med_stoch", 1, (375, 52), (881, 155), (0, 0), (1026, 0), (1026, 0)),
    ("hopper", "med_stoch", 2, (254, 102), (961, 25), (3, 7), (977, 0), (977, 0)),
    ("walker", "med_stoch", 1, (384, 21), (399, 21), (507, 7), (369, 10), (359, 15)),
    ("walker", "med_stoch", 2, (512, 24), (517, 19), (515, 30), (527, 12), (532, 5)),
    ("halfcheetah", "med_stoch", 1, (4744, 19), (5500, 12), (5443, 21), (4415, 25), (4439, 59)),
    ("halfcheetah", "med_stoch", 2, (4123, 19), (4712, 40), (4824, 51), (3928, 18), (3936, 18)),
    ("ant", "med_stoch", 1, (790, 9), (1068, 12), (1161, 32), (775, 7), (774, 15)),
    ("ant", "med_stoch", 2, (781, 6), (1089, 29), (1150, 18), (768, 5), (761, 6)),
    ("humanoid", "med_stoch", 1, (1375, 387), (489, 87), (0, 0), (1947, 901), (1963, 264)),
    ("humanoid", "med_stoch", 2, (1309, 372), (816, 177), (0, 0), (3021, 1042), (2976, 241)),
    ("hopper", "opt_det", 1, (2602, 5), (1976, 383), (1904, 321), (2594, 8), (2603, 4)),
    ("hopper", "opt_det", 2, (3046, 34), (3014, 47), (2202, 410), (3071, 10), (3050, 22)),
    ("walker", "opt_det", 1, (2735, 26), (2409, 235), (877, 1077), (2646, 133), (2691, 121)),
    ("walker", "opt_det", 2, (3019, 6), (3019, 45), (0, 0), (3014, 5), (3013, 5)),
    ("halfcheetah", "opt_det", 1, (11265, 243), (10405, 275), (1755, 1142), (11674, 90), (11661, 49)),
    ("halfcheetah", "opt_det", 2, (11360, 265), (10792, 209), (1139, 960), (11797, 29), (11691, 96)),
    ("ant", "opt_det", 1, (4901, 65), (4646, 179), (1756, 2151), (4881, 74), (4933, 74)),
    ("ant", "opt_det", 2, (4975, 108), (4734, 100), (0, 0), (5041, 29), (4974, 52)),
    ("humanoid", "opt_det", 1, (4872, 895), (4884, 641), (0, 0), (5462, 124), (5503, 1)),
    ("humanoid", "opt_det", 2, (5320, 125), (5362, 54), (0, 0), (5413, 64), (5413, 29)),
    ("hopper", "opt_stoch", 1, (2359, 153), (2650, 99), (1962, 300), (1952, 85), (2012, 101)),
    ("hopper", "opt_stoch", 2, (2035, 217), (1678, 113), (1461, 75), (2063, 95), (2092, 100)),
    ("walker", "opt_stoch", 1, (2834, 120), (3386, 196), (3278, 128), (2024, 131), (1987, 114)),
    ("walker", "opt_stoch", 2, (3200, 16), (3375, 12), (2100, 1715), (3091, 15), (3090, 10)),
    ("halfcheetah", "opt_stoch", 1, (10258, 1255), (10928, 215), (694, 651), (11659, 75), (11663, 44)),
    ("halfcheetah", "opt_stoch", 2, (10882, 634), (11755, 97), (1470, 1211), (11871, 57), (11819, 78)),
    ("ant", "opt_stoch", 1, (4981, 91), (4878, 117), (3462, 1740), (5000, 79), (4992, 86)),
    ("ant", "opt_stoch", 2, (5067, 83), (5054, 157), (0, 0), (5079, 55), (5124, 47)),
    ("humanoid", "opt_stoch", 1, (2129, 381), (1715, 637), (0, 0), (3514, 1195), (3180, 503)),
    ("humanoid", "opt_stoch", 2, (4328, 569), (1970, 512), (0, 0), (4875, 885), (4772, 272)),
]
PAPER_TABLE2 = {(env, kind, index): dict(zip(PAPER_TABLE2_COLUMNS, cells, strict=True))
                for env, kind, index, *cells in _PAPER_TABLE2_ROWS}
#: the BAIL authors' BAIL on the SAC training batches of this study (their repository's README table, the paper's
#: Table 1 BAIL column; gym -v2, mean ± std over seeds); no other algorithm's figure on these batches is published
#: where this project could read it
PAPER_SAC_BAIL = {("hopper", "sac", 1): {"bail": (3296, 105)}, ("walker", "sac", 1): {"bail": (2455, 211)}}
#: each kind of :data:`PAPER_EXEC_KINDS` as the paper's tables name its rows
EXEC_KINDS = {"sac": "SAC training batch (Table 1)", "med_det": "M σ = 0", "med_stoch": "M σ = σ(s)",
              "opt_det": "O σ = 0", "opt_stoch": "O σ = σ(s)"}
#: the report's columns: the study's cells (:data:`PAPER_EXEC_CELLS`) in the paper's order, then BEAR (shown once a
#: run of it is kept)
EXEC_CENTRAL = tuple(a for a in PAPER_TABLE2_COLUMNS if a in dict(PAPER_EXEC_CELLS))
EXEC_ALGOS = (*EXEC_CENTRAL, *(a for a in PAPER_TABLE2_COLUMNS if a not in EXEC_CENTRAL))
#: how the report names each algorithm in a claim
ALGO_NAMES = {"bail": "BAIL", "bcq": "BCQ", "bc": "BC", "marwil": "MARWIL", "bear": "BEAR"}
#: the probabilities of improvement over every execution batch: P(first > second)
EXEC_PAIRS = [("bail", "bcq"), ("bc", "bail"), ("marwil", "bc")]
#: supp. E's reading of Table 2: the algorithms with the most wins
PAPER_MOST_WINS = ("bc", "marwil")


def exec_batches() -> list[tuple[str, str]]:
    """The report's rows as ``(env, kind)``: per env of :data:`PAPER_EXEC_ENVS`, its SAC training batch, then its
    execution batches in :data:`PAPER_EXEC_KINDS`' order (all B1)."""
    return [(env, kind) for env in PAPER_EXEC_ENVS for kind in PAPER_EXEC_KINDS]


def _paper_figure(pair: tuple[int, int] | None) -> str:
    return "" if pair is None else f"{pair[0]} ± {pair[1]}"


def _behaviour_return(batch: dict) -> float | None:
    """The return of a batch's behaviour policy from its kept metadata: an execution batch's ``behaviour_return``
    (the SAC policy it runs, as the SAC run evaluated it), the SAC training batch's ``behaviour_final_eval_return``
    (the SAC run's final evaluation: the batch is that whole run); ``None`` while no metadata is kept."""
    meta = batch["metadata"] or {}
    return meta.get("behaviour_final_eval_return" if batch["kind"] == "sac" else "behaviour_return")


def _gap(a: dict | None, b: dict | None) -> float | None:
    """``a``'s IQM against ``b``'s, in % of ``b``'s (``None`` while either has too few seeds)."""
    if a is None or b is None or (not a.get("reference") and a.get("seeds", 0) < MIN_SEEDS_FOR_VERDICT) or (
            not b.get("reference") and b.get("seeds", 0) < MIN_SEEDS_FOR_VERDICT) or not b["final_return_iqm"]:
        return None
    return 100.0 * (a["final_return_iqm"] - b["final_return_iqm"]) / abs(b["final_return_iqm"])


def exec_claims(batches: list[dict]) -> list[dict]:
    """supp. Table 2's claims (and Table 1's on the SAC training batches), each read on the batches it concerns by
    the paper cell's rule (:func:`claim_verdict`, :data:`MIN_SEEDS_FOR_VERDICT` seeds a side): on each O σ = 0 batch,
    BAIL, BC and MARWIL ≈ the behaviour policy (its return a fixed figure, :func:`reference_row`: the claim holds
    where the IQM interval contains it); on Hopper M σ = σ(s), BAIL below BC; on every execution batch MARWIL ≈ BC;
    on each SAC training batch BAIL ≫ BC. Each with the first side's IQM against the second's (``gap``, %)."""
    claims = []

    def claim(batch, text, a, b, kind):
        verdict = ("pending (the batch's metadata, with its behaviour policy's return, is not kept yet)"
                   if b is None and text.endswith("behaviour policy") else claim_verdict(a, b, kind))
        claims.append({"batch": batch["batch"], "claim": text, "verdict": verdict, "gap": _gap(a, b)})

    for batch in batches:
        cells = batch["cells"]
        if batch["kind"] == "opt_det":
            behaviour = _behaviour_return(batch)
            for algo in ("bail", "bc", "marwil"):
                claim(batch, f"{ALGO_NAMES[algo]} ≈ the behaviour policy", cells.get(algo),
                      None if behaviour is None else reference_row(behaviour), "similar")
        if (batch["env"], batch["kind"]) == ("hopper", "med_stoch"):
            claim(batch, "BAIL below BC", cells.get("bail"), cells.get("bc"), "below")
        if batch["kind"] == "sac":
            claim(batch, "BAIL ≫ BC (Table 1)", cells.get("bail"), cells.get("bc"), "above")
        else:
            claim(batch, "MARWIL ≈ BC", cells.get("marwil"), cells.get("bc"), "similar")
    return claims


def _ready_cells(cells: dict[str, dict]) -> dict[str, dict] | None:
    """The cells of an execution batch that a ranking reads, those with :data:`MIN_SEEDS_FOR_VERDICT` seeds (BEAR
    where it has them), or ``None`` while any of :data:`EXEC_CENTRAL` has fewer."""
    ready = {a: cells[a] for a in EXEC_ALGOS if cells.get(a, {}).get("seeds", 0) >= MIN_SEEDS_FOR_VERDICT}
    return ready if all(a in ready for a in EXEC_CENTRAL) else None


def row_winners(cells: dict[str, dict]) -> list[str] | None:
    """The algorithms that win an execution batch: the best IQM and every one whose IQM interval overlaps the best's
    (:func:`interval_order`: a tie, no difference shown); ``None`` while the batch is not ready
    (:func:`_ready_cells`)."""
    ready = _ready_cells(cells)
    if ready is None:
        return None
    best = max(ready, key=lambda a: ready[a]["final_return_iqm"])
    return [a for a in ready if a == best or not interval_order(ready[a], ready[best]).startswith("below")]


def paper_winners(paper: dict[str, tuple[int, int]], algos) -> list[str]:
    """The algorithms of ``algos`` with the best mean of a supp. Table 2 row (ties: equal means)."""
    best = max(paper[a][0] for a in algos)
    return [a for a in algos if paper[a][0] == best]


def _sign(x: float) -> int:
    return (x > 0) - (x < 0)


def row_ordering(cells: dict[str, dict], paper: dict[str, tuple[int, int]]) -> dict:
    """How an execution batch orders its algorithms (IQM) against supp. Table 2's row (means): Kendall's tau-b over
    the algorithms with :data:`MIN_SEEDS_FOR_VERDICT` seeds (``scipy.stats.kendalltau``; ``None`` where one side ties
    them all), and the row's pairs counted concordant, discordant and tied (either side equal); pending while the
    batch is not ready (:func:`_ready_cells`)."""
    from scipy.stats import kendalltau

    ready = _ready_cells(cells)
    if ready is None:
        return {"algorithms": [], "tau": None, "pairs": None, "reading": "pending"}
    algos = list(ready)
    ours = [ready[a]["final_return_iqm"] for a in algos]
    theirs = [paper[a][0] for a in algos]
    tau = float(kendalltau(ours, theirs).statistic)
    tau = None if not np.isfinite(tau) else tau
    signs = [_sign(ours[i] - ours[j]) * _sign(theirs[i] - theirs[j])
             for i in range(len(algos)) for j in range(i + 1, len(algos))]
    pairs = {"concordant": signs.count(1), "discordant": signs.count(-1), "tied": signs.count(0)}
    reading = ("undefined (one side ties every algorithm)" if tau is None else "the same order" if tau == 1.0
               else "agrees in part" if tau > 0 else "does not agree")
    return {"algorithms": algos, "ours": sorted(algos, key=lambda a: -ready[a]["final_return_iqm"]),
            "paper": sorted(algos, key=lambda a: -paper[a][0]), "tau": tau, "pairs": pairs, "reading": reading}


def exec_rankings(batches: list[dict]) -> dict:
    """Over the execution batches: each one's winners (:func:`row_winners`) beside the paper's on its supp. Table 2
    row among the same algorithms (:func:`paper_winners`) and the two orderings (:func:`row_ordering`); the count of
    rows each algorithm wins, ours, the paper's on the same rows and the paper's over its 40 rows (all five
    algorithms); the verdict on supp. E's "BC and MARWIL win the most rows" (holds where the most wins go to them
    alone); the orderings over all rows (Kendall's tau-a over every row's pairs pooled: (concordant - discordant) /
    pairs); and the probabilities of improvement of :data:`EXEC_PAIRS` over the batches (:func:`improvement`, raw
    returns) with the verdict on "BAIL ≈ BCQ on average" (holds where P(BAIL > BCQ)'s interval contains 0.5)."""
    rows = []
    for batch in batches:
        winners = row_winners(batch["cells"])
        ordering = row_ordering(batch["cells"], batch["paper"])
        rows.append({"batch": batch["batch"], "winners": winners,
                     "paper_winners": None if winners is None else paper_winners(batch["paper"],
                                                                                 ordering["algorithms"]),
                     "ordering": ordering})
    ready = [r for r in rows if r["winners"] is not None]
    wins = {a: {"ours": sum(a in r["winners"] for r in ready), "paper_same_rows": sum(a in r["paper_winners"]
                                                                                      for r in ready),
                "paper_all_rows": sum(a in paper_winners(p, PAPER_TABLE2_COLUMNS) for p in PAPER_TABLE2.values())}
            for a in EXEC_ALGOS}
    if len(ready) < len(rows):
        most, verdict = [], f"pending ({len(ready)} of {len(rows)} execution batches ranked)"
    else:
        top = max(w["ours"] for w in wins.values())
        most = [a for a, w in wins.items() if w["ours"] == top]
        holds = set(most) <= set(PAPER_MOST_WINS)
        verdict = (f"{'holds' if holds else 'does not hold'} (the most wins, {top} of {len(rows)}: "
                   f"{', '.join(ALGO_NAMES[a] for a in most)})")
    pooled = {k: sum(r["ordering"]["pairs"][k] for r in rows if r["ordering"]["pairs"] is not None)
              for k in ("concordant", "discordant", "tied")}
    n_pairs = sum(pooled.values())
    pairs = [improvement(batches, a, b, normalised=False) for a, b in EXEC_PAIRS]
    average = pairs[0]
    if average["reading"].startswith("pending"):
        average_verdict = average["reading"]
    else:
        holds = average["reading"].startswith("no difference shown")
        average_verdict = (f"{'holds' if holds else 'does not hold'} (P(BAIL > BCQ) = {_fmt(average['p'], 2)} "
                           f"[{_fmt(average['ci_low'], 2)}, {_fmt(average['ci_high'], 2)}]: {average['reading']})")
    same_rows = [(b["env"], b["kind"], 1) for b in batches]
    paper_means = {a: {"same_rows": float(np.mean([PAPER_TABLE2[k][a][0] for k in same_rows])),
                       "all_rows": float(np.mean([p[a][0] for p in PAPER_TABLE2.values()]))}
                   for a in PAPER_TABLE2_COLUMNS}
    return {"rows": rows, "ranked": len(ready), "wins": wins, "most_wins": most, "most_wins_verdict": verdict,
            "ordering": {"rows": sum(r["ordering"]["tau"] is not None for r in rows),
                         "same_order": sum(r["ordering"]["tau"] == 1.0 for r in rows), **pooled,
                         "tau_pooled": None if not n_pairs else (pooled["concordant"] - pooled["discordant"])
                         / n_pairs},
            "probability_of_improvement": pairs, "average_verdict": average_verdict, "paper_means": paper_means}


#: the keys of an execution batch's metadata that the report keeps (no machine's paths)
EXEC_METADATA_KEYS = ("episode_return_mean", "episode_return_std", "episode_return_min", "episode_return_max",
                      "num_episodes", "num_transitions", "behaviour_return", "behaviour_final_eval_return",
                      "collection_wall_time_s", "env_id", "recipe_hash")
EXEC_POLICY_KEYS = ("which", "stochastic", "eval_step", "eval_return_mean", "eval_return_std", "mediocre_threshold",
                    "threshold_reached")


def _exec_row_cells(batch: dict, algos: list[str]) -> list[str]:
    """A row's mean ± std cells with the paper's figure beside each (none published: the cell alone)."""
    out = []
    for a in algos:
        figure = _paper_figure(batch["paper"].get(a))
        out.append(_mean_cell(batch["cells"].get(a)) + (f"; paper {figure}" if figure else ""))
    return out


def _behaviour_cell(batch: dict) -> str:
    value = _behaviour_return(batch)
    if value is None:
        return "pending"
    policy = (batch["metadata"] or {}).get("behaviour_policy") or {}
    note = ("SAC run's final evaluation" if batch["kind"] == "sac" else
            f"{policy.get('which', '')} policy at step {policy['eval_step']:,}" if policy.get("eval_step") else "")
    if policy.get("threshold_reached") is False:
        note += f"; threshold {_fmt(policy.get('mediocre_threshold'), 0)} not reached: the best evaluation"
    return _fmt(value) + (f" ({note})" if note else "")


def sac_run_summary(env: str, metadata: dict | None) -> dict | None:
    """What the report says of an env's SAC behaviour run, from its ``sac`` training batch's kept metadata (the batch is
    the run's first 10^6 transitions and its metadata carries the run's evaluations): its pace (env steps and updates
    per second, evaluations included in the first), its learning curve, the first evaluation at or above the env's
    mediocre threshold (``conf/env/<env>.yaml``: the mediocre behaviour policy of the ``med_*`` batches) and its final
    evaluation (the optimal policy of the ``opt_*`` batches); ``None`` until the metadata is kept."""
    if metadata is None or not metadata.get("evaluations"):
        return None
    threshold = float(OmegaConf.load(HERE.parent / "conf" / "env" / f"{env}.yaml").mediocre_threshold)
    curve = [(int(e["step"]), float(e["return_mean"])) for e in metadata["evaluations"]]
    crossed = next(((step, ret) for step, ret in curve if ret >= threshold), None)
    return {"env": env, "env_steps": metadata.get("sac_run_train_steps"),
            "gradient_steps": metadata.get("gradient_steps"),
            "env_steps_per_s": metadata.get("env_steps_per_s"), "updates_per_s": metadata.get("updates_per_s"),
            "resumed_from_step": metadata.get("resumed_from_step"), "mediocre_threshold": threshold,
            "crossed_at_step": None if crossed is None else crossed[0],
            "crossed_with_return": None if crossed is None else crossed[1],
            "final_eval_return": metadata.get("behaviour_final_eval_return"),
            "best_eval_return": max(ret for _, ret in curve), "curve": curve}


def plot_sac_runs(runs: list[dict], path: Path) -> Path | None:
    """One figure of the SAC behaviour runs (:func:`sac_run_summary`): each env's evaluation return against env steps,
    its mediocre threshold as a dashed line and the evaluation that crossed it marked; ``None`` without a run."""
    if not runs:
        return None
    from torchrl_bail.reports.plots import new_figure, save_figure

    fig = new_figure(figsize=(7.0, 4.2), layout="constrained")
    ax = fig.subplots()
    for run in runs:
        steps, returns = zip(*run["curve"], strict=True)
        label = f"{run['env']} (final {run['final_eval_return']:.0f})"
        (line,) = ax.plot(np.asarray(steps) / 1e6, returns, label=label)
        ax.axhline(run["mediocre_threshold"], color=line.get_color(), linestyle="--", linewidth=0.8)
        if run["crossed_at_step"] is not None:
            ax.plot([run["crossed_at_step"] / 1e6], [run["crossed_with_return"]], "o", color=line.get_color())
    ax.set_xlabel("env steps (millions)")
    ax.set_ylabel("evaluation return (10 deterministic episodes)")
    ax.set_title("SAC behaviour runs: dashed, the mediocre threshold; dot, the mediocre policy")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    return save_figure(fig, path)


def _sac_run_lines(runs: list[dict], figure: Path | None) -> list[str]:
    """The Table 2 report's SAC-runs paragraph and table (:func:`sac_run_summary`)."""
    lines = ["", "The SAC behaviour runs (one per env, B1: the training batch is the run's first 10^6 transitions, the "
             "execution batches run its mediocre and final policies), from each SAC batch's kept metadata:", "",
             "| env | env steps | env steps/s | updates/s | mediocre threshold | first evaluation at or above it "
             "(step: return) | final evaluation | best evaluation |", "|---|---|---|---|---|---|---|---|"]
    for r in runs:
        crossed = ("never" if r["crossed_at_step"] is None
                   else f"{r['crossed_at_step']:,}: {r['crossed_with_return']:.1f}")
        lines.append(f"| {r['env']} | {r['env_steps']:,} | {_fmt(r['env_steps_per_s'])} | {_fmt(r['updates_per_s'])} | "
                     f"{r['mediocre_threshold']:g} | {crossed} | {_fmt(r['final_eval_return'])} | "
                     f"{_fmt(r['best_eval_return'])} |")
    if not runs:
        lines.append("| pending | | | | | | | |")
    lines += ["", "Pace: one core, `threads=1`, evaluations (10 deterministic episodes every 5000 steps) included in "
              "env steps/s; a run resumed from a checkpoint counts from its restart. "
              + (f"Figure: `{figure.name}`." if figure is not None else "Figure: none yet.")]
    return lines


def exec_table_report(results: Path) -> dict:
    """``results/table2.{md,json}`` and ``results/curves_<batch>.png`` of the execution-batch study
    (:func:`paper_exec_jobs`, kept runs and batch metadata in ``results``), supp. Table 2 style: one row per batch
    (:func:`exec_batches`: each env's SAC training batch as a Table 1 row, then its four execution batches) with the
    batch's mean episode return and its behaviour policy's return (:func:`_behaviour_return`) from its kept
    metadata, each algorithm's mean ± std beside the paper's figure (:data:`PAPER_TABLE2`, :data:`PAPER_SAC_BAIL`)
    and its IQM [95 % CI]; a verdict per claim (:func:`exec_claims`); the rows each algorithm wins and how each row
    orders the algorithms against the paper's (:func:`exec_rankings`). A cell without its seeds, a batch without
    metadata, reads "pending"; reads kept files only, so ``--report-only`` rebuilds it at any stage. Returns the JSON
    written."""
    from torchrl_bail.core.io import write_json_atomic, write_text_atomic

    jobs = paper_exec_jobs()
    batches, sac_runs = [], []
    for env, kind in exec_batches():
        label = f"{env}_{kind}_b1"
        cells, meta_path, metadata, rows = batch_rows(results, jobs, label, EXEC_ALGOS)
        if kind == "sac" and (run := sac_run_summary(env, metadata)) is not None:
            sac_runs.append(run)
        complete = metadata is not None and all(rows.get(a, {}).get("seeds", 0) >= rows[a]["scheduled"]
                                                for a in EXEC_CENTRAL if a in rows)
        figure = plot_batch_curves(label, cells, metadata, results / f"curves_{label}.png", EXEC_ALGOS)
        kept = None if metadata is None else {k: metadata.get(k) for k in EXEC_METADATA_KEYS}
        if kept is not None and isinstance(metadata.get("behaviour_policy"), dict):
            kept["behaviour_policy"] = {k: metadata["behaviour_policy"].get(k) for k in EXEC_POLICY_KEYS}
        batches.append({"batch": label, "env": env, "kind": kind, "row": EXEC_KINDS[kind],
                        "paper": (PAPER_SAC_BAIL if kind == "sac" else PAPER_TABLE2).get((env, kind, 1), {}),
                        "metadata_file": None if meta_path is None else _shown(meta_path), "metadata": kept,
                        "complete": complete, "cells": rows, "figure": None if figure is None else figure.name})
    for b in batches:
        b["behaviour_return"] = _behaviour_return(b)
    claims = exec_claims(batches)
    rankings = exec_rankings([b for b in batches if b["kind"] != "sac"])
    done = [b["batch"] for b in batches if b["complete"]]
    status = ("Batches complete (every cell at its seeds: "
              + ", ".join(f"{a} x {dict(PAPER_EXEC_CELLS)[a]}" for a in EXEC_CENTRAL)
              + f"; the batch's metadata kept): {len(done)} of {len(batches)}" + (f" ({', '.join(done)})" if done
                                                                                 else "") + ".")
    algos = [*EXEC_CENTRAL, *(a for a in EXEC_ALGOS if a not in EXEC_CENTRAL
                              and any(b["cells"].get(a, {}).get("seeds") for b in batches))]
    out = {"status": status, "complete_batches": done, "min_seeds_for_verdict": MIN_SEEDS_FOR_VERDICT,
           "bootstrap": {"reps": CROSS_BATCH_REPS, "seed": CROSS_BATCH_SEED, "across_batches": HIERARCHICAL_BOOTSTRAP},
           "batches": batches, "claims": claims, "rankings": rankings, "sac_runs": sac_runs}
    sac_figure = plot_sac_runs(sac_runs, results / "sac_runs.png")

    def meta(b, key):
        return "pending" if b["metadata"] is None or b["metadata"].get(key) is None else _fmt(b["metadata"][key])

    names = [ALGO_NAMES[a] for a in algos]
    lines = [status, "",
             "| batch | paper's row | data: mean episode return | behaviour policy's return | " + " | ".join(names)
             + " |", "|---|---|---|---|" + "---|" * len(algos)]
    lines += [f"| {b['batch']} | {b['row']} | {meta(b, 'episode_return_mean')} | {_behaviour_cell(b)} | "
              + " | ".join(_exec_row_cells(b, algos)) + " |" for b in batches]
    lines += ["", "Final return (the mean of a run's last evaluations), mean ± sample std over seeds; beside it the "
              "paper's figure on the same kind of batch (B1), mean ± std over seeds on gym's -v2 envs: supp. Table 2 "
              "(arXiv:1910.12179) for the execution batches; for the SAC training batches the BAIL authors' BAIL "
              "(their repository's README, the paper's Table 1 column), the only figure published there. These runs "
              "use Gymnasium's -v5 envs (simulator and rewards changed) and batches made again, so a level is a "
              "ballpark and the ordering of the algorithms is what compares. Data: the batch's mean episode "
              "return; behaviour policy's return: the frozen SAC policy an execution batch runs, as the SAC run "
              "evaluated it (`behaviour_return`), or for a SAC training batch the run's final evaluation (the batch "
              "is the whole run); both from the batch's kept metadata.json.", "", *_iqm_table(batches, algos, names),
              "", "| batch | claim | verdict | first side's IQM against the second's |", "|---|---|---|---|"]
    lines += [f"| {c['batch']} | {c['claim']} | {c['verdict']} | "
              + ("" if c["gap"] is None else f"{c['gap']:+.1f} %") + " |" for c in claims]
    lines += ["", f"A verdict needs {MIN_SEEDS_FOR_VERDICT} seeds a side (the paper cell's rule): 'above' and 'below' "
              "claims hold where the first group's IQM interval lies wholly above (below) the second's, ≈ claims "
              "where they overlap (no difference shown, which is not proof of equality). The behaviour policy's "
              "return is one measured figure, so BAIL ≈ the behaviour policy holds where BAIL's IQM interval "
              "contains it; the last column says how far apart the two are."]
    lines += _exec_ranking_lines(rankings, batches)
    figures = ", ".join(f"`{_shown(results / b['figure'])}`" for b in batches if b["figure"]) or "none yet"
    lines += ["", f"Learning curves, one figure per batch (updates on a linear axis, each seed's evaluations averaged "
              f"per {CURVE_WINDOW_UPDATES} updates; the mean over seeds, a band from the lowest to the highest seed): "
              f"{figures}."]
    lines += _sac_run_lines(sac_runs, sac_figure)
    text = "\n".join(lines) + "\n"
    write_text_atomic(results / "table2.md", text)
    write_json_atomic(results / "table2.json", out)
    return out


def _exec_ranking_lines(rankings: dict, batches: list[dict]) -> list[str]:
    """The Table 2 report's wins, orderings and averages (:func:`exec_rankings`), as Markdown lines."""
    def names(algos):
        return ", ".join(ALGO_NAMES[a] for a in algos)

    lines = ["", "| batch | ours: best IQM (ties: intervals overlapping the best's) | paper: best mean (same "
             "algorithms) | ours, best to worst | paper, best to worst | Kendall's tau | reading |",
             "|---|---|---|---|---|---|---|"]
    for r in rankings["rows"]:
        o = r["ordering"]
        if r["winners"] is None:
            lines.append(f"| {r['batch']} | pending | pending |  |  |  | pending |")
            continue
        lines.append(f"| {r['batch']} | {names(r['winners'])} | {names(r['paper_winners'])} | "
                     f"{' > '.join(ALGO_NAMES[a] for a in o['ours'])} | "
                     f"{' > '.join(ALGO_NAMES[a] for a in o['paper'])} | {_fmt(o['tau'], 2) or 'undefined'} | "
                     f"{o['reading']} |")
    n = len(rankings["rows"])
    lines += ["", f"| algorithm | rows won, ours ({rankings['ranked']} of {n} ranked) | paper, the same rows | paper, "
              f"all {len(PAPER_TABLE2)} rows of Table 2 |", "|---|---|---|---|"]
    lines += [f"| {ALGO_NAMES[a]} | {w['ours']} | {w['paper_same_rows']} | {w['paper_all_rows']} |"
              for a, w in rankings["wins"].items()]
    ordering = rankings["ordering"]
    tau = ("pending" if ordering["tau_pooled"] is None else
           f"{ordering['tau_pooled']:+.2f} ({ordering['concordant']} pairs concordant, {ordering['discordant']} "
           f"discordant, {ordering['tied']} tied, over {ordering['rows']} rows; {ordering['same_order']} rows in the "
           "paper's order)")
    means = rankings["paper_means"]
    lines += ["", "| Table 2's reading (supp. E) | verdict |", "|---|---|",
              f"| BC and MARWIL win the most rows | {rankings['most_wins_verdict']} |",
              f"| BAIL ≈ BCQ on average (the paper: BAIL's mean {means['bail']['same_rows']:.0f} against BCQ's "
              f"{means['bcq']['same_rows']:.0f} on these rows, {means['bail']['all_rows']:.0f} against "
              f"{means['bcq']['all_rows']:.0f} on all {len(PAPER_TABLE2)}) | {rankings['average_verdict']} |",
              f"| our orderings against the paper's, over every ranked row | Kendall's tau {tau} |", "",
              "A row is ranked once BAIL, BCQ, BC and MARWIL each have "
              f"{MIN_SEEDS_FOR_VERDICT} seeds there (BEAR joins where it has them). Its winners: the best IQM and "
              "every algorithm whose IQM interval overlaps the best's (a tie); the paper's: the best mean of its "
              "row among the same algorithms (ties: equal means). 'BC and MARWIL win the most rows' holds where the "
              "most wins go to them alone. Kendall's tau per row: tau-b between our IQMs and the paper's means "
              "(scipy.stats.kendalltau); over all rows, every row's pairs pooled: (concordant - discordant) / "
              "pairs, a pair tied on either side counting neither way.", "",
              *_improvement_lines(rankings["probability_of_improvement"], len(rankings["rows"])), "",
              f"Over the execution batches, on raw returns (a probability of improvement compares runs within a "
              f"batch, so no normalisation enters). {_bootstrap_sentence(len(rankings['rows']))}"]
    return lines


# ---------------------------------------------------------------------------------------------------------------
# the off-policy-evaluation report (``--study ope_headline``): how well FQE ranks the headline batch's policies
# ---------------------------------------------------------------------------------------------------------------

#: the bootstrap of the rank correlation's interval: replications (policies drawn with replacement) and numpy seed
OPE_REPS, OPE_SEED = 2_000, 0


def _last_evaluation(run: Path) -> float | None:
    """The return of a run's final policy (``policy.pt``) as training measured it: its last evaluation's mean return
    (``logs/scalars/eval/return.csv``, the value ``policy.pt`` records)."""
    from torchrl_bail.reports.plots import _read_scalar_csv

    csv = run / "logs" / "scalars" / "eval" / "return.csv"
    if not csv.is_file():
        return None
    returns = _read_scalar_csv(csv)
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
        entry["reference_run"] = _shown(reference)
        entry["reference_final_return"] = ref_summary["final_return"]
    run = run_dir_of(job, results / "runs")
    summary = None if run is None else _read_json(run / "summary.json")
    if summary is None:
        return entry
    entry.update(run=_shown(run), final_return=summary["final_return"], best_return=summary["best_return"],
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
    report(results, ablations=study == "study")
    curve_check(results)
    if study == "paper_hopper":
        paper_cell_report(results, STUDIES[study]())
    if study == "paper_batches":
        cross_batch_report(results, headline)
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

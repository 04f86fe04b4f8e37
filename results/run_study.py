"""Reruns the results study of the docs ("Results"), or any row of it, from scratch.

    python results/run_study.py                              # everything: 11 batches, every algorithm, reports (hours)
    python results/run_study.py --only hopper_ddpg05/bail/seed  # one row: its batch and 3 seeds, then the reports
    python results/run_study.py --list                       # the jobs, in the order they run
    python results/run_study.py --study paper_hopper --jobs 2   # the paper-scale Hopper study (days of CPU)
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
opt_det (B1, 50k transitions); every registered algorithm (:data:`torchrl_bail.algo_schemas.ALGO_SCHEMAS`: BAIL,
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
``--status`` lists every job of a study as done, running (its log was written in the last 10 minutes) or left,
with the checkpoint's progress (updates done / scheduled) where one exists and the time the updates left take at
the run's pace so far.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path

from omegaconf import OmegaConf

from torchrl_bail.algo_schemas import ALGO_SCHEMAS, study_algorithms

HERE = Path(__file__).resolve().parent
SEEDS = (1, 2, 3)
ENVS = ("hopper", "walker")
KINDS = ("ddpg01", "ddpg05", "sac", "med_stoch", "opt_det")
#: the study's cost rule, read from the registry (each schema's ``study`` line, :mod:`torchrl_bail.algo_schemas`): a
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
    from torchrl_bail.config_builders import run_length_overrides

    if ALGO_SCHEMAS[algo].cost == "imitation":
        return []
    return run_length_overrides(algo, OFFLINE_RL_UPDATES, OFFLINE_RL_EVALUATIONS)


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


STUDIES = {"study": study_jobs, "paper_hopper": paper_hopper_jobs, "paper_batches": paper_batches_jobs}


def run_dir_of(job: Job, runs: Path) -> Path | None:
    """The run directory of a training job under ``runs`` (the workdir's ``outputs``, or the results' ``runs``, which
    keeps the same layout: ``<batch>_b1/<algo>/seed<s>[,<overrides>]``)."""
    named = dict(arg.split("=", 1) for arg in job.args)
    extra = sorted(arg for arg in job.args if not arg.startswith(("+exp=", "algo=", "seed=", "batch.index=")))
    label = f"{named['+exp']}_b{named.get('batch.index', 1)}"  # batch.index is in the path, not the suffix
    for run in sorted((runs / label / named["algo"]).glob(f"seed{named['seed']}*")):
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


def _collected_steps(job: Job, data_dir: Path | None) -> str:
    """`` (N steps collected)``: the env steps of the last checkpoint of the batch's partial collection, if any."""
    from torchrl_bail.behaviour.checkpoint import CollectionCheckpoint
    from torchrl_bail.data.cache import default_data_dir
    from torchrl_bail.data.locks import PARTIAL

    named = dict(arg.split("=", 1) for arg in job.args)
    batch = f"{named['+exp']}_b{named.get('batch.index', 1)}"
    partials = (Path(data_dir or default_data_dir()) / PARTIAL).glob(f"{batch}-*")
    steps = [s for s in (CollectionCheckpoint(p, every_s=None).steps for p in partials) if s is not None]
    return f" ({max(steps)} steps collected)" if steps else ""


def landed(job: Job, results: Path | None) -> bool:
    """Whether a training job's ``summary.json`` is already kept in ``results/runs`` (gathered by an earlier call,
    maybe on another machine whose workdir is gone): such a job is done and does not run again."""
    if results is None or job.module != "torchrl_bail.train":
        return False
    run = run_dir_of(job, results / "runs")
    return run is not None and (run / "summary.json").is_file()


def job_status(job: Job, workdir: Path, data_dir: Path | None = None, results: Path | None = None) -> str:
    """``done``, ``running`` or ``left``, with the progress of its checkpoint (``updates done/scheduled``) or of its
    partial collection (``steps collected``) where there is one. A job whose summary is kept in ``results`` is
    done."""
    if landed(job, results):
        return "done"
    log = workdir / "logs" / (job.name.replace("/", "__") + ".log")
    running = _is_running(log)
    if job.module != "torchrl_bail.train":
        text = log.read_text(errors="replace") if log.is_file() else ""
        if re.search(r": (collected|already cached) at ", text):
            return "done"
        return ("running" if running else "left") + _collected_steps(job, data_dir)
    run = run_dir_of(job, workdir / "outputs")
    if run is not None and (run / "summary.json").is_file():
        return "done"
    progress = ""
    if run is not None and (run / "checkpoint.pt").is_file():
        import torch

        state = torch.load(run / "checkpoint.pt", map_location="cpu", weights_only=False)
        progress = f" ({state['iteration']}/{state['iterations']} updates{_time_left(state, run, running)})"
    return ("running" if running else "left") + progress


def _time_left(state: dict, run: Path, running: bool) -> str:
    """``, about N min left``: the updates left at the run's own pace so far (its checkpoint's training seconds per
    update, evaluations included), less what a running job has done since that checkpoint; empty before any."""
    done, wall = state["iteration"], state.get("wall_time_s")
    if not done or not wall:
        return ""
    left = (state["iterations"] - done) * wall / done
    if running:
        left -= time.time() - (run / "checkpoint.pt").stat().st_mtime
    return f", about {max(left, 0.0) / 60:.0f} min left"


def conditions() -> dict:
    """What the machine was doing as a job started or ended: the 1/5/15-minute load averages and the UTC time."""
    return {"load": [round(x, 2) for x in os.getloadavg()], "utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}


def run_job(job: Job, workdir: Path, data_dir: Path | None,
            results: Path | None = None) -> tuple[Job, int | None, float, dict]:
    """Runs ``job`` (its output appended to ``workdir/logs/<job>.log``); returns its exit code (``None``: it had
    finished in an earlier call, its log or its kept summary in ``results`` says so, and nothing ran), wall
    seconds and the job's record for ``timings.json``: wall seconds, torch threads, the CPUs the job may run on,
    the load averages at its start and end (a load near the job's own threads is a quiet machine), the CPU."""
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    if data_dir is not None:
        env["TORCHRL_BAIL_DATA_DIR"] = str(data_dir)
    log = workdir / "logs" / (job.name.replace("/", "__") + ".log")
    log.parent.mkdir(parents=True, exist_ok=True)
    if landed(job, results) or (job.module == "torchrl_bail.train" and log.is_file()
                                and FINISHED.search(log.read_text(errors="replace"))):
        return job, None, 0.0, {}
    extra = ["progress=false"] + (["threads=1"] if job.module == "torchrl_bail.train" else [])
    record = {"threads": 1 if job.module == "torchrl_bail.train" else None, "cpus": sorted(os.sched_getaffinity(0)),
              "cpu": machine_cpu(), "start": conditions()}
    start = time.perf_counter()
    pid_file = log.with_suffix(".pid")  # while it exists and names a live process, --status says "running"
    with open(log, "a") as out:
        proc = subprocess.Popen([sys.executable, "-m", job.module, *job.args, *extra], cwd=workdir, env=env,
                                stdout=out, stderr=subprocess.STDOUT)
        pid_file.write_text(f"{proc.pid}\n")
        try:
            rc = proc.wait()
        finally:
            pid_file.unlink(missing_ok=True)
    seconds = time.perf_counter() - start
    return job, rc, seconds, {"wall_s": seconds, **record, "end": conditions()}


def whole_job_record(job: Job, record: dict, workdir: Path) -> dict:
    """The ``timings.json`` record of a job that just finished. A run resumed from its checkpoint (an earlier call
    was interrupted: a killed process, a session's end) is charged its accumulated training time, the summary's
    ``wall_time_s`` (the checkpoint carries it across resumes; the minutes between the last checkpoint and a kill are
    lost, and so is each start-up), not this call's last part alone, which ``last_part_s`` keeps with the iterations
    it resumed from; ``start`` is then the last part's."""
    run = run_dir_of(job, workdir / "outputs") if job.module == "torchrl_bail.train" else None
    summary_path = run / "summary.json" if run is not None else None
    summary = json.loads(summary_path.read_text()) if summary_path is not None and summary_path.is_file() else {}
    if not summary.get("resumed_from_iteration"):
        return record
    return {**record, "wall_s": float(summary["wall_time_s"]), "last_part_s": record["wall_s"],
            "resumed_from_iteration": summary["resumed_from_iteration"]}


def machine_cpu() -> str:
    """The CPU's model name (``/proc/cpuinfo``), or the platform's processor string."""
    import platform

    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        for line in cpuinfo.read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or "unknown"


def wall_seconds(entry: float | dict) -> float:
    """A ``timings.json`` entry's wall seconds: the bare number of older entries, or a record's ``wall_s``."""
    return float(entry["wall_s"] if isinstance(entry, dict) else entry)


def gather(workdir: Path, results: Path) -> list[Path]:
    """Copies every finished run's summary, config and logs from ``workdir/outputs`` into ``results/runs``."""
    copied = []
    for summary in sorted((workdir / "outputs").glob("*/*/*/summary.json")):
        run = summary.parent
        target = results / "runs" / run.relative_to(workdir / "outputs")
        target.mkdir(parents=True, exist_ok=True)
        for name in ("summary.json", "config.yaml"):
            shutil.copy2(run / name, target / name)
        if (run / "logs").is_dir():
            shutil.copytree(run / "logs", target / "logs", dirs_exist_ok=True)
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

    from torchrl_bail.io import write_json_atomic, write_text_atomic
    from torchrl_bail.plots import read_eval_curve

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
        mean = np.mean([c[:n] for c in curves], axis=0)
        x = np.arange(n // 2, n)
        slope, intercept = np.polyfit(x, mean[n // 2:], 1)
        spread = float(np.std(mean[n // 2:] - (slope * x + intercept), ddof=2))
        change, level = float(slope * (x[-1] - x[0])), float(mean[n // 2:].mean())
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
    from torchrl_bail.config_builders import algo_config

    yaml = OmegaConf.create({"algo": algo_config(row["algo"])})
    extra = ", ".join(f"{k.rsplit('.', 1)[-1]}={v}" for k, v in sorted(row["overrides"].items())
                      if v is not None and OmegaConf.select(yaml, k) != v)
    return f"{row['algo']} ({extra})" if extra else row["algo"]


def claim_verdict(a: dict | None, b: dict | None, kind: str) -> str:
    """The verdict on one claim from the two groups' report rows (IQM and its 95 % bootstrap interval)."""
    seeds = [0 if row is None else row["seeds"] for row in (a, b)]
    if min(seeds) < MIN_SEEDS_FOR_VERDICT:
        return f"pending (seeds so far: {seeds[0]} and {seeds[1]}; {MIN_SEEDS_FOR_VERDICT} each needed)"
    lo_a, hi_a = a["final_return_iqm_ci_low"], a["final_return_iqm_ci_high"]
    lo_b, hi_b = b["final_return_iqm_ci_low"], b["final_return_iqm_ci_high"]
    if lo_a > hi_b:
        order = "above: the IQM intervals are disjoint"
    elif lo_b > hi_a:
        order = "below: the IQM intervals are disjoint"
    else:
        order = "no difference shown: the IQM intervals overlap"
    holds = order.startswith("above") if kind == "above" else order.startswith("no difference")
    return f"{'holds' if holds else 'does not hold'} ({order})"


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
    from torchrl_bail.io import write_json_atomic, write_text_atomic

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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--study", choices=sorted(STUDIES), default="study",
                        help="study: the 50k-transition study (docs: Results); paper_hopper: Hopper at paper scale")
    parser.add_argument("--only", help="run only the jobs whose name matches this regex (e.g. hopper_ddpg05/bail)")
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="jobs at a time (default: cores)")
    parser.add_argument("--workdir", type=Path, help="where outputs/ and logs/ go (default: <study>_work)")
    parser.add_argument("--data-dir", type=Path, help="batch cache (default: TORCHRL_BAIL_DATA_DIR or ~/.cache)")
    parser.add_argument("--results", type=Path, help="where the kept files and reports go (default: results/<study>)")
    parser.add_argument("--list", action="store_true", help="print the jobs and exit")
    parser.add_argument("--status", action="store_true", help="print each job's state (done, running, left)")
    parser.add_argument("--report-only", action="store_true", help="only gather the finished runs and report")
    args = parser.parse_args(argv)
    args.workdir = args.workdir or Path(f"{args.study}_work")
    args.results = args.results or HERE / args.study

    jobs = STUDIES[args.study]()
    if args.only:  # a row's batch is collected by its first training job (the others wait on its lock)
        jobs = [j for j in jobs if re.search(args.only, j.name)]
    if args.list:
        print("\n".join(f"{j.name}: python -m {j.module} {' '.join(j.args)}" for j in jobs))
        return 0
    if args.status:
        states = [(j.name, job_status(j, args.workdir, args.data_dir, args.results)) for j in jobs]
        width = max(len(state) for _, state in states)
        print("\n".join(f"{state:<{width}}  {name}" for name, state in states))
        counts = {k: sum(state.startswith(k) for _, state in states) for k in ("done", "running", "left")}
        print(", ".join(f"{v} {k}" for k, v in counts.items()) + f" of {len(states)} jobs")
        return 0
    args.workdir.mkdir(parents=True, exist_ok=True)
    args.results.mkdir(parents=True, exist_ok=True)
    timings_path = args.results / "timings.json"
    failed = []
    if not args.report_only:
        # one queue, batches first: training starts while the last batches are still being collected (a job
        # whose batch another job is collecting waits on the batch's lock, then reuses it)
        with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
            futures = [pool.submit(run_job, j, args.workdir.resolve(), args.data_dir, args.results) for j in jobs]
            for done, future in enumerate(as_completed(futures), 1):
                job, rc, seconds, record = future.result()
                if rc is None:
                    continue  # finished in an earlier call
                # read again before each write: another runner (another CPU's job) may have recorded since
                timings = json.loads(timings_path.read_text()) if timings_path.exists() else {}
                if rc == 0:
                    timings.setdefault(job.name, whole_job_record(job, record, args.workdir))
                print(f"[{done}/{len(jobs)}] {job.name}: {'ok' if rc == 0 else f'FAILED (exit {rc})'} "
                      f"in {seconds:.0f} s", flush=True)
                if rc != 0:
                    failed.append(job.name)
                tmp = timings_path.with_suffix(f".{os.getpid()}.tmp")
                tmp.write_text(json.dumps(timings, indent=1, sort_keys=True) + "\n")
                tmp.replace(timings_path)
    copied = gather(args.workdir, args.results)
    report(args.results, ablations=args.study == "study")
    curve_check(args.results)
    if args.study == "paper_hopper":
        paper_cell_report(args.results, STUDIES[args.study]())
    reports = "study.md, ablations.md" if args.study == "study" else "study.md, cell.md"
    kept = len(list((args.results / "runs").glob("*/*/*/summary.json")))
    print(f"{len(copied)} runs copied from {args.workdir / 'outputs'}; {kept} runs in {args.results / 'runs'}; "
          f"reports in {args.results}: {reports}")
    if failed:
        print("failed (see their logs in " f"{args.workdir / 'logs'}): " + ", ".join(failed), file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

"""Where a study's jobs stand (``python -m torchrl_bail.study status``): done, running or left, with progress and
the time left.

A job is **done** when :func:`torchrl_bail.study.sweeps.finished` says so (its ``summary.json``, its batch); else
**running** while a live process holds its lock (a training run's directory lock, a batch's lock in the data dir:
:func:`torchrl_bail.data.locks.lock_is_held`, on any host that shares the directories), else **left**. A job with a
checkpoint gives its progress (updates done of scheduled, or transitions kept of wanted) and the time the rest takes
at its own pace so far; one without is priced at the median cost of the finished jobs like it (the same algorithm's
training runs, collections made the same way: :func:`collection_kind`), read from their records (``summary.json``'s
``wall_time_s``, a batch's ``collection_wall_time_s``) in the work dir and in the study's results.
"""

from __future__ import annotations

import json
import statistics
from dataclasses import dataclass
from pathlib import Path

import torch

from torchrl_bail.behaviour.checkpoint import CollectionCheckpoint
from torchrl_bail.data.locks import LOCKS, PARTIAL, liveness_settings, lock_is_held
from torchrl_bail.study.declaration import Study, StudyJob
from torchrl_bail.study.sweeps import finished, job_batch, job_configs, job_dir
from torchrl_bail.training.resume import RUN_LOCK, RUN_LOCK_STALE_AFTER_S

#: a collection's batch kind -> how it is made, which sets its cost: a DDPG run, a SAC run (10^6 steps of SAC
#: updates), or an execution batch (a frozen SAC policy acting, no update)
COLLECTION_KINDS = (("_sac_", "sac run"), ("_med_", "execution"), ("_opt_", "execution"))


def collection_kind(batch: str) -> str:
    """How the batch labelled ``batch`` is made (:data:`COLLECTION_KINDS`; ``"ddpg"`` otherwise).

    Examples:
        >>> collection_kind("hopper_sac_b1"), collection_kind("walker_med_det_b1"), collection_kind("hopper_ddpg05_b2")
        ('sac run', 'execution', 'ddpg')
    """
    return next((kind for token, kind in COLLECTION_KINDS if token in f"_{batch}"), "ddpg")


@dataclass(frozen=True)
class JobState:
    """Where one job stands; ``str()`` gives it as ``status`` prints it: ``running (2500/10000 updates, about 25 min
    left)``."""

    state: str                             #: ``done``, ``running`` or ``left``
    progress: tuple[int, int] | None = None  #: updates (or transitions) done, of how many
    unit: str = "updates"
    seconds_left: float | None = None      #: at the job's own pace so far, else at its kind's recorded cost
    priced: bool = False                   #: ``seconds_left`` is its kind's recorded cost, not its own pace

    def __str__(self) -> str:
        parts = [] if self.progress is None else [f"{self.progress[0]}/{self.progress[1]} {self.unit}"]
        if self.state != "done" and self.seconds_left is not None:
            parts.append(f"about {_duration(self.seconds_left)} left"
                         + (" at the recorded cost of its kind" if self.priced else ""))
        return self.state + (f" ({', '.join(parts)})" if parts else "")


def _duration(seconds: float) -> str:
    return f"{seconds / 3600:.1f} h" if seconds >= 5400 else f"{seconds / 60:.0f} min"


def _pace_left(done: int, total: int, wall: float | None) -> float | None:
    return None if not done or not wall else (total - done) * wall / done


def _training_state(run: Path) -> JobState:
    checkpoint = run / "checkpoint.pt"
    state = "running" if lock_is_held(run / RUN_LOCK, RUN_LOCK_STALE_AFTER_S) else "left"
    if not checkpoint.is_file():
        return JobState(state)
    saved = torch.load(checkpoint, map_location="cpu", weights_only=False)
    done, total = int(saved["iteration"]), int(saved["iterations"])
    return JobState(state, (done, total), "updates", _pace_left(done, total, saved.get("wall_time_s")))


def _collection_state(batch: str, path: Path) -> JobState:
    """A collection not finished: running while a process holds the lock of its batch (at ``path``), with the
    progress of its partial collection's last checkpoint."""
    data_dir = path.parent
    state = "running" if lock_is_held(data_dir / LOCKS / f"{path.name}.lock", liveness_settings()[0]) else "left"
    partials = sorted((data_dir / PARTIAL).glob(f"{batch}-*"))
    found = [s for p in partials if (s := CollectionCheckpoint(p, every_s=None).load()) is not None]
    if not found:
        return JobState(state)
    saved = max(found, key=lambda s: int(s["loop"]["t"]))
    kept, size = int(saved["buffers"]["kept"]), saved["buffers"].get("steps")
    if size is None:  # an older checkpoint names no batch size
        return JobState(state)
    wall = None if saved.get("timed_from_step") else saved.get("wall_time_s")
    return JobState(state, (kept, int(size)), "transitions", _pace_left(kept, int(size), wall))


def _read(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def recorded_costs(roots: list[Path], data_dirs: list[Path]) -> dict[str, list[float]]:
    """The recorded seconds of finished jobs, by kind: ``train/<algo>`` from every ``summary.json`` under ``roots``
    (``wall_time_s``), ``collect/<collection_kind>`` from every batch metadata under ``data_dirs`` and ``roots``
    (``collection_wall_time_s``, only where timed from the first step)."""
    costs: dict[str, list[float]] = {}
    for root in roots:
        for path in root.rglob("summary.json") if root.is_dir() else ():
            summary = _read(path)
            if summary and summary.get("wall_time_s") and summary.get("algo"):
                costs.setdefault(f"train/{summary['algo']}", []).append(float(summary["wall_time_s"]))
    metadata = [p for d in data_dirs if d.is_dir() for p in d.glob("*/metadata.json")]
    metadata += [p for root in roots if root.is_dir() for p in root.rglob("*.metadata.json")]
    for path in metadata:
        meta = _read(path)
        if meta and meta.get("collection_wall_time_s") and not meta.get("collection_timed_from_step"):
            label = f"{meta.get('name')}"
            costs.setdefault(f"collect/{collection_kind(label)}", []).append(float(meta["collection_wall_time_s"]))
    return costs


def _kind(job: StudyJob) -> str:
    return f"collect/{collection_kind(job.batch)}" if job.command == "collect" else f"train/{job.overrides['algo']}"


def job_states(study: Study, workdir: Path, data_dir: Path) -> list[tuple[StudyJob, JobState]]:
    """Every job of ``study`` (run in ``workdir`` with batches in ``data_dir``) with where it stands."""
    costs = recorded_costs([workdir / "outputs", *([study.results] if study.results else [])], [data_dir])
    out = []
    for step, job, cfg in job_configs(study, workdir, data_dir):
        if finished(step.command, cfg):
            state = JobState("done")
        elif step.command == "collect":
            state = _collection_state(job.batch, job_batch(cfg))
        else:
            state = _training_state(job_dir(cfg))
        if state.state != "done" and state.seconds_left is None and costs.get(_kind(job)):
            share = 1 - state.progress[0] / state.progress[1] if state.progress else 1.0
            state = JobState(state.state, state.progress, state.unit,
                             statistics.median(costs[_kind(job)]) * share, priced=True)
        out.append((job, state))
    return out


def summary_line(states: list[tuple[StudyJob, JobState]]) -> str:
    """``N done, N running, N left of N jobs; left to run: about X h of one core (N jobs of a kind with no recorded
    cost)``."""
    count = {s: sum(state.state == s for _, state in states) for s in ("done", "running", "left")}
    unfinished = [state for _, state in states if state.state != "done"]
    known = [state.seconds_left for state in unfinished if state.seconds_left is not None]
    line = (f"{count['done']} done, {count['running']} running, {count['left']} left of {len(states)} jobs")
    if unfinished:
        line += f"; left to run: about {sum(known) / 3600:.1f} h of one core for {len(known)} of them"
        if len(known) < len(unfinished):
            line += f" ({len(unfinished) - len(known)} of a kind with no recorded cost yet)"
    return line

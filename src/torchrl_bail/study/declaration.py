"""A study declared as data: a YAML file of steps, each a list of cells, each a grid of overrides.

A study (``declared/<name>.yaml``, or any YAML file of the same form) reads::

    description: one paragraph: what the study measures and where the paper says it
    results: results/paper_exec        # where `report` gathers the kept runs and writes the tables
    report: exec_table                 # which report builds them (torchrl_bail.study.reports)
    every_job: [preset=paper]          # overrides of every job (optional)
    steps:                             # in order: a step starts once the one before it has ended
      - name: hopper batches
        command: collect               # collect | train: the entry point that runs each job
        cells:
          - grid: {batch: [hopper_sac_b1, hopper_med_det_b1]}
      - name: hopper trainings
        command: train
        cells:
          - grid: {seed: [1, 2, 3], batch: [hopper_sac_b1], algo: [bail, bc, bcq]}
            schedule: {updates: 100000, evaluations: 20}
          - grid: {batch: [hopper_sac_b1], algo: [marwil], seed: [1, 2, 3]}
            tag: value_warmup
            overrides: [algo.value_warmup_updates=1000]

A cell's jobs are its grid's product, the first key outermost (``seed`` first: seed 1 of every batch and algorithm
before seed 2). A grid key is a command-line key (``algo``, ``seed``, ``eval.episodes``, ...) or ``batch``: a batch
label ``<experiment>_b<index>`` (``hopper_ddpg05_b2``), which stands for ``+exp=hopper_ddpg05 batch.index=2`` (the
index left out at 1), the name that run directories and results give a batch. ``schedule`` sets the run length of
the actor-critics (an algorithm whose registry ``cost`` is ``offline_rl``: BCQ, BEAR, TD3+BC, IQL) in updates of
their own mini-batch size, with that many evaluations (``configuration.config_builders.run_length_overrides``); the
imitation learners (BAIL, BC, MARWIL, ...) keep their yaml's epochs. ``tag`` names a variant: its jobs are
``<batch>/<algo>/<tag>/seed<s>``.

Each job has a name, the one the study's records use: ``collect/<batch>`` for a collection,
``<batch>/<algo>[/<tag>]/seed<s>`` for a training run.
"""

from __future__ import annotations

import itertools
import re
from dataclasses import dataclass, field
from pathlib import Path

from omegaconf import DictConfig, ListConfig, OmegaConf

from torchrl_bail.configuration.algo_schemas import ALGO_SCHEMAS
from torchrl_bail.configuration.config_builders import run_length_overrides
from torchrl_bail.core.errors import CommandLineError

#: the studies this package declares (``python -m torchrl_bail.study list``)
DECLARED = Path(__file__).resolve().parent / "declared"
#: the entry points a step may run
COMMANDS = ("collect", "train")
LABEL = re.compile(r"^(?P<exp>[A-Za-z0-9_]+?)_b(?P<index>[1-9][0-9]*)$")


class StudyError(CommandLineError):
    """A study's declaration is malformed, or a study's name is unknown: the message says where and what is
    expected (the study command, and ``train``/``collect`` running a step, print it as one line)."""


@dataclass(frozen=True)
class StudyJob:
    """One job of a study: ``python -m torchrl_bail.<command> <args>``."""

    name: str                  #: ``collect/<batch>`` or ``<batch>/<algo>[/<tag>]/seed<s>``
    args: tuple[str, ...]      #: the job's command-line overrides (a cell's win over the study's ``every_job``)
    command: str = "train"     #: ``collect`` or ``train``

    @property
    def module(self) -> str:
        """The entry point's module, ``torchrl_bail.train``."""
        return f"torchrl_bail.{self.command}"

    @property
    def overrides(self) -> dict[str, str]:
        """The job's ``key=value`` arguments as a mapping (``{"+exp": "hopper_ddpg05", "algo": "bail", ...}``)."""
        return dict(arg.split("=", 1) for arg in self.args)

    @property
    def row(self) -> str:
        """The name less its seed, ``hopper_sac_b1/bail``: the cell the job is a seed of."""
        return self.name.rsplit("/seed", 1)[0]

    @property
    def batch(self) -> str:
        """The job's batch label, ``hopper_ddpg05_b2``."""
        return self.name.split("/")[1] if self.command == "collect" else self.name.split("/")[0]


@dataclass(frozen=True)
class Step:
    name: str
    command: str
    jobs: tuple[StudyJob, ...]


@dataclass(frozen=True)
class Study:
    name: str
    path: Path
    description: str
    results: Path | None
    report: str | None
    steps: tuple[Step, ...] = field(default_factory=tuple)

    @property
    def jobs(self) -> list[StudyJob]:
        """Every job, in the order the steps run them."""
        return [job for step in self.steps for job in step.jobs]


def batch_overrides(label: str) -> list[str]:
    """The overrides that name the batch ``label``.

    Examples:
        >>> batch_overrides("hopper_ddpg05_b1"), batch_overrides("hopper_ddpg05_b2")
        (['+exp=hopper_ddpg05'], ['+exp=hopper_ddpg05', 'batch.index=2'])
    """
    match = LABEL.match(label)
    if match is None:
        raise StudyError(f"batch {label!r}: expected a batch label <experiment>_b<index>, e.g. hopper_ddpg05_b1")
    index = int(match["index"])
    return [f"+exp={match['exp']}"] + ([f"batch.index={index}"] if index != 1 else [])


def _value(value) -> str:
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, (list, ListConfig)):
        return "[" + ",".join(_value(v) for v in value) + "]"
    return str(value)


def _merged(*groups: list[str]) -> tuple[str, ...]:
    """The overrides of ``groups`` in order, a key given again replacing its earlier value (a cell's override wins
    over the study's ``every_job``), so that no key reaches the command line (and the run directory's name) twice.

    Examples:
        >>> _merged(["preset=quick", "eval.episodes=1"], ["algo=bc"], ["eval.episodes=5"])
        ('preset=quick', 'eval.episodes=5', 'algo=bc')
    """
    merged: dict[str, str] = {}
    for group in groups:
        for override in group:
            merged[override.split("=", 1)[0]] = override
    return tuple(merged.values())


def _cell_jobs(study: str, step: int, command: str, cell: DictConfig, every_job: list[str]) -> list[StudyJob]:
    where = f"study {study}, step {step + 1}"
    unknown = set(cell) - {"grid", "schedule", "tag", "overrides"}
    if unknown:
        raise StudyError(f"{where}: unknown cell key {sorted(unknown)[0]!r} (grid, schedule, tag or overrides)")
    grid = cell.get("grid")
    if not isinstance(grid, DictConfig) or "batch" not in grid:
        raise StudyError(f"{where}: a cell's grid must be a mapping with a 'batch' list (batch labels)")
    keys = list(grid)
    if command == "train" and not {"algo", "seed"} <= set(keys):
        raise StudyError(f"{where}: a train step's grid names 'batch', 'algo' and 'seed' (it has {keys})")
    values = [list(grid[k]) if isinstance(grid[k], ListConfig) else [grid[k]] for k in keys]
    schedule = cell.get("schedule")
    tag = cell.get("tag")
    extra = [str(o) for o in cell.get("overrides") or []]
    jobs = []
    for combo in itertools.product(*values):
        point = dict(zip(keys, combo, strict=True))
        overrides = batch_overrides(str(point["batch"]))
        if command == "collect":
            name = f"collect/{point['batch']}"
        else:
            algo = str(point["algo"])
            if algo not in ALGO_SCHEMAS:
                raise StudyError(f"{where}: unknown algorithm {algo!r} (one of {', '.join(sorted(ALGO_SCHEMAS))})")
            name = "/".join([str(point["batch"]), algo, *([str(tag)] if tag else []), f"seed{point['seed']}"])
            overrides += [f"algo={algo}", f"seed={point['seed']}"]
            if schedule is not None and ALGO_SCHEMAS[algo].cost == "offline_rl":
                overrides += run_length_overrides(algo, int(schedule.updates), schedule.get("evaluations"))
        overrides += [f"{k}={_value(v)}" for k, v in point.items() if k not in ("batch", "algo", "seed")]
        jobs.append(StudyJob(name, _merged(every_job, overrides, extra), command))
    return jobs


def load_study(name_or_path: str | Path) -> Study:
    """The study ``name_or_path``: a declared study's name (``paper_exec``: ``declared/paper_exec.yaml``) or the path
    of a YAML file of the same form. Raises :class:`StudyError` on a malformed one (an
    unknown key, command or algorithm, a job declared twice)."""
    path = Path(name_or_path)
    if not path.suffix:
        path = DECLARED / f"{name_or_path}.yaml"
        if not path.is_file():
            raise StudyError(f"no study {str(name_or_path)!r}: give a declared study "
                             f"({', '.join(declared_studies())}) or the path of a study's YAML file")
    elif not path.is_file():
        raise StudyError(f"no study file {str(name_or_path)!r}")
    spec = OmegaConf.load(path)
    unknown = set(spec) - {"description", "results", "report", "every_job", "steps"}
    if unknown:
        raise StudyError(f"study {path.stem}: unknown key {sorted(unknown)[0]!r} (description, results, report, "
                         "every_job or steps)")
    every_job = [str(o) for o in spec.get("every_job") or []]
    steps, seen = [], set()
    for i, step in enumerate(spec.get("steps") or []):
        if step.get("command") not in COMMANDS:
            raise StudyError(f"study {path.stem}, step {i + 1}: command {step.get('command')!r} is not one of "
                             f"{', '.join(COMMANDS)}")
        jobs = [job for cell in step.get("cells") or []
                for job in _cell_jobs(path.stem, i, step.command, cell, every_job)]
        twice = [job.name for job in jobs if job.name in seen or seen.add(job.name)]
        if twice:
            raise StudyError(f"study {path.stem}, step {i + 1}: job {twice[0]} is declared twice")
        steps.append(Step(str(step.get("name") or f"step {i + 1}"), str(step.command), tuple(jobs)))
    results = spec.get("results")
    return Study(path.stem, path.absolute(), str(spec.get("description") or ""),
                 None if results is None else Path(results),
                 spec.get("report"), tuple(steps))


def declared_studies() -> list[str]:
    """The names of the studies this package declares."""
    return sorted(p.stem for p in DECLARED.glob("*.yaml"))

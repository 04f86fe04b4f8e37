"""``python -m torchrl_bail.study``: run, follow and report a declared study, on any Hydra launcher.

    python -m torchrl_bail.study list                                  # the declared studies
    python -m torchrl_bail.study list paper_exec                       # its steps and jobs, in order
    python -m torchrl_bail.study run paper_exec --workdir W            # every step, one job after another
    python -m torchrl_bail.study run paper_exec --workdir W hydra/launcher=joblib hydra.launcher.n_jobs=2
    python -m torchrl_bail.study run paper_exec --workdir W hydra/launcher=slurm hydra.launcher.partition=cpu
    python -m torchrl_bail.study status paper_exec --workdir W         # done / running / left, time left
    python -m torchrl_bail.study report paper_exec --workdir W         # the study's tables and figures

``run`` runs the study's steps in order, each as one Hydra multirun (:mod:`torchrl_bail.study.sweeps`); the
arguments after the study's name go to every step's command line (a launcher, its settings, any override of every
job). Re-running it resumes: finished jobs are skipped, stopped ones continue from their checkpoints. ``--cpus 0``
runs the steps under ``taskset -c 0`` (each job with one torch thread, ``threads: 1``). A study is a declared one's
name or the path of a study's YAML file (:mod:`torchrl_bail.study.declaration`). SIGTERM or Ctrl-C stops the step's
running job at its next update, with its checkpoint saved. Exit codes: 0 done, 1 a step failed (the next one does not
start), 2 a bad command line or study, 130/143 stopped by SIGINT/SIGTERM.
"""

from __future__ import annotations

import argparse
import os
import shlex
import shutil
import signal
import subprocess
import sys
from pathlib import Path

from torchrl_bail.cli import CONTINUE_WITH
from torchrl_bail.study.declaration import Study, StudyError, declared_studies, load_study


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m torchrl_bail.study", description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="action", required=True)
    listing = sub.add_parser("list", help="the declared studies, or one study's steps and jobs")
    listing.add_argument("study", nargs="?")
    for name, text in (("run", "run the study's steps in order (resumes)"),
                       ("status", "where each job stands, and the time left"),
                       ("report", "the study's tables and figures from its kept runs")):
        action = sub.add_parser(name, help=text)
        action.add_argument("study", help="a declared study's name or the path of a study's YAML file")
        action.add_argument("--workdir", type=Path, default=Path("."),
                            help="where the runs go (<workdir>/outputs); default: the current directory")
        action.add_argument("--data-dir", type=Path, default=None,
                            help="where batches are cached; default: $TORCHRL_BAIL_DATA_DIR or ~/.cache/torchrl_bail")
        if name == "run":
            action.add_argument("--cpus", default=None, help="run every job on these CPUs (taskset -c, e.g. 0)")
            action.add_argument("--steps", default=None,
                                help="only these steps (comma-separated numbers from 1, as `list` shows them)")
            action.epilog = ("Any other argument is a Hydra override for every step: a launcher "
                             "(hydra/launcher=joblib), its settings, any job key (eval.episodes=5).")
        if name == "report":
            action.add_argument("--results", type=Path, default=None,
                                help="where the kept runs and the report go; default: the study's `results`")
    return parser


def _data_dir(given: Path | None) -> Path:
    from torchrl_bail.data.cache import data_dir_of

    return data_dir_of(None, given)


def _list(study_name: str | None) -> int:
    if study_name is None:
        for name in declared_studies():
            study = load_study(name)
            print(f"{name}: {len(study.jobs)} jobs in {len(study.steps)} steps. {study.description}")
        return 0
    study = load_study(study_name)
    print(study.description)
    for i, step in enumerate(study.steps, 1):
        print(f"step {i}: {step.name} ({step.command}, {len(step.jobs)} jobs)")
        for job in step.jobs:
            print(f"  {job.name}: {' '.join(job.args)}")
    return 0


def _steps(study: Study, chosen: str | None) -> list[int]:
    if chosen is None:
        return list(range(len(study.steps)))
    try:
        steps = [int(s) - 1 for s in chosen.split(",")]
    except ValueError:
        steps = [-1]
    if any(not 0 <= s < len(study.steps) for s in steps):
        raise StudyError(f"--steps {chosen}: study {study.name} has steps 1-{len(study.steps)}")
    return steps


def _run_step(command: list[str], workdir: Path, env: dict[str, str]) -> tuple[int, int | None]:
    """Runs one step's command; a SIGTERM or SIGINT to this process goes on to the step (whose job checkpoints and
    exits, as on Slurm), and this waits for it. Returns the step's exit code and the signal that stopped it, if
    any."""
    proc = subprocess.Popen(command, cwd=workdir, env=env)
    received: list[int] = []

    def forward(signum, frame):
        received.append(signum)
        if proc.poll() is None:
            proc.send_signal(signum)

    previous = {sig: signal.signal(sig, forward) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        rc = proc.wait()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return rc, (received[0] if received else None)


def _run(args: argparse.Namespace, argv: list[str] | None = None) -> int:
    from torchrl_bail.study.sweeps import step_command  # loads torch: not for `list`

    study = load_study(args.study)
    workdir = args.workdir.absolute()
    workdir.mkdir(parents=True, exist_ok=True)
    data_dir = _data_dir(args.data_dir)
    pinned = []
    if args.cpus is not None:
        if shutil.which("taskset") is None:
            raise StudyError("--cpus needs taskset (util-linux)")
        pinned = ["taskset", "-c", str(args.cpus)]
    again = " ".join(["python -m torchrl_bail.study", *map(shlex.quote, sys.argv[1:] if argv is None else argv)])
    env = {**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1"), CONTINUE_WITH: again}
    for i in _steps(study, args.steps):
        step = study.steps[i]
        print(f"study {study.name}, step {i + 1} of {len(study.steps)}: {step.name} ({len(step.jobs)} jobs)",
              flush=True)
        command = [*pinned, *step_command(study.path, i + 1, step.command, workdir, data_dir, list(args.overrides))]
        rc, stopped_by = _run_step(command, workdir, env)
        if stopped_by is not None:
            print(f"study {study.name}: stopped by {signal.Signals(stopped_by).name} in step {i + 1}; the job that "
                  "ran saved its checkpoint: run the same command again to resume", file=sys.stderr)
            return 128 + stopped_by
        if rc != 0:
            print(f"study {study.name}: step {i + 1} failed (exit code {rc}); run the same command again to resume",
                  file=sys.stderr)
            return 1
    print(f"study {study.name}: every step done; `python -m torchrl_bail.study report {args.study} "
          f"--workdir {args.workdir}` makes its tables")
    return 0


def _status(args: argparse.Namespace) -> int:
    from torchrl_bail.study.status import job_states, summary_line

    study = load_study(args.study)
    states = job_states(study, args.workdir.absolute(), _data_dir(args.data_dir))
    width = max(len(job.name) for job, _ in states)
    for job, state in states:
        print(f"{job.name:<{width}}  {state}")
    print(summary_line(states))
    return 0


def _report(args: argparse.Namespace) -> int:
    from torchrl_bail.study.reports import build_report

    study = load_study(args.study)
    results = args.results or study.results
    if results is None:
        raise StudyError(f"study {study.name} names no results directory: give --results")
    for path in build_report(study, args.workdir.absolute(), results, _data_dir(args.data_dir)):
        print(path)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args, overrides = parser.parse_known_args(argv)
    if overrides and args.action != "run" or any(o.startswith("-") for o in overrides):
        parser.error(f"unrecognized arguments: {' '.join(overrides)}")
    args.overrides = overrides
    try:
        if args.action == "list":
            return _list(args.study)
        if args.action == "run":
            return _run(args, argv)
        return {"status": _status, "report": _report}[args.action](args)
    except StudyError as err:
        print(f"python -m torchrl_bail.study: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())

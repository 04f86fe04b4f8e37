"""The command-line front of ``train`` and ``collect``: every job's config composed and checked before anything
is written or imported, and a bad command line, config or batch reported in one line (exit status 2).

This module loads Hydra, OmegaConf and the schemas (:mod:`torchrl_bail.configuration.config`,
:mod:`torchrl_bail.configuration.algo_schemas`,
...) only, so a bad command line ends in about a second, before torch loads. What it reports in one line: the
errors of :mod:`torchrl_bail.core.errors`
(:data:`~torchrl_bail.core.errors.USER_ERRORS`) and Hydra's and OmegaConf's own; anything else keeps its traceback.

``--help`` lists the options of each config group as the files of ``conf/`` name them
(:func:`torchrl_bail.configuration.hydra_setup.group_options`).

Ctrl-C and SIGTERM (:mod:`torchrl_bail.core.interrupts`, installed here for the whole command): the running loop writes
its checkpoint at its next safe point, and the command ends with one line on stderr naming what was saved and the
command that continues (:func:`continue_command`), exit status 130 (SIGINT) or 143 (SIGTERM).
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib
import logging
import os
import shlex
import signal
import sys
from collections.abc import Callable, Iterator
from typing import Any

from torchrl_bail.configuration.config import validate_config
from torchrl_bail.configuration.hydra_setup import config_dir, group_options
from torchrl_bail.core.errors import USER_ERRORS, CommandLineError
from torchrl_bail.core.interrupts import Interrupted, handled, signal_name
from torchrl_bail.core.io import describe_file_error

__all__ = ["checkpoint_before_requeue", "continue_command", "describe_error", "describe_interrupt",
           "exit_on_config_error", "job_threads", "run_cli", "use_job_threads"]

log = logging.getLogger("torchrl_bail")


def job_threads(cfg, launcher=None) -> int | None:
    """Torch threads for this job: the ``threads`` config key when set (1 by default, ``conf/config.yaml``), else
    (``threads=null``) ``cores // n_jobs`` under the joblib launcher (so that side-by-side jobs do not oversubscribe
    the cores), else ``None`` (torch's default, one thread per core).

    Why 1 by default: the networks here (256 x 256, mini-batches of 100-1000) gain little from a second thread on a
    quiet machine and lose most of their pace when one of their threads is descheduled: beside busy processes two
    threads ran several times slower than one (``benchmarks/bench_threads.py``; the record is
    ``results/benchmarks/bench_threads.json``, the Benchmarks page quotes it)."""
    threads = cfg.get("threads")
    if threads:
        return int(threads)
    if launcher is None or "joblib" not in str(launcher.get("_target_", "")):
        return None
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    n_jobs = int(launcher.get("n_jobs") or 1)
    return max(1, cores // (cores if n_jobs < 0 else n_jobs))


def use_job_threads(cfg) -> None:
    """Sets torch's thread count to the job's (:func:`job_threads`, under the running Hydra launcher) when it has
    one: every ``train`` and ``collect`` job, so that side-by-side jobs share the cores and ``threads=N`` means the
    same to both commands. Logs the count the job runs with, among its first lines (``train`` also keeps it in
    ``summary.json`` as ``torch_threads``, a collection in its batch's metadata as ``collection_threads``)."""
    import torch
    from hydra.core.hydra_config import HydraConfig

    threads = job_threads(cfg, HydraConfig.get().get("launcher"))
    if threads is not None:
        torch.set_num_threads(threads)
    log.info("torch threads: %d (%s)", torch.get_num_threads(),
             "threads=null: torch's default" if threads is None else f"threads={threads}")


def describe_error(err: BaseException) -> str:
    """One line for a configuration error from Hydra, OmegaConf or :func:`validate_config`."""
    from hydra.errors import MissingConfigException, OverrideParseException
    from omegaconf.errors import ConfigAttributeError, ConfigKeyError, OmegaConfBaseException

    def one_line(text: str) -> str:
        return " ".join(line.strip() for line in str(text).splitlines() if line.strip())

    if isinstance(err, OverrideParseException):
        detail = one_line(err.message).split(" See https://")[0]
        return f"override {err.override!r} is not valid Hydra override syntax ({detail}); expected key=value"
    if isinstance(err, MissingConfigException) and err.options is not None and err.missing_cfg_file:
        group, _, option = err.missing_cfg_file.rpartition("/")
        choices = group_options().get(group, sorted(err.options))
        return f"{group}={option}: no such option in conf/{group}/; expected one of {', '.join(choices)}"
    unknown_key = isinstance(err, ConfigKeyError | ConfigAttributeError)
    if unknown_key and dataclasses.is_dataclass(err.object_type) and getattr(err, "full_key", None):
        known = ", ".join(f.name for f in dataclasses.fields(err.object_type))
        return f"config key {err.full_key}: no such key; expected one of {known}"
    if isinstance(err, OmegaConfBaseException) and getattr(err, "full_key", None):
        return f"config key {err.full_key}: {one_line(err.msg).split(' full_key:')[0]}"
    cause = err.__cause__ or err.__context__
    if isinstance(cause, OmegaConfBaseException | MissingConfigException):
        return describe_error(cause)
    return one_line(err)


def _config_errors() -> tuple[type[BaseException], ...]:
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    return (*USER_ERRORS, HydraException, OmegaConfBaseException)


def _job_overrides(argv: list[str]) -> list[list[str]]:
    """The override list of every job the command line launches: one for a run, one per sweep point for ``-m``
    (the basic sweeper's expansion); none when a flag (``--help``, ``--cfg`` ...) or another sweeper is in play."""
    flags = [a for a in argv if a.startswith("-")]
    overrides = [a for a in argv if not a.startswith("-")]
    if not flags:
        return [overrides]
    if not set(flags) <= {"-m", "--multirun"} or any(a.startswith("hydra/sweeper=") for a in overrides):
        return []
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parsed = OverridesParser.create().parse_overrides(overrides)
    return [job for batch in BasicSweeper.split_arguments(parsed, None) for job in batch]


def _precompose(argv: list[str]) -> None:
    """Composes and validates the config of every job before Hydra creates a run directory or launches a job."""
    jobs = _job_overrides(argv)
    if not jobs:
        return
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        for overrides in jobs:
            try:
                cfg = compose("config", overrides=overrides)
            except (TypeError, ValueError) as err:  # Hydra's own checks of odd overrides (e.g. "=3")
                raise CommandLineError(f"the overrides {' '.join(overrides)!r} do not compose: {err}; expected "
                                       "key=value items (see --help)") from None
            validate_config(cfg)


def import_schema_modules() -> None:
    """Imports the modules that define the registries' schemas (every algorithm, every behaviour recipe): torch with
    them, once, before a sweep's jobs are launched, after every job's config was checked.

    The registries read the schemas without importing their modules (:mod:`torchrl_bail.configuration.schema_reader`). A
    launcher
    that sends the jobs' configs to other processes (joblib, submitit) pickles them with cloudpickle, which copies a
    class by value when its module is not imported; the worker's copy would be no registered schema, and the job
    would fail. Imported, the classes pickle by reference, as the modules' own."""
    importlib.import_module("torchrl_bail.algorithms")
    importlib.import_module("torchrl_bail.behaviour")


@contextlib.contextmanager
def exit_on_config_error() -> Iterator[None]:
    """A configuration or dataset error, or a file-system fault (:func:`~torchrl_bail.core.io.describe_file_error`),
    inside the body ends the process: ONE line on stderr, exit code 2.

    Used around the whole command line (:func:`run_cli`) and inside each Hydra job, where it stops a sweep at
    the first bad job without Hydra's multi-line report. Other errors keep their traceback.
    """
    try:
        yield
    except _config_errors() as err:
        print(f"torchrl_bail: {describe_error(err)}", file=sys.stderr)
        sys.exit(2)
    except Exception as err:  # a full disk, no permission, a read-only file system: the file and the remedy
        message = describe_file_error(err)
        if message is None:
            raise
        print(f"torchrl_bail: {message}", file=sys.stderr)
        sys.exit(2)


#: the environment variable in which a command that runs an entry point for its own names the command line that
#: continues it, for the line an interrupted run ends with (:func:`describe_interrupt`)
CONTINUE_WITH = "TORCHRL_BAIL_CONTINUE_WITH"


def continue_command(command: str, argv: list[str]) -> str:
    """The command line that continues an interrupted ``command argv``: the same, without a ``resume=`` override
    (``resume=false`` would start over, ``resume=<dir>`` is refused once the run directory has a checkpoint of its
    own; the default, ``resume=auto``, continues).

    Examples:
        >>> continue_command("python -m torchrl_bail.train", ["+exp=hopper_ddpg05", "resume=false", "algo.name=a b"])
        "python -m torchrl_bail.train +exp=hopper_ddpg05 'algo.name=a b'"
    """
    kept = [a for a in argv if a.partition("=")[0].lstrip("+") != "resume"]
    return " ".join([command, *map(shlex.quote, kept)])


def describe_interrupt(err: Interrupted, command: str) -> str:
    """The one line an interrupted command ends with: the signal, what was saved, the command that continues."""
    saved = (f"saved {err.saved}" if err.saved else
             "stopped before anything new was saved (the last checkpoint, if any, is kept)")
    return f"interrupted by {signal_name(err.signum)}: {saved}; continue with: {command}"


def _preemption_signal() -> int | None:
    """The signal submitit (the Slurm launcher) requeues the job on, when this process is a submitit job whose
    handler for it is in place; ``None`` otherwise."""
    if "SUBMITIT_FOLDER" not in os.environ:
        return None
    sig = getattr(signal, f"SIG{os.environ.get('SUBMITIT_PREEMPT_SIGNAL', 'USR2')}", None)
    return sig if sig is not None and callable(signal.getsignal(sig)) else None


#: the exit status of a Slurm job that saved its work on SIGTERM (128 + 15, as a shell reports a SIGTERM'd process)
SIGTERM_EXIT = 128 + signal.SIGTERM


def _do_nothing(signum: int, frame: Any) -> None:
    """A signal handler that ignores its signal without a word (unlike ``SIG_IGN``, not inherited by a child)."""


@contextlib.contextmanager
def checkpoint_before_requeue() -> Iterator[None]:
    """In a Slurm job (hydra-submitit launcher), both ways Slurm stops a job save the work first: the running loop
    writes its checkpoint at its next safe point (:mod:`torchrl_bail.core.interrupts`: within one update, or one episode
    of
    a collection), then

    - on submitit's signal (USR2, ``signal_delay_s`` before the **time limit**): submitit's own handler requeues the
      job (``scontrol requeue``) and exits;
    - on **SIGTERM** (a preemption under ``PreemptMode=REQUEUE``, ``scontrol requeue``, ``scancel``): the job exits at
      once with status 143 and no traceback, so that Slurm's own requeue starts it again (or, after a plain
      ``scancel``, the next launch of the same sweep resumes it). submitit ignores SIGTERM; left to it, the job would
      run on until Slurm's SIGKILL (``KillWait`` later) and lose the work since its last checkpoint. No result is
      written for submitit (``SystemExit`` passes its error handler), so the launcher keeps waiting for the
      requeued job.

    SIGCONT, which Slurm sends with each signal, is ignored silently for the rest of the job, and so is SIGTERM from
    the handover to submitit's requeue on: submitit's handlers for them only log, and a log record written from a
    signal handler while the interrupted code writes the same log file fails with "reentrant call" and a traceback
    in the job's log.

    Once the body is done, the time-limit signal is ignored (a finished job that Slurm signals in its last minute
    still ends COMPLETED). No named semaphore is left for Python's resource tracker, which Slurm's requeue kills with
    the job step (:mod:`torchrl_bail.data.local_buffer`, :mod:`torchrl_bail.core.progress`).

    Elsewhere a no-op (the entry point's :func:`run_cli` handles SIGINT and SIGTERM)."""
    sig = _preemption_signal()
    if sig is None:
        yield
        return
    signal.signal(signal.SIGCONT, signal.SIG_DFL)  # for the rest of the job (see above)
    try:
        with handled([sig, signal.SIGTERM]):
            yield
    except Interrupted as err:
        if err.signum not in (sig, signal.SIGTERM):
            raise
        signum, saved = err.signum, "saved " + err.saved if err.saved else "nothing new saved"
    else:
        # the work is done: a time-limit signal from now on would only requeue a finished run or, as the interpreter
        # shuts down (its handlers back to the default), end the job by that signal, and Slurm would record it FAILED
        signal.signal(sig, signal.SIG_IGN)
        return
    if signum == signal.SIGTERM:
        print(f"torchrl_bail: SIGTERM from Slurm (preemption, requeue or cancel): {saved}; exiting for Slurm's "
              "requeue", file=sys.stderr, flush=True)
        raise SystemExit(SIGTERM_EXIT)
    print(f"torchrl_bail: {signal_name(sig)} from Slurm: {saved}; handing over to submitit's requeue",
          file=sys.stderr, flush=True)
    import subprocess

    # Slurm stops the requeued job step with SIGCONT and SIGTERM, which submitit's handler only logs; from here on the
    # job only ends (submitit's handler exits or raises), so SIGTERM does nothing, silently, until the process is gone
    # (logging's flush at exit included); a Python handler, so the `scontrol` it runs gets the default SIGTERM back
    signal.signal(signal.SIGTERM, _do_nothing)
    try:
        signal.getsignal(sig)(sig, None)  # submitit: requeue, exit
    except subprocess.CalledProcessError as err:
        # Slurm carries the requeue out by stopping the job step with SIGTERM, and that can reach submitit's
        # `scontrol requeue` before it has exited (seen on a loaded core): the job is being requeued, so it ends as
        # on Slurm's SIGTERM, without a result for submitit
        if err.returncode != -signal.SIGTERM:
            raise
        print("torchrl_bail: Slurm stopped the job while requeueing it; exiting for the requeue", file=sys.stderr,
              flush=True)
        raise SystemExit(SIGTERM_EXIT) from None


def run_cli(hydra_main: Callable[[], Any], extra_overrides: list[str] | None = None, *,
            command: str | None = None) -> None:
    """Runs a ``@hydra.main`` function after composing and validating every job's config, so that a bad command
    line ends with one line on stderr and exit code 2 before anything is written or imported.

    SIGINT and SIGTERM end it at the running loop's next checkpoint with one line on stderr and exit status 130 or
    143 (:func:`describe_interrupt`; ``command``, e.g. ``python -m torchrl_bail.train``, starts the command line
    that continues it)."""
    os.environ["HYDRA_FULL_ERROR"] = "1"  # Hydra re-raises instead of printing its own multi-line report
    user_argv = sys.argv[1:]
    argv = [*user_argv, *(extra_overrides or [])]
    with handled():
        try:
            with exit_on_config_error():
                _precompose(argv)
                if {"-m", "--multirun"} & set(argv):
                    import_schema_modules()
                sys.argv = [sys.argv[0], *argv]
                hydra_main()
        except Interrupted as err:
            # a command that runs this one for its own (python -m torchrl_bail.study run) names itself instead
            again = (os.environ.get(CONTINUE_WITH)
                     or continue_command(command or f"python {sys.argv[0]}", user_argv))
            sys.stdout.flush()
            print(f"torchrl_bail: {describe_interrupt(err, again)}", file=sys.stderr, flush=True)
            sys.exit(err.exit_status)

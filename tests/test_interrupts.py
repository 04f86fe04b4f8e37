"""Ctrl-C and SIGTERM end a command in one line and keep the work.

Real, unpatched ``python -m torchrl_bail.collect`` and ``python -m torchrl_bail.train`` processes (tiny configs) are
interrupted with SIGINT and SIGTERM: each writes its checkpoint at the interrupt, ends with exit status 130 / 143 and
one line on stderr naming what it saved and the command that continues, and that command makes the same batch (every
data file, byte for byte) or the same ``summary.json`` and scalar logs as a run that was never interrupted. The
children get SIGINT's default handler back (``preexec_fn``): a suite started in the background hands them SIGINT
ignored, and an ignored SIGINT stays ignored by design. The unit part checks :mod:`torchrl_bail.core.interrupts` itself.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from _summaries import comparable

from torchrl_bail.cli import checkpoint_before_requeue, continue_command
from torchrl_bail.core import interrupts
from torchrl_bail.data.locks import PARTIAL, SCRATCH


@pytest.fixture(autouse=True)
def _signal_handlers_restored():
    """Under a stand-in submitit job, ``checkpoint_before_requeue`` leaves SIGCONT and SIGTERM silenced for the rest
    of the process (a job that only ends): this test process gets its own handlers back after each test."""
    kept = {sig: signal.getsignal(sig) for sig in (signal.SIGCONT, signal.SIGTERM, signal.SIGUSR2, signal.SIGINT)}
    yield
    for sig, handler in kept.items():
        signal.signal(sig, handler)

ROOT = Path(__file__).resolve().parents[1]
#: a DDPG batch of 2000 Hopper steps from a tiny agent, short episodes: a collection of a few seconds
TINY_COLLECT = ["+exp=hopper_ddpg05", "batch.steps=2000", "batch.start_steps=100", "env.max_episode_steps=40",
                "batch.agent.actor_hidden=[16,16]", "batch.agent.critic_hidden=[16,16]", "batch.agent.batch_size=16",
                "progress=false"]
#: BC on a 1000-step batch: 1200 updates, an evaluation every 300
TINY_TRAIN = ["+exp=hopper_ddpg05", "preset=quick", "batch.steps=1000", "batch.start_steps=200",
              "batch.agent.actor_hidden=[16,16]", "batch.agent.critic_hidden=[16,16]", "env.max_episode_steps=50",
              "eval.episodes=2", "eval.max_steps=50", "returns.horizon=50", "progress=false", "algo=bc",
              "algo.policy.hidden=[64,64]", "algo.batch_size=100", "algo.epochs=0.12", "eval.every_epochs=0.03"]
METADATA_VOLATILE = ("created_at", "collection_wall_time_s", "env_steps_per_s", "updates_per_s", "resumed_from_step")


def _env() -> dict[str, str]:
    src = str(ROOT / "src")
    path = os.environ.get("PYTHONPATH")
    return {**os.environ, "PYTHONPATH": f"{src}{os.pathsep}{path}" if path else src, "RL_WARNINGS": "0",
            "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def _default_sigint() -> None:
    # a suite started as a background job hands its children SIGINT ignored: Ctrl-C's handler is put back
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _command(module: str, args: list[str]) -> list[str]:
    return [sys.executable, "-m", f"torchrl_bail.{module}", *args]


def _run(module: str, args: list[str], timeout: float = 300) -> subprocess.CompletedProcess:
    done = subprocess.run(_command(module, args), capture_output=True, text=True, env=_env(), cwd=ROOT,
                          timeout=timeout, preexec_fn=_default_sigint)
    assert done.returncode == 0, done.stderr[-3000:]
    return done


def _interrupt(module: str, args: list[str], sig: int, ready, timeout: float = 300) -> tuple[int, str]:
    """Starts the command, sends ``sig`` once ``ready()`` holds; returns ``(exit status, stderr)``."""
    proc = subprocess.Popen(_command(module, args), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            env=_env(), cwd=ROOT, preexec_fn=_default_sigint)
    try:
        deadline = time.time() + timeout
        while not ready() and proc.poll() is None and time.time() < deadline:
            time.sleep(0.02)
        assert proc.poll() is None, f"the command ended before the signal: {proc.stderr.read()[-3000:]}"
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return proc.returncode, err


def _the_line(stderr: str, sig: int, continues: list[str], module: str) -> str:
    lines = stderr.strip().splitlines()
    assert len(lines) == 1, f"one line on stderr, got:\n{stderr[-3000:]}"
    (line,) = lines
    assert line.startswith(f"torchrl_bail: interrupted by {signal.Signals(sig).name}: saved "), line
    assert "Traceback" not in stderr
    assert line.endswith(f"; continue with: {continue_command(f'python -m torchrl_bail.{module}', continues)}"), line
    return line


def _batch_files(data_dir: Path) -> dict[str, object]:
    (batch,) = [p for p in data_dir.iterdir() if (p / "metadata.json").is_file()]
    out: dict[str, object] = {}
    for path in sorted(p for p in batch.rglob("*") if p.is_file()):
        if path.name == "metadata.json":
            meta = json.loads(path.read_text())
            out[path.name] = {k: v for k, v in meta.items() if k not in METADATA_VOLATILE}
        else:
            out[path.relative_to(batch).as_posix()] = path.read_bytes()
    return out


@pytest.fixture(scope="module")
def reference_batch(tmp_path_factory):
    root = tmp_path_factory.mktemp("reference_batch")
    _run("collect", [*TINY_COLLECT, f"data_dir={root / 'data'}", f"hydra.run.dir={root / 'hydra'}"])
    return _batch_files(root / "data")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_an_interrupted_collection_checkpoints_says_so_in_one_line_and_continues_to_the_same_batch(
        tmp_path, reference_batch, sig):
    data_dir = tmp_path / "data"
    args = [*TINY_COLLECT, f"data_dir={data_dir}", f"hydra.run.dir={tmp_path / 'hydra'}"]

    def collecting() -> bool:  # the scratch directory appears once the collection's loop is being set up
        return any((data_dir / SCRATCH).glob("*")) if (data_dir / SCRATCH).is_dir() else False

    status, stderr = _interrupt("collect", args, sig, collecting)
    assert status == 128 + sig
    line = _the_line(stderr, sig, args, "collect")
    (state,) = list((data_dir / PARTIAL).glob("*/state.pt"))
    assert "the collection checkpoint at env step " in line and str(state.parent) in line
    step = int(line.split("at env step ")[1].split()[0])
    assert 0 < step < 2000
    assert not [p for p in data_dir.iterdir() if (p / "metadata.json").is_file()], "no batch yet"
    assert list((data_dir / SCRATCH).glob("*")) == [], "the scratch directory went with the process"
    _run("collect", args)  # the same command continues
    meta = json.loads(next(data_dir.glob("*/metadata.json")).read_text())
    assert meta["resumed_from_step"] == step
    assert _batch_files(data_dir) == reference_batch, "every file of the batch, byte for byte"
    assert list((data_dir / PARTIAL).iterdir()) == []


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """The batch (collected once) and the uninterrupted runs' outputs: ``{(seeds, seed): outputs}``."""
    root = tmp_path_factory.mktemp("reference_runs")
    data = [f"data_dir={root / 'data'}"]
    _run("collect", [*TINY_TRAIN, *data, f"hydra.run.dir={root / 'collect'}"])
    _run("train", [*TINY_TRAIN, *data, f"hydra.run.dir={root / 'single' / 'seed1'}"])
    _run("train", [*TINY_TRAIN, *data, "seeds=[1, 2]", f"hydra.run.dir={root / 'stacked' / 'seed1'}"])
    return data, {(None, 1): _outputs(root / "single" / "seed1"),
                  **{((1, 2), s): _outputs(root / "stacked" / f"seed{s}") for s in (1, 2)}}


def _outputs(run_dir: Path) -> dict[str, object]:
    summary = json.loads((run_dir / "summary.json").read_text())
    logs = {p.relative_to(run_dir).as_posix(): p.read_text() for p in sorted((run_dir / "logs").rglob("*.csv"))}
    return {"summary": comparable(summary), "logs": logs,
            "policy": (run_dir / "policy.pt").stat().st_size > 0}


@pytest.mark.parametrize("sig,seeds", [(signal.SIGINT, None), (signal.SIGTERM, None), (signal.SIGTERM, (1, 2))],
                         ids=["SIGINT", "SIGTERM", "SIGTERM-stacked"])
def test_an_interrupted_training_run_checkpoints_says_so_in_one_line_and_continues_to_the_same_summary(
        tmp_path, trained, sig, seeds):
    data, reference = trained
    args = [*TINY_TRAIN, *data, f"hydra.run.dir={tmp_path / 'seed1'}", *([f"seeds={list(seeds)}"] if seeds else [])]
    dirs = [tmp_path / f"seed{s}" for s in seeds or [1]]
    first = dirs[0] / "checkpoint.pt"

    def training() -> bool:  # the checkpoint before the first update
        return first.is_file()

    status, stderr = _interrupt("train", args, sig, training)
    assert status == 128 + sig
    line = _the_line(stderr, sig, args, "train")
    assert "the checkpoint at iteration " in line and all(str(d / "checkpoint.pt") in line for d in dirs)
    iteration = int(line.split("at iteration ")[1].split()[0])
    assert 0 < iteration < 1200, "stopped mid-training, after an update"
    assert not any((d / "summary.json").exists() for d in dirs)
    _run("train", args)  # the same command continues
    for seed, run_dir in zip(seeds or [1], dirs, strict=True):
        summary = json.loads((run_dir / "summary.json").read_text())
        assert summary["resumed_from_iteration"] == [iteration]
        assert _outputs(run_dir) == reference[seeds, seed], "summary.json and every scalar log, as if never interrupted"


# -- the requests themselves -------------------------------------------------------------------------------------
def test_a_signal_outside_a_loop_stops_at_once_and_an_ignored_signal_stays_ignored():
    previous = signal.signal(signal.SIGTERM, signal.SIG_IGN)
    try:
        with interrupts.handled():
            assert signal.getsignal(signal.SIGTERM) is signal.SIG_IGN, "an ignored signal stays ignored"
            signal.raise_signal(signal.SIGTERM)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        with interrupts.handled():
            with pytest.raises(interrupts.Interrupted) as raised:
                signal.raise_signal(signal.SIGTERM)
        assert raised.value.exit_status == 143 and raised.value.saved is None
        assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL, "the previous handler is put back"
    finally:
        signal.signal(signal.SIGTERM, previous)


@pytest.fixture
def sigint_not_ignored():
    """Python's own SIGINT handler for the test: a suite started as a background job runs with SIGINT ignored,
    which :func:`interrupts.handled` keeps ignored, so a raised SIGINT would never reach it."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def test_a_second_signal_stops_at_once_except_while_a_checkpoint_is_written(sigint_not_ignored):
    with interrupts.handled():
        with pytest.raises(interrupts.Interrupted) as raised:
            with interrupts.safe_points():
                signal.raise_signal(signal.SIGINT)
                assert interrupts.requested() == signal.SIGINT, "the first one waits for a safe point"
                with interrupts.saving():
                    signal.raise_signal(signal.SIGINT)  # waits for the write
                    written = True
                assert written and interrupts.requested() == signal.SIGINT
                signal.raise_signal(signal.SIGINT)  # not during a write: at once
                pytest.fail("the second signal did not stop the process")
        assert raised.value.signum == signal.SIGINT and raised.value.saved is None
        with pytest.raises(interrupts.Interrupted):
            with interrupts.safe_points():
                signal.raise_signal(signal.SIGINT)
        # a region left without a safe point on the way raises for the pending request, saying nothing was saved


def test_the_continue_command_drops_resume_overrides():
    assert continue_command("python -m torchrl_bail.train", ["+exp=hopper_ddpg05", "resume=false", "seed=2"]) == \
        "python -m torchrl_bail.train +exp=hopper_ddpg05 seed=2"
    assert continue_command("python -m torchrl_bail.collect", ["+resume=/x", "batch.agent.actor_hidden=[16,16]"]) == \
        "python -m torchrl_bail.collect 'batch.agent.actor_hidden=[16,16]'"


def test_a_slurm_preemption_signal_checkpoints_first_then_goes_to_submitits_requeue(monkeypatch, capsys):
    """Under submitit (``SUBMITIT_FOLDER``), its preemption signal (USR2) is a request the loop honours at its next
    safe point; then submitit's own handler (here a stand-in that records its call) requeues the job."""
    events = []

    class Requeued(SystemExit):
        pass

    def submitit_handler(signum, frame):
        events.append("requeue")
        raise Requeued(-1)

    monkeypatch.setenv("SUBMITIT_FOLDER", "/tmp/submitit")
    monkeypatch.delenv("SUBMITIT_PREEMPT_SIGNAL", raising=False)
    signal.signal(signal.SIGUSR2, submitit_handler)  # the fixture puts every handler back
    with pytest.raises(Requeued):
        with checkpoint_before_requeue():
            with interrupts.safe_points():
                signal.raise_signal(signal.SIGUSR2)
                events.append("update")  # the signal waits for the safe point
                assert interrupts.requested() == signal.SIGUSR2
                events.append("checkpoint")
                interrupts.stop("the checkpoint at iteration 3 of 9 in run/checkpoint.pt")
    assert events == ["update", "checkpoint", "requeue"]
    assert signal.getsignal(signal.SIGUSR2) is submitit_handler, "submitit's handler is back in place"
    assert capsys.readouterr().err.strip() == (
        "torchrl_bail: SIGUSR2 from Slurm: saved the checkpoint at iteration 3 of 9 in run/checkpoint.pt; "
        "handing over to submitit's requeue")
    monkeypatch.delenv("SUBMITIT_FOLDER")  # not a submitit job: USR2 is left alone
    with pytest.raises(Requeued), checkpoint_before_requeue(), interrupts.safe_points():
        signal.raise_signal(signal.SIGUSR2)


def test_under_submitit_slurms_sigcont_and_the_handovers_sigterm_reach_no_logging_handler(monkeypatch):
    """Slurm sends SIGCONT with each signal, and SIGCONT and SIGTERM when it stops a requeued job step; submitit's
    handlers for them write a log record, and one written while the interrupted code writes the same log file fails
    ("reentrant call", a traceback in the job's log, seen in a time-limit drill). So neither reaches them: not while
    the loop runs, nor while submitit's own requeue runs, nor after it (the job is ending: logging flushes its files
    at exit)."""
    logged, requeue_saw = [], []

    class Requeued(SystemExit):
        pass

    def submitit_requeue(signum, frame):  # Slurm stops the step as soon as `scontrol requeue` is issued
        signal.raise_signal(signal.SIGCONT)
        signal.raise_signal(signal.SIGTERM)
        requeue_saw.append("requeued")
        raise Requeued(-1)

    def submitit_bypass(signum, frame):
        logged.append(signal.Signals(signum).name)

    monkeypatch.setenv("SUBMITIT_FOLDER", "/tmp/submitit")
    monkeypatch.delenv("SUBMITIT_PREEMPT_SIGNAL", raising=False)
    for sig in (signal.SIGUSR2, signal.SIGTERM, signal.SIGCONT):  # the fixture puts every handler back
        signal.signal(sig, submitit_requeue if sig == signal.SIGUSR2 else submitit_bypass)
    with pytest.raises(Requeued), checkpoint_before_requeue(), interrupts.safe_points():
        signal.raise_signal(signal.SIGCONT)
        signal.raise_signal(signal.SIGUSR2)
        interrupts.stop("the checkpoint at iteration 4 of 9 in run/checkpoint.pt")
    assert requeue_saw == ["requeued"] and logged == [], "submitit's logging handlers were called"
    signal.raise_signal(signal.SIGCONT)
    signal.raise_signal(signal.SIGTERM)
    assert logged == [], "submitit's logging handlers are back while the job ends"


def test_under_submitit_sigterm_checkpoints_first_then_exits_143_for_slurms_requeue(monkeypatch, capsys):
    """Preemption, ``scontrol requeue`` and ``scancel`` send SIGTERM, which submitit only logs: the loop checkpoints at
    its next safe point, then the job exits 143 through ``SystemExit`` (which submitit's error handler lets pass, so no
    result is written and the launcher waits for the requeued job), with one line and submitit's handlers back; after
    a finished body, the time-limit signal is ignored."""
    calls = []
    monkeypatch.setenv("SUBMITIT_FOLDER", "/tmp/submitit")
    monkeypatch.delenv("SUBMITIT_PREEMPT_SIGNAL", raising=False)
    for sig in (signal.SIGUSR2, signal.SIGTERM):  # the fixture puts every handler back
        signal.signal(sig, lambda signum, frame: calls.append(signum))
    submitit_term = signal.getsignal(signal.SIGTERM)
    with pytest.raises(SystemExit) as stopped:
        with checkpoint_before_requeue(), interrupts.safe_points():
            signal.raise_signal(signal.SIGTERM)
            assert interrupts.requested() == signal.SIGTERM
            interrupts.stop("the checkpoint at iteration 4 of 9 in run/checkpoint.pt")
    assert stopped.value.code == 143 and calls == [], "submitit's handlers were not called"
    assert signal.getsignal(signal.SIGTERM) is submitit_term
    assert capsys.readouterr().err.strip() == (
        "torchrl_bail: SIGTERM from Slurm (preemption, requeue or cancel): saved the checkpoint at iteration 4 of "
        "9 in run/checkpoint.pt; exiting for Slurm's requeue")
    with checkpoint_before_requeue():
        pass
    assert signal.getsignal(signal.SIGUSR2) is signal.SIG_IGN


def test_under_submitit_a_requeue_command_stopped_by_the_requeue_ends_the_job_for_slurms_requeue(monkeypatch, capsys):
    """On the time-limit signal submitit runs ``scontrol requeue``; Slurm carries it out by stopping the job step, and
    on a loaded core that SIGTERM can reach ``scontrol`` before it has exited. submitit then raises
    ``CalledProcessError`` (-15); the job must end as on Slurm's SIGTERM (exit 143, one line, no result for submitit)
    rather than fail. Any other failure of submitit's handler still propagates."""
    import subprocess

    monkeypatch.setenv("SUBMITIT_FOLDER", "/tmp/submitit")
    monkeypatch.delenv("SUBMITIT_PREEMPT_SIGNAL", raising=False)
    failures = iter([-signal.SIGTERM, 1])

    def submitit_requeue(signum, frame):
        raise subprocess.CalledProcessError(next(failures), ["scontrol", "requeue", "9"])

    for sig in (signal.SIGUSR2, signal.SIGTERM):  # the fixture puts every handler back
        signal.signal(sig, submitit_requeue if sig == signal.SIGUSR2 else signal.SIG_DFL)
    with pytest.raises(SystemExit) as stopped:
        with checkpoint_before_requeue(), interrupts.safe_points():
            signal.raise_signal(signal.SIGUSR2)
            interrupts.stop("the checkpoint at iteration 4 of 9 in run/checkpoint.pt")
    assert stopped.value.code == 143
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        "torchrl_bail: Slurm stopped the job while requeueing it; exiting for the requeue")
    signal.signal(signal.SIGUSR2, submitit_requeue)
    with pytest.raises(subprocess.CalledProcessError):
        with checkpoint_before_requeue(), interrupts.safe_points():
            signal.raise_signal(signal.SIGUSR2)
            interrupts.stop("the checkpoint at iteration 5 of 9 in run/checkpoint.pt")

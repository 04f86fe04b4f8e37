"""Kill drill: does a long job survive SIGKILL, Ctrl-C and SIGTERM? ``python benchmarks/kill_drill.py --trials 10``

Runs a reference job once, uninterrupted. Then each trial starts the same job in a fresh directory, SIGKILLs it
after a random delay (one or two times, each kill followed by a restart of the same command, which resumes), lets
the last start finish, and compares its outputs with the reference's. ``--signal INT`` or ``--signal TERM`` sends
that signal instead, and each interrupted start must also end as the docs promise: exit status 130 / 143 and one
line on stderr, ``torchrl_bail: interrupted by SIG...: saved ...; continue with: <the command>`` (a start that
breaks it counts as a mismatch). The comparison: for training, ``summary.json`` (wall time,
paths and ``resumed_from_iteration`` aside), every CSV scalar log byte for byte, and the final weights of every
network. It prints one line per trial and how many trials matched; the exit status is 1 when any did not.

A kill can land anywhere: during start-up or the batch load (nothing to resume: the restart starts fresh),
during BAIL's envelope fit (before the first checkpoint), during training or an evaluation (resume from the last
checkpoint), or after the end (the restart reports the run complete). ``--target`` picks what is drilled:

* ``training`` (default): ``python -m torchrl_bail.train`` at a tiny scale (a 1500-step batch, small networks);
  the batch is collected once beforehand so every process trains on the same cached batch.
* ``collection``: ``python -m torchrl_bail.collect`` into a per-trial data directory, checkpointing every 150 env
  steps, comparing the batch files (metadata timings and ``resumed_from_step`` aside): a killed collection resumes
  from its last checkpoint (``<data_dir>/.partial``) and must give the reference's bytes.
  ``benchmarks/_collection_drill.py`` runs the same check for the SAC run too.

Its record (``--json``; default ``results/benchmarks/kill_drill.json``, a drill of another algorithm or signal
belongs in ``kill_drill_<what>.json``) keeps the command, checkout, machine and load, and every trial: when each
signal landed, what the run resumed from, and what differed.

Extra Hydra overrides follow ``--`` (e.g. ``-- algo.epochs=0.5``). A target is a class with ``command``,
``setup``, ``outputs`` and a ``progress_file``; registering another one in :data:`TARGETS` is all the drill needs.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from _bench import Record, add_record_argument

ROOT = Path(__file__).resolve().parents[1]
#: a batch of 1500 Hopper steps from a tiny agent, short evaluations: seconds per job
TINY = [
    "+exp=hopper_ddpg05", "preset=quick", "batch.steps=1500", "batch.start_steps=300",
    "batch.agent.actor_hidden=[32,32]", "batch.agent.critic_hidden=[32,32]", "env.max_episode_steps=200",
    "eval.episodes=2", "eval.max_steps=200", "returns.horizon=200", "progress=false",
]
#: summary entries that legitimately differ between an interrupted and an uninterrupted run
VOLATILE = ("wall_time_s", "run_dir", "batch_path", "resumed_from_iteration")


#: the drilled run's length and evaluations, and its networks' width: enough updates that training, not the process's
#: start-up (3-4 s of imports), fills most of the kill window, with an evaluation (and checkpoint) every tenth of them,
#: so that most kills land between checkpoints (300 updates took 0.5 s of a 6 s run: 2 kills in 16 landed mid-run)
DRILL_UPDATES, DRILL_EVALUATIONS, DRILL_HIDDEN = 3000, 10, (32, 32)


def _checkout(module: str):
    """This checkout's ``torchrl_bail.<module>`` (``algo_schemas``, the algorithm registry, and ``config_builders``:
    both torch-free)."""
    if str(ROOT / "src") not in sys.path:
        sys.path.insert(0, str(ROOT / "src"))
    return importlib.import_module(f"torchrl_bail.{module}")


def _drill(algo: str) -> list[str]:
    """An algorithm's overrides for the drilled run: its tiny run (its registry entry's, the contract suite's,
    :func:`torchrl_bail.configuration.config_builders.tiny_run_overrides`) at the drill's length."""
    return _checkout("config_builders").tiny_run_overrides(algo, DRILL_UPDATES, DRILL_HIDDEN,
                                                           evaluations=DRILL_EVALUATIONS)


def _env() -> dict:
    src = str(ROOT / "src")
    path = os.environ.get("PYTHONPATH")
    return {**os.environ, "PYTHONPATH": f"{src}{os.pathsep}{path}" if path else src, "RL_WARNINGS": "0",
            "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1"), "HYDRA_FULL_ERROR": "1"}


def _sha1(path: Path) -> str:
    return hashlib.sha1(path.read_bytes()).hexdigest()


class TrainingTarget:
    """``python -m torchrl_bail.train`` into ``run_dir``; outputs: summary, scalar logs, final weights."""

    name = "training"
    #: a file whose appearance marks the first point a restart can resume from
    progress_file = "checkpoint.pt"
    #: a file whose appearance marks a finished run (a restart reports it complete)
    done_pattern = "summary.json"

    def __init__(self, algo: str, overrides: list[str], data_dir: Path) -> None:
        self.algo = algo
        self.overrides = [*TINY, f"algo={algo}", *_drill(algo), *overrides, f"data_dir={data_dir}"]
        self.data_dir = data_dir

    def setup(self) -> None:
        """Collects the batch once, so that no trial's timing includes it and every job reads the same file."""
        subprocess.run([sys.executable, "-m", "torchrl_bail.collect", *self.overrides, "hydra.run.dir=" +
                        str(self.data_dir / "collect_run")], env=_env(), check=True, capture_output=True, cwd=ROOT)

    def command(self, run_dir: Path) -> list[str]:
        return [sys.executable, "-m", "torchrl_bail.train", *self.overrides, f"hydra.run.dir={run_dir}"]

    def outputs(self, run_dir: Path) -> dict[str, object]:
        import torch

        summary = json.loads((run_dir / "summary.json").read_text())
        out = {"summary": {k: v for k, v in summary.items() if k not in VOLATILE}}
        for path in sorted((run_dir / "logs" / "scalars").rglob("*.csv")):
            out[path.relative_to(run_dir).as_posix()] = path.read_text()
        state = torch.load(run_dir / "checkpoint.pt", map_location="cpu", weights_only=False)["algorithm"]["modules"]
        out["weights"] = {f"{m}/{k}": hashlib.sha1(v.cpu().contiguous().numpy().tobytes()).hexdigest()
                          for m, sd in state.items() for k, v in sd.items() if hasattr(v, "numpy")}
        return out

    def resumed_from(self, run_dir: Path) -> list[int]:
        return json.loads((run_dir / "summary.json").read_text()).get("resumed_from_iteration", [])


class CollectionTarget:
    """``python -m torchrl_bail.collect`` into a per-run data directory; outputs: every file of the batch."""

    name = "collection"
    progress_file = "data/.partial"  # appears with the first checkpoint
    done_pattern = "data/*/metadata.json"  # the finished batch
    #: metadata entries that legitimately differ between runs
    VOLATILE_METADATA = ("created_at", "collection_wall_time_s", "env_steps_per_s", "updates_per_s",
                         "resumed_from_step")

    def __init__(self, algo: str, overrides: list[str], data_dir: Path) -> None:
        self.overrides = [*TINY, "batch.checkpoint_every_steps=150", *overrides]

    def setup(self) -> None:
        """Nothing: collecting is what is drilled."""

    def command(self, run_dir: Path) -> list[str]:
        return [sys.executable, "-m", "torchrl_bail.collect", *self.overrides, f"data_dir={run_dir / 'data'}",
                f"hydra.run.dir={run_dir}"]

    def outputs(self, run_dir: Path) -> dict[str, object]:
        out: dict[str, object] = {}
        root = run_dir / "data"
        for path in sorted(p for p in root.rglob("*") if p.is_file()):
            rel = path.relative_to(root).as_posix()
            if path.name == "metadata.json":
                meta = json.loads(path.read_text())
                out[rel] = {k: v for k, v in meta.items() if k not in self.VOLATILE_METADATA}
            else:
                out[rel] = _sha1(path)
        return out

    def resumed_from(self, run_dir: Path) -> list[int]:
        steps = []
        for meta in (run_dir / "data").glob("*/metadata.json"):
            step = json.loads(meta.read_text()).get("resumed_from_step")
            steps += [] if step is None else [step]
        return steps


TARGETS = {"training": TrainingTarget, "collection": CollectionTarget}

#: where a signal can land, judged from what the run directory holds right after it
STAGES = ("before the first checkpoint", "mid-run", "after the end")


def stage(target, run_dir: Path) -> str:
    """Where the signal just sent landed: before ``target``'s first checkpoint, between checkpoints, or after the
    run had finished (its last output written, the process still exiting)."""
    if any(run_dir.glob(target.done_pattern)):
        return STAGES[2]
    return STAGES[1] if (run_dir / target.progress_file).exists() else STAGES[0]


def _default_sigint() -> None:
    """A drill started in the background hands its children SIGINT ignored, which they keep: put Ctrl-C back."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def interrupt_fault(sig: int, returncode: int, stderr: str) -> str | None:
    """What is wrong with how a job ended after ``sig`` (``None``: exit status ``128 + sig``, no traceback, and one
    line on stderr naming what was saved and the command that continues).

    Examples:
        >>> interrupt_fault(signal.SIGINT, 130, "torchrl_bail: interrupted by SIGINT: saved; continue with: python -m")
        >>> interrupt_fault(signal.SIGTERM, -15, "")
        'exit status -15, not 143'
    """
    lines = stderr.strip().splitlines()
    if returncode != 128 + sig:
        return f"exit status {returncode}, not {128 + sig}"
    if len(lines) != 1:
        return f"{len(lines)} lines on stderr, not one"
    name = signal.Signals(sig).name
    if not (lines[0].startswith(f"torchrl_bail: interrupted by {name}: ") and "; continue with: python -m" in lines[0]):
        return f"stderr line {lines[0][:80]!r}"
    return None


def _run(cmd: list[str], log: Path, kill_after: float | None, watch: Callable[[], str] | None = None,
         sig: int = signal.SIGKILL) -> tuple[bool, float, dict[str, float], str | None]:
    """Runs ``cmd`` (output to ``log``); sends it ``sig`` (SIGKILL) after ``kill_after`` s.

    Returns ``(signalled, seconds, {stage: seconds until `watch()` first returned it}, what was wrong with how it
    ended after SIGINT/SIGTERM or None)``; a job that finished before the signal counts as not signalled.
    """
    start = time.perf_counter()
    appeared: dict[str, float] = {}
    err_path = log.with_suffix(".stderr")
    with open(log, "a") as f, open(err_path, "w") as err:
        proc = subprocess.Popen(cmd, stdout=f, stderr=err, env=_env(), cwd=ROOT, preexec_fn=_default_sigint)
        while proc.poll() is None:
            elapsed = time.perf_counter() - start
            if kill_after is not None and elapsed >= kill_after:
                proc.send_signal(sig)
                proc.wait(timeout=None if sig == signal.SIGKILL else 600)
                break
            if watch is not None:
                appeared.setdefault(watch(), elapsed)
            time.sleep(0.05)
    stderr = err_path.read_text()
    with open(log, "a") as f:
        f.write(stderr)
    elapsed = time.perf_counter() - start
    if kill_after is not None and elapsed >= kill_after and proc.returncode != 0:
        fault = None if sig == signal.SIGKILL else interrupt_fault(sig, proc.returncode, stderr)
        return True, elapsed, appeared, fault
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd[:4])} ... exited with {proc.returncode}; see {log}")
    return False, elapsed, appeared, None


def _differences(a: dict, b: dict) -> list[str]:
    keys = sorted(set(a) | set(b))
    out = []
    for k in keys:
        if a.get(k) != b.get(k):
            if isinstance(a.get(k), dict) and isinstance(b.get(k), dict):
                sub = [f"{k}.{kk}" for kk in sorted(set(a[k]) | set(b[k])) if a[k].get(kk) != b[k].get(kk)]
                out.extend(sub[:3])
            else:
                out.append(k)
    return out


def drill(target, workdir: Path, *, trials: int, seed: int = 0, max_kills: int = 2, sig: int = signal.SIGKILL,
          report=print) -> tuple[int, list[dict], dict[str, float]]:
    """Reference run + ``trials`` runs interrupted by ``sig`` and resumed; returns ``(matches, per-trial records,
    the reference run's seconds: whole, until its first checkpoint, until its last output)``."""
    target.setup()
    ref_dir = workdir / "reference"
    _, ref_seconds, appeared, _ = _run(target.command(ref_dir), workdir / "reference.log", None,
                                       watch=lambda: stage(target, ref_dir))
    reference = target.outputs(ref_dir)
    # the kill window: from shortly before the first checkpoint to the last output (what a process does after it,
    # exiting, a kill cannot harm); a stage the polling missed falls back to the whole run
    first = appeared.get(STAGES[1], ref_seconds / 2)
    last = appeared.get(STAGES[2], ref_seconds)
    report(f"reference {target.name} run: {ref_seconds:.1f} s ({target.progress_file} after {first:.1f} s, "
           f"done after {last:.1f} s) "
           f"-> {ref_dir}")
    rng = random.Random(seed)
    records, matches = [], 0
    for trial in range(1, trials + 1):
        run_dir = workdir / f"trial{trial:02d}"
        log = workdir / f"trial{trial:02d}.log"
        kills, stages, faults = [], [], []
        for _ in range(rng.randint(1, max_kills)):
            # most kills land after the first checkpoint (training, evaluation, writing), some before it
            delay = rng.uniform(0.7 * first, last)
            killed, seconds, _, fault = _run(target.command(run_dir), log, delay, sig=sig)
            kills.append(f"{seconds:.1f}s" if killed else "(finished first)")
            stages += [stage(target, run_dir)] if killed else []
            faults += [] if fault is None else [fault]
        _run(target.command(run_dir), log, None)
        diffs = [*faults, *_differences(reference, target.outputs(run_dir))]
        matches += not diffs
        record = {"trial": trial, "kills": kills, "stages": stages, "resumed_from": target.resumed_from(run_dir),
                  "diffs": diffs}
        records.append(record)
        report(f"trial {trial:2d}: {signal.Signals(sig).name} at {', '.join(kills):<26} resumed from "
               f"{record['resumed_from'] or '-'} -> {'match' if not diffs else 'MISMATCH ' + ', '.join(diffs)}")
    return matches, records, {"run_s": ref_seconds, "first_checkpoint_s": first, "done_s": last}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--target", choices=sorted(TARGETS), default="training")
    parser.add_argument("--algo", default="bail", choices=list(_checkout("algo_schemas").ALGO_SCHEMAS),
                        help="training target: the algorithm (default bail)")
    parser.add_argument("--trials", type=int, default=10)
    parser.add_argument("--max-kills", type=int, default=2, help="kills per trial: 1..N, drawn at random")
    parser.add_argument("--seed", type=int, default=0, help="seeds the kill delays")
    parser.add_argument("--signal", choices=["KILL", "INT", "TERM"], default="KILL",
                        help="what interrupts the jobs: SIGKILL (default), SIGINT (Ctrl-C) or SIGTERM")
    parser.add_argument("--workdir", type=Path, default=None, help="default: a temporary directory, removed")
    parser.add_argument("overrides", nargs="*", help="extra Hydra overrides (after --)")
    add_record_argument(parser, __file__)
    args = parser.parse_args(argv)
    record = Record(__file__, args.json, reference="the uninterrupted run",
                    settings={k: v for k, v in vars(args).items() if k not in ("json", "workdir")})
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="kill_drill_"))
    workdir.mkdir(parents=True, exist_ok=True)
    target = TARGETS[args.target](args.algo, list(args.overrides), workdir / "data")
    try:
        matches, records, reference = drill(target, workdir, trials=args.trials, seed=args.seed,
                                            max_kills=args.max_kills, sig=getattr(signal, f"SIG{args.signal}"))
    finally:
        if args.workdir is None:
            shutil.rmtree(workdir, ignore_errors=True)
    landed = {where: sum(r["stages"].count(where) for r in records) for where in STAGES}
    kills = sum(landed.values())
    resumed = sum(bool(r["resumed_from"]) for r in records)
    label = args.algo if args.target == "training" else "collection"
    line = (f"{label}: {matches}/{args.trials} trials matched the uninterrupted run ({kills} SIG{args.signal}s: "
            + ", ".join(f"{n} {where}" for where, n in landed.items())
            + f"; {resumed} trials resumed from a checkpoint)")
    print(line)
    record.write([], drill={"target": args.target, "label": label, "signal": args.signal, "trials": args.trials,
                            "reference": reference, "matched": matches, "signals_sent": kills, "landed": landed,
                            "resumed": resumed,
                            "result": line,
                            "per_trial": records})
    return 0 if matches == args.trials else 1


if __name__ == "__main__":
    sys.exit(main())

"""Resume a killed run: start a training, SIGKILL it mid-way, rerun the same command and compare with a run that
was never interrupted.

    python docs/tutorials/resume_a_killed_run.py

A run's directory comes from its config (not the clock), and a checkpoint is written after BAIL's envelope fit,
at every evaluation and every ``checkpoint.every_minutes``; rerunning the command finds the checkpoint and continues.
Any further argument is a Hydra override added to every run.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work-dir", type=Path, default=Path("tutorial_resume"))
    args, overrides = parser.parse_known_args()
    command = [sys.executable, "-m", "torchrl_bail.train", "+exp=hopper_ddpg05", "preset=quick", "algo=bail",
               "progress=false", *overrides]
    killed, uninterrupted = args.work_dir / "killed", args.work_dir / "uninterrupted"

    # 1. Start the run and kill it (SIGKILL: no clean-up at all) once it has written its first checkpoint.
    print("$", " ".join(command).replace(sys.executable, "python"), f"hydra.run.dir={killed}", "   # killed below",
          flush=True)
    proc = subprocess.Popen([*command, f"hydra.run.dir={killed}"])
    while not (killed / "checkpoint.pt").exists() and proc.poll() is None:
        time.sleep(0.05)
    if proc.poll() is None:
        os.kill(proc.pid, signal.SIGKILL)
    print("killed" if proc.wait() == -signal.SIGKILL else "the run ended before the kill", flush=True)

    # 2. Rerun the very same command: "resuming ... from its checkpoint at iteration N of M".
    subprocess.run([*command, f"hydra.run.dir={killed}"], check=True)
    # 3. Once more: a finished run is reported, not trained again ("... is already complete").
    subprocess.run([*command, f"hydra.run.dir={killed}"], check=True)

    # 4. The same run without the kill gives the same numbers (on CPU, byte for byte, wall time and paths aside).
    subprocess.run([*command, f"hydra.run.dir={uninterrupted}"], check=True)
    a, b = (json.loads((d / "summary.json").read_text()) for d in (killed, uninterrupted))
    print(f"resumed from iteration(s) {a['resumed_from_iteration']}: final_return {a['final_return']!r}")
    print(f"never interrupted:            final_return {b['final_return']!r}")
    same = [k for k in a if k not in ("wall_time_s", "run_dir", "resumed_from_iteration") and a[k] != b.get(k)]
    print("summaries differ in: " + ", ".join(same) if same else "the summaries agree in every score")


if __name__ == "__main__":
    main()

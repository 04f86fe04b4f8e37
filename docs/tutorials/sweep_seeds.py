"""Sweep seeds: locally in one command, side by side on a workstation's cores, or as a Slurm job array.

    python docs/tutorials/sweep_seeds.py                  # runs the local sweep, prints the other two commands
    python docs/tutorials/sweep_seeds.py --seeds 1,2,3,4,5 --jobs 4   # also runs the side-by-side sweep

Any further argument is a Hydra override added to every command.
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
from pathlib import Path


def sh(*args: str) -> None:
    print("$", shlex.join(args).replace(sys.executable, "python"), flush=True)
    subprocess.run(args, check=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="1,2,3")
    parser.add_argument("--jobs", type=int, default=0, help="also run the sweep with the joblib launcher, N at a time")
    parser.add_argument("--work-dir", type=Path, default=Path("tutorial_sweep"))
    args, overrides = parser.parse_known_args()
    train = [sys.executable, "-m", "torchrl_bail.train"]
    common = ["+exp=hopper_ddpg05", "preset=quick", "algo=bail", "progress=false", *overrides]

    # 1. A local multirun (-m): Hydra's basic launcher runs one job per seed, one after the other. Each job gets the
    #    run directory a single run of that seed would get, so a killed sweep resumes by rerunning it.
    sweep = args.work_dir / "sweep"
    sh(*train, "-m", *common, f"seed={args.seeds}", f"hydra.sweep.dir={sweep}")

    # 2. The same seeds in ONE process, their networks stacked (seeds=[...]): one update step serves every seed,
    #    and each seed writes a run directory and summary.json laid out as its single-seed run's.
    stacked = args.work_dir / "stacked"
    sh(*train, *common, f"seeds=[{args.seeds}]", f"hydra.run.dir={stacked}")

    # 3. Side by side on the local cores: hydra-joblib-launcher (pip install -e ".[parallel]"); every job gets
    #    cores // n_jobs torch threads, and jobs needing the same batch wait for the one that collects it.
    joblib = [*train, "-m", "hydra/launcher=joblib", f"hydra.launcher.n_jobs={max(args.jobs, 2)}", *common,
              f"seed={args.seeds}", f"hydra.sweep.dir={args.work_dir / 'joblib'}"]
    if args.jobs:
        sh(*joblib)
    else:
        print("side by side:", shlex.join(joblib).replace(sys.executable, "python"))

    # 4. On a Slurm cluster: hydra-submitit-launcher (pip install -e ".[slurm]") submits one job per seed; a
    #    pre-empted or timed-out job is requeued and resumes from its checkpoint.
    slurm = [*train, "-m", "hydra/launcher=slurm", "hydra.launcher.partition=cpu", "+exp=hopper_ddpg05",
             "algo=bail,bc", "seed=1,2,3,4,5"]
    print("on Slurm:", shlex.join(slurm).replace(sys.executable, "python"))

    # 5. One table over the sweep (the report prints it and writes seeds.md), and each seed's score alone and
    #    stacked: equal to float rounding in a short run; the rounding grows over a long one (the page says how far).
    sh(sys.executable, "-m", "torchrl_bail.report", str(sweep), "--out", str(args.work_dir / "seeds"), "--reps", "200")
    for seed in args.seeds.split(","):
        one = summary(sweep, seed)
        print(f"seed {seed}: final_return {one:.2f} alone, {summary(stacked, seed):.2f} stacked")


def summary(root: Path, seed: str) -> float:
    """``final_return`` of the run of ``seed`` below ``root``."""
    for path in root.rglob("summary.json"):
        values = json.loads(path.read_text())
        if str(values["seed"]) == seed:
            return values["final_return"]
    raise FileNotFoundError(f"no summary.json of seed {seed} below {root}")


if __name__ == "__main__":
    main()

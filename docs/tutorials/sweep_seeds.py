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
    #    Where they part: the envelope fits agree (best epoch, selection border), the first evaluation already differs.
    for seed in args.seeds.split(","):
        (one, one_dir), (stack, stack_dir) = summary(sweep, seed), summary(stacked, seed)
        print(f"seed {seed}: final_return {one['final_return']:.2f} alone, {stack['final_return']:.2f} stacked")
        print(f"  envelope best epoch {one['envelope_best_epoch']} / {stack['envelope_best_epoch']}, selection border "
              f"{one['selection_border']:.5f} / {stack['selection_border']:.5f}, first evaluation "
              f"{first_evaluation(one_dir):.1f} / {first_evaluation(stack_dir):.1f} (alone / stacked)")


def summary(root: Path, seed: str) -> tuple[dict, Path]:
    """The ``summary.json`` of the run of ``seed`` below ``root``, and its run directory."""
    for path in root.rglob("summary.json"):
        values = json.loads(path.read_text())
        if str(values["seed"]) == seed:
            return values, path.parent
    raise FileNotFoundError(f"no summary.json of seed {seed} below {root}")


def first_evaluation(run_dir: Path) -> float:
    """The return of a run's first evaluation (its CSV log ``eval/return.csv``: ``iteration,value`` rows)."""
    first_row = (run_dir / "logs" / "scalars" / "eval" / "return.csv").read_text().splitlines()[0]
    return float(first_row.split(",")[1])


if __name__ == "__main__":
    main()

"""Reproduce one row of the paper's comparison: BAIL against BC on Hopper's DDPG sigma = 0.5 batch (B1).

    python docs/tutorials/reproduce_a_row.py                      # the results study's row
    python docs/tutorials/reproduce_a_row.py --seeds 1,2,3,4,5 preset=paper   # the paper's scale (hours)

Any further argument is a Hydra override added to every run (``algo.epochs=1``, ``data_dir=/scratch``...).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path


def sh(*args: str) -> None:
    print("$", " ".join(args).replace(sys.executable, "python"), flush=True)
    subprocess.run(args, check=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work-dir", type=Path, default=Path("tutorial_row"), help="where runs and the report go")
    parser.add_argument("--seeds", default="1,2,3", help="training seeds, comma-separated")
    parser.add_argument("--algos", default="bail,bc", help="algorithms, comma-separated (bail,pbail,bc,marwil,...)")
    args, overrides = parser.parse_known_args()
    runs = args.work_dir / "outputs"

    # 1. One Hydra multirun: every algorithm x seed on the same batch. The batch is collected by the first job
    #    (an online DDPG run with N(0, 0.5^2) exploration noise) and cached; the other jobs reuse it.
    #    preset=study is the results study's scale: a 50k-transition batch, 2 imitation epochs per run.
    sh(sys.executable, "-m", "torchrl_bail.train", "-m", "+exp=hopper_ddpg05", "preset=study",
       f"algo={args.algos}", f"seed={args.seeds}", f"hydra.sweep.dir={runs}", "progress=false", *overrides)

    # 2. The report groups the runs by batch and algorithm: mean +- std and the IQM with a bootstrap interval. It
    #    prints its tables and writes them to row.md.
    sh(sys.executable, "-m", "torchrl_bail.report", str(runs), "--out", str(args.work_dir / "row"), "--reps", "200")

    # 3. Each run's summary.json holds its score; the row above is their mean over seeds.
    for summary in sorted(runs.rglob("summary.json")):
        s = json.loads(summary.read_text())
        print(f"{s['algo']:>6} seed {s['seed']}: final_return {s['final_return']:8.1f}   "
              f"(batch mean episode return {s['dataset_mean_episode_return']:.1f})")


if __name__ == "__main__":
    main()

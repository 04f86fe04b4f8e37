"""A local sweep run serially vs side by side through ``hydra/launcher=joblib``: wall time of the whole command.

    python benchmarks/bench_sweep.py [--jobs 2] [--epochs 0.05] [--rounds 2] [--algo bc]

Both sides run the same ``-m`` sweep (``seed=1..jobs``, one algorithm, the quick Hopper DDPG sigma=0.5 recipe
shortened to a small batch) from one shared, already collected batch, each job with one torch thread: serially with
Hydra's basic launcher and ``threads=1``, and through the joblib launcher with ``n_jobs=jobs`` (which gives each job
``cores // n_jobs`` threads). The rounds alternate between the two sides so that a noisy neighbour hits both; the
script prints each round, the median wall times and ``serial / parallel`` (> 1: the parallel sweep is faster) and
checks that both sides wrote the same ``final_return`` for every seed.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _bench import Record, add_record_argument, summarise

RECIPE = ["+exp=hopper_ddpg05", "preset=quick", "batch.steps=1500", "batch.start_steps=500", "progress=false"]


def sweep(data_dir: Path, out: Path, *, jobs: int, epochs: float, algo: str, parallel: bool) -> float:
    seeds = ",".join(str(s) for s in range(1, jobs + 1))
    launcher = ["hydra/launcher=joblib", f"hydra.launcher.n_jobs={jobs}"] if parallel else ["threads=1"]
    cmd = [sys.executable, "-m", "torchrl_bail.train", "-m", *RECIPE, f"algo={algo}", f"algo.epochs={epochs}",
           f"eval.every_epochs={epochs / 2}", "eval.episodes=2", f"seed={seeds}", f"data_dir={data_dir}",
           f"hydra.sweep.dir={out}", *launcher]
    start = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - start


def final_returns(out: Path) -> dict[str, float]:
    return {str(p.parent.relative_to(out)): json.loads(p.read_text())["final_return"]
            for p in sorted(out.rglob("summary.json"))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--epochs", type=float, default=0.05)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--algo", default="bc")
    add_record_argument(parser, __file__)
    args = parser.parse_args()
    record = Record(__file__, args.json, reference="serial sweep", settings=vars(args))
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    os.environ.update(env)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        data_dir = tmp / "data"
        # the batch first, so that both sides only train
        subprocess.run([sys.executable, "-m", "torchrl_bail.collect", *RECIPE, f"data_dir={data_dir}"], check=True,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        times: dict[str, list[float]] = {"serial": [], "joblib": []}
        returns: dict[str, dict] = {}
        for r in range(args.rounds):
            for side in ("serial", "joblib") if r % 2 == 0 else ("joblib", "serial"):
                out = tmp / f"{side}{r}"
                t = sweep(data_dir, out, jobs=args.jobs, epochs=args.epochs, algo=args.algo,
                          parallel=side == "joblib")
                times[side].append(t)
                returns[side] = final_returns(out)
                print(f"round {r} {side:6s} {t:7.1f} s", flush=True)
    serial, parallel = statistics.median(times["serial"]), statistics.median(times["joblib"])
    same = returns["serial"] == returns["joblib"]
    print(f"{args.jobs} jobs of {args.algo}, {args.epochs} epochs each on {os.cpu_count()} cores: serial "
          f"{serial:.1f} s, joblib {parallel:.1f} s, serial/joblib = {serial / parallel:.2f}; "
          f"same final returns: {same}")
    # sweeps per hour, so that ratio = joblib rate / serial rate = serial time / joblib time (> 1: joblib is faster)
    row = summarise(f"{args.jobs} jobs of {args.algo}, {args.epochs} epochs each", "sweeps/h",
                    {side: [3600 / t for t in values] for side, values in (("joblib", times["joblib"]),
                                                                           ("serial", times["serial"]))},
                    ratio_of=("joblib", "serial"), wall_s=times, same_final_returns=same, final_returns=returns)
    record.write([row])


if __name__ == "__main__":
    main()

"""What a paper-scale job costs, and whether a second thread pays: a short probe of the real training command.

Usage (on a quiet machine: nothing else running; the batch installed, docs: Paper scale)::

    python benchmarks/bench_paper_cost.py       # BAIL's envelope and each algorithm of the paper study; threads 1, 2
    python benchmarks/bench_paper_cost.py --algos bcq,bear --threads 1,2 --repeats 2

For each algorithm and thread count the probe runs the cell's own command (``python -m torchrl_bail.train
+exp=hopper_ddpg05 algo=<a> threads=<t>``, the 10^6-transition batch, ``preset=paper``) twice, with a short and a
three-times longer schedule and a single evaluation at the end, and reads each run's ``wall_time_s``. The
difference of the two runs is the cost of the extra updates alone (loading the batch, its returns, the
evaluation and start-up cancel), so ``updates/s = extra updates / extra seconds``: the rate the job's updates run
at. BAIL's envelope is probed the same way, by its epochs (``envelope``: passes over the 0.8 training split per
second). A job's time is then its updates over that rate plus its evaluations (``eval.every_epochs``), which the
cell's committed timings measure whole (``results/paper_hopper/cell.md``).

The record (``results/benchmarks/bench_paper_cost.json``) holds every run's wall time and, per algorithm, the
rate at each thread count and their ratio (threads=2 / threads=1: above 1, the second thread pays).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from _bench import Record, add_record_argument, summarise

from torchrl_bail.configuration.algo_schemas import ALGO_SCHEMAS, blocks_with, envelope_algorithm
from torchrl_bail.configuration.config_builders import algo_config

#: the probe's short number of epochs per cost class (the registry's ``cost``,
# :mod:`torchrl_bail.configuration.algo_schemas`):
#: 2000 updates at batch 1000, 2000 at batch 100
SHORT_EPOCHS = {"imitation": 2, "offline_rl": 0.2}


def _schedules() -> dict[str, tuple[str, float, int]]:
    """algorithm -> (the override the probe lengthens, its short value, updates per unit of it), for every registered
    algorithm (updates per epoch of 10^6 samples: 10^6 / its batch size) and BAIL's envelope (passes over the training
    split); the long run is 3x, so the extra updates take tens of seconds, well above the ~1 s spread of the fixed
    part (start-up, loading the batch, its returns, the one evaluation: ~45 s)."""
    schedules = {name: ("algo.epochs", SHORT_EPOCHS[schema.cost], 10**6 // algo_config(name).batch_size)
                 for name, schema in ALGO_SCHEMAS.items()}
    return {**schedules, "envelope": ("algo.envelope.epochs", 2, 1)}


SCHEDULES = _schedules()
#: the algorithm whose envelope the ``envelope`` probe lengthens: the registered one whose envelope has epochs (BAIL)
ENVELOPE_OF = envelope_algorithm()
#: what the probe runs by default: the envelope and every algorithm of the paper-scale study (the registry's
#: ``paper_study``)
DEFAULT_PROBES = ["envelope", *(name for name, schema in ALGO_SCHEMAS.items() if schema.paper_study)]
#: what every probe run shares: one evaluation, at the end, no checkpoints, no progress bars
COMMON = ["+exp=hopper_ddpg05", "progress=false", "checkpoint.enabled=false", "eval.final_window=1"]


def probe_run(algo: str, threads: int, length: float, workdir: Path) -> float:
    """Wall seconds (``summary.json``'s ``wall_time_s``) of one training run of ``algo`` whose probed schedule is
    ``length``."""
    key, _, _ = SCHEDULES[algo]
    name = ENVELOPE_OF if algo == "envelope" else algo
    run_dir = workdir / f"{algo}_t{threads}_{length}"
    overrides = [f"algo={name}", f"threads={threads}", f"{key}={length}", f"hydra.run.dir={run_dir}", *COMMON]
    if algo == "envelope":
        overrides += ["algo.epochs=0.1", "eval.every_epochs=0.1"]
    else:  # a block with epochs of its own (BAIL's envelope) at 1 on both sides
        overrides += [*(f"algo.{block}.epochs=1" for block in blocks_with(name, "epochs")),
                      f"eval.every_epochs={length * 3}"]
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
    subprocess.run([sys.executable, "-m", "torchrl_bail.train", *overrides], check=True, env=env,
                   stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    return float(json.loads((run_dir / "summary.json").read_text())["wall_time_s"])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--algos", default=",".join(DEFAULT_PROBES),
                        help="comma-separated, from: " + ", ".join(SCHEDULES))
    parser.add_argument("--threads", default="1,2", help="thread counts to compare (default: %(default)s)")
    parser.add_argument("--repeats", type=int, default=1, help="short/long pairs per algorithm and thread count")
    add_record_argument(parser, __file__)
    args = parser.parse_args(argv)
    algos = [a for a in args.algos.split(",") if a]
    unknown = sorted(set(algos) - set(SCHEDULES))
    if unknown:
        parser.error(f"unknown --algos {', '.join(unknown)}; choose from {', '.join(SCHEDULES)}")
    threads = [int(t) for t in args.threads.split(",")]
    record = Record(__file__, args.json, reference="threads=1", settings=vars(args))
    rows = []
    with tempfile.TemporaryDirectory(prefix="paper_cost_") as tmp:
        for algo in algos:
            key, short, per_unit = SCHEDULES[algo]
            rounds: dict[str, list[float]] = {}
            runs = []
            for t in threads:
                for r in range(args.repeats):
                    short_s = probe_run(algo, t, short, Path(tmp) / f"r{r}")
                    long_s = probe_run(algo, t, round(short * 3, 6), Path(tmp) / f"r{r}")
                    rate = 2 * short * per_unit / (long_s - short_s)
                    rounds.setdefault(f"threads={t}", []).append(rate)
                    runs.append({"threads": t, "repeat": r, "short_s": short_s, "long_s": long_s, "rate": rate})
                    print(f"{algo} threads={t}: {short_s:.1f} s / {long_s:.1f} s -> {rate:.1f} "
                          f"{'epochs' if algo == 'envelope' else 'updates'}/s", flush=True)
            name = f"{algo} ({key} {short} vs {round(short * 3, 6)})"
            unit = "envelope epochs/s" if algo == "envelope" else "updates/s"
            first, last = f"threads={threads[0]}", f"threads={threads[-1]}"
            rows.append(summarise(name, unit, rounds, ratio_of=(last, first), runs=runs))
            record.write(rows)  # after every algorithm: a long probe keeps what it measured
    for row in record.write(rows)["table"]:
        print(f"{row['case']}: threads={threads[-1]} / threads={threads[0]} = {row['ratio']:.2f} "
              f"({row['torchrl_bail']:.1f} vs {row['reference']:.1f} {row['unit']})")
    return 0


if __name__ == "__main__":
    sys.exit(main())

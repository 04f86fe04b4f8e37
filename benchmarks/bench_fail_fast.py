"""How fast a bad command line fails, against what loading an algorithm's module costs.

    python benchmarks/bench_fail_fast.py [--repeats 5] [--json PATH]

A command line is checked against the typed schemas before torch, tensordict and torchrl load
(:mod:`torchrl_bail.configuration.schema_reader`), so that a typo costs about a second rather than the several seconds
of those
imports. Each round runs, in fresh processes and one after the other (so a noisy neighbour hits every case):

* ``schemas``: ``python -c "import torchrl_bail.configuration.algo_schemas, torchrl_bail.configuration.batch_schemas"``,
the registries, read
  from every algorithm's and recipe's file without importing it;
* ``algorithm module``: ``python -c "import torchrl_bail.algorithms.iql"``, one algorithm's module, which imports
  torch, tensordict and torchrl (what every command line would pay without the schema reader);
* ``bad command line``: ``python -m torchrl_bail.train +exp=hopper_ddpg05 algo=iql algo.batch_size=0``, which must
  exit with status 2 and one line naming the key (the probe stops otherwise).

The record (``results/benchmarks/bench_fail_fast.json``) holds every round's wall seconds and two rows, each the
ratio of medians (seconds / seconds: below 1, the first is faster): the bad command line over the algorithm
module, and the schemas over the algorithm module.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time

from _bench import Record, add_record_argument, summarise

CASES = {
    "schemas": [sys.executable, "-c",
                "import torchrl_bail.configuration.algo_schemas, torchrl_bail.configuration.batch_schemas"],
    "algorithm module": [sys.executable, "-c", "import torchrl_bail.algorithms.iql"],
    "bad command line": [sys.executable, "-m", "torchrl_bail.train", "+exp=hopper_ddpg05", "algo=iql",
                         "algo.batch_size=0"],
}
#: the exit status each case must end with; the bad command line's one line must name the key
EXPECTED_STATUS = {"schemas": 0, "algorithm module": 0, "bad command line": 2}


def timed(name: str) -> float:
    """Wall seconds of one fresh process of case ``name``, after checking its exit status (and the bad command
    line's one-line error)."""
    start = time.perf_counter()
    done = subprocess.run(CASES[name], capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if done.returncode != EXPECTED_STATUS[name]:
        raise SystemExit(f"{name}: exit status {done.returncode}, expected {EXPECTED_STATUS[name]}\n{done.stderr}")
    if name == "bad command line" and (len(done.stderr.strip().splitlines()) != 1
                                       or "algo.batch_size" not in done.stderr):
        raise SystemExit(f"{name}: expected one line naming algo.batch_size, got:\n{done.stderr}")
    return seconds


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=5, help="rounds; each runs every case once")
    add_record_argument(parser, __file__)
    args = parser.parse_args(argv)
    record = Record(__file__, args.json, reference="algorithm module", settings=vars(args))
    timed("algorithm module")  # warm the file cache for every case
    rounds: dict[str, list[float]] = {name: [] for name in CASES}
    for _ in range(args.repeats):
        for name in CASES:
            rounds[name].append(timed(name))
    for name, seconds in rounds.items():
        print(f"{name:>17}: median {statistics.median(seconds):.2f} s (best {min(seconds):.2f} s)")
    rows = [summarise(f"{case} vs algorithm module", "s (fresh process)",
                      {case: rounds[case], "algorithm module": rounds["algorithm module"]},
                      ratio_of=(case, "algorithm module"))
            for case in ("bad command line", "schemas")]
    for row in rows:
        print(f"{row['name']}: ×{row['ratio']:.2f}")
    record.write(rows)


if __name__ == "__main__":
    main()

"""Torch threads on a busy CPU: how fast the README's collection and BAIL's envelope updates run with 1 and 2 torch
threads on a quiet machine and beside one and two busy processes (the measurement behind the ``threads: 1`` default,
``conf/config.yaml``).

    python benchmarks/bench_threads.py [--steps 1200 --start-steps 700] [--updates 600] [--busy 0 1 2] [--json PATH]

Each case runs in a fresh child process, unpinned, with ``threads=1`` or ``threads=2``:

* collection: README command 1's collection (``python -m torchrl_bail.collect +exp=hopper_ddpg05 preset=quick``)
  cut to ``--steps`` env steps, the first ``--start-steps`` of them random (the rest one DDPG update per step at
  each episode's end, as the real collection), in a temporary data dir; its rate is env steps per second of the
  whole command, start-up included;
* envelope: ``--updates`` steps of BAIL's upper envelope as a run makes them (:class:`UpperEnvelopeLoss`,
  :func:`~torchrl_bail.training.envelope.envelope_step`, mini-batches of 800 from a Hopper-sized training split).

A busy process is a pure-Python spin loop (one core's worth of work, as another job's single thread), started
before the case and killed after it. The ratio row of each (workload, busy) pair is the rate with 2 threads over the
rate with 1 (below 1: the second thread costs). One round per case: the effect measured is a collapse (tens of
times slower), not a few per cent. Run it on an otherwise idle machine; the record keeps the load average at start
and end so that a reader can check.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

os.environ.setdefault("RL_WARNINGS", "0")

from _bench import ROOT, Record, add_record_argument, machine, print_columns, summarise  # noqa: E402

SPIN = "while True:\n    pass\n"
OBS = 11  # Hopper-v5


def envelope_rate(updates: int) -> float:
    """Envelope updates per second in this process, after a warm-up of a tenth of them (child side)."""
    import torch
    from tensordict import TensorDict

    from torchrl_bail.modules import make_value_network
    from torchrl_bail.objectives.upper_envelope import UpperEnvelopeLoss
    from torchrl_bail.training.envelope import envelope_step

    n, batch = 200_000, 800
    g = torch.Generator().manual_seed(1)
    observations, returns = torch.randn(n, OBS, generator=g), torch.rand(n, generator=g) * 300
    train_index = torch.randperm(n, generator=g)[: int(0.8 * n)]
    torch.manual_seed(0)
    loss_module = UpperEnvelopeLoss(make_value_network(OBS), penalty=1000.0)
    optimizer = torch.optim.Adam(loss_module.parameters(), lr=3e-3, weight_decay=0.02)

    def step(i: int) -> None:
        start = (i * batch) % (len(train_index) - batch)
        index = train_index[start:start + batch]
        td = TensorDict({"observation": observations[index], "return": returns[index]}, batch_size=[batch])
        envelope_step(loss_module, optimizer, td)

    for i in range(max(1, updates // 10)):
        step(i)
    began = time.perf_counter()
    for i in range(updates):
        step(i)
    return updates / (time.perf_counter() - began)


def run_case(workload: str, threads: int, busy: int, args) -> float:
    """The case's rate (env steps/s or updates/s) from a fresh child process, beside ``busy`` spin loops."""
    hogs = [subprocess.Popen([sys.executable, "-c", SPIN]) for _ in range(busy)]
    try:
        time.sleep(0.5 if busy else 0)  # the spinners are on the CPU before the case starts
        if workload == "envelope":
            out = subprocess.run([sys.executable, __file__, "--child-envelope", str(args.updates),
                                  "--child-threads", str(threads)], check=True, capture_output=True, text=True,
                                 cwd=ROOT)
            return float(out.stdout.strip().splitlines()[-1])
        with tempfile.TemporaryDirectory() as tmp:
            began = time.perf_counter()
            subprocess.run([sys.executable, "-m", "torchrl_bail.collect", "+exp=hopper_ddpg05", "preset=quick",
                            f"batch.steps={args.steps}", f"batch.start_steps={args.start_steps}", f"threads={threads}",
                            "progress=false", f"data_dir={tmp}/data", f"hydra.run.dir={tmp}/run"],
                           check=True, capture_output=True, cwd=ROOT)
            return args.steps / (time.perf_counter() - began)
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=1200, help="env steps of the cut-down collection")
    parser.add_argument("--start-steps", type=int, default=700, help="... of which random (no updates)")
    parser.add_argument("--updates", type=int, default=600, help="timed envelope updates per case")
    parser.add_argument("--busy", type=int, nargs="+", default=[0, 1, 2], help="busy processes beside each case")
    parser.add_argument("--workloads", nargs="+", default=["collection", "envelope"],
                        choices=["collection", "envelope"])
    parser.add_argument("--child-envelope", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--child-threads", type=int, help=argparse.SUPPRESS)
    add_record_argument(parser, __file__)
    args = parser.parse_args()
    if args.child_envelope is not None:  # a case's child process: print the rate alone
        import torch

        torch.set_num_threads(args.child_threads)
        print(envelope_rate(args.child_envelope))
        return
    if not 0 <= args.start_steps < args.steps:
        parser.error(f"--start-steps {args.start_steps}: expected 0 <= start steps < --steps {args.steps}")

    record = Record(__file__, args.json, reference="1 torch thread",
                    settings={k: getattr(args, k) for k in ("steps", "start_steps", "updates", "busy", "workloads")})
    rows = []
    for workload in args.workloads:
        unit = "env steps/s" if workload == "collection" else "updates/s"
        for busy in args.busy:
            rates = {}
            for threads in (1, 2):
                rates[f"threads={threads}"] = [run_case(workload, threads, busy, args)]
                print(f"{workload}, {busy} busy, threads={threads}: {rates[f'threads={threads}'][0]:.1f} {unit}",
                      flush=True)
            rows.append(summarise(f"{workload}, beside {busy} busy process{'es' if busy != 1 else ''}", unit, rates,
                                  ratio_of=("threads=2", "threads=1"), workload=workload, busy=busy))
            record.write(rows)
    print_columns(f"threads=2 / threads=1  ({machine()})", rows,
                  [("threads=1", "threads=1", ">10.1f"), ("threads=2", "threads=2", ">10.1f"),
                   ("ratio", "ratio", ">7.2f"), ("unit", "unit", "<12")])
    record.write(rows)


if __name__ == "__main__":
    main()

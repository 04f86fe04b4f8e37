"""BCQ, BEAR and BC training throughput: torchrl_bail vs d3rlpy 2.8, side by side, same sizes, one thread.

Usage (d3rlpy 2.8.1 pins an older gymnasium, so it lives in its own virtual environment)::

    python -m venv .d3venv
    .d3venv/bin/pip install torch==2.13.0          # first, so d3rlpy keeps this torch
    .d3venv/bin/pip install d3rlpy==2.8.1 torch==2.13.0
    OMP_NUM_THREADS=1 python benchmarks/bench_d3rlpy.py --python .d3venv/bin/python

Both sides time one training iteration as each library's training loop runs it: torchrl_bail's
``algorithm.update(buffer.sample())`` (the trainer's loop, :mod:`torchrl_bail.training.trainer`), d3rlpy's
``algo.update(dataset.sample_transition_batch(batch_size))`` (what ``fit`` runs per step). The d3rlpy side is a
long-lived subprocess (``_d3rlpy_worker.py`` under ``--python``); rounds alternate between the two sides so a
noisy neighbour hits both, and the table reports the medians and ``ratio = torchrl_bail / d3rlpy``.

Rates are per CPU second of the timed process (``time.process_time``; one thread, so this is the rate an idle
core would give) and, beside them, per wall-clock second. On a shared machine the wall-clock rounds swing by 2x
with the neighbours' load; CPU time is what stays comparable between rounds.

Sizes (the BAIL paper's baselines, arXiv:1910.12179, Sec. 5 and supplement): 100k synthetic transitions with
|S| = 11, |A| = 3; BCQ: VAE 750-750 with latent 2|A|, actor and two critics 400-300, batch 100, 10 sampled
actions in the target, Adam 1e-3 everywhere; BEAR: the same plus 5 MMD samples, Laplacian kernel
(sigma 10), warm start over (d3rlpy ``warmup_steps=0``, ours ``warm_start_updates=0``); BC: 400-300
deterministic tanh actor, MSE, batch 1000.

How d3rlpy's per-update work differs from ours (read from d3rlpy 2.8.1's ``algos/qlearning/torch``):

* **BCQ** (``bcq_impl.py``) runs the same network shapes on the same inputs in the same order, but not the same
  decoder head (d3rlpy 2.8.1's ``VAEDecoder`` applies no ``tanh`` under its default ``with_squash=True``; ours
  does, as the authors') (VAE step, critic step
  with a 10-sample target through the target actor, actor step, Polyak of critics and actor). Its actor loss
  evaluates *both* critics and keeps ``Q_1`` (``compute_expected_q(..., "none")[0]``): one wasted 400-300
  forward on the batch. Its critic loss is the same sum of two MSEs; its Polyak update is a Python loop of
  ``mul_``/``add_`` per tensor (ours: one fused ``lerp_``).
* **BEAR** (``bear_impl.py``) is d3rlpy's SAC-based variant, *not* the authors' version 0 we implement:
  there is no target actor (the critic target samples the current policy and subtracts an entropy term, and
  only the critics are Polyak-averaged); the actor loss is SAC's (one policy sample per state, ``min_j Q_j``
  on ``[B]`` rows) plus ``alpha * (MMD - eps)``, whereas ours (the authors') takes ``min_j mean_m Q_j`` over the
  5 MMD samples, i.e. runs both critics on ``[5B]`` rows forward and backward: 5x d3rlpy's actor-side critic
  work. d3rlpy runs the policy twice per actor step (SAC sample, MMD samples), we run it once; its ``log_alpha``
  step reuses the actor loss' graph (``retain_graph``). Here d3rlpy's temperature step is switched off
  (``temp_learning_rate=0``; BEAR as the BAIL authors ran it has no entropy term), which only removes work from
  d3rlpy's side. Net: d3rlpy's BEAR update does about 13 % fewer multiply-adds than ours.
* **BC** (``bc_impl.py``): the same network, loss and optimizer.
* **Sampling.** d3rlpy builds a batch from ``batch_size`` Python-level ``sample_transition()`` calls and converts
  numpy to torch; ours is one indexed gather of a TensorDict. This dominates the BC gap (batch 1000).
* **Optimizers.** d3rlpy uses torch's default (per-tensor) ``torch.optim.Adam``; ours is the fused kernel
  (same update up to float32 rounding). d3rlpy converts every loss to a Python float each step; ours returns
  detached tensors.
* **Wasted work in d3rlpy's BCQ actor step**: the VAE decoder sample is drawn with gradients on, so the backward
  runs through the 750-750 decoder too, and the critics' weight gradients are computed and discarded (46 backward
  matrix products per update against our 29).
* **Memory.** Our update page-faults ~2000 times (glibc hands 3 MB activation buffers back to the OS and maps
  them again), d3rlpy's ~20; keeping freed memory in our process removes the faults without a measurable change
  in our CPU-time rate.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import torch  # noqa: E402
from _bench import Record, add_record_argument, machine, print_columns, summarise
from bench_bcq_bear import ACT, BATCH, N_MATCH, N_TARGET, OBS, synthetic_data  # noqa: E402
from torchrl.data import RandomSampler, TensorDictReplayBuffer, TensorStorage  # noqa: E402

from torchrl_bail.algorithms.bc import BehaviourCloning  # noqa: E402
from torchrl_bail.algorithms.bcq import BCQ  # noqa: E402
from torchrl_bail.algorithms.bear import BEAR  # noqa: E402
from torchrl_bail.configuration.config_builders import algo_config  # noqa: E402
from torchrl_bail.modules import action_spec_from_bounds  # noqa: E402

BC_BATCH = 1000
TRANSITIONS = 100_000
WORKER = Path(__file__).with_name("_d3rlpy_worker.py")


def start_worker(python: str, cfg: dict, threads: int) -> tuple[subprocess.Popen, dict]:
    """``_d3rlpy_worker.py`` under ``python`` with ``cfg`` (its mode and constants), ``threads`` torch threads and
    none of our ``PYTHONPATH``; returns the process and the JSON header it answers with (d3rlpy's versions)."""
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}
    env.pop("PYTHONPATH", None)
    proc = subprocess.Popen([python, str(WORKER), json.dumps({**cfg, "threads": threads})], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env)
    header = proc.stdout.readline()
    if not header:
        raise SystemExit(f"the d3rlpy worker did not start under {python} (is d3rlpy 2.8 installed there?)")
    return proc, json.loads(header)


class D3rlpySide:
    """The d3rlpy subprocess: ``rate(name, n)`` runs ``n`` of its updates and returns updates/s."""

    def __init__(self, python: str, threads: int) -> None:
        cfg = {"threads": threads, "transitions": TRANSITIONS, "obs": OBS, "act": ACT, "net_hidden": [400, 300],
               "vae_hidden": [750, 750], "batch": BATCH, "n_target": N_TARGET, "n_match": N_MATCH,
               "bc_batch": BC_BATCH}
        self.proc, self.versions = start_worker(python, cfg, threads)

    def rates(self, name: str, n: int) -> tuple[float, float]:
        self.proc.stdin.write(f"{name} {n}\n")
        self.proc.stdin.flush()
        wall, cpu = self.proc.stdout.readline().split()
        return float(wall), float(cpu)

    def close(self) -> None:
        self.proc.stdin.write("quit\n")
        self.proc.stdin.close()
        self.proc.wait()


def rates(fn, n: int) -> tuple[float, float]:
    """``(calls per wall-clock second, calls per CPU second of this process)`` over ``n`` calls of ``fn``."""
    wall, cpu = time.perf_counter(), time.process_time()
    for _ in range(n):
        fn()
    return n / (time.perf_counter() - wall), n / (time.process_time() - cpu)


def our_updates(data, compile_mode: bool | str = False) -> dict:
    """One training iteration per algorithm: ``algorithm.update(buffer.sample())``, as the trainer runs it
    (``compile_mode``: the ``compile`` config key, :meth:`~torchrl_bail.algorithms.Algorithm.compile`)."""
    spec = action_spec_from_bounds([-1.0] * ACT, [1.0] * ACT)
    out = {}
    for name, cls, batch, kwargs in [("bcq", BCQ, BATCH, {}), ("bear", BEAR, BATCH, {"warm_start_updates": 0}),
                                     ("bc", BehaviourCloning, BC_BATCH, {})]:
        torch.manual_seed(0)
        algo = cls(OBS, spec, algo_config(name, batch_size=batch, epochs=1, **kwargs))
        algo.compile(compile_mode)
        buffer = TensorDictReplayBuffer(storage=TensorStorage(data), sampler=RandomSampler(), batch_size=batch)
        out[name] = (lambda a=algo, b=buffer: a.update(b.sample()))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--python", required=True, help="the interpreter of d3rlpy's virtual environment")
    parser.add_argument("--updates", type=int, default=20, help="updates per timed round (BC: 5x as many)")
    parser.add_argument("--repeats", type=int, default=5, help="alternating rounds per side")
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads on both sides")
    parser.add_argument("--algos", default="bcq,bear,bc", help="comma-separated subset of bcq,bear,bc")
    parser.add_argument("--compile", default="false",
                        help="our side's compile setting (false, true, max-autotune, ...); d3rlpy 2.8 compiles "
                             "only on CUDA (its compile_graph), so its side stays eager on a CPU")
    add_record_argument(parser, __file__)
    args = parser.parse_args()
    record = Record(__file__, args.json, reference="d3rlpy 2.8 (updates per CPU second)", settings=vars(args))
    torch.set_num_threads(args.threads)
    compile_mode = {"false": False, "true": True}.get(args.compile.lower(), args.compile)
    peer = D3rlpySide(args.python, args.threads)
    ours = our_updates(synthetic_data(TRANSITIONS), compile_mode)
    suffix = "" if compile_mode is False else f", compile={args.compile}"
    names = {"bcq": f"BCQ update (batch 100{suffix})", "bear": f"BEAR update (batch 100{suffix})",
             "bc": f"BC update (batch 1000{suffix})"}
    rows = []
    try:
        for algo in args.algos.split(","):
            n = args.updates * (5 if algo == "bc" else 1)
            compile_start = time.perf_counter()
            rates(ours[algo], 5)  # warm-up (and, with --compile, the compilation)
            if compile_mode is not False:
                print(f"{names[algo]}: compiled in {time.perf_counter() - compile_start:.0f} s", flush=True)
            peer.rates(algo, 5)
            lib, d3 = [], []
            for _ in range(args.repeats):
                lib.append(rates(ours[algo], n))
                d3.append(peer.rates(algo, n))
            row = summarise(names[algo], "updates per CPU-s",
                            {"torchrl_bail_cpu": [r[1] for r in lib], "d3rlpy_cpu": [r[1] for r in d3],
                             "torchrl_bail_wall": [r[0] for r in lib], "d3rlpy_wall": [r[0] for r in d3]},
                            ratio_of=("torchrl_bail_cpu", "d3rlpy_cpu"))
            row.update(ratio_cpu=row["ratio"], ratio_wall=row["torchrl_bail_wall"] / row["d3rlpy_wall"])
            rows.append(row)
            record.write(rows, d3rlpy_versions=peer.versions)  # after every row: a stopped run keeps its rows
            print(f"{names[algo]:<44} CPU-time rates: torchrl_bail {row['torchrl_bail_cpu']:7.1f}  d3rlpy "
                  f"{row['d3rlpy_cpu']:7.1f}  ratio {row['ratio_cpu']:5.2f}   (wall clock: {row['ratio_wall']:.2f})",
                  flush=True)
    finally:
        peer.close()
    peer_versions = f"d3rlpy {peer.versions['d3rlpy']} with torch {peer.versions['torch']}"
    print_columns(f"updates/s per CPU second, medians of {args.repeats} alternating rounds ({machine()}; "
                  f"{peer_versions})", rows,
                  [("torchrl_bail", "torchrl_bail_cpu", ">13.1f"), ("d3rlpy", "d3rlpy_cpu", ">9.1f"),
                   ("ratio", "ratio_cpu", ">7.2f"), ("(wall clock ratio)", "ratio_wall", ">18.2f")])
    record.write(rows, d3rlpy_versions=peer.versions)


if __name__ == "__main__":
    sys.exit(main())

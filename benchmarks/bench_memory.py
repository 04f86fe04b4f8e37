"""Peak memory of a paper-scale batch through the whole BAIL pipeline: returns, envelope fit, selection, imitation.

    python benchmarks/bench_memory.py                       # Humanoid-v5's shapes, 10^6 transitions
    python benchmarks/bench_memory.py --env hopper --transitions 200000 --out results/memory/hopper.json

The batch is synthetic (random observations and actions of the env's shapes, 1000-step time-limited episodes,
rewards ~ N(5, 1)): memory depends on the shapes and the count, not on the values. It is written as a native
batch, then ``python -m torchrl_bail.train dataset=<it>`` runs BAIL on it in a child process with the paper's
networks and mini-batch sizes but one envelope epoch and a few imitation updates (memory does not grow with
epochs). The child's peak resident set size (``getrusage(RUSAGE_CHILDREN).ru_maxrss``, the kernel's high-water
mark, so nothing between two samples is missed) is the figure; the JSON record also keeps the run's summary.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from _bench import Record, add_record_argument
from tensordict import TensorDict

from torchrl_bail.data.batch import save_batch

#: (gymnasium id, observation dim, action dim, action bound) of the five paper envs in their v5 versions
SHAPES = {
    "hopper": ("Hopper-v5", 11, 3, 1.0),
    "walker": ("Walker2d-v5", 17, 6, 1.0),
    "halfcheetah": ("HalfCheetah-v5", 17, 6, 1.0),
    "ant": ("Ant-v5", 105, 8, 1.0),
    "humanoid": ("Humanoid-v5", 348, 17, 0.4),
}


def synthetic_batch(n: int, obs_dim: int, act_dim: int, bound: float, episode_len: int = 1000) -> TensorDict:
    """A TED batch of ``n`` transitions in time-limited episodes of ``episode_len`` steps."""
    gen = torch.Generator().manual_seed(0)
    obs = torch.randn(n, obs_dim, generator=gen)
    step = torch.arange(n)
    truncated = ((step + 1) % episode_len == 0).unsqueeze(-1)
    truncated[-1] = True
    zeros = torch.zeros(n, 1, dtype=torch.bool)
    return TensorDict({
        "observation": obs,
        "action": (torch.rand(n, act_dim, generator=gen) * 2 - 1) * bound,
        "episode": step // episode_len,
        "next": {"observation": torch.roll(obs, -1, 0), "reward": torch.randn(n, 1, generator=gen) + 5,
                 "done": truncated.clone(), "terminated": zeros, "truncated": truncated},
    }, [n])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="humanoid", choices=sorted(SHAPES))
    parser.add_argument("--transitions", type=int, default=1_000_000)
    parser.add_argument("--updates", type=int, default=20, help="imitation mini-batches after the envelope fit")
    add_record_argument(parser, __file__)
    parser.add_argument("--out", dest="json", help="the same as --json (the record's path)")
    args = parser.parse_args()
    run_record = Record(__file__, args.json, reference="none (absolute figures)", settings=vars(args))

    env_id, obs_dim, act_dim, bound = SHAPES[args.env]
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        batch = save_batch(synthetic_batch(args.transitions, obs_dim, act_dim, bound), Path(tmp) / "batch",
                           {"env_id": env_id})
        size_gib = sum(f.stat().st_size for f in (Path(tmp) / "batch").rglob("*") if f.is_file()) / 2**30
        del batch
        written_s = time.perf_counter() - start
        samples = args.updates * 100
        cmd = [sys.executable, "-m", "torchrl_bail.train", f"dataset={tmp}/batch", f"env={args.env}",
               "algo=bail", "algo.envelope.epochs=1", f"algo.epochs={samples / 1e6}",
               f"eval.every_epochs={samples / 1e6}", "eval.episodes=1", "eval.max_steps=100",
               "eval.final_window=1", "progress=false", "checkpoint.enabled=false", f"data_dir={tmp}/cache",
               f"hydra.run.dir={tmp}/run"]
        start = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True)
        run_s = time.perf_counter() - start
        if proc.returncode:
            sys.exit(f"the training run failed:\n{proc.stderr[-3000:]}")
        peak_gib = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024 / 2**30  # ru_maxrss is in KiB
        summary = json.loads((Path(tmp) / "run" / "summary.json").read_text())
    record = {
        "env": args.env, "env_id": env_id, "transitions": args.transitions, "observation_dim": obs_dim,
        "action_dim": act_dim, "batch_on_disk_gib": round(size_gib, 3), "peak_rss_gib": round(peak_gib, 3),
        "write_s": round(written_s, 1), "run_s": round(run_s, 1),
        "selected_fraction": summary["selected_fraction"], "envelope_epochs": 1, "imitation_updates": args.updates,
        "command": " ".join(["python", "benchmarks/bench_memory.py", *sys.argv[1:]]),
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}",
    }
    print(json.dumps(record, indent=1))
    run_record.write([], memory=record)


if __name__ == "__main__":
    main()

"""``compile=true`` against eager: training updates per second of every algorithm, compiled and eager side by side.

    python benchmarks/bench_compile.py [--algos bail,pbail,...: default every algorithm] [--modes true] [--device cpu]
                                       [--updates 30] [--repeats 5] [--threads 1] [--json PATH]

Each case builds the algorithm twice from the same seed at the paper's sizes (``conf/algo/<name>.yaml``: BC/BAIL's
imitation 400-300 at batch 1000, Progressive BAIL with its 128-128 envelope at batch 1000, MARWIL 400-300 + value
net at batch 1000, BCQ/BEAR with 750-750 VAE and 400-300 actor/critics at batch 100; Hopper shapes, obs 11, act 3),
compiles one of them (:meth:`~torchrl_bail.algorithms.Algorithm.compile` with each ``--modes`` entry) and times
what the training loop runs per iteration: ``TensorDictReplayBuffer.sample()`` on the device, then ``update``.
Compiled and eager rounds alternate (medians over ``--repeats``), so a noisy neighbour hits both; the table gives
both rates, their ratio (compiled / eager) and the one-off compile time (the first calls).

BAIL's update is BC's imitation step on the selected pairs (the same method): its row times it on BAIL's object.

``--device cuda`` for a GPU session (``benchmarks/gpu_check.sh``); rounds then end with a
``torch.cuda.synchronize()``. Modes there: ``true`` (inductor + one CUDA graph of the whole update,
:class:`tensordict.nn.CudaGraphModule`), ``reduce-overhead`` (inductor's own CUDA graphs of the compiled pieces),
``default`` (inductor, no CUDA graphs).
"""

from __future__ import annotations

import argparse
import time

import torch
from _bench import Record, add_record_argument, summarise
from tensordict import TensorDict
from torchrl.data import RandomSampler, TensorDictReplayBuffer, TensorStorage

from torchrl_bail.algorithms import ALGORITHMS, PrepareContext
from torchrl_bail.configuration.algo_schemas import envelope_algorithm
from torchrl_bail.configuration.config_builders import algo_config
from torchrl_bail.modules import action_spec_from_bounds

OBS, ACT, ROWS = 11, 3, 20_000


def synthetic_data(n: int = ROWS) -> TensorDict:
    g = torch.Generator().manual_seed(0)
    obs = torch.randn(n, OBS, generator=g)
    return TensorDict({
        "observation": obs, "action": torch.rand(n, ACT, generator=g) * 2 - 1,
        "return": 100 + 50 * obs[:, 0] + 10 * torch.rand(n, generator=g),
        "next": {"observation": torch.randn(n, OBS, generator=g), "reward": torch.randn(n, 1, generator=g),
                 "terminated": torch.rand(n, 1, generator=g) < 0.01},
    }, [n])


def build(name: str, device: torch.device, data: TensorDict):
    """The algorithm at its yaml's sizes and a replay buffer over the data it trains on (BAIL: the whole batch)."""
    torch.manual_seed(0)
    algo = ALGORITHMS[name](OBS, action_spec_from_bounds([-1.0] * ACT, [1.0] * ACT), algo_config(name), device)
    prepared = data if name == envelope_algorithm() else algo.prepare(data, PrepareContext())  # no envelope fit
    storage = TensorStorage(prepared.to(device))
    buffer = TensorDictReplayBuffer(storage=storage, sampler=RandomSampler(), batch_size=algo.batch_size)
    return algo, buffer


def updates_per_second(algo, buffer, n: int, device: torch.device) -> float:
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    sync()
    start = time.perf_counter()
    for _ in range(n):
        algo.update(buffer.sample())
    sync()
    return n / (time.perf_counter() - start)


def measure(name: str, mode, device: torch.device, data: TensorDict, n: int, repeats: int) -> dict:
    eager, eager_buffer = build(name, device, data)
    compiled, compiled_buffer = build(name, device, data)
    compiled.compile(mode)
    start = time.perf_counter()
    updates_per_second(compiled, compiled_buffer, 8, device)  # compiles (and captures CUDA graphs) here
    compile_s = time.perf_counter() - start
    updates_per_second(eager, eager_buffer, 3, device)
    eager_rates, compiled_rates = [], []
    for _ in range(repeats):
        eager_rates.append(updates_per_second(eager, eager_buffer, n, device))
        compiled_rates.append(updates_per_second(compiled, compiled_buffer, n, device))
    return summarise(f"{name} update (batch {eager.batch_size}), compile={str(mode).lower()} on {device}",
                     "updates/s", {"compiled_updates_per_s": compiled_rates, "eager_updates_per_s": eager_rates},
                     ratio_of=("compiled_updates_per_s", "eager_updates_per_s"), algo=name, mode=str(mode).lower(),
                     device=str(device), compile_s=compile_s, batch_size=eager.batch_size)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--algos", default=",".join(ALGORITHMS))
    parser.add_argument("--modes", default="true", help="comma-separated compile settings (true, default, "
                        "reduce-overhead, max-autotune)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--updates", type=int, default=30, help="updates per timed round")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (0: torch's default)")
    add_record_argument(parser, __file__)
    args = parser.parse_args()
    record = Record(__file__, args.json, reference="eager", settings=vars(args))
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    modes = [True if m.lower() == "true" else m for m in args.modes.split(",")]
    data = synthetic_data()
    rows = []
    print(f"compiled vs eager updates/s on {device} (torch {torch.__version__}, {torch.get_num_threads()} threads)")
    print(f"{'algo':<8} {'mode':<16} {'batch':>5} {'eager':>10} {'compiled':>10} {'ratio':>6} {'compile s':>10}")
    for name in args.algos.split(","):
        for mode in modes:
            row = measure(name, mode, device, data, args.updates, args.repeats)
            rows.append(row)
            print(f"{name:<8} {row['mode']:<16} {row['batch_size']:>5} {row['eager_updates_per_s']:>10.1f} "
                  f"{row['compiled_updates_per_s']:>10.1f} {row['ratio']:>6.2f} {row['compile_s']:>10.1f}", flush=True)
    record.write(rows)


if __name__ == "__main__":
    main()

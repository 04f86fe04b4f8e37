"""Many seeds in one process: 5 seeds stacked (torchrl_bail.core.stacking) against 5 single-seed runs doing the same
work.

    OMP_NUM_THREADS=1 python benchmarks/bench_seed_stack.py [--seeds 5] [--algos bc bail bcq bear ...]
                                                            [--repeats 15] [--device cpu|cuda] [--json PATH]

For each algorithm of the registry, with its paper configuration (``conf/algo/<name>.yaml``) at Hopper sizes
(obs 11, act 3) on a synthetic batch of 20 000 transitions, the same process alternates, round by round:

* ``stacked``: one training iteration of the :class:`~torchrl_bail.core.stacking.SeedStack` of ``S`` seeds: a ``[S, B]``
  mini-batch from :class:`~torchrl_bail.core.stacking.SeedBatchSampler` and one update step;
* ``sequential``: the same iteration of the ``S`` single-seed algorithms one after the other (each samples its
  mini-batch as :func:`~torchrl_bail.training.trainer.train` does and takes its update step): what ``S`` separate runs
  compute.

``speedup`` = stacked iterations/s / sequential rounds/s: the wall time of ``S`` sequential seeds over that of the
stacked run (>= 1: the stack is no slower per seed; on a GPU the stacked run should cost <= 1.5x one seed, i.e.
``speedup >= S / 1.5``; the column ``vs 1 seed`` gives stacked time / one seed's time). The row ``bail envelope``
times BAIL's envelope fit (2 epochs over the batch): one seed-stacked fit against ``S`` fits. Rates are medians over
the rounds, so a noisy neighbour on a shared machine hits both sides alike.
"""

from __future__ import annotations

import argparse
import time

import torch
from _bench import Record, add_record_argument, machine, print_columns, summarise
from tensordict import TensorDict
from torchrl.data import RandomSampler, TensorDictReplayBuffer, TensorStorage

from torchrl_bail.algorithms import ALGORITHMS, PrepareContext
from torchrl_bail.configuration.algo_schemas import blocks_with, envelope_algorithm
from torchrl_bail.configuration.config_builders import algo_config
from torchrl_bail.core.stacking import SeedBatchSampler, SeedStack, prepare_seeds
from torchrl_bail.modules import action_spec_from_bounds, make_value_network
from torchrl_bail.training.envelope import fit_upper_envelope

OBS, ACT, N = 11, 3, 20_000
SPEC = action_spec_from_bounds([-1.0] * ACT, [1.0] * ACT)


def synthetic_batch(device) -> TensorDict:
    g = torch.Generator().manual_seed(0)
    return TensorDict({
        "observation": torch.randn(N, OBS, generator=g), "action": torch.rand(N, ACT, generator=g) * 2 - 1,
        "return": 50 * torch.rand(N, generator=g),
        "next": {"observation": torch.randn(N, OBS, generator=g), "reward": torch.randn(N, 1, generator=g),
                 "terminated": torch.zeros(N, 1, dtype=torch.bool)},
    }, [N]).to(device)


def _sync(device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _one_round(fn, rates: list[float]) -> None:
    """Times one call of ``fn`` and appends its rate (calls per second) to ``rates``."""
    start = time.perf_counter()
    fn()
    rates.append(1.0 / (time.perf_counter() - start))


def interleaved(name: str, stacked, sequential, single, *, repeats: int, warmup: int = 3) -> dict:
    """Rates of the three callables, alternating round by round: one row with every round, the medians,
    ``speedup`` (= ``ratio``, stacked / sequential) and ``vs_one_seed`` (stacked time / one seed's time)."""
    for fn in (stacked, sequential, single):
        for _ in range(warmup):
            fn()
    rates: tuple[list[float], list[float], list[float]] = ([], [], [])
    for _ in range(repeats):
        for fn, r in zip((stacked, sequential, single), rates, strict=True):
            _one_round(fn, r)
    keys = ("stacked_per_s", "sequential_per_s", "single_per_s")
    row = summarise(name, "iterations/s", dict(zip(keys, rates, strict=True)),
                    ratio_of=("stacked_per_s", "sequential_per_s"))
    row.update(speedup=row["ratio"], vs_one_seed=row["single_per_s"] / row["stacked_per_s"])
    return row


def bench_updates(name: str, seeds: int, data: TensorDict, device, repeats: int) -> dict:
    config = algo_config(name, **{f"{block}.epochs": 1 for block in blocks_with(name, "epochs")})
    cls = ALGORITHMS[name]

    def build(seed: int):
        torch.manual_seed(seed)
        return cls(OBS, SPEC, config, device)

    contexts = [PrepareContext(generator=torch.Generator().manual_seed(s)) for s in range(seeds)]
    # the stack: its seeds' prepared data (BAIL: a quick one-epoch envelope keeps about 30 %)
    stacked_algos = [build(s) for s in range(seeds)]
    prepared = prepare_seeds(stacked_algos, data, contexts)
    stack = SeedStack(stacked_algos)
    streams = [torch.Generator(device=device).manual_seed(s) for s in range(seeds)]
    sampler = SeedBatchSampler(prepared, stack.batch_size, streams, device=device)
    # the sequential runs: each with its own replay buffer, as train() builds it
    singles = [build(s) for s in range(seeds)]
    buffers = [TensorDictReplayBuffer(storage=TensorStorage(d.to(device)), sampler=RandomSampler(),
                                      batch_size=a.batch_size) for a, d in zip(singles, prepared, strict=True)]

    def stacked() -> None:
        stack.update(sampler.sample())
        _sync(device)

    def sequential() -> None:
        for algorithm, buffer in zip(singles, buffers, strict=True):
            algorithm.update(buffer.sample())
        _sync(device)

    def single() -> None:
        singles[0].update(buffers[0].sample())
        _sync(device)

    return interleaved(f"{name} update (batch {stack.batch_size})", stacked, sequential, single, repeats=repeats)


def bench_envelope(seeds: int, data: TensorDict, device, repeats: int) -> dict:
    config = algo_config(envelope_algorithm())
    env = config.envelope
    kwargs = dict(penalty=env.penalty, lr=env.lr, weight_decay=env.weight_decay, batch_size=env.batch_size,
                  epochs=2, val_fraction=env.val_fraction, patience=env.patience, progress=False, device=device)
    observations, returns = data["observation"], data["return"]

    def networks():
        torch.manual_seed(0)
        return [make_value_network(OBS, tuple(env.hidden), head_scale=env.head_scale).to(device)
                for _ in range(seeds)]

    def stacked() -> None:
        fit_upper_envelope(networks(), observations, returns,
                           generators=[torch.Generator().manual_seed(s) for s in range(seeds)], **kwargs)
        _sync(device)

    def sequential() -> None:
        for s, net in enumerate(networks()):
            fit_upper_envelope([net], observations, returns, generators=[torch.Generator().manual_seed(s)], **kwargs)
        _sync(device)

    def single() -> None:
        fit_upper_envelope(networks()[:1], observations, returns, generators=[torch.Generator().manual_seed(0)],
                           **kwargs)
        _sync(device)

    return interleaved(f"{envelope_algorithm()} envelope fit (2 epochs, batch {env.batch_size})", stacked, sequential,
                       single, repeats=max(3, repeats // 5), warmup=1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--algos", nargs="+", default=[name for name, cls in ALGORITHMS.items()
                                                       if cls.seed_stack_refusal is None])
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=None)
    add_record_argument(parser, __file__)
    args = parser.parse_args()
    record = Record(__file__, args.json, reference=f"{args.seeds} seeds one after the other", settings=vars(args))
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    data = synthetic_batch(device)
    rows = [bench_updates(name, args.seeds, data, device, args.repeats) for name in args.algos]
    if envelope_algorithm() in args.algos:
        rows.append(bench_envelope(args.seeds, data, device, args.repeats))
    columns = [("stacked/s", "stacked_per_s", ">10.2f"), ("sequential/s", "sequential_per_s", ">13.2f"),
                   ("speedup", "speedup", ">8.2f"), ("vs 1 seed", "vs_one_seed", ">10.2f")]
    print_columns(f"{args.seeds} seeds stacked vs {args.seeds} sequential on {device} ({machine()})", rows, columns)
    record.write(rows)


if __name__ == "__main__":
    main()

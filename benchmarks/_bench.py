"""Shared timing helpers for the benchmark scripts (``python benchmarks/bench_<name>.py``).

Every benchmark measures a torchrl_bail code path and a bare-PyTorch version of the same math *in the same
process, interleaved*, and reports ``ratio = torchrl_bail rate / bare rate`` (1.0 = no overhead; the issues ask
for >= 0.8). Rates are medians over ``repeats`` alternating rounds, so a noisy neighbour hits both sides.
"""

from __future__ import annotations

import json
import os
import statistics
import time
from collections.abc import Callable, Sequence
from pathlib import Path

os.environ.setdefault("RL_WARNINGS", "0")

import torch  # noqa: E402
from torch import nn  # noqa: E402

__all__ = ["rate", "compare", "bare_mlp", "print_table", "write_json"]


def rate(fn: Callable[[], object], n: int, warmup: int = 10) -> float:
    """Calls per second of ``fn`` over ``n`` calls after ``warmup`` calls."""
    for _ in range(warmup):
        fn()
    start = time.perf_counter()
    for _ in range(n):
        fn()
    return n / (time.perf_counter() - start)


def compare(name: str, library: Callable[[], object], bare: Callable[[], object], *, n: int, repeats: int = 5,
            unit: str = "updates/s") -> dict:
    """Interleaved rounds of ``library`` and ``bare``; returns one table row with medians and their ratio."""
    rate(library, 0, warmup=max(3, n // 10))
    rate(bare, 0, warmup=max(3, n // 10))
    lib_rates, bare_rates = [], []
    for _ in range(repeats):
        lib_rates.append(rate(library, n, warmup=0))
        bare_rates.append(rate(bare, n, warmup=0))
    lib, base = statistics.median(lib_rates), statistics.median(bare_rates)
    return {"name": name, "unit": unit, "torchrl_bail": lib, "bare": base, "ratio": lib / base}


def bare_mlp(in_features: int, out_features: int, hidden: Sequence[int]) -> nn.Sequential:
    """``Linear -> ReLU`` blocks then a linear head, PyTorch default init (the bare-loop twin of ``modules.mlp``)."""
    layers: list[nn.Module] = []
    width = in_features
    for h in hidden:
        layers += [nn.Linear(width, h), nn.ReLU()]
        width = h
    layers.append(nn.Linear(width, out_features))
    return nn.Sequential(*layers)


def print_table(rows: list[dict], title: str) -> None:
    print(f"\n{title}  (torch {torch.__version__}, {torch.get_num_threads()} threads)")
    print(f"{'case':<34} {'torchrl_bail':>14} {'bare torch':>14} {'ratio':>7}  unit")
    for r in rows:
        print(f"{r['name']:<34} {r['torchrl_bail']:>14.1f} {r['bare']:>14.1f} {r['ratio']:>7.2f}  {r['unit']}")


def write_json(rows: list[dict], path: str | os.PathLike | None) -> None:
    if path:
        Path(path).write_text(json.dumps(rows, indent=2) + "\n")

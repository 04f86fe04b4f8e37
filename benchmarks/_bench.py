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

__all__ = ["rate", "compare", "bare_mlp", "machine", "print_columns", "print_table", "write_json"]


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


def machine() -> str:
    """``"torch <version>, <n> thread(s), load average <l> on <c> CPUs"``: what a table's numbers were measured on
    (read at the end of a run, so the load average covers it)."""
    return (f"torch {torch.__version__}, {torch.get_num_threads()} thread(s), load average {os.getloadavg()[0]:.1f} "
            f"on {os.cpu_count()} CPUs")


def print_columns(title: str, rows: list[dict], columns: Sequence[tuple[str, str, str]], name_width: int = 44) -> None:
    """``title``, then one line per row: its ``name`` and, per ``(header, key, format spec)`` column, ``row[key]``
    formatted (``">10.2f"``) under its header, aligned as the spec says (``<``: left, else right)."""
    cells = [[format(r[key], spec) for r in rows] for _, key, spec in columns]
    widths = [max([len(header), *map(len, column)]) for (header, _, _), column in zip(columns, cells)]
    aligns = ["<" if spec.startswith("<") else ">" for _, _, spec in columns]
    print(f"\n{title}")
    print(f"{'case':<{name_width}}" + "".join(f" {h:{a}{w}}" for (h, _, _), a, w in zip(columns, aligns, widths)))
    for i, r in enumerate(rows):
        print(f"{r['name']:<{name_width}}" + "".join(f" {column[i]:{a}{w}}"
                                                     for column, a, w in zip(cells, aligns, widths)))


def print_table(rows: list[dict], title: str) -> None:
    """The torchrl_bail-vs-bare table of :func:`compare` rows."""
    print_columns(f"{title}  ({machine()})", rows,
                  [("torchrl_bail", "torchrl_bail", ">14.1f"), ("bare torch", "bare", ">14.1f"),
                   ("ratio", "ratio", ">7.2f"), ("unit", "unit", "<10")], name_width=34)


def write_json(rows: list[dict], path: str | os.PathLike | None) -> None:
    if path:
        Path(path).write_text(json.dumps(rows, indent=2) + "\n")

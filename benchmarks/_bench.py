"""Shared timing and record helpers for the benchmark scripts (``python benchmarks/bench_<name>.py``).

Every benchmark measures a torchrl_bail code path and a reference doing the same work (bare PyTorch, a plain
gymnasium loop, eager updates, sequential seeds) *in the same process, interleaved*, and reports
``ratio = torchrl_bail rate / reference rate`` (1.0 = no overhead; the issues ask for >= 0.8). Rates are medians
over ``repeats`` alternating rounds, so a noisy neighbour hits both sides.

Every run writes a JSON record (:class:`Record`, default ``results/benchmarks/<script stem>.json``): the command
line, package versions, CPU model and affinity, threads, load average at start and end, timestamps, wall and CPU
seconds of the process, the git commit (and the uncommitted files of ``src/``, ``conf/``), every round's
figure of every side, and the derived ratio rows (``table``). ``benchmarks/render_records.py`` renders the tables of
``docs/benchmarks.md`` from these records.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import shlex
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from importlib import metadata
from pathlib import Path

os.environ.setdefault("RL_WARNINGS", "0")

import torch  # noqa: E402
from torch import nn  # noqa: E402

from torchrl_bail.core.io import write_json_atomic  # noqa: E402

__all__ = ["rate", "compare", "summarise", "bare_mlp", "machine", "print_columns", "print_table", "write_json",
           "Record", "RECORDS", "PACKAGES", "add_record_argument", "derive_table"]

ROOT = Path(__file__).resolve().parents[1]
RECORDS = ROOT / "results" / "benchmarks"
# the versions a record states (the d3rlpy side of bench_d3rlpy*.py adds its own)
PACKAGES = ("torch", "torchrl", "tensordict", "gymnasium", "mujoco", "numpy")


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
    return summarise(name, unit, {"torchrl_bail": lib_rates, "bare": bare_rates}, calls_per_round=n)


def summarise(name: str, unit: str, rounds: Mapping[str, Sequence[float]],
              ratio_of: tuple[str, str] = ("torchrl_bail", "bare"), **extra) -> dict:
    """One measured row: every side's rounds (``rounds[side]``, one figure per round), their medians under the
    side's name, and ``ratio`` = median of ``ratio_of[0]`` / median of ``ratio_of[1]``; ``extra`` keys are kept."""
    medians = {side: statistics.median(values) for side, values in rounds.items()}
    numerator, denominator = ratio_of
    return {"name": name, "unit": unit, **medians, "ratio": medians[numerator] / medians[denominator],
            "ratio_of": [numerator, denominator], "rounds": {side: list(v) for side, v in rounds.items()}, **extra}


def derive_table(rows: Sequence[dict]) -> list[dict]:
    """The ratio rows a record's table shows, derived from its measured rows (those with ``ratio_of``): case, unit,
    the two sides' medians, ``ratio`` and the number of rounds behind each median."""
    table = []
    for row in rows:
        if "ratio_of" not in row:
            continue
        numerator, denominator = row["ratio_of"]
        ours = statistics.median(row["rounds"][numerator])
        reference = statistics.median(row["rounds"][denominator])
        table.append({"case": row["name"], "unit": row["unit"], "torchrl_bail": ours, "reference": reference,
                      "ratio": ours / reference, "rounds": len(row["rounds"][numerator])})
    return table


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
    widths = [max([len(header), *map(len, column)]) for (header, _, _), column in zip(columns, cells, strict=True)]
    aligns = ["<" if spec.startswith("<") else ">" for _, _, spec in columns]
    print(f"\n{title}")
    print(f"{'case':<{name_width}}"
          + "".join(f" {h:{a}{w}}" for (h, _, _), a, w in zip(columns, aligns, widths, strict=True)))
    for i, r in enumerate(rows):
        print(f"{r['name']:<{name_width}}" + "".join(f" {column[i]:{a}{w}}"
                                                     for column, a, w in zip(cells, aligns, widths, strict=True)))


def print_table(rows: list[dict], title: str) -> None:
    """The torchrl_bail-vs-bare table of :func:`compare` rows."""
    print_columns(f"{title}  ({machine()})", rows,
                  [("torchrl_bail", "torchrl_bail", ">14.1f"), ("bare torch", "bare", ">14.1f"),
                   ("ratio", "ratio", ">7.2f"), ("unit", "unit", "<10")], name_width=34)


def write_json(rows: list[dict], path: str | os.PathLike | None) -> None:
    if path:
        write_json_atomic(path, rows)


def add_record_argument(parser: argparse.ArgumentParser, script: str) -> None:
    """``--json PATH``: where the run's :class:`Record` goes (default ``results/benchmarks/<script stem>.json``;
    ``--json ''`` writes none)."""
    default = RECORDS / f"{Path(script).stem}.json"
    parser.add_argument("--json", default=str(default.relative_to(ROOT)),
                        help="the run's JSON record (default: %(default)s, relative to the repository root; "
                             "'' writes none)")


def _versions(packages: Sequence[str] = PACKAGES) -> dict[str, str | None]:
    out: dict[str, str | None] = {"python": platform.python_version()}
    for name in packages:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _git() -> dict | None:
    """The checkout measured: ``HEAD`` and the files of ``src/`` and ``conf/`` that differ from it."""
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=True)
        status = subprocess.run(["git", "status", "--porcelain", "--", "src", "conf"], cwd=ROOT, capture_output=True,
                                text=True, check=True)
    except (OSError, subprocess.CalledProcessError):
        return None
    return {"commit": head.stdout.strip(), "uncommitted": [line[3:] for line in status.stdout.splitlines()]}


def _now() -> str:
    return datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")


class Record:
    """A benchmark run's JSON record: made at the start of ``main`` (command line, start time and load average),
    written by :meth:`write` at the end (or after each row of a long run) atomically to ``path``.

    ``reference`` names what the ratio divides by (``"bare PyTorch"``, ``"eager"``, ...). :meth:`write` stores
    ``rows`` as given (each round of each side included, see :func:`summarise`) and the derived ``table``.
    """

    def __init__(self, script: str, path: str | os.PathLike | None, *, reference: str, settings: Mapping | None = None):
        self.script = Path(script).name
        self.path = None if not path else (Path(path) if Path(path).is_absolute() else ROOT / path)
        self.reference = reference
        self.settings = dict(settings or {})
        self.started = _now()
        self.load_start = list(os.getloadavg())
        self._t0, self._cpu0 = time.perf_counter(), time.process_time()
        self.git = _git()

    def snapshot(self, rows: Sequence[dict], **extra) -> dict:
        """The record as it stands: everything :meth:`write` writes."""
        affinity = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
        return {
            "script": self.script,
            "command": shlex.join(["python", os.path.relpath(sys.argv[0], ROOT), *sys.argv[1:]]),
            "settings": self.settings,
            "started": self.started,
            "finished": _now(),
            "wall_s": time.perf_counter() - self._t0,
            # CPU seconds this process got (all its threads): on a busy CPU well below wall_s x threads
            "process_cpu_s": time.process_time() - self._cpu0,
            "versions": _versions(),
            "git": self.git,
            "machine": {"cpu_model": _cpu_model(), "cpus": os.cpu_count(), "affinity": affinity,
                        "torch_threads": torch.get_num_threads(),
                        "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS")},
            "load_average": {"start": self.load_start, "end": list(os.getloadavg())},
            "reference": self.reference,
            **extra,
            "rows": list(rows),
            "table": derive_table(rows),
        }

    def write(self, rows: Sequence[dict], **extra) -> dict:
        """Writes the record (atomically; nothing when the path is empty) and returns it."""
        record = self.snapshot(rows, **extra)
        if self.path is not None:
            write_json_atomic(self.path, record)
            print(f"record: {self.path}", flush=True)
        return record

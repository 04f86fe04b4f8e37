"""Renders the tables of ``docs/benchmarks.md`` from the benchmark records, one Markdown file per table.

    python benchmarks/render_records.py            # (re)writes results/benchmarks/*.md
    python benchmarks/render_records.py --check    # exits 1 naming every table that differs from its records

Sources (every figure of the tables comes from one of them; nothing is typed by hand):

* ``results/benchmarks/<script stem>.json``: the records the benchmark scripts write (:class:`_bench.Record`):
  ``ratios.md`` (every measured row of every record: both sides' medians, the ratio, the number of rounds),
  ``records.md`` (what each record was measured on: command, CPU, pinning, threads, load average, versions) and
  ``collection_rates.md`` (``bench_collection.py``'s env and collection rates);
* ``results/d3rlpy/<batch>.json``: the rows ``bench_d3rlpy_returns.py`` wrote (``d3rlpy_returns_<batch>.md``). A
  row without the fields the script writes for every row (``d3rlpy_evaluations``) was copied into the file from
  the run's printed output; its figures are marked ``†`` in the table.

``docs/benchmarks.md`` includes the files with ``--8<--`` (pymdownx.snippets), as the Results page includes
``results/study/study.md``; ``tests/test_bench_records.py`` renders them again and compares.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

from torchrl_bail.io import write_text_atomic

ROOT = Path(__file__).resolve().parents[1]
RECORDS = ROOT / "results" / "benchmarks"
D3RLPY = ROOT / "results" / "d3rlpy"
# the order of the ratio table; a record of any other script follows, by name
ORDER = ("bench_bail", "bench_marwil", "bench_bcq_bear", "bench_collection", "bench_evaluation", "bench_seed_stack",
         "bench_compile", "bench_d3rlpy", "bench_sweep", "bench_memory")
D3RLPY_BATCHES = ("hopper_sac_b1", "hopper_ddpg05_b1", "hopper_ddpg05_b1_bcq_decoder_tanh")
COPIED = "†"


def load_records(directory: Path = RECORDS) -> dict[str, dict]:
    """``{script stem: record}`` of every ``*.json`` record in ``directory``, in the table's order."""
    found = {p.stem: json.loads(p.read_text()) for p in directory.glob("*.json")}
    order = [s for s in ORDER if s in found] + sorted(set(found) - set(ORDER))
    return {stem: found[stem] for stem in order}


def num(value: float) -> str:
    """A rate or time at a precision that fits its size: 1234.5, 56.7, 8.91, 0.123."""
    size = abs(value)
    return f"{value:.1f}" if size >= 10 else f"{value:.2f}" if size >= 0.1 else f"{value:.3f}"


def render_ratios(records: dict[str, dict]) -> str:
    lines = ["| script | case | torchrl_bail | reference | unit | ratio | rounds |", "|---|---|---|---|---|---|---|"]
    for stem, record in records.items():
        for row in record["rows"]:
            if "ratio_of" in row:
                numerator, denominator = row["ratio_of"]
                ours = statistics.median(row["rounds"][numerator])
                reference = statistics.median(row["rounds"][denominator])
                cells = [num(ours), f"{record['reference']}: {num(reference)}", row["unit"],
                         f"**{ours / reference:.2f}**", str(len(row["rounds"][numerator]))]
            elif "rounds" in row:  # absolute figures of the library's own variants, no reference
                medians = ", ".join(f"{side.removesuffix('_s')}: {num(statistics.median(values))}"
                                    for side, values in row["rounds"].items())
                cells = [medians, "—", row["unit"], "—", str(min(len(v) for v in row["rounds"].values()))]
            else:
                continue
            lines.append(f"| `{stem}.py` | {row['name']} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _load(load: list[float]) -> str:
    return f"{load[0]:.2f}"


def _commit(git: dict | None) -> str:
    """``HEAD``'s short hash, with the number of files of ``src/`` and ``conf/`` that differed from it."""
    if not git:
        return "?"
    dirty = len(git["uncommitted"])
    return f"`{git['commit'][:8]}`" + (f" + {dirty} uncommitted src/conf files" if dirty else "")


def render_records(records: dict[str, dict]) -> str:
    lines = ["| record | command | started (UTC) | commit | wall s | CPU s of the process | CPU | CPUs pinned / torch "
             "threads / OMP_NUM_THREADS | load average (1 min) start → end |", "|---|---|---|---|---|---|---|---|---|"]
    versions = {}
    for stem, r in records.items():
        m = r["machine"]
        pinned = ",".join(map(str, m["affinity"])) if m["affinity"] is not None else "?"
        started = r["started"].replace("+00:00", "")
        lines.append(f"| `results/benchmarks/{stem}.json` | `{r['command']}` | {started} | {_commit(r.get('git'))} | "
                     f"{r['wall_s']:.0f} | "
                     f"{r['process_cpu_s']:.0f} | {m['cpu_model']} ({m['cpus']} CPUs) | {pinned} / "
                     f"{m['torch_threads']} / {m['OMP_NUM_THREADS']} | {_load(r['load_average']['start'])} → "
                     f"{_load(r['load_average']['end'])} |")
        versions.setdefault(", ".join(f"{k} {v}" for k, v in r["versions"].items()), []).append(stem)
    lines.append("")
    for text, stems in versions.items():
        which = "all records" if len(versions) == 1 else ", ".join(f"`{s}`" for s in stems)
        lines.append(f"Versions ({which}): {text}.")
    return "\n".join(lines) + "\n"


def render_collection_rates(record: dict) -> str:
    c = record["collection"]
    lines = ["| recipe | env steps/s, acting only | agent updates/s (replay sample included) | steady state, one "
             "update per env step: env steps/s | hours per 10^6 steps |", "|---|---|---|---|---|"]
    for algo, actor in (("ddpg", "ddpg_actor"), ("sac", "sac_actor")):
        lines.append(f"| {algo.upper()} | {num(c[f'env_steps_per_s_{actor}'])} | {num(c[f'{algo}_updates_per_s'])} | "
                     f"{num(c[f'{algo}_collection_steps_per_s'])} | {num(c[f'{algo}_hours_per_1e6_steps'])} |")
    lines.append(f"| random actions | {num(c['env_steps_per_s_random'])} | — | — | — |")
    return "\n".join(lines) + "\n"


def d3rlpy_rows(path: Path) -> list[dict]:
    """The rows of a ``bench_d3rlpy_returns.py`` output: a plain list (older files) or a record's ``rows``."""
    data = json.loads(path.read_text())
    return data["rows"] if isinstance(data, dict) else data


def recorded(row: dict) -> bool:
    """Whether the script wrote the row (it writes ``d3rlpy_evaluations`` on every row it writes)."""
    return "d3rlpy_evaluations" in row


def render_d3rlpy_returns(rows: list[dict]) -> str:
    lines = ["| batch | algo | updates | seeds | torchrl_bail per seed | d3rlpy per seed | torchrl_bail mean ± std "
             "| d3rlpy mean ± std |", "|---|---|---|---|---|---|---|---|"]
    copied = []
    for batch in dict.fromkeys(r["batch"] for r in rows):
        for algo in dict.fromkeys(r["algo"] for r in rows if r["batch"] == batch):
            group = [r for r in rows if r["batch"] == batch and r["algo"] == algo]
            mark = COPIED if not all(recorded(r) for r in group) else ""
            copied += [f"{algo} seed {r['seed']}" for r in group if not recorded(r)]

            def per_seed(side, group=group):
                return " / ".join(f"{r[side]:.1f}" + ("" if recorded(r) else COPIED) for r in group)

            def mean_std(side, group=group, mark=mark):
                values = [r[side] for r in group]
                spread = f"{statistics.stdev(values):.1f}" if len(values) > 1 else "—"
                return f"{statistics.mean(values):.1f} ± {spread}{mark}"

            updates = sorted({r["updates"] for r in group})
            lines.append(f"| {batch} | {algo} | {', '.join(map(str, updates))} | "
                         f"{', '.join(str(r['seed']) for r in group)} | {per_seed('torchrl_bail')} | "
                         f"{per_seed('d3rlpy')} | {mean_std('torchrl_bail')} | {mean_std('d3rlpy')} |")
    if copied:
        lines += ["", f"{COPIED} Not written by the script: {', '.join(copied)} were copied into the JSON from the "
                  "run's printed output (one decimal), and the means marked so include them."]
    return "\n".join(lines) + "\n"


def render_all(records_dir: Path = RECORDS, d3rlpy_dir: Path = D3RLPY) -> dict[Path, str]:
    """``{output path: Markdown}`` of every table."""
    records = load_records(records_dir)
    out = {records_dir / "ratios.md": render_ratios(records), records_dir / "records.md": render_records(records)}
    if "bench_collection" in records:
        out[records_dir / "collection_rates.md"] = render_collection_rates(records["bench_collection"])
    for batch in D3RLPY_BATCHES:
        rows = d3rlpy_rows(d3rlpy_dir / f"{batch}.json")
        out[records_dir / f"d3rlpy_returns_{batch}.md"] = render_d3rlpy_returns(rows)
    return out


def stale(records_dir: Path = RECORDS, d3rlpy_dir: Path = D3RLPY) -> list[Path]:
    """The table files that are missing or differ from what their records render."""
    return [path for path, text in render_all(records_dir, d3rlpy_dir).items()
            if not path.is_file() or path.read_text() != text]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="compare, write nothing; exit 1 if a table differs")
    args = parser.parse_args(argv)
    if args.check:
        paths = stale()
        for path in paths:
            print(f"{path.relative_to(ROOT)} differs from its records: python benchmarks/render_records.py",
                  file=sys.stderr)
        return 1 if paths else 0
    for path, text in render_all().items():
        write_text_atomic(path, text)
        print(f"wrote {path.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

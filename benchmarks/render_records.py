"""Renders the tables of ``docs/benchmarks.md`` from the benchmark records, one Markdown file per table.

    python benchmarks/render_records.py            # (re)writes results/benchmarks/*.md
    python benchmarks/render_records.py --check    # exits 1 naming every table that differs from its records

Sources (every figure of the tables comes from one of them; nothing is typed by hand):

* ``results/benchmarks/<script stem>.json``: the records the benchmark scripts write (:class:`_bench.Record`):
  ``ratios.md`` (every measured row of every record: both sides' medians, the ratio, the number of rounds),
  ``records.md`` (what each record was measured on: command, CPU, pinning, threads, load average, versions) and
  ``collection_rates.md`` (``bench_collection.py``'s env and collection rates);
* ``results/d3rlpy/*.json``: the rows ``bench_d3rlpy_returns.py`` wrote; :data:`D3RLPY_TABLES` names the files
  whose rows make each ``d3rlpy_returns_<table>.md``. A row without the curve the script writes on every row
  (``d3rlpy_evaluations``) was not written by it, and rendering refuses it, as it refuses a cell given twice.

``docs/benchmarks.md`` includes the files with ``--8<--`` (pymdownx.snippets), as the Results page includes
``results/study/study.md``; ``tests/test_bench_records.py`` renders them again and compares.
"""

from __future__ import annotations

import argparse
import json
import re
import statistics
import sys
from pathlib import Path

from torchrl_bail.core.io import write_text_atomic

ROOT = Path(__file__).resolve().parents[1]
RECORDS = ROOT / "results" / "benchmarks"
D3RLPY = ROOT / "results" / "d3rlpy"
# the order of the ratio table; a record of any other script follows, by name
ORDER = ("bench_bail", "bench_marwil", "bench_bcq_bear", "bench_collection", "bench_evaluation", "bench_seed_stack",
         "bench_compile", "bench_d3rlpy", "bench_sweep", "bench_memory")
#: each d3rlpy returns table and the ``results/d3rlpy/<name>.json`` files whose rows it shows
D3RLPY_TABLES = {
    "hopper_sac_b1": ("hopper_sac_b1",),
    # BC seeds 4-5 and BEAR (the first runs); BC and BCQ seeds 1-3 (rerun, both sides' curves recorded)
    "hopper_ddpg05_b1": ("hopper_ddpg05_b1", "hopper_ddpg05_b1_bc_bcq"),
    "hopper_ddpg05_b1_bcq_decoder_tanh": ("hopper_ddpg05_b1_bcq_decoder_tanh",),
}
#: the row order of a d3rlpy table (bench_d3rlpy_returns.ALGOS); any other algorithm follows, by name
D3RLPY_ALGOS = ("bc", "bcq", "bear")


def load_records(directory: Path = RECORDS) -> dict[str, dict]:
    """``{script stem: record}`` of every ``*.json`` record in ``directory``, in the table's order."""
    found = {p.stem: json.loads(p.read_text()) for p in directory.glob("*.json")}
    order = [s for s in ORDER if s in found] + sorted(set(found) - set(ORDER))
    return {stem: found[stem] for stem in order}


def num(value: float) -> str:
    """A rate or time at a precision that fits its size: 1234.5, 56.7, 8.91, 0.123."""
    size = abs(value)
    return f"{value:.1f}" if size >= 10 else f"{value:.2f}" if size >= 0.1 else f"{value:.3f}"


def case_name(name: str) -> str:
    """A row's name with any float written at its shortest (``0.6000000000000001`` -> ``0.6``)."""
    return re.sub(r"\d+\.\d{10,}", lambda m: f"{float(m.group()):.12g}", name)


def render_ratios(records: dict[str, dict]) -> str:
    lines = ["| script | case | torchrl_bail | reference | unit | ratio | rounds |", "|---|---|---|---|---|---|---|"]
    for record in records.values():
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
            # the script that wrote the record: a second record of one script has a file name of its own
            lines.append(f"| `{record['script']}` | {case_name(row['name'])} | " + " | ".join(cells) + " |")
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
    """What each record was measured on, one list item per record (a table of these columns runs off the page)."""
    lines, versions = [], {}
    for stem, r in records.items():
        m = r["machine"]
        pinned = ",".join(map(str, m["affinity"])) if m["affinity"] is not None else "?"
        started = r["started"].replace("+00:00", "").replace("T", " ")
        lines.append(f"- `results/benchmarks/{stem}.json`: `{r['command']}`  \n"
                     f"  started {started} UTC at {_commit(r.get('git'))}; {r['wall_s']:.0f} s wall clock, "
                     f"{r['process_cpu_s']:.0f} CPU s of the process; {m['cpu_model']} ({m['cpus']} CPUs), "
                     f"pinned to CPU {pinned}, {m['torch_threads']} torch thread(s), "
                     f"OMP_NUM_THREADS={m['OMP_NUM_THREADS']}; load average (1 min) "
                     f"{_load(r['load_average']['start'])} → {_load(r['load_average']['end'])}")
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
    """The rows of a ``bench_d3rlpy_returns.py`` output: a plain list (older files) or a record's ``rows``; a row the
    script did not write (no ``d3rlpy_evaluations``, the curve it writes on every row) is refused."""
    data = json.loads(path.read_text())
    rows = data["rows"] if isinstance(data, dict) else data
    for row in rows:
        if "d3rlpy_evaluations" not in row:
            raise ValueError(f"{path.name}: {row['batch']} {row['algo']} seed {row['seed']} has no curve "
                             "(d3rlpy_evaluations): not a row bench_d3rlpy_returns.py wrote")
    return rows


def table_rows(paths: list[Path]) -> list[dict]:
    """The rows of ``paths`` in table order (algorithm, then seed); a cell (batch, algorithm, seed) given twice is
    refused, so a figure has one home."""
    rows, seen = [], {}
    for path in paths:
        for row in d3rlpy_rows(path):
            cell = (row["batch"], row["algo"], row["seed"])
            if cell in seen:
                raise ValueError(f"{cell[0]} {cell[1]} seed {cell[2]} is in both {seen[cell]} and {path.name}")
            seen[cell] = path.name
            rows.append(row)

    def order(row):
        known = row["algo"] in D3RLPY_ALGOS
        return (D3RLPY_ALGOS.index(row["algo"]) if known else len(D3RLPY_ALGOS), row["algo"], row["seed"])

    return sorted(rows, key=order)


def render_d3rlpy_returns(rows: list[dict]) -> str:
    lines = ["| batch | algo | updates | seeds | torchrl_bail per seed | d3rlpy per seed | torchrl_bail mean ± std "
             "| d3rlpy mean ± std |", "|---|---|---|---|---|---|---|---|"]
    for batch in dict.fromkeys(r["batch"] for r in rows):
        for algo in dict.fromkeys(r["algo"] for r in rows if r["batch"] == batch):
            group = [r for r in rows if r["batch"] == batch and r["algo"] == algo]

            def per_seed(side, group=group):
                return " / ".join(f"{r[side]:.1f}" for r in group)

            def mean_std(side, group=group):
                values = [r[side] for r in group]
                spread = f"{statistics.stdev(values):.1f}" if len(values) > 1 else "—"
                return f"{statistics.mean(values):.1f} ± {spread}"

            updates = sorted({r["updates"] for r in group})
            lines.append(f"| {batch} | {algo} | {', '.join(map(str, updates))} | "
                         f"{', '.join(str(r['seed']) for r in group)} | {per_seed('torchrl_bail')} | "
                         f"{per_seed('d3rlpy')} | {mean_std('torchrl_bail')} | {mean_std('d3rlpy')} |")
    return "\n".join(lines) + "\n"


def render_all(records_dir: Path = RECORDS, d3rlpy_dir: Path = D3RLPY) -> dict[Path, str]:
    """``{output path: Markdown}`` of every table."""
    records = load_records(records_dir)
    out = {records_dir / "ratios.md": render_ratios(records), records_dir / "records.md": render_records(records)}
    if "bench_collection" in records:
        out[records_dir / "collection_rates.md"] = render_collection_rates(records["bench_collection"])
    for table, sources in D3RLPY_TABLES.items():
        rows = table_rows([d3rlpy_dir / f"{source}.json" for source in sources])
        out[records_dir / f"d3rlpy_returns_{table}.md"] = render_d3rlpy_returns(rows)
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

"""Results table from run directories: ``python -m torchrl_bail.report multirun/ outputs/``.

Finds every ``summary.json`` below the given directories, groups runs by (batch, algorithm) and prints a
Markdown table of ``final_return`` mean ± std over seeds (the paper's convention), with the batch's mean
episode return beside it. ``--out results.md`` also writes it (atomically); ``--plot results.png`` draws a
bar chart per batch.

Examples:
    >>> rows = aggregate([{"batch": "hopper_ddpg05_b1", "algo": "bail", "seed": s, "final_return": r,
    ...                    "dataset_mean_episode_return": 100.0} for s, r in [(1, 300.0), (2, 500.0)]])
    >>> rows[0]["mean"], rows[0]["std"], rows[0]["seeds"]
    (400.0, 100.0, 2)
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections import defaultdict
from pathlib import Path

from torchrl_bail.io import write_text_atomic

__all__ = ["find_summaries", "aggregate", "format_table", "main"]

ALGO_ORDER = ["bail", "pbail", "bc", "marwil", "bcq", "bear"]


def find_summaries(paths: list[Path]) -> list[dict]:
    summaries = []
    for root in paths:
        root = Path(root)
        if not root.exists():
            raise FileNotFoundError(f"{root}: no such directory")
        files = [root] if root.name == "summary.json" else sorted(root.rglob("summary.json"))
        for f in files:
            try:
                summaries.append(json.loads(f.read_text()))
            except json.JSONDecodeError as err:
                raise ValueError(f"{f}: not a valid summary.json ({err})") from None
    return summaries


def aggregate(summaries: list[dict]) -> list[dict]:
    """One row per (batch, algo): mean and population std of ``final_return`` over seeds."""
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for s in summaries:
        groups[(s.get("batch"), s["algo"])].append(s)
    rows = []
    for (batch, algo), runs in groups.items():
        scores = [r["final_return"] for r in runs]
        mean = sum(scores) / len(scores)
        std = math.sqrt(sum((x - mean) ** 2 for x in scores) / len(scores))
        rows.append({"batch": batch, "algo": algo, "mean": mean, "std": std, "seeds": len(scores),
                     "dataset_mean": runs[0].get("dataset_mean_episode_return"),
                     "wall_time_s": sum(r.get("wall_time_s", 0.0) for r in runs) / len(runs)})
    order = {a: i for i, a in enumerate(ALGO_ORDER)}
    rows.sort(key=lambda r: (str(r["batch"]), order.get(r["algo"], len(order)), r["algo"]))
    return rows


def format_table(rows: list[dict]) -> str:
    lines = ["| batch | algo | final_return (mean ± std) | seeds | batch mean return | wall time / run |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        ds = "" if r["dataset_mean"] is None else f"{r['dataset_mean']:.1f}"
        lines.append(f"| {r['batch']} | {r['algo']} | {r['mean']:.1f} ± {r['std']:.1f} | {r['seeds']} | {ds} | "
                     f"{r['wall_time_s']:.0f} s |")
    return "\n".join(lines)


def plot_rows(rows: list[dict], path: Path) -> Path:
    from torchrl_bail.plots import plt, save_figure

    batches = sorted({str(r["batch"]) for r in rows})
    fig, axes = plt.subplots(1, len(batches), figsize=(4.5 * len(batches), 3.6), squeeze=False)
    for ax, batch in zip(axes[0], batches):
        sub = [r for r in rows if str(r["batch"]) == batch]
        ax.bar([r["algo"] for r in sub], [r["mean"] for r in sub], yerr=[r["std"] for r in sub], capsize=4)
        if sub[0]["dataset_mean"] is not None:
            ax.axhline(sub[0]["dataset_mean"], color="gray", linestyle="--", label="batch mean")
            ax.legend(loc="best")
        ax.set_title(batch)
        ax.set_ylabel("final return")
    return save_figure(fig, path)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m torchrl_bail.report", description=__doc__.split("\n\n")[0])
    parser.add_argument("paths", nargs="+", type=Path, help="run or sweep directories (searched recursively)")
    parser.add_argument("--out", type=Path, help="also write the Markdown table here")
    parser.add_argument("--plot", type=Path, help="also draw a bar chart here (PNG)")
    args = parser.parse_args(argv)
    try:
        summaries = find_summaries(args.paths)
    except (FileNotFoundError, ValueError) as err:
        print(f"torchrl_bail.report: {err}", file=sys.stderr)
        return 2
    if not summaries:
        print(f"torchrl_bail.report: no summary.json under {', '.join(map(str, args.paths))}", file=sys.stderr)
        return 1
    rows = aggregate(summaries)
    table = format_table(rows)
    print(table)
    if args.out:
        write_text_atomic(args.out, table + "\n")
    if args.plot:
        plot_rows(rows, args.plot)
    return 0


if __name__ == "__main__":
    sys.exit(main())

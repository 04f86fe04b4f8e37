"""Results a researcher can publish: ``python -m torchrl_bail.report multirun/ outputs/ --out results --plot``.

Finds every ``summary.json`` below the given directories and groups the runs by

* the **batch recipe**: its name and recipe hash (``metadata.json`` of the batch, or the ``-<hash>`` suffix of
  ``batch_path``), so two batches with one name but different recipes are never averaged together;
* the **algorithm**;
* every **override that separates runs**: the run's resolved ``config.yaml`` files are compared key by key and
  any key whose value differs between runs of one (batch, algorithm) cell is a separating key (an ablation such
  as ``algo.selection.by=return``), except seeds and keys that only change how a run is executed
  (:data:`~torchrl_bail.configuration.run_dirs.RUN_ONLY_KEYS`: ``progress``, ``logger.*``, ``device``, ``data_dir``,
  ``resume``...),
  ``hydra.*`` and ``env.*``/``batch.*``/``dataset`` (the batch identity already covers them); together
  :data:`NON_SEPARATING_KEYS`.

Per group it reports the number of distinct seeds, the mean and sample standard deviation (``ddof=1``) of
``final_return`` and ``best_return``, the interquartile mean (IQM) of ``final_return`` with a 95 % stratified
bootstrap confidence interval (rliable, Agarwal et al. 2021; numpy's stream seeded with ``--bootstrap-seed`` afresh
for each group, so a group's interval does not depend on the others; see :func:`numpy_seed`) and the mean normalized
score where ``summary.json`` has one (``final_return_normalized``). When some run's ``summary.json`` holds
``fqe_selected`` (written by ``python -m torchrl_bail.ope`` for a run with ``eval.snapshots``), every group also
gets ``fqe_selected_return``'s mean and standard deviation over its runs that have one (with their count): the
evaluation return of the policy snapshot FQE chose, what a user without the simulator would have deployed, beside
``final_return`` and ``best_return`` (which the simulator chose). Without such a run neither the column nor its table
appears.

``--out PREFIX`` writes ``PREFIX.md`` (batches as rows, a variant's non-default values in the row name,
algorithms as columns, the best mean per row in bold), ``PREFIX.csv`` and ``PREFIX.json`` (every group, with
its runs and the separating keys). ``--plot`` also draws learning curves averaged over seeds with 95 % bands
(``PREFIX_curves.png``) and rliable's aggregate-metrics and performance-profile figures (``PREFIX_aggregate.png``,
``PREFIX_profiles.png``). An unreadable or incomplete ``summary.json`` stops the report with one line naming the
file (exit 2).

The rliable package is an optional extra (``pip install "torchrl_bail[report]"``): it pulls pandas, arch,
statsmodels and seaborn, and arch 7 needs pandas < 3.

Examples:
    >>> runs = [Run(Path(f"r{s}"), {"algo": "bc", "seed": s, "final_return": r, "best_return": r + 10.0},
    ...             {}, ("hopper_ddpg05_b1", "abcd1234")) for s, r in [(1, 300.0), (2, 500.0), (3, 400.0)]]
    >>> (g,) = group_runs(runs)
    >>> g.label, g.seeds, stats(g.scores("final_return"))
    ('bc', 3, (400.0, 100.0))
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import statistics
import sys
from collections import Counter, defaultdict
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from torchrl_bail.configuration.algo_schemas import ALGO_SCHEMAS
from torchrl_bail.configuration.run_dirs import RUN_ONLY_KEYS
from torchrl_bail.core.io import write_json_atomic, write_text_atomic
from torchrl_bail.reports.plots import mean_curve, new_figure, read_eval_curve, save_figure
from torchrl_bail.training.resume import ADDED_KEYS, RENAMED_KEYS

__all__ = ["Run", "Group", "ReportError", "find_runs", "group_runs", "separating_keys", "stats", "iqm_interval",
           "summarise", "format_markdown", "fqe_selected_return", "numpy_seed", "main", "NON_SEPARATING_KEYS",
           "check_one_data_per_batch"]

#: the algorithms' order in tables and figures: their schemas' (the registry's)
ALGO_ORDER = list(ALGO_SCHEMAS)
#: keys every summary.json must have to enter the report
REQUIRED_KEYS = ("algo", "seed", "final_return", "best_return")
#: config keys (with everything under them) that never separate groups: the run-only keys the schema marks, the
#: seed, Hydra's node and the batch identity (``env``, ``batch``, ``dataset``: a run's batch already groups it)
NON_SEPARATING_KEYS = (*RUN_ONLY_KEYS, "seed", "hydra", "dataset", "env", "batch")
#: what a run's summary.json says of the data it trained on: every run of one batch (name and recipe hash) must agree
#: on all of them, or its scores do not compare (:func:`check_one_data_per_batch`)
DATA_KEYS = ("num_transitions", "num_episodes", "dataset_mean_episode_return", "dataset_max_episode_return")


class ReportError(ValueError):
    """A summary.json (or a directory given) cannot enter the report; the message names the file."""


@dataclass
class Run:
    """One finished run: its directory, ``summary.json``, flattened resolved config and batch identity."""

    run_dir: Path
    summary: dict
    config: dict
    batch: tuple[str, str | None]  # (name, recipe hash)

    @property
    def algo(self) -> str:
        return str(self.summary["algo"])


@dataclass
class Group:
    batch: tuple[str, str | None]
    algo: str
    variant: tuple[tuple[str, Any], ...]  # (key, value) of the separating keys, sorted
    label: str  # the algorithm, plus the variant's non-default values
    variant_label: str  # the non-default values alone ("" for the default configuration)
    runs: list[Run] = field(default_factory=list)

    @property
    def seeds(self) -> int:
        return len({r.summary["seed"] for r in self.runs})

    def scores(self, key: str) -> list[float]:
        return [float(r.summary[key]) for r in self.runs if r.summary.get(key) is not None]


# ---------------------------------------------------------------------------------------------------------------
# reading runs
# ---------------------------------------------------------------------------------------------------------------


def _flatten(obj: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(obj, dict):
        out: dict[str, Any] = {}
        for k, v in obj.items():
            out.update(_flatten(v, f"{prefix}{k}."))
        return out
    if isinstance(obj, list):
        obj = json.dumps(obj)  # hashable, and prints like the override that set it
    return {prefix[:-1]: obj}


def _read_config(run_dir: Path) -> dict[str, Any]:
    path = run_dir / "config.yaml"
    if not path.is_file():
        return {}
    from omegaconf import OmegaConf

    try:
        config = _flatten(OmegaConf.to_container(OmegaConf.load(path), resolve=False))
    except Exception as err:  # noqa: BLE001 - any parse error is reported with the file
        raise ReportError(f"{path}: unreadable config ({err})") from None
    for key, value in ADDED_KEYS.items():  # runs made before a key existed ran as its default
        config.setdefault(key, value)
    for old, new in RENAMED_KEYS.items():  # and read a renamed key under its new name
        if old in config:
            config[new] = config.pop(old)
    return config


def _batch_identity(summary: dict) -> tuple[str, str | None]:
    """(batch name, recipe hash): from ``batch_recipe_hash``, the batch's ``metadata.json`` or its directory."""
    name = str(summary.get("batch"))
    recipe = summary.get("batch_recipe_hash")
    path = summary.get("batch_path")
    if recipe is None and path:
        meta = Path(path) / "metadata.json"
        try:
            recipe = json.loads(meta.read_text()).get("recipe_hash")
        except (OSError, ValueError):
            stem = Path(path).name
            if "-" in stem and len(stem.rsplit("-", 1)[1]) == 8:
                recipe = stem.rsplit("-", 1)[1]
    return name, recipe


def _read_summary(path: Path) -> dict:
    try:
        summary = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ReportError(f"{path}: unreadable summary.json ({err})") from None
    if not isinstance(summary, dict):
        raise ReportError(f"{path}: summary.json is not a JSON object")
    missing = [k for k in REQUIRED_KEYS if k not in summary]
    if missing:
        raise ReportError(f"{path}: incomplete summary.json, missing {', '.join(missing)}")
    for key in ("final_return", "best_return"):
        if not isinstance(summary[key], (int, float)):
            raise ReportError(f"{path}: incomplete summary.json, {key} = {summary[key]!r} is not a number")
    selected = summary.get("fqe_selected")
    if selected is not None and not (isinstance(selected, dict) and isinstance(selected.get("online_return"),
                                                                                (int, float, type(None)))):
        raise ReportError(f"{path}: fqe_selected = {selected!r} has no online_return")
    return summary


def fqe_selected_return(summary: dict) -> float | None:
    """The evaluation return of the snapshot FQE selected (``summary["fqe_selected"]["online_return"]``), or
    ``None`` when the run has no selection."""
    selected = summary.get("fqe_selected")
    value = selected.get("online_return") if isinstance(selected, dict) else None
    return None if value is None else float(value)


def find_runs(paths: list[Path]) -> list[Run]:
    """Every run below ``paths`` (directories searched recursively, or ``summary.json`` files)."""
    runs = []
    for root in map(Path, paths):
        if not root.exists():
            raise ReportError(f"{root}: no such file or directory")
        files = [root] if root.is_file() else sorted(root.rglob("summary.json"))
        for f in files:
            summary = _read_summary(f)
            runs.append(Run(f.parent, summary, _read_config(f.parent), _batch_identity(summary)))
    check_one_data_per_batch(runs)
    return runs


def check_one_data_per_batch(runs: list[Run]) -> None:
    """Raises :class:`ReportError` when two runs of one batch (the same name and recipe hash) trained on different
    data, as their summaries' :data:`DATA_KEYS` tell: a batch made again on another kind of CPU or with other library
    versions follows the same recipe but holds other transitions, and runs on the two copies are not one cell. Runs
    whose summaries predate a key are not compared on it."""
    first: dict[tuple, Run] = {}
    for run in runs:
        seen = first.setdefault(run.batch, run)
        differ = [k for k in DATA_KEYS if k in run.summary and k in seen.summary and run.summary[k] != seen.summary[k]]
        if differ:
            said = "; ".join(f"{k} {seen.summary[k]!r} vs {run.summary[k]!r}" for k in differ)
            raise ReportError(f"{seen.run_dir} and {run.run_dir} name one batch ({run.batch[0]}, recipe "
                              f"{run.batch[1]}) but trained on different data ({said}): report the runs of each copy "
                              "of the batch apart")


# ---------------------------------------------------------------------------------------------------------------
# grouping
# ---------------------------------------------------------------------------------------------------------------


def _run_only(key: str) -> bool:
    return any(key == k or key.startswith(f"{k}.") for k in NON_SEPARATING_KEYS)


def separating_keys(runs: list[Run]) -> dict[str, list[str]]:
    """Per algorithm, the config keys whose values differ between runs of one (batch, algorithm) cell."""
    cells: dict[tuple, list[Run]] = defaultdict(list)
    for r in runs:
        cells[(r.batch, r.algo)].append(r)
    keys: dict[str, set[str]] = defaultdict(set)
    for (_, algo), cell in cells.items():
        keys[algo]  # every algorithm appears, with or without keys
        for key in set().union(*(r.config for r in cell)):
            if not _run_only(key) and len({repr(r.config.get(key)) for r in cell}) > 1:
                keys[algo].add(key)
    return {algo: sorted(k) for algo, k in keys.items()}


def _fmt_value(v: Any) -> str:
    return "null" if v is None else str(v).lower() if isinstance(v, bool) else str(v)


def group_runs(runs: list[Run]) -> list[Group]:
    """Groups by (batch recipe, algorithm, values of the separating keys), in the paper's order."""
    sep = separating_keys(runs)
    # the default of a separating key: its most common value among the algorithm's runs (ties: first in order)
    defaults = {}
    for algo, keys in sep.items():
        algo_runs = [r for r in runs if r.algo == algo]
        for key in keys:
            counts = Counter(repr(r.config.get(key)) for r in algo_runs)
            defaults[(algo, key)] = max(sorted(counts), key=lambda v: counts[v])
    groups: dict[tuple, Group] = {}
    for r in runs:
        variant = tuple((k, r.config.get(k)) for k in sep[r.algo])
        key = (r.batch, r.algo, tuple((k, repr(v)) for k, v in variant))
        if key not in groups:
            changed = [f"{k}={_fmt_value(v)}" for k, v in variant if repr(v) != defaults[(r.algo, k)]]
            variant_label = ", ".join(changed)
            label = f"{r.algo} [{variant_label}]" if changed else r.algo
            groups[key] = Group(r.batch, r.algo, variant, label, variant_label)
        groups[key].runs.append(r)
    order = {a: i for i, a in enumerate(ALGO_ORDER)}
    return sorted(groups.values(), key=lambda g: (g.batch[0], str(g.batch[1]), g.variant_label,
                                                  order.get(g.algo, len(order)), g.algo))


# ---------------------------------------------------------------------------------------------------------------
# statistics
# ---------------------------------------------------------------------------------------------------------------


def stats(scores: list[float]) -> tuple[float, float]:
    """Mean and sample standard deviation (``ddof=1``; NaN with a single score)."""
    if not scores:
        return math.nan, math.nan
    return float(statistics.fmean(scores)), float(statistics.stdev(scores)) if len(scores) > 1 else math.nan


def _rliable():
    try:
        from rliable import library, metrics
    except ImportError as err:
        raise ImportError(f"the report's IQM and bootstrap intervals need rliable ({err}); "
                          f"pip install \"torchrl_bail[report]\"") from None
    return library, metrics


@contextmanager
def numpy_seed(seed: int):
    """Seeds numpy's global random stream for the block and restores the previous state afterwards.

    rliable 1.2.0's ``StratifiedBootstrap`` resamples with ``np.random.choice`` (the global stream): its
    ``random_state`` argument reaches arch but not the resampling, so seeding that stream is what makes an
    interval reproducible.
    """
    import numpy as np

    state = np.random.get_state()
    np.random.seed(seed)
    try:
        yield
    finally:
        np.random.set_state(state)


def iqm_interval(scores: list[float], *, reps: int = 2_000, seed: int = 0) -> tuple[float, float, float]:
    """IQM of one group's per-seed scores and its 95 % stratified-bootstrap interval ``(iqm, low, high)``.

    The scores form rliable's ``(runs x 1 task)`` matrix; the bootstrap runs under :func:`numpy_seed` ``(seed)``.
    """
    import numpy as np

    library, metrics = _rliable()
    matrix = np.asarray(scores, dtype=float).reshape(-1, 1)
    with numpy_seed(seed):
        point, interval = library.get_interval_estimates(
            {"g": matrix}, lambda x: np.array([metrics.aggregate_iqm(x)]), reps=reps)
    return float(point["g"][0]), float(interval["g"][0, 0]), float(interval["g"][1, 0])


def summarise(groups: list[Group], *, reps: int = 2_000, seed: int = 0) -> list[dict]:
    """One row per group: seeds, mean/std of final and best return, IQM with its CI, normalised score."""
    rows = []
    with_selection = any(fqe_selected_return(r.summary) is not None for g in groups for r in g.runs)
    for g in groups:
        final, best = g.scores("final_return"), g.scores("best_return")
        iqm, low, high = iqm_interval(final, reps=reps, seed=seed)
        normalized = g.scores("final_return_normalized")
        dataset = g.scores("dataset_mean_episode_return")
        rows.append({
            "batch": g.batch[0], "recipe_hash": g.batch[1], "algo": g.algo, "label": g.label,
            "variant": g.variant_label, "overrides": {k: v for k, v in g.variant},
            "seeds": g.seeds, "runs": len(g.runs),
            "final_return_mean": stats(final)[0], "final_return_std": stats(final)[1],
            "best_return_mean": stats(best)[0], "best_return_std": stats(best)[1],
            "final_return_iqm": iqm, "final_return_iqm_ci_low": low, "final_return_iqm_ci_high": high,
            "final_return_normalized_mean": stats(normalized)[0] if normalized else None,
            "final_return_normalized_std": stats(normalized)[1] if normalized else None,
            "dataset_mean_episode_return": stats(dataset)[0] if dataset else None,
            "run_dirs": [str(r.run_dir) for r in g.runs],
        })
        if with_selection:  # a column only when some run has a selection
            selected = [v for v in (fqe_selected_return(r.summary) for r in g.runs) if v is not None]
            rows[-1].update({"fqe_selected_return_mean": stats(selected)[0] if selected else None,
                             "fqe_selected_return_std": stats(selected)[1] if selected else None,
                             "fqe_selected_runs": len(selected)})
    return rows


# ---------------------------------------------------------------------------------------------------------------
# output
# ---------------------------------------------------------------------------------------------------------------


def _batch_name(row: dict, names: dict[str, set]) -> str:
    """The batch's name, with its recipe hash when two recipes share that name."""
    return f"{row['batch']} ({row['recipe_hash']})" if len(names[row["batch"]]) > 1 else row["batch"]


def _cell(row: dict) -> str:
    std = "" if math.isnan(row["final_return_std"]) else f" ± {row['final_return_std']:.1f}"
    return f"{row['final_return_mean']:.1f}{std}"


def _fqe_cell(row: dict) -> str:
    if row["fqe_selected_return_mean"] is None:
        return "—"
    std = "" if math.isnan(row["fqe_selected_return_std"]) else f" ± {row['fqe_selected_return_std']:.1f}"
    return f"{row['fqe_selected_return_mean']:.1f}{std} ({row['fqe_selected_runs']})"


def _iqm_cell(row: dict) -> str:
    low, high = row["final_return_iqm_ci_low"], row["final_return_iqm_ci_high"]
    return f"{row['final_return_iqm']:.1f} [{low:.1f}, {high:.1f}]"


def _table(table: dict[str, dict[str, dict]], algos: list[str], cell, key: str) -> list[str]:
    """Rows of ``table`` (name -> algo -> row), the batch's mean episode return, one column per algorithm; the
    best ``key`` per row in bold (when there is more than one column)."""
    lines = ["| batch | data | " + " | ".join(algos) + " |", "|---|---|" + "---|" * len(algos)]
    for name, cells in table.items():
        best = max((c[key] for c in cells.values() if c[key] is not None), default=None)
        data = next((c["dataset_mean_episode_return"] for c in cells.values()
                     if c.get("dataset_mean_episode_return") is not None), None)
        out = [""] * len(algos)
        for i, a in enumerate(algos):
            c = cells.get(a)
            if c is not None:
                out[i] = f"**{cell(c)}**" if c[key] == best and best is not None and len(algos) > 1 else cell(c)
        lines.append(f"| {name} | {'' if data is None else f'{data:.1f}'} | " + " | ".join(out) + " |")
    return lines


def format_markdown(rows: list[dict], separating: dict[str, list[str]] | None = None) -> str:
    """Batches (and variants) as rows, algorithms as columns: ``final_return`` mean ± std, then its IQM with the
    95 % bootstrap CI; the best per row in bold; ``data`` is the batch's mean episode return."""
    order = {a: i for i, a in enumerate(ALGO_ORDER)}
    algos = sorted({r["algo"] for r in rows}, key=lambda a: (order.get(a, len(order)), a))
    names: dict[str, set] = defaultdict(set)
    for r in rows:
        names[r["batch"]].add(r["recipe_hash"])
    table: dict[str, dict[str, dict]] = defaultdict(dict)
    for r in rows:
        name = _batch_name(r, names) + (f" [{r['variant']}]" if r["variant"] else "")
        table[name][r["algo"]] = r
    seeds = sorted({r["seeds"] for r in rows})
    lines = _table(table, algos, _cell, "final_return_mean")
    lines += ["", f"final_return: mean ± sample std (ddof=1) over {'/'.join(map(str, seeds))} seeds; "
                  f"best mean per row in bold; data: the batch's mean episode return."]
    used = {a: k for a, k in (separating or {}).items() if k}
    if used:
        lines.append("Groups separated by overrides: " + "; ".join(f"{a}: {', '.join(k)}" for a, k in used.items()))
    lines += ["", *_table(table, algos, _iqm_cell, "final_return_iqm"), "",
              "final_return: interquartile mean over seeds [95 % stratified-bootstrap confidence interval] (rliable); "
              "best IQM per row in bold."]
    if any(r.get("fqe_selected_return_mean") is not None for r in rows):
        lines += ["", *_table(table, algos, _fqe_cell, "fqe_selected_return_mean"), "",
                  "fqe_selected_return: mean ± sample std of the evaluation return of the policy snapshot FQE chose "
                  "(python -m torchrl_bail.ope), over the runs (in brackets) that have one; best mean per row in "
                  "bold."]
    return "\n".join(lines)


CSV_FIELDS = ["batch", "recipe_hash", "algo", "label", "variant", "seeds", "runs", "final_return_mean",
              "final_return_std", "best_return_mean", "best_return_std", "final_return_iqm",
              "final_return_iqm_ci_low", "final_return_iqm_ci_high", "final_return_normalized_mean",
              "final_return_normalized_std", "dataset_mean_episode_return"]


#: the CSV's columns after :data:`CSV_FIELDS` when some run has an FQE selection
FQE_CSV_FIELDS = ["fqe_selected_return_mean", "fqe_selected_return_std", "fqe_selected_runs"]


def format_csv(rows: list[dict]) -> str:
    buf = io.StringIO()
    fields = CSV_FIELDS + (FQE_CSV_FIELDS if any("fqe_selected_return_mean" in r for r in rows) else [])
    writer = csv.DictWriter(buf, fieldnames=fields, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return buf.getvalue()


def _json_safe(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_json_safe(v) for v in value]
    return value


# ---------------------------------------------------------------------------------------------------------------
# figures (--plot)
# ---------------------------------------------------------------------------------------------------------------


#: panels per row of the learning-curve figure (one panel per batch)
CURVE_COLUMNS = 3
#: a panel whose longest curve ends at least this many times later than its shortest gets a log x-axis, so that a
#: short schedule (BCQ's 10 epochs beside BC's 100 at the paper's scale) is not squeezed against the left edge
LOG_EPOCH_AXIS_SPAN = 4.0


def _plot_curves(groups, path: Path) -> Path | None:
    batches = sorted({g.batch for g in groups}, key=str)
    panels = []
    for batch in batches:
        lines = []
        for g in (g for g in groups if g.batch == batch):
            curves = [c for c in (read_eval_curve(r.run_dir) for r in g.runs) if c is not None and len(c[0])]
            if curves:
                lines.append((g.label, len(curves), *mean_curve(curves)))
        if lines:
            panels.append((batch, lines))
    if not panels:
        return None
    cols = min(len(panels), CURVE_COLUMNS)
    rows = math.ceil(len(panels) / cols)
    fig = new_figure(figsize=(5.0 * cols, 4.8 * rows), layout="constrained")
    axes = fig.subplots(rows, cols, squeeze=False).ravel()
    for ax in axes[len(panels):]:
        ax.set_visible(False)
    for ax, (batch, lines) in zip(axes, panels, strict=False):
        for label, n, x, mean, half in lines:
            ax.plot(x, mean, label=f"{label} ({n} seed{'s' if n != 1 else ''})")
            ax.fill_between(x, mean - half, mean + half, alpha=0.2)
        ends = [x[-1] for _, _, x, _, _ in lines]
        log_axis = min(x[0] for _, _, x, _, _ in lines) > 0 and max(ends) >= LOG_EPOCH_AXIS_SPAN * min(ends)
        if log_axis:
            ax.set_xscale("log")
        ax.set_title(batch[0])
        ax.set_xlabel("epoch (10^6 samples)" + (", log scale" if log_axis else ""))
        ax.set_ylabel("evaluation return (mean over seeds)")
        ax.grid(alpha=0.3)
        # below the axes, where it hides no curve
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2, fontsize="small")
    return save_figure(fig, path)


def _normalized_scores(groups):
    """``label -> (runs x batches)`` matrix, the score's name and its reference level (the score that means "as good
    as the reference": the optimality gap's threshold).

    The D4RL/Minari normalised score when every run has one (0 random, 100 expert: reference level 100), otherwise
    ``final_return`` divided by the batch's mean episode return (1.0 = as good as the data on average: level 1.0).
    Each batch contributes its first ``n`` seeds in seed order (whatever their scores), ``n`` the fewest seeds any of
    the label's batches has (rliable needs a full matrix).
    """
    import numpy as np

    runs = [r for g in groups for r in g.runs]
    if all(r.summary.get("final_return_normalized") is not None for r in runs):
        name, level, score = "normalised score", 100.0, lambda s: float(s["final_return_normalized"])
    else:
        name, level = "final return / batch mean episode return", 1.0
        score = lambda s: float(s["final_return"]) / float(s["dataset_mean_episode_return"])  # noqa: E731
    by_label: dict[str, list] = {}
    for g in groups:
        if any(not r.summary.get("dataset_mean_episode_return") for r in g.runs) and name != "normalised score":
            continue
        in_seed_order = sorted(g.runs, key=lambda r: (int(r.summary.get("seed", 0)), str(r.run_dir)))
        by_label.setdefault(g.label, []).append([score(r.summary) for r in in_seed_order])
    matrices = {}
    for label, columns in by_label.items():
        n = min(len(c) for c in columns)
        matrices[label] = np.array([c[:n] for c in columns]).T
    return matrices, name, level


def aggregate_estimates(matrices, level: float, *, reps: int = 2_000, seed: int = 0):
    """rliable's median, IQM, mean and optimality gap of each label's ``(runs x batches)`` matrix with their
    stratified-bootstrap intervals: ``(point, interval, names)``. The optimality gap is the mean shortfall below
    ``level``, the score's reference level (:func:`_normalized_scores`: 100 on the D4RL 0-100 scale, 1.0 for the
    batch-mean ratio); a threshold of 1.0 on the 0-100 scale would show 0 for every algorithm."""
    import numpy as np

    library, metrics = _rliable()

    def aggregates(x):
        return np.array([metrics.aggregate_median(x), metrics.aggregate_iqm(x), metrics.aggregate_mean(x),
                         metrics.aggregate_optimality_gap(x, level)])

    with numpy_seed(seed):
        point, interval = library.get_interval_estimates(matrices, aggregates, reps=reps)
    return point, interval, ["Median", "IQM", "Mean", f"Optimality gap (below {level:g})"]


def plot_report(groups, prefix: str, *, reps: int = 2_000, seed: int = 0) -> list[Path]:
    """The report's figures: ``PREFIX_curves.png``, ``PREFIX_aggregate.png``, ``PREFIX_profiles.png``."""
    import numpy as np

    written = []
    curves = _plot_curves(groups, Path(f"{prefix}_curves.png"))
    if curves is not None:
        written.append(curves)
    matrices, name, level = _normalized_scores(groups)
    if not matrices:
        return written
    library, _ = _rliable()
    from rliable import plot_utils

    point, interval, panels = aggregate_estimates(matrices, level, reps=reps, seed=seed)
    fig, _ = plot_utils.plot_interval_estimates(point, interval, panels, algorithms=list(matrices), xlabel=name,
                                                xlabel_y_coordinate=-0.35)
    written.append(save_figure(fig, Path(f"{prefix}_aggregate.png")))
    all_scores = np.concatenate([m.ravel() for m in matrices.values()])
    taus = np.linspace(min(0.0, all_scores.min()), max(1.0, all_scores.max()), 81)
    with numpy_seed(seed):
        profiles, profile_cis = library.create_performance_profile(matrices, taus, reps=min(reps, 2000))
    fig = new_figure(figsize=(6.4, 4.0))
    ax = fig.subplots()
    plot_utils.plot_performance_profiles(profiles, taus, performance_profile_cis=profile_cis, ax=ax,
                                         xlabel=f"{name} (tau)")
    ax.legend(loc="best", fontsize="small")
    written.append(save_figure(fig, Path(f"{prefix}_profiles.png")))
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m torchrl_bail.report", description=__doc__.split("\n\n")[0])
    parser.add_argument("paths", nargs="+", type=Path, help="run or sweep directories (searched recursively)")
    parser.add_argument("--out", type=Path, help="write PREFIX.md, PREFIX.csv and PREFIX.json")
    parser.add_argument("--plot", action="store_true",
                        help="also draw PREFIX_curves.png, PREFIX_aggregate.png and PREFIX_profiles.png")
    parser.add_argument("--reps", type=int, default=2_000,
                        help="bootstrap replications (default 2000; rliable suggests 50000 for final figures: minutes)")
    parser.add_argument("--bootstrap-seed", type=int, default=0, help="seed of every group's bootstrap")
    args = parser.parse_args(argv)
    if args.plot and args.out is None:
        parser.error("--plot needs --out PREFIX (the figures are written beside the tables)")
    try:
        runs = find_runs(args.paths)
    except ReportError as err:
        print(f"torchrl_bail.report: {err}", file=sys.stderr)
        return 2
    if not runs:
        print(f"torchrl_bail.report: no summary.json under {', '.join(map(str, args.paths))}", file=sys.stderr)
        return 1
    groups = group_runs(runs)
    separating = separating_keys(runs)
    try:
        rows = summarise(groups, reps=args.reps, seed=args.bootstrap_seed)
    except ImportError as err:
        print(f"torchrl_bail.report: {err}", file=sys.stderr)
        return 2
    table = format_markdown(rows, separating)
    print(table)
    if args.out:
        prefix = str(args.out)
        write_text_atomic(prefix + ".md", table + "\n")
        write_text_atomic(prefix + ".csv", format_csv(rows))
        write_json_atomic(prefix + ".json", _json_safe({"separating_keys": separating, "groups": rows}))
        if args.plot:
            for path in plot_report(groups, prefix, reps=args.reps, seed=args.bootstrap_seed):
                print(f"wrote {path}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())

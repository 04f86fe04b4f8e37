"""What the studies' reports share: reading a batch's cells from the kept runs, a verdict per claim of the paper,
the aggregates over batches with their intervals, the learning-curve figure of a batch, and the Markdown cells.

A **cell** is one algorithm on one batch: the seeds the study schedules (its jobs) and the runs kept of them in its
results directory (:mod:`torchrl_bail.study.gather`), summarised as :func:`torchrl_bail.report.summarise` does (mean,
sample std, IQM with its 95 % stratified-bootstrap interval) with its per-seed final returns, also on the batch's
min-max scale (:func:`normalised_return`) where the batch's metadata is kept (:func:`batch_rows`). A **claim** of the
paper (arXiv:1910.12179: Table 1, supp. Table 2) compares two cells' IQM intervals (:func:`claim_verdict`), pending
below :data:`MIN_SEEDS_FOR_VERDICT` seeds a side. Over several batches, an algorithm's IQM and a pair's probability
of improvement get their intervals from a hierarchical bootstrap, batches then seeds (:func:`hierarchical_interval`).
Every interval is seeded (:data:`BOOTSTRAP_REPS`, :data:`BOOTSTRAP_SEED`): a report rebuilt from the same kept runs
is the same bytes.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from torchrl_bail.report import Group, find_runs, numpy_seed, summarise
from torchrl_bail.reports.plots import new_figure, read_eval_curve, read_scalar_csv, save_figure
from torchrl_bail.study.declaration import StudyJob
from torchrl_bail.study.gather import batch_label, run_dir_of

#: the checkout this package runs from (``src/torchrl_bail/study`` three folders down): the reports show the paths
#: inside it relative to it (:func:`shown_path`), so that the kept reports hold no machine's paths
REPOSITORY = Path(__file__).resolve().parents[3]

#: published figures the paper-scale cell is read beside: raw returns of gym's -v2 Hopper, where these runs use
#: Gymnasium's -v5 (its simulator and rewards changed), so a level is a ballpark and the ordering is what compares
PAPER_ANCHORS = {
    "bail": ("2054 ± 158", "BAIL's authors, Hopper DDPG σ = 0.5 B1, 10^6 transitions (arXiv:1910.12179, Table 1)"),
    "bcq": ("curve only", "BCQ paper Fig. 2a, Hopper final buffer (arXiv:1812.02900): no table, so no number is "
                          "quoted; supp. C.2 of the BAIL paper says its BCQ runs agree with that figure"),
}

#: the paper's claims on the headline cell (Hopper DDPG σ = 0.5 B1), each a comparison of two groups' IQM
#: intervals: (claim, a, b, kind); kind "above": a's interval lies above b's; "similar": the two intervals overlap
#: (no difference shown)
PAPER_CLAIMS = [
    ("BAIL ≫ BC", "bail", "bc", "above"),
    ("BAIL above BCQ (BCQ at 10^5 of the paper's 10^6 updates)", "bail", "bcq", "above"),
    ("BAIL above BEAR (BEAR at 10^5 of the paper's 10^6 updates)", "bail", "bear", "above"),
    ("Progressive BAIL ≈ BAIL", "pbail", "bail", "similar"),
    ("MARWIL above BC", "marwil", "bc", "above"),
    ("MARWIL with V fitted first above BC", "marwil (value_warmup_updates=1000)", "bc", "above"),
]

#: fewer seeds than this and a claim's verdict is "pending"
MIN_SEEDS_FOR_VERDICT = 3

#: bootstrap replications and numpy seed of every interval of the studies' reports (torchrl_bail.report's defaults)
BOOTSTRAP_REPS, BOOTSTRAP_SEED = 2_000, 0

#: how a final return is put on one scale across batches (:func:`normalised_return`)
NORMALISATION = ("min-max by the batch's own episodes: (final return - the batch's worst episode return) / (its "
                 "best - its worst), from the batch's metadata (episode_return_min, episode_return_max); 0 = the "
                 "batch's worst episode, 1 = its best")

#: the learning-curve figures' window: each seed's evaluations averaged per this many updates (the actor-critics'
#: evaluation interval at the paper schedule, so every algorithm lands on one grid)
CURVE_WINDOW_UPDATES = 5000

#: how every aggregate over batches gets its interval (:func:`hierarchical_interval`), as the reports say it
HIERARCHICAL_BOOTSTRAP = ("a hierarchical bootstrap: each replication draws the batches with replacement, then the "
                          "seeds of each drawn batch with replacement (each algorithm's on its own), so the interval "
                          "covers which batches were drawn as well as which seeds")


def interval_order(a: dict | None, b: dict | None) -> str:
    """Where group ``a`` lies against group ``b`` from their report rows (IQM and its 95 % bootstrap interval):
    "above" or "below" where the intervals are disjoint, "no difference shown" where they overlap, "pending" while
    either side has fewer than :data:`MIN_SEEDS_FOR_VERDICT` seeds. A row marked ``"reference": True`` is a fixed
    figure, not a group of runs (a behaviour policy's return: :func:`reference_row`), and needs no seeds."""
    seeds = [0 if row is None else row["seeds"] for row in (a, b) if row is None or not row.get("reference")]
    if seeds and min(seeds) < MIN_SEEDS_FOR_VERDICT:
        return f"pending (seeds so far: {' and '.join(map(str, seeds))}; {MIN_SEEDS_FOR_VERDICT} each needed)"
    lo_a, hi_a = a["final_return_iqm_ci_low"], a["final_return_iqm_ci_high"]
    lo_b, hi_b = b["final_return_iqm_ci_low"], b["final_return_iqm_ci_high"]
    if lo_a > hi_b:
        return "above: the IQM intervals are disjoint"
    if lo_b > hi_a:
        return "below: the IQM intervals are disjoint"
    return "no difference shown: the IQM intervals overlap"


def reference_row(value: float) -> dict:
    """A fixed figure (a behaviour policy's measured return) as a report row that :func:`interval_order` reads: its
    interval is the one point, and it needs no seeds."""
    return {"reference": True, "seeds": None, "final_return_iqm": float(value),
            "final_return_iqm_ci_low": float(value), "final_return_iqm_ci_high": float(value)}


def claim_verdict(a: dict | None, b: dict | None, kind: str) -> str:
    """The verdict on one claim from the two groups' report rows (:func:`interval_order`): an "above" claim holds
    where ``a``'s interval lies wholly above ``b``'s, a "below" claim where it lies wholly below, an "≈" claim
    ("similar") where the intervals overlap."""
    order = interval_order(a, b)
    if order.startswith("pending"):
        return order
    holds = order.startswith(kind) if kind in ("above", "below") else order.startswith("no difference")
    return f"{'holds' if holds else 'does not hold'} ({order})"


def normalised_return(final_return: float, metadata: dict) -> float:
    """A final return on its batch's min-max scale (:data:`NORMALISATION`): 0 = the batch's worst episode, 1 = its
    best. Min-max by the batch itself, not by reference scores: every batch's metadata has both bounds (the
    random-policy scores of ``results/reference_scores.json`` have no expert end yet), the four batches differ in
    env and behaviour quality, and the question BAIL asks is how much of the batch's best behaviour a policy
    recovers. The map is increasing, so within a batch it changes no ordering; it sets the weight of each batch in
    the aggregate."""
    low, high = float(metadata["episode_return_min"]), float(metadata["episode_return_max"])
    return (float(final_return) - low) / (high - low)


def kept_metadata(results: Path, label: str, recipe_hashes: set[str]) -> tuple[Path | None, dict | None]:
    """The batch's ``metadata.json`` kept in ``results/batches`` (``<label>-<recipe hash>.metadata.json``, copied there
    by :func:`~torchrl_bail.study.gather.keep_batch`): the one whose recipe hash the runs name, or the only one."""
    files = sorted((results / "batches").glob(f"{label}-*.metadata.json"))
    if recipe_hashes:
        files = [f for f in files if f.name[len(label) + 1:].split(".")[0] in recipe_hashes]
    if len(files) != 1:
        return None, None
    return files[0], json.loads(files[0].read_text())


def _train_cell(job: StudyJob) -> tuple[str, str, int] | None:
    """``(batch label, algorithm, seed)`` of a training job without a variant tag, else ``None``."""
    if job.module != "torchrl_bail.train" or len(job.name.split("/")) != 3:
        return None
    named = job.overrides
    return batch_label(job), named["algo"], int(named["seed"])


def batch_cells(results: Path, jobs: list[StudyJob], label: str, algos: tuple[str, ...]) -> dict[str, dict]:
    """``algo -> {"scheduled": seeds the study runs, "runs": kept run directories}`` of batch ``label`` (``jobs``:
    the study's, its kept runs in ``results/runs``), for the columns ``algos``."""
    cells: dict[str, dict] = {}
    for job in jobs:
        cell = _train_cell(job)
        if cell is None or cell[0] != label or cell[1] not in algos:
            continue
        entry = cells.setdefault(cell[1], {"scheduled": 0, "runs": []})
        entry["scheduled"] += 1
        run = run_dir_of(job, results / "runs")
        if run is not None and (run / "summary.json").is_file():
            entry["runs"].append(run)
    return cells


def batch_rows(root: Path, jobs: list[StudyJob], label: str, algos: tuple[str, ...]
               ) -> tuple[dict[str, dict], Path | None, dict | None, dict[str, dict]]:
    """Batch ``label`` of a study (``jobs``, its kept results in ``root``) as a report row reads it: its cells
    (:func:`batch_cells` over ``algos``), its kept metadata (:func:`kept_metadata`, the one whose recipe hash the
    runs name) with that file's path, and per algorithm its :func:`_cell_row` with the seeds scheduled (``{"seeds":
    0}`` and the seeds scheduled while no run is kept)."""
    cells = batch_cells(root, jobs, label, algos)
    hashes = set()
    for cell in cells.values():
        for run in cell["runs"]:
            path = json.loads((run / "summary.json").read_text()).get("batch_path") or ""
            if "-" in Path(path).name:
                hashes.add(Path(path).name.rsplit("-", 1)[1])
    meta_path, metadata = kept_metadata(root, label, hashes)
    rows = {}
    for algo, cell in cells.items():
        row = _cell_row(label, algo, cell["runs"], metadata) if cell["runs"] else {"seeds": 0}
        rows[algo] = {"scheduled": cell["scheduled"], **row}
    return cells, meta_path, metadata, rows


def shown_path(path: Path) -> str:
    """A path relative to the repository where it lies inside it (the kept reports hold no machine's paths)."""
    path = Path(path).resolve()
    return str(path.relative_to(REPOSITORY)) if path.is_relative_to(REPOSITORY) else str(path)


def _cell_row(label: str, algo: str, runs: list[Path], metadata: dict | None) -> dict:
    """One algorithm's row on one batch: :func:`torchrl_bail.report.summarise` over its kept runs (mean, sample std,
    IQM with its 95 % stratified-bootstrap interval), its per-seed final returns in seed order and, where the
    batch's metadata is kept, their normalised values."""
    found = sorted(find_runs(runs), key=lambda r: int(r.summary["seed"]))
    row = summarise([Group((label, None), algo, (), algo, "", found)], reps=BOOTSTRAP_REPS,
                    seed=BOOTSTRAP_SEED)[0]
    row = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in row.items()
           if k not in ("label", "variant", "overrides", "recipe_hash", "batch")}
    row["run_dirs"] = [shown_path(r.run_dir) for r in found]
    row["seed_ids"] = [int(r.summary["seed"]) for r in found]
    row["per_seed"] = [float(r.summary["final_return"]) for r in found]
    row["per_seed_normalised"] = (None if metadata is None else
                                  [normalised_return(x, metadata) for x in row["per_seed"]])
    return row


def _windowed_curve(run: Path):
    """``(window ends, mean evaluation return per window)`` of a kept run, windows of :data:`CURVE_WINDOW_UPDATES`
    updates (the trainer logs each evaluation at its update count: the step of ``eval/return.csv``); ``None``
    without CSV evaluation logs."""
    if read_eval_curve(run) is None:
        return None
    returns = read_scalar_csv(run / "logs" / "scalars" / "eval" / "return.csv")
    windows: dict[int, list[float]] = {}
    for step, value in returns.items():
        windows.setdefault(-(-step // CURVE_WINDOW_UPDATES), []).append(value)
    ends = sorted(windows)
    return np.array(ends) * CURVE_WINDOW_UPDATES, np.array([np.mean(windows[w]) for w in ends])


def plot_batch_curves(label: str, cells: dict[str, dict], metadata: dict | None, path: Path,
                      algos: tuple[str, ...]) -> Path | None:
    """``curves_<batch>.png``: every algorithm's evaluation return against updates on a linear axis (every schedule
    of the study ends between 5 x 10^4 and 1.25 x 10^5 updates, where its epochs of 10^6 samples run from 10 to 100),
    each seed averaged per :data:`CURVE_WINDOW_UPDATES` updates; the mean over seeds as a line, the lowest to the
    highest seed as a band; the batch's mean episode return dashed. ``algos``: the algorithms, in the order that
    gives each its colour."""
    lines = []
    for i, algo in enumerate(algos):
        runs = cells.get(algo, {}).get("runs", [])
        curves = [c for c in map(_windowed_curve, runs) if c is not None and len(c[0])]
        if not curves:
            continue
        n = min(len(x) for x, _ in curves)
        ys = np.stack([y[:n] for _, y in curves])
        epochs = max(read_eval_curve(r)[0][-1] for r in runs if read_eval_curve(r) is not None)
        lines.append((algo, f"C{i}", len(curves), f"{epochs:g}", curves[0][0][:n] / 1000, ys))
    if not lines:
        return None
    fig = new_figure(figsize=(8.0, 4.8), layout="constrained")
    ax = fig.subplots()
    for algo, color, n, epochs, x, ys in lines:
        ax.plot(x, ys.mean(0), color=color, linewidth=1.8,
                label=f"{algo} ({n} seed{'s' if n != 1 else ''}, {epochs} epochs)")
        ax.fill_between(x, ys.min(0), ys.max(0), color=color, alpha=0.12, linewidth=0)
    if metadata is not None:
        ax.axhline(metadata["episode_return_mean"], color="gray", linestyle="--", label="batch mean episode return")
    ax.set_title(f"{label}: evaluation return, mean over seeds (band: lowest to highest seed)")
    ax.set_xlabel(f"updates (thousands; each seed's evaluations averaged per {CURVE_WINDOW_UPDATES} updates)")
    ax.set_ylabel("evaluation return")
    ax.set_xlim(left=0)
    ax.grid(alpha=0.3)
    ax.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize="small")
    return save_figure(fig, path)


def _seeded_interval(scores, func) -> tuple[float, float, float]:
    """``(point, low, high)`` of rliable's stratified bootstrap over ``scores`` (a runs x batches matrix, or a pair
    of them), under the report's seeded numpy stream (:func:`torchrl_bail.report.numpy_seed`): seeds resampled within
    each batch, the batches themselves fixed. Kept beside each aggregate as ``seeds_only`` to show what the batches
    add: where every batch is perfectly separated it is a single point."""
    from rliable import library  # an optional extra (torchrl_bail[report])

    with numpy_seed(BOOTSTRAP_SEED):
        point, interval = library.get_interval_estimates({"x": scores}, func, reps=BOOTSTRAP_REPS)
    return float(np.ravel(point["x"])[0]), float(np.ravel(interval["x"][0])[0]), float(np.ravel(interval["x"][1])[0])


def hierarchical_interval(matrices: list[np.ndarray], func, reps: int | None = None,
                          seed: int | None = None) -> tuple[float, float, float]:
    """``(point, low, high)`` of ``func(*matrices)`` (each a runs x batches matrix over the same batches, in the same
    column order; the runs may differ between matrices) with its 95 % percentile interval from
    :data:`HIERARCHICAL_BOOTSTRAP`: ``reps`` replications (default :data:`BOOTSTRAP_REPS`) of a numpy generator
    seeded with ``seed`` (default :data:`BOOTSTRAP_SEED`), so a rerun gives the same numbers. Each replication
    draws the batch columns with replacement, one draw shared by every matrix (a comparison stays within a batch),
    then resamples each drawn column's rows with replacement, for each matrix apart (a batch drawn twice gets two
    independent draws of its seeds). With one batch it is the bootstrap over seeds alone."""
    reps = BOOTSTRAP_REPS if reps is None else reps
    rng = np.random.default_rng(BOOTSTRAP_SEED if seed is None else seed)
    matrices = [np.asarray(m, dtype=float) for m in matrices]
    n_batches = matrices[0].shape[1]
    if any(m.shape[1] != n_batches for m in matrices):
        raise ValueError(f"every matrix needs the same batches (columns): {[m.shape for m in matrices]}")
    columns = np.arange(n_batches)
    stats = np.empty(reps)
    for i in range(reps):
        drawn = rng.integers(0, n_batches, n_batches)
        stats[i] = float(np.ravel(func(*(m[:, drawn][rng.integers(0, m.shape[0], (m.shape[0], n_batches)), columns]
                                         for m in matrices)))[0])
    low, high = np.percentile(stats, [2.5, 97.5])
    return float(np.ravel(func(*matrices))[0]), float(low), float(high)


def _matrix(batches: list[dict], algo: str, entered: list[str], key: str = "per_seed_normalised") -> np.ndarray:
    """``runs x batches`` of ``algo``'s final returns (``key``: normalised, or ``per_seed`` for the raw ones) on the
    batches ``entered``: each batch's first ``n`` seeds in seed order, ``n`` the fewest seeds any of them has (rliable
    needs a full matrix)."""
    columns = [b["cells"][algo][key] for b in batches if b["batch"] in entered]
    n = min(len(c) for c in columns)
    return np.array([c[:n] for c in columns]).T


def _against(row: dict, side: str) -> str:
    """The batches that go the other way of an across-batch reading (their own probability of improvement on
    ``side`` of 0.5), as a clause to append to it; "" when none does."""
    against = [batch for batch, p in row["per_batch"].items() if (p < 0.5 if side == "below" else p > 0.5)]
    return f", though {side} 0.5 on {', '.join(against)}" if against else ""


def _ready(batch: dict, algo: str, normalised: bool = True) -> bool:
    """Whether ``algo`` enters an aggregate on ``batch``: :data:`MIN_SEEDS_FOR_VERDICT` seeds there and, on the
    normalised scale, the batch's metadata kept."""
    cell = batch["cells"].get(algo)
    return ((batch["metadata"] is not None or not normalised) and cell is not None
            and cell.get("seeds", 0) >= MIN_SEEDS_FOR_VERDICT)


def aggregate_iqm(batches: list[dict], algo: str) -> dict | None:
    """``algo``'s IQM of normalised final returns over the batches where it has :data:`MIN_SEEDS_FOR_VERDICT` seeds,
    with its :func:`hierarchical_interval` (and, as ``seeds_only``, the interval over seeds alone); ``None`` where
    no batch is entered."""
    from rliable import metrics

    entered = [b["batch"] for b in batches if _ready(b, algo)]
    if not entered:
        return None
    m = _matrix(batches, algo, entered)
    point, low, high = hierarchical_interval([m], metrics.aggregate_iqm)
    seeds_only = _seeded_interval(m, lambda x: np.array([metrics.aggregate_iqm(x)]))[1:]
    return {"batches": entered, "n_batches": len(entered), "seeds_per_batch": int(m.shape[0]), "iqm": point,
            "ci_low": low, "ci_high": high, "seeds_only": list(seeds_only)}


def improvement(batches: list[dict], a: str, b: str, normalised: bool = True) -> dict:
    """P(``a`` > ``b``) (rliable's probability of improvement: a run of ``a`` ends above a run of ``b`` on the same
    batch, averaged over batches) over the batches where both have :data:`MIN_SEEDS_FOR_VERDICT` seeds, with its
    :func:`hierarchical_interval` (``seeds_only``: the interval over seeds alone) and each batch's own value
    (``per_batch``), and the reading: pending until every batch is entered, then above or below 0.5 where the whole
    interval is, naming the batches that go the other way. ``normalised``: read the normalised final returns (the
    same ordering within a batch; a batch without metadata enters nothing) or the raw ones."""
    from rliable import metrics

    key = "per_seed_normalised" if normalised else "per_seed"
    entered = [x["batch"] for x in batches if _ready(x, a, normalised) and _ready(x, b, normalised)]
    row = {"a": a, "b": b, "batches": entered, "n_batches": len(entered), "p": None, "ci_low": None,
           "ci_high": None, "seeds_only": None, "seeds": None, "per_batch": {}}
    if entered:
        x, y = _matrix(batches, a, entered, key), _matrix(batches, b, entered, key)
        row["p"], row["ci_low"], row["ci_high"] = hierarchical_interval([x, y], metrics.probability_of_improvement)
        row["seeds_only"] = list(_seeded_interval([x, y], metrics.probability_of_improvement)[1:])
        row["seeds"] = [int(x.shape[0]), int(y.shape[0])]
        row["per_batch"] = {batch: float(metrics.probability_of_improvement(x[:, [i]], y[:, [i]]))
                            for i, batch in enumerate(entered)}
    if len(entered) < len(batches):
        row["reading"] = (f"pending ({len(entered)} of {len(batches)} batches entered; the reading needs every batch "
                          f"with {MIN_SEEDS_FOR_VERDICT} seeds of both)")
    elif row["ci_low"] > 0.5:
        row["reading"] = f"{a} above {b} across batches (the interval lies above 0.5)" + _against(row, "below")
    elif row["ci_high"] < 0.5:
        row["reading"] = f"{a} below {b} across batches (the interval lies below 0.5)" + _against(row, "above")
    else:
        row["reading"] = "no difference shown (the interval contains 0.5)"
    return row


def fmt(x: float | None, digits: int = 1) -> str:
    """``x`` with ``digits`` decimals, or nothing for ``None``."""
    return "" if x is None else f"{x:.{digits}f}"


def mean_cell(cell: dict | None) -> str:
    """A cell's mean ± std over its seeds (:func:`batch_rows`), with the seeds it has of those scheduled while it has
    fewer; "pending" while it has none, "not run" where the study does not schedule it."""
    if cell is None:
        return "not run"
    seeds, scheduled = cell.get("seeds", 0), cell["scheduled"]
    if seeds == 0:
        return f"pending (0 of {scheduled} seeds)"
    std = cell["final_return_std"]
    text = fmt(cell["final_return_mean"]) + ("" if std is None else f" ± {fmt(std)}")
    return text + (f" ({seeds} of {scheduled} seeds)" if seeds < scheduled else "")


def iqm_cell(cell: dict | None) -> str:
    """A cell's IQM [95 % CI], "pending" below :data:`MIN_SEEDS_FOR_VERDICT` seeds."""
    if cell is None:
        return "not run"
    seeds, scheduled = cell.get("seeds", 0), cell["scheduled"]
    if seeds < MIN_SEEDS_FOR_VERDICT:
        return f"pending ({seeds} of {scheduled} seeds)"
    text = (f"{fmt(cell['final_return_iqm'])} [{fmt(cell['final_return_iqm_ci_low'])}, "
            f"{fmt(cell['final_return_iqm_ci_high'])}]")
    return text + (f" ({seeds} of {scheduled} seeds)" if seeds < scheduled else "")


def iqm_table(batches: list[dict], algos: list[str], names: list[str] | None = None) -> list[str]:
    """A report's table of each batch's per-algorithm IQM interval (:func:`iqm_cell`), headed by ``names`` (default:
    the algorithms' own), and its caption."""
    return ["| batch | " + " | ".join(names or algos) + " |", "|---|" + "---|" * len(algos),
            *(f"| {b['batch']} | " + " | ".join(iqm_cell(b["cells"].get(a)) for a in algos) + " |" for b in batches),
            "", f"Interquartile mean of the final return over seeds [95 % stratified-bootstrap interval] (rliable, "
            f"{BOOTSTRAP_REPS} replications); pending below {MIN_SEEDS_FOR_VERDICT} seeds."]


def bootstrap_sentence(n_batches: int) -> str:
    """What every interval over batches is, for the reports' text."""
    return (f"Intervals: 95 %, {HIERARCHICAL_BOOTSTRAP} ({BOOTSTRAP_REPS} replications, numpy seed "
            f"{BOOTSTRAP_SEED}, the same numbers on every rerun). With {n_batches} batches to draw from, these "
            "intervals are coarse. '[over seeds alone]': rliable's stratified bootstrap, the seeds drawn "
            "within each batch and the batches fixed, which cannot show batches that disagree.")


def improvement_lines(pairs: list[dict], n_batches: int) -> list[str]:
    """The table of :func:`improvement` rows and what they mean, as Markdown lines."""
    lines = ["| comparison | batches entered | seeds (first, second) | probability of improvement [95 % CI] "
             "| [over seeds alone] | per batch | reading |", "|---|---|---|---|---|---|---|"]
    for p in pairs:
        entered = f"{', '.join(p['batches'])} ({len(p['batches'])} of {n_batches})" if p["batches"] else "none"
        value = "" if p["p"] is None else f"{fmt(p['p'], 3)} [{fmt(p['ci_low'], 3)}, {fmt(p['ci_high'], 3)}]"
        alone = "" if p["seeds_only"] is None else f"[{fmt(p['seeds_only'][0], 3)}, {fmt(p['seeds_only'][1], 3)}]"
        seeds = "" if p["seeds"] is None else f"{p['seeds'][0]}, {p['seeds'][1]}"
        per_batch = ", ".join(f"{batch} {fmt(v, 2)}" for batch, v in p["per_batch"].items())
        lines.append(f"| P({p['a']} > {p['b']}) | {entered} | {seeds} | {value} | {alone} | {per_batch} | "
                     f"{p['reading']} |")
    return lines + ["", "Probability of improvement (rliable): the chance that a run of the first algorithm ends above "
                    "a run of the second on the same batch, averaged over the batches entered; the reading needs all "
                    f"{n_batches} batches, and then says 'above' when the whole interval lies above 0.5, naming any "
                    "batch whose own value lies on the other side, and 'no difference shown' when the interval "
                    "contains 0.5. A batch where every run of one algorithm ends above every run of the other gives 1 "
                    "(or 0) whatever seeds are drawn, so over seeds alone batches that disagree that cleanly give a "
                    "one-point interval; drawing the batches too shows the disagreement as width. Read it with the "
                    "per-batch column."]


def bootstrap_settings() -> dict:
    """The replications and numpy seed of every interval, as the reports' JSON records them."""
    return {"reps": BOOTSTRAP_REPS, "seed": BOOTSTRAP_SEED}

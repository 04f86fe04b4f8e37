"""Figures a person would rather look at than read: a run's learning curve, and the report's figures (learning
curves averaged over seeds, rliable's aggregate metrics and performance profiles). The envelope plot is in
:mod:`torchrl_bail.envelope`. All figures are written atomically (temp file, then rename)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from torchrl_bail.io import atomic_path  # noqa: E402

__all__ = ["save_figure", "plot_learning_curve", "read_eval_curve", "plot_report"]


def save_figure(fig, path: Path, dpi: int = 120) -> Path:
    """Saves ``fig`` to ``path`` atomically and closes it."""
    try:
        with atomic_path(path, suffix=Path(path).suffix) as tmp:
            fig.savefig(tmp, dpi=dpi, bbox_inches="tight")
    finally:
        plt.close(fig)
    return Path(path)


def plot_learning_curve(
    epochs: Sequence[float],
    returns: Sequence[float],
    path: Path,
    *,
    dataset_mean: float | None = None,
    title: str | None = None,
    start_epoch: float = 0.0,
) -> Path:
    """Evaluation return against epochs (10^6 samples), with the batch's mean episode return as a line.

    ``start_epoch`` shifts the x axis (the paper starts BAIL's curve at epoch 50, after the envelope).
    """
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    ax.plot([start_epoch + e for e in epochs], returns, marker="o", markersize=3, label="evaluation return")
    if dataset_mean is not None:
        ax.axhline(dataset_mean, color="gray", linestyle="--", label="batch mean episode return")
    ax.set_xlabel("epoch (10^6 samples)")
    ax.set_ylabel("average return (deterministic)")
    if title:
        ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(loc="best")
    return save_figure(fig, path)


# ---------------------------------------------------------------------------------------------------------------
# report figures (``python -m torchrl_bail.report DIR --out PREFIX --plot``)
# ---------------------------------------------------------------------------------------------------------------


def _read_scalar_csv(path: Path) -> dict[int, float]:
    """A TorchRL ``CSVLogger`` scalar file: one ``step,value`` line per logged value."""
    out = {}
    for line in Path(path).read_text().splitlines():
        step, value = line.split(",")
        out[int(float(step))] = float(value)
    return out


def read_eval_curve(run_dir: Path):
    """``(epochs, returns)`` of a run's evaluations, from ``logs/scalars/eval/{epoch,return}.csv``.

    The trainer logs ``eval/return`` (mean deterministic return) and ``eval/epoch`` at the same iteration;
    ``None`` when the run has no CSV logs (another logger backend).
    """
    import numpy as np

    scalars = Path(run_dir) / "logs" / "scalars" / "eval"
    if not (scalars / "return.csv").is_file() or not (scalars / "epoch.csv").is_file():
        return None
    returns, epochs = _read_scalar_csv(scalars / "return.csv"), _read_scalar_csv(scalars / "epoch.csv")
    steps = sorted(set(returns) & set(epochs))
    return np.array([epochs[s] for s in steps]), np.array([returns[s] for s in steps])


def _mean_curve(curves):
    """Mean over seeds and a 95 % normal band (1.96 standard errors) on the shortest run's epoch grid."""
    import numpy as np

    grid = min((c[0] for c in curves), key=lambda e: e[-1])
    ys = np.stack([np.interp(grid, e, r) for e, r in curves])
    mean = ys.mean(0)
    half = 1.96 * ys.std(0, ddof=1) / np.sqrt(len(ys)) if len(ys) > 1 else np.zeros_like(mean)
    return grid, mean, half


def _plot_curves(groups, path: Path) -> Path | None:
    batches = sorted({g.batch for g in groups}, key=str)
    panels = []
    for batch in batches:
        lines = []
        for g in (g for g in groups if g.batch == batch):
            curves = [c for c in (read_eval_curve(r.run_dir) for r in g.runs) if c is not None and len(c[0])]
            if curves:
                lines.append((g.label, len(curves), *_mean_curve(curves)))
        if lines:
            panels.append((batch, lines))
    if not panels:
        return None
    fig, axes = plt.subplots(1, len(panels), figsize=(5.0 * len(panels), 3.8), squeeze=False)
    for ax, (batch, lines) in zip(axes[0], panels):
        for label, n, x, mean, half in lines:
            ax.plot(x, mean, label=f"{label} ({n} seeds)")
            ax.fill_between(x, mean - half, mean + half, alpha=0.2)
        ax.set_title(batch[0])
        ax.set_xlabel("epoch (10^6 samples)")
        ax.set_ylabel("evaluation return (mean over seeds)")
        ax.grid(alpha=0.3)
        ax.legend(loc="best", fontsize="small")
    return save_figure(fig, path)


def _normalised_scores(groups):
    """``label -> (runs x batches)`` matrix and the score's name.

    The D4RL/Minari normalised score when every run has one, otherwise ``final_return`` divided by the batch's
    mean episode return (1.0 = as good as the data on average). Each batch contributes its first ``n`` seeds,
    ``n`` the fewest seeds any of the label's batches has (rliable needs a full matrix).
    """
    import numpy as np

    runs = [r for g in groups for r in g.runs]
    if all(r.summary.get("final_return_normalized") is not None for r in runs):
        name, score = "normalised score", lambda s: float(s["final_return_normalized"])
    else:
        name = "final return / batch mean episode return"
        score = lambda s: float(s["final_return"]) / float(s["dataset_mean_episode_return"])  # noqa: E731
    by_label: dict[str, list] = {}
    for g in groups:
        if any(not r.summary.get("dataset_mean_episode_return") for r in g.runs) and name != "normalised score":
            continue
        by_label.setdefault(g.label, []).append(sorted(score(r.summary) for r in g.runs))
    matrices = {}
    for label, columns in by_label.items():
        n = min(len(c) for c in columns)
        matrices[label] = np.array([c[:n] for c in columns]).T
    return matrices, name


def plot_report(groups, prefix: str, *, reps: int = 2_000, seed: int = 0) -> list[Path]:
    """The report's figures: ``PREFIX_curves.png``, ``PREFIX_aggregate.png``, ``PREFIX_profiles.png``."""
    import numpy as np

    from torchrl_bail.report import _rliable, numpy_seed

    written = []
    curves = _plot_curves(groups, Path(f"{prefix}_curves.png"))
    if curves is not None:
        written.append(curves)
    matrices, name = _normalised_scores(groups)
    if not matrices:
        return written
    library, metrics = _rliable()
    from rliable import plot_utils

    def aggregates(x):
        return np.array([metrics.aggregate_median(x), metrics.aggregate_iqm(x), metrics.aggregate_mean(x),
                         metrics.aggregate_optimality_gap(x, 1.0)])

    with numpy_seed(seed):
        point, interval = library.get_interval_estimates(matrices, aggregates, reps=reps)
    fig, _ = plot_utils.plot_interval_estimates(point, interval, ["Median", "IQM", "Mean", "Optimality gap"],
                                                algorithms=list(matrices), xlabel=name,
                                                xlabel_y_coordinate=-0.35)
    written.append(save_figure(fig, Path(f"{prefix}_aggregate.png")))
    all_scores = np.concatenate([m.ravel() for m in matrices.values()])
    taus = np.linspace(min(0.0, all_scores.min()), max(1.0, all_scores.max()), 81)
    with numpy_seed(seed):
        profiles, profile_cis = library.create_performance_profile(matrices, taus, reps=min(reps, 2000))
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    plot_utils.plot_performance_profiles(profiles, taus, performance_profile_cis=profile_cis, ax=ax,
                                         xlabel=f"{name} (tau)")
    ax.legend(loc="best", fontsize="small")
    written.append(save_figure(fig, Path(f"{prefix}_profiles.png")))
    return written

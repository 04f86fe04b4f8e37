"""Figures a person would rather look at than read: a run's learning curve and the helpers of the report's
figures (:mod:`torchrl_bail.report`; the envelope plot is in :mod:`torchrl_bail.envelope`). All figures are written
atomically (temp file, then rename).

Figures are plain :class:`matplotlib.figure.Figure` objects rendered straight to files: importing this module
neither imports matplotlib nor selects a backend, so a notebook or GUI using :mod:`torchrl_bail` keeps its own.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from torchrl_bail.io import atomic_path

__all__ = ["new_figure", "save_figure", "plot_learning_curve", "read_eval_curve", "mean_curve"]


def new_figure(**kwargs):
    """A matplotlib ``Figure`` outside pyplot (no backend, no global figure list); ``kwargs`` go to ``Figure``."""
    from matplotlib.figure import Figure

    return Figure(**kwargs)


def save_figure(fig, path: Path, dpi: int = 120) -> Path:
    """Saves ``fig`` to ``path`` atomically; a figure made through pyplot is closed afterwards."""
    try:
        with atomic_path(path, suffix=Path(path).suffix) as tmp:
            fig.savefig(tmp, dpi=dpi, bbox_inches="tight")
    finally:
        if getattr(fig.canvas, "manager", None) is not None:
            import matplotlib.pyplot as plt

            plt.close(fig)
    return Path(path)


def __getattr__(name: str):
    """``from torchrl_bail.plots import plt``: pyplot, imported on first use (its default backend)."""
    if name == "plt":
        import matplotlib.pyplot as plt

        return plt
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


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
    fig = new_figure(figsize=(6.4, 4.0))
    ax = fig.subplots()
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
# evaluation curves of finished runs (the report's figures)
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


def mean_curve(curves):
    """Mean over seeds and a 95 % normal band (1.96 standard errors) on the shortest run's epoch grid."""
    import numpy as np

    grid = min((c[0] for c in curves), key=lambda e: e[-1])
    ys = np.stack([np.interp(grid, e, r) for e, r in curves])
    mean = ys.mean(0)
    half = 1.96 * ys.std(0, ddof=1) / np.sqrt(len(ys)) if len(ys) > 1 else np.zeros_like(mean)
    return grid, mean, half

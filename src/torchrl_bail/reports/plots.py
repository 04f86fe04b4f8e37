"""Figures a person would rather look at than read: a run's learning curve, BAIL's upper envelope (the paper's
Fig. 13) and the helpers of the report's figures (:mod:`torchrl_bail.report`). All figures are written atomically
(temp file, then rename).

Figures are plain :class:`matplotlib.figure.Figure` objects rendered straight to files: importing this module
neither imports matplotlib nor selects a backend, so a notebook or GUI using :mod:`torchrl_bail` keeps its own.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from torchrl_bail.core.io import atomic_path

__all__ = ["new_figure", "save_figure", "plot_learning_curve", "plot_envelope", "read_eval_curve", "mean_curve"]


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
    """``from torchrl_bail.reports.plots import plt``: pyplot, imported on first use (its default backend)."""
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


def plot_envelope(values, returns, path: str | Path, *, title: str | None = None) -> Path:
    """The paper's Fig. 13: states sorted by ``V`` ascending, the envelope as a line, the returns as dots.

    Args:
        values (Tensor or array): ``V(s_i)``, ``[N]`` (a CPU tensor or array, e.g.
            :func:`~torchrl_bail.training.envelope.envelope_values`).
        returns (Tensor or array): ``G_i``, ``[N]``.
        path (str or Path): the image file (``.png``, ``.pdf``, ...).

    Keyword Args:
        title (str, optional): the figure title. Defaults to the share of returns above the envelope.

    Returns:
        the path written.
    """
    values = np.asarray(values, dtype=np.float64).reshape(-1)
    returns = np.asarray(returns, dtype=np.float64).reshape(-1)
    if values.shape != returns.shape:
        raise ValueError(f"values and returns must have the same number of elements, got "
                         f"{values.size} and {returns.size}")
    order = np.argsort(values, kind="stable")
    x = np.arange(len(values))
    below = float(np.mean(values < returns)) if len(values) else math.nan  # envelope.fraction_below
    fig = new_figure(figsize=(6.4, 4.0))
    ax = fig.subplots()
    ax.plot(x, returns[order], linestyle="none", marker=".", markersize=1.0, alpha=0.5,
            color="tab:blue", label="return G", rasterized=True)
    ax.plot(x, values[order], color="tab:red", linewidth=1.5, label="upper envelope V")
    ax.set_xlabel("states, sorted by V (ascending)")
    ax.set_ylabel("return")
    ax.set_title(title if title is not None else f"Upper envelope ({below:.1%} of returns above V)")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", markerscale=8)
    return save_figure(fig, Path(path))


def read_scalar_csv(path: Path) -> dict[int, float]:
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
    returns, epochs = read_scalar_csv(scalars / "return.csv"), read_scalar_csv(scalars / "epoch.csv")
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

"""Draws the Concepts page's data-flow figure (``assets/data_flow.svg``) with matplotlib: the boxes are the stages a
batch goes through, each naming the code that does it. ``docs/hooks.py`` draws it at every build; no JavaScript
and no network are needed to see it. ``python docs/gen_data_flow.py OUT.svg`` writes it by hand.
"""

from __future__ import annotations

import io
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from matplotlib.patches import FancyBboxPatch

#: (title, what happens, the code) from top to bottom
STAGES = (
    ("batch", "OfflineBatch: a TED TensorDict on disk, collected (DDPG, SAC) or imported (D4RL, Minari)",
     "behaviour.ensure_batch · data.importers.import_dataset"),
    ("returns", "Monte-Carlo returns G, the 'gain' augmentation for time-limited episodes",
     "data.monte_carlo_returns"),
    ("envelope", "V(s) ≥ G fitted with the penalty K = 1000, weight decay and early stopping",
     "objectives.UpperEnvelopeLoss · envelope.fit_upper_envelope"),
    ("best-action filter", "keep the pairs (s, a) whose ratio G / V(s) is in the top 30 %",
     "transforms.BestActionFilter"),
    ("imitation", "behaviour cloning of the selected actions by a deterministic tanh policy",
     "torchrl.objectives.BCLoss · trainer.train"),
    ("evaluation", "deterministic episodes in one batched env, every 0.5 epoch",
     "evaluation.Evaluator → summary.json, plots, checkpoints"),
)
#: the other algorithms join the flow after the returns and rejoin it at evaluation
BASELINES = "BC · MARWIL · BCQ · BEAR:\ntheir own losses\non the whole batch"


def draw() -> bytes:
    width, height, gap = 7.2, 0.78, 0.42
    fig = plt.figure(figsize=(10.0, len(STAGES) * (height + gap) + 0.2))
    ax = fig.add_axes((0, 0, 1, 1))
    total = len(STAGES) * (height + gap)
    ax.set_xlim(0, 10.0)
    ax.set_ylim(0, total + 0.2)
    ax.axis("off")
    tops = []
    for i, (title, what, code) in enumerate(STAGES):
        y = total - (i + 1) * (height + gap) + gap
        tops.append(y)
        ax.add_patch(FancyBboxPatch((0.2, y), width, height, boxstyle="round,pad=0.02,rounding_size=0.08",
                                    facecolor="#fff3e0" if title in ("envelope", "best-action filter") else "#f5f5f5",
                                    edgecolor="#e64a19", linewidth=1.4))
        ax.text(0.35, y + height - 0.2, title, fontsize=13.5, fontweight="bold", va="center")
        ax.text(0.35, y + height / 2 - 0.04, what, fontsize=11, va="center")
        ax.text(0.35, y + 0.16, code, fontsize=10.5, va="center", family="monospace", color="#5d4037")
        if i:
            ax.annotate("", xy=(0.2 + width / 2, y + height), xytext=(0.2 + width / 2, y + height + gap),
                        arrowprops={"arrowstyle": "-|>", "color": "#e64a19", "lw": 1.6})
    side_x = 0.2 + width + 0.35
    returns_y, evaluation_y = tops[1] + height / 2, tops[-1] + height / 2
    ax.annotate("", xy=(side_x + 0.9, (returns_y + evaluation_y) / 2 + 0.55), xytext=(0.2 + width, returns_y),
                arrowprops={"arrowstyle": "-", "color": "#757575", "lw": 1.2, "linestyle": "--",
                            "connectionstyle": "angle,angleA=0,angleB=90"})
    ax.annotate("", xy=(0.2 + width, evaluation_y), xytext=(side_x + 0.9, (returns_y + evaluation_y) / 2 - 0.55),
                arrowprops={"arrowstyle": "-|>", "color": "#757575", "lw": 1.2, "linestyle": "--",
                            "connectionstyle": "angle,angleA=-90,angleB=0"})
    ax.text(side_x + 0.9, (returns_y + evaluation_y) / 2, BASELINES, fontsize=11, ha="center", va="center",
            color="#424242")
    out = io.BytesIO()
    fig.savefig(out, format="svg", metadata={"Date": None})  # no timestamp: the same file at every build
    plt.close(fig)
    return out.getvalue()


if __name__ == "__main__":
    with open(sys.argv[1] if len(sys.argv) > 1 else "data_flow.svg", "wb") as f:
        f.write(draw())

"""What the batch cache holds: one row per cached batch (``python -m torchrl_bail.collect --list``)."""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from torchrl_bail.data.batch import load_batch
from torchrl_bail.data.cache import data_dir_of

__all__ = ["list_batches", "format_bytes"]


def _du(path: Path) -> int:
    total = 0
    for root, _, files in os.walk(path):
        for f in files:
            with contextlib.suppress(OSError):
                total += os.stat(os.path.join(root, f)).st_blocks * 512
    return total


def _recipe_summary(meta: Mapping[str, Any]) -> str:
    recipe = meta.get("recipe") or {}
    kind = recipe.get("recipe", "?")
    parts = [f"{kind}", f"steps={recipe.get('steps')}", f"seed={meta.get('seed')}"]
    # by the keys a recipe has, never its name (this layer does not know the recipes): DDPG's noise, a frozen policy
    if "sigma" in recipe:
        parts.append(f"sigma={recipe.get('sigma')}")
    if "policy" in recipe:
        parts.append(f"{recipe.get('policy')}/{'stoch' if recipe.get('stochastic') else 'det'}")
        if meta.get("behaviour_return") is not None:
            parts.append(f"policy_return={meta['behaviour_return']:.0f}")
    if meta.get("oracle"):
        parts.append("oracle")
    return " ".join(parts)


def list_batches(data_dir: str | os.PathLike | None = None) -> list[dict[str, Any]]:
    """One row per cached batch in ``data_dir``: name, path, bytes on disk, sizes, episode-return stats, recipe."""
    data_dir = data_dir_of(None, data_dir)
    rows = []
    if not data_dir.is_dir():
        return rows
    for meta_path in sorted(data_dir.glob("*/metadata.json")):
        path = meta_path.parent
        if path.name.startswith("."):
            continue
        try:
            meta = json.loads(meta_path.read_text())
        except (OSError, ValueError):
            continue
        row = {"name": path.name, "path": str(path), "bytes": _du(path), "env_id": meta.get("env_id"),
               "recipe": _recipe_summary(meta)}
        stats = _episode_stats(path, meta)
        row.update(stats)
        rows.append(row)
    return rows


def _episode_stats(path: Path, meta: Mapping[str, Any]) -> dict[str, Any]:
    stats = meta.get("stats") or {}
    out = {
        "transitions": stats.get("num_transitions", meta.get("num_transitions")),
        "episodes": stats.get("num_episodes", meta.get("num_episodes")),
        "mean_return": stats.get("episode_return_mean", stats.get("mean_episode_return")),
        "max_return": stats.get("episode_return_max", stats.get("max_episode_return")),
    }
    if any(v is None for v in out.values()):
        with contextlib.suppress(Exception):
            batch = load_batch(path)
            rets = batch.episode_returns()
            out = {"transitions": int(batch.num_transitions), "episodes": int(batch.num_episodes),
                   "mean_return": float(rets.mean()), "max_return": float(rets.max())}
    return out


def format_bytes(n: int) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if n < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return str(n)

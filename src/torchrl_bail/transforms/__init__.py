"""Replay-buffer transforms: BAIL's best-action selection."""

from __future__ import annotations

from torchrl_bail.transforms.best_action import (
    BestActionFilter,
    NonPositiveValue,
    best_action_mask,
    project_values,
    select_best_actions,
)

__all__ = ["BestActionFilter", "NonPositiveValue", "best_action_mask", "project_values", "select_best_actions"]

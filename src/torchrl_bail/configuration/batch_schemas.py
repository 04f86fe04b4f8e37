"""The batch recipes' registry (:data:`BATCH_SCHEMAS`, ``conf/batch``): one schema per recipe, named
``batch/base_<recipe>_schema`` in Hydra (:func:`torchrl_bail.configuration.hydra_setup.register_schemas`); the rules
come from
:mod:`torchrl_bail.configuration.config`. This module holds the keys every batch has; a recipe's schema is written in
its module of
:mod:`torchrl_bail.behaviour` (``@batch_schema("<recipe>")``) beside the collection, and read from there without
importing it (:mod:`torchrl_bail.configuration.schema_reader`), so a bad command line fails before torch loads.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Optional  # noqa: UP035 -- OmegaConf reads these annotations at runtime

from omegaconf import MISSING

from torchrl_bail.configuration.config import (
    Checked,
    at_least,
    discount,
    non_negative,
    option_name,
    positive,
    registry_name,
)
from torchrl_bail.configuration.schema_reader import read_schemas, register_as, schema_block
from torchrl_bail.core.errors import ConfigError

__all__ = ["BATCH_SCHEMAS", "BatchConfig", "OracleConfig", "batch_schema", "schema_block"]


@dataclass
class OracleConfig(Checked):
    enabled: bool = MISSING
    horizon: int = at_least(2)
    keep: int = at_least(1, "a positive number of steps kept per episode")
    gamma: float = discount()

    def check(self) -> None:
        if self.horizon <= self.keep:
            raise ConfigError("horizon", self.horizon, f"an episode length larger than keep = {self.keep}")


@dataclass
class BatchConfig(Checked):
    kind: str = option_name("batch")
    recipe: str = registry_name("BATCH_SCHEMAS")
    index: int = at_least(1, "an integer >= 1 (B1, B2, ...)")
    seed: Optional[int] = non_negative("null or an integer >= 0")
    steps: int = positive("a positive number of transitions")
    oracle: OracleConfig = MISSING
    # how a batch is collected, never what it holds (outside the recipe hash): conf/batch/_collection.yaml
    checkpoint_every_s: Optional[float] = positive("seconds of work between collection checkpoints, or null (never)")
    checkpoint_every_steps: Optional[int] = at_least(1, "env steps between collection checkpoints, or null")
    lock_stale_after_s: float = positive("seconds after which another host's lock without heartbeat is stale")
    heartbeat_every_s: float = positive("seconds between heartbeats of this job's locks and scratch directories")

    def check(self) -> None:
        self._registered_as("recipe", BATCH_SCHEMAS, "the recipe of this batch schema")


#: recipe name -> its schema, by name; filled by :func:`batch_schema` as the modules of
#: :mod:`torchrl_bail.behaviour` are read (:func:`_read_recipe_schemas`), kept equal to
#: :data:`torchrl_bail.behaviour.recipes.RECIPES` by a test
BATCH_SCHEMAS: dict[str, type[BatchConfig]] = {}


def batch_schema(name: str) -> Callable[[type], type]:
    """Registers the decorated class as the schema of recipe ``name`` (``batch.recipe``) in :data:`BATCH_SCHEMAS`,
    made a dataclass; written in the recipe's own module and read from there without importing it
    (:mod:`torchrl_bail.configuration.schema_reader`)."""
    return register_as(BATCH_SCHEMAS, name)


def _read_recipe_schemas() -> None:
    read_schemas(Path(__file__).parents[1] / "behaviour", "torchrl_bail.behaviour", {"batch_schema"}, BATCH_SCHEMAS)


_read_recipe_schemas()

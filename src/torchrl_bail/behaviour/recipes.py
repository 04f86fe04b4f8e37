"""The recipe registry: each behaviour recipe registers itself beside its code, and every dispatch goes through it.

Recipes (``cfg.batch.recipe``), each a :class:`Recipe` registered at the end of its module:

* ``ddpg`` -- :mod:`torchrl_bail.behaviour.ddpg`: the whole replay buffer of an online DDPG run with N(0, sigma^2)
  exploration noise (supp. C.2, final buffer).
* ``sac`` -- :mod:`torchrl_bail.behaviour.sac_run`: the first ``steps`` transitions of an online SAC run (paper Sec. 5;
  supp. E).
* ``sac_exec`` -- :mod:`torchrl_bail.behaviour.execution`: ``steps`` transitions of a frozen SAC policy (mediocre or
  optimal, deterministic or stochastic; paper Sec. 5; supp. E). The SAC run behind it is shared with the ``sac`` batch.

:func:`~torchrl_bail.behaviour.catalogue.collect_batch` asks :func:`recipe_of` for the recipe of ``cfg.batch`` and
calls its :meth:`Recipe.collect`, :meth:`Recipe.checkpoint` and :meth:`Recipe.remove_checkpoint`; it never names one.
Adding a recipe is one module and its yamls: its batch schema (a
:class:`~torchrl_bail.configuration.batch_schemas.BatchConfig`
subclass decorated with ``@batch_schema("<recipe>")``, read from the module without importing it, so that
:data:`torchrl_bail.configuration.batch_schemas.BATCH_SCHEMAS` stays torch-free; kept equal to :data:`RECIPES` by a
test) and a
:class:`Recipe` subclass ending with ``register_recipe(MyRecipe())``; :mod:`torchrl_bail.behaviour` imports the
recipe modules.

Any recipe can be collected in *oracle* mode (``batch.oracle.enabled=true``, supp. D.1): see
:class:`~torchrl_bail.behaviour.buffers.BatchSink`. Names, hashes and cache paths are those of
:mod:`torchrl_bail.data.cache`.

A recipe's values are checked by its schema (:data:`torchrl_bail.configuration.batch_schemas.BATCH_SCHEMAS`)
when :func:`~torchrl_bail.configuration.config_builders.collection_config` types a config, which every entry point of
this package
calls first.

Examples:
    >>> tuple(RECIPES)
    ('ddpg', 'sac', 'sac_exec')
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from pathlib import Path
from typing import Any, ClassVar

from tensordict import TensorDictBase

from torchrl_bail.behaviour.checkpoint import CollectionCheckpoint
from torchrl_bail.core.errors import ConfigError

__all__ = ["RECIPES", "Recipe", "recipe_of", "register_recipe"]


class Recipe(ABC):
    """One behaviour recipe: how a batch of ``cfg.batch.recipe == name`` is collected.

    Attributes:
        name: the ``batch.recipe`` value (its batch schema is registered under the same name).
    """

    name: ClassVar[str]

    @abstractmethod
    def collect(self, cfg, *, scratch: Path, progress: bool, data_dir: Path,
                checkpoint: CollectionCheckpoint) -> tuple[TensorDictBase, dict[str, Any]]:
        """Runs the recipe: ``(transitions [batch.steps], metadata extras)``; resumes from / saves to
        ``checkpoint``; ``data_dir`` is the batch cache (for what the recipe shares there)."""

    def checkpoint(self, cfg, data_dir: Path, name: str) -> CollectionCheckpoint:
        """Where the collection of the batch ``name`` checkpoints. Default: its own ``.partial/<name>``. Made at the
        start of the collection: its clock (:attr:`CollectionCheckpoint.wall_time_s`) gives the batch's
        ``collection_wall_time_s``."""
        return CollectionCheckpoint.for_config(cfg, data_dir, name)

    def remove_checkpoint(self, cfg, data_dir: Path, checkpoint: CollectionCheckpoint) -> None:
        """Removes the checkpoint once the batch is saved. Default: at once."""
        checkpoint.remove()


#: the registered recipes by name, in registration order
RECIPES: dict[str, Recipe] = {}


def register_recipe(recipe: Recipe, *, replace: bool = False) -> Recipe:
    """Adds ``recipe`` to :data:`RECIPES` (a second recipe of the same name is an error unless ``replace``)."""
    if recipe.name in RECIPES and not replace:
        raise ValueError(f"behaviour recipe {recipe.name!r} is already registered "
                         f"({type(RECIPES[recipe.name]).__name__})")
    RECIPES[recipe.name] = recipe
    return recipe


def recipe_of(cfg) -> Recipe:
    """The registered recipe of ``cfg.batch.recipe``; :class:`~torchrl_bail.core.errors.ConfigError` naming the known
    ones otherwise."""
    name = cfg.batch.recipe
    if name not in RECIPES:
        raise ConfigError("batch.recipe", name, f"one of {', '.join(RECIPES)} (the registered behaviour recipes)")
    return RECIPES[name]

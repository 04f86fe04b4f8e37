"""The recipe catalogue: which behaviour recipes exist and what a valid ``cfg.env`` / ``cfg.batch`` looks like.

Recipes (``cfg.batch.recipe``):

* ``ddpg`` -- :mod:`torchrl_bail.behaviour.ddpg`: the whole replay buffer of an online DDPG run with N(0, sigma^2)
  exploration noise (supp. C.2, final buffer).
* ``sac`` -- :mod:`torchrl_bail.behaviour.sac_run`: the first ``steps`` transitions of an online SAC run (paper Sec. 5;
  supp. E).
* ``sac_exec`` -- :mod:`torchrl_bail.behaviour.execution`: ``steps`` transitions of a frozen SAC policy (mediocre or
  optimal, deterministic or stochastic; paper Sec. 5; supp. E). The SAC run behind it is shared with the ``sac`` batch.

Any recipe can be collected in *oracle* mode (``batch.oracle.enabled=true``, supp. D.1): see
:class:`~torchrl_bail.behaviour.buffers.BatchSink`. Names, hashes and cache paths are those of
:mod:`torchrl_bail.data.cache`.

A recipe's values are checked by its schema (:data:`torchrl_bail.config.BATCH_SCHEMAS`) when
:func:`~torchrl_bail.config.collection_config` types a config, which every entry point of this package calls first.

Examples:
    >>> RECIPES
    ('ddpg', 'sac', 'sac_exec')
"""

from __future__ import annotations

from torchrl_bail.config import BATCH_SCHEMAS

__all__ = ["RECIPES"]

#: the recipes, as their schemas are registered
RECIPES = tuple(BATCH_SCHEMAS)

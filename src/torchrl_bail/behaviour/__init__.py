"""The online side that *makes* offline batches: behaviour agents (DDPG, SAC), their shared step loop, execution
and oracle batches, and :func:`ensure_batch`, which returns the cached batch of a config or collects it first.

Layering: this package reads and writes the bottom layer :mod:`torchrl_bail.data` (format, cache) and builds its
networks from :mod:`torchrl_bail.modules`; the offline learners (:mod:`torchrl_bail.algorithms`) never import it.
Only the entry points (``torchrl_bail.collect``, ``torchrl_bail.train``) do.

Modules: :mod:`~torchrl_bail.behaviour.recipes` (the recipe catalogue), :mod:`~torchrl_bail.behaviour.catalogue`
(``ensure_batch`` / ``collect_batch``), :mod:`~torchrl_bail.behaviour.loop` (the step loop),
:mod:`~torchrl_bail.behaviour.buffers` (episode store, plain/oracle batch sink),
:mod:`~torchrl_bail.behaviour.checkpoint` (checkpoints: a killed collection resumes to the same batch),
:mod:`~torchrl_bail.behaviour.ddpg`, :mod:`~torchrl_bail.behaviour.sac` (the agent),
:mod:`~torchrl_bail.behaviour.sac_run` (the shared SAC run), :mod:`~torchrl_bail.behaviour.execution`.
"""

from torchrl_bail.behaviour.catalogue import collect_batch, ensure_batch
from torchrl_bail.behaviour.recipes import RECIPES

__all__ = ["RECIPES", "collect_batch", "ensure_batch"]

"""The bottom layer: atomic writes (:mod:`~torchrl_bail.core.io`), the one-line error classes
(:mod:`~torchrl_bail.core.errors`), the interrupt requests (:mod:`~torchrl_bail.core.interrupts`), the progress
bars (:mod:`~torchrl_bail.core.progress`) and seed stacks (:mod:`~torchrl_bail.core.stacking`). Nothing here imports
anything else of the package."""

"""The reporting layer below the ``report`` entry point: the figures (:mod:`~torchrl_bail.reports.plots`)."""

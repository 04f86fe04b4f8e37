"""torchrl_bail's study sweeper for Hydra (``hydra/sweeper=study``): :mod:`.study_sweeper`."""

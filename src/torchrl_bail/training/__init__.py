"""The training layer: the one training loop (:mod:`~torchrl_bail.training.trainer`), the envelope fit as named steps
(:mod:`~torchrl_bail.training.envelope`) and run directories: resume, lock, finished runs
(:mod:`~torchrl_bail.training.resume`). The package face imports nothing."""

"""The configuration layer, torch-free: the rule language and the top-level ``Config``
(:mod:`~torchrl_bail.configuration.config`), the two registries (:mod:`~torchrl_bail.configuration.algo_schemas`,
:mod:`~torchrl_bail.configuration.batch_schemas`) filled by :mod:`~torchrl_bail.configuration.schema_reader`, the
typed builders (:mod:`~torchrl_bail.configuration.config_builders`), run-directory naming
(:mod:`~torchrl_bail.configuration.run_dirs`) and Hydra's setup (:mod:`~torchrl_bail.configuration.hydra_setup`)."""

"""The paper's studies as one command, on any Hydra launcher: ``python -m torchrl_bail.study run|status|report|list``.

A study is declared as data (:mod:`torchrl_bail.study.declaration`: steps of cells, each a grid of overrides); ``run``
launches each step as a Hydra multirun of its entry point (``train`` or ``collect``) through the study sweeper
(``hydra/sweeper=study``, :mod:`torchrl_bail.study.sweeps`), which skips the jobs already done and hands the rest to
whichever launcher the command names: the basic one (one job after another), ``hydra/launcher=joblib`` on one
machine, ``hydra/launcher=slurm`` on a cluster. Re-running it resumes: finished jobs are skipped and stopped ones
continue from their checkpoints (run directories are derived from the config, never from the clock).
"""

from torchrl_bail.study.declaration import Step, Study, StudyError, StudyJob, declared_studies, load_study

__all__ = ["Step", "Study", "StudyError", "StudyJob", "declared_studies", "load_study"]

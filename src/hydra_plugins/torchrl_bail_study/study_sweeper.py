"""``hydra/sweeper=study``: one step of a declared study as a Hydra sweep (:mod:`torchrl_bail.study.sweeps`).

Hydra finds sweepers in the ``hydra_plugins`` namespace package, hence this module outside ``torchrl_bail``; what it
launches, and why, is :mod:`torchrl_bail.study.sweeps`'s to say.
"""

# no ``from __future__ import annotations``: Hydra imports plugin modules without entering them in sys.modules,
# where a dataclass cannot look string annotations up
import logging
from dataclasses import dataclass
from typing import Any

from hydra.core.config_store import ConfigStore
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.plugins import Plugins
from hydra.plugins.sweeper import Sweeper
from hydra.types import HydraContext, TaskFunction
from omegaconf import DictConfig

log = logging.getLogger(__name__)


@dataclass
class StudySweeperConf:
    _target_: str = "hydra_plugins.torchrl_bail_study.study_sweeper.StudySweeper"
    study: str = "???"                    #: a declared study's name or the path of a study's YAML file
    step: int = 1                         #: which of its steps (1 is the first, as `study list` numbers them)
    max_batch_size: int | None = None  #: jobs handed to the launcher at once (null: the whole step)


ConfigStore.instance().store(group="hydra/sweeper", name="study", node=StudySweeperConf, provider="torchrl_bail")


class StudySweeper(Sweeper):
    """Launches the jobs of step ``step`` of ``study`` that are not done yet, in the study's order, each with the
    command line's overrides after its own; a failed job fails the sweep once every job of its batch has ended."""

    def __init__(self, study: str, step: int, max_batch_size: int | None = None) -> None:
        super().__init__()
        self.study, self.step, self.max_batch_size = study, int(step), max_batch_size
        self.hydra_context: HydraContext | None = None
        self.config: DictConfig | None = None
        self.launcher = None

    def setup(self, *, hydra_context: HydraContext, task_function: TaskFunction, config: DictConfig) -> None:
        self.hydra_context, self.config = hydra_context, config
        self.launcher = Plugins.instance().instantiate_launcher(hydra_context=hydra_context,
                                                               task_function=task_function, config=config)

    def sweep(self, arguments: list[str]) -> Any:
        from torchrl_bail.study.declaration import StudyError, load_study
        from torchrl_bail.study.sweeps import finished

        assert self.config is not None and self.hydra_context is not None and self.launcher is not None
        swept = [o.input_line for o in OverridesParser.create().parse_overrides(arguments) if o.is_sweep_override()]
        if swept:
            raise StudyError(f"a study's jobs are its declaration's; {swept[0]!r} sweeps (give one value)")
        study = load_study(self.study)
        if not 1 <= self.step <= len(study.steps):
            raise StudyError(f"study {study.name} has steps 1-{len(study.steps)}, not {self.step}")
        step = study.steps[self.step - 1]
        command = str(self.config.hydra.job.name)
        if step.command != command:
            raise StudyError(f"step {self.step} of study {study.name} runs {step.command}, not {command}")
        loader = self.hydra_context.config_loader
        pending, done = [], 0
        for job in step.jobs:
            overrides = [*job.args, *arguments]
            if finished(command, loader.load_sweep_config(self.config, overrides)):
                done += 1
            else:
                pending.append((job, overrides))
        log.info("study %s, step %d (%s): %d of %d jobs done, launching %d", study.name, self.step, step.name, done,
                 len(step.jobs), len(pending))
        size = self.max_batch_size or max(len(pending), 1)
        returns = []
        for start in range(0, len(pending), size):
            chunk = pending[start:start + size]
            for job, _ in chunk:
                log.info("  %s", job.name)
            results = self.launcher.launch([overrides for _, overrides in chunk], initial_job_idx=start)
            returns.append(results)
            for result in results:
                _ = result.return_value  # re-raises a failed job's exception
        return returns

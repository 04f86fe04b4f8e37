"""Hydra registration: the schemas in Hydra's ConfigStore (:func:`register_schemas`), the config directory with the
resolvers ``conf/config.yaml`` uses (:func:`config_dir`) and the config groups' options (:func:`group_options`, the
``--help`` list). Torch-free.
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf

from torchrl_bail.configuration.algo_schemas import ALGO_SCHEMAS
from torchrl_bail.configuration.batch_schemas import BATCH_SCHEMAS
from torchrl_bail.configuration.config import Config
from torchrl_bail.configuration.run_dirs import batch_label, run_dir_suffix

__all__ = ["config_dir", "group_options", "register_schemas"]



def register_schemas() -> None:
    """Stores the schemas in Hydra's ConfigStore: ``base_config_schema``, ``algo/base_<name>_schema`` and
    ``batch/base_<recipe>_schema`` (idempotent; :func:`torchrl_bail.config_dir` calls it)."""
    from hydra.core.config_store import ConfigStore

    cs = ConfigStore.instance()
    cs.store(name="base_config_schema", node=Config)
    for name, schema in ALGO_SCHEMAS.items():
        cs.store(group="algo", name=f"base_{name}_schema", node=schema)
    for recipe, schema in BATCH_SCHEMAS.items():
        cs.store(group="batch", name=f"base_{recipe}_schema", node=schema)
    _register_joblib_launcher(cs)


def _register_joblib_launcher(cs) -> None:
    """``hydra/launcher=joblib``: local parallel sweeps through the hydra-joblib-launcher plugin
    (``pip install -e ".[parallel]"``), stored over the plugin's own node with 2 jobs at once by default (the plugin's
    10 would hold ten 10^6-transition batches in memory on a laptop)::

        python -m torchrl_bail.train -m hydra/launcher=joblib hydra.launcher.n_jobs=4 +exp=hopper_ddpg05 seed=1,2,3,4

    Jobs run side by side in worker processes; each sets torch's thread count to cores // n_jobs (at least 1; an
    explicit ``threads`` config key wins), so n_jobs x threads never exceeds the cores. Jobs that need the same batch
    wait on its lock and one of them collects it. Memory: a paper-scale BAIL job needs a few GiB (Humanoid ~8).

    A node in the ConfigStore, not a yaml file: a file named like the plugin's node is "validated against ConfigStore
    schema with the same name", which Hydra warns about on every composition. The plugin's module is imported first,
    so that its own registration never comes after this one. Without the plugin: nothing is stored."""
    from dataclasses import dataclass

    try:
        from hydra_plugins.hydra_joblib_launcher.config import JobLibLauncherConf
    except ImportError:
        return

    @dataclass
    class TwoJobsJoblibLauncherConf(JobLibLauncherConf):
        n_jobs: int = 2

    cs.store(group="hydra/launcher", name="joblib", node=TwoJobsJoblibLauncherConf, provider="torchrl_bail")


def group_options(conf: Path | None = None) -> dict[str, list[str]]:
    """The options of each config group: ``{group: [option, ...]}`` from the yaml files under ``conf/`` (default:
    :func:`config_dir`), without Hydra's own groups (``hydra/...``) and the files named
    ``_<name>`` (parts other files include).

    Examples:
        >>> group_options()["algo"][:3]
        ['bail', 'bc', 'bcq']
    """
    conf = Path(conf) if conf is not None else config_dir()
    groups: dict[str, list[str]] = {}
    for path in sorted(conf.rglob("*.yaml")):
        group = path.parent.relative_to(conf).as_posix()
        if group != "." and not group.startswith("hydra") and not path.stem.startswith("_"):
            groups.setdefault(group, []).append(path.stem)
    return groups


#: what ``--help`` opens with, per command (Hydra's job name): the commands a user types first, then what ``+exp=`` and
#: ``preset=`` choose; Hydra's own help (the groups' options, the composed config) follows
COMMAND_HELP = {
    "train": """\
python -m torchrl_bail.train: train one of the paper's algorithms (BAIL by default, algo=...) on an offline batch,
generating and caching the batch first if it is not cached yet.

  python -m torchrl_bail.train +exp=hopper_ddpg05 preset=quick seed=1   # BAIL end to end, under an hour on 2 cores
  python -m torchrl_bail.train +exp=hopper_ddpg05 algo=bc seed=2        # another algorithm, the paper's scale
  python -m torchrl_bail.train -m +exp=hopper_ddpg05 seed=1,2,3         # a sweep of seeds (multirun)
  python -m torchrl_bail.train dataset=path/to/d4rl.hdf5 env=hopper     # your own data instead of a generated batch

+exp=<env>_<batch> picks the environment and the batch (the exp group below, e.g. walker_sac, hopper_med_stoch);
batch.index=2 the second behaviour seed (B2). preset=quick|study|paper scales the batch and the schedules (paper, the
default: 10^6 transitions). threads=1 by default (threads=N opts in to more). Docs: docs/getting-started.md.
The README's two commands: pip install torch==2.13.0 && pip install -e . && python -m torchrl_bail.train
+exp=hopper_ddpg05 preset=quick seed=1 (the first example above); pip install -e ".[test]" && python -m pytest -q.
""",
    "collect": """\
python -m torchrl_bail.collect: make a batch (train the behaviour agent online, keep its data) into the cache.

  python -m torchrl_bail.collect +exp=hopper_ddpg05 preset=quick   # a 50k-transition DDPG sigma=0.5 batch
  python -m torchrl_bail.collect +exp=walker_med_stoch             # trains the shared SAC run first if needed
  python -m torchrl_bail.collect --list                            # the cached batches

+exp=<env>_<batch> picks the environment and the batch (the exp group below); batch.index=2 the second behaviour
seed (B2). preset=quick|study|paper sets the batch's size (paper, the default: 10^6 transitions). Docs:
docs/guides/batch-catalogue.md.
""",
}


def _command_help(job_name: str) -> str:
    """The opening of ``--help`` for the command named ``job_name`` (:data:`COMMAND_HELP`; the ``command_help``
    resolver of ``conf/config.yaml``'s ``hydra.help.header``), Hydra's plain line for any other."""
    return COMMAND_HELP.get(job_name, f"{job_name} is powered by Hydra.\n")


def _groups_help() -> str:
    """The ``--help`` lines of :func:`group_options`: the ``config_groups`` resolver of ``conf/config.yaml``'s
    ``hydra.help.template`` (Hydra's own list also shows the schemas, ``base_<name>_schema``, and the parts)."""
    return "\n".join(f"{group}: {', '.join(options)}" for group, options in sorted(group_options().items()))


def config_dir() -> Path:
    """Directory holding the Hydra configs.

    An installed wheel ships them as ``torchrl_bail/conf``; a source checkout (editable install) keeps
    them at the repository's top-level ``conf/``. The typed schemas the yaml files name
    (:mod:`torchrl_bail.configuration.algo_schemas`,
    :mod:`torchrl_bail.configuration.batch_schemas`) are registered with Hydra's ConfigStore on the way, and the
    resolvers
    ``conf/config.yaml`` uses (:func:`run_dir_suffix`, :func:`batch_label`; ``config_groups``, :func:`group_options`
    for ``--help``).
    """
    register_schemas()
    for name, resolver in (("run_dir_suffix", run_dir_suffix), ("batch_label", batch_label),
                           ("config_groups", _groups_help), ("command_help", _command_help)):
        if not OmegaConf.has_resolver(name):
            OmegaConf.register_new_resolver(name, resolver)
    packaged = Path(__file__).resolve().parents[1] / "conf"
    if packaged.is_dir():
        return packaged
    repo = Path(__file__).resolve().parents[3] / "conf"
    if repo.is_dir():
        return repo
    raise FileNotFoundError(
        f"torchrl_bail configs not found: looked in {packaged} and {repo}. Reinstall the package."
    )

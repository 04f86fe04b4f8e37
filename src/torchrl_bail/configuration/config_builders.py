"""Typed config nodes built from the yaml files, for library code and tests that configure without the command line:
:func:`algo_config` / :func:`checked_algo_config` (an ``algo`` node over ``conf/algo/<name>.yaml``) and
:func:`collection_config` (what collecting a batch reads, a :class:`CollectionConfig`). Torch-free.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Optional  # noqa: UP035 -- OmegaConf reads these annotations at runtime

from omegaconf import MISSING, DictConfig, OmegaConf

from torchrl_bail.configuration.algo_schemas import ALGO_SCHEMAS, blocks_with
from torchrl_bail.configuration.batch_schemas import BATCH_SCHEMAS
from torchrl_bail.configuration.config import Checked, EnvConfig, validate_config
from torchrl_bail.configuration.hydra_setup import config_dir
from torchrl_bail.core.errors import ConfigError

__all__ = ["CollectionConfig", "algo_config", "checked_algo_config", "collection_config", "run_length_overrides",
           "tiny_run_overrides"]



@dataclass
class CollectionConfig(Checked):
    """What collecting a batch reads (:mod:`torchrl_bail.behaviour`, :mod:`torchrl_bail.data.cache`): the env, the
    batch recipe and where batches live; :func:`collection_config` makes one, every rule checked."""

    env: EnvConfig = MISSING
    batch: Any = MISSING       # one of BATCH_SCHEMAS
    data_dir: Optional[str] = None


def collection_config(cfg: Any) -> CollectionConfig:
    """The typed :class:`CollectionConfig` of ``cfg`` (a composed config, its ``env``/``batch``/``data_dir`` nodes as a
    mapping, or a :class:`CollectionConfig`): ``batch`` typed by the schema of its ``recipe``, every rule checked
    (the first failure raises :class:`ConfigError` naming ``env.<key>`` or ``batch.<key>``). A node the command line
    composed comes back with the values it has; a plain mapping must give every value (no defaults are assumed).

    Examples:
        >>> from hydra import compose, initialize_config_dir
        >>> with initialize_config_dir(str(config_dir()), version_base="1.3"):
        ...     cfg = compose("config", overrides=["+exp=hopper_ddpg05"])
        >>> collection = collection_config(cfg)
        >>> type(collection.batch).__name__, collection.batch.agent.tau, collection.env.id
        ('DDPGBatchConfig', 0.005, 'Hopper-v5')
        >>> collection_config({"env": cfg.env, "batch": {**cfg.batch, "recipe": "dqn"}})
        Traceback (most recent call last):
        ...
        torchrl_bail.core.errors.ConfigError: config key batch.recipe = 'dqn': expected one of ddpg, sac, sac_exec
    """
    if isinstance(cfg, CollectionConfig):
        return cfg
    get = cfg.get if hasattr(cfg, "get") else lambda key, default=None: getattr(cfg, key, default)
    recipe = (get("batch") or {}).get("recipe")
    schema = BATCH_SCHEMAS.get(recipe)
    if schema is None:
        raise ConfigError("batch.recipe", recipe, f"one of {', '.join(BATCH_SCHEMAS)}")
    node = OmegaConf.structured(CollectionConfig(env=OmegaConf.structured(EnvConfig),
                                                 batch=OmegaConf.structured(schema)))
    try:
        node = OmegaConf.merge(node, {"env": get("env"), "batch": get("batch"), "data_dir": get("data_dir")})
    except Exception as err:  # noqa: BLE001 - OmegaConf's type errors: one line naming the key
        key = getattr(err, "full_key", None) or "batch"
        raise ConfigError(key, getattr(err, "value", None), str(getattr(err, "msg", err)).splitlines()[0]) from None
    validate_config(node)
    return OmegaConf.to_object(node)


def algo_config(name: str, /, **overrides: Any) -> DictConfig:
    """The ``algo`` node of ``algo=<name>``: the values of ``conf/algo/<name>.yaml`` typed by their schema, with
    ``overrides`` applied and every rule checked, as the command line does.

    The yaml file is the one place an algorithm's defaults live; this is how library code and tests configure an
    algorithm without the command line. A key may be dotted (``**{"policy.hidden": [8]}``) and a dict merges into
    its block (``vae={"hidden": [16]}`` keeps the VAE's other values).

    Examples:
        >>> cfg = algo_config("bcq", batch_size=8, vae={"hidden": [16]})
        >>> cfg.tau, cfg.batch_size, list(cfg.vae.hidden), cfg.vae.lr
        (0.005, 8, [16], 0.001)
        >>> algo_config("bail", **{"selection.percentile": 1.5})
        Traceback (most recent call last):
        ...
        torchrl_bail.core.errors.ConfigError: config key algo.selection.percentile = 1.5: expected a fraction in (0, 1]
    """
    node = _algo_defaults(name)
    for key, value in overrides.items():
        OmegaConf.update(node, key, value, merge=True)
    return _checked_algo(node)


def checked_algo_config(name: str, config: Any) -> DictConfig:
    """``config`` (an ``algo`` node: a DictConfig or a plain nested mapping) over the defaults of
    ``conf/algo/<name>.yaml``, as a fresh node typed by the schema of ``name``; the first failed rule raises
    :class:`ConfigError` naming ``algo.<key>``. A complete node (the command line's) comes back as it is; keys a
    mapping leaves out take the yaml's values."""
    if isinstance(config, DictConfig):
        config = OmegaConf.to_container(config, resolve=True)
    if config.get("name", name) != name:
        raise ConfigError("algo.name", config["name"], f"{name} (the config of the algorithm being built)")
    return _checked_algo(OmegaConf.merge(_algo_defaults(name), config))


def _algo_defaults(name: str) -> DictConfig:
    try:
        schema = ALGO_SCHEMAS[name]
    except KeyError:
        raise ConfigError("algo.name", name, f"one of {', '.join(ALGO_SCHEMAS)}") from None
    values = OmegaConf.load(config_dir() / "algo" / f"{name}.yaml")
    values.pop("defaults", None)  # it names ``schema``
    return OmegaConf.merge(OmegaConf.structured(schema), values)


def _checked_algo(node: DictConfig) -> DictConfig:
    try:
        validate_config(node)
    except ConfigError as err:
        raise err.under("algo") from None
    return node


def run_length_overrides(name: str, updates: int, evaluations: Optional[int] = None) -> list[str]:
    """The command-line overrides that make a run of algorithm ``name`` last ``updates`` mini-batches of its yaml's
    size: ``algo.epochs`` (epochs count ``conf/config.yaml``'s ``samples_per_epoch``), and, given ``evaluations``,
    ``eval.every_epochs`` for an evaluation every ``1 / evaluations`` of the run.

    Examples:
        >>> run_length_overrides("bcq", 10**5, evaluations=20)  # batches of 100
        ['algo.epochs=10', 'eval.every_epochs=0.5']
        >>> run_length_overrides("td3bc", 10**5, evaluations=20)  # batches of 256
        ['algo.epochs=25.6', 'eval.every_epochs=1.28']
    """
    epochs = updates * algo_config(name).batch_size / OmegaConf.load(config_dir() / "config.yaml").samples_per_epoch
    return [f"algo.epochs={epochs:g}"] + ([f"eval.every_epochs={epochs / evaluations:g}"] if evaluations else [])


def tiny_run_overrides(name: str, updates: int, hidden: Sequence[int], evaluations: Optional[int] = None) -> list[str]:
    """The command-line overrides of a run of algorithm ``name`` that takes seconds on a tiny batch: ``algo.epochs``
    for ``updates`` mini-batches of its yaml's size (at ``conf/config.yaml``'s ``samples_per_epoch``), every network
    :func:`~torchrl_bail.configuration.algo_schemas.blocks_with` a ``hidden`` key ``hidden`` wide, its registry entry's
    ``tiny``, and, given ``evaluations``, an evaluation every ``1 / evaluations`` of the run (its length:
    :func:`run_length_overrides`). The contract suite's tiny runs (``tests/_contract.py``: 5 updates) and the kill
    drill (``benchmarks/kill_drill.py``: 300) are this at two lengths.

    Examples:
        >>> tiny_run_overrides("bear", 5, [16, 16])  # doctest: +NORMALIZE_WHITESPACE
        ['algo.epochs=0.0005', 'algo.vae.hidden=[16,16]', 'algo.critic.hidden=[16,16]',
         'algo.actor.hidden=[16,16]', 'algo.warm_start_updates=2']
        >>> tiny_run_overrides("bc", 300, [32, 32], evaluations=10)
        ['algo.epochs=0.3', 'algo.policy.hidden=[32,32]', 'eval.every_epochs=0.03']
    """
    if ALGO_SCHEMAS[name].tiny is None:
        schema = ALGO_SCHEMAS[name]
        raise ValueError(f"{schema.__name__}.tiny is not stated: the algo keys a run of a few updates needs besides "
                         f"small networks and its length, () if none (state it on the schema in {schema.__module__})")
    length, *evaluation = run_length_overrides(name, updates, evaluations)
    width = "[" + ",".join(str(int(h)) for h in hidden) + "]"
    overrides = [length, *(f"algo.{block}.hidden={width}" for block in blocks_with(name, "hidden")),
                 *(f"algo.{override}" for override in ALGO_SCHEMAS[name].tiny)]
    return overrides + evaluation

"""The rule language of the typed schemas, the top-level :class:`Config` and :func:`validate_config`.

Each group's yaml file names its schema in its defaults list (Hydra 1.3 "structured config schema")::

    # conf/algo/bail.yaml
    defaults:
      - base_bail_schema
      - _self_

The yaml files hold every value (one default per constant, with its comment); a schema here holds the types and
the allowed ranges, written with the rules of this module (:func:`positive`, :func:`one_of`, ...). The
groups' schemas live beside what they configure: each algorithm's in its module of :mod:`torchrl_bail.algorithms`,
each batch recipe's in its module of :mod:`torchrl_bail.behaviour`, read torch-free into their registries,
:mod:`torchrl_bail.configuration.algo_schemas` and :mod:`torchrl_bail.configuration.batch_schemas`
(:mod:`torchrl_bail.configuration.schema_reader`);
:mod:`torchrl_bail.configuration.hydra_setup` registers them with Hydra. Hydra rejects a wrong type (``seed=abc``) or an
unknown key (``algo.foo=1``) while it composes;
:func:`validate_config` then instantiates every schema node bottom-up, so each ``__post_init__`` range check runs
and the first failure raises :class:`ConfigError` naming the full key and what was expected. The top level checks
what spans groups: env/batch combinations from the catalogue, ``returns.augment=oracle``, and paths.

This module imports only Hydra/OmegaConf, so a bad command line ends in about a second, before torch loads; the
command-line front that turns its errors into one line is :mod:`torchrl_bail.cli`.

Examples:
    >>> from hydra import compose, initialize_config_dir
    >>> from torchrl_bail import config_dir
    >>> from torchrl_bail.configuration.config import validate_config
    >>> with initialize_config_dir(str(config_dir()), version_base="1.3"):
    ...     cfg = compose("config", overrides=["+exp=hopper_ddpg05", "algo.selection.percentile=1.5"])
    >>> validate_config(cfg)
    Traceback (most recent call last):
    ...
    torchrl_bail.core.errors.ConfigError: config key algo.selection.percentile = 1.5: expected a fraction in (0, 1]
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional  # noqa: UP035 -- OmegaConf reads these annotations at runtime

from omegaconf import MISSING, DictConfig, OmegaConf

from torchrl_bail.core.errors import ConfigError

__all__ = ["COMPILE_MODES", "Config", "ConfigError", "DDPG_ENVS", "EnvConfig", "RESUME_MODES",
           "is_compile_setting", "option_name", "registry_name", "run_only", "validate_config"]

#: the envs the paper made DDPG batches for (docs: The batch catalogue)
DDPG_ENVS = ("hopper", "walker", "halfcheetah")



# ---------------------------------------------------------------------------------------------------------------
# field rules: a value's type comes from the annotation, its range from the rule (checked in __post_init__)
# ---------------------------------------------------------------------------------------------------------------


def rule(check: Callable[[Any], bool], expected: str):
    return field(default=MISSING, metadata={"check": check, "expected": expected})


def run_only(rule=None):
    """Marks a top-level key as run-only: it changes how a run reports, where it finds its files or how it executes,
    never its numbers. The one mark behind :data:`RUN_ONLY_KEYS` (a checkpoint resumes across them, the report never
    separates runs by them) and the run directory's name (:func:`run_dir_excluded_keys`)."""
    metadata = {} if rule is None else dict(rule.metadata)
    return field(default=MISSING, metadata={**metadata, "run_only": True})


def is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and not math.isnan(v)


def positive(expected: str = "a positive number"):
    return rule(lambda v: v > 0, expected)


def at_least(low: int, expected: str | None = None):
    return rule(lambda v: v >= low, expected or f"an integer >= {low}")


def non_negative(expected: str = "a number >= 0"):
    return rule(lambda v: v >= 0, expected)


def discount():
    return rule(lambda v: 0 < v <= 1, "a discount in (0, 1]")


def fraction():
    return rule(lambda v: 0 < v <= 1, "a fraction in (0, 1]")


def one_of(*choices: Any):
    """A closed set of values; ``metadata["choices"]`` holds them (the configuration reference lists them)."""
    return field(default=MISSING, metadata={"check": lambda v: v in choices, "expected": " | ".join(map(str, choices)),
                                            "choices": choices})


def option_name(group: str):
    """A key that names its own group option (``env.name`` is ``hopper`` in ``conf/env/hopper.yaml``). Any string is
    accepted, so a yaml file of your own may add an option; ``metadata["option_of"]`` names the group, whose shipped
    options the configuration reference lists as the allowed values."""
    return field(default=MISSING, metadata={"option_of": group, "expected": f"the name of a conf/{group}/ option"})


def layers():
    return rule(lambda v: len(v) > 0 and all(h > 0 for h in v), "a list of positive layer widths, e.g. [400, 300]")


def learning_rate():
    return positive("a positive learning rate")


def registry_name(registry: str):
    """A key holding its schema's name in a registry (``algo.name`` in
    :data:`~torchrl_bail.configuration.algo_schemas.ALGO_SCHEMAS`, ``batch.recipe`` in
    :data:`~torchrl_bail.configuration.batch_schemas.BATCH_SCHEMAS`), checked by :meth:`Checked._registered_as`."""
    return field(default=MISSING, metadata={"registry": registry, "expected": f"this schema's name in {registry}"})


class Checked:
    """Runs every field's rule, then :meth:`check` (rules that span fields), on instantiation."""

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            rule = f.metadata.get("check")
            if rule is not None and value is not None and not rule(value):
                raise ConfigError(f.name, value, f.metadata["expected"])
        self.check()

    def check(self) -> None:
        """Cross-field rules; raise :class:`ConfigError` with the (relative) key."""

    def _registered_as(self, key: str, registry: dict[str, type], hint: str) -> None:
        """``key`` must hold the name this schema has in ``registry`` (its module's registry)."""
        name = next(name for name, schema in registry.items() if schema is type(self))
        if getattr(self, key) != name:
            raise ConfigError(key, getattr(self, key), f"{name} ({hint})")

    def _ordered(self, low: str, high: str) -> None:
        if not getattr(self, low) < getattr(self, high):
            raise ConfigError(low, getattr(self, low), f"less than {high} = {getattr(self, high)}")


# ---------------------------------------------------------------------------------------------------------------
# env (conf/env)
# ---------------------------------------------------------------------------------------------------------------


@dataclass
class EnvConfig(Checked):
    name: str = option_name("env")
    id: str = MISSING
    max_episode_steps: Optional[int] = at_least(1, "a positive integer (or null for the env's default)")
    mediocre_threshold: int = MISSING


# ---------------------------------------------------------------------------------------------------------------
# the top level (conf/config.yaml)
# ---------------------------------------------------------------------------------------------------------------


@dataclass
class ReturnsConfig(Checked):
    gamma: float = discount()
    horizon: int = at_least(1)
    augment: str = one_of("gain", "none", "oracle")


@dataclass
class EvalConfig(Checked):
    episodes: int = at_least(1, "a positive integer")
    every_epochs: float = positive("a positive number of epochs")
    max_steps: int = at_least(1, "a positive integer")
    final_window: int = at_least(1, "a positive integer")
    snapshots: int = at_least(0, "an integer >= 0 (0: none)")


@dataclass
class LoggerConfig(Checked):
    backend: str = one_of("csv", "tensorboard", "wandb", "mlflow")
    project: str = MISSING
    group: Optional[str] = MISSING
    name: Optional[str] = MISSING


@dataclass
class CheckpointConfig(Checked):
    enabled: bool = MISSING
    every_minutes: Optional[float] = rule(lambda v: v is None or v > 0,  # noqa: UP045 -- read by OmegaConf
                                           "null or a positive number of minutes")


#: the ``compile`` key's values besides ``false``: ``true`` (inductor's default mode; on a GPU the whole update is
#: also captured in one CUDA graph) or a :func:`torch.compile` mode (:meth:`torchrl_bail.algorithms.Algorithm.compile`)
COMPILE_MODES = (True, "default", "reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs")


def is_compile_setting(v: Any) -> bool:
    """Whether ``v`` is a value of the ``compile`` key: ``False``, ``True`` or one of :data:`COMPILE_MODES`."""
    return isinstance(v, bool) or (isinstance(v, str) and v in COMPILE_MODES[1:])


def _seed_list(v: Any) -> bool:
    """``seeds``: null, a count ``S >= 1`` or a non-empty list of distinct integers ``>= 0``."""
    if v is None:
        return True
    if isinstance(v, bool):
        return False
    if isinstance(v, int):
        return v >= 1
    return (isinstance(v, (list, tuple)) and len(v) > 0 and len(set(v)) == len(v)
            and all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in v))


def _device_name(v: str) -> bool:
    return v in ("cpu", "cuda", "auto") or (v.startswith("cuda:") and v[5:].isdigit())


#: the ``resume`` key's words; any other value must be an existing run directory (:mod:`torchrl_bail.training.resume`)
RESUME_MODES = ("auto", "true", "false")
_RESUME_EXPECTED = " | ".join(RESUME_MODES) + " | an existing run directory"


def _resume_rule():
    """``resume``'s documentation (checked in :meth:`Config.check`, where a path is looked up): one of
    :data:`RESUME_MODES`, or else a run directory (``metadata["or"]``)."""
    return field(default=MISSING, metadata={"expected": _RESUME_EXPECTED, "choices": RESUME_MODES,
                                            "or": "an existing run directory"})


@dataclass
class Config(Checked):
    env: EnvConfig = MISSING
    batch: Any = MISSING       # one of batch_schemas.BATCH_SCHEMAS, chosen by the batch yaml's defaults
    algo: Any = MISSING        # one of algo_schemas.ALGO_SCHEMAS
    seed: int = non_negative("an integer >= 0")
    seeds: Any = rule(_seed_list, "null, a count S >= 1 (seeds seed..seed+S-1) or a list of distinct seeds >= 0, "
                       "e.g. [1,2,3]")
    # run-only: numbers change only across devices
    device: str = run_only(rule(_device_name, "cpu | cuda | cuda:N | auto"))
    # not a run-only key: compiled kernels round differently, so compile=true is another run (docs: Compiled updates)
    compile: Any = rule(is_compile_setting, "false | true | " + " | ".join(COMPILE_MODES[1:]))
    data_dir: Optional[str] = run_only()
    dataset: Optional[str] = MISSING
    progress: bool = run_only()
    resume: str = run_only(_resume_rule())   # auto | true | false | <run_dir> (see torchrl_bail.training.resume)
    threads: Optional[int] = run_only(rule(lambda v: v is None or v >= 1,  # noqa: UP045
                                            "null or a number of threads >= 1"))
    returns: ReturnsConfig = MISSING
    samples_per_epoch: int = at_least(1, "a positive integer")
    eval: EvalConfig = MISSING
    logger: LoggerConfig = run_only()
    checkpoint: CheckpointConfig = run_only()

    def check(self) -> None:
        if self.dataset is not None:
            if not Path(self.dataset).expanduser().exists():
                raise ConfigError("dataset", self.dataset, "an existing D4RL .hdf5 file, Minari dataset folder or "
                                  "native batch folder (relative paths start at the launch directory)")
        else:
            if self.batch.recipe == "ddpg" and self.env.name not in DDPG_ENVS:
                raise ConfigError("batch", self.batch.kind, f"a batch that exists for env={self.env.name}: DDPG "
                                  f"batches are made for {', '.join(DDPG_ENVS)} only; use sac, med_*, opt_*")
            if self.returns.augment == "oracle" and not self.batch.oracle.enabled:
                raise ConfigError("returns.augment", "oracle", "gain | none, or oracle together with "
                                  "batch.oracle.enabled=true (oracle returns come from an oracle batch's real "
                                  "continuations)")
        if self.data_dir is not None and Path(self.data_dir).expanduser().is_file():
            raise ConfigError("data_dir", self.data_dir, "a directory (or null), not a file")
        if self.device.startswith("cuda"):
            import torch  # only for this question

            if not torch.cuda.is_available():
                raise ConfigError("device", self.device, "a CUDA device, but torch sees none (use device=cpu or auto)")
        if self.resume.lower() not in RESUME_MODES and not Path(self.resume).expanduser().is_dir():
            raise ConfigError("resume", self.resume, _RESUME_EXPECTED)


# ---------------------------------------------------------------------------------------------------------------
# validation (the command-line front that reports its errors: torchrl_bail.cli)
# ---------------------------------------------------------------------------------------------------------------


def validate_config(cfg: DictConfig) -> None:
    """Instantiates every schema node of ``cfg`` (children first): the first failed rule raises
    :class:`ConfigError` with its full key. Nodes without a schema (plain dicts) are not checked."""
    from omegaconf.errors import MissingMandatoryValue

    def visit(node: DictConfig) -> None:
        for key in node.keys():
            child = node._get_node(key)
            if isinstance(child, DictConfig) and not child._is_missing() and not child._is_none():
                visit(child)
        schema = OmegaConf.get_type(node)
        if not dataclasses.is_dataclass(schema):
            return
        known = [f.name for f in dataclasses.fields(schema)]
        for key in node.keys():
            if key not in known and not (node._get_parent() is None and key == "hydra"):
                path = node._get_full_key(None)
                raise ConfigError(f"{path}.{key}" if path else str(key), node._get_node(key)._value(),
                                  f"no such key here; known keys: {', '.join(known)}")
        try:
            OmegaConf.to_object(node)
        except ConfigError as err:
            raise err.under(node._get_full_key(None)) from None
        except MissingMandatoryValue as err:
            raise ConfigError(err.full_key, "???", "a value (it has no default)") from None

    visit(cfg)

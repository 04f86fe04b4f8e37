"""Typed schemas of every config group, checked before any work starts.

Each group's yaml file names its schema in its defaults list (Hydra 1.3 "structured config schema")::

    # conf/algo/bail.yaml
    defaults:
      - base_bail_schema
      - _self_

The yaml files hold every value (one default per constant, with its comment); a schema here holds the types and
the allowed ranges. Hydra rejects a wrong type (``seed=abc``) or an unknown key (``algo.foo=1``) while it composes;
:func:`validate_config` then instantiates every schema node bottom-up, so each ``__post_init__`` range check runs
and the first failure raises :class:`ConfigError` naming the full key and what was expected. The top level checks
what spans groups: env/batch combinations from the catalogue, ``returns.augment=oracle``, and paths.

This module imports only Hydra/OmegaConf, so a bad command line ends in about a second, before torch loads; the
command-line front that turns its errors into one line is :mod:`torchrl_bail.cli`.

Examples:
    >>> from hydra import compose, initialize_config_dir
    >>> from torchrl_bail import config_dir
    >>> with initialize_config_dir(str(config_dir()), version_base="1.3"):
    ...     cfg = compose("config", overrides=["+exp=hopper_ddpg05", "algo.selection.percentile=1.5"])
    >>> validate_config(cfg)
    Traceback (most recent call last):
    ...
    torchrl_bail.errors.ConfigError: config key algo.selection.percentile = 1.5: expected a fraction in (0, 1]
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, List, Optional  # noqa: UP035 -- OmegaConf reads these annotations at runtime

from omegaconf import MISSING, DictConfig, OmegaConf

from torchrl_bail.errors import CommandLineError, ConfigError

__all__ = ["ALGO_SCHEMAS", "algo_config", "checked_algo_config", "config_dir", "BATCH_SCHEMAS", "COMPILE_MODES",
           "CollectionConfig", "collection_config", "DDPG_ENVS", "RESUME_MODES", "RUN_DIR_KEYS", "RUN_ONLY_KEYS",
           "CommandLineError", "Config", "ConfigError", "batch_label", "group_options", "is_compile_setting",
           "option_name", "register_schemas", "registry_name", "run_dir_excluded_keys", "run_dir_suffix", "run_only",
           "validate_config"]

#: the envs the paper made DDPG batches for (docs: The batch catalogue)
DDPG_ENVS = ("hopper", "walker", "halfcheetah")


# ---------------------------------------------------------------------------------------------------------------
# field rules: a value's type comes from the annotation, its range from the rule (checked in __post_init__)
# ---------------------------------------------------------------------------------------------------------------


def _rule(check: Callable[[Any], bool], expected: str):
    return field(default=MISSING, metadata={"check": check, "expected": expected})


def run_only(rule=None):
    """Marks a top-level key as run-only: it changes how a run reports, where it finds its files or how it executes,
    never its numbers. The one mark behind :data:`RUN_ONLY_KEYS` (a checkpoint resumes across them, the report never
    separates runs by them) and the run directory's name (:func:`run_dir_excluded_keys`)."""
    metadata = {} if rule is None else dict(rule.metadata)
    return field(default=MISSING, metadata={**metadata, "run_only": True})


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and not math.isnan(v)


def positive(expected: str = "a positive number"):
    return _rule(lambda v: v > 0, expected)


def at_least(low: int, expected: str | None = None):
    return _rule(lambda v: v >= low, expected or f"an integer >= {low}")


def non_negative(expected: str = "a number >= 0"):
    return _rule(lambda v: v >= 0, expected)


def discount():
    return _rule(lambda v: 0 < v <= 1, "a discount in (0, 1]")


def fraction():
    return _rule(lambda v: 0 < v <= 1, "a fraction in (0, 1]")


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
    return _rule(lambda v: len(v) > 0 and all(h > 0 for h in v), "a list of positive layer widths, e.g. [400, 300]")


def learning_rate():
    return positive("a positive learning rate")


def registry_name(registry: str):
    """A key holding its schema's name in a registry of this module (``algo.name`` in :data:`ALGO_SCHEMAS`,
    ``batch.recipe`` in :data:`BATCH_SCHEMAS`), checked by :meth:`_Checked._registered_as`."""
    return field(default=MISSING, metadata={"registry": registry, "expected": f"this schema's name in {registry}"})


class _Checked:
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
        """``key`` must hold the name this schema has in ``registry`` (:data:`ALGO_SCHEMAS`, :data:`BATCH_SCHEMAS`)."""
        name = next(name for name, schema in registry.items() if schema is type(self))
        if getattr(self, key) != name:
            raise ConfigError(key, getattr(self, key), f"{name} ({hint})")

    def _ordered(self, low: str, high: str) -> None:
        if not getattr(self, low) < getattr(self, high):
            raise ConfigError(low, getattr(self, low), f"less than {high} = {getattr(self, high)}")


# ---------------------------------------------------------------------------------------------------------------
# env and batch (conf/env, conf/batch)
# ---------------------------------------------------------------------------------------------------------------


@dataclass
class EnvConfig(_Checked):
    name: str = option_name("env")
    id: str = MISSING
    max_episode_steps: Optional[int] = at_least(1, "a positive integer (or null for the env's default)")
    mediocre_threshold: int = MISSING


@dataclass
class OracleConfig(_Checked):
    enabled: bool = MISSING
    horizon: int = at_least(2)
    keep: int = at_least(1, "a positive number of steps kept per episode")
    gamma: float = discount()

    def check(self) -> None:
        if self.horizon <= self.keep:
            raise ConfigError("horizon", self.horizon, f"an episode length larger than keep = {self.keep}")


@dataclass
class BatchConfig(_Checked):
    kind: str = option_name("batch")
    recipe: str = registry_name("BATCH_SCHEMAS")
    index: int = at_least(1, "an integer >= 1 (B1, B2, ...)")
    seed: Optional[int] = non_negative("null or an integer >= 0")
    steps: int = positive("a positive number of transitions")
    oracle: OracleConfig = MISSING
    # how a batch is collected, never what it holds (outside the recipe hash): conf/batch/_collection.yaml
    checkpoint_every_s: Optional[float] = positive("seconds of work between collection checkpoints, or null (never)")
    checkpoint_every_steps: Optional[int] = at_least(1, "env steps between collection checkpoints, or null")
    lock_stale_after_s: float = positive("seconds after which another host's lock without heartbeat is stale")
    heartbeat_every_s: float = positive("seconds between heartbeats of this job's locks and scratch directories")

    def check(self) -> None:
        self._registered_as("recipe", BATCH_SCHEMAS, "the recipe of this batch schema")


@dataclass
class DDPGAgentConfig(_Checked):
    actor_hidden: List[int] = layers()
    critic_hidden: List[int] = layers()
    critic_arch: str = one_of("late_action", "concat")
    actor_lr: float = learning_rate()
    critic_lr: float = learning_rate()
    critic_weight_decay: float = non_negative("a non-negative L2 coefficient")
    gamma: float = discount()
    tau: float = _rule(lambda v: 0 < v <= 1, "a soft-update rate in (0, 1]")
    batch_size: int = at_least(1, "a positive mini-batch size")


@dataclass
class DDPGBatchConfig(BatchConfig):
    sigma: float = non_negative("a non-negative noise std (absolute, not scaled by the action bound)")
    start_steps: int = at_least(0, "a non-negative number of uniformly random steps")
    agent: DDPGAgentConfig = MISSING


@dataclass
class SACAgentConfig(_Checked):
    actor_hidden: List[int] = layers()
    critic_hidden: List[int] = layers()
    actor_lr: float = learning_rate()
    critic_lr: float = learning_rate()
    alpha_lr: float = learning_rate()
    gamma: float = discount()
    polyak: float = _rule(lambda v: 0 <= v < 1, "a target-network decay in [0, 1) (0.995)")
    alpha_init: float = positive("a positive initial entropy coefficient")
    target_entropy: Any = _rule(lambda v: v == "auto" or _is_number(v), "auto or a number")
    log_std_min: float = MISSING
    log_std_max: float = MISSING
    batch_size: int = at_least(1)
    loss_function: str = one_of("l2", "smooth_l1", "l1")
    log_prob_on: str = one_of("tanh", "action")
    start_steps: int = at_least(0)
    train_steps: int = at_least(1)
    eval_every: int = at_least(1)
    eval_episodes: int = at_least(1)

    def check(self) -> None:
        self._ordered("log_std_min", "log_std_max")


@dataclass
class SACBatchConfig(BatchConfig):
    sac: SACAgentConfig = MISSING

    def check(self) -> None:
        super().check()
        if self.steps > self.sac.train_steps:
            raise ConfigError("steps", self.steps, f"at most sac.train_steps = {self.sac.train_steps} (the batch is "
                              "the first steps transitions of the SAC run)")


@dataclass
class SACExecBatchConfig(BatchConfig):
    sac: SACAgentConfig = MISSING
    policy: str = one_of("mediocre", "optimal")
    stochastic: bool = MISSING


# ---------------------------------------------------------------------------------------------------------------
# algorithms (conf/algo)
# ---------------------------------------------------------------------------------------------------------------


@dataclass
class NetConfig(_Checked):
    hidden: List[int] = layers()
    lr: float = learning_rate()


@dataclass
class AlgoConfig(_Checked):
    name: str = registry_name("ALGO_SCHEMAS")
    batch_size: int = at_least(1, "a positive mini-batch size")
    epochs: float = positive("a positive number of epochs (10^6 samples each)")

    def check(self) -> None:
        self._registered_as("name", ALGO_SCHEMAS, "choose the algorithm with algo=<name>")


@dataclass
class EnvelopeConfig(_Checked):
    hidden: List[int] = layers()
    head_scale: float = positive()
    penalty: float = _rule(lambda v: v >= 1, "a penalty K >= 1 (1: ordinary regression)")
    lr: float = learning_rate()
    weight_decay: float = non_negative("a non-negative L2 coefficient")
    val_fraction: float = _rule(lambda v: 0 <= v < 1, "a fraction in [0, 1) (0: no validation, no early stopping)")
    patience: int = at_least(1)


@dataclass
class BAILEnvelopeConfig(EnvelopeConfig):
    batch_size: int = at_least(1)
    epochs: int = at_least(1)
    early_stopping: str = one_of("paper", "as_coded")


@dataclass
class SelectionConfig(_Checked):
    percentile: float = fraction()


@dataclass
class BAILSelectionConfig(SelectionConfig):
    by: str = one_of("envelope", "return")
    nonpositive_value: str = one_of("raw", "project", "error")


@dataclass
class BAILConfig(AlgoConfig):
    envelope: BAILEnvelopeConfig = MISSING
    selection: BAILSelectionConfig = MISSING
    policy: NetConfig = MISSING


@dataclass
class PBAILEnvelopeConfig(EnvelopeConfig):
    validate_every: int = at_least(1)


@dataclass
class PBAILConfig(AlgoConfig):
    envelope: PBAILEnvelopeConfig = MISSING
    selection: SelectionConfig = MISSING
    best_envelope: str = one_of("paper", "as_coded")
    selection_envelope: str = one_of("best", "training")
    v_projection: bool = MISSING
    validation: str = one_of("split", "with_replacement")
    policy: NetConfig = MISSING


@dataclass
class BCConfig(AlgoConfig):
    policy: NetConfig = MISSING


@dataclass
class MARWILConfig(AlgoConfig):
    beta: float = non_negative()
    c2_init: float = positive()
    c2_rate: float = fraction()
    vf_coeff: float = non_negative()
    max_exponent: float = positive()
    eps: float = non_negative()
    value_warmup_updates: int = at_least(0)
    value: NetConfig = MISSING
    policy: NetConfig = MISSING


@dataclass
class VAEConfig(NetConfig):
    latent_per_action: int = at_least(1)
    log_std_min: float = MISSING
    log_std_max: float = MISSING

    def check(self) -> None:
        self._ordered("log_std_min", "log_std_max")


@dataclass
class CriticConfig(NetConfig):
    vmap: Any = _rule(lambda v: v in ("auto", True, False), "auto | true | false")


@dataclass
class TwinCriticVAEConfig(AlgoConfig):
    lmbda: float = _rule(lambda v: 0 <= v <= 1, "a weight in [0, 1]")
    num_samples: int = at_least(1)
    kl_weight: float = non_negative()
    latent_clip: float = positive()
    gamma: float = discount()
    tau: float = _rule(lambda v: 0 < v <= 1, "a soft-update rate in (0, 1]")
    vae: VAEConfig = MISSING
    critic: CriticConfig = MISSING


@dataclass
class BCQConfig(TwinCriticVAEConfig):
    phi: float = non_negative()
    actor: NetConfig = MISSING


@dataclass
class BEARActorConfig(NetConfig):
    noise_clip: float = positive()
    log_std_min: float = MISSING
    log_std_max: float = MISSING


@dataclass
class BEARConfig(TwinCriticVAEConfig):
    kernel_sigma: float = positive()
    num_samples_match: int = at_least(1)
    mmd_stabilizer: float = non_negative()
    epsilon: float = non_negative()
    log_alpha_init: Optional[float] = None
    log_alpha_min: float = MISSING
    log_alpha_max: float = MISSING
    lagrange_lr: float = learning_rate()
    warm_start_updates: int = at_least(0)
    actor: BEARActorConfig = MISSING

    def check(self) -> None:
        super().check()
        self._ordered("log_alpha_min", "log_alpha_max")


@dataclass
class TD3BCConfig(AlgoConfig):
    alpha: float = non_negative("a non-negative weight alpha of the Q term (0: behaviour cloning)")
    policy_noise: float = non_negative("a non-negative std of the target policy's noise, times max_action")
    noise_clip: float = non_negative("a non-negative clip of the target policy's noise, times max_action")
    policy_delay: int = at_least(1, "a positive number of critic updates per actor update")
    gamma: float = discount()
    tau: float = _rule(lambda v: 0 < v <= 1, "a soft-update rate in (0, 1]")
    normalize_observations: bool = MISSING
    normalize_eps: float = positive("a positive number added to the observations' standard deviation")
    actor: NetConfig = MISSING
    critic: CriticConfig = MISSING


@dataclass
class IQLActorConfig(NetConfig):
    log_std_min: float = MISSING
    log_std_max: float = MISSING
    lr_schedule: str = one_of("cosine", "constant")

    def check(self) -> None:
        self._ordered("log_std_min", "log_std_max")


@dataclass
class IQLConfig(AlgoConfig):
    expectile: float = _rule(lambda v: 0 < v < 1, "an expectile in (0, 1) (0.5: mean regression)")
    beta: float = non_negative("a non-negative inverse temperature of the advantage weights")
    # TorchRL's IQLLoss clips the advantage weights at 100 (a constant of its code): the one value it can train
    max_weight: float = _rule(lambda v: v == 100, "100, the clip of exp(beta A) that TorchRL's IQLLoss hard-codes")
    gamma: float = discount()
    tau: float = _rule(lambda v: 0 < v <= 1, "a soft-update rate in (0, 1]")
    reward_scale: str = one_of("locomotion", "none")
    actor: IQLActorConfig = MISSING
    critic: CriticConfig = MISSING
    value: NetConfig = MISSING


# ---------------------------------------------------------------------------------------------------------------
# the top level (conf/config.yaml)
# ---------------------------------------------------------------------------------------------------------------


@dataclass
class ReturnsConfig(_Checked):
    gamma: float = discount()
    horizon: int = at_least(1)
    augment: str = one_of("gain", "none", "oracle")


@dataclass
class EvalConfig(_Checked):
    episodes: int = at_least(1, "a positive integer")
    every_epochs: float = positive("a positive number of epochs")
    max_steps: int = at_least(1, "a positive integer")
    final_window: int = at_least(1, "a positive integer")


@dataclass
class LoggerConfig(_Checked):
    backend: str = one_of("csv", "tensorboard", "wandb", "mlflow")
    project: str = MISSING
    group: Optional[str] = MISSING
    name: Optional[str] = MISSING


@dataclass
class CheckpointConfig(_Checked):
    enabled: bool = MISSING
    every_minutes: Optional[float] = _rule(lambda v: v is None or v > 0,  # noqa: UP045 -- read by OmegaConf
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


#: the ``resume`` key's words; any other value must be an existing run directory (:mod:`torchrl_bail.resume`)
RESUME_MODES = ("auto", "true", "false")
_RESUME_EXPECTED = " | ".join(RESUME_MODES) + " | an existing run directory"


def _resume_rule():
    """``resume``'s documentation (checked in :meth:`Config.check`, where a path is looked up): one of
    :data:`RESUME_MODES`, or else a run directory (``metadata["or"]``)."""
    return field(default=MISSING, metadata={"expected": _RESUME_EXPECTED, "choices": RESUME_MODES,
                                            "or": "an existing run directory"})


@dataclass
class Config(_Checked):
    env: EnvConfig = MISSING
    batch: Any = MISSING       # one of BATCH_SCHEMAS, chosen by the batch yaml's defaults
    algo: Any = MISSING        # one of ALGO_SCHEMAS
    seed: int = non_negative("an integer >= 0")
    seeds: Any = _rule(_seed_list, "null, a count S >= 1 (seeds seed..seed+S-1) or a list of distinct seeds >= 0, "
                       "e.g. [1,2,3]")
    # run-only: numbers change only across devices
    device: str = run_only(_rule(_device_name, "cpu | cuda | cuda:N | auto"))
    # not a run-only key: compiled kernels round differently, so compile=true is another run (docs: Compiled updates)
    compile: Any = _rule(is_compile_setting, "false | true | " + " | ".join(COMPILE_MODES[1:]))
    data_dir: Optional[str] = run_only()
    dataset: Optional[str] = MISSING
    progress: bool = run_only()
    resume: str = run_only(_resume_rule())   # auto | true | false | <run_dir> (see torchrl_bail.resume)
    threads: Optional[int] = run_only(_rule(lambda v: v is None or v >= 1,  # noqa: UP045
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


@dataclass
class CollectionConfig(_Checked):
    """What collecting a batch reads (:mod:`torchrl_bail.behaviour`, :mod:`torchrl_bail.data.cache`): the env, the
    batch recipe and where batches live; :func:`collection_config` makes one, every rule checked."""

    env: EnvConfig = MISSING
    batch: Any = MISSING       # one of BATCH_SCHEMAS
    data_dir: Optional[str] = None


#: the top-level keys marked :func:`run_only` in :class:`Config`: a checkpoint resumes across them
#: (:mod:`torchrl_bail.resume`), the report never separates runs by them, run directories leave them out of their names
RUN_ONLY_KEYS = tuple(f.name for f in dataclasses.fields(Config) if f.metadata.get("run_only"))
#: the other keys a run directory's name leaves out: those already in its path (``conf/config.yaml``'s
#: ``hydra.run.dir``; ``seeds=``: one directory per seed) and ``dataset`` (a path)
RUN_DIR_KEYS = ("exp", "env", "batch", "batch.index", "algo", "seed", "seeds", "dataset")
#: longest override suffix kept verbatim in a directory name (file systems allow 255 bytes per component)
_MAX_SUFFIX = 120


def run_dir_excluded_keys() -> list[str]:
    """The overrides a run directory's name leaves out (Hydra's ``override_dirname.exclude_keys`` in
    ``conf/config.yaml``, which a test ties to this): :data:`RUN_DIR_KEYS` and every key under :data:`RUN_ONLY_KEYS`.

    Examples:
        >>> [k for k in run_dir_excluded_keys() if k.startswith("logger.")]
        ['logger.backend', 'logger.project', 'logger.group', 'logger.name']
    """
    keys = list(RUN_DIR_KEYS)
    for f in dataclasses.fields(Config):
        if f.metadata.get("run_only"):
            schema = f.type if isinstance(f.type, type) else globals().get(str(f.type))
            nested = dataclasses.is_dataclass(schema)
            keys += [f"{f.name}.{leaf.name}" for leaf in dataclasses.fields(schema)] if nested else [f.name]
    return keys


def run_dir_suffix(override_dirname: str) -> str:
    """``",<overrides>"`` for a non-empty Hydra ``override_dirname`` (``/`` -> ``%``; long ones shortened with a
    hash), else ``""``: registered as the ``run_dir_suffix`` resolver of ``conf/config.yaml``'s run dirs.

    Examples:
        >>> run_dir_suffix("")
        ''
        >>> run_dir_suffix("algo.epochs=3,preset=quick")
        ',algo.epochs=3,preset=quick'
        >>> run_dir_suffix("dataset=/data/hopper.hdf5")
        ',dataset=%data%hopper.hdf5'
    """
    text = str(override_dirname or "").replace(os.sep, "%")
    if not text:
        return ""
    if len(text) > _MAX_SUFFIX:
        digest = hashlib.sha1(text.encode()).hexdigest()[:10]
        text = f"{text[:_MAX_SUFFIX - 11]}~{digest}"
    return "," + text


def batch_label(env: str, kind: str, index: int, dataset: str | None) -> str:
    """What a run trained on, for its logger group (``conf/config.yaml``'s ``batch_label`` resolver):
    ``<env>_<kind>_b<index>`` for a generated batch; for a ``dataset=`` run, whose ``batch`` group is not read, the
    dataset's name (a file's stem, a Minari folder's name), prefixed with the env unless it starts with it.

    Examples:
        >>> batch_label("hopper", "ddpg05", 1, None), batch_label("hopper", "ddpg05", 1, "/data/hopper_medium-v2.hdf5")
        ('hopper_ddpg05_b1', 'hopper_medium-v2')
        >>> batch_label("hopper", "ddpg05", 1, "~/.minari/datasets/mujoco/hopper/expert-v0/data")
        'hopper_expert-v0'
    """
    if not dataset:
        return f"{env}_{kind}_b{index}"
    path = Path(str(dataset))
    name = path.parent.name if path.name == "data" else (path.stem if path.suffix in (".hdf5", ".h5") else path.name)
    return name if name.startswith(str(env)) else f"{env}_{name}"


ALGO_SCHEMAS = {"bail": BAILConfig, "pbail": PBAILConfig, "bc": BCConfig, "marwil": MARWILConfig,
                "bcq": BCQConfig, "bear": BEARConfig, "td3bc": TD3BCConfig, "iql": IQLConfig}
BATCH_SCHEMAS = {"ddpg": DDPGBatchConfig, "sac": SACBatchConfig, "sac_exec": SACExecBatchConfig}


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
        torchrl_bail.errors.ConfigError: config key batch.recipe = 'dqn': expected one of ddpg, sac, sac_exec
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
        torchrl_bail.errors.ConfigError: config key algo.selection.percentile = 1.5: expected a fraction in (0, 1]
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


def group_options(conf: Path | None = None) -> dict[str, list[str]]:
    """The options of each config group: ``{group: [option, ...]}`` from the yaml files under ``conf/`` (default:
    :func:`~torchrl_bail.config.config_dir`), without Hydra's own groups (``hydra/...``) and the files named
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


def _groups_help() -> str:
    """The ``--help`` lines of :func:`group_options`: the ``config_groups`` resolver of ``conf/config.yaml``'s
    ``hydra.help.template`` (Hydra's own list also shows the schemas, ``base_<name>_schema``, and the parts)."""
    return "\n".join(f"{group}: {', '.join(options)}" for group, options in sorted(group_options().items()))


def config_dir() -> Path:
    """Directory holding the Hydra configs.

    An installed wheel ships them as ``torchrl_bail/conf``; a source checkout (editable install) keeps
    them at the repository's top-level ``conf/``. The typed schemas the yaml files name
    (:mod:`torchrl_bail.config`) are registered with Hydra's ConfigStore on the way, and the resolvers
    ``conf/config.yaml`` uses (:func:`run_dir_suffix`, :func:`batch_label`; ``config_groups``, :func:`group_options`
    for ``--help``).
    """
    register_schemas()
    for name, resolver in (("run_dir_suffix", run_dir_suffix), ("batch_label", batch_label),
                           ("config_groups", _groups_help)):
        if not OmegaConf.has_resolver(name):
            OmegaConf.register_new_resolver(name, resolver)
    packaged = Path(__file__).resolve().parent / "conf"
    if packaged.is_dir():
        return packaged
    repo = Path(__file__).resolve().parents[2] / "conf"
    if repo.is_dir():
        return repo
    raise FileNotFoundError(
        f"torchrl_bail configs not found: looked in {packaged} and {repo}. Reinstall the package."
    )

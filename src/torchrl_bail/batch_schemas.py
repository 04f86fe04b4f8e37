"""The batch recipes' schemas (``conf/batch``): one per recipe, registered in :data:`BATCH_SCHEMAS` and named
``batch/base_<recipe>_schema`` in Hydra (:func:`torchrl_bail.hydra_setup.register_schemas`). Torch-free, like every
schema, so a bad command line fails before torch loads; the rules come from :mod:`torchrl_bail.config`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, List, Optional  # noqa: UP035 -- OmegaConf reads these annotations at runtime

from omegaconf import MISSING

from torchrl_bail.config import (
    Checked,
    at_least,
    discount,
    is_number,
    layers,
    learning_rate,
    non_negative,
    one_of,
    option_name,
    positive,
    registry_name,
    rule,
)
from torchrl_bail.errors import ConfigError

__all__ = ["BATCH_SCHEMAS", "BatchConfig", "DDPGAgentConfig", "DDPGBatchConfig", "OracleConfig", "SACAgentConfig",
           "SACBatchConfig", "SACExecBatchConfig"]


@dataclass
class OracleConfig(Checked):
    enabled: bool = MISSING
    horizon: int = at_least(2)
    keep: int = at_least(1, "a positive number of steps kept per episode")
    gamma: float = discount()

    def check(self) -> None:
        if self.horizon <= self.keep:
            raise ConfigError("horizon", self.horizon, f"an episode length larger than keep = {self.keep}")


@dataclass
class BatchConfig(Checked):
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
class DDPGAgentConfig(Checked):
    actor_hidden: List[int] = layers()
    critic_hidden: List[int] = layers()
    critic_arch: str = one_of("late_action", "concat")
    actor_lr: float = learning_rate()
    critic_lr: float = learning_rate()
    critic_weight_decay: float = non_negative("a non-negative L2 coefficient")
    gamma: float = discount()
    tau: float = rule(lambda v: 0 < v <= 1, "a soft-update rate in (0, 1]")
    batch_size: int = at_least(1, "a positive mini-batch size")


@dataclass
class DDPGBatchConfig(BatchConfig):
    sigma: float = non_negative("a non-negative noise std (absolute, not scaled by the action bound)")
    start_steps: int = at_least(0, "a non-negative number of uniformly random steps")
    agent: DDPGAgentConfig = MISSING


@dataclass
class SACAgentConfig(Checked):
    actor_hidden: List[int] = layers()
    critic_hidden: List[int] = layers()
    actor_lr: float = learning_rate()
    critic_lr: float = learning_rate()
    alpha_lr: float = learning_rate()
    gamma: float = discount()
    polyak: float = rule(lambda v: 0 <= v < 1, "a target-network decay in [0, 1) (0.995)")
    alpha_init: float = positive("a positive initial entropy coefficient")
    target_entropy: Any = rule(lambda v: v == "auto" or is_number(v), "auto or a number")
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


#: recipe name -> its schema (kept equal to :data:`torchrl_bail.behaviour.recipes.RECIPES` by a test)
BATCH_SCHEMAS = {"ddpg": DDPGBatchConfig, "sac": SACBatchConfig, "sac_exec": SACExecBatchConfig}

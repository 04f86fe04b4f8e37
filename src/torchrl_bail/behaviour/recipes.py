"""The recipe catalogue: which behaviour recipes exist and what a valid ``cfg.env`` / ``cfg.batch`` looks like.

Recipes (``cfg.batch.recipe``):

* ``ddpg`` -- :mod:`torchrl_bail.behaviour.ddpg`: the whole replay buffer of an online DDPG run with N(0, sigma^2)
  exploration noise (supp. C.2, final buffer).
* ``sac`` -- :mod:`torchrl_bail.behaviour.sac`: the first ``steps`` transitions of an online SAC run (paper Sec. 5;
  supp. E).
* ``sac_exec`` -- :mod:`torchrl_bail.behaviour.execution`: ``steps`` transitions of a frozen SAC policy (mediocre or
  optimal, deterministic or stochastic; paper Sec. 5; supp. E). The SAC run behind it is shared with the ``sac`` batch.

Any recipe can be collected in *oracle* mode (``batch.oracle.enabled=true``, supp. D.1): see
:class:`~torchrl_bail.behaviour.buffers.BatchSink`. Names, hashes and cache paths are those of
:mod:`torchrl_bail.data.cache`.

Examples:
    >>> cfg = {"env": {"name": "hopper", "id": "Hopper-v5", "max_episode_steps": 1000},
    ...        "batch": {"kind": "ddpg05", "recipe": "dqn", "index": 1, "steps": 1000}}
    >>> validate_recipe(cfg)  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    torchrl_bail.behaviour.recipes.CollectionConfigError: config key batch.recipe = 'dqn': expected one of ddpg, ...
"""

from __future__ import annotations

import math

from torchrl_bail.data.cache import config_value, oracle_settings

__all__ = ["RECIPES", "EXEC_POLICIES", "CollectionConfigError", "validate_recipe"]

RECIPES = ("ddpg", "sac", "sac_exec")
EXEC_POLICIES = ("mediocre", "optimal")


class CollectionConfigError(ValueError):
    """A behaviour-data recipe value is missing or out of range; the message names the config key."""



def validate_recipe(cfg) -> None:
    """Checks ``cfg.env`` / ``cfg.batch`` before any work starts; raises :class:`CollectionConfigError`."""

    def need(cond: bool, key: str, expected: str) -> None:
        if not cond:
            raise CollectionConfigError(f"config key {key} = {config_value(cfg, key)!r}: expected {expected}")

    def number(key: str) -> bool:
        v = config_value(cfg, key)
        return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)

    def integer(key: str) -> bool:
        v = config_value(cfg, key)
        return isinstance(v, int) and not isinstance(v, bool)

    def hidden(key: str) -> None:
        v = config_value(cfg, key)
        need(isinstance(v, list) and all(isinstance(h, int) and h > 0 for h in v), key,
             "a list of positive layer widths, e.g. [400, 300]")

    need(isinstance(config_value(cfg, "env.id"), str), "env.id", "a gymnasium id such as Hopper-v5")
    need(isinstance(config_value(cfg, "env.name"), str), "env.name", "a short env name such as hopper")
    limit = config_value(cfg, "env.max_episode_steps")
    need(limit is None or (integer("env.max_episode_steps") and limit >= 1), "env.max_episode_steps",
         "a positive integer (or null for the env's default)")
    need(isinstance(config_value(cfg, "batch.kind"), str), "batch.kind", "a string such as ddpg05")
    recipe = config_value(cfg, "batch.recipe")
    need(recipe in RECIPES, "batch.recipe", f"one of {', '.join(RECIPES)}")
    need(integer("batch.index") and config_value(cfg, "batch.index") >= 1, "batch.index",
         "an integer >= 1 (B1, B2, ...)")
    need(config_value(cfg, "batch.seed") is None or integer("batch.seed"), "batch.seed", "null or an integer")
    need(integer("batch.steps") and config_value(cfg, "batch.steps") > 0, "batch.steps",
         "a positive number of transitions")

    for key in ("checkpoint_every_s", "lock_stale_after_s", "heartbeat_every_s", "checkpoint_every_steps"):
        value = config_value(cfg, f"batch.{key}")
        need(value is None or (number(f"batch.{key}") and value > 0), f"batch.{key}",
             "a positive number, or null" + (" (never)" if key.startswith("checkpoint") else " (the default)"))
    oracle = config_value(cfg, "batch.oracle")
    if oracle is not None:
        need(isinstance(oracle, dict) and isinstance(oracle.get("enabled", False), bool), "batch.oracle.enabled",
             "true or false")
    if oracle_settings(cfg):
        need(integer("batch.oracle.keep") and config_value(cfg, "batch.oracle.keep") >= 1, "batch.oracle.keep",
             "a positive number of steps kept per episode")
        need(integer("batch.oracle.horizon")
             and config_value(cfg, "batch.oracle.horizon") > config_value(cfg, "batch.oracle.keep"),
             "batch.oracle.horizon", "an episode length larger than batch.oracle.keep")
        need(number("batch.oracle.gamma") and 0 < config_value(cfg, "batch.oracle.gamma") <= 1, "batch.oracle.gamma",
             "a discount in (0, 1]")

    if recipe == "ddpg":
        need(number("batch.sigma") and config_value(cfg, "batch.sigma") >= 0, "batch.sigma",
             "a non-negative noise std (absolute, not scaled by the action bound)")
        need(integer("batch.start_steps") and config_value(cfg, "batch.start_steps") >= 0, "batch.start_steps",
             "a non-negative number of uniformly random steps")
        hidden("batch.agent.actor_hidden")
        hidden("batch.agent.critic_hidden")
        for key in ("actor_lr", "critic_lr"):
            need(number(f"batch.agent.{key}") and config_value(cfg, f"batch.agent.{key}") > 0, f"batch.agent.{key}",
                 "a positive learning rate")
        need(number("batch.agent.critic_weight_decay") and config_value(cfg, "batch.agent.critic_weight_decay") >= 0,
             "batch.agent.critic_weight_decay", "a non-negative L2 coefficient")
        need(number("batch.agent.gamma") and 0 < config_value(cfg, "batch.agent.gamma") <= 1, "batch.agent.gamma",
             "a discount in (0, 1]")
        need(number("batch.agent.tau") and 0 < config_value(cfg, "batch.agent.tau") <= 1, "batch.agent.tau",
             "a soft-update rate in (0, 1]")
        need(integer("batch.agent.batch_size") and config_value(cfg, "batch.agent.batch_size") >= 1,
             "batch.agent.batch_size", "a positive mini-batch size")
        arch = config_value(cfg, "batch.agent.critic_arch", "late_action")
        need(arch in ("late_action", "concat"), "batch.agent.critic_arch", "late_action | concat")
    else:
        _validate_sac_block(cfg, need, number, integer, hidden)
        if recipe == "sac":
            need(config_value(cfg, "batch.steps") <= config_value(cfg, "batch.sac.train_steps"), "batch.steps",
                 f"at most batch.sac.train_steps = {config_value(cfg, 'batch.sac.train_steps')} (the batch is the "
                 "first batch.steps transitions of the SAC run)")
        if recipe == "sac_exec":
            need(config_value(cfg, "batch.policy") in EXEC_POLICIES, "batch.policy", "mediocre | optimal")
            need(isinstance(config_value(cfg, "batch.stochastic"), bool), "batch.stochastic",
                 "false (sigma=0: max_action*tanh(mu)) or true (sigma=sigma(s))")
            if config_value(cfg, "batch.policy") == "mediocre":
                need(number("env.mediocre_threshold"), "env.mediocre_threshold",
                     "the return at which the mediocre SAC policy is frozen")


def _validate_sac_block(cfg, need, number, integer, hidden) -> None:
    need(isinstance(config_value(cfg, "batch.sac"), dict), "batch.sac", "the SAC agent block (see conf/batch/sac.yaml)")
    hidden("batch.sac.actor_hidden")
    hidden("batch.sac.critic_hidden")
    for key in ("actor_lr", "critic_lr", "alpha_lr"):
        need(number(f"batch.sac.{key}") and config_value(cfg, f"batch.sac.{key}") > 0, f"batch.sac.{key}",
             "a positive learning rate")
    need(number("batch.sac.gamma") and 0 < config_value(cfg, "batch.sac.gamma") <= 1, "batch.sac.gamma",
         "a discount in (0, 1]")
    need(number("batch.sac.polyak") and 0 <= config_value(cfg, "batch.sac.polyak") < 1, "batch.sac.polyak",
         "a target-network decay in [0, 1) (0.995)")
    need(number("batch.sac.alpha_init") and config_value(cfg, "batch.sac.alpha_init") > 0, "batch.sac.alpha_init",
         "a positive initial entropy coefficient")
    te = config_value(cfg, "batch.sac.target_entropy")
    need(te == "auto" or number("batch.sac.target_entropy"), "batch.sac.target_entropy", "auto or a number")
    need(number("batch.sac.log_std_min") and number("batch.sac.log_std_max")
         and config_value(cfg, "batch.sac.log_std_min") < config_value(cfg, "batch.sac.log_std_max"),
         "batch.sac.log_std_min", "log_std_min < log_std_max")
    for key, lo in (("batch_size", 1), ("start_steps", 0), ("train_steps", 1), ("eval_every", 1),
                    ("eval_episodes", 1)):
        need(integer(f"batch.sac.{key}") and config_value(cfg, f"batch.sac.{key}") >= lo, f"batch.sac.{key}",
             f"an integer >= {lo}")
    need(config_value(cfg, "batch.sac.loss_function") in ("l2", "smooth_l1", "l1"), "batch.sac.loss_function",
         "l2 | smooth_l1 | l1")


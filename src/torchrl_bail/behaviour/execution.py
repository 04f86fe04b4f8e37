"""SAC execution batches (paper Sec. 5; supp. E): ``batch.steps`` transitions of a frozen SAC policy, mediocre or
optimal, deterministic (``stochastic: false``, sigma = 0: ``max_action * tanh(mu(s))``) or stochastic
(``sigma = sigma(s)``).

The policy comes from the shared SAC run (:func:`~torchrl_bail.behaviour.sac_run.ensure_sac_run`: trained once, reused
by every execution batch of the same env, seed and ``batch.sac`` block). The metadata keeps the policy file, its
evaluation step and its measured return (``behaviour_return``).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import torch
from omegaconf import MISSING
from tensordict import TensorDict, TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_bail.behaviour.buffers import BehaviourBuffers
from torchrl_bail.behaviour.checkpoint import CollectionCheckpoint, Resumable
from torchrl_bail.behaviour.loop import (
    BehaviourRun,
    ReturnTracker,
    collect_timed,
    env_bounds,
    env_steps_per_s,
    make_collection_env,
    seed_all,
)
from torchrl_bail.behaviour.recipes import Recipe, register_recipe
from torchrl_bail.behaviour.sac_run import SACAgentConfig, ensure_sac_run
from torchrl_bail.configuration.batch_schemas import BatchConfig, batch_schema
from torchrl_bail.configuration.config import one_of
from torchrl_bail.data.cache import (
    batch_name,
    behaviour_seed,
    data_dir_of,
    episode_limit,
    oracle_settings,
)

__all__ = ["EXEC_SEED_OFFSET", "collect_sac_exec"]


# -- the schema (conf/batch, recipe: sac_exec), read by torchrl_bail.configuration.batch_schemas without importing this
# module --


@batch_schema("sac_exec")
class SACExecBatchConfig(BatchConfig):
    sac: SACAgentConfig = MISSING
    policy: str = one_of("mediocre", "optimal")
    stochastic: bool = MISSING


log = logging.getLogger("torchrl_bail")

EXEC_SEED_OFFSET = 10_000  # execution envs are seeded apart from the SAC run's own env


def collect_sac_exec(cfg, *, scratch: Path, progress: bool = True, data_dir=None,
                     checkpoint: CollectionCheckpoint | None = None) -> tuple[TensorDictBase, dict[str, Any]]:
    """An execution batch: ``batch.steps`` transitions of the mediocre/optimal SAC policy (sigma = 0 or sigma(s)).

    ``checkpoint``: resumed from and saved to (the loop, the transitions, the RNG states; the policy is frozen),
    or ``None``."""
    steps = int(cfg.batch.steps)
    stochastic = bool(cfg.batch.stochastic)
    which = cfg.batch.policy
    root = data_dir_of(cfg, data_dir)
    run = ensure_sac_run(cfg, progress=progress, data_dir=root)
    if which == "optimal":
        evaluation, reached = run.optimal(), True
    else:
        threshold = float(cfg.env.mediocre_threshold)
        evaluation, reached = run.mediocre(threshold)
        if not reached:
            log.warning("no evaluation of SAC run %s reached the mediocre threshold %.0f; using the best one "
                        "(step %d, return %.1f)", run.path.name, threshold, evaluation["step"],
                        evaluation["return_mean"])
    actor = run.load_actor(evaluation)
    seed = behaviour_seed(cfg) + EXEC_SEED_OFFSET
    seed_all(seed)
    env = make_collection_env(cfg.env.id, max_episode_steps=episode_limit(cfg), seed=seed)
    mode = ExplorationType.RANDOM if stochastic else ExplorationType.DETERMINISTIC
    try:
        low, high = env_bounds(env)

        @torch.no_grad()
        def act(observation: torch.Tensor, t: int) -> torch.Tensor:
            with set_exploration_type(mode):
                return actor(TensorDict({"observation": observation}, batch_size=[]))["action"]

        buffers = BehaviourBuffers(steps, Path(scratch), oracle=oracle_settings(cfg), replay_batch_size=None)
        tracker = ReturnTracker(steps, desc=f"collect {batch_name(cfg)}", progress=progress)
        runner = BehaviourRun(env, act, tracker=tracker)
        resumable = Resumable(checkpoint, runner, buffers) if checkpoint is not None else None
        data, wall = collect_timed(buffers, runner, resumable=resumable)
    finally:
        env.close()
    extra = {
        "action_low": low.tolist(),
        "action_high": high.tolist(),
        "behaviour": "sac_exec",
        "behaviour_policy": {
            "which": which,
            "stochastic": stochastic,
            "run": str(run.path),
            "file": str(run.path / evaluation["file"]),
            "eval_step": evaluation["step"],
            "eval_return_mean": evaluation["return_mean"],
            "eval_return_std": evaluation["return_std"],
            "mediocre_threshold": None if which == "optimal" else float(cfg.env.mediocre_threshold),
            "threshold_reached": reached,
        },
        "behaviour_return": evaluation["return_mean"],
        "env_steps": runner.t,
        "env_steps_per_s": env_steps_per_s(runner, wall, resumable),
        "simulator_unstable_episodes": runner.unstable_episodes,
        "resumed_from_step": resumable.resumed_from_step if resumable is not None else None,
    }
    return data, extra


class SACExecRecipe(Recipe):
    """``batch.recipe=sac_exec``: :func:`collect_sac_exec` (the SAC run behind it is shared, under its own lock)."""

    name = "sac_exec"

    def collect(self, cfg, *, scratch, progress, data_dir, checkpoint):
        return collect_sac_exec(cfg, scratch=scratch, progress=progress, data_dir=data_dir, checkpoint=checkpoint)


register_recipe(SACExecRecipe())

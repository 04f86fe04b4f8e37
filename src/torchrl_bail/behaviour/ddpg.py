"""DDPG training batches (supp. C.2, final buffer): the whole replay buffer of an online DDPG run, as in the BCQ
repository.

The behaviour agent is the BCQ-repo DDPG (Fujimoto et al. 2018/2019, the "final buffer" of the BCQ paper):

* actor ``obs -> 400 -> 300 -> |A|``, ReLU, ``max_action * tanh``; Adam lr 1e-4;
* critic ``400 -> (concat action) 300 -> 1`` (``critic_arch: late_action``, the BCQ-repo layout; ``concat`` is a
  plain ``(s, a) -> 400 -> 300 -> 1`` MLP from :func:`~torchrl_bail.modules.make_qvalue_network`); Adam lr 1e-3
  with coupled L2 ``weight_decay`` 1e-2;
* TorchRL :class:`~torchrl.objectives.DDPGLoss` with target actor *and* target critic (``delay_actor=True``, the
  BCQ repo has both), squared TD error, a TD(0) estimator with gamma 0.99 that bootstraps on ``terminated`` (a
  time-limit truncation is bootstrapped), and :class:`~torchrl.objectives.SoftUpdate` with tau 0.005;
* each gradient step updates the critic first, then the actor against the *updated* critic, then both targets
  (the order of the BCQ-repo ``DDPG.train``), on a mini-batch of 100 drawn uniformly from everything stored.

Procedure: ``start_steps`` (1000) uniformly random actions, then ``mu(s) + N(0, sigma^2)`` with an absolute sigma
(0.1 or 0.5, *not* scaled by the action bound), clipped to the bounds; at the end of every episode (terminated or
truncated, the random phase included, the last one excepted when the batch is full) ``episode_length`` gradient
steps. Every transition is stored in order with its true ``terminated`` / ``truncated`` flags and real terminal
next-observations; the replay buffer *is* the batch.

Examples:
    >>> import torch
    >>> from torchrl_bail.modules import action_spec_from_bounds
    >>> agent = DDPGAgent(11, action_spec_from_bounds([-1.0] * 3, [1.0] * 3), actor_hidden=[32, 32],
    ...                   critic_hidden=[32, 32])
    >>> agent.act(torch.zeros(11)).shape
    torch.Size([3])
"""

from __future__ import annotations

import copy
import logging
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, List

import torch
from omegaconf import MISSING
from tensordict import TensorDictBase
from torch import nn
from torchrl.modules import ValueOperator
from torchrl.objectives import DDPGLoss, ValueEstimators
from torchrl.objectives.utils import distance_loss
from torchrl.objectives.value.functional import td0_return_estimate

from torchrl_bail.behaviour.buffers import BehaviourBuffers
from torchrl_bail.behaviour.checkpoint import CheckpointableAgent, CollectionCheckpoint, Resumable
from torchrl_bail.behaviour.loop import (
    BehaviourRun,
    ReturnTracker,
    agent_kwargs,
    collect_timed,
    env_bounds,
    env_steps_per_s,
    make_collection_env,
    seed_all,
)
from torchrl_bail.behaviour.recipes import Recipe, register_recipe
from torchrl_bail.configuration.batch_schemas import BatchConfig, batch_schema, schema_block
from torchrl_bail.configuration.config import (
    Checked,
    at_least,
    discount,
    layers,
    learning_rate,
    non_negative,
    one_of,
    rule,
)
from torchrl_bail.data.cache import batch_name, behaviour_seed, episode_limit, oracle_settings
from torchrl_bail.modules import (
    action_spec_from_bounds,
    fused_soft_update,
    make_deterministic_actor,
    make_qvalue_network,
)

__all__ = ["LateActionCritic", "make_ddpg_critic", "DDPGAgent", "collect_ddpg"]


# -- the schema (conf/batch, recipe: ddpg), read by torchrl_bail.configuration.batch_schemas without importing this
# module --


@schema_block
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


@batch_schema("ddpg")
class DDPGBatchConfig(BatchConfig):
    sigma: float = non_negative("a non-negative noise std (absolute, not scaled by the action bound)")
    start_steps: int = at_least(0, "a non-negative number of uniformly random steps")
    agent: DDPGAgentConfig = MISSING


log = logging.getLogger("torchrl_bail")


class LateActionCritic(nn.Module):
    """``Q(s, a) = l3(relu(l2([relu(l1(s)), a])))``: the action joins after the first layer (BCQ-repo DDPG)."""

    def __init__(self, obs_dim: int, act_dim: int, hidden: Sequence[int] = (400, 300)):
        super().__init__()
        if len(hidden) != 2:
            raise ValueError(f"the late-action DDPG critic has exactly two hidden layers, got {list(hidden)}")
        self.l1 = nn.Linear(obs_dim, hidden[0])
        self.l2 = nn.Linear(hidden[0] + act_dim, hidden[1])
        self.l3 = nn.Linear(hidden[1], 1)

    def forward(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        h = torch.relu(self.l1(observation))
        h = torch.relu(self.l2(torch.cat([h, action], -1)))
        return self.l3(h)


def make_ddpg_critic(obs_dim: int, act_dim: int, hidden: Sequence[int] = (400, 300), *,
                     arch: str = "late_action") -> ValueOperator:
    """The DDPG critic as a :class:`~torchrl.modules.ValueOperator` writing ``state_action_value``."""
    if arch == "late_action":
        return ValueOperator(LateActionCritic(obs_dim, act_dim, hidden), in_keys=["observation", "action"])
    if arch == "concat":
        return make_qvalue_network(obs_dim, act_dim, hidden)
    raise ValueError(f"batch.agent.critic_arch must be late_action or concat, got {arch!r}")


class DDPGAgent(CheckpointableAgent):
    """The BCQ-repo DDPG on TorchRL's :class:`~torchrl.objectives.DDPGLoss` (see the module docstring)."""

    OPTIMIZERS = ("actor_optim", "critic_optim")  # saved with the networks by state_dict()

    def __init__(self, obs_dim: int, action_spec, *, actor_hidden: Sequence[int] = (400, 300),
                 critic_hidden: Sequence[int] = (400, 300), actor_lr: float = 1e-4, critic_lr: float = 1e-3,
                 critic_weight_decay: float = 1e-2, gamma: float = 0.99, tau: float = 0.005,
                 batch_size: int = 100, critic_arch: str = "late_action"):
        act_dim = action_spec.shape[-1]
        self.batch_size = int(batch_size)
        self.actor = make_deterministic_actor(obs_dim, action_spec, actor_hidden)
        self.critic = make_ddpg_critic(obs_dim, act_dim, critic_hidden, arch=critic_arch)
        self.loss = DDPGLoss(self.actor, self.critic, delay_actor=True, delay_value=True, loss_function="l2")
        self.loss.make_value_estimator(ValueEstimators.TD0, gamma=gamma)  # bootstraps on ~terminated
        self.target_updater = fused_soft_update(self.loss, tau=tau)  # a SoftUpdate; built before the first forward
        self.actor_optim = torch.optim.Adam(self.loss.actor_network_params.values(True, True), lr=actor_lr,
                                            foreach=True)
        self.critic_optim = torch.optim.Adam(self.loss.value_network_params.values(True, True), lr=critic_lr,
                                             weight_decay=critic_weight_decay, foreach=True)
        self.updates = 0
        self._fast = _FastDDPGTerms(self)

    @torch.no_grad()
    def act(self, observation: torch.Tensor) -> torch.Tensor:
        """The deterministic action ``mu(s)`` (within the bounds): ``self.actor``'s output, without TensorDicts."""
        return self._fast.act(observation)

    def loss_value(self, batch: TensorDictBase) -> torch.Tensor:
        """``DDPGLoss.loss_value`` (squared TD(0) error on the target networks), without TensorDict plumbing."""
        return self._fast.loss_value(batch)

    def loss_actor(self, batch: TensorDictBase) -> torch.Tensor:
        """``DDPGLoss.loss_actor`` (``-Q(s, mu(s))``, critic weights frozen), without TensorDict plumbing."""
        return self._fast.loss_actor(batch)

    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        """One gradient step: critic, then actor against the updated critic, then the soft target update.

        The losses are TorchRL's :class:`~torchrl.objectives.DDPGLoss` numbers (``tests/test_behaviour_agents.py``
        checks them against it); returned detached as 0-d tensors (no sync per update).
        """
        loss_value = self.loss_value(batch)
        self.critic_optim.zero_grad(set_to_none=True)
        loss_value.backward()
        self.critic_optim.step()
        loss_actor = self.loss_actor(batch)
        self.actor_optim.zero_grad(set_to_none=True)
        loss_actor.backward()
        self.actor_optim.step()
        self.target_updater.step()
        self.updates += 1
        return {"loss_value": loss_value.detach(), "loss_actor": loss_actor.detach()}

    def train(self, replay, num_updates: int) -> dict[str, float] | None:
        """``num_updates`` gradient steps on mini-batches drawn uniformly (with replacement) from ``replay``;
        the last one's losses as floats."""
        out = None
        for _ in range(int(num_updates)):
            out = self.update(replay.sample())
        return None if out is None else {k: float(v) for k, v in out.items()}


class _FastDDPGTerms:
    """DDPGLoss's two losses as plain tensor code: the online networks called directly, the targets as copies of
    them bound once to the loss's target tensors (which :class:`~torchrl_bail.modules.FusedSoftUpdate` updates in
    place), the critic's weights frozen (not detached copies) while the actor loss runs."""

    def __init__(self, agent: DDPGAgent):
        loss = agent.loss
        self.loss = loss
        self.body, self.head = agent.actor[0].module, agent.actor[1]
        self.critic = agent.critic.module
        target_actor, target_critic = copy.deepcopy(agent.actor), copy.deepcopy(agent.critic)
        loss.target_actor_network_params.to_module(target_actor)
        loss.target_value_network_params.to_module(target_critic)
        self.target_body, self.target_head = target_actor[0].module, target_actor[1]
        self.target_critic = target_critic.module
        self.critic_params = list(self.critic.parameters())

    @staticmethod
    def _act(body: nn.Module, head, observation: torch.Tensor) -> torch.Tensor:
        """:class:`~torchrl.modules.TanhModule`'s map ``low + (high - low) * (tanh(x) + 1) / 2`` on the body."""
        feature = body(observation).tanh()
        if head.clamp:
            eps = torch.finfo(feature.dtype).resolution
            feature = feature.clamp(-1 + eps, 1 - eps)
        low, high = head.action_low, head.action_high
        return low + (high - low) * (feature + 1) / 2

    def act(self, observation: torch.Tensor) -> torch.Tensor:
        return self._act(self.body, self.head, observation)

    def loss_value(self, batch: TensorDictBase) -> torch.Tensor:
        loss = self.loss
        observation, action = batch["observation"], batch["action"]
        predicted = self.critic(observation, action).squeeze(-1)
        with torch.no_grad():
            next_observation = batch["next", "observation"]
            next_action = self._act(self.target_body, self.target_head, next_observation)
            next_value = self.target_critic(next_observation, next_action)
            target = td0_return_estimate(loss.value_estimator.gamma, next_value, batch["next", "reward"],
                                         batch["next", "terminated"]).squeeze(-1)
        return distance_loss(predicted, target, loss_function=loss.loss_function).mean()

    def loss_actor(self, batch: TensorDictBase) -> torch.Tensor:
        observation = batch["observation"]
        for p in self.critic_params:
            p.requires_grad_(False)
        try:
            value = self.critic(observation, self._act(self.body, self.head, observation))
        finally:
            for p in self.critic_params:
                p.requires_grad_(True)
        return (-value.squeeze(-1)).mean()



def collect_ddpg(cfg, *, scratch: Path, progress: bool = True, agent_hook=None,
                 checkpoint: CollectionCheckpoint | None = None) -> tuple[TensorDictBase, dict[str, Any]]:
    """Runs the DDPG recipe of ``cfg.batch`` on ``cfg.env``; returns (memmapped batch [steps], metadata extras).

    Args:
        cfg: the composed config (``env``, ``batch``); validated by the caller.
        scratch: a scratch directory for the replay buffer (removed by the caller).
        progress: show a tqdm bar (env steps/s, mean return of the last 10 episodes).
        agent_hook: called with the :class:`DDPGAgent` once built (tests use it to watch the updates).
        checkpoint: resume from it if it holds a checkpoint, and save checkpoints there (removed by the caller
            once the batch is saved); ``None``: no checkpoints.
    """
    steps = int(cfg.batch.steps)
    sigma = float(cfg.batch.sigma)
    start_steps = int(cfg.batch.start_steps)
    seed = behaviour_seed(cfg)
    seed_all(seed)
    env = make_collection_env(cfg.env.id, max_episode_steps=episode_limit(cfg), seed=seed)
    try:
        low, high = env_bounds(env)
        obs_dim = env.observation_spec["observation"].shape[-1]
        act_dim = low.shape[-1]
        agent = DDPGAgent(obs_dim, action_spec_from_bounds(low, high),
                          **agent_kwargs(DDPGAgent, cfg.batch.agent))
        if agent_hook is not None:
            agent_hook(agent)
        buffers = BehaviourBuffers(steps, Path(scratch), oracle=oracle_settings(cfg),
                                   replay_batch_size=agent.batch_size)
        span = high - low

        def act(observation: torch.Tensor, t: int) -> torch.Tensor:
            if t < start_steps:
                return low + span * torch.rand(act_dim)
            action = agent.act(observation)
            if sigma > 0:
                action = action + sigma * torch.randn(act_dim)
            return torch.maximum(torch.minimum(action, high), low)

        train_time = [0.0, 0]  # seconds in the agent's updates and the updates made in them (checkpointed)

        def on_episode_end(length: int, ret: float, t: int) -> None:
            t0, before = time.perf_counter(), agent.updates
            agent.train(buffers.replay, length)
            train_time[0] += time.perf_counter() - t0
            train_time[1] += agent.updates - before

        tracker = ReturnTracker(steps, desc=f"collect {batch_name(cfg)}", progress=progress)
        runner = BehaviourRun(env, act, on_episode_end=on_episode_end, tracker=tracker)
        resumable = None
        if checkpoint is not None:
            def load(state: dict) -> None:
                agent.load_state_dict(state["agent"])
                train_time[:] = state.get("train_time", [0.0, 0])  # (an older version's checkpoint has none)

            resumable = Resumable(checkpoint, runner, buffers, load=load,
                                  state=lambda: {"agent": agent.state_dict(), "train_time": list(train_time)})
        data, wall = collect_timed(buffers, runner, resumable=resumable)
    finally:
        env.close()
    returns = tracker.all_returns
    extra = {
        "action_low": low.tolist(),
        "action_high": high.tolist(),
        "behaviour": "ddpg",
        "sigma": sigma,
        "gradient_steps": agent.updates,
        "env_steps": runner.t,
        "behaviour_episodes": runner.episodes,
        "simulator_unstable_episodes": runner.unstable_episodes,
        "resumed_from_step": resumable.resumed_from_step if resumable is not None else None,
        "behaviour_final_return_mean10": float(sum(returns[-10:]) / max(1, len(returns[-10:]))),
        "env_steps_per_s": env_steps_per_s(runner, wall, resumable),
        "updates_per_s": train_time[1] / max(train_time[0], 1e-9),
    }
    log.info("DDPG collection done: %d env steps, %d gradient steps, %.1f env steps/s", runner.t, agent.updates,
             extra["env_steps_per_s"])
    return data, extra


class DDPGRecipe(Recipe):
    """``batch.recipe=ddpg``: :func:`collect_ddpg`."""

    name = "ddpg"

    def collect(self, cfg, *, scratch, progress, data_dir, checkpoint):
        return collect_ddpg(cfg, scratch=scratch, progress=progress, checkpoint=checkpoint)


register_recipe(DDPGRecipe())

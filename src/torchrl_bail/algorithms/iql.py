"""IQL (Kostrikov, Nair & Levine, "Offline Reinforcement Learning with Implicit Q-Learning", ICLR 2022,
arXiv:2110.06169): a value function fitted as an upper expectile of the critics, critics regressed to
``r + gamma V(s')``, and a Gaussian actor by advantage-weighted regression; no action is ever queried outside the
batch.

The losses are TorchRL's :class:`~torchrl.objectives.IQLLoss`. With ``min Q'`` the smaller of the two target
critics at the batch's ``(s, a)``:

* value: ``|tau - 1(u < 0)| u^2`` with ``u = min Q'(s, a) - V(s)`` and ``tau`` the ``expectile``;
* actor: ``-w log pi(a | s)`` with the advantage weights ``w = min(exp(beta (min Q'(s, a) - V(s))), 100)``
  (``V`` without gradient; TorchRL hard-codes the clip at 100, so the schema allows ``max_weight: 100`` only);
* critics: ``sum_i (Q_i(s, a) - y)^2`` with ``y = r + gamma (1 - terminated) V(s')`` (TD(0), no gradient into V).

Each is averaged over the mini-batch. One update follows the authors' order: a value step, an actor step (with
the updated ``V``), a critic step (with the updated ``V``), then the Polyak update of the target critics
(``tau``). The actor's Adam learning rate follows a cosine from ``actor.lr`` to 0 over the run's updates
(``actor.lr_schedule: cosine``; the authors' ``optax.cosine_decay_schedule``): update ``t`` (from 0) of ``T`` steps
with ``actor.lr * (1 + cos(pi t / T)) / 2``. ``T`` is what the training loop tells the algorithm
(:meth:`IQL.plan_updates`: its ``ceil(epochs * samples_per_epoch / batch_size)``); until then the config's epochs
of 10^6 samples. The learning rate follows from the count of updates, which the checkpoint keeps, so a resumed run
continues the schedule where it stopped.

The actor is a Gaussian with a mean ``tanh(MLP(s))`` and a state-independent log standard deviation (one parameter
per action dimension, starting at 0, clipped to ``[log_std_min, log_std_max]``), both on actions scaled to
``[-1, 1]`` (the action bounds' affine map; the identity for MuJoCo's ``+-1`` bounds). The evaluation policy is its
mean.

With ``reward_scale: locomotion`` (the authors' MuJoCo setting) :meth:`IQL.prepare` multiplies every reward by
``1000 / (max_k R_k - min_k R_k)``, ``R_k`` the undiscounted return of episode ``k`` of the batch (episodes told
apart by their ids, ``"episode"``, else by ``("next", "done")``; the unfinished last episode counts, as in the
authors' split of a dataset into trajectories). The factor goes into the checkpoint, and a resumed run applies it
without computing it again.

Seeds cannot be stacked (``seeds=``): the stack turns ``nn.Linear`` layers into seed-stacked ones, and the actor's
bare log-std parameter would be shared by the seeds' rows.

Examples:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from torchrl_bail.modules import action_spec_from_bounds
    >>> config = {"actor": {"hidden": [16]}, "critic": {"hidden": [16]}, "value": {"hidden": [16]},
    ...           "batch_size": 8, "epochs": 8 * 4 / 1e6}
    >>> algo = IQL(4, action_spec_from_bounds([-1.0] * 2, [1.0] * 2), config)
    >>> end = torch.zeros(8, 1, dtype=torch.bool)
    >>> batch = TensorDict({"observation": torch.randn(8, 4), "action": torch.rand(8, 2) * 2 - 1,
    ...                     "next": {"observation": torch.randn(8, 4), "reward": torch.randn(8, 1),
    ...                              "terminated": end, "done": end}}, [8])
    >>> [round(float(algo.update(batch)["actor_lr"]) / 3e-4, 3) for _ in range(4)]  # cosine over 4 updates
    [1.0, 0.854, 0.5, 0.146]
"""

from __future__ import annotations

import math

import torch
from omegaconf import MISSING
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import TensorSpec
from torchrl.envs.utils import ExplorationType
from torchrl.modules import IndependentNormal, ProbabilisticActor, ValueOperator
from torchrl.objectives import IQLLoss, ValueEstimators

from torchrl_bail.algorithms.base import Algorithm, PrepareContext
from torchrl_bail.algorithms.twin_critic_vae import use_vmap
from torchrl_bail.configuration.algo_schemas import AlgoConfig, CriticConfig, NetConfig, algo_schema, schema_block
from torchrl_bail.configuration.config import discount, non_negative, one_of, rule
from torchrl_bail.data.returns import EPISODE_KEYS
from torchrl_bail.modules import fused_soft_update, make_qvalue_network, mlp

__all__ = ["IQL", "GaussianActorParams", "MeanAction", "episode_returns", "locomotion_reward_factor"]


# -- the schema (conf/algo/iql.yaml), read by torchrl_bail.configuration.algo_schemas without importing this module --


@schema_block
class IQLActorConfig(NetConfig):
    log_std_min: float = MISSING
    log_std_max: float = MISSING
    lr_schedule: str = one_of("cosine", "constant")

    def check(self) -> None:
        self._ordered("log_std_min", "log_std_max")


@algo_schema("iql")
class IQLConfig(AlgoConfig):
    column = 8
    cost = "offline_rl"
    study = "none"
    tiny = ()
    description = ("IQL (arXiv:2110.06169): expectile value (τ = {expectile:g}), critics to r + γV(s'), "
                   "advantage-weighted Gaussian actor (β = {beta:g}, weights clipped at {max_weight:g}) with a cosine "
                   "learning rate; locomotion reward scaling; not in the BAIL paper")
    losses = ("torchrl.objectives.IQLLoss",)

    expectile: float = rule(lambda v: 0 < v < 1, "an expectile in (0, 1) (0.5: mean regression)")
    beta: float = non_negative("a non-negative inverse temperature of the advantage weights")
    # TorchRL's IQLLoss clips the advantage weights at 100 (a constant of its code): the one value it can train
    max_weight: float = rule(lambda v: v == 100, "100, the clip of exp(beta A) that TorchRL's IQLLoss hard-codes")
    gamma: float = discount()
    tau: float = rule(lambda v: 0 < v <= 1, "a soft-update rate in (0, 1]")
    reward_scale: str = one_of("locomotion", "none")
    actor: IQLActorConfig = MISSING
    critic: CriticConfig = MISSING
    value: NetConfig = MISSING


class GaussianActorParams(nn.Module):
    """``s -> (loc, scale)`` of the IQL actor: ``loc = c + h tanh(MLP(s))`` and ``scale = h exp(clip(log_std))``
    with ``c, h`` the action bounds' centre and half range and ``log_std`` one state-independent parameter per
    action dimension (from 0)."""

    def __init__(self, obs_dim: int, action_spec: TensorSpec, hidden, log_std_min: float, log_std_max: float) -> None:
        super().__init__()
        act_dim = action_spec.shape[-1]
        self.net = mlp(obs_dim, act_dim, hidden)
        self.log_std = nn.Parameter(torch.zeros(act_dim))
        self.log_std_min, self.log_std_max = float(log_std_min), float(log_std_max)
        low = torch.as_tensor(action_spec.space.low, dtype=torch.float32)
        high = torch.as_tensor(action_spec.space.high, dtype=torch.float32)
        self.register_buffer("action_centre", (high + low) / 2)
        self.register_buffer("action_half_range", (high - low) / 2)

    def mean(self, observation: torch.Tensor) -> torch.Tensor:
        return self.action_centre + self.action_half_range * torch.tanh(self.net(observation))

    def forward(self, observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        loc = self.mean(observation)
        scale = self.action_half_range * self.log_std.clamp(self.log_std_min, self.log_std_max).exp()
        return loc, scale.expand_as(loc)


class MeanAction(nn.Module):
    """The deterministic policy's network: the mean of :class:`GaussianActorParams` (a plain tensor function, so
    the policy exports to ``pt2``, ``onnx`` and TorchScript)."""

    def __init__(self, params: GaussianActorParams) -> None:
        super().__init__()
        self.params = params

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return self.params.mean(observation)


def episode_returns(data: TensorDictBase) -> torch.Tensor:
    """The undiscounted return (float64) of each episode of ``data`` ``[N]``, in the order of first appearance.

    Episodes are told apart by their ids (:data:`~torchrl_bail.data.returns.EPISODE_KEYS`), else by
    ``("next", "done")`` (a row after a done starts the next episode); the unfinished last episode counts.

    Examples:
        >>> from tensordict import TensorDict
        >>> done = torch.tensor([False, True, False, False, True]).unsqueeze(-1)
        >>> td = TensorDict({"next": {"reward": torch.tensor([[1.0], [2.0], [3.0], [4.0], [5.0]]), "done": done}},
        ...                 [5])
        >>> episode_returns(td).tolist()
        [3.0, 12.0]
    """
    reward = data.get(("next", "reward")).reshape(-1).double()
    keys = data.keys(include_nested=True)
    key = next((k for k in EPISODE_KEYS if k in keys), None)
    if key is not None:
        _, episode = torch.unique(data.get(key).reshape(-1), sorted=False, return_inverse=True)
        first = torch.full((int(episode.max()) + 1,), len(episode), dtype=torch.long)
        first = first.scatter_reduce(0, episode, torch.arange(len(episode)), reduce="amin")
        order = torch.argsort(first)
        rank = torch.empty_like(order)
        rank[order] = torch.arange(len(order))
        episode = rank[episode]
    else:
        done = data.get(("next", "done")).reshape(-1).long()
        episode = torch.cat([done.new_zeros(1), done[:-1].cumsum(0)])
    return torch.zeros(int(episode.max()) + 1, dtype=torch.float64).index_add_(0, episode, reward)


def locomotion_reward_factor(data: TensorDictBase) -> float:
    """``1000 / (max_k R_k - min_k R_k)`` over the episode returns of :func:`episode_returns` (the authors' MuJoCo
    reward scaling). Raises ``ValueError`` when the returns do not differ (fewer than two episodes)."""
    returns = episode_returns(data)
    spread = float(returns.max() - returns.min())
    if not spread > 0:
        raise ValueError(f"IQL's reward_scale=locomotion divides by the spread of the batch's episode returns, and "
                         f"its {len(returns)} episode(s) have none; use algo.reward_scale=none")
    return 1000.0 / spread


class IQL(Algorithm):
    """IQL on :class:`~torchrl.objectives.IQLLoss`, from ``conf/algo/iql.yaml``'s config (arguments as in
    :class:`~torchrl_bail.algorithms.base.Algorithm`).

    The config's ``actor`` block is the Gaussian actor (``hidden``, Adam ``lr``, ``log_std_min``/``log_std_max``,
    ``lr_schedule``), ``critic`` the two independently initialised critics ``(s, a) -> hidden -> 1`` (``hidden``,
    ``lr``, ``vmap``), ``value`` the state-value network ``s -> hidden -> 1``; ``expectile``, ``beta`` and ``gamma``
    go to the loss, ``tau`` to the target update, ``reward_scale`` to :meth:`prepare`.
    """

    name = "iql"
    seed_stack_refusal = "its actor's state-independent log std is a bare parameter, not a seed-stackable layer"
    state_attributes = ("updates", "reward_factor")

    def __init__(self, obs_dim: int, action_spec: TensorSpec, config, device="cpu") -> None:
        super().__init__(obs_dim, action_spec, config, device)
        cfg = self.config
        act_dim = action_spec.shape[-1]
        params = GaussianActorParams(obs_dim, action_spec, tuple(cfg.actor.hidden), cfg.actor.log_std_min,
                                     cfg.actor.log_std_max)
        actor = ProbabilisticActor(
            TensorDictModule(params, in_keys=["observation"], out_keys=["loc", "scale"]),
            in_keys=["loc", "scale"], spec=action_spec, distribution_class=IndependentNormal,
            return_log_prob=False, default_interaction_type=ExplorationType.RANDOM,
        )
        critics = [make_qvalue_network(obs_dim, act_dim, tuple(cfg.critic.hidden)) for _ in range(2)]
        value = ValueOperator(mlp(obs_dim, 1, tuple(cfg.value.hidden)), in_keys=["observation"],
                              out_keys=["state_value"])
        self.loss = IQLLoss(actor, critics, value, num_qvalue_nets=2, loss_function="l2",
                            temperature=float(cfg.beta), expectile=float(cfg.expectile),
                            deactivate_vmap=not use_vmap(cfg.critic.vmap, self.device)).to(self.device)
        self.loss.make_value_estimator(ValueEstimators.TD0, gamma=cfg.gamma)
        self.target_updater = fused_soft_update(self.loss, tau=float(cfg.tau))
        self.modules["loss"] = self.loss
        self.optimizers["value"] = _adam(self.loss.value_network_params.parameters(), cfg.value.lr, self.device)
        self.optimizers["actor"] = _adam(self.loss.actor_network_params.parameters(), cfg.actor.lr, self.device)
        self.optimizers["critic"] = _adam(self.loss.qvalue_network_params.parameters(), cfg.critic.lr, self.device)
        self._policy = TensorDictModule(MeanAction(params), in_keys=["observation"], out_keys=["action"])
        #: updates so far (the cosine schedule's position)
        self.updates = 0
        #: what :meth:`prepare` multiplied the rewards by (1 for ``reward_scale: none``)
        self.reward_factor = 1.0
        #: the updates the actor's cosine schedule spans (:meth:`plan_updates`)
        self.total_updates = max(1, math.ceil(self.epochs * 1e6 / self.samples_per_update))

    @property
    def policy(self) -> TensorDictModule:
        return self._policy

    def plan_updates(self, updates: int) -> None:
        """The cosine schedule spans ``updates`` updates (the training loop's count for the whole run)."""
        self.total_updates = max(1, int(updates))

    def actor_lr(self, update: int) -> float:
        """The actor's learning rate at update ``update`` (counted from 0)."""
        lr = float(self.config.actor.lr)
        if self.config.actor.lr_schedule == "constant":
            return lr
        return lr * 0.5 * (1.0 + math.cos(math.pi * min(update, self.total_updates) / self.total_updates))

    def summary(self) -> dict:
        return {"reward_factor": self.reward_factor}

    # -- data ---------------------------------------------------------------------------------------------------------
    def prepare(self, data: TensorDictBase, ctx: PrepareContext) -> TensorDictBase:
        """What the loss reads, with the rewards scaled (``reward_scale: locomotion``: by
        :func:`locomotion_reward_factor` of ``data``, kept as :attr:`reward_factor`); ``data`` is left as it is."""
        if self.config.reward_scale == "locomotion":
            self.reward_factor = locomotion_reward_factor(data)
        return self._scaled(data)

    def restore_prepared(self, data: TensorDictBase, ctx: PrepareContext) -> TensorDictBase:
        """On resume: the rewards scaled by the checkpoint's :attr:`reward_factor` (not computed again)."""
        return self._scaled(data)

    def _scaled(self, data: TensorDictBase) -> TensorDictBase:
        missing = [key for key in self.loss.in_keys if key not in data.keys(include_nested=True)]
        if missing:
            raise KeyError(f"IQL needs the batch entries {self.loss.in_keys}; missing {missing}")
        data = data.select(*self.loss.in_keys)
        data.set(("next", "reward"), data.get(("next", "reward")) * self.reward_factor)
        return data

    # -- the update ---------------------------------------------------------------------------------------------------
    #: the tensor work of an update; :meth:`update` sets the actor's learning rate around it
    compiled_method = "_update"

    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        self.optimizers["actor"].param_groups[0]["lr"].fill_(self.actor_lr(self.updates))
        self.updates += 1
        return self._update(batch)

    def _update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        loss_value, _ = self.loss.value_loss(batch)
        self._step("value", loss_value)
        loss_actor, _ = self.loss.actor_loss(batch)
        self._step("actor", loss_actor)
        loss_qvalue, _ = self.loss.qvalue_loss(batch)
        self._step("critic", loss_qvalue)
        self.target_updater.step()
        return {"loss_value": loss_value.detach(), "loss_actor": loss_actor.detach(),
                "loss_qvalue": loss_qvalue.detach(),
                "actor_lr": self.optimizers["actor"].param_groups[0]["lr"].detach().clone()}

    def _step(self, name: str, loss: torch.Tensor) -> None:
        optimizer = self.optimizers[name]
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()


def _adam(params, lr: float, device: torch.device) -> torch.optim.Adam:
    """Fused Adam (as :func:`~torchrl_bail.algorithms.twin_critic_vae.adam`) with its learning rate a tensor on
    ``device``: :meth:`IQL.update` sets it in place, which neither reads back to the host nor changes a compiled
    update's graph."""
    return torch.optim.Adam(params, lr=torch.tensor(float(lr), device=device), fused=True)

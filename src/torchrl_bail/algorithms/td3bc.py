"""TD3+BC (Fujimoto & Gu, "A Minimalist Approach to Offline Reinforcement Learning", NeurIPS 2021,
arXiv:2106.06860): TD3 whose actor loss adds a behaviour-cloning term, on standardised observations.

The losses are TorchRL's :class:`~torchrl.objectives.TD3BCLoss`. The two critics regress (squared error, summed
over the critics) to ``r + gamma (1 - terminated) min_i Q'_i(s', clip(pi'(s') + eps, low, high))`` with the target
policy's noise ``eps ~ N(0, policy_noise^2)`` clipped to ``+-noise_clip`` (both times ``max_action``, as in the
authors' code); the actor minimises ``-lambda Q_1(s, pi(s)) + mean (pi(s) - a)^2`` with
``lambda = alpha / mean |Q_1(s, pi(s))|`` over the mini-batch. One update follows the authors' order: a critic
step; every ``policy_delay``-th update also an actor step against the updated critics, then the Polyak update of
the target actor and critics (``tau``). Between actor steps the actor loss is still computed (without gradient),
so every update logs the same scalars.

Observations are standardised with the batch's mean and standard deviation (``+ normalize_eps``; the authors'
statistics, over every transition) in :meth:`TD3BC.prepare`, next observations alike. The evaluation policy
standardises its input with the same statistics (:class:`Standardize`, in front of the actor and saved with it),
so ``policy.pt`` and its exports act on raw observations.

Seeds cannot be stacked (``seeds=``): ``lambda`` averages ``|Q|`` over the whole mini-batch, which for a stacked
``[S, B]`` batch would mix the seeds.

Examples:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from torchrl_bail.modules import action_spec_from_bounds
    >>> config = {"actor": {"hidden": [16]}, "critic": {"hidden": [16]}, "batch_size": 8}
    >>> algo = TD3BC(4, action_spec_from_bounds([-1.0] * 2, [1.0] * 2), config)
    >>> end = torch.zeros(8, 1, dtype=torch.bool)
    >>> batch = TensorDict({"observation": torch.randn(8, 4), "action": torch.rand(8, 2) * 2 - 1,
    ...                     "next": {"observation": torch.randn(8, 4), "reward": torch.randn(8, 1),
    ...                              "terminated": end, "done": end}}, [8])
    >>> [float(algo.update(batch)["actor_step"]) for _ in range(4)]  # policy_delay = 2
    [0.0, 1.0, 0.0, 1.0]
"""

from __future__ import annotations

import torch
from omegaconf import MISSING
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torchrl.data import TensorSpec
from torchrl.objectives import TD3BCLoss, ValueEstimators

from torchrl_bail.algorithms.base import Algorithm, PrepareContext
from torchrl_bail.algorithms.twin_critic_vae import adam, use_vmap
from torchrl_bail.configuration.algo_schemas import AlgoConfig, CriticConfig, NetConfig, algo_schema
from torchrl_bail.configuration.config import at_least, discount, non_negative, positive, rule
from torchrl_bail.modules import fused_soft_update, make_deterministic_actor, make_qvalue_network

__all__ = ["TD3BC", "Standardize", "StandardizedPolicy"]


# -- the schema (conf/algo/td3bc.yaml), read by torchrl_bail.configuration.algo_schemas without importing this module --


@algo_schema("td3bc")
class TD3BCConfig(AlgoConfig):
    column = 7
    cost = "offline_rl"
    study = "all"  # in the study since it landed (30 jobs): kept, now stated
    tiny = ()
    description = ("TD3+BC (arXiv:2106.06860): TD3 with a behaviour-cloning term in the actor loss (α = {alpha:g}), "
                   "standardised observations; not in the BAIL paper")
    losses = ("torchrl.objectives.TD3BCLoss",)

    alpha: float = non_negative("a non-negative weight alpha of the Q term (0: behaviour cloning)")
    policy_noise: float = non_negative("a non-negative std of the target policy's noise, times max_action")
    noise_clip: float = non_negative("a non-negative clip of the target policy's noise, times max_action")
    policy_delay: int = at_least(1, "a positive number of critic updates per actor update")
    gamma: float = discount()
    tau: float = rule(lambda v: 0 < v <= 1, "a soft-update rate in (0, 1]")
    normalize_observations: bool = MISSING
    normalize_eps: float = positive("a positive number added to the observations' standard deviation")
    actor: NetConfig = MISSING
    critic: CriticConfig = MISSING


class Standardize(nn.Module):
    """``(x - loc) / scale`` with ``loc`` and ``scale`` buffers (0 and 1 until set; a plain tensor function, so a
    policy holding it exports to ``pt2`` and ``onnx``)."""

    def __init__(self, size: int) -> None:
        super().__init__()
        self.register_buffer("loc", torch.zeros(size))
        self.register_buffer("scale", torch.ones(size))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.loc) / self.scale


class StandardizedPolicy(TensorDictModuleBase):
    """``actor`` on standardised observations: reads ``"observation"``, writes ``"action"``, and leaves the input's
    observation as it was (the actor reads a standardised copy)."""

    def __init__(self, standardize: Standardize, actor: TensorDictModuleBase) -> None:
        super().__init__()
        self.standardize, self.actor = standardize, actor
        self.in_keys, self.out_keys = ["observation"], ["action"]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        inputs = tensordict.select("observation")
        inputs.set("observation", self.standardize(inputs.get("observation")))
        return tensordict.set("action", self.actor(inputs).get("action"))


class TD3BC(Algorithm):
    """TD3+BC on :class:`~torchrl.objectives.TD3BCLoss`, from ``conf/algo/td3bc.yaml``'s config (arguments as in
    :class:`~torchrl_bail.algorithms.base.Algorithm`).

    The config's ``actor`` block is the deterministic tanh actor (``hidden``, Adam ``lr``), ``critic`` the two
    independently initialised critics ``(s, a) -> hidden -> 1`` (``hidden``, ``lr``, ``vmap``); ``alpha``,
    ``policy_noise``, ``noise_clip`` and ``gamma`` go to the loss, ``tau`` to the target update, ``policy_delay``
    sets the actor's cadence and ``normalize_observations`` / ``normalize_eps`` the standardisation.
    """

    name = "td3bc"
    seed_stack_refusal = "TorchRL's TD3BCLoss weighs its Q term by mean |Q| over the whole mini-batch"
    state_attributes = ("updates",)

    def __init__(self, obs_dim: int, action_spec: TensorSpec, config, device="cpu") -> None:
        super().__init__(obs_dim, action_spec, config, device)
        cfg = self.config
        act_dim = action_spec.shape[-1]
        actor = make_deterministic_actor(obs_dim, action_spec, tuple(cfg.actor.hidden))
        critics = [make_qvalue_network(obs_dim, act_dim, tuple(cfg.critic.hidden)) for _ in range(2)]
        max_action = float(action_spec.space.high.abs().max())
        self.loss = TD3BCLoss(actor, critics, action_spec=action_spec, num_qvalue_nets=2,
                              policy_noise=cfg.policy_noise * max_action, noise_clip=cfg.noise_clip * max_action,
                              alpha=cfg.alpha, loss_function="l2",
                              deactivate_vmap=not use_vmap(cfg.critic.vmap, self.device)).to(self.device)
        self.loss.make_value_estimator(ValueEstimators.TD0, gamma=cfg.gamma)
        self.target_updater = fused_soft_update(self.loss, tau=float(cfg.tau))
        self.standardize = Standardize(obs_dim).to(self.device)
        self.modules["loss"] = self.loss
        self.modules["standardize"] = self.standardize
        self.optimizers["critic"] = adam(self.loss.qvalue_network_params.parameters(), cfg.critic.lr)
        self.optimizers["actor"] = adam(self.loss.actor_network_params.parameters(), cfg.actor.lr)
        self._policy = StandardizedPolicy(self.standardize, actor)
        #: updates so far: the actor steps on every ``policy_delay``-th
        self.updates = 0

    @property
    def policy(self) -> StandardizedPolicy:
        return self._policy

    def prepare(self, data: TensorDictBase, ctx: PrepareContext) -> TensorDictBase:
        """What the loss reads, observations (and next observations) standardised with the batch's statistics,
        which :attr:`standardize` keeps for the policy; the caller's ``data`` is left as it is."""
        missing = [key for key in self.loss.in_keys if key not in data.keys(include_nested=True)]
        if missing:
            raise KeyError(f"TD3+BC needs the batch entries {self.loss.in_keys}; missing {missing}")
        data = data.select(*self.loss.in_keys)
        if self.config.normalize_observations:
            observation = data.get("observation")
            loc, scale = observation.mean(0), observation.std(0, correction=0) + self.config.normalize_eps
            for key in ("observation", ("next", "observation")):
                data.set(key, (data.get(key) - loc) / scale)  # what self.standardize computes, on the data's device
            self.standardize.loc.copy_(loc)
            self.standardize.scale.copy_(scale)
        return data

    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        self.updates += 1
        if self.updates % self.config.policy_delay == 0:
            return self._full_update(batch)
        return self._critic_update(batch)

    def compile(self, mode: bool | str = True, *, backend: str = "inductor", cudagraphs: bool | None = None) -> None:
        """As :meth:`Algorithm.compile <torchrl_bail.algorithms.base.Algorithm.compile>`, for both kinds of update
        (:meth:`update` picks one from its count, Python state a compiled graph must not hold)."""
        for method in ("_critic_update", "_full_update"):
            self.compiled_method = method
            super().compile(mode, backend=backend, cudagraphs=cudagraphs)

    def _critic_update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        metrics = self._critic_step(batch)
        with torch.no_grad():
            loss_actor, meta_actor = self.loss.actor_loss(batch)
        return {**metrics, **self._actor_metrics(loss_actor, meta_actor), "actor_step": torch.zeros_like(loss_actor)}

    def _full_update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        metrics = self._critic_step(batch)
        loss_actor, meta_actor = self.loss.actor_loss(batch)
        self._step("actor", loss_actor)
        self.target_updater.step()
        loss_actor = loss_actor.detach()
        return {**metrics, **self._actor_metrics(loss_actor, meta_actor), "actor_step": torch.ones_like(loss_actor)}

    def _critic_step(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        loss_qvalue, meta = self.loss.qvalue_loss(batch)
        self._step("critic", loss_qvalue)
        return {"loss_qvalue": loss_qvalue.detach(), "target_value": meta["target_value"].mean()}

    @staticmethod
    def _actor_metrics(loss_actor: torch.Tensor, meta: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        return {"loss_actor": loss_actor, "bc_loss": meta["bc_loss"], "lmbd": meta["lmbd"].detach(),
                "q_actor": meta["state_action_value_actor"].mean()}

    def _step(self, name: str, loss: torch.Tensor) -> None:
        optimizer = self.optimizers[name]
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()

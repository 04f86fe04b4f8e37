"""The SAC behaviour agent of the ``sac`` and execution batches (paper Sec. 5; supp. E); the shared SAC run that
trains and stores it is :mod:`torchrl_bail.behaviour.sac_run`.

**The SAC agent** ("sac_adapt", the authors' data generator) on TorchRL's :class:`~torchrl.objectives.SACLoss`
(v2: no state-value net):

* tanh-Gaussian policy (:func:`~torchrl_bail.modules.make_sac_actor`) ``obs -> 256 -> 256 -> (mu, log sigma)``,
  ``log sigma`` clamped to [-20, 2], action ``max_action * tanh(mu + sigma * eps)``; its log-probability is that of
  the *unscaled* tanh output in [-1, 1], as in sac_adapt (``sac.log_prob_on: tanh``,
  :class:`~torchrl_bail.modules.TanhNormalScoredOnTanh`), in the actor loss, the alpha loss and the soft-Q target
  alike; the critics see the scaled action;
* twin critics ``(s, a) -> 256 -> 256 -> 1`` with target copies, squared TD error summed over the two critics,
  a TD(0) target with gamma 0.99 that bootstraps on ``terminated``, Polyak averaging 0.995
  (``SoftUpdate(eps=0.995)``);
* automatic entropy tuning, ``log alpha`` initialised to 0, target entropy ``-|A|`` (``target_entropy: auto``) on the
  tanh output. With ``log_prob_on: action`` (TorchRL's density of the scaled action) ``auto`` becomes
  ``-|A| + sum(log max_action)``, which re-centres alpha's tuning but leaves ``-alpha * sum(log max_action)`` in
  every soft-Q target (about ``+15.6 alpha`` per step on Humanoid, bound 0.4): not the authors' agent. With bound 1
  (Hopper, Walker2d, HalfCheetah, Ant) both settings are the same numbers, so ``log_prob_on`` enters the run's
  identity (and the batch hash) only when a bound differs from 1 (:func:`~torchrl_bail.data.cache.sac_identity`);
* Adam 3e-4 for the actor, the critics and alpha; batch 256 drawn uniformly from everything stored;
* ``start_steps`` (10^4) uniformly random actions, then actions sampled from the policy; at the end of every episode
  ``episode_length`` gradient steps; every ``eval_every`` (5000) env steps an evaluation of ``eval_episodes`` (10)
  deterministic episodes (``max_action * tanh(mu)``).
"""


from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.objectives import SACLoss, ValueEstimators
from torchrl.objectives.utils import distance_loss
from torchrl.objectives.value.functional import td0_return_estimate

from torchrl_bail.behaviour.checkpoint import CheckpointableAgent
from torchrl_bail.modules import PlainMLP, fused_soft_update, make_qvalue_network, make_sac_actor

__all__ = ["SACAgent"]

class SACAgent(CheckpointableAgent):
    """sac_adapt's SAC on TorchRL's :class:`~torchrl.objectives.SACLoss` (see the module docstring)."""

    OPTIMIZERS = ("actor_optim", "critic_optim", "alpha_optim")  # saved with the networks by state_dict()

    def __init__(self, obs_dim: int, action_spec, *, actor_hidden: Sequence[int] = (256, 256),
                 critic_hidden: Sequence[int] = (256, 256), actor_lr: float = 3e-4, critic_lr: float = 3e-4,
                 alpha_lr: float = 3e-4, gamma: float = 0.99, polyak: float = 0.995, alpha_init: float = 1.0,
                 target_entropy: float | str = "auto", log_std_min: float = -20.0, log_std_max: float = 2.0,
                 batch_size: int = 256, loss_function: str = "l2", log_prob_on: str = "tanh"):
        act_dim = action_spec.shape[-1]
        self.batch_size = int(batch_size)
        self.actor_hidden = list(actor_hidden)
        self.log_std_bounds = (float(log_std_min), float(log_std_max))
        self.log_prob_on = log_prob_on
        self.actor = make_sac_actor(obs_dim, action_spec, actor_hidden, log_std_min=log_std_min,
                                    log_std_max=log_std_max, log_prob_on=log_prob_on)
        self.qvalue = make_qvalue_network(obs_dim, act_dim, critic_hidden)
        if target_entropy == "auto":  # -|A| on the tanh output, wherever the log-probabilities are measured
            half_range = (action_spec.space.high - action_spec.space.low) / 2
            shift = float(torch.log(half_range).sum()) if log_prob_on == "action" else 0.0
            target_entropy = -float(act_dim) + shift
        self.target_entropy = float(target_entropy)
        self.loss = SACLoss(self.actor, self.qvalue, num_qvalue_nets=2, loss_function=loss_function,
                            alpha_init=alpha_init, target_entropy=self.target_entropy, delay_actor=False,
                            delay_qvalue=True, action_spec=action_spec,
                            deactivate_vmap=True)  # on CPU two plain critic calls beat one vmapped call
        self.loss.make_value_estimator(ValueEstimators.TD0, gamma=gamma)  # bootstraps on ~terminated
        self.target_updater = fused_soft_update(self.loss, eps=polyak)  # a SoftUpdate(eps=0.995)
        self.actor_optim = torch.optim.Adam(self.loss.actor_network_params.values(True, True), lr=actor_lr,
                                            foreach=True)
        self.critic_optim = torch.optim.Adam(self.loss.qvalue_network_params.values(True, True), lr=critic_lr,
                                             foreach=True)
        self.alpha_optim = torch.optim.Adam([self.loss.log_alpha], lr=alpha_lr, foreach=True)
        self.updates = 0
        self._fast = _FastSACTerms(self)

    @torch.no_grad()
    def act(self, observation: torch.Tensor, *, deterministic: bool = False) -> torch.Tensor:
        """An action of the policy: sampled (the same draw ``self.actor`` makes under ``RANDOM``, without its
        TensorDict plumbing), or with ``deterministic`` the mean action ``max_action * tanh(mu)``."""
        if not deterministic:
            return self._fast.distribution_at(observation).rsample()
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            td = TensorDict({"observation": observation}, batch_size=observation.shape[:-1])
            return self.actor(td)["action"]

    def losses(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        """``loss_qvalue``, ``loss_actor``, ``loss_alpha`` and ``alpha`` of ``self.loss`` (TorchRL's SACLoss v2) on
        ``batch``, computed without its TensorDict plumbing: the same networks, weights, draws (next-state action
        first, then the actor's) and formulas, about 20 % faster on CPU (benchmarks/bench_collection.py).
        ``tests/test_behaviour_agents.py`` checks it against ``self.loss(batch)``."""
        return self._fast(batch)

    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        """One gradient step on actor, critics and alpha (all from the same mini-batch), then Polyak averaging.

        Returns the detached losses and alpha as 0-d tensors (``float()`` them when logging: no sync per update).
        """
        out = self.losses(batch)
        total = out["loss_actor"] + out["loss_qvalue"] + out["loss_alpha"]
        self.actor_optim.zero_grad(set_to_none=True)
        self.critic_optim.zero_grad(set_to_none=True)
        self.alpha_optim.zero_grad(set_to_none=True)
        total.backward()  # actor loss sees detached critics, alpha loss detached log-probs: no cross-talk
        self.critic_optim.step()
        self.actor_optim.step()
        self.alpha_optim.step()
        self.target_updater.step()
        self.updates += 1
        return {k: out[k].detach() for k in ("loss_qvalue", "loss_actor", "alpha")}

    def train(self, replay, num_updates: int) -> dict[str, float] | None:
        """``num_updates`` gradient steps on mini-batches of ``replay``; the last one's losses as floats."""
        out = None
        for _ in range(int(num_updates)):
            out = self.update(replay.sample())
        return None if out is None else {k: float(v) for k, v in out.items()}

    def policy_state(self) -> dict[str, torch.Tensor]:
        return {k: v.detach().clone() for k, v in self.actor.state_dict().items()}


class _FastSACTerms:
    """SACLoss v2's losses as plain tensor code over the loss module's own parameter tensors (no copies).

    The twin critics are the stacked ``[2, ...]`` parameters of ``SACLoss`` (and their targets), each run by
    :class:`~torchrl_bail.modules.PlainMLP` from views of the stack; the actor is the agent's policy network and
    distribution class.
    """

    def __init__(self, agent: SACAgent):
        loss = agent.loss
        self.loss = loss
        self.num_critics = loss.num_qvalue_nets
        self.runner = PlainMLP.build(loss.qvalue_network.module, ("module",))
        # the stacked [num_critics, ...] tensors themselves (members are sliced per call: always the live weights)
        self.critic = {key: loss.qvalue_network_params.get(key) for key in self.runner.keys}
        self.target_critic = {key: loss.target_qvalue_network_params.get(key) for key in self.runner.keys}
        self.params_net = agent.actor.module[0].module  # obs -> (loc, scale)
        kwargs = agent.actor.module[1].distribution_kwargs
        self.distribution = agent.actor.module[1].distribution_class
        self.low, self.high = kwargs["low"], kwargs["high"]

    def _q(self, stacked: dict, observation: torch.Tensor, action: torch.Tensor, detach: bool = False) -> torch.Tensor:
        """``[num_critics, N]`` action values."""
        members = self.runner.members(stacked, self.num_critics, detach=detach)
        return torch.stack([self.runner(weights, observation, action) for weights in members]).squeeze(-1)

    def distribution_at(self, observation: torch.Tensor):
        """The policy's action distribution at ``observation``."""
        loc, scale = self.params_net(observation)
        return self.distribution(loc, scale, low=self.low, high=self.high, tanh_loc=False)

    def _sample(self, observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.distribution_at(observation).rsample_and_log_prob()

    def __call__(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        loss = self.loss
        alpha = loss.log_alpha.detach().exp()
        observation, action = batch["observation"], batch["action"]
        with torch.no_grad():  # the soft TD(0) target on the target critics (bootstraps on ~terminated)
            next_observation = batch["next", "observation"]
            next_action, next_log_prob = self._sample(next_observation)
            next_q = self._q(self.target_critic, next_observation, next_action)
            next_value = (next_q - alpha * next_log_prob).min(0)[0]
            reward, terminated = batch["next", "reward"].squeeze(-1), batch["next", "terminated"].squeeze(-1)
            target = td0_return_estimate(loss.value_estimator.gamma, next_value, reward, terminated)
        predicted = self._q(self.critic, observation, action)
        loss_qvalue = distance_loss(predicted, target.expand_as(predicted),
                                    loss_function=loss.loss_function).sum(0).mean()
        new_action, log_prob = self._sample(observation)
        min_q = self._q(self.critic, observation, new_action, detach=True).min(0)[0]
        loss_actor = (alpha * log_prob - min_q).mean()
        loss_alpha = (-loss.log_alpha * (log_prob.detach() + loss.target_entropy)).mean()
        return {"loss_qvalue": loss_qvalue, "loss_actor": loss_actor, "loss_alpha": loss_alpha, "alpha": alpha}

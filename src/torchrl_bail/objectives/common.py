"""What BCQ and BEAR share, written once: the soft clipped double-Q target, the VAE + twin-critic loss base
class, and the best-of-N evaluation policy.

Both algorithms (supp. C.2, BCQ, 8.4) train a conditional VAE on the batch's actions, two critics with a target copy,
and an actor with a target copy; their critic target draws ``N`` candidate actions at the next state and takes

    Q'(s') = max_n [ lambda * min_j Q'_j(s', a_n) + (1 - lambda) * max_j Q'_j(s', a_n) ]
    y      = r + gamma * (1 - terminated) * Q'(s')

They differ only in where the candidates come from (BCQ: VAE samples perturbed by the target actor; BEAR: the
target actor's own samples) and in the actor's objective.
"""

from __future__ import annotations

import copy
from abc import abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from tensordict.utils import NestedKey, unravel_key
from torch import nn
from torchrl.modules import ValueOperator
from torchrl.objectives import LossModule
from torchrl.objectives.utils import _cache_values, _vmap_func

from torchrl_bail.modules import PlainMLP
from torchrl_bail.objectives._shared import check_reduction, reduce_per_seed, required_entry
from torchrl_bail.objectives.vae import conditional_vae_loss

__all__ = ["BestOfNPolicy", "TwinCriticVAELoss", "soft_clipped_double_q_target", "expand_samples"]


def soft_clipped_double_q_target(
    next_values: torch.Tensor,
    reward: torch.Tensor,
    terminated: torch.Tensor,
    *,
    gamma: torch.Tensor | float,
    lmbda: torch.Tensor | float,
) -> torch.Tensor:
    """The BCQ/BEAR critic target ``y = r + gamma * (1 - terminated) * max_n softmin_j Q'_j(s', a_n)``.

    ``softmin_j`` is the soft clipped double-Q ``lmbda * min_j + (1 - lmbda) * max_j`` over the critics.

    Args:
        next_values (torch.Tensor): ``Q'_j(s', a_n)``, shape ``[J, *B, N]`` (critics first, samples last).
        reward (torch.Tensor): ``r``, shape ``[*B]`` or ``[*B, 1]``.
        terminated (torch.Tensor): the *true-terminal* flag, shape ``[*B]`` or ``[*B, 1]``. A time-limit
            truncation is not terminal and is bootstrapped; never pass ``done`` here.

    Keyword Args:
        gamma: the discount. lmbda: the weight of the minimum (0.75 for BCQ and BEAR).

    Returns:
        ``y`` of shape ``[*B]``.

    Examples:
        >>> q = torch.tensor([[[1.0, 4.0]], [[3.0, 2.0]]])  # 2 critics, 1 state, 2 samples
        >>> # sample 0: 0.75 * 1 + 0.25 * 3 = 1.5; sample 1: 0.75 * 2 + 0.25 * 4 = 2.5; max = 2.5
        >>> soft_clipped_double_q_target(q, torch.tensor([1.0]), torch.tensor([False]), gamma=0.5, lmbda=0.75)
        tensor([2.2500])
        >>> soft_clipped_double_q_target(q, torch.tensor([1.0]), torch.tensor([True]), gamma=0.5, lmbda=0.75)
        tensor([1.])
    """
    soft = lmbda * next_values.amin(0) + (1 - lmbda) * next_values.amax(0)
    next_value = soft.amax(-1)
    if reward.ndim == next_value.ndim + 1:
        reward = reward.squeeze(-1)
    if terminated.ndim == next_value.ndim + 1:
        terminated = terminated.squeeze(-1)
    not_terminated = (~terminated.bool()).to(next_value.dtype)
    return reward.to(next_value.dtype) + gamma * not_terminated * next_value


def _next(key: NestedKey) -> NestedKey:
    """``("next", key)``, flattened when ``key`` is itself nested."""
    return unravel_key(("next", key))


def expand_samples(tensor: torch.Tensor, num_samples: int) -> torch.Tensor:
    """``[*B, F] -> [*B, N, F]`` (a view)."""
    return tensor.unsqueeze(-2).expand(*tensor.shape[:-1], num_samples, tensor.shape[-1])


class TwinCriticVAELoss(LossModule):
    """Base class of :class:`~torchrl_bail.objectives.bcq.BCQLoss` and :class:`~torchrl_bail.objectives.bear.BEARLoss`.

    It owns the conditional VAE (no target copy), the actor (with a target copy) and the two critics (stacked
    parameters with a target copy, evaluated with :func:`torch.vmap`), and implements what the two losses
    share: :meth:`vae_loss`, :meth:`qvalue_loss` with :func:`soft_clipped_double_q_target`, the ``[S, B]``
    reductions and the pieces :class:`BestOfNPolicy` needs. A subclass says where the critic target's candidate
    actions come from (:meth:`_target_candidates`), where the policy's come from (:meth:`candidate_actions`) and
    what the actor minimises.

    Networks read and write the loss' keys: the critics read ``tensor_keys.observation`` and
    ``tensor_keys.action`` and write ``tensor_keys.state_action_value``.
    """

    @dataclass
    class _AcceptedKeys:
        """Maintains default values for all configurable tensordict keys.

        Attributes:
            observation (NestedKey): the state; the next state is ``("next", observation)``.
                Defaults to ``"observation"``.
            action (NestedKey): the batch's action. Defaults to ``"action"``.
            reward (NestedKey): the reward, read as ``("next", reward)``. Defaults to ``"reward"``.
            terminated (NestedKey): the true-terminal flag, read as ``("next", terminated)``; ``done`` is never
                used, so a time-limit truncation is bootstrapped. Defaults to ``"terminated"``.
            state_action_value (NestedKey): where the critics write ``Q(s, a)``.
                Defaults to ``"state_action_value"``.
        """

        observation: NestedKey = "observation"
        action: NestedKey = "action"
        reward: NestedKey = "reward"
        terminated: NestedKey = "terminated"
        state_action_value: NestedKey = "state_action_value"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    default_value_estimator = None
    #: coefficients a float may be assigned to (``loss.gamma = 0.98``: an in-place update of the buffer)
    _schedulable_buffers = frozenset({"lmbda", "gamma", "kl_weight"})

    actor_network: TensorDictModule
    actor_network_params: TensorDictParams
    target_actor_network_params: TensorDictParams
    qvalue_network: TensorDictModule
    qvalue_network_params: TensorDictParams
    target_qvalue_network_params: TensorDictParams
    vae_network: nn.Module
    vae_network_params: TensorDictParams
    target_vae_network_params: TensorDictParams

    def __init__(
        self,
        actor_network: TensorDictModule,
        qvalue_network: TensorDictModule | Sequence[TensorDictModule],
        vae_network: nn.Module,
        *,
        num_samples: int,
        lmbda: float,
        gamma: float,
        kl_weight: float,
        reduction: str | None,
        deactivate_vmap: bool,
    ) -> None:
        reduction = check_reduction(reduction)
        if int(num_samples) < 1:
            raise ValueError(f"num_samples must be >= 1, got {num_samples}")
        if not 0.0 <= float(lmbda) <= 1.0:
            raise ValueError(f"lmbda must be in [0, 1], got {lmbda}")
        if not 0.0 <= float(gamma) <= 1.0:
            raise ValueError(f"gamma must be in [0, 1], got {gamma}")
        if not float(kl_weight) >= 0:
            raise ValueError(f"kl_weight must be >= 0, got {kl_weight}")
        super().__init__()
        self.convert_to_functional(actor_network, "actor_network", create_target_params=True)
        if isinstance(qvalue_network, (list, tuple)):
            if len(qvalue_network) != 2:
                raise ValueError(f"expected 2 critics, got {len(qvalue_network)}")
            self.convert_to_functional(list(qvalue_network), "qvalue_network", expand_dim=2,
                                       create_target_params=True)
        else:
            self.convert_to_functional(qvalue_network, "qvalue_network", expand_dim=2, create_target_params=True)
        self.convert_to_functional(vae_network, "vae_network")
        self.num_samples = int(num_samples)
        self.register_coeff_buffer("lmbda", lmbda)
        self.register_coeff_buffer("gamma", gamma)
        self.register_coeff_buffer("kl_weight", kl_weight)
        self.reduction = reduction
        self.deactivate_vmap = bool(deactivate_vmap)
        self._make_vmap()

    def _make_vmap(self) -> None:
        self._vmap_qvalue = _vmap_func(self.qvalue_network, (None, 0), randomness=self.vmap_randomness,
                                       pseudo_vmap=self.deactivate_vmap)
        network = self.qvalue_network
        self._plain_critic = (PlainMLP.build(network.module, ("module",))
                              if type(network) in (TensorDictModule, ValueOperator) else None)

    def __deepcopy__(self, memo: dict) -> TwinCriticVAELoss:
        """A copy that computes from its own tensors only: the cached detached critic parameters (views of this
        loss' critics, kept between calls) stay behind and are rebuilt from the copy's critics on first use, and
        the vmapped critic is rebuilt on the copy's network. (TorchRL's own ``TD3Loss`` carries its cache over.)"""
        cls = type(self)
        new = cls.__new__(cls)
        memo[id(self)] = new
        new.__dict__.update({key: {} if key == "_cache" else copy.deepcopy(value, memo)
                             for key, value in self.__dict__.items()})
        new._make_vmap()
        return new

    def _plain_critic_members(self, params: TensorDictBase) -> list[dict] | None:
        """The critics' weights as plain tensors when they are MLPs reading ``(observation, action)``, else None."""
        if self._plain_critic is None:
            return None
        k = self.tensor_keys
        network = self.qvalue_network
        if list(network.in_keys) != [k.observation, k.action] or list(network.out_keys) != [k.state_action_value]:
            return None
        return self._plain_critic.members(params, 2)

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    @property
    def in_keys(self) -> list[NestedKey]:
        k = self.tensor_keys
        return [k.observation, k.action, _next(k.observation), _next(k.reward), _next(k.terminated)]

    @property
    @_cache_values
    def _cached_detach_qvalue_network_params(self) -> TensorDictBase:
        """Both critics' current parameters, detached (views: they follow the optimizer's in-place steps)."""
        return self.qvalue_network_params.detach()

    @property
    @_cache_values
    def _cached_detached_q1_params(self) -> TensorDictBase:
        """The first critic's current parameters, detached."""
        return self._cached_detach_qvalue_network_params[0]

    # -- networks on plain tensors -------------------------------------------------------------------
    def _q_values(self, observation: torch.Tensor, action: torch.Tensor, params: TensorDictBase) -> torch.Tensor:
        """Both critics: ``[2, *B]`` for inputs ``[*B, F]``.

        With ``deactivate_vmap`` the critics run one after the other (each with its slice of the stacked
        parameters): on CPU two plain matrix products beat the batched one ``torch.vmap`` turns them into.
        """
        k = self.tensor_keys
        if self.deactivate_vmap:
            members = self._plain_critic_members(params)
            if members is not None:
                return torch.stack([self._plain_critic(w, observation, action) for w in members]).squeeze(-1)
        td = TensorDict({k.observation: observation, k.action: action}, batch_size=observation.shape[:-1])
        if not self.deactivate_vmap:
            return self._vmap_qvalue(td, params).get(k.state_action_value).squeeze(-1)
        values = []
        for member in params.unbind(0):
            with member.to_module(self.qvalue_network, preserve_module_state=False):
                values.append(self.qvalue_network(td).get(k.state_action_value))
        return torch.stack(values).squeeze(-1)

    def q1_value(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """``Q_1(s, a)`` with the current, detached parameters of the first critic: ``[*B]``."""
        k = self.tensor_keys
        members = self._plain_critic_members(self._cached_detach_qvalue_network_params)
        if members is not None:
            return self._plain_critic(members[0], observation, action).squeeze(-1)
        td = TensorDict({k.observation: observation, k.action: action}, batch_size=observation.shape[:-1])
        with self._cached_detached_q1_params.to_module(self.qvalue_network, preserve_module_state=False):
            return self.qvalue_network(td).get(k.state_action_value).squeeze(-1)

    def _actor(self, observation: torch.Tensor, action: torch.Tensor | None, params: TensorDictBase) -> TensorDictBase:
        """Runs the actor with ``params`` on the observation (and a candidate action, for BCQ)."""
        k = self.tensor_keys
        td = TensorDict({k.observation: observation}, batch_size=observation.shape[:-1])
        if action is not None:
            td.set(k.action, action)
        with params.to_module(self.actor_network, preserve_module_state=False):
            return self.actor_network(td)

    def _vae_samples(self, observation: torch.Tensor, num_samples: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``num_samples`` VAE actions per state with clipped prior latents: ``(actions, pre-tanh)``."""
        with self.vae_network_params.to_module(self.vae_network, preserve_module_state=False):
            return self.vae_network.sample(observation, num_samples)

    @abstractmethod
    def _target_candidates(self, next_observation: torch.Tensor, num_samples: int) -> torch.Tensor:
        """Candidate actions ``[*B, N, |A|]`` at the next state for the critic target (no gradient needed)."""

    @abstractmethod
    def candidate_actions(self, observation: torch.Tensor, num_samples: int) -> torch.Tensor:
        """Candidate actions ``[*B, N, |A|]`` the evaluation policy picks the best of (by ``Q_1``)."""

    # -- helpers -----------------------------------------------------------------------------------
    def _reduce(self, loss: torch.Tensor, tensordict: TensorDictBase) -> torch.Tensor:
        return reduce_per_seed(self, loss, tensordict)

    def _terminated(self, tensordict: TensorDictBase) -> torch.Tensor:
        key = _next(self.tensor_keys.terminated)
        terminated = tensordict.get(key, None)
        if terminated is None:
            raise KeyError(
                f"{type(self).__name__}: the batch has no {key!r} entry. The critic target bootstraps on the "
                f"true-terminal flag (never on 'done', which would stop bootstrapping at time limits); store it "
                f"or point set_keys(terminated=...) at it"
            )
        return terminated

    # -- shared losses -----------------------------------------------------------------------------
    def vae_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """``(loss_vae, {"recon_loss", "kl_loss"})``: reconstruction MSE + ``kl_weight`` x KL; VAE only."""
        loss, metadata = conditional_vae_loss(self, tensordict)
        self._clear_weakrefs(tensordict, "vae_network_params")
        return loss, metadata

    def qvalue_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """``(loss_qvalue, {"q_mean", "target_value_mean"})``: the sum of both critics' squared errors to
        :func:`soft_clipped_double_q_target`, computed without gradient from the target networks; critics only.
        """
        k = self.tensor_keys
        with torch.no_grad():
            next_observation = required_entry(self, tensordict, _next(k.observation))
            candidates = self._target_candidates(next_observation, self.num_samples)
            next_values = self._q_values(expand_samples(next_observation, self.num_samples), candidates,
                                         self.target_qvalue_network_params)
            target = soft_clipped_double_q_target(
                next_values, required_entry(self, tensordict, _next(k.reward)), self._terminated(tensordict),
                gamma=self.gamma, lmbda=self.lmbda,
            )
        q = self._q_values(required_entry(self, tensordict, k.observation), required_entry(self, tensordict, k.action),
                           self.qvalue_network_params)
        loss = self._reduce((q - target).pow(2).sum(0), tensordict)
        metadata = {"q_mean": q.detach().mean(0).mean(-1), "target_value_mean": target.mean(-1)}
        self._clear_weakrefs(tensordict, "qvalue_network_params", "target_qvalue_network_params",
                             "target_actor_network_params", "vae_network_params")
        return loss, metadata


class BestOfNPolicy(TensorDictModuleBase):
    """The BCQ/BEAR evaluation policy: ``num_samples`` candidate actions per state, the one with the highest ``Q_1``.

    Candidates come from the loss' :meth:`~TwinCriticVAELoss.candidate_actions` (BCQ: VAE samples perturbed by
    the actor; BEAR: the actor's samples), ``Q_1`` is the first critic with its current parameters. It reads
    ``tensor_keys.observation`` and writes ``tensor_keys.action`` for any leading batch shape (e.g. ``[E]``
    environments at once), never builds a graph, and draws its candidates from torch's global random stream
    whatever the exploration type (this *is* the authors' deterministic test-time procedure).

    Args:
        loss_module (TwinCriticVAELoss): the loss whose networks act; registered as a submodule, so the
            policy's ``state_dict`` and ``.to()`` cover them.
        num_samples (int): candidates per state (10 in the 2019 BCQ and in BEAR).
    """

    def __init__(self, loss_module: TwinCriticVAELoss, num_samples: int) -> None:
        super().__init__()
        if int(num_samples) < 1:
            raise ValueError(f"num_samples must be >= 1, got {num_samples}")
        self.loss_module = loss_module
        self.num_samples = int(num_samples)
        self.in_keys = [loss_module.tensor_keys.observation]
        self.out_keys = [loss_module.tensor_keys.action]

    @torch.no_grad()
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        observation = tensordict.get(self.in_keys[0])
        candidates = self.loss_module.candidate_actions(observation, self.num_samples)
        q1 = self.loss_module.q1_value(expand_samples(observation, self.num_samples), candidates)
        best = q1.argmax(-1)
        index = best[..., None, None].expand(*best.shape, 1, candidates.shape[-1])
        tensordict.set(self.out_keys[0], candidates.gather(-2, index).squeeze(-2))
        return tensordict

"""Fitted Q Evaluation (FQE): the value of a fixed policy estimated from the batch alone, without the simulator.

The loss regresses ``Q(s, a)`` on the batch's transitions to ``r + gamma * (1 - terminated) * Q'(s', pi(s'))``
with a target copy ``Q'`` of the network; :meth:`FQELoss.policy_value` reads the estimate off the fitted network,
the mean of ``Q(s_0, pi(s_0))`` over the batch's episode starts. The loop that fits it, with its defaults, and the
command that scores a run's policy are in :mod:`torchrl_bail.ope`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictModule, dispatch
from tensordict.utils import NestedKey, unravel_key
from torchrl.envs.utils import set_exploration_type
from torchrl.modules import ValueOperator
from torchrl.objectives import LossModule

from torchrl_bail.modules import PlainMLP
from torchrl_bail.objectives._shared import check_reduction, reduce_per_seed, required_entry

__all__ = ["FQELoss", "episode_starts"]


def _next(key: NestedKey) -> NestedKey:
    """``("next", key)``, flattened when ``key`` is itself nested."""
    return unravel_key(("next", key))


def _drop_trailing_one(tensor: torch.Tensor, batch_dims: int) -> torch.Tensor:
    return tensor.squeeze(-1) if tensor.ndim == batch_dims + 1 and tensor.shape[-1] == 1 else tensor


def episode_starts(episode: torch.Tensor) -> torch.Tensor:
    """``[N]`` booleans, True at the first row of each episode block of a TED batch (``episode`` ids, ``[N]``).

    The batch's first row starts an episode; every later row whose id differs from the row before starts one too,
    as the batches of this package (and the importers' conversions) store episodes in order.

    Examples:
        >>> episode_starts(torch.tensor([0, 0, 0, 1, 1, 2])).tolist()
        [True, False, False, True, False, True]
    """
    if episode.ndim != 1 or episode.numel() == 0:
        raise ValueError(f"episode ids must be a non-empty [N] tensor, got shape {tuple(episode.shape)}")
    starts = torch.ones_like(episode, dtype=torch.bool)
    starts[1:] = episode[1:] != episode[:-1]
    return starts


#: FQE's discount: :class:`FQELoss`'s default and the gamma of the evaluation's discounted return
#: (:class:`torchrl_bail.evaluation.Evaluator`), so that every OPE estimate is judged against the true return it
#: estimates; :attr:`torchrl_bail.ope.FQESettings.gamma` repeats it (that module loads no torch; tests/test_fqe.py
#: holds the two equal). ``0.99``: d3rlpy's FQE default
FQE_GAMMA = 0.99


class FQELoss(LossModule):
    r"""Fitted Q Evaluation of a fixed policy ``pi``: the squared TD error of ``Q(s, a)`` against ``Q'(s', pi(s'))``.

    Presented in "Batch Policy Learning under Constraints", Le, Voloshin and Yue, ICML 2019,
    https://arxiv.org/abs/1903.08738 (Fitted Q Evaluation); used to choose among offline-trained
    policies without the simulator in "Hyperparameter Selection for Offline Reinforcement Learning", Paine et al.,
    2020, https://arxiv.org/abs/2007.09055.

    For a batch of transitions ``(s, a, r, s', terminated)`` and the fixed policy ``pi``:

    * ``y = r + gamma * (1 - terminated) * Q'(s', pi(s'))``, computed without gradient, ``Q'`` the target copy of
      the network (a time-limit truncation is not terminal: it is bootstrapped);
    * ``loss_qvalue`` per transition: ``(Q(s, a) - y)^2``; it reaches the Q network only (the policy is frozen).

    Le et al. fit each ``Q_k`` to the targets of ``Q_{k-1}`` to convergence; with gradient steps this is a target
    network copied every ``target_update_period`` steps (a hard update, e.g. :class:`~torchrl.objectives.HardUpdate`,
    which the fitting loop :func:`torchrl_bail.ope.fit_fqe` steps). The policy's estimated value is
    :meth:`policy_value`: the mean of ``Q(s_0, pi(s_0))`` over the batch's episode starts (Paine et al.'s
    initial-state value estimate), a *discounted* value: ``gamma`` counts, so it ranks policies rather than
    predicting their undiscounted test return.

    Defaults of the fitting (:class:`torchrl_bail.ope.FQESettings`, used by ``python -m torchrl_bail.ope``) and their
    sources:

    * Q network ``(s, a) -> 256 -> 256 -> 1``, ReLU; Adam, learning rate ``1e-4``; mini-batches of ``100``
      transitions; ``gamma = 0.99``; the target copied every ``100`` updates (a hard update, Le et al.'s iterations):
      d3rlpy's FQE (``d3rlpy.ope.FQEConfig``: ``learning_rate=1e-4``, ``batch_size=100``, ``gamma=0.99``,
      ``target_update_interval=100``; its default vector encoder is 256-256 ReLU), which cites Le et al. and whose
      offline-policy-selection tutorial follows Paine et al.
    * updates: d3rlpy's off-policy-evaluation reference page fits FQE for ``10^5``
      (``fqe.fit(dataset, n_steps=100000)``); here a fit stops by a rule on its curve, at most at ``5 x 10^5``
      (:class:`~torchrl_bail.ope.FQESettings`: none of the OPE study's kept curves had settled at ``10^5``).
    * Not verified here: the appendix of Paine et al. (its network sizes, learning rate, number of updates and
      target period) could not be read when this was written; the values above are d3rlpy's, checked in its source.

    Args:
        qvalue_network (TensorDictModule): ``Q``; reads ``tensor_keys.observation`` and ``tensor_keys.action`` and
            writes ``tensor_keys.state_action_value`` (``[*B, 1]`` or ``[*B]``), e.g.
            :func:`~torchrl_bail.modules.make_qvalue_network`. Its parameters are the loss' parameters (shared);
            a target copy is made.
        policy_network (TensorDictModule): ``pi``; reads ``tensor_keys.observation`` and writes
            ``tensor_keys.action`` (e.g. a policy from :func:`~torchrl_bail.evaluation.policy.load_policy`). Its weights
            are
            copied at construction into buffers (``policy_network_params``: they follow ``.to()`` and the
            ``state_dict`` and are never trained). It acts in TorchRL's deterministic mode; a policy that samples
            anyway (BCQ's and BEAR's best-of-N) draws from torch's global generator, one action per state.

    Keyword Args:
        gamma (float): discount, in ``[0, 1]``. Defaults to :data:`FQE_GAMMA` (``0.99``), FQE's default, which
            :class:`torchrl_bail.ope.FQESettings` and the evaluation's discounted return take too.
        reduction (str, optional): ``"none"`` | ``"mean"`` | ``"sum"``. Defaults to ``"mean"``. ``"none"`` gives one
            value per transition (``[B]`` or ``[S, B]``); ``"mean"`` averages over the last batch dimension and then
            over the leading ones.

    The output holds ``loss_qvalue`` and detached diagnostics reduced over the last batch dimension: ``q_mean``
    (``Q(s, a)``), ``target_value_mean`` (``y``) and ``td_error_abs_mean`` (``|Q(s, a) - y|``).

    Choices:

    * **The next action.** When the batch carries ``("next", tensor_keys.policy_action)`` the target reads
      ``pi(s')`` from it instead of running the policy: for a fixed policy and a fixed batch it is computed once
      (:meth:`add_policy_actions`), which also fixes a sampling policy's draws for the whole fit.
    * **Bootstrap mask** = ``("next", "terminated")``; a missing entry raises instead of falling back on ``done``.
    * **gamma** is a constructor argument (a buffer that takes a float: ``loss.gamma = 0.98``), not a TorchRL value
      estimator, as in this package's other bootstrapping losses: ``default_value_estimator`` is ``None``.
    * **reset_parameters_recursive** redraws the Q network and its target only; the evaluated policy stays.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.objectives import HardUpdate
        >>> from torchrl_bail.modules import action_spec_from_bounds, make_deterministic_actor, make_qvalue_network
        >>> from torchrl_bail.objectives.fqe import FQELoss
        >>> _ = torch.manual_seed(0)
        >>> policy = make_deterministic_actor(11, action_spec_from_bounds([-1.0] * 3, [1.0] * 3), (64, 64))
        >>> loss = FQELoss(make_qvalue_network(11, 3, (256, 256)), policy, gamma=0.99)
        >>> updater = HardUpdate(loss, value_network_update_interval=100 - 1)  # copies on every 100th step()
        >>> optimizer = torch.optim.Adam(loss.parameters(), lr=1e-4)
        >>> n = 32
        >>> data = TensorDict({"observation": torch.randn(n, 11), "action": torch.rand(n, 3) * 2 - 1,
        ...                    "episode": torch.arange(n) // 8,
        ...                    "next": {"observation": torch.randn(n, 11), "reward": torch.randn(n, 1),
        ...                             "terminated": torch.zeros(n, 1, dtype=torch.bool)}}, [n])
        >>> out = loss(data)
        >>> sorted(out.keys())
        ['loss_qvalue', 'q_mean', 'target_value_mean', 'td_error_abs_mean']
        >>> optimizer.zero_grad(); out["loss_qvalue"].backward(); optimizer.step(); updater.step()
        >>> loss.policy_value(data).shape  # the mean of Q(s_0, pi(s_0)) over the 4 episode starts
        torch.Size([])

    This class is compatible with non-tensordict based calls too: the keyword arguments are the ``in_keys``
    (nested keys joined by ``_``). ``select_out_keys`` picks what comes back.

    Examples:
        >>> import torch
        >>> from torchrl_bail.modules import action_spec_from_bounds, make_deterministic_actor, make_qvalue_network
        >>> from torchrl_bail.objectives.fqe import FQELoss
        >>> policy = make_deterministic_actor(11, action_spec_from_bounds([-1.0] * 3, [1.0] * 3), (64, 64))
        >>> loss = FQELoss(make_qvalue_network(11, 3, (64, 64)), policy)
        >>> _ = loss.select_out_keys("loss_qvalue")
        >>> loss(observation=torch.randn(8, 11), action=torch.rand(8, 3) * 2 - 1,
        ...      next_observation=torch.randn(8, 11), next_reward=torch.randn(8, 1),
        ...      next_terminated=torch.zeros(8, 1, dtype=torch.bool)).shape
        torch.Size([])
    """

    @dataclass
    class _AcceptedKeys:
        """Maintains default values for all configurable tensordict keys.

        Attributes:
            observation (NestedKey): the state; the next state is ``("next", observation)``.
                Defaults to ``"observation"``.
            action (NestedKey): the batch's action, and the policy's output. Defaults to ``"action"``.
            reward (NestedKey): the reward, read as ``("next", reward)``. Defaults to ``"reward"``.
            terminated (NestedKey): the true-terminal flag, read as ``("next", terminated)``; ``done`` is never
                used, so a time-limit truncation is bootstrapped. Defaults to ``"terminated"``.
            state_action_value (NestedKey): where the Q network writes ``Q(s, a)``.
                Defaults to ``"state_action_value"``.
            policy_action (NestedKey): where :meth:`~FQELoss.add_policy_actions` stores ``pi(s)`` (and, under
                ``"next"``, ``pi(s')``); read when present instead of running the policy.
                Defaults to ``"policy_action"``.
            episode (NestedKey): the episode id of each transition, which :meth:`~FQELoss.policy_value` finds the
                episode starts by. Defaults to ``"episode"``.
        """

        observation: NestedKey = "observation"
        action: NestedKey = "action"
        reward: NestedKey = "reward"
        terminated: NestedKey = "terminated"
        state_action_value: NestedKey = "state_action_value"
        policy_action: NestedKey = "policy_action"
        episode: NestedKey = "episode"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    default_value_estimator = None
    out_keys = ["loss_qvalue", "q_mean", "target_value_mean", "td_error_abs_mean"]
    #: coefficients a float may be assigned to (``loss.gamma = 0.98``: an in-place update of the buffer)
    _schedulable_buffers = frozenset({"gamma"})

    qvalue_network: TensorDictModule
    qvalue_network_params: TensorDictParams
    target_qvalue_network_params: TensorDictParams
    policy_network: TensorDictModule
    policy_network_params: TensorDictParams

    def __init__(
        self,
        qvalue_network: TensorDictModule,
        policy_network: TensorDictModule,
        *,
        gamma: float = FQE_GAMMA,
        reduction: Literal["mean", "sum", "none"] | None = None,
    ) -> None:
        reduction = check_reduction(reduction)
        if not 0.0 <= float(gamma) <= 1.0:
            raise ValueError(f"FQELoss: gamma must be in [0, 1], got {gamma}")
        super().__init__()
        self.convert_to_functional(qvalue_network, "qvalue_network", create_target_params=True)
        # the evaluated policy: a frozen copy of its weights, as buffers (never in parameters(), never trained)
        frozen = TensorDict.from_module(policy_network).detach().clone()
        self.policy_network_params = TensorDictParams(frozen, no_convert=True)
        self.__dict__["policy_network"] = policy_network
        self.register_coeff_buffer("gamma", float(gamma))
        self.reduction = reduction
        network = self.qvalue_network
        self._plain_q = (PlainMLP.build(network.module, ("module",))
                         if type(network) in (TensorDictModule, ValueOperator) else None)

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    @property
    def in_keys(self) -> list[NestedKey]:
        k = self.tensor_keys
        return [k.observation, k.action, _next(k.observation), _next(k.reward), _next(k.terminated)]

    def reset_parameters_recursive(self) -> None:
        """Redraws the Q network and its target; the evaluated policy is left as it is."""
        self._reset_module_parameters("qvalue_network", self.qvalue_network)

    # -- networks on plain tensors ---------------------------------------------------------------------
    def _q(self, observation: torch.Tensor, action: torch.Tensor, params: TensorDictBase) -> torch.Tensor:
        """``Q(s, a)`` with ``params``: ``[*B]`` for inputs ``[*B, F]``.

        An MLP reading ``(observation, action)`` runs from plain tensors (:class:`~torchrl_bail.modules.PlainMLP`:
        the same operations, without swapping the weights into the module at every call); any other network runs
        through ``params.to_module``.
        """
        k = self.tensor_keys
        network = self.qvalue_network
        if (self._plain_q is not None and list(network.in_keys) == [k.observation, k.action]
                and list(network.out_keys) == [k.state_action_value]):
            value = self._plain_q({key: params.get(key) for key in self._plain_q.keys}, observation, action)
            return _drop_trailing_one(value, observation.ndim - 1)
        td = TensorDict({k.observation: observation, k.action: action}, batch_size=observation.shape[:-1])
        with params.to_module(self.qvalue_network, preserve_module_state=False):
            value = self.qvalue_network(td).get(k.state_action_value)
        return _drop_trailing_one(value, observation.ndim - 1)

    @torch.no_grad()
    def policy_actions(self, observation: torch.Tensor) -> torch.Tensor:
        """``pi(s)`` for observations ``[*B, F]`` (deterministic mode, no gradient): ``[*B, |A|]``."""
        k = self.tensor_keys
        td = TensorDict({k.observation: observation}, batch_size=observation.shape[:-1])
        with set_exploration_type(self.deterministic_sampling_mode), \
                self.policy_network_params.to_module(self.policy_network, preserve_module_state=False):
            return self.policy_network(td).get(k.action)

    @torch.no_grad()
    def add_policy_actions(self, tensordict: TensorDictBase, *, chunk: int = 65536,
                           on_chunk: Callable[[int], None] | None = None) -> TensorDictBase:
        """Writes ``pi(s)`` under ``tensor_keys.policy_action`` and ``pi(s')`` under ``("next", policy_action)``
        (``chunk`` rows at a time) into a ``[N]`` ``tensordict`` and returns it: the targets and
        :meth:`policy_value` then read them instead of running the policy at every call. ``on_chunk``, when given,
        is called with the number of rows of each chunk once it is done (``2 N`` rows in all: a progress bar's
        ``update``; a sampling policy's ``2 N`` draws can take minutes)."""
        k = self.tensor_keys

        def chunk_actions(part: torch.Tensor) -> torch.Tensor:
            actions = self.policy_actions(part)
            if on_chunk is not None:
                on_chunk(part.shape[0])
            return actions

        for observation_key in (k.observation, _next(k.observation)):
            observation = required_entry(self, tensordict, observation_key)
            actions = torch.cat([chunk_actions(part) for part in observation.split(chunk)])
            key = k.policy_action if observation_key == k.observation else _next(k.policy_action)
            tensordict.set(key, actions)
        return tensordict

    def _action_of_policy(self, tensordict: TensorDictBase, observation_key: NestedKey,
                          action_key: NestedKey) -> tuple[torch.Tensor, torch.Tensor]:
        """``(s, pi(s))``: the stored policy action when the batch has one, else the policy's."""
        observation = required_entry(self, tensordict, observation_key)
        action = tensordict.get(action_key, None)
        return observation, self.policy_actions(observation) if action is None else action

    def _terminated(self, tensordict: TensorDictBase) -> torch.Tensor:
        key = _next(self.tensor_keys.terminated)
        terminated = tensordict.get(key, None)
        if terminated is None:
            raise KeyError(
                f"FQELoss: the batch has no {key!r} entry. The target bootstraps on the true-terminal flag (never on "
                f"'done', which would stop bootstrapping at time limits); store it or point set_keys(terminated=...) "
                f"at it"
            )
        return terminated

    # -- the estimate ---------------------------------------------------------------------------------------
    @torch.no_grad()
    def state_values(self, tensordict: TensorDictBase) -> torch.Tensor:
        """``Q(s, pi(s))`` per row with the current network (``pi(s)`` from ``tensor_keys.policy_action`` when
        present): the batch shape."""
        k = self.tensor_keys
        observation, action = self._action_of_policy(tensordict, k.observation, k.policy_action)
        value = self._q(observation, action, self.qvalue_network_params)
        self._clear_weakrefs(tensordict, "qvalue_network_params", "policy_network_params")
        return value

    @torch.no_grad()
    def policy_value(self, tensordict: TensorDictBase) -> torch.Tensor:
        """The policy's estimated value: the mean of ``Q(s_0, pi(s_0))`` over the episode starts of a ``[N]`` batch
        (:func:`episode_starts` of ``tensor_keys.episode``), a scalar."""
        starts = episode_starts(required_entry(self, tensordict, self.tensor_keys.episode))
        return self.state_values(tensordict[starts]).mean()

    # -- the loss -----------------------------------------------------------------------------------------
    def qvalue_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """``(loss_qvalue, {"q_mean", "target_value_mean", "td_error_abs_mean"})``: the squared TD error of
        ``Q(s, a)`` against ``r + gamma * (1 - terminated) * Q'(s', pi(s'))``, reduced; the Q network only.

        Args:
            tensordict (TensorDictBase): the transitions (:attr:`in_keys`), batch shape ``[B]`` or ``[S, B]``.
        """
        k = self.tensor_keys
        batch_dims = tensordict.batch_dims
        with torch.no_grad():
            next_observation, next_action = self._action_of_policy(tensordict, _next(k.observation),
                                                                   _next(k.policy_action))
            next_value = self._q(next_observation, next_action, self.target_qvalue_network_params)
            reward = _drop_trailing_one(required_entry(self, tensordict, _next(k.reward)), batch_dims)
            terminated = _drop_trailing_one(self._terminated(tensordict), batch_dims)
            not_terminated = (~terminated.bool()).to(next_value.dtype)
            target = reward.to(next_value.dtype) + self.gamma * not_terminated * next_value
        q = self._q(required_entry(self, tensordict, k.observation), required_entry(self, tensordict, k.action),
                    self.qvalue_network_params)
        error = q - target
        loss = reduce_per_seed(self, error.square(), tensordict)
        metadata = {"q_mean": q.detach().mean(-1), "target_value_mean": target.mean(-1),
                    "td_error_abs_mean": error.detach().abs().mean(-1)}
        self._clear_weakrefs(tensordict, "qvalue_network_params", "target_qvalue_network_params",
                             "policy_network_params")
        return loss, metadata

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Computes :meth:`qvalue_loss`.

        Args:
            tensordict (TensorDictBase): input with :attr:`in_keys` (and, optionally, the stored
                ``("next", tensor_keys.policy_action)``).

        Returns:
            A :class:`~tensordict.TensorDict` with ``loss_qvalue`` and the diagnostics.
        """
        loss, metadata = self.qvalue_loss(tensordict)
        out = TensorDict({"loss_qvalue": loss, **metadata})
        self._clear_weakrefs(tensordict, out, "qvalue_network_params", "target_qvalue_network_params",
                             "policy_network_params")
        return out

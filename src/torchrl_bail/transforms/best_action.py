"""Best-action selection (supp. Alg. 1): keep the pairs whose return is closest to the upper envelope.

For every state-action pair ``i`` BAIL forms the ratio ``G_i / V(s_i)`` of its return to the envelope, takes as
border ``x`` the ``floor(p N)``-th largest ratio and keeps every pair with ``G_i / V(s_i) >= x`` (ties at the
border are all kept, so slightly more than ``p N`` pairs may survive).

* :func:`best_action_mask` is the selection itself, on ``[B]`` or ``[S, B]`` tensors (one selection per row),
  also used by Progressive BAIL inside each mini-batch.
* :class:`BestActionFilter` is the selection as a TorchRL replay-buffer transform: it filters rows at
  write time (``rb.extend``), so the buffer stores only the selected pairs and samples fixed-size batches.
* :func:`select_best_actions` returns the selected rows of a TensorDict in one call.
"""

from __future__ import annotations

import math
import warnings
from typing import Any, Literal

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.data import Composite
from torchrl.envs import EnvBase
from torchrl.envs.transforms import Transform

__all__ = ["NonPositiveValue", "project_values", "best_action_mask", "BestActionFilter", "select_best_actions"]

#: How ``V <= 0`` enters the ratio ``G / V``: ``"raw"`` (the authors' plain ratio), ``"project"``
#: (``V <- exp(V - 1)`` where ``V < 1``, Progressive BAIL's projection) or ``"error"``.
NonPositiveValue = Literal["raw", "project", "error"]


def project_values(values: torch.Tensor) -> torch.Tensor:
    """Progressive BAIL's projection of the envelope before the ratio ``G / V`` (authors' code, not in the paper):
    ``V <- exp(V - 1)`` where ``V < 1``, unchanged elsewhere. Continuous at 1, in ``(0, 1)`` below it, so ``V <= 0``
    never flips the ranking. The one place this rule lives (``nonpositive_value="project"``).

    Examples:
        >>> project_values(torch.tensor([-1.0, 0.0, 1.0, 5.0]))
        tensor([0.1353, 0.3679, 1.0000, 5.0000])
    """
    return torch.where(values < 1, torch.exp(values - 1), values)


def _check_percentile(percentile: float) -> float:
    percentile = float(percentile)
    if not 0.0 < percentile <= 1.0:
        raise ValueError(f"percentile must be in (0, 1] (the share of pairs kept, e.g. 0.3), got {percentile}")
    return percentile


def _check_mode(nonpositive_value: str) -> str:
    if nonpositive_value not in ("raw", "project", "error"):
        raise ValueError(f"nonpositive_value must be 'raw', 'project' or 'error', got {nonpositive_value!r}")
    return nonpositive_value


def _align(returns: torch.Tensor, values: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Drops a trailing singleton that only one of the two has (``[B]`` vs ``[B, 1]``)."""
    if returns.shape != values.shape:
        if values.ndim == returns.ndim + 1 and values.shape[-1] == 1:
            values = values.squeeze(-1)
        elif returns.ndim == values.ndim + 1 and returns.shape[-1] == 1:
            returns = returns.squeeze(-1)
    if returns.shape != values.shape:
        raise ValueError(
            f"returns and values must have the same shape ([B] or [S, B]), got {tuple(returns.shape)} and "
            f"{tuple(values.shape)}"
        )
    return returns, values


def best_action_mask(
    returns: torch.Tensor,
    values: torch.Tensor,
    percentile: float = 0.30,
    *,
    nonpositive_value: NonPositiveValue = "raw",
    return_border: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """Which pairs BAIL keeps: ``G / V >= x`` with ``x`` the ``floor(p B)``-th largest ratio (supp. Alg. 1).

    The selection runs along the last dimension: ``[B]`` gives one selection, ``[S, B]`` one per row (e.g.
    per seed). At least one pair per row is kept (``floor(p B)`` is raised to 1). Ties at the border are all
    kept. A ``0 / 0`` ratio (``"raw"`` mode) is never selected.

    Args:
        returns (torch.Tensor): ``G``, shape ``[B]`` or ``[S, B]``.
        values (torch.Tensor): ``V(s)``, the same shape (a trailing singleton is accepted).
        percentile (float): ``p``, the share kept, in ``(0, 1]``. Defaults to ``0.30`` (BAIL; Progressive BAIL
            uses ``0.25``).

    Keyword Args:
        nonpositive_value (str): how values ``V <= 0`` enter the ratio. Defaults to ``"raw"``.

            * ``"raw"``: the authors' static-BAIL code, the plain ratio ``G / V``. With ``V < 0`` the ordering
              flips (a negative return over a negative envelope gives a positive ratio); with MuJoCo returns
              ``V`` is almost always positive.
            * ``"project"``: Progressive BAIL's projection, ``V <- exp(V - 1)`` where ``V < 1`` (continuous at
              1, always positive).
            * ``"error"``: raise a :class:`ValueError` if any ``V <= 0``.
        return_border (bool): also return the border ``x`` (shape ``[]`` or ``[S]``). Defaults to ``False``.

    Returns:
        a boolean mask with the shape of the inputs (and the border if ``return_border``).

    Examples:
        >>> g = torch.tensor([1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0])
        >>> best_action_mask(g, torch.full((10,), 10.0), 0.3)
        tensor([False, False, False, False, False, False, False,  True,  True,  True])
        >>> mask, border = best_action_mask(torch.stack([g, g.flip(0)]), torch.full((2, 10), 10.0), 0.2,
        ...                                 return_border=True)
        >>> mask.sum(-1), border
        (tensor([2, 2]), tensor([0.9000, 0.9000]))
    """
    percentile = _check_percentile(percentile)
    nonpositive_value = _check_mode(nonpositive_value)
    returns, values = _align(returns, values)
    if returns.ndim == 0:
        raise ValueError("returns and values must have at least one dimension ([B] or [S, B])")
    if not returns.is_floating_point():
        returns = returns.to(values.dtype if values.is_floating_point() else torch.get_default_dtype())
    values = values.to(returns.dtype)
    if nonpositive_value == "error":
        bad = values <= 0
        if bool(bad.any()):
            raise ValueError(
                f"{int(bad.sum())} of {values.numel()} envelope values are <= 0 (min {float(values.min()):.4g}); the "
                "ratio G / V is meaningless there. Use nonpositive_value='project' (V <- exp(V - 1) for V < 1) or "
                "'raw' (the authors' plain ratio)"
            )
    elif nonpositive_value == "project":
        values = project_values(values)
    n = returns.shape[-1]
    if n == 0:
        mask = torch.zeros(returns.shape, dtype=torch.bool, device=returns.device)
        border = torch.full(returns.shape[:-1], math.nan, dtype=returns.dtype, device=returns.device)
        return (mask, border) if return_border else mask
    ratio = returns / values
    undefined = torch.isnan(ratio)  # 0 / 0: ranked last and never kept, even when the border reaches it
    ratio = torch.where(undefined, torch.full_like(ratio, -math.inf), ratio)
    # round() guards floor against representation error (e.g. 0.3 * 10 = 3.0000000000000004)
    k = max(1, math.floor(round(percentile * n, 6)))
    # the k-th largest is the (n - k + 1)-th smallest
    border = torch.kthvalue(ratio, n - k + 1, dim=-1).values
    mask = (ratio >= border.unsqueeze(-1)) & ~undefined
    return (mask, border) if return_border else mask


class BestActionFilter(Transform):
    """BAIL's best-action selection as a write-time replay-buffer transform (supp. Alg. 1).

    BAIL: Best-Action Imitation Learning for Batch Deep Reinforcement Learning, https://arxiv.org/abs/1910.12179.

    On ``rb.extend(data)`` (the inverse transform) it keeps only the rows selected by :func:`best_action_mask`
    over the *whole* extended batch, so the buffer stores exactly the best pairs and samples fixed-size,
    uniform mini-batches from them. Extend the buffer with the whole batch in one call: a write-time transform
    cannot take back rows it stored, so a second ``extend`` selects the top ``percentile`` of its own rows only
    (it warns once per filter; a new selection takes a new filter).

    At sample time (``forward``) the batch size is never changed: rows are only tagged with a boolean
    ``selected_key`` entry, ``G / V >= border`` with the lowest border of the write-time selections (so every
    row stored through the filter is tagged ``True``). Called directly on a batch before any write-time
    selection, it tags the top ``percentile`` of that batch, which pairs with a masked loss
    (``loss.loss_mask_key``).

    The border and the counts are buffers of the transform's ``state_dict``: a buffer saved with
    ``rb.dumps(path)`` and read back with ``rb.loads(path)`` (or a filter loaded with ``load_state_dict``) tags
    exactly as the original. Inside a :class:`~torchrl.envs.TransformedEnv` the filter does nothing (it adds no
    entry and declares no spec), so an env may carry it.

    Args:
        value_network (TensorDictModuleBase, optional): the upper envelope. If given, ``V`` is computed (in
            chunks, without gradients, on the network's device) for rows that lack ``value_key`` and written
            there. If ``None``, ``value_key`` must be present in the data. The network is referenced, not
            registered as a sub-module (it is not part of the transform's ``state_dict``).

    Keyword Args:
        percentile (float): the share kept, in ``(0, 1]``. Defaults to ``0.30``.
        return_key (NestedKey): the Monte-Carlo return ``G``. Defaults to ``"return"``.
        value_key (NestedKey): the envelope value ``V(s)``. Defaults to ``"state_value"``.
        nonpositive_value (str): ``"raw"`` | ``"project"`` | ``"error"``, see :func:`best_action_mask`.
            Defaults to ``"raw"`` (the authors' code).
        selected_key (NestedKey, optional): the boolean tag written at sample time; ``None`` makes ``forward`` a
            pass-through. Defaults to ``"best_action"``.
        chunk_size (int): rows per forward pass of ``value_network``. Defaults to ``65536``.

    Attributes:
        border (float): the border ``x`` of the write-time selection (the lowest, after several ``extend``
            calls; ``nan`` before any).
        num_seen (int): rows offered to the write-time selections.
        num_selected (int): rows they kept.
        selected_fraction (float): ``num_selected / num_seen`` (``nan`` before any).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        >>> data = TensorDict({
        ...     "observation": torch.randn(100, 3),
        ...     "action": torch.rand(100, 2),
        ...     "return": torch.arange(100.0),
        ...     "state_value": torch.full((100, 1), 200.0),
        ... }, [100])
        >>> rb = TensorDictReplayBuffer(storage=LazyTensorStorage(100), batch_size=8,
        ...                             transform=BestActionFilter(percentile=0.3))
        >>> _ = rb.extend(data)
        >>> len(rb), rb.storage[: len(rb)]["return"].min().item()
        (30, 70.0)
        >>> batch = rb.sample()
        >>> batch.shape, bool(batch["best_action"].all())
        (torch.Size([8]), True)
    """

    def __init__(
        self,
        value_network: TensorDictModuleBase | None = None,
        *,
        percentile: float = 0.30,
        return_key: NestedKey = "return",
        value_key: NestedKey = "state_value",
        nonpositive_value: NonPositiveValue = "raw",
        selected_key: NestedKey | None = "best_action",
        chunk_size: int = 65536,
    ) -> None:
        super().__init__(
            in_keys=[return_key, value_key],
            out_keys=[] if selected_key is None else [selected_key],
        )
        self.percentile = _check_percentile(percentile)
        self.nonpositive_value = _check_mode(nonpositive_value)
        if int(chunk_size) < 1:
            raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
        self.return_key = return_key
        self.value_key = value_key
        self.selected_key = selected_key
        self.chunk_size = int(chunk_size)
        # referenced, not a sub-module: the envelope belongs to (and is checkpointed by) its owner
        self.__dict__["value_network"] = value_network
        # the write-time selection, in the state_dict (rb.dumps / rb.loads carry it)
        self.register_buffer("_border", torch.tensor(math.nan, dtype=torch.float64))
        self.register_buffer("_num_seen", torch.zeros((), dtype=torch.long))
        self.register_buffer("_num_selected", torch.zeros((), dtype=torch.long))
        self._warned_chunks = False

    @property
    def border(self) -> float:
        return float(self._border)

    @property
    def num_seen(self) -> int:
        return int(self._num_seen)

    @property
    def num_selected(self) -> int:
        return int(self._num_selected)

    @property
    def selected_fraction(self) -> float:
        return self.num_selected / self.num_seen if self.num_seen else math.nan

    def _in_env(self) -> bool:
        """Whether the filter sits in an environment's transforms (where it has nothing to do)."""
        holder = self
        while holder is not None:
            ref = holder.__dict__.get("_container")
            holder = ref() if ref is not None else None
            if isinstance(holder, EnvBase):
                return True
        return False

    # -- helpers -----------------------------------------------------------------------------------
    @torch.no_grad()
    def _values(self, tensordict: TensorDictBase) -> torch.Tensor:
        """``V`` for every row: read from ``value_key`` or computed by ``value_network`` (and stored there)."""
        values = tensordict.get(self.value_key, None)
        if values is not None:
            return values
        network = self.value_network
        if network is None:
            raise KeyError(
                f"BestActionFilter: the data has no envelope value at {self.value_key!r} and no value_network was "
                f"given to compute it; keys present: {sorted(map(str, tensordict.keys(True, True)))}"
            )
        device = next(iter(network.parameters()), torch.empty(0)).device
        out_key = self.value_key if self.value_key in network.out_keys else network.out_keys[0]
        chunks = []
        for chunk in tensordict.select(*network.in_keys).split(self.chunk_size):
            chunks.append(network(chunk.to(device)).get(out_key).to(tensordict.device or chunk.device))
        values = torch.cat(chunks)
        tensordict.set(self.value_key, values)
        return values

    def _returns(self, tensordict: TensorDictBase) -> torch.Tensor:
        returns = tensordict.get(self.return_key, None)
        if returns is None:
            raise KeyError(
                f"BestActionFilter: the data has no return at {self.return_key!r}; keys present: "
                f"{sorted(map(str, tensordict.keys(True, True)))}"
            )
        return returns

    @staticmethod
    def _flat(tensor: torch.Tensor, batch_size: torch.Size) -> torch.Tensor:
        if tensor.shape == batch_size + (1,):
            return tensor.squeeze(-1)
        return tensor

    # -- write time: keep the best rows ------------------------------------------------------------
    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        if self._in_env():  # an action on its way to the env: nothing to select
            return tensordict
        if tensordict.batch_dims != 1:
            raise ValueError(
                f"BestActionFilter selects over a flat batch [N]; got batch size {tuple(tensordict.batch_size)}. "
                "Flatten the data (td.reshape(-1)) before extending the buffer"
            )
        returns = self._flat(self._returns(tensordict), tensordict.batch_size)
        values = self._flat(self._values(tensordict), tensordict.batch_size)
        mask, border = best_action_mask(
            returns, values, self.percentile, nonpositive_value=self.nonpositive_value, return_border=True
        )
        if self.num_seen and not self._warned_chunks:
            self._warned_chunks = True
            warnings.warn(
                f"BestActionFilter: this extend selects the top {self.percentile} of its own {len(mask)} rows; the "
                f"{self.num_selected} rows stored before were selected among theirs (a stored row cannot be taken "
                "back). Extend once with the whole batch to select over all of it, and use a new filter for a new "
                "selection (warned once per filter)",
                UserWarning,
                stacklevel=2,
            )
        # new tensors, not in-place updates: a clone (Transform.clone shares the buffers' tensors) keeps its own
        self._num_seen = self._num_seen + len(mask)
        self._num_selected = self._num_selected + int(mask.sum())
        self._border = torch.fmin(self._border, border.to(self._border))  # fmin: nan before the first selection
        return tensordict[mask.to(tensordict.device or mask.device)]

    # -- sample time: never change the batch size --------------------------------------------------
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if self.selected_key is None:
            return tensordict
        batch_size = tensordict.batch_size
        returns = self._flat(self._returns(tensordict), batch_size)
        values = self._flat(self._values(tensordict), batch_size)
        if math.isnan(self.border):  # no write-time selection yet: select within this batch
            selected = best_action_mask(returns, values, self.percentile, nonpositive_value=self.nonpositive_value)
        else:
            returns, values = _align(returns, values)
            if self.nonpositive_value == "project":
                values = project_values(values)
            selected = returns / values >= self.border
        tensordict.set(self.selected_key, selected)
        return tensordict

    # -- inside an environment: nothing to do, nothing added -------------------------------------------
    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        return next_tensordict

    def transform_output_spec(self, output_spec: Composite) -> Composite:
        return output_spec

    def __repr__(self) -> str:
        return (
            f"{self.__class__.__name__}(percentile={self.percentile}, return_key={self.return_key!r}, "
            f"value_key={self.value_key!r}, nonpositive_value={self.nonpositive_value!r}, "
            f"value_network={'None' if self.value_network is None else type(self.value_network).__name__})"
        )


def select_best_actions(
    tensordict: TensorDictBase,
    value_network: TensorDictModuleBase | None = None,
    percentile: float = 0.30,
    **kwargs: Any,
) -> TensorDictBase:
    """The rows of ``tensordict`` that BAIL keeps (a new TensorDict; the input is not modified).

    Args:
        tensordict (TensorDictBase): a flat ``[N]`` batch with the return (``"return"``) and either the envelope
            value (``"state_value"``) or the value network's inputs.
        value_network (TensorDictModuleBase, optional): the envelope; ``None`` reads ``"state_value"``.
        percentile (float): the share kept. Defaults to ``0.30``.
        **kwargs: the keyword arguments of :class:`BestActionFilter` (``return_key``, ``value_key``,
            ``nonpositive_value``, ...).

    Examples:
        >>> from tensordict import TensorDict
        >>> data = TensorDict({"return": torch.arange(10.0), "state_value": torch.full((10,), 10.0)}, [10])
        >>> select_best_actions(data, percentile=0.2)["return"]
        tensor([8., 9.])
    """
    return BestActionFilter(value_network, percentile=percentile, **kwargs).inv(tensordict)

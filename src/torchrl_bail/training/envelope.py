"""Fitting BAIL's upper envelope ``V(s)`` to the returns ``G`` (supp. B.1-B.2, Alg. 1), and looking at the result.

:func:`fit_upper_envelope` is the authors' static-BAIL procedure: Adam with *coupled* weight decay on every
parameter, a train/validation split that forces the highest return into training, epochs of sequential
mini-batches over the reshuffled training split, a validation loss after every epoch and early stopping with
patience ``C = 4``. The penalty loss itself is :class:`~torchrl_bail.objectives.upper_envelope.UpperEnvelopeLoss`.
It fits the envelopes of a list of seeds, one :class:`EnvelopeFit` each (one seed: a list of one).

It is built from named steps that Progressive BAIL (:mod:`torchrl_bail.algorithms.pbail`) reuses:
:func:`envelope_split`, :func:`train_one_epoch` (made of :func:`envelope_step`), :func:`validation_loss`, and the
one early-stopping rule, :class:`EarlyStoppingTracker`, with its :class:`BestWeights` record ``phi'``.

:func:`envelope_values` evaluates a fitted envelope over a whole batch and :func:`fraction_below` measures how
many returns it fails to cover (:func:`torchrl_bail.reports.plots.plot_envelope` draws the paper's Fig. 13).

Examples:
    >>> import torch
    >>> from torchrl_bail.modules import make_value_network
    >>> _ = torch.manual_seed(0)
    >>> obs = torch.randn(500, 3)
    >>> returns = obs[:, 0] + 0.1 * torch.randn(500)
    >>> (fit,) = fit_upper_envelope([make_value_network(3)], obs, returns, epochs=5, progress=False,
    ...                             generators=[torch.Generator().manual_seed(0)])
    >>> len(fit.train_index), len(fit.val_index), len(fit.val_loss)
    (401, 99, 5)
    >>> values = envelope_values(fit.value_network, obs)
    >>> values.shape
    torch.Size([500])
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase

from torchrl_bail.core.progress import tqdm
from torchrl_bail.core.stacking import SeedModules
from torchrl_bail.objectives.upper_envelope import UpperEnvelopeLoss

__all__ = [
    "EarlyStopping",
    "BestWeights",
    "EarlyStoppingTracker",
    "EnvelopeFit",
    "envelope_split",
    "fit_upper_envelope",
    "check_fit_arguments",
    "envelope_step",
    "train_one_epoch",
    "validation_loss",
    "envelope_values",
    "fraction_below",
]

#: ``"paper"`` (= ``"paper_best"``): revert to a real copy of the best weights after ``patience`` consecutive
#: non-improving epochs, keep training, return the best weights. ``"paper_revert"``: the same reverts, return
#: the weights of the last epoch. ``"as_coded"`` (= ``"as_coded_last"``): the authors' released code, whose
#: "best" snapshot aliases the live weights: no effective revert, the last weights are returned.
EarlyStopping = Literal["paper", "paper_best", "paper_revert", "as_coded", "as_coded_last"]

_MODES = {
    "paper": "paper_best",
    "paper_best": "paper_best",
    "paper_revert": "paper_revert",
    "as_coded": "as_coded",
    "as_coded_last": "as_coded",
}

#: validation points evaluated per forward pass (memory only: the loss is the exact mean over all of them)
_VALIDATION_CHUNK = 65536


@dataclass
class EnvelopeFit:
    """What :func:`fit_upper_envelope` returns for one seed.

    Attributes:
        value_network: the seed's fitted envelope (the module passed in, updated in place).
        train_loss: per epoch, the mean penalty loss over that epoch's mini-batches (weighted by their size).
        val_loss: per epoch, the mean penalty loss over the whole validation set (``nan`` without one).
        best_epoch: the 1-based epoch with the lowest validation loss (the last epoch without validation).
        best_val_loss: that loss.
        train_index / val_index: the split, as indices into the ``observations`` passed in.
        revert_epochs: the epochs after which the weights were reverted to the best copy.
        early_stopping: the resolved mode (``"paper_best"``, ``"paper_revert"`` or ``"as_coded"``).
        returned: ``"best"`` or ``"last"``: which weights ``value_network`` holds.
        optimizer: the Adam optimizer used (coupled L2 ``weight_decay``; over the seed-stacked parameters when
            several seeds were fitted together).
    """

    value_network: TensorDictModuleBase
    train_loss: list[float]
    val_loss: list[float]
    best_epoch: int
    best_val_loss: float
    train_index: torch.Tensor
    val_index: torch.Tensor
    revert_epochs: list[int] = field(default_factory=list)
    early_stopping: str = "paper_best"
    returned: Literal["best", "last"] = "best"
    optimizer: torch.optim.Optimizer | None = None

    @property
    def reverted(self) -> bool:
        """Whether the weights were reverted to the best copy at least once during training."""
        return bool(self.revert_epochs)

    @property
    def epochs(self) -> int:
        """Number of epochs trained."""
        return len(self.train_loss)


def envelope_split(
    returns: torch.Tensor, val_fraction: float = 0.2, *, generator: torch.Generator | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """The authors' train/validation split (supp. B.1).

    The index of the largest return is forced into training; the other ``N - 1`` indices are shuffled and the
    first ``floor((1 - val_fraction) * N)`` of them join it (so training holds ``floor(0.8 N) + 1`` points);
    the rest form the validation set. Tiny batches may leave the validation set empty.

    Args:
        returns (torch.Tensor): the returns ``G``, shape ``[N]`` (or ``[N, 1]``).
        val_fraction (float): the validation share, in ``[0, 1)``. Defaults to ``0.2``.

    Keyword Args:
        generator (torch.Generator, optional): a CPU generator for the shuffle. Defaults to ``None`` (the global
            RNG).

    Returns:
        ``(train_index, val_index)``, int64 CPU tensors; ``train_index[0]`` is the index of the largest return.

    Examples:
        >>> returns = torch.tensor([0.0, 5.0, 1.0, 2.0, 3.0])
        >>> train, val = envelope_split(returns, generator=torch.Generator().manual_seed(0))
        >>> int(train[0]), len(train), len(val)
        (1, 5, 0)
        >>> train, val = envelope_split(torch.arange(10.0), generator=torch.Generator().manual_seed(0))
        >>> int(train[0]), len(train), len(val), sorted(torch.cat([train, val]).tolist()) == list(range(10))
        (9, 9, 1, True)
    """
    if not 0.0 <= float(val_fraction) < 1.0:
        raise ValueError(f"val_fraction must be in [0, 1), got {val_fraction}")
    returns = returns.detach().reshape(-1)
    n = returns.numel()
    if n == 0:
        raise ValueError("cannot split an empty batch: returns has 0 elements")
    best = int(torch.argmax(returns).item())
    others = torch.cat([torch.arange(best), torch.arange(best + 1, n)])
    others = others[torch.randperm(n - 1, generator=generator)]
    # round() guards floor against representation error, e.g. (1 - 0.2) * N for N = 10^6
    n_first = min(n - 1, math.floor(round((1.0 - float(val_fraction)) * n, 6)))
    train_index = torch.cat([torch.tensor([best]), others[:n_first]])
    return train_index, others[n_first:]


def _flat_returns(observations: torch.Tensor, returns: torch.Tensor) -> torch.Tensor:
    if not isinstance(observations, torch.Tensor) or not isinstance(returns, torch.Tensor):
        raise TypeError(
            f"observations and returns must be tensors, got {type(observations).__name__} and "
            f"{type(returns).__name__}"
        )
    if observations.ndim != 2:
        raise ValueError(f"observations must have shape [N, obs_dim], got {tuple(observations.shape)}")
    if returns.ndim == 2 and returns.shape[-1] == 1:
        returns = returns.squeeze(-1)
    if returns.ndim != 1 or returns.shape[0] != observations.shape[0]:
        raise ValueError(
            f"returns must have shape [N] or [N, 1] with N = {observations.shape[0]} (the number of "
            f"observations), got {tuple(returns.shape)}"
        )
    if not torch.isfinite(returns).all():
        bad = int((~torch.isfinite(returns)).sum())
        raise ValueError(f"returns contain {bad} non-finite value(s) (nan/inf); the envelope needs finite returns")
    return returns


def _module_device(module: torch.nn.Module) -> torch.device:
    for tensor in module.parameters():
        return tensor.device
    return torch.device("cpu")


def _module_dtype(module: torch.nn.Module) -> torch.dtype:
    for tensor in module.parameters():
        if tensor.is_floating_point():
            return tensor.dtype
    return torch.get_default_dtype()


class BestWeights:
    """The record ``phi'`` of the lowest-validation envelope weights (supplementary material B.1).

    ``copy=True`` keeps a real copy (what the paper describes). ``copy=False`` reproduces the authors' released
    code, whose "best" record is ``module.state_dict()``: references to the *live* tensors, so the record always
    equals the current weights and loading it back changes nothing (spec: the aliasing bug).

    Examples:
        >>> net = torch.nn.Linear(2, 1)
        >>> best = BestWeights(net)
        >>> best.save()
        >>> with torch.no_grad():
        ...     _ = net.weight.add_(1.0)
        >>> best.load_into(net)  # back to the recorded weights
        >>> aliased = BestWeights(net, copy=False)
        >>> aliased.save()
        >>> with torch.no_grad():
        ...     _ = net.weight.add_(1.0)
        >>> torch.equal(aliased.state["weight"], net.weight)  # the record follows the live weights
        True
    """

    def __init__(self, module: torch.nn.Module, *, copy: bool = True) -> None:
        self.module = module
        self.copy = bool(copy)
        self.state: dict[str, torch.Tensor] | None = None

    def save(self) -> None:
        """``phi' <- phi``: a real copy, or (``copy=False``) the live references."""
        if self.copy:
            self.state = {key: value.detach().clone() for key, value in self.module.state_dict().items()}
        else:
            self.state = self.module.state_dict()

    @property
    def recorded(self) -> bool:
        return self.state is not None

    def load_into(self, module: torch.nn.Module) -> None:
        """Loads ``phi'`` into ``module`` (the training envelope on a revert, or the selection envelope)."""
        if self.state is None:
            raise RuntimeError("no best weights recorded yet")
        module.load_state_dict(self.state)

    def state_dict(self) -> dict[str, Any]:
        """For checkpoints: the copy (``None`` when aliased: the live weights are checkpointed anyway)."""
        copied = self.state if self.copy else None
        return {"state": None if copied is None else {k: v.clone() for k, v in copied.items()},
                "recorded": self.recorded}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if self.copy:
            self.state = state["state"]
        else:
            self.state = self.module.state_dict() if state["recorded"] else None


class EarlyStoppingTracker:
    """The early-stopping rule of BAIL's envelope (supplementary material B.1), one instance per fit, shared by
    static BAIL (:func:`fit_upper_envelope`, one validation per epoch) and Progressive BAIL (one validation every
    ``validate_every`` iterations).

    After every validation loss ``L``:

    * ``L < best`` (strictly): ``phi' <- phi`` (:class:`BestWeights`), the count of non-improving validations is
      reset to 0; returns ``"improved"``.
    * otherwise the count grows by one; when it reaches ``patience`` (``C = 4``) and reverting is on (and a best
      record exists), ``phi <- phi'`` and **the count restarts at 0**: the next revert needs ``C`` more
      non-improving validations. Returns ``"reverted"`` then, else ``"worse"``.
    * a ``nan`` loss (a diverged envelope) never improves: it counts as non-improving.

    Without a validation set there is nothing to observe: callers do not call :meth:`observe` (no early stopping).

    The restart after a revert is the chosen reading of B.1 ("returned to phi' once there are C consecutive times
    with L_phi > L_phi'"): after a revert the streak that triggered it is used up. The authors' code resets the
    count only on an improvement, but its revert is a no-op (aliasing), so the two readings only differ in the
    paper variants; static BAIL has always restarted the count, and Progressive BAIL follows the same rule.

    Args:
        network: the training envelope ``phi``.

    Keyword Args:
        patience (int): ``C``. Defaults to ``4``.
        revert (bool): ``phi <- phi'`` after ``patience`` non-improving validations. Defaults to ``True``.
        copy_best (bool): ``phi'`` is a real copy (``False``: the authors' aliasing, see :class:`BestWeights`).
            Defaults to ``True``.

    Examples:
        >>> net = torch.nn.Linear(1, 1)
        >>> tracker = EarlyStoppingTracker(net, patience=2)
        >>> [tracker.observe(loss) for loss in (3.0, 2.0, 2.5, 2.1, 2.4, 1.0, 1.5)]
        ['improved', 'improved', 'worse', 'reverted', 'worse', 'improved', 'worse']
        >>> tracker.best_loss, tracker.best_step, tracker.reverts
        (1.0, 6, [4])
    """

    def __init__(self, network: torch.nn.Module, *, patience: int = 4, revert: bool = True,
                 copy_best: bool = True) -> None:
        if int(patience) < 1:
            raise ValueError(f"patience must be >= 1, got {patience}")
        self.network = network
        self.patience = int(patience)
        self.revert = bool(revert)
        self.best = BestWeights(network, copy=copy_best)
        self.best_loss = math.inf
        self.best_step = 0
        self.increases = 0
        self.step = 0
        self.reverts: list[int] = []

    def observe(self, loss: float) -> Literal["improved", "worse", "reverted"]:
        """Feeds one validation loss (validations are counted 1, 2, ... as ``step``); see the class docstring."""
        self.step += 1
        if loss < self.best_loss:
            self.best_loss, self.best_step, self.increases = loss, self.step, 0
            self.best.save()
            return "improved"
        self.increases += 1
        if self.revert and self.increases == self.patience and self.best.recorded:
            self.best.load_into(self.network)
            self.reverts.append(self.step)
            self.increases = 0
            return "reverted"
        return "worse"

    def state_dict(self) -> dict[str, Any]:
        return {"best_loss": self.best_loss, "best_step": self.best_step, "increases": self.increases,
                "step": self.step, "reverts": list(self.reverts), "best": self.best.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.best_loss, self.best_step = float(state["best_loss"]), int(state["best_step"])
        self.increases, self.step, self.reverts = int(state["increases"]), int(state["step"]), list(state["reverts"])
        self.best.load_state_dict(state["best"])


def check_fit_arguments(*, batch_size: int, epochs: int, patience: int, val_fraction: float,
                        early_stopping: str) -> str:
    """Validates :func:`fit_upper_envelope`'s settings; returns the resolved early-stopping mode."""
    mode = _MODES.get(early_stopping)
    if mode is None:
        raise ValueError(f"early_stopping must be one of {sorted(_MODES)}, got {early_stopping!r}")
    if int(batch_size) < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    if int(epochs) < 1:
        raise ValueError(f"epochs must be >= 1, got {epochs}")
    if int(patience) < 1:
        raise ValueError(f"patience must be >= 1, got {patience}")
    if not 0.0 <= float(val_fraction) < 1.0:
        raise ValueError(f"val_fraction must be in [0, 1), got {val_fraction}")
    return mode


def envelope_step(loss_module: UpperEnvelopeLoss, optimizer: torch.optim.Optimizer,
                  batch: TensorDictBase) -> torch.Tensor:
    """One Adam step on the penalty loss of ``batch``; returns the detached loss.

    Seed-stacked envelopes (:func:`~torchrl_bail.core.stacking.stack_modules`, a ``[S, B]`` batch, a loss with
    ``reduction="none"``): the loss is each seed's mean ``[S]``, and their sum is back-propagated, so each seed's
    slice receives exactly its own gradient.
    """
    loss, _ = loss_module.envelope_loss(batch)
    if loss.ndim:  # per-point losses [S, B] -> per seed [S]
        loss = loss.mean(-1)
    optimizer.zero_grad(set_to_none=True)
    loss.sum().backward()
    optimizer.step()
    return loss.detach()


def train_one_epoch(loss_module: UpperEnvelopeLoss, optimizer: torch.optim.Optimizer, data: TensorDict,
                    train_index: torch.Tensor, batch_size: int, *,
                    generators: Sequence[torch.Generator | None]) -> list[float]:
    """One pass over the reshuffled training split in sequential mini-batches of ``batch_size`` (the last, partial
    one kept); returns the mean loss over the epoch (mini-batch losses weighted by their size, summed in the loss'
    dtype and divided in Python's float), one per seed.

    ``data`` holds the observations (the envelope's in-key) and returns (the loss' ``value_target``) of the whole
    batch on the training device; ``train_index`` (same device) selects the training split, ``[n]`` for one envelope
    or ``[S, n]`` for ``S`` seed-stacked ones (see :func:`envelope_step`: each seed's split); ``generators`` holds
    each seed's shuffle generator (CPU; ``[None]``: the global stream).
    """
    n_train = train_index.shape[-1]
    rows = [row[torch.randperm(n_train, generator=g).to(row.device)]
            for row, g in zip(train_index.reshape(-1, n_train), generators, strict=True)]
    order = torch.stack(rows).reshape(train_index.shape)
    obs_key, return_key = loss_module.value_network.in_keys[0], loss_module.tensor_keys.value_target
    observations, returns = data.get(obs_key), data.get(return_key)
    running = None
    for start in range(0, n_train, batch_size):
        index = order[..., start : start + batch_size]
        batch = TensorDict({obs_key: observations[index], return_key: returns[index]}, batch_size=index.shape)
        loss = envelope_step(loss_module, optimizer, batch) * index.shape[-1]
        running = loss if running is None else running + loss
    return [float(seed_loss) / n_train for seed_loss in running.reshape(-1)]


@torch.no_grad()
def validation_loss(loss_module: UpperEnvelopeLoss, validation: TensorDictBase) -> list[float]:
    """The mean penalty loss over every validation point (``nan`` for an empty set), one per seed, evaluated in
    chunks for memory.

    ``validation`` is ``[n]`` (one envelope) or ``[S, n]`` (seed-stacked envelopes, each seed's validation set), and
    ``loss_module`` returns per-point losses (``reduction="none"``): each seed's loss is the mean over its last
    dimension, the same reduction for one seed as for ``S``.
    """
    n = validation.batch_size[-1]
    if n == 0:
        return [math.nan] * validation.batch_size[:-1].numel()
    total = 0
    for chunk in validation.split(_VALIDATION_CHUNK, dim=validation.batch_dims - 1):
        loss, _ = loss_module.envelope_loss(chunk)
        if loss.shape != chunk.batch_size:
            raise ValueError(f"validation_loss needs per-point losses (reduction='none'): the loss of a "
                             f"{list(chunk.batch_size)} chunk has shape {list(loss.shape)}")
        total = total + loss.mean(-1) * chunk.batch_size[-1]
    return (total / n).reshape(-1).tolist()


def fit_upper_envelope(
    value_networks: Sequence[TensorDictModuleBase],
    observations: torch.Tensor,
    returns: torch.Tensor,
    *,
    generators: Sequence[torch.Generator | None] | None = None,
    penalty: float = 1000.0,
    lr: float = 3e-3,
    weight_decay: float = 0.02,
    batch_size: int = 800,
    epochs: int = 50,
    val_fraction: float = 0.2,
    patience: int = 4,
    early_stopping: EarlyStopping = "paper",
    device: torch.device | str | None = None,
    progress: bool = True,
    callback: Callable[[int, dict[str, list]], Any] | None = None,
) -> list[EnvelopeFit]:
    """Fits the upper envelope ``V_phi`` to the returns as the authors do (supp. B.1-B.2, Alg. 1), for each seed of a
    list (one seed: a list of one); returns one :class:`EnvelopeFit` per seed.

    BAIL: Best-Action Imitation Learning for Batch Deep Reinforcement Learning, https://arxiv.org/abs/1910.12179.

    * **Loss**: :class:`~torchrl_bail.objectives.upper_envelope.UpperEnvelopeLoss` with ``K = penalty``: the
      mean over a mini-batch of ``(V - G)^2``, times ``K`` where ``V < G``.
    * **Regulariser**: ``torch.optim.Adam(weight_decay=0.02)`` on *all* parameters (biases included). This is
      coupled L2 (``0.02 * phi`` added to the gradient), not AdamW.
    * **Split**: :func:`envelope_split`: the largest return is forced into training, ``floor(0.8 N) + 1``
      training points, the rest validation.
    * **Epochs**: one pass over the training split per epoch, reshuffled every epoch, in sequential
      mini-batches of ``batch_size`` without replacement; the last, partial mini-batch is kept.
    * **Validation**: after every epoch, the penalty loss on the whole validation set. This is the *mean* over
      the validation points; the authors' code sums chunk means over chunks of 800, which is the same up to a
      constant factor (and the extra weight it gives the last partial chunk). Only the comparison between
      epochs matters, so the choice of scale changes nothing but the logged numbers.
    * **Early stopping** (patience ``C``), ``early_stopping=``:

      - ``"paper"`` (default; alias ``"paper_best"``), the supplementary material's B.1: keep a real copy
        ``phi'`` of the lowest-validation weights; after ``C`` consecutive epochs without improvement on the
        best, revert ``phi <- phi'`` and keep training (the count restarts after a revert); at the end return
        ``phi'``, the best weights seen.
      - ``"paper_revert"``: the same reverts, but the weights of the last epoch are returned.
      - ``"as_coded"`` (alias ``"as_coded_last"``), the released code: its "best" snapshot is
        ``module.state_dict()``, which aliases the live tensors, so its revert is a no-op and it returns the
        weights after the last epoch. Use it to reproduce the authors' numbers.

      Without a validation set (``val_fraction=0`` or a tiny batch) there is no early stopping and the last
      weights are returned in every mode.

    **Seeds.** The ``S`` networks are fitted as one (:class:`~torchrl_bail.core.stacking.SeedModules`): their parameters
    stacked along a seed dimension, the mini-batches of all seeds through one batched step, each seed's mean loss
    back-propagated into its own slice. Each seed keeps its own split, shuffles, validation losses, early stopping
    (patience count, best weights) and returned weights: those of its own fit with its generator, to float rounding
    (a batched matrix product rounds differently). A list of one network is fitted unstacked, with the plain
    layers' products and the same per-seed reductions, so a one-seed fit is the same, to every digit, as the fit
    of that network before seeds could be stacked.

    Args:
        value_networks (sequence of TensorDictModuleBase): one envelope per seed, of one architecture, e.g.
            :func:`~torchrl_bail.modules.make_value_network`; each reads the observations from its first in-key and
            writes ``"state_value"``. They are trained in place (and moved to ``device``).
        observations (torch.Tensor): ``[N, obs_dim]``.
        returns (torch.Tensor): ``[N]`` (or ``[N, 1]``) Monte-Carlo returns ``G``.

    Keyword Args:
        generators (sequence of torch.Generator, optional): per seed, a CPU generator for its split and epoch
            shuffles; the same seed (and the same initial weights) gives the same fit. Defaults to ``None`` (every
            seed draws from the global RNG, one after the other).
        penalty (float): ``K``. Defaults to ``1000.0``.
        lr (float): Adam learning rate. Defaults to ``3e-3``.
        weight_decay (float): coupled L2 coefficient of Adam. Defaults to ``0.02``.
        batch_size (int): mini-batch size. Defaults to ``800``.
        epochs (int): passes over the training split. Defaults to ``50``.
        val_fraction (float): validation share in ``[0, 1)``. Defaults to ``0.2``.
        patience (int): ``C``, consecutive non-improving epochs before a revert. Defaults to ``4``.
        early_stopping (str): ``"paper"`` | ``"paper_best"`` | ``"paper_revert"`` | ``"as_coded"`` |
            ``"as_coded_last"``, see above. Defaults to ``"paper"``.
        device (torch.device or str, optional): where to train. Defaults to the first network's device.
        progress (bool): show a tqdm bar over epochs with the losses (averaged over the seeds). Defaults to
            ``True``.
        callback (callable, optional): called after every epoch as ``callback(epoch, info)`` with
            ``info = {"train_loss", "val_loss", "best_epoch", "best_val_loss", "reverted"}``, each a list of one
            value per seed; a truthy return value stops training after that epoch. Defaults to ``None``.

    Returns:
        a list of :class:`EnvelopeFit`, one per seed.
    """
    mode = check_fit_arguments(batch_size=batch_size, epochs=epochs, patience=patience, val_fraction=val_fraction,
                               early_stopping=early_stopping)
    returns = _flat_returns(observations, returns)
    value_networks = list(value_networks)
    generators = [None] * len(value_networks) if generators is None else list(generators)
    if not value_networks or len(generators) != len(value_networks):
        raise ValueError(f"fit_upper_envelope needs one value network and one generator per seed, got "
                         f"{len(value_networks)} networks and {len(generators)} generators")
    device = torch.device(device) if device is not None else _module_device(value_networks[0])
    for network in value_networks:
        network.to(device)
    seeds = SeedModules(value_networks)
    # per-point losses, each seed's mean taken by envelope_step / validation_loss ([S, B] -> [S], [B] -> [])
    loss_module = UpperEnvelopeLoss(seeds.module, penalty=penalty, reduction="none")
    optimizer = torch.optim.Adam(loss_module.parameters(), lr=lr, weight_decay=weight_decay)
    splits = [envelope_split(returns.cpu(), val_fraction, generator=g) for g in generators]
    if float(val_fraction) > 0 and len(splits[0][1]) == 0:
        warnings.warn(
            f"fit_upper_envelope: {len(returns)} points leave no validation point at val_fraction={val_fraction}; "
            "training without validation or early stopping (the last weights are returned)",
            stacklevel=2,
        )
    dtype = _module_dtype(seeds.module)
    keys = (seeds.module.in_keys[0], loss_module.tensor_keys.value_target)
    data = TensorDict(dict(zip(keys, (observations.to(device=device, dtype=dtype),
                                      returns.to(device=device, dtype=dtype)), strict=True)), batch_size=[len(returns)])
    train_index, val_index = (seeds.batch(parts).to(device) for parts in zip(*splits, strict=True))
    # as coded, the "best" record aliases the live weights and is never loaded back
    trackers = [EarlyStoppingTracker(network, patience=patience, revert=mode != "as_coded",
                                     copy_best=mode != "as_coded") for network in seeds.seeds]
    losses = _train_epochs(loss_module, optimizer, data, train_index, data[val_index], trackers, generators,
                           batch_size=int(batch_size), epochs=int(epochs), progress=progress, callback=callback)
    fits = []
    for network, seed, tracker, (train_losses, val_losses), (seed_train_index, seed_val_index) in zip(
            value_networks, seeds.seeds, trackers, losses, splits, strict=True):
        best = mode == "paper_best" and tracker.best.recorded
        if best:
            tracker.best.load_into(seed)
        validated = len(seed_val_index) > 0
        fits.append(EnvelopeFit(
            value_network=network, train_loss=train_losses, val_loss=val_losses,
            best_epoch=tracker.best_step if validated else len(train_losses),
            best_val_loss=tracker.best_loss if validated else math.nan, train_index=seed_train_index,
            val_index=seed_val_index, revert_epochs=tracker.reverts, early_stopping=mode,
            returned="best" if best else "last", optimizer=optimizer,
        ))
    seeds.unstack()
    return fits


def _train_epochs(loss_module: UpperEnvelopeLoss, optimizer: torch.optim.Optimizer, data: TensorDict,
                  train_index: torch.Tensor, validation: TensorDict, trackers: list[EarlyStoppingTracker],
                  generators: list[torch.Generator | None], *, batch_size: int, epochs: int, progress: bool,
                  callback) -> list[tuple[list[float], list[float]]]:
    """:func:`fit_upper_envelope`'s epochs over the training split ``train_index`` (``[*S, n]``): train, validate on
    ``validation``, let each seed's tracker observe its validation loss, call ``callback``; returns each seed's
    ``(train losses, validation losses)``, one per epoch."""
    has_validation = validation.batch_size[-1] > 0
    losses: list[tuple[list[float], list[float]]] = [([], []) for _ in trackers]
    bar = tqdm(range(1, epochs + 1), desc="upper envelope", unit="epoch", disable=not progress, leave=False)
    for epoch in bar:
        train = train_one_epoch(loss_module, optimizer, data, train_index, batch_size, generators=generators)
        val = validation_loss(loss_module, validation)
        for tracker, (seed_train, seed_val), tr, va in zip(trackers, losses, train, val, strict=True):
            seed_train.append(tr)
            seed_val.append(va)
            if has_validation:
                tracker.observe(va)
        best_epochs = [tracker.best_step if has_validation else epoch for tracker in trackers]
        bar.set_postfix(train=f"{sum(train) / len(train):.4g}", val=f"{sum(val) / len(val):.4g}",
                        best=max(best_epochs))
        if callback is not None and callback(epoch, {
            "train_loss": train, "val_loss": val, "best_epoch": best_epochs,
            "best_val_loss": [tracker.best_loss if has_validation else math.nan for tracker in trackers],
            "reverted": [bool(tracker.reverts) for tracker in trackers],
        }):
            break
    bar.close()
    return losses


@torch.no_grad()
def envelope_values(
    value_network: TensorDictModuleBase, observations: torch.Tensor, batch_size: int = 65536
) -> torch.Tensor:
    """``V(s)`` for every observation, ``[N]``, computed in chunks without gradients.

    The chunks run on the network's device; the result is on the device of ``observations``.

    Examples:
        >>> from torchrl_bail.modules import make_value_network
        >>> envelope_values(make_value_network(4), torch.zeros(10, 4), batch_size=3).shape
        torch.Size([10])
    """
    if observations.ndim != 2:
        raise ValueError(f"observations must have shape [N, obs_dim], got {tuple(observations.shape)}")
    if int(batch_size) < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    device, dtype = _module_device(value_network), _module_dtype(value_network)
    obs_key, value_key = value_network.in_keys[0], value_network.out_keys[0]
    chunks = []
    for chunk in observations.split(int(batch_size)):
        td = TensorDict({obs_key: chunk.to(device=device, dtype=dtype)}, batch_size=chunk.shape[:1])
        chunks.append(value_network(td).get(value_key).reshape(-1).to(observations.device))
    if not chunks:
        return observations.new_zeros(0, dtype=dtype)
    return torch.cat(chunks)


def fraction_below(values: torch.Tensor, returns: torch.Tensor) -> float:
    """Share of points whose return lies above the envelope (``V < G``).

    Examples:
        >>> fraction_below(torch.tensor([1.0, 2.0, 3.0, 4.0]), torch.tensor([0.0, 2.5, 3.0, 5.0]))
        0.5
    """
    values, returns = values.detach().reshape(-1), returns.detach().reshape(-1)
    if values.shape != returns.shape:
        raise ValueError(f"values and returns must have the same number of elements, got "
                         f"{values.numel()} and {returns.numel()}")
    if values.numel() == 0:
        return math.nan
    return float((values < returns.to(values.device, values.dtype)).to(torch.float64).mean())

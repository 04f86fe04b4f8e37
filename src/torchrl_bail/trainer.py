"""The one offline training loop every algorithm runs through.

``train`` samples mini-batches with replacement from the data an algorithm prepared, calls the algorithm's
update step, evaluates the deterministic policy every ``eval_every_epochs`` (an epoch is 10^6 samples
consumed, the paper's unit), logs scalars, shows a progress bar with ETA and the latest evaluation return,
and writes an atomic checkpoint after each evaluation.

Examples:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from torchrl_bail.algorithms.bc import BehaviourCloning
    >>> from torchrl_bail.modules import action_spec_from_bounds
    >>> algo = BehaviourCloning(obs_dim=3, action_spec=action_spec_from_bounds([-1.0], [1.0]), hidden=(8,),
    ...                         batch_size=10, epochs=100 / 1e6)
    >>> data = TensorDict({"observation": torch.randn(50, 3), "action": torch.rand(50, 1) * 2 - 1}, [50])
    >>> history = train(algo, data, evaluate=lambda policy: 1.0, eval_every_epochs=50 / 1e6, progress=False)
    >>> history.iterations, [e.epoch * 1e6 for e in history.evaluations]
    (10, [50.0, 100.0])
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import torch
from tensordict import TensorDictBase
from torchrl.data import RandomSampler, TensorDictReplayBuffer, TensorStorage
from tqdm.auto import tqdm

from torchrl_bail.algorithms.base import Algorithm
from torchrl_bail.io import atomic_path

__all__ = ["EvalPoint", "TrainHistory", "train", "save_checkpoint"]


@dataclass
class EvalPoint:
    iteration: int
    epoch: float
    mean_return: float
    returns: list[float] = field(default_factory=list)
    failures: int = 0


@dataclass
class TrainHistory:
    iterations: int = 0
    evaluations: list[EvalPoint] = field(default_factory=list)
    wall_time_s: float = 0.0

    def final_return(self, window: int = 10) -> float:
        """Mean of the last ``window`` evaluations (our per-seed score; spec 7)."""
        last = self.evaluations[-window:]
        return float(sum(e.mean_return for e in last) / len(last)) if last else float("nan")

    def best_return(self) -> float:
        return max((e.mean_return for e in self.evaluations), default=float("nan"))


def save_checkpoint(path: Path, state: dict) -> None:
    """``torch.save`` to a temp file in the same directory, then an atomic rename."""
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def train(
    algorithm: Algorithm,
    data: TensorDictBase,
    *,
    evaluate: Callable | None = None,
    samples_per_epoch: int = 1_000_000,
    eval_every_epochs: float = 0.5,
    logger=None,
    checkpoint_path: Path | None = None,
    progress: bool = True,
    log_every: int = 100,
    on_new_best: Callable[[EvalPoint, int], None] | None = None,
) -> TrainHistory:
    """Runs ``algorithm`` for ``algorithm.epochs`` epochs on ``data``.

    Args:
        algorithm: the :class:`~torchrl_bail.algorithms.base.Algorithm` (its ``prepare`` already ran).
        data: the TensorDict ``[N]`` to sample from (with replacement).

    Keyword Args:
        evaluate: ``policy -> EvalResult | float``; called every ``eval_every_epochs`` and at the end.
        samples_per_epoch (int): samples in one epoch. Defaults to ``10**6``.
        eval_every_epochs (float): evaluation period in epochs. Defaults to ``0.5``.
        logger: a TorchRL logger (``log_scalar``), optional.
        checkpoint_path: where to write the checkpoint after every evaluation, optional.
        progress (bool): tqdm progress bar. Defaults to ``True``.
        log_every (int): training scalars are averaged and logged every ``log_every`` updates.
        on_new_best: ``(point, index)`` called when an evaluation beats every earlier one (e.g. to save the
            best policy); ``index`` is the evaluation's position in ``history.evaluations``.
    """
    if len(data) == 0:
        raise ValueError("the training data is empty: nothing to sample mini-batches from")
    batch_size = algorithm.batch_size
    per_update = algorithm.samples_per_update
    iterations = max(1, math.ceil(algorithm.epochs * samples_per_epoch / per_update))
    eval_interval = max(1, round(eval_every_epochs * samples_per_epoch / per_update))
    data = data.to(algorithm.device)
    buffer = TensorDictReplayBuffer(
        storage=TensorStorage(data), sampler=RandomSampler(), batch_size=batch_size
    )
    history = TrainHistory()
    start = time.perf_counter()
    sums: dict[str, torch.Tensor] = {}
    bar = tqdm(total=iterations, desc=f"{algorithm.name}", unit="it", disable=not progress, dynamic_ncols=True)
    for it in range(1, iterations + 1):
        metrics = algorithm.update(buffer.sample())
        for k, v in metrics.items():
            sums[k] = sums.get(k, 0.0) + v
        if logger is not None and it % log_every == 0:
            for k, v in sums.items():
                logger.log_scalar(f"train/{k}", float(v) / log_every, step=it)
            sums.clear()
        elif logger is None and it % log_every == 0:
            sums.clear()
        if evaluate is not None and (it % eval_interval == 0 or it == iterations):
            point = _evaluate(evaluate, algorithm, it, it * per_update / samples_per_epoch)
            is_best = all(point.mean_return > e.mean_return for e in history.evaluations)
            history.evaluations.append(point)
            if on_new_best is not None and is_best:
                on_new_best(point, len(history.evaluations) - 1)
            if logger is not None:
                logger.log_scalar("eval/return", point.mean_return, step=it)
                logger.log_scalar("eval/epoch", point.epoch, step=it)
                logger.log_scalar("eval/failures", point.failures, step=it)
            bar.set_postfix(epoch=f"{point.epoch:.2f}", eval_return=f"{point.mean_return:.1f}")
            if checkpoint_path is not None:
                save_checkpoint(checkpoint_path, {
                    "algorithm": algorithm.state_dict(),
                    "iteration": it,
                    "evaluations": [e.__dict__ for e in history.evaluations],
                })
        bar.update(1)
    bar.close()
    history.iterations = iterations
    history.wall_time_s = time.perf_counter() - start
    return history


def _evaluate(evaluate: Callable, algorithm: Algorithm, iteration: int, epoch: float) -> EvalPoint:
    result = evaluate(algorithm.policy)
    if isinstance(result, (int, float)):
        return EvalPoint(iteration, epoch, float(result))
    return EvalPoint(iteration, epoch, result.mean_return, list(result.returns), result.failures)

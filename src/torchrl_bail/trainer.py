"""The one offline training loop every algorithm runs through.

``train`` samples mini-batches with replacement from the data an algorithm prepared, calls the algorithm's
update step, evaluates the deterministic policy every ``eval_every_epochs`` (an epoch is 10^6 samples
consumed, the paper's unit), logs scalars, shows a progress bar with ETA and the latest evaluation return,
and writes an atomic checkpoint before the first update, after each evaluation and every few minutes. Given
that checkpoint back (``resume_from``), it continues where the checkpoint left off and produces the same numbers
as a run that was never interrupted (docs: "Interrupted runs and preemption").

Examples:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from torchrl_bail.algorithms.bc import BehaviourCloning
    >>> from torchrl_bail.config import algo_config
    >>> from torchrl_bail.modules import action_spec_from_bounds
    >>> config = algo_config("bc", batch_size=10, epochs=100 / 1e6, policy={"hidden": [8]})
    >>> algo = BehaviourCloning(3, action_spec_from_bounds([-1.0], [1.0]), config)
    >>> data = TensorDict({"observation": torch.randn(50, 3), "action": torch.rand(50, 1) * 2 - 1}, [50])
    >>> history = train(algo, data, evaluate=lambda policy: 1.0, eval_every_epochs=50 / 1e6, progress=False)
    >>> history.iterations, [e.epoch * 1e6 for e in history.evaluations]
    (10, [50.0, 100.0])
"""

from __future__ import annotations

import math
import random
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.data import RandomSampler, TensorDictReplayBuffer, TensorStorage
from tqdm.auto import tqdm

from torchrl_bail.algorithms.base import Algorithm
from torchrl_bail.io import write_atomic

__all__ = ["CHECKPOINT_FORMAT", "EvalPoint", "TrainHistory", "rng_state", "save_checkpoint", "set_rng_state", "train"]

#: version of the checkpoint layout :func:`train` writes and resumes from
CHECKPOINT_FORMAT = 1


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
        """Mean of the last ``window`` evaluations (our per-seed score; supp. C.4)."""
        last = self.evaluations[-window:]
        return float(sum(e.mean_return for e in last) / len(last)) if last else float("nan")

    def best_return(self) -> float:
        return max((e.mean_return for e in self.evaluations), default=float("nan"))


def save_checkpoint(path: Path, state: dict) -> None:
    """``torch.save`` to a temp file in the same directory, then an atomic rename (a full disk: one line naming it)."""
    write_atomic(path, lambda f: torch.save(state, f))


def rng_state() -> dict[str, Any]:
    """The global random streams a run draws from: ``random``, NumPy and torch (CPU and, if present, CUDA).

    The mini-batch sampler (:class:`~torchrl.data.RandomSampler` over a :class:`~torchrl.data.TensorStorage`
    without a dedicated generator) draws its indices from torch's global generator of the data's device, so
    these states determine the sampler's stream too.
    """
    state = {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state()}
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["torch_cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict[str, Any]) -> None:
    """Restores what :func:`rng_state` captured."""
    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    torch.set_rng_state(state["torch"])
    if "torch_cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["torch_cuda"])


def train(
    algorithm: Algorithm,
    data: TensorDictBase,
    *,
    evaluate: Callable | None = None,
    samples_per_epoch: int = 1_000_000,
    eval_every_epochs: float = 0.5,
    logger=None,
    checkpoint_path: Path | None = None,
    checkpoint_every_s: float | None = None,
    checkpoint_extra: Callable[[], dict] | None = None,
    resume_from: dict | None = None,
    progress: bool = True,
    log_every: int = 100,
    on_new_best: Callable[[EvalPoint, int], None] | None = None,
) -> TrainHistory | list[TrainHistory]:
    """Runs ``algorithm`` for ``algorithm.epochs`` epochs on ``data``.

    Args:
        algorithm: the :class:`~torchrl_bail.algorithms.base.Algorithm` (its ``prepare`` already ran).
        data: the TensorDict ``[N]`` to sample from (with replacement).

    Keyword Args:
        evaluate: ``policy -> EvalResult | float``; called every ``eval_every_epochs`` and at the end. When it
            has ``state_dict``/``load_state_dict`` (its random stream), that state is checkpointed too.
        samples_per_epoch (int): samples in one epoch. Defaults to ``10**6``.
        eval_every_epochs (float): evaluation period in epochs. Defaults to ``0.5``.
        logger (Logger, optional): a TorchRL logger (``log_scalar``).
        checkpoint_path: where to write the checkpoint: before the first update, after every evaluation and
            every ``checkpoint_every_s`` seconds of training. Optional.
        checkpoint_every_s (float, optional): time-based checkpoint cadence (for long gaps between evaluations).
        checkpoint_extra: ``() -> dict`` of run-level entries added to each checkpoint (config, log sizes).
        resume_from (dict, optional): a checkpoint this function wrote; training continues after its iteration
            with every network, optimizer, metric accumulator, evaluation and random stream as they were, so the
            rest of the run is the same as an uninterrupted one. The algorithm's own
            :meth:`~torchrl_bail.algorithms.base.Algorithm.load_state_dict` must already have run.
        progress (bool): tqdm progress bar. Defaults to ``True``.
        log_every (int): training scalars are averaged and logged every ``log_every`` updates.
        on_new_best: ``(point, index)`` called when an evaluation beats every earlier one (e.g. to save the
            best policy); ``index`` is the evaluation's position in ``history.evaluations``.

    Several seeds at once (:mod:`torchrl_bail.stacking`): ``algorithm`` is a
    :class:`~torchrl_bail.stacking.SeedStack` of ``S`` seeds, ``data`` its
    :class:`~torchrl_bail.stacking.SeedBatchSampler`, ``evaluate`` returns one result per seed; ``logger``,
    ``on_new_best``, ``checkpoint_path``, ``checkpoint_extra`` and ``resume_from`` are lists, one per seed (one
    single-seed checkpoint per seed, :meth:`~torchrl_bail.stacking.SeedStack.seed_checkpoints`). A training scalar
    of shape ``[S]`` is logged per seed; a plain scalar (a loss averaged over the seeds) goes to every seed as
    ``train/<name>_mean_over_seeds``. The function then returns one :class:`TrainHistory` per seed.
    """
    seeds = getattr(algorithm, "seeds_count", None)
    batch_size = algorithm.batch_size
    per_update = algorithm.samples_per_update
    iterations = max(1, math.ceil(algorithm.epochs * samples_per_epoch / per_update))
    eval_interval = max(1, round(eval_every_epochs * samples_per_epoch / per_update))
    if seeds is None:
        if len(data) == 0:
            raise ValueError("the training data is empty: nothing to sample mini-batches from")
        data = data.to(algorithm.device)
        sampler = RandomSampler()
        buffer = TensorDictReplayBuffer(storage=TensorStorage(data), sampler=sampler, batch_size=batch_size)
    else:
        buffer = sampler = data  # a SeedBatchSampler: [S, B] mini-batches, one random stream per seed
    loggers = [logger] if seeds is None else list(logger or [None] * seeds)
    best_callbacks = [on_new_best] if seeds is None else list(on_new_best or [None] * seeds)
    histories = [TrainHistory() for _ in loggers]
    history = histories[0]
    sums: dict[str, torch.Tensor] = {}
    done, prior_wall_time = 0, 0.0
    if resume_from is not None:
        if seeds is not None:  # one checkpoint per seed
            resume_from = algorithm.merge_checkpoints(resume_from, sampler)
        done, prior_wall_time = _restore(resume_from, iterations, histories, sums, sampler, evaluate,
                                         per_seed=seeds is not None)
    start = time.perf_counter()

    def checkpoint(it: int) -> None:
        state = {
            "format": CHECKPOINT_FORMAT,
            "iteration": it,
            "iterations": iterations,
            "evaluations": ([asdict(e) for e in history.evaluations] if seeds is None
                            else [[asdict(e) for e in h.evaluations] for h in histories]),
            "metric_sums": {k: v.clone() if torch.is_tensor(v) else v for k, v in sums.items()},
            "rng": rng_state(),
            "sampler": sampler.state_dict(),
            "evaluator": evaluate.state_dict() if hasattr(evaluate, "state_dict") else None,
            "wall_time_s": prior_wall_time + time.perf_counter() - start,
        }
        if seeds is None:
            save_checkpoint(checkpoint_path, {**state, "algorithm": algorithm.state_dict(),
                                              **(checkpoint_extra() if checkpoint_extra is not None else {})})
            return
        for path, seed_state, extra in zip(checkpoint_path, algorithm.seed_checkpoints(state),
                                           checkpoint_extra or [None] * seeds):
            save_checkpoint(path, {**seed_state, **(extra() if extra is not None else {})})

    if checkpoint_path is not None and done == 0:
        checkpoint(0)  # what prepare() produced survives a kill before the first evaluation
    last_checkpoint = time.monotonic()
    bar = tqdm(total=iterations, initial=done, desc=f"{algorithm.name}", unit="it", disable=not progress,
               dynamic_ncols=True)
    for it in range(done + 1, iterations + 1):
        metrics = algorithm.update(buffer.sample())
        for k, v in metrics.items():
            sums[k] = sums.get(k, 0.0) + v
        if it % log_every == 0:
            for j, seed_logger in enumerate(loggers):
                for k, v in sums.items() if seed_logger is not None else ():
                    if seeds is not None and not (torch.is_tensor(v) and v.ndim):  # a loss' mean over the seeds
                        k, v = f"{k}_mean_over_seeds", v
                    value = v[j] if torch.is_tensor(v) and v.ndim else v
                    seed_logger.log_scalar(f"train/{k}", float(value) / log_every, step=it)
            sums.clear()
        evaluated = evaluate is not None and (it % eval_interval == 0 or it == iterations)
        if evaluated:
            points = _evaluate(evaluate, algorithm, it, it * per_update / samples_per_epoch)
            for point, seed_history, seed_logger, callback in zip(points, histories, loggers, best_callbacks):
                is_best = all(point.mean_return > e.mean_return for e in seed_history.evaluations)
                seed_history.evaluations.append(point)
                if callback is not None and is_best:
                    callback(point, len(seed_history.evaluations) - 1)
                if seed_logger is not None:
                    seed_logger.log_scalar("eval/return", point.mean_return, step=it)
                    seed_logger.log_scalar("eval/epoch", point.epoch, step=it)
                    seed_logger.log_scalar("eval/failures", point.failures, step=it)
            mean_return = sum(p.mean_return for p in points) / len(points)
            bar.set_postfix(epoch=f"{points[0].epoch:.2f}", eval_return=f"{mean_return:.1f}")
        if checkpoint_path is not None and (
            evaluated or it == iterations
            or (checkpoint_every_s is not None and time.monotonic() - last_checkpoint >= checkpoint_every_s)
        ):
            checkpoint(it)
            last_checkpoint = time.monotonic()
        bar.update(1)
    bar.close()
    for seed_history in histories:
        seed_history.iterations = iterations
        seed_history.wall_time_s = prior_wall_time + time.perf_counter() - start
    return history if seeds is None else histories


def _restore(state: dict, iterations: int, histories: list[TrainHistory], sums: dict, sampler, evaluate, *,
             per_seed: bool) -> tuple[int, float]:
    """Loads the loop's side of a checkpoint (``per_seed``: a stack's merged checkpoint, one evaluation list per
    seed, however many seeds); returns ``(iteration, wall time so far)``."""
    if state.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"checkpoint format {state.get('format')!r} is not {CHECKPOINT_FORMAT}: it was written by "
                         "another version of torchrl_bail and cannot be resumed (start over with resume=false)")
    if state["iterations"] != iterations:
        raise ValueError(f"the checkpoint's schedule has {state['iterations']} iterations but this run has "
                         f"{iterations}: the algorithm's epochs/batch size or samples_per_epoch changed")
    for history, evaluations in zip(histories, state["evaluations"] if per_seed else [state["evaluations"]]):
        history.evaluations.extend(EvalPoint(**e) for e in evaluations)
    sums.update(state["metric_sums"])
    sampler.load_state_dict(state["sampler"])
    if state.get("evaluator") is not None and hasattr(evaluate, "load_state_dict"):
        evaluate.load_state_dict(state["evaluator"])
    set_rng_state(state["rng"])
    return int(state["iteration"]), float(state.get("wall_time_s", 0.0))


def _evaluate(evaluate: Callable, algorithm: Algorithm, iteration: int, epoch: float) -> list[EvalPoint]:
    """One evaluation as one point per seed (a list of one for a single-seed run)."""
    results = evaluate(algorithm.policy)
    return [EvalPoint(iteration, epoch, float(result)) if isinstance(result, (int, float)) else
            EvalPoint(iteration, epoch, result.mean_return, list(result.returns), result.failures)
            for result in (results if isinstance(results, list) else [results])]

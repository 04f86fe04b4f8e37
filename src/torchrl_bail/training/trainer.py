"""The one offline training loop every algorithm runs through.

:func:`train` samples mini-batches with replacement from the data an algorithm prepared, calls the algorithm's
update step, evaluates the deterministic policy every ``eval_every_epochs`` (an epoch is 10^6 samples
consumed, the paper's unit), logs scalars, shows a progress bar with ETA and the latest evaluation return,
and writes an atomic checkpoint before the first update, after each evaluation and every few minutes, and, when
the entry point turned Ctrl-C or SIGTERM into a request (:mod:`torchrl_bail.core.interrupts`), after the update during
which it came, before it raises :class:`~torchrl_bail.core.interrupts.Interrupted`. Given
that checkpoint back (``resume_from``), it continues where the checkpoint left off and produces the same numbers
as a run that was never interrupted (docs: "Interrupted runs and preemption").

:func:`train` trains a :class:`Trainee` of ``S >= 1`` seeds and keeps every per-seed value (loggers, callbacks,
histories, checkpoint paths) in lists of ``S``; one seed is a list of one. :func:`make_trainee` makes the trainee of
a list of algorithms: one algorithm trains itself (:class:`AlgorithmTrainee`), ``S > 1`` train stacked
(:class:`~torchrl_bail.core.stacking.StackedTrainee`).

Examples:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from torchrl_bail.algorithms.bc import BehaviourCloning
    >>> from torchrl_bail.configuration.config_builders import algo_config
    >>> from torchrl_bail.modules import action_spec_from_bounds
    >>> config = algo_config("bc", batch_size=10, epochs=100 / 1e6, policy={"hidden": [8]})
    >>> algo = BehaviourCloning(3, action_spec_from_bounds([-1.0], [1.0]), config)
    >>> data = TensorDict({"observation": torch.randn(50, 3), "action": torch.rand(50, 1) * 2 - 1}, [50])
    >>> (history,) = train(make_trainee([algo], [data]), evaluate=lambda policy: [1.0], eval_every_epochs=50 / 1e6,
    ...                    progress=False)
    >>> history.iterations, [e.epoch * 1e6 for e in history.evaluations]
    (10, [50.0, 100.0])
"""

from __future__ import annotations

import contextlib
import math
import random
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.data import RandomSampler, TensorStorage

from torchrl_bail.algorithms.base import Algorithm
from torchrl_bail.core import interrupts
from torchrl_bail.core.io import write_atomic
from torchrl_bail.core.progress import tqdm
from torchrl_bail.core.stacking import SeedBatchSampler, SeedStack, StackedTrainee
from torchrl_bail.data.local_buffer import local_replay_buffer
from torchrl_bail.data.locks import check_fence

__all__ = ["CHECKPOINT_FORMAT", "AlgorithmTrainee", "EvalPoint", "TrainHistory", "Trainee", "evaluation_count",
           "make_trainee", "rng_state", "save_checkpoint", "set_rng_state", "snapshot_indices", "train"]

#: version of the checkpoint layout :func:`train` writes and resumes from
CHECKPOINT_FORMAT = 1


@dataclass
class EvalPoint:
    iteration: int
    epoch: float
    mean_return: float
    returns: list[float] = field(default_factory=list)
    failures: int = 0
    #: the mean discounted return at FQE's gamma (:attr:`~torchrl_bail.evaluation.EvalResult.mean_discounted_return`)
    discounted_return: float | None = None


@dataclass
class TrainHistory:
    iterations: int = 0
    evaluations: list[EvalPoint] = field(default_factory=list)
    wall_time_s: float = 0.0

    def final_return(self, window: int = 10) -> float:
        """Mean of the last ``window`` evaluations (our per-seed score; supp. C.4)."""
        last = self.evaluations[-window:]
        return float(sum(e.mean_return for e in last) / len(last)) if last else float("nan")

    def final_discounted_return(self, window: int = 10) -> float | None:
        """:meth:`final_return` of the discounted returns (``None`` when one of those evaluations has none)."""
        last = [e.discounted_return for e in self.evaluations[-window:]]
        return None if not last or None in last else float(sum(last) / len(last))

    def best_return(self) -> float:
        return max((e.mean_return for e in self.evaluations), default=float("nan"))


def evaluation_count(iterations: int, eval_interval: int) -> int:
    """How many evaluations :func:`train` makes: one every ``eval_interval`` iterations, and one at the end.

    Examples:
        >>> evaluation_count(10, 5), evaluation_count(12, 5)
        (2, 3)
    """
    return iterations // eval_interval + (iterations % eval_interval != 0)


def snapshot_indices(evaluations: int, count: int) -> list[int]:
    """The evaluations (indices into a run's ``evaluations``) whose policies a run of ``count`` snapshots keeps:
    ``count`` of them spread evenly, the ``k``-th at ``ceil(k * evaluations / count) - 1``, so that the last one is the
    final evaluation; every evaluation when ``count >= evaluations``, none for ``count = 0``.

    Examples:
        >>> snapshot_indices(10, 3), snapshot_indices(4, 8), snapshot_indices(10, 0)
        ([3, 6, 9], [0, 1, 2, 3], [])
    """
    count = min(count, evaluations)
    return [-(-k * evaluations // count) - 1 for k in range(1, count + 1)]


def save_checkpoint(path: Path, state: dict) -> None:
    """``torch.save`` to a temp file in the same directory, then an atomic rename (a full disk: one line naming it).

    Fenced: right before the rename, :func:`~torchrl_bail.data.locks.check_fence` refuses (``LockLost``, the temp
    file removed) when a lock this thread holds, the run directory's, was taken over by another job meanwhile, so a
    suspended run that wakes up after a take-over never overwrites its successor's checkpoint."""
    def write(f) -> None:
        torch.save(state, f)
        check_fence()

    write_atomic(path, write)


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


class Trainee(Protocol):
    """What :func:`train` trains: ``S >= 1`` seeds of one algorithm, seen as one learner (:func:`make_trainee`).

    :class:`AlgorithmTrainee` is one seed's algorithm with TorchRL's replay buffer;
    :class:`~torchrl_bail.core.stacking.StackedTrainee` is a :class:`~torchrl_bail.core.stacking.SeedStack` of ``S``
    seeds with
    its :class:`~torchrl_bail.core.stacking.SeedBatchSampler`. Per-seed values travel as lists of ``S``.
    """

    name: str
    epochs: float
    samples_per_update: int
    #: how the seeds' networks are held, for the run's log: ``"unstacked"`` or ``"networks stacked"``
    layout: str

    @property
    def seeds(self) -> int:
        """``S``, the number of seeds trained."""

    @property
    def policy(self) -> Callable:
        """The evaluation policy (``[S, N, obs_dim]`` observations when ``S > 1``)."""

    def sample(self) -> TensorDictBase:
        """The next mini-batch."""

    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        """One update step; returns its training scalars."""

    def plan_updates(self, updates: int) -> None:
        """Tells every seed's algorithm the run's number of updates
        (:meth:`~torchrl_bail.algorithms.base.Algorithm.plan_updates`)."""

    def compile(self, mode: bool | str) -> None:
        """Compiles the one update step (:meth:`~torchrl_bail.algorithms.base.Algorithm.compile`; a no-op for
        ``False``), after the checkpoint's state is in place."""

    def seed_metrics(self, sums: dict[str, Any]) -> list[dict[str, Any]]:
        """The accumulated training scalars as each seed logs them (one dict per seed)."""

    def checkpoints(self, state: dict[str, Any]) -> list[dict[str, Any]]:
        """The loop's ``state`` (``"evaluations"``: one list per seed) as one single-seed checkpoint per seed, each
        with its ``"algorithm"`` state and its mini-batch stream."""

    def restore(self, checkpoints: list[dict[str, Any]]) -> dict[str, Any]:
        """Loads the seeds' checkpoints' mini-batch streams; returns the loop's state (the inverse of
        :meth:`checkpoints`; each seed's algorithm already holds its ``"algorithm"`` state)."""

    def algorithms(self) -> list[Algorithm]:
        """Each seed's own algorithm, holding its current trained state."""


class AlgorithmTrainee:
    """One seed: ``algorithm`` itself, its mini-batches drawn with replacement from ``data`` (moved to the
    algorithm's device) by TorchRL's :class:`~torchrl.data.RandomSampler`, as a single-seed run always trained."""

    seeds = 1
    layout = "unstacked"

    def __init__(self, algorithm: Algorithm, data: TensorDictBase) -> None:
        if len(data) == 0:
            raise ValueError("the training data is empty: nothing to sample mini-batches from")
        self.algorithm = algorithm
        self.name, self.epochs = algorithm.name, algorithm.epochs
        self.samples_per_update = algorithm.samples_per_update
        self.sampler = RandomSampler()
        self.buffer = local_replay_buffer(TensorStorage, data.to(algorithm.device), sampler=self.sampler,
                                          batch_size=algorithm.batch_size)

    @property
    def policy(self):
        return self.algorithm.policy

    def sample(self) -> TensorDictBase:
        return self.buffer.sample()

    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        return self.algorithm.update(batch)

    def plan_updates(self, updates: int) -> None:
        self.algorithm.plan_updates(updates)

    def compile(self, mode: bool | str) -> None:
        self.algorithm.compile(mode)

    def seed_metrics(self, sums: dict[str, Any]) -> list[dict[str, Any]]:
        return [sums]

    def checkpoints(self, state: dict[str, Any]) -> list[dict[str, Any]]:
        (evaluations,) = state["evaluations"]
        return [{**state, "evaluations": evaluations, "sampler": self.sampler.state_dict(),
                 "algorithm": self.algorithm.state_dict()}]

    def restore(self, checkpoints: list[dict[str, Any]]) -> dict[str, Any]:
        (state,) = checkpoints
        self.sampler.load_state_dict(state["sampler"])
        return {**state, "evaluations": [state["evaluations"]]}

    def algorithms(self) -> list[Algorithm]:
        return [self.algorithm]


def make_trainee(algorithms: Sequence[Algorithm], datas: Sequence[TensorDictBase],
                 streams: Sequence[torch.Generator] | None = None) -> Trainee:
    """The :class:`Trainee` of ``S >= 1`` seeds' algorithms (each built, and prepared into its ``datas`` entry, as
    its single-seed run does).

    One algorithm trains itself (:class:`AlgorithmTrainee`): its mini-batches come from TorchRL's replay buffer on
    the global random stream, and its update is the plain one, so a list of one is the single-seed run to every
    digit (a seed-stacked update of one seed would round differently, see :mod:`torchrl_bail.core.stacking`). ``S > 1``
    train as one :class:`~torchrl_bail.core.stacking.SeedStack` on a
    :class:`~torchrl_bail.core.stacking.SeedBatchSampler`
    whose ``streams`` (per seed, the generator on the algorithms' device its mini-batch indices come from) give
    each seed its single-seed run's mini-batches.
    """
    algorithms, datas = list(algorithms), list(datas)
    if len(algorithms) == 1:
        return AlgorithmTrainee(algorithms[0], datas[0])
    if streams is None:
        raise ValueError(f"{len(algorithms)} seeds train stacked: pass one mini-batch stream (torch.Generator) per "
                         "seed")
    stack = SeedStack(algorithms)
    return StackedTrainee(stack, SeedBatchSampler(datas, stack.batch_size, streams, device=stack.device))


def train(
    trainee: Trainee,
    *,
    evaluate: Callable[[Callable], Sequence] | None = None,
    evaluation_state: Any | None = None,
    samples_per_epoch: int = 1_000_000,
    eval_every_epochs: float = 0.5,
    loggers: Sequence | None = None,
    checkpoint_paths: Sequence[Path] | None = None,
    checkpoint_every_s: float | None = None,
    checkpoint_extras: Sequence[Callable[[], dict] | None] | None = None,
    resume_from: Sequence[dict] | None = None,
    progress: bool = True,
    log_every: int = 100,
    on_new_best: Sequence[Callable[[EvalPoint, int], None] | None] | None = None,
    snapshots: int = 0,
    on_snapshot: Sequence[Callable[[EvalPoint, int], None] | None] | None = None,
) -> list[TrainHistory]:
    """The training loop: runs the ``S`` seeds of ``trainee`` (:func:`make_trainee`; their ``prepare`` already ran)
    for ``trainee.epochs`` epochs; returns one :class:`TrainHistory` per seed. Every per-seed argument is a list of
    ``S`` (``None`` entries allowed), a list of one for one seed.

    Keyword Args:
        evaluate: ``policy -> [result per seed]`` (an :class:`~torchrl_bail.evaluation.EvalResult` or a float
            each), e.g. :meth:`Evaluator.evaluate <torchrl_bail.evaluation.Evaluator.evaluate>`; called every
            ``eval_every_epochs`` and at the end.
        evaluation_state: the object whose ``state_dict``/``load_state_dict`` (the evaluation's random stream)
            is checkpointed with the loop, when it has them (the :class:`~torchrl_bail.evaluation.Evaluator`).
        samples_per_epoch (int): samples in one epoch. Defaults to ``10**6``.
        eval_every_epochs (float): evaluation period in epochs. Defaults to ``0.5``.
        loggers: per seed, a TorchRL logger (``log_scalar``). Its training scalars are what the trainee's
            ``seed_metrics`` names: a stack logs each seed's own ``[S]`` values under their names and a loss
            averaged over the seeds as ``train/<name>_mean_over_seeds``.
        checkpoint_paths: per seed, where to write its single-seed checkpoint: before the first update, after
            every evaluation and every ``checkpoint_every_s`` seconds of training. Optional.
        checkpoint_every_s (float, optional): time-based checkpoint cadence (for long gaps between evaluations).
        checkpoint_extras: per seed, ``() -> dict`` of run-level entries added to each of its checkpoints (config,
            log sizes).
        resume_from: per seed, a checkpoint this function wrote (a stack's seeds must have stopped at the same
            iteration); training continues after its iteration with every network, optimizer, metric
            accumulator, evaluation and random stream as they were, so the rest of the run is the same as an
            uninterrupted one. Each seed's algorithm must already hold the checkpoint's ``"algorithm"`` state
            (:meth:`~torchrl_bail.algorithms.base.Algorithm.load_state_dict`).
        progress (bool): tqdm progress bar. Defaults to ``True``.
        log_every (int): training scalars are averaged and logged every ``log_every`` updates.
        on_new_best: per seed, ``(point, index)`` called when an evaluation beats every earlier one of that seed
            (e.g. to save the best policy); ``index`` is the evaluation's position in its history.
        snapshots (int): how many evaluations, spread evenly over training (:func:`snapshot_indices`, the last one
            included), call ``on_snapshot``. Defaults to ``0``.
        on_snapshot: per seed, ``(point, index)`` called at those evaluations, after ``on_new_best`` and before
            the checkpoint (e.g. to save the policy: a resumed run calls it at the same evaluations as an
            uninterrupted one, and again at one whose checkpoint a kill prevented).
    """
    count = trainee.seeds
    per_update = trainee.samples_per_update
    iterations = max(1, math.ceil(trainee.epochs * samples_per_epoch / per_update))
    eval_interval = max(1, round(eval_every_epochs * samples_per_epoch / per_update))
    trainee.plan_updates(iterations)
    loggers = list(loggers or [None] * count)
    best_callbacks = list(on_new_best or [None] * count)
    snapshot_callbacks = list(on_snapshot or [None] * count)
    kept = set(snapshot_indices(evaluation_count(iterations, eval_interval), snapshots))
    extras = list(checkpoint_extras or [None] * count)
    histories = [TrainHistory() for _ in range(count)]
    sums: dict[str, torch.Tensor] = {}
    done, prior_wall_time = 0, 0.0
    if resume_from is not None:
        done, prior_wall_time = _restore(trainee, list(resume_from), iterations, histories, sums, evaluation_state)
    start = time.perf_counter()

    def checkpoint(it: int) -> None:
        with interrupts.saving():  # every seed's file whole before a signal may stop the process
            state = _loop_state(it, iterations, histories, sums, evaluation_state, prior_wall_time, start)
            _save_checkpoints(trainee, state, checkpoint_paths, extras)

    bar = tqdm(total=iterations, initial=done, desc=f"{trainee.name}", unit="it", disable=not progress,
               dynamic_ncols=True)
    # signals wait for the end of an update (interrupts.safe_points); the bar is closed on every way out
    with interrupts.safe_points(), contextlib.closing(bar):
        if checkpoint_paths is not None and done == 0:
            checkpoint(0)  # what prepare() produced survives a kill before the first evaluation
        last_checkpoint = time.monotonic()
        for it in range(done + 1, iterations + 1):
            metrics = trainee.update(trainee.sample())
            for k, v in metrics.items():
                sums[k] = sums.get(k, 0.0) + v
            if it % log_every == 0:
                _log_training(trainee, sums, loggers, log_every, it)
                sums.clear()
            evaluated = evaluate is not None and (it % eval_interval == 0 or it == iterations)
            if evaluated:
                points = _evaluate(evaluate, trainee, it, it * per_update / samples_per_epoch)
                _record_evaluation(points, histories, loggers, best_callbacks, it, snapshot_callbacks, kept)
                mean_return = sum(p.mean_return for p in points) / len(points)
                bar.set_postfix(epoch=f"{points[0].epoch:.2f}", eval_return=f"{mean_return:.1f}")
            saved = checkpoint_paths is not None and (
                evaluated or it == iterations
                or (checkpoint_every_s is not None and time.monotonic() - last_checkpoint >= checkpoint_every_s)
            )
            if saved:
                checkpoint(it)
                last_checkpoint = time.monotonic()
            bar.update(1)
            if interrupts.requested() is not None:  # Ctrl-C/SIGTERM: the checkpoint at this iteration, then stop
                _stop_on_interrupt(checkpoint, checkpoint_paths, saved, it, iterations)
    for seed_history in histories:
        seed_history.iterations = iterations
        seed_history.wall_time_s = prior_wall_time + time.perf_counter() - start
    return histories


def _loop_state(it: int, iterations: int, histories: list[TrainHistory], sums: dict, evaluation_state,
                prior_wall_time: float, start: float) -> dict[str, Any]:
    """The loop's side of a checkpoint at iteration ``it``: schedule, evaluations, metric sums, random streams and
    the wall time so far (``prior_wall_time`` of earlier processes + this one's since ``start``)."""
    return {
        "format": CHECKPOINT_FORMAT,
        "iteration": it,
        "iterations": iterations,
        "evaluations": [[asdict(e) for e in h.evaluations] for h in histories],
        "metric_sums": {k: v.clone() if torch.is_tensor(v) else v for k, v in sums.items()},
        "rng": rng_state(),
        "evaluator": evaluation_state.state_dict() if hasattr(evaluation_state, "state_dict") else None,
        "wall_time_s": prior_wall_time + time.perf_counter() - start,
    }


def _save_checkpoints(trainee: Trainee, state: dict[str, Any], paths: Sequence[Path],
                      extras: Sequence[Callable[[], dict] | None]) -> None:
    """Writes each seed's checkpoint: the trainee's seed state with the loop's ``state`` and the seed's extras."""
    for path, seed_state, extra in zip(paths, trainee.checkpoints(state), extras, strict=True):
        save_checkpoint(path, {**seed_state, **(extra() if extra is not None else {})})


def _log_training(trainee: Trainee, sums: dict, loggers: Sequence, log_every: int, it: int) -> None:
    """Logs each seed's training scalars, averaged over the last ``log_every`` updates."""
    for seed_logger, seed_sums in zip(loggers, trainee.seed_metrics(sums), strict=True):
        for k, v in seed_sums.items() if seed_logger is not None else ():
            seed_logger.log_scalar(f"train/{k}", float(v) / log_every, step=it)


def _record_evaluation(points: list[EvalPoint], histories: list[TrainHistory], loggers: Sequence,
                       best_callbacks: Sequence, it: int, snapshot_callbacks: Sequence, kept: set[int]) -> None:
    """Appends each seed's evaluation to its history, calls its ``on_new_best`` on a new best and its
    ``on_snapshot`` when the evaluation's index is ``kept``, logs it."""
    for point, seed_history, seed_logger, callback, snapshot in zip(points, histories, loggers, best_callbacks,
                                                                   snapshot_callbacks, strict=True):
        is_best = all(point.mean_return > e.mean_return for e in seed_history.evaluations)
        seed_history.evaluations.append(point)
        index = len(seed_history.evaluations) - 1
        if callback is not None and is_best:
            callback(point, index)
        if snapshot is not None and index in kept:
            snapshot(point, index)
        if seed_logger is not None:
            seed_logger.log_scalar("eval/return", point.mean_return, step=it)
            if point.discounted_return is not None:
                seed_logger.log_scalar("eval/discounted_return", point.discounted_return, step=it)
            seed_logger.log_scalar("eval/epoch", point.epoch, step=it)
            seed_logger.log_scalar("eval/failures", point.failures, step=it)


def _stop_on_interrupt(checkpoint: Callable[[int], None], checkpoint_paths: Sequence[Path] | None, saved: bool,
                       it: int, iterations: int) -> None:
    """Stops the run on a requested interrupt, with the checkpoint at iteration ``it`` written first (when
    checkpoints are on)."""
    if checkpoint_paths is None:
        interrupts.stop("nothing (checkpoint.enabled=false: a rerun starts over)")
    if not saved:
        checkpoint(it)
    interrupts.stop(f"the checkpoint at iteration {it} of {iterations} in "
                    f"{', '.join(str(p) for p in checkpoint_paths)}")


def _restore(trainee: Trainee, checkpoints: list[dict], iterations: int, histories: list[TrainHistory], sums: dict,
             evaluation_state) -> tuple[int, float]:
    """Loads the loop's side of the seeds' checkpoints; returns ``(iteration, wall time so far)``."""
    for checkpoint in checkpoints:
        if checkpoint.get("format") != CHECKPOINT_FORMAT:
            raise ValueError(f"checkpoint format {checkpoint.get('format')!r} is not {CHECKPOINT_FORMAT}: it was "
                             "written by another version of torchrl_bail and cannot be resumed (start over with "
                             "resume=false)")
        if checkpoint["iterations"] != iterations:
            raise ValueError(f"the checkpoint's schedule has {checkpoint['iterations']} iterations but this run has "
                             f"{iterations}: the algorithm's epochs/batch size or samples_per_epoch changed")
    state = trainee.restore(checkpoints)
    for history, evaluations in zip(histories, state["evaluations"], strict=True):
        history.evaluations.extend(EvalPoint(**e) for e in evaluations)
    sums.update(state["metric_sums"])
    if state.get("evaluator") is not None and hasattr(evaluation_state, "load_state_dict"):
        evaluation_state.load_state_dict(state["evaluator"])
    set_rng_state(state["rng"])
    return int(state["iteration"]), float(state.get("wall_time_s", 0.0))


def _evaluate(evaluate: Callable, trainee: Trainee, iteration: int, epoch: float) -> list[EvalPoint]:
    """One evaluation as one point per seed."""
    return [EvalPoint(iteration, epoch, float(result)) if isinstance(result, (int, float)) else
            EvalPoint(iteration, epoch, result.mean_return, list(result.returns), result.failures,
                      getattr(result, "mean_discounted_return", None))
            for result in evaluate(trainee.policy)]

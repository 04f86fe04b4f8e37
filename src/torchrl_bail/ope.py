"""Score trained policies without the simulator: ``python -m torchrl_bail.ope RUN_DIR... [--fits K] [--seed S]``.

For each run directory, Fitted Q Evaluation (:class:`~torchrl_bail.objectives.fqe.FQELoss`, Le et al. 2019; used
for policy selection by Paine et al. 2020): the run's policy (``policy.pt``; ``--best``: ``policy_best.pt``, loaded
with :func:`~torchrl_bail.evaluation.policy.load_policy`) is held fixed and a Q network is fitted on the run's own batch
(the
data cache its ``config.yaml`` names: the generated batch of its ``env`` x ``batch``, or its ``dataset=``; nothing
is collected here) by :func:`fit_fqe`, until its curve settles (:func:`curve_converged`: ``--stop-window``,
``--stop-tol``) or ``--updates``, the cap. ``--fits K`` independent fits (seeds ``S .. S + K - 1``,
:func:`fit_fqe_fits`) give the estimate, their mean, and its spread, their standard deviation. A fit's estimate is
the mean of ``Q(s_0, pi(s_0))`` over the batch's episode starts, a discounted value (``--gamma``) meant for ranking
policies trained on the same batch.

Beside the run it writes ``ope.json`` (``ope_best.json`` with ``--best``), atomically: the estimate and spread, the
settings and seed, the number of fits and how many settled before the cap, the policy file's SHA-1, the batch, and
each fit's curve (the estimate and the mean TD loss every ``--log-every`` updates). A finished ``ope.json`` is kept
unless ``--force`` (or the run was trained again since: its policy file's SHA-1 differs).

A run trained with ``eval.snapshots=N`` kept ``N`` policy snapshots (listed in its ``summary.json``); each is fitted
too (``snapshots/ope_policy_<iteration>.json``) and :func:`select_snapshot` ranks them by a selection rule
(``--rule``, :func:`rule_scores`: the highest mean estimate by default, or a pessimistic lower bound, or the estimate
less a penalty for acting far from the batch): the ranking and ``fqe_selected`` (the policy it would deploy, with
the evaluation return the run recorded for it) go into ``ope.json``, and ``fqe_selected`` into ``summary.json``. Each
fit shows a tqdm bar (ETA) and checkpoints into ``ope_checkpoint.pt`` (``ope_fit<i>_checkpoint.pt`` for the later
fits) every ``--checkpoint-every-s`` seconds and on Ctrl-C or SIGTERM; the same command continues from it, to the
same numbers as an uninterrupted fit, and keeps the fits that had finished (a checkpoint is used only when its
settings, seed, policy and batch are the command's; they are removed once ``ope.json`` is written).

A bad option stops the command before anything is loaded, with one line (exit status 2). A run that cannot be
scored (no such directory, no ``config.yaml`` or policy file, a damaged policy file, a batch not in the cache) is
reported in one line with its reason, and every other run is scored all the same; the command then ends with a line
naming the runs not scored, and exit status 2. When none of the runs can be scored it stops before torch loads.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import hashlib
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["DEFAULT_FITS", "DEFAULT_RULE", "FQESettings", "OPEError", "RULES", "action_gap", "compare_rules",
           "curve_converged", "fit_fqe", "fit_fqe_fits", "fqe_update", "listed_snapshots", "ranking_quality",
           "rule_scores", "run_batch", "score_run", "select_by_rule", "select_snapshot", "spearman_interval", "main"]

#: 2: a record holds the estimate as the mean of ``num_fits`` fits, their ``spread`` and each fit's curve (``fits``)
OPE_FORMAT = 2
#: independent fits per policy (``--fits``): the estimate is their mean and the spread their standard deviation.
#: 4 is the smallest number whose mean has a standard error, from the mini-batch noise alone that the 40 kept
#: curves of the OPE study show (the detrended standard deviation of each curve's last 20 points: median 1.92 % of
#: the estimate), at most half the stopping tolerance: (1.92 / 1.0)^2 = 3.7 (docs/guides/ope.md, "Several fits")
DEFAULT_FITS = 4
#: the selection rules (:func:`rule_scores`) and the default one: no other is measured to rank the OPE study's
#: policies better (docs/guides/ope.md, "Selection rules")
RULES = ("mean", "lower_bound", "gap_penalised")
DEFAULT_RULE = "mean"
#: ``lower_bound``: mean - k x spread; ``gap_penalised``: mean - lambda x gap x the candidates' median |mean|
DEFAULT_K, DEFAULT_LAMBDA = 1.0, 1.0
#: the entries of a batch the fit reads
_KEYS = ("observation", "action", "episode", ("next", "observation"), ("next", "reward"), ("next", "terminated"))


class OPEError(ValueError):
    """A run cannot be scored (its batch is not in the cache, sizes do not match...); the message names the run."""


@dataclass(frozen=True)
class FQESettings:
    """How :func:`fit_fqe` fits FQE; the defaults and their sources are in :class:`~torchrl_bail.objectives.fqe.FQELoss`
    (d3rlpy's ``FQEConfig`` and its off-policy-evaluation reference page).

    Attributes:
        updates: the most gradient updates of a fit (its cap): the stopping rule (``stop_window``, ``stop_tol``,
            :func:`curve_converged`) ends it earlier once its curve has settled. Defaults to ``500_000``: a cost
            bound, not a convergence claim; a fit that reaches it is recorded ``converged: false``. (d3rlpy fits
            ``10^5``; none of the OPE study's 40 kept curves had settled there.)
        batch_size: transitions per mini-batch, drawn uniformly with replacement. Defaults to ``100``.
        lr: Adam's learning rate. Defaults to ``1e-4``.
        hidden: the Q network's hidden sizes (ReLU). Defaults to ``(256, 256)``.
        target_update_period: the target network is copied from the network every this many updates.
            Defaults to ``100``.
        gamma: discount. Defaults to :data:`~torchrl_bail.objectives.fqe.FQE_GAMMA` (``0.99``, the value the
            evaluation's discounted return (:class:`~torchrl_bail.evaluation.Evaluator`) takes too).
        log_every: a point of the fitting curve (estimate, mean TD loss) every this many updates, and at the last.
            Defaults to ``1000``.
        stop_window: the stopping rule's window, in points of the curve (:func:`curve_converged`); ``0`` turns the
            rule off (every fit runs ``updates`` updates). Defaults to ``20``.
        stop_tol: the stopping rule's tolerance, relative to the estimate. Defaults to ``0.02``.

    Examples:
        >>> FQESettings()  # doctest: +NORMALIZE_WHITESPACE
        FQESettings(updates=500000, batch_size=100, lr=0.0001, hidden=(256, 256), target_update_period=100,
                    gamma=0.99, log_every=1000, stop_window=20, stop_tol=0.02)
        >>> FQESettings(updates=0).check()
        Traceback (most recent call last):
        ...
        ValueError: updates = 0: expected an integer >= 1
    """

    updates: int = 500_000
    batch_size: int = 100
    lr: float = 1e-4
    hidden: tuple[int, ...] = (256, 256)
    target_update_period: int = 100
    gamma: float = 0.99  # = objectives.fqe.FQE_GAMMA (tests/test_fqe.py): this module loads no torch at import
    log_every: int = 1000
    stop_window: int = 20
    stop_tol: float = 0.02

    def check(self) -> FQESettings:
        """Raises :class:`ValueError` naming the first value out of range; returns the settings."""
        for name in ("updates", "batch_size", "target_update_period", "log_every"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} = {value!r}: expected an integer >= 1")
        if not (isinstance(self.lr, (int, float)) and math.isfinite(self.lr) and self.lr > 0):
            raise ValueError(f"lr = {self.lr!r}: expected a positive learning rate")
        if not (isinstance(self.gamma, (int, float)) and 0.0 <= self.gamma <= 1.0):
            raise ValueError(f"gamma = {self.gamma!r}: expected a discount in [0, 1]")
        if isinstance(self.stop_window, bool) or not isinstance(self.stop_window, int) or self.stop_window < 0:
            raise ValueError(f"stop_window = {self.stop_window!r}: expected an integer >= 0 (0: no stopping rule)")
        if not (isinstance(self.stop_tol, (int, float)) and math.isfinite(self.stop_tol) and self.stop_tol >= 0):
            raise ValueError(f"stop_tol = {self.stop_tol!r}: expected a tolerance >= 0")
        if not self.hidden or any(isinstance(h, bool) or not isinstance(h, int) or h < 1 for h in self.hidden):
            raise ValueError(f"hidden = {self.hidden!r}: expected one or more positive layer sizes")
        return self


def curve_converged(estimates: Sequence[float], window: int, tol: float) -> bool:
    """The stopping rule of a fit: has the curve of estimates settled?

    With ``n`` points so far (one every ``log_every`` updates), the mean of the last ``window`` points and the mean of
    the ``window`` points ending at point ``n // 2`` (half the updates so far) differ by less than ``tol`` times the
    first's size. So a fit stops once doubling its updates changed the estimate by less than ``tol``: a curve that
    approaches its limit exponentially passes within a few time constants, one that keeps rising (linearly, or as a
    logarithm) does not, and a plateau shorter than half the fit is not taken for the limit. Until ``n // 2 >= window``
    (and with ``window = 0``) it never stops. The defaults (``window = 20``, ``tol = 0.02``) were measured on the
    OPE study's kept curves (docs/guides/ope.md, "The stopping rule").

    Examples:
        >>> settled = [100.0 * (1 - 0.5 ** (k / 4)) for k in range(1, 81)]  # a time constant of 6 points
        >>> curve_converged(settled[:40], 10, 0.02), curve_converged(settled, 10, 0.02)
        (False, True)
        >>> curve_converged([float(k) for k in range(1, 81)], 10, 0.02)  # rising: never
        False
    """
    n = len(estimates)
    if window < 1 or n // 2 < window:
        return False
    last = sum(estimates[n - window:]) / window
    half = sum(estimates[n // 2 - window:n // 2]) / window
    return abs(last - half) < tol * abs(last)


def _bar(total: int, desc: str, unit: str, progress: bool, **kwargs):
    """A tqdm bar of this command (ETA; off without ``progress``): the fit's, and the policy's passes over the
    batch, which take minutes for a sampling policy at 10^6 transitions."""
    from torchrl_bail.core.progress import tqdm

    return tqdm(total=total, desc=desc, unit=unit, disable=not progress, dynamic_ncols=True, mininterval=0.5,
                **kwargs)


def _as_float(value) -> float:
    return float(value.item() if hasattr(value, "item") else value)


def _read_checkpoint(path: Path | None, identity: dict) -> dict | None:
    """The fit checkpoint at ``path`` when it is this fit's (same ``identity``), else ``None`` (with a line on
    stderr when one is there but not usable)."""
    import torch

    if path is None or not path.exists():
        return None
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 - an unreadable checkpoint is set aside: the fit starts over
        print(f"torchrl_bail.ope: ignoring unreadable {path} ({type(err).__name__}); fitting from the start",
              file=sys.stderr)
        return None
    if not isinstance(state, dict) or state.get("format") != OPE_FORMAT or state.get("identity") != identity:
        print(f"torchrl_bail.ope: {path} is another fit's (settings, seed, policy or batch differ); fitting from "
              f"the start", file=sys.stderr)
        return None
    return state


@contextlib.contextmanager
def _own_random_stream(seed: int, device):
    """Inside the block, torch's global generators (the CPU's, and ``device``'s when it is a GPU) seeded with
    ``seed``; after it, as they were before. What a fit draws from them (the Q network's initial weights, a sampling
    policy's actions) is its seed's alone, and the caller's random stream goes on as if the fit had not run."""
    import torch

    device = torch.device(device)
    cuda = [torch.cuda.current_device() if device.index is None else device.index] if device.type == "cuda" else []
    with torch.random.fork_rng(devices=cuda):
        torch.default_generator.manual_seed(int(seed))
        for index in cuda:
            with torch.cuda.device(index):
                torch.cuda.manual_seed(int(seed))
        yield


def fqe_update(loss, optimizer, updater, batch):
    """One update of the fit (:func:`fit_fqe`'s step, and ``benchmarks/bench_fqe.py``'s): the squared TD error of
    ``loss`` (:class:`~torchrl_bail.objectives.fqe.FQELoss`) on ``batch``, a step of ``optimizer``, a step of the
    target ``updater``; returns the loss, detached."""
    loss_value, _ = loss.qvalue_loss(batch)
    optimizer.zero_grad(set_to_none=True)
    loss_value.backward()
    optimizer.step()
    updater.step()
    return loss_value.detach()


def fit_fqe(policy, data, settings: FQESettings | None = None, *, seed: int = 0, device="cpu",
            progress: bool = False, checkpoint_path: str | Path | None = None, checkpoint_every_s: float = 300.0,
            identity: dict | None = None, desc: str = "fqe") -> dict[str, Any]:
    """Fits FQE for the fixed ``policy`` on ``data`` and returns its estimate and fitting curve.

    The fit runs until its curve settles by the stopping rule (:func:`curve_converged` with ``settings.stop_window``
    and ``settings.stop_tol``, checked at each point of the curve) or for ``settings.updates`` updates, the cap.
    :func:`fit_fqe_fits` makes several independent fits of one policy.

    Seeded with ``seed``: torch's global generator, seeded with ``seed`` for the fit and restored after it (the
    caller's random stream goes on as if the fit had not run), draws the Q network's initial weights, then the
    policy's actions at every state and next state (computed once:
    :meth:`~torchrl_bail.objectives.fqe.FQELoss.add_policy_actions`; only a sampling policy such as BCQ's draws
    here); a generator of its own draws the mini-batches. The same seed, data, settings, device and thread count
    give the same numbers, whatever the caller drew before. Those actions (minutes of draws for a sampling
    policy at 10^6 transitions, with a bar of their own) are part of every checkpoint, and the first checkpoint is
    written as soon as they are computed: a continued fit never computes them again.

    Args:
        policy (TensorDictModule): the policy to evaluate (``"observation" -> "action"``).
        data (TensorDictBase): a ``[N]`` TED batch with ``observation``, ``action``, ``episode`` and ``("next",
            "observation" | "reward" | "terminated")``; it is copied to ``device``, the rest is left out.
        settings (FQESettings, optional): defaults to :class:`FQESettings`'s defaults.

    Keyword Args:
        seed (int): see above. Defaults to ``0``.
        device (str | torch.device): where the fit runs. Defaults to ``"cpu"``.
        progress (bool): a tqdm bar (ETA, the current estimate and TD loss). Defaults to ``False``.
        checkpoint_path (str | Path, optional): where the fit checkpoints (once the policy's actions are computed,
            every ``checkpoint_every_s`` seconds and when Ctrl-C or SIGTERM arrives through
            :mod:`torchrl_bail.core.interrupts`) and what it continues from
            when that file holds a checkpoint of the same ``identity``.
        checkpoint_every_s (float): seconds between checkpoints. Defaults to ``300``.
        identity (dict, optional): what a checkpoint must match to be continued (settings and seed are added).
        desc (str): the bar's label.

    Returns:
        ``{"estimate", "updates", "converged", "curve", "num_episode_starts", "num_transitions", "wall_time_s",
        "resumed_at"}``; ``curve`` is a list of ``{"update", "estimate", "td_loss"}`` (``td_loss``: the mean squared
        TD error over the updates since the previous point), ``updates`` the updates run (the stopping rule's stop,
        else ``settings.updates``), ``converged`` whether the stopping rule (:func:`curve_converged`) ended the fit,
        ``resumed_at`` the update a checkpoint continued from (``0`` when the fit started afresh). With a
        ``checkpoint_path``, a finished fit leaves its result there: the same call returns it without fitting.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_bail.modules import action_spec_from_bounds, make_deterministic_actor
        >>> policy = make_deterministic_actor(3, action_spec_from_bounds([-1.0], [1.0]), (8,))
        >>> n = 20
        >>> data = TensorDict({"observation": torch.randn(n, 3), "action": torch.rand(n, 1),
        ...                    "episode": torch.arange(n) // 5,  # 4 episodes of 5 steps
        ...                    "next": {"observation": torch.randn(n, 3), "reward": torch.ones(n, 1),
        ...                             "terminated": torch.zeros(n, 1, dtype=torch.bool)}}, [n])
        >>> settings = FQESettings(updates=20, hidden=(16,), log_every=10)
        >>> result = fit_fqe(policy, data, settings, seed=1)
        >>> [point["update"] for point in result["curve"]], result["num_episode_starts"]
        ([10, 20], 4)
        >>> result["estimate"] == fit_fqe(policy, data, settings, seed=1)["estimate"]  # same seed, same numbers
        True
    """
    with _own_random_stream(seed, device):
        return _fit_fqe(policy, data, settings, seed=seed, device=device, progress=progress,
                        checkpoint_path=checkpoint_path, checkpoint_every_s=checkpoint_every_s, identity=identity,
                        desc=desc)


def _fit_fqe(policy, data, settings: FQESettings | None, *, seed: int, device, progress: bool,
             checkpoint_path: str | Path | None, checkpoint_every_s: float, identity: dict | None,
             desc: str) -> dict[str, Any]:
    """:func:`fit_fqe` inside its own random stream (torch's global generator seeded with ``seed``)."""
    import torch
    from torchrl.objectives import HardUpdate

    from torchrl_bail.core import interrupts
    from torchrl_bail.core.io import write_atomic
    from torchrl_bail.modules import make_qvalue_network
    from torchrl_bail.objectives.fqe import FQELoss, episode_starts

    settings = (settings or FQESettings()).check()
    device = torch.device(device)
    checkpoint_path = None if checkpoint_path is None else Path(checkpoint_path)
    identity = {**(identity or {}), "settings": dataclasses.asdict(settings), "seed": int(seed),
                "device": device.type}
    identity["settings"]["hidden"] = list(settings.hidden)
    state = _read_checkpoint(checkpoint_path, identity)
    if state is not None and "result" in state:  # this fit had finished (one of several fits of a command)
        return dict(state["result"])
    data = data.select(*_KEYS).to_tensordict().to(device)
    num = int(data.batch_size[0])
    obs_dim, act_dim = data["observation"].shape[-1], data["action"].shape[-1]

    loss = FQELoss(make_qvalue_network(obs_dim, act_dim, settings.hidden), policy, gamma=settings.gamma).to(device)
    # TorchRL's HardUpdate copies on the (interval + 1)-th step(): every target_update_period-th update here
    updater = HardUpdate(loss, value_network_update_interval=settings.target_update_period - 1)
    action_keys = (loss.tensor_keys.policy_action, ("next", loss.tensor_keys.policy_action))
    _add_policy_actions(state, loss, data, action_keys, desc=desc, progress=progress)
    starts = data[episode_starts(data["episode"])]
    optimizer = torch.optim.Adam(loss.parameters(), lr=settings.lr)
    generator = torch.Generator(device=device).manual_seed(int(seed))

    done, curve, prior_wall_time, td_sum, td_count = _restore(state, loss, optimizer, generator, updater, device)
    resumed_at = done
    start = time.perf_counter()

    def save(update: int) -> str:
        with interrupts.saving():
            checkpoint = {"format": OPE_FORMAT, "identity": identity, "update": update, "loss": loss.state_dict(),
                          "optimizer": optimizer.state_dict(), "generator": generator.get_state(),
                          "target_counter": updater.counter, "curve": curve, "td_sum": td_sum.cpu(),
                          "td_count": td_count, "wall_time_s": prior_wall_time + time.perf_counter() - start,
                          "policy_actions": [data.get(key).cpu() for key in action_keys]}
            write_atomic(checkpoint_path, lambda f: torch.save(checkpoint, f))
        return f"the FQE fit at update {update} in {checkpoint_path}"

    if checkpoint_path is not None and state is None:
        save(0)  # the policy's actions first: a stop before the first timed checkpoint never draws them again

    def settled() -> bool:  # the stopping rule, at a point of the curve
        return curve_converged([point["estimate"] for point in curve], settings.stop_window, settings.stop_tol)

    # a checkpoint taken at the very point the rule stopped at (a signal there) is a finished fit
    converged = bool(curve) and curve[-1]["update"] == done and settled()
    bar = _bar(settings.updates, desc, "update", progress, initial=done)
    # signals wait for the end of an update (interrupts.safe_points); the bar is closed on every way out
    with interrupts.safe_points(), contextlib.closing(bar):
        last_save = time.monotonic()
        for update in range(done + 1, done + 1 if converged else settings.updates + 1):
            index = torch.randint(num, (settings.batch_size,), generator=generator, device=device)
            td_sum += fqe_update(loss, optimizer, updater, data[index])
            td_count += 1
            if update % settings.log_every == 0 or update == settings.updates:
                estimate = _as_float(loss.policy_value(starts))
                curve.append({"update": update, "estimate": estimate, "td_loss": _as_float(td_sum) / td_count})
                td_sum.zero_()
                td_count = 0
                bar.set_postfix(estimate=f"{estimate:.2f}", td_loss=f"{curve[-1]['td_loss']:.3g}")
                converged = settled()
            bar.update(1)
            if converged:
                break
            stopping = interrupts.requested() is not None  # Ctrl-C/SIGTERM: the checkpoint at this update, then stop
            saved = None
            if checkpoint_path is not None and (stopping or (
                    update < settings.updates and time.monotonic() - last_save >= checkpoint_every_s)):
                saved = save(update)
                last_save = time.monotonic()
            if stopping:
                interrupts.stop(saved)
        result = {"estimate": curve[-1]["estimate"], "updates": curve[-1]["update"], "converged": converged,
                  "curve": curve, "num_episode_starts": int(starts.batch_size[0]), "num_transitions": num,
                  "wall_time_s": prior_wall_time + time.perf_counter() - start, "resumed_at": resumed_at}
        if checkpoint_path is not None:  # finished: a command stopped in a later fit keeps this one as it is
            with interrupts.saving():
                finished = {"format": OPE_FORMAT, "identity": identity, "update": result["updates"],
                            "result": result}
                write_atomic(checkpoint_path, lambda f: torch.save(finished, f))
    return result


def _add_policy_actions(state: dict | None, loss, data, action_keys, *, desc: str, progress: bool) -> None:
    """The policy's actions at every state and next state of ``data``, from the checkpoint ``state`` when it holds
    them (a checkpoint of an older version has none), else computed (drawn, for a sampling policy)."""
    if state is not None and "policy_actions" in state:
        for key, actions in zip(action_keys, state["policy_actions"], strict=True):
            data.set(key, actions.to(data.device))
        return
    with _bar(2 * int(data.batch_size[0]), f"{desc}: the policy's actions", "state", progress) as actions_bar:
        loss.add_policy_actions(data, on_chunk=actions_bar.update)


def _restore(state: dict | None, loss, optimizer, generator, updater, device) -> tuple:
    """A fit's loop state from its checkpoint (``state``; ``None``: a fresh fit): ``(update, curve, wall time so
    far, the TD loss sum and count since the last point)``, the networks, optimizer, generator and target counter
    set as they were."""
    import torch

    if state is None:
        return 0, [], 0.0, torch.zeros((), dtype=torch.float64, device=device), 0
    loss.load_state_dict(state["loss"])
    optimizer.load_state_dict(state["optimizer"])
    generator.set_state(state["generator"])
    updater.counter = int(state["target_counter"])
    return (int(state["update"]), list(state["curve"]), float(state["wall_time_s"]), state["td_sum"].to(device),
            int(state["td_count"]))


def _fit_checkpoint(path: Path | None, index: int) -> Path | None:
    """The checkpoint of the ``index``-th of several fits: ``path`` itself for the first, and beside it for the
    others ``ope_fit<index>_checkpoint.pt`` for ``ope_checkpoint.pt`` (``<stem>_fit<index><suffix>`` for a name
    without ``_checkpoint``): every fit's checkpoint ends in ``_checkpoint.pt``."""
    if path is None or index == 0:
        return path
    stem = path.stem
    if stem.endswith("_checkpoint"):
        return path.with_name(f"{stem[:-len('_checkpoint')]}_fit{index}_checkpoint{path.suffix}")
    return path.with_name(f"{stem}_fit{index}{path.suffix}")


def fit_fqe_fits(policy, data, settings: FQESettings | None = None, *, fits: int = DEFAULT_FITS, seed: int = 0,
                 device="cpu", progress: bool = False, checkpoint_path: str | Path | None = None,
                 checkpoint_every_s: float = 300.0, identity: dict | None = None,
                 desc: str = "fqe") -> dict[str, Any]:
    """``fits`` independent FQE fits of ``policy`` (:func:`fit_fqe`, seeds ``seed``, ``seed + 1``, ...: each its own Q
    network initialisation, mini-batches and, for a sampling policy, draws), each until the stopping rule or the
    cap; the estimate is their mean and the spread their standard deviation.

    Each fit checkpoints into its own file (``checkpoint_path`` for the first, ``ope_fit<i>_checkpoint.pt`` beside
    ``ope_checkpoint.pt`` for the others), and a finished fit's checkpoint holds its result: a command stopped during
    the third fit continues that one and keeps the first two as they were. Other arguments as in :func:`fit_fqe`.

    Returns:
        ``{"estimate", "spread", "fits", "converged_fits", "num_episode_starts", "num_transitions", "wall_time_s",
        "resumed_at"}``: ``estimate`` the mean of the fits' estimates; ``spread`` their sample standard deviation
        (``None`` for one fit); ``fits`` one ``{"seed", "estimate", "updates", "converged", "curve", "wall_time_s",
        "resumed_at"}`` per fit (``converged``: the stopping rule ended it before the cap); ``wall_time_s`` their
        sum; ``resumed_at`` the update the first continued fit started from (``0``: none was).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_bail.modules import action_spec_from_bounds, make_deterministic_actor
        >>> policy = make_deterministic_actor(3, action_spec_from_bounds([-1.0], [1.0]), (8,))
        >>> n = 20
        >>> data = TensorDict({"observation": torch.randn(n, 3), "action": torch.rand(n, 1),
        ...                    "episode": torch.arange(n) // 5,
        ...                    "next": {"observation": torch.randn(n, 3), "reward": torch.ones(n, 1),
        ...                             "terminated": torch.zeros(n, 1, dtype=torch.bool)}}, [n])
        >>> result = fit_fqe_fits(policy, data, FQESettings(updates=20, hidden=(16,), log_every=10), fits=3, seed=5)
        >>> [fit["seed"] for fit in result["fits"]], result["spread"] > 0
        ([5, 6, 7], True)
    """
    import statistics

    if isinstance(fits, bool) or not isinstance(fits, int) or fits < 1:
        raise ValueError(f"fits = {fits!r}: expected an integer >= 1")
    checkpoint_path = None if checkpoint_path is None else Path(checkpoint_path)
    results, last = [], None
    for index in range(fits):
        last = fit_fqe(policy, data, settings, seed=seed + index, device=device, progress=progress,
                       checkpoint_path=_fit_checkpoint(checkpoint_path, index), checkpoint_every_s=checkpoint_every_s,
                       identity=identity, desc=desc if fits == 1 else f"{desc} fit {index + 1}/{fits}")
        results.append({"seed": seed + index, **{key: last[key] for key in ("estimate", "updates", "converged",
                                                                            "curve", "wall_time_s", "resumed_at")}})
    estimates = [fit["estimate"] for fit in results]
    return {"estimate": sum(estimates) / fits, "spread": statistics.stdev(estimates) if fits > 1 else None,
            "fits": results, "converged_fits": sum(bool(fit["converged"]) for fit in results),
            "num_episode_starts": last["num_episode_starts"], "num_transitions": last["num_transitions"],
            "wall_time_s": sum(fit["wall_time_s"] for fit in results),
            "resumed_at": next((fit["resumed_at"] for fit in results if fit["resumed_at"]), 0)}


# -- a run directory ----------------------------------------------------------------------------------------------
def _sha1(path: Path) -> str:
    digest = hashlib.sha1()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def run_batch(run_dir: str | Path, cfg=None, data_dir: str | Path | None = None):
    """The batch the run in ``run_dir`` trained on (an :class:`~torchrl_bail.data.batch.OfflineBatch`; its
    transitions are ``.data``), from the data cache (``data_dir``: else the config's ``data_dir``, else
    ``$TORCHRL_BAIL_DATA_DIR`` or ``~/.cache/torchrl_bail``), or its ``dataset=``; never collected here. ``cfg``: the
    run's config, read from its ``config.yaml`` when not given. Raises :class:`OPEError` when the batch is not in the
    cache."""
    from torchrl_bail.configuration.config_builders import collection_config
    from torchrl_bail.data.cache import batch_path, load_cached_batch

    run_dir = Path(run_dir)
    if cfg is None:
        from omegaconf import OmegaConf

        cfg = OmegaConf.load(run_dir / "config.yaml")

    if cfg.get("dataset"):
        from torchrl_bail.data.importers import import_dataset

        return import_dataset(Path(str(cfg.dataset)).expanduser(), env_id=cfg.env.id,
                              data_dir=data_dir if data_dir is not None else cfg.get("data_dir"))
    collection = collection_config(cfg)
    path = batch_path(collection, data_dir)
    batch = load_cached_batch(path, remedy="it cannot be scored")
    if batch is None:
        raise OPEError(f"{run_dir}: its batch {path} is not in the data cache; collect it (python -m "
                       f"torchrl_bail.collect with the run's +exp/env/batch) or point --data-dir at the cache that "
                       f"holds it")
    return batch


def output_path(run_dir: str | Path, *, best: bool = False) -> Path:
    """``<run_dir>/ope.json`` (``ope_best.json`` for the best-evaluated policy)."""
    return Path(run_dir) / ("ope_best.json" if best else "ope.json")


def _settings_record(settings: FQESettings) -> dict[str, Any]:
    return {**dataclasses.asdict(settings), "hidden": list(settings.hidden)}


def action_gap(policy, data, *, seed: int = 0, chunk: int = 65536, progress: bool = False) -> float:
    """How far ``policy`` acts from the batch: the root mean square, over the batch's transitions and action
    dimensions, of ``pi(s) - a``, each dimension divided by half its action range (``policy.record``'s
    ``action_low``/``action_high``), so ``0`` is the batch's own actions and ``2`` the far end of the range.

    A diagnostic beside FQE's estimate, not a part of it: FQE's target queries ``Q(s', pi(s'))``, and the further
    ``pi`` leaves the batch's actions the more of its estimate is extrapolation (Fujimoto et al. 2019,
    arXiv:1812.02900, sec. 3). A sampling policy (BCQ's) draws its actions from torch's generator seeded with
    ``seed``, restored afterwards (the caller's random stream is left as it was); at 10^6 transitions those draws
    take minutes, hence ``progress`` (a tqdm bar over the states).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_bail.modules import action_spec_from_bounds, make_deterministic_actor
        >>> policy = make_deterministic_actor(3, action_spec_from_bounds([-2.0], [2.0]), (8,))
        >>> policy.record = {"action_low": [-2.0], "action_high": [2.0]}
        >>> data = TensorDict({"observation": torch.randn(10, 3)}, [10])
        >>> with torch.no_grad():
        ...     data["action"] = policy(data.clone())["action"] + 1.0  # one unit off: half a half-range
        >>> round(action_gap(policy, data), 6)
        0.5
    """
    import torch

    from torchrl_bail.evaluation.policy import policy_actions

    low = torch.as_tensor(policy.record["action_low"], dtype=torch.float64)
    high = torch.as_tensor(policy.record["action_high"], dtype=torch.float64)
    half_range = (high - low) / 2
    observation, action = data["observation"], data["action"]
    device = next(iter(policy.parameters()), torch.empty(0)).device
    total, count = 0.0, 0
    with _own_random_stream(seed, device), _bar(observation.shape[0], "action gap", "state", progress) as bar:
        for start in range(0, observation.shape[0], chunk):
            acted = policy_actions(policy, observation[start:start + chunk]).to("cpu", torch.float64)
            gap = (acted - action[start:start + chunk].to("cpu", torch.float64)) / half_range
            total += float(gap.square().sum())
            count += gap.numel()
            bar.update(acted.shape[0])
    return math.sqrt(total / count)


def _load_policy(path: Path, device):
    """:func:`~torchrl_bail.evaluation.policy.load_policy` of the policy file ``path``; a damaged file raises
    :class:`~torchrl_bail.evaluation.policy.PolicyFileError` calling it corrupt or truncated (the policy-file reader
    checks
    the zip archive ``torch.save`` writes, :func:`~torchrl_bail.evaluation.policy.read_policy_file`)."""
    from torchrl_bail.evaluation.policy import load_policy

    return load_policy(path, device=device)


def _fit_policy(policy, out: Path, *, batch, settings: FQESettings, seed: int, device, progress: bool,
                checkpoint_every_s: float, desc: str, fits: int = DEFAULT_FITS) -> dict[str, Any]:
    """Fits FQE ``fits`` times for ``policy`` (from :func:`~torchrl_bail.evaluation.policy.load_policy`) on ``batch``
    (:func:`fit_fqe_fits`) and writes its record to ``out`` atomically, checkpointing beside it
    (``<out stem>_checkpoint.pt``, and ``<out stem>_fit<i>_checkpoint.pt`` for the later fits; removed once ``out``
    is written); returns the record."""
    import torch

    from torchrl_bail.core.io import write_json_atomic
    from torchrl_bail.data.batch import platform_record

    record = policy.record
    policy_file = Path(record["path"])
    identity = {"policy_sha1": _sha1(policy_file), "batch": str(batch.path), "num_transitions": batch.num_transitions}
    checkpoint = out.with_name(out.stem + "_checkpoint.pt")
    result = fit_fqe_fits(policy, batch.data, settings, fits=fits, seed=seed, device=device, progress=progress,
                          checkpoint_path=checkpoint, checkpoint_every_s=checkpoint_every_s, identity=identity,
                          desc=desc)
    ope = {
        "format": OPE_FORMAT,
        "estimator": "fqe",
        "estimate": result["estimate"],
        "spread": result["spread"],
        "num_fits": fits,
        "converged_fits": result["converged_fits"],
        "gamma": settings.gamma,
        "updates": max(fit["updates"] for fit in result["fits"]),
        "seed": int(seed),
        "settings": _settings_record(settings),
        "algo": record["algo"],
        "policy": policy_file.name,
        "policy_sha1": identity["policy_sha1"],
        "batch": str(batch.path),
        "num_transitions": result["num_transitions"],
        "num_episode_starts": result["num_episode_starts"],
        "device": torch.device(device).type,
        "threads": torch.get_num_threads(),
        "wall_time_s": result["wall_time_s"],
        "resumed_at": result["resumed_at"],
        "fits": result["fits"],
        "action_gap": action_gap(policy, batch.data, seed=seed, progress=progress),
        "platform": platform_record(),
    }
    write_json_atomic(out, ope)
    for index in range(fits):
        _fit_checkpoint(checkpoint, index).unlink(missing_ok=True)
    return ope


def _read_record(path: Path) -> dict | None:
    """The JSON object at ``path``, or ``None`` when there is none (or it does not parse: it is written again)."""
    import json

    try:
        record = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError):
        return None
    return record if isinstance(record, dict) else None


def _kept(out: Path, policy_file: Path) -> dict | None:
    """The finished record at ``out`` when it scored the policy file as it is now, else ``None`` (with a line on
    stderr when the run was trained again since)."""
    if not out.exists():
        return None
    import json

    record = json.loads(out.read_text())
    if record.get("policy_sha1") not in (None, _sha1(policy_file)):
        print(f"torchrl_bail.ope: {out} scored another {policy_file.name} (the run was trained again since); fitting "
              f"again", file=sys.stderr)
        return None
    return record


def listed_snapshots(run_dir: str | Path) -> list[dict] | None:
    """The policy snapshots the run's ``summary.json`` lists (``eval.snapshots``), or ``None`` (none, or no summary)."""
    run_dir = Path(run_dir)
    summary = _read_record(run_dir / "summary.json")
    snapshots = None if summary is None else summary.get("snapshots")
    if not snapshots:
        return None
    if not isinstance(snapshots, list) or not all(isinstance(s, dict) and {"path", "iteration", "eval_return"} <= set(s)
                                                  for s in snapshots):
        raise OPEError(f"{run_dir / 'summary.json'}: its snapshots are not a list of {{path, iteration, eval_return}}")
    return snapshots


def _same_weights(a, b) -> bool:
    import torch

    sa, sb = a.state_dict(), b.state_dict()
    return (a.record["algo"] == b.record["algo"] and sa.keys() == sb.keys()
            and all(sa[k].shape == sb[k].shape and torch.equal(sa[k], sb[k].to(sa[k].device)) for k in sa))


def _record_selection(run_dir: Path, selected: dict) -> None:
    """Writes ``fqe_selected`` into the run's ``summary.json`` (atomically; nothing when it already holds it)."""
    from torchrl_bail.core.io import write_json_atomic

    path = run_dir / "summary.json"
    summary = _read_record(path)
    if summary is None:
        raise OPEError(f"{path}: not readable; the selection is in {output_path(run_dir)}")
    if summary.get("fqe_selected") != selected:
        write_json_atomic(path, {**summary, "fqe_selected": selected})


def select_snapshot(run_dir: str | Path, ope: dict, final_policy, batch, *, settings: FQESettings, seed: int = 0,
                    device="cpu", force: bool = False, progress: bool = False, checkpoint_every_s: float = 300.0,
                    snapshots: list[dict] | None = None, fits: int = DEFAULT_FITS, rule: str = DEFAULT_RULE,
                    k: float = DEFAULT_K, lam: float = DEFAULT_LAMBDA) -> dict[str, Any]:
    """Chooses, among a run's policy snapshots and its final policy, the one the selection ``rule`` scores best
    (:func:`rule_scores`; the default, ``"mean"``: the highest FQE estimate); returns ``ope`` (the final policy's
    record) with the ranking, after writing it to ``ope.json`` and ``fqe_selected`` to ``summary.json`` (each
    atomically).

    Each snapshot the run's ``summary.json`` lists (``eval.snapshots``, :func:`listed_snapshots`) is fitted on
    ``batch`` (the run's, :func:`run_batch`) with the command's settings and seed (the same Q network initialisation
    and mini-batches for every candidate) into ``snapshots/ope_<snapshot>.json``, checkpointed beside it, and kept
    for a later command when it scored that file with the same settings, seed, number of fits, device and batch
    (unless ``force``). The snapshot with the final policy's weights (the last one) takes the final policy's own
    fit from ``ope`` when that was made alike; the final policy is a candidate of its own only when no snapshot has
    its weights. Other arguments as in :func:`fit_fqe`.

    ``fqe_selected`` = ``{path, iteration, fqe_estimate, online_return}``: the candidate of the highest score (the
    earliest on a tie), its estimate (the mean over its fits) and the evaluation return the run recorded for that
    policy, what deploying it without a simulator gives. Each candidate of the ranking holds its ``fqe_estimate``,
    ``fqe_spread``, ``action_gap``, ``score`` and ``rank``; ``selection`` the rule and its ``k`` and ``lambda``.
    """
    import functools

    import torch

    from torchrl_bail.core.io import write_json_atomic

    run_dir = Path(run_dir)
    snapshots = listed_snapshots(run_dir) if snapshots is None else snapshots
    fit = functools.partial(_fit_policy, batch=batch, settings=settings, seed=seed, device=device, progress=progress,
                            checkpoint_every_s=checkpoint_every_s, fits=fits)
    wanted = {"settings": _settings_record(settings), "seed": int(seed), "num_fits": int(fits),
              "device": torch.device(device).type, "batch": str(batch.path)}

    def alike(record: dict) -> bool:  # a record fitted as this command fits (one fit: before num_fits was recorded)
        return all({**record, "num_fits": record.get("num_fits", 1)}.get(key) == value for key, value in wanted.items())

    final_fit_usable = alike(ope)
    candidates, final_seen = [], False
    entries = list(snapshots or [])
    for entry in entries:
        path = run_dir / str(entry["path"])
        if not path.is_file():
            raise OPEError(f"{run_dir}: its summary.json lists the policy snapshot {entry['path']}, which is missing")
        policy = _load_policy(path, device)
        is_final = _same_weights(policy, final_policy)
        final_seen = final_seen or is_final
        if is_final and final_fit_usable:
            record, fitted_in = ope, output_path(run_dir).name
        else:
            out = path.with_name(f"ope_{path.stem}.json")
            record = None if force else _read_record(out)
            if record is None or not alike(record) or record.get("policy_sha1") != _sha1(path):
                record = fit(policy, out, desc=f"{run_dir.name} {entry['path']}")
            fitted_in = out.relative_to(run_dir).as_posix()
        candidates.append({"path": str(entry["path"]), "iteration": int(entry["iteration"]),
                           "eval_return": entry["eval_return"], **_candidate_figures(record),
                           "fitted_in": fitted_in})
    if not final_seen:  # the final policy is a candidate of its own
        info = final_policy.record.get("info", {})
        if final_fit_usable:
            record, fitted_in = ope, output_path(run_dir).name
        else:
            out = run_dir / "snapshots" / "ope_final.json"
            record, fitted_in = fit(final_policy, out, desc=f"{run_dir.name} policy.pt"), \
                out.relative_to(run_dir).as_posix()
        candidates.append({"path": Path(final_policy.record["path"]).name, "iteration": info.get("iteration"),
                           "eval_return": info.get("mean_return"), **_candidate_figures(record),
                           "fitted_in": fitted_in})
    scores = rule_scores([c["fqe_estimate"] for c in candidates], rule=rule,
                         spreads=[c["fqe_spread"] for c in candidates], gaps=[c["action_gap"] for c in candidates],
                         k=k, lam=lam)
    order = sorted(range(len(candidates)), key=lambda i: (-scores[i], i))
    for rank, i in enumerate(order, 1):
        candidates[i]["score"], candidates[i]["rank"] = scores[i], rank
    chosen = candidates[order[0]]
    selected = {"path": chosen["path"], "iteration": chosen["iteration"], "fqe_estimate": chosen["fqe_estimate"],
                "online_return": chosen["eval_return"]}
    returns = [c["eval_return"] for c in candidates if c["eval_return"] is not None]
    ope = {**ope, "snapshots": candidates, "fqe_selected": selected,
           "selection": {**wanted, **_rule_record(rule, k, lam), "candidates": len(candidates),
                         "best_online_return": max(returns) if returns else None}}
    write_json_atomic(output_path(run_dir), ope)
    _record_selection(run_dir, selected)  # after ope.json: a command stopped between the two writes it again
    return ope


def score_run(run_dir: str | Path, settings: FQESettings | None = None, *, seed: int = 0, device="cpu",
              best: bool = False, data_dir: str | Path | None = None, force: bool = False, progress: bool = False,
              checkpoint_every_s: float = 300.0, fits: int = DEFAULT_FITS, rule: str = DEFAULT_RULE,
              k: float = DEFAULT_K, lam: float = DEFAULT_LAMBDA) -> tuple[dict[str, Any], bool]:
    """Scores one run directory: ``(record, fitted)``, the record written to :func:`output_path` (or the one
    already there, ``fitted = False``, unless ``force`` or the policy file changed since). Arguments as in
    :func:`fit_fqe` and the command line.

    A run with policy snapshots (``eval.snapshots``; not with ``best``) is then ranked by :func:`select_snapshot`,
    which adds the ranking and ``fqe_selected`` to the record and ``fqe_selected`` to ``summary.json``; a kept record
    without them, or ranked by another rule, gets them (the fits kept).
    """
    import torch
    from omegaconf import OmegaConf

    settings = (settings or FQESettings()).check()
    run_dir = Path(run_dir)
    out = output_path(run_dir, best=best)
    snapshots = None if best else listed_snapshots(run_dir)
    kept = None if force else _kept(out, run_dir / ("policy_best.pt" if best else "policy.pt"))
    ranked = "fqe_selected" in (kept or {}) and all(
        (kept.get("selection") or {}).get(key) == value for key, value in _rule_record(rule, k, lam).items())
    if kept is not None and (not snapshots or ranked) and "action_gap" in kept:
        if snapshots:
            _record_selection(run_dir, kept["fqe_selected"])  # a command stopped between ope.json and summary.json
        return kept, False
    device = torch.device(device)
    policy = _load_policy(run_dir / ("policy_best.pt" if best else "policy.pt"), device)
    cfg = OmegaConf.load(run_dir / "config.yaml")
    batch = run_batch(run_dir, cfg, data_dir)
    record = policy.record
    if (batch.obs_dim, batch.act_dim) != (int(record["obs_dim"]), int(record["act_dim"])):
        raise OPEError(f"{run_dir}: its batch {batch.path} has observation/action sizes ({batch.obs_dim}, "
                       f"{batch.act_dim}) where its policy has ({record['obs_dim']}, {record['act_dim']})")
    if kept is None:
        kept = _fit_policy(policy, out, batch=batch, settings=settings, seed=seed, device=device, progress=progress,
                           checkpoint_every_s=checkpoint_every_s, desc=run_dir.name, fits=fits)
    elif "action_gap" not in kept:  # a record written before ope recorded it: no new fit, the gap added
        from torchrl_bail.core.io import write_json_atomic

        kept = {**kept, "action_gap": action_gap(policy, batch.data, seed=int(kept.get("seed", seed)),
                                                 progress=progress)}
        write_json_atomic(out, kept)
    if snapshots:
        kept = select_snapshot(run_dir, kept, policy, batch, settings=settings, seed=seed, device=device, force=force,
                               progress=progress, checkpoint_every_s=checkpoint_every_s, snapshots=snapshots,
                               fits=fits, rule=rule, k=k, lam=lam)
    return kept, True


def _candidate_figures(record: dict) -> dict[str, Any]:
    """What the selection rules read from a policy's record: its estimate, spread and action gap."""
    spread = record.get("spread")
    return {"fqe_estimate": float(record["estimate"]), "fqe_spread": None if spread is None else float(spread),
            "action_gap": None if record.get("action_gap") is None else float(record["action_gap"])}


def _rule_record(rule: str, k: float, lam: float) -> dict[str, Any]:
    """The rule as ``ope.json``'s ``selection`` records it (only the knob the rule uses)."""
    return {"rule": rule, "rule_k": float(k) if rule == "lower_bound" else None,
            "rule_lambda": float(lam) if rule == "gap_penalised" else None}


def rule_scores(means: Sequence[float], *, rule: str = DEFAULT_RULE, spreads: Sequence[float | None] | None = None,
                gaps: Sequence[float | None] | None = None, k: float = DEFAULT_K,
                lam: float = DEFAULT_LAMBDA) -> list[float]:
    """Each candidate's score under a selection rule; the rule deploys the highest (:func:`select_by_rule`).

    Rules (Paine et al. 2020 select by the estimate; the other two are this package's answers to FQE's
    failures on the OPE study, docs/guides/ope.md):

    * ``"mean"``: the estimate, the mean over a policy's fits;
    * ``"lower_bound"``: ``mean - k * spread``, the spread the standard deviation over the policy's fits
      (:func:`fit_fqe_fits`): pessimism, a policy whose fits disagree is trusted less. Needs two fits or more;
    * ``"gap_penalised"``: ``mean - lam * gap * scale``, the gap :func:`action_gap` (0: the batch's own actions,
      per half action range) and ``scale`` the median ``|mean|`` of the candidates, so ``lam`` is unit-free: the
      share of a typical estimate a policy forfeits per unit of action gap (``lam = 1``: a policy acting half a
      half-range from the batch on RMS loses half a typical estimate). The further a policy acts from the batch, the
      more of its estimate is extrapolation.

    Raises:
        ValueError: an unknown rule, a negative ``k`` or ``lam``, lengths that differ, or a spread or gap missing
            where the rule needs it.

    Examples:
        >>> rule_scores([10.0, 8.0], rule="lower_bound", spreads=[4.0, 1.0], k=1.0)
        [6.0, 7.0]
        >>> rule_scores([10.0, 8.0], rule="gap_penalised", gaps=[0.5, 0.1], lam=1.0)
        [5.5, 7.1]
    """
    import statistics

    if rule not in RULES:
        raise ValueError(f"rule {rule!r}: expected one of {', '.join(RULES)}")
    if not (math.isfinite(k) and k >= 0 and math.isfinite(lam) and lam >= 0):
        raise ValueError(f"k = {k!r}, lambda = {lam!r}: expected finite numbers >= 0")
    means = [float(m) for m in means]
    if rule == "mean":
        return means
    other, name = (spreads, "spread") if rule == "lower_bound" else (gaps, "action gap")
    if other is None or len(other) != len(means):
        raise ValueError(f"rule {rule!r} needs one {name} per candidate")
    if any(value is None or not math.isfinite(value) for value in other):
        needs = " (a spread needs 2 fits or more: --fits)" if rule == "lower_bound" else ""
        raise ValueError(f"rule {rule!r} needs every candidate's {name}{needs}")
    if rule == "lower_bound":
        return [m - k * float(sd) for m, sd in zip(means, other, strict=True)]
    scale = statistics.median(abs(m) for m in means)
    return [m - lam * float(gap) * scale for m, gap in zip(means, other, strict=True)]


def select_by_rule(means: Sequence[float], **kwargs) -> int:
    """The index of the candidate a rule deploys: the highest :func:`rule_scores` (the earliest on a tie).

    >>> select_by_rule([10.0, 8.0]), select_by_rule([10.0, 8.0], rule="lower_bound", spreads=[4.0, 1.0])
    (0, 1)
    """
    scores = rule_scores(means, **kwargs)
    return max(range(len(scores)), key=lambda i: (scores[i], -i))


def compare_rules(means: Sequence[float], truths: dict[str, Sequence[float]], *,
                  spreads: Sequence[float | None] | None = None, gaps: Sequence[float | None] | None = None,
                  k: float = DEFAULT_K, lam: float = DEFAULT_LAMBDA, rules: Sequence[str] = RULES,
                  interval: bool = True) -> dict[str, dict[str, Any]]:
    """Each selection rule's ranking of policies whose true values are known.

    Args:
        means: each policy's estimate (the mean over its fits), as :func:`rule_scores`.
        truths: named true values, one per policy each (e.g. ``{"discounted": ..., "undiscounted": ...}``).
        spreads: each policy's spread over its fits (``lower_bound``).
        gaps: each policy's action gap (``gap_penalised``).
        k: the lower bound's multiple of the spread.
        lam: the gap penalty's weight.
        rules: the rules compared.
        interval: add :func:`spearman_interval`.

    Returns:
        ``{rule: {"available": True, "scores", "selected", <truth name>: {"spearman", "spearman_ci", "best",
        "regret"}, ...}}`` (:func:`ranking_quality`: the regret is the best true value minus that of the policy the
        rule deploys, ``0`` when it deploys the best); a rule that cannot score these policies (``lower_bound``
        without spreads) is ``{"available": False, "reason"}``.

    Examples:
        >>> out = compare_rules([10.0, 8.0, 5.0], {"true": [1.0, 3.0, 2.0]}, spreads=[4.0, 1.0, 1.0],
        ...                     gaps=[0.1, 0.1, 0.1], interval=False)
        >>> out["mean"]["selected"], out["mean"]["true"]["regret"], out["lower_bound"]["true"]["regret"]
        (0, 2.0, 0.0)
    """
    report = {}
    for rule in rules:
        try:
            scores = rule_scores(means, rule=rule, spreads=spreads, gaps=gaps, k=k, lam=lam)
        except ValueError as err:
            report[rule] = {"available": False, "reason": str(err)}
            continue
        entry = {"available": True, "scores": scores, "selected": select_by_rule(scores)}
        for name, values in truths.items():
            quality = ranking_quality(scores, values)
            entry[name] = {"spearman": quality["spearman"], "best": quality["best"], "regret": quality["regret"]}
            if interval:
                entry[name]["spearman_ci"] = list(spearman_interval(scores, values))
        report[rule] = entry
    return report


def ranking_quality(estimates: Sequence[float], returns: Sequence[float]) -> dict[str, Any]:
    """How well off-policy estimates rank policies whose true returns are known (Paine et al. 2020, sec. 4: rank
    correlation and the regret of the policy an estimator selects).

    Args:
        estimates: one estimate per policy (e.g. each run's ``ope.json`` ``estimate``).
        returns: the same policies' true returns, in the same order (e.g. each run's ``final_return``).

    Returns:
        ``spearman``: Spearman's rank correlation (``scipy.stats.spearmanr``, ties averaged; ``None`` when either
        side is constant); ``selected``: the index of the highest estimate (the earliest on a tie), the policy a user
        without a simulator would deploy; ``best``: the index of the highest true return; ``regret``: the best true
        return minus the selected policy's (``0`` when the estimates pick the best); ``n``: the number of policies.

    Raises:
        ValueError: fewer than 2 policies, lengths that differ, or a value that is not finite.

    Examples:
        >>> q = ranking_quality([3.0, 1.0, 2.0], [300.0, 100.0, 250.0])
        >>> q["spearman"], q["selected"], q["regret"]
        (1.0, 0, 0.0)
        >>> ranking_quality([1.0, 3.0, 2.0], [300.0, 100.0, 250.0])["regret"]
        200.0
    """
    import numpy as np

    estimates, returns = np.asarray(estimates, dtype=float), np.asarray(returns, dtype=float)
    if estimates.ndim != 1 or estimates.shape != returns.shape:
        raise ValueError(f"expected one estimate per return, got shapes {estimates.shape} and {returns.shape}")
    if len(estimates) < 2:
        raise ValueError(f"a ranking needs at least 2 policies, got {len(estimates)}")
    if not (np.isfinite(estimates).all() and np.isfinite(returns).all()):
        raise ValueError("every estimate and return must be finite")
    try:
        from scipy.stats import spearmanr
    except ImportError as err:  # scipy comes with the report extra
        raise ImportError("ranking_quality needs scipy: pip install 'torchrl_bail[report]'") from err
    constant = np.ptp(estimates) == 0 or np.ptp(returns) == 0
    selected, best = int(np.argmax(estimates)), int(np.argmax(returns))
    return {"n": int(len(estimates)), "spearman": None if constant else float(spearmanr(estimates, returns).statistic),
            "selected": selected, "best": best, "regret": float(returns[best] - returns[selected])}


def spearman_interval(estimates: Sequence[float], returns: Sequence[float], *, reps: int = 2000,
                      seed: int = 0) -> tuple[float | None, float | None]:
    """A 95 % percentile-bootstrap interval of Spearman's rank correlation between ``estimates`` and ``returns``:
    the policies drawn with replacement ``reps`` times (numpy's ``default_rng(seed)``), the draws where either side
    is constant left out (:func:`ranking_quality` gives them no correlation). ``(None, None)`` when every draw is.
    The OPE study's method (``results/run_study.py``, 2000 replications, seed 0), here for any pair of lists.

    Examples:
        >>> low, high = spearman_interval([1.0, 2.0, 3.0, 4.0, 5.0], [10.0, 30.0, 20.0, 40.0, 50.0])
        >>> -1.0 <= low <= 0.9 <= high <= 1.0
        True
    """
    import numpy as np

    rng = np.random.default_rng(seed)
    e, r, values = np.asarray(estimates, dtype=float), np.asarray(returns, dtype=float), []
    for _ in range(reps):
        idx = rng.integers(0, len(e), len(e))
        rho = ranking_quality(e[idx], r[idx])["spearman"]
        if rho is not None:
            values.append(rho)
    if not values:
        return None, None
    low, high = np.percentile(values, [2.5, 97.5])
    return float(low), float(high)


# -- the command line -------------------------------------------------------------------------------------------
def _hidden(text: str) -> tuple[int, ...]:
    try:
        sizes = tuple(int(part) for part in text.replace(" ", "").split(",") if part)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected layer sizes like 256,256") from None
    if not sizes or any(size < 1 for size in sizes):
        raise argparse.ArgumentTypeError(f"{text!r}: expected one or more positive layer sizes like 256,256")
    return sizes


class _Parser(argparse.ArgumentParser):
    """The command's parser: an error is one line, ``torchrl_bail.ope: <what is wrong>`` (exit status 2), not
    argparse's usage block (``--help`` shows it)."""

    def error(self, message: str):
        self.exit(2, f"torchrl_bail.ope: {message} (--help lists the options)\n")


def _parser() -> argparse.ArgumentParser:
    defaults = FQESettings()
    parser = _Parser(prog="python -m torchrl_bail.ope", description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dirs", nargs="+", type=Path, metavar="RUN_DIR", help="finished run directories")
    parser.add_argument("--updates", type=int, default=defaults.updates,
                        help=f"the most gradient updates of a fit; the stopping rule ends it earlier (default "
                             f"{defaults.updates})")
    parser.add_argument("--fits", type=int, default=DEFAULT_FITS,
                        help=f"independent fits per policy (seeds SEED, SEED+1, ...): the estimate is their mean, the "
                             f"spread their standard deviation (default {DEFAULT_FITS})")
    parser.add_argument("--stop-window", type=int, default=defaults.stop_window,
                        help=f"stopping rule: curve points averaged at the end and at half the fit; 0: no rule, "
                             f"every fit runs --updates (default {defaults.stop_window})")
    parser.add_argument("--stop-tol", type=float, default=defaults.stop_tol,
                        help=f"stopping rule: the fit stops once the two averages differ by less than this share of "
                             f"the estimate (default {defaults.stop_tol})")
    parser.add_argument("--rule", choices=RULES, default=DEFAULT_RULE,
                        help=f"how a run's snapshots are chosen: the highest mean estimate, mean - k x spread, or "
                             f"mean - lambda x action gap x the candidates' median estimate (default {DEFAULT_RULE})")
    parser.add_argument("--rule-k", type=float, default=DEFAULT_K,
                        help=f"lower_bound's k (default {DEFAULT_K})")
    parser.add_argument("--rule-lambda", type=float, default=DEFAULT_LAMBDA,
                        help=f"gap_penalised's lambda (default {DEFAULT_LAMBDA})")
    parser.add_argument("--seed", type=int, default=0, help="seed of the Q network, the policy's draws and the "
                        "mini-batches (default 0)")
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads (default 1)")
    parser.add_argument("--device", choices=["cpu", "cuda", "auto"], default="cpu",
                        help="where the fit runs (default cpu; auto: cuda when available)")
    parser.add_argument("--best", action="store_true", help="score policy_best.pt into ope_best.json")
    parser.add_argument("--force", action="store_true",
                        help="refit a run whose ope.json exists (and its snapshots' fits)")
    parser.add_argument("--data-dir", type=Path, help="the data cache holding the runs' batches (default: each "
                        "run's data_dir, else $TORCHRL_BAIL_DATA_DIR or ~/.cache/torchrl_bail)")
    parser.add_argument("--batch-size", type=int, default=defaults.batch_size,
                        help=f"transitions per update (default {defaults.batch_size})")
    parser.add_argument("--lr", type=float, default=defaults.lr, help=f"Adam's learning rate (default {defaults.lr})")
    parser.add_argument("--hidden", type=_hidden, default=defaults.hidden,
                        help="the Q network's hidden sizes (default " + ",".join(map(str, defaults.hidden)) + ")")
    parser.add_argument("--target-update-period", type=int, default=defaults.target_update_period,
                        help=f"updates between target copies (default {defaults.target_update_period})")
    parser.add_argument("--gamma", type=float, default=defaults.gamma,
                        help=f"discount of the estimate (default {defaults.gamma})")
    parser.add_argument("--log-every", type=int, default=defaults.log_every,
                        help=f"updates between points of the fitting curve (default {defaults.log_every})")
    parser.add_argument("--checkpoint-every-s", type=float, default=300.0,
                        help="seconds between checkpoints of a fit (default 300)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    return parser


def _check_run_dir(path: Path, best: bool) -> str | None:
    """Why ``path`` cannot be scored (a missing directory, config or policy), or ``None``."""
    if not path.is_dir():
        return f"{path}: no such run directory"
    if not (path / "config.yaml").is_file():
        return f"{path}: not a run directory (no config.yaml)"
    policy = path / ("policy_best.pt" if best else "policy.pt")
    if not policy.is_file():
        return f"{path}: no {policy.name} (a finished run directory holds it)"
    return None


def _describe_fits(ope: dict) -> str:
    """``± 1.234 (std over 4 fits, 3 converged, 120000-500000 updates)``, or the one fit's updates."""
    fits = ope.get("fits")
    if not fits:  # a record of one fit, written before fits were recorded
        return f"{ope['updates']} updates"
    updates = sorted(fit["updates"] for fit in fits)
    span = str(updates[0]) if updates[0] == updates[-1] else f"{updates[0]}-{updates[-1]}"
    converged = f"{ope['converged_fits']} of {len(fits)} settled before the cap"
    if len(fits) == 1:
        return f"{span} updates, {converged}"
    return f"std {ope['spread']:.3f} over {len(fits)} fits, {span} updates, {converged}"


def _print_result(run_dir: Path, out: Path, ope: dict, fitted: bool, settings: FQESettings, seed: int,
                  fits: int) -> None:
    if fitted:
        print(f"{run_dir}: FQE estimate {ope['estimate']:.3f} (discounted, gamma {ope['gamma']}; "
              f"{_describe_fits(ope)}; {ope['num_episode_starts']} episode starts) -> {out}")
    else:
        same = ope.get("settings") == _settings_record(settings) and ope.get("seed") == seed and \
            ope.get("num_fits", 1) == fits
        note = "" if same else " (fitted with other settings, seed or number of fits: --force refits)"
        print(f"{run_dir}: kept {out}, FQE estimate {ope['estimate']:.3f}{note}")
    selected = ope.get("fqe_selected")
    if selected is not None:
        rule = (ope.get("selection") or {}).get("rule", "mean")
        print(f"{run_dir}: FQE selects {selected['path']} (iteration {selected['iteration']}, estimate "
              f"{selected['fqe_estimate']:.3f}, the highest {'estimate' if rule == 'mean' else rule + ' score'} of "
              f"{len(ope['snapshots'])}); its evaluation return {selected['online_return']} -> {out}, "
              f"{run_dir / 'summary.json'}")


def _checked_settings(parser: _Parser, args: argparse.Namespace) -> FQESettings:
    """The fit's settings from the command line; a number out of range stops the command in one line."""
    settings = FQESettings(updates=args.updates, batch_size=args.batch_size, lr=args.lr, hidden=tuple(args.hidden),
                           target_update_period=args.target_update_period, gamma=args.gamma,
                           log_every=args.log_every, stop_window=args.stop_window, stop_tol=args.stop_tol)
    try:
        settings.check()
    except ValueError as err:  # "updates = 0: expected ..." -> "--updates 0: expected ..."
        name, _, rest = str(err).partition(" = ")
        parser.error(f"--{name.replace('_', '-')} {rest}")
    if args.threads < 1:
        parser.error(f"--threads {args.threads}: expected a positive number of threads")
    if args.fits < 1:
        parser.error(f"--fits {args.fits}: expected an integer >= 1")
    if args.rule == "lower_bound" and args.fits < 2:
        parser.error(f"--rule lower_bound needs a spread, so --fits 2 or more (got --fits {args.fits})")
    for name, value in (("--rule-k", args.rule_k), ("--rule-lambda", args.rule_lambda)):
        if not (math.isfinite(value) and value >= 0):
            parser.error(f"{name} {value}: expected a finite number >= 0")
    if not args.checkpoint_every_s > 0:
        parser.error(f"--checkpoint-every-s {args.checkpoint_every_s}: expected a positive number of seconds")
    return settings


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    settings = _checked_settings(parser, args)
    if args.data_dir is not None and not args.data_dir.is_dir():
        print(f"torchrl_bail.ope: --data-dir {args.data_dir}: no such directory", file=sys.stderr)
        return 2
    run_dirs = list(dict.fromkeys(args.run_dirs))
    # the runs that cannot be scored: each is reported, every other one scored, and the status is then 2
    failed = {path: problem for path in run_dirs if (problem := _check_run_dir(path, args.best)) is not None}
    for problem in failed.values():
        print(f"torchrl_bail.ope: {problem}", file=sys.stderr)
    if len(failed) == len(run_dirs):
        return 2  # nothing to score: stopped before torch loads

    import torch

    from torchrl_bail.cli import describe_interrupt
    from torchrl_bail.core.errors import USER_ERRORS
    from torchrl_bail.core.interrupts import Interrupted, handled
    from torchrl_bail.core.io import FileSystemError
    from torchrl_bail.evaluation.policy import PolicyFileError

    device = args.device
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    if device == "cuda" and not torch.cuda.is_available():
        print("torchrl_bail.ope: --device cuda: no CUDA device is available (use --device cpu)", file=sys.stderr)
        return 2
    torch.set_num_threads(args.threads)
    with handled():
        for run_dir in run_dirs:
            if run_dir in failed:
                continue
            try:
                ope, fitted = score_run(run_dir, settings, seed=args.seed, device=device, best=args.best,
                                        data_dir=args.data_dir, force=args.force, progress=not args.no_progress,
                                        checkpoint_every_s=args.checkpoint_every_s, fits=args.fits,
                                        rule=args.rule, k=args.rule_k, lam=args.rule_lambda)
            except Interrupted as err:
                command = " ".join(["python -m torchrl_bail.ope", *(argv if argv is not None else sys.argv[1:])])
                print(f"torchrl_bail.ope: {describe_interrupt(err, command)}", file=sys.stderr)
                return err.exit_status
            except (OPEError, PolicyFileError, FileSystemError, *USER_ERRORS) as err:
                print(f"torchrl_bail.ope: {err}", file=sys.stderr)
                failed[run_dir] = str(err)
                continue
            _print_result(run_dir, output_path(run_dir, best=args.best), ope, fitted, settings, args.seed, args.fits)
    if failed and len(run_dirs) > 1:  # after the fits' output: which runs the lines above were about
        names = ", ".join(str(path) for path in run_dirs if path in failed)
        print(f"torchrl_bail.ope: {len(failed)} of {len(run_dirs)} runs could not be scored (see above): {names}",
              file=sys.stderr)
    return 2 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

"""Checkpoints of a behaviour run: a killed collection continues from its last checkpoint and makes the *same* batch.

A checkpoint lives in ``<data_dir>/.partial/<key>/`` (:func:`~torchrl_bail.data.locks.partial_directory`; ``key``
is the batch's directory name, or the SAC run's, hash included) and is written only by the holder of that batch's
(or run's) lock. It is removed once the batch (or the run) is saved. Layout:

* ``segments/<store>_<start>_<end>.pt`` -- the transitions stored since the previous checkpoint, one file per
  store (the batch; in oracle mode also the agent's replay store), each written once;
* ``state.pt`` -- everything else, written *last*: the loop (env steps, episodes, returns so far), the sinks'
  counters, the list of segments, the RNG states (torch, NumPy and ``random`` global generators, and the
  collection env's ``np_random``), the recipe's own state (agent networks, target networks, optimizers,
  alpha, evaluations so far, ...), and the collection's wall time so far (:attr:`CollectionCheckpoint.wall_time_s`).

Every file is written to a temporary name and renamed into place (:func:`~torchrl_bail.core.io.atomic_path`), so a
kill at any moment leaves the previous complete checkpoint (segments named in ``state.pt`` exist before it is
renamed): nothing half-written ever loads as whole. Each rename is fenced
(:func:`~torchrl_bail.data.locks.check_fence`): a job whose lock was taken over meanwhile (suspended, or cut off
from the file server, past the staleness timeout) raises :class:`~torchrl_bail.data.locks.LockLost` just before
it, and its file is never published, so it cannot overwrite the checkpoint of the job that took over.

When: only at an episode end (after the agent's gradient steps and any evaluation), when
``batch.checkpoint_every_s`` seconds of work passed since the last one (default 120) or
``batch.checkpoint_every_steps`` env steps (``null`` by default; tests use it to force checkpoints), or when Ctrl-C
or SIGTERM asked the entry point to stop (:mod:`torchrl_bail.core.interrupts`: the run goes on to the episode's end,
saves, and stops there; one that came during the batch's last episode waits for the batch itself, or for the
checkpoint before a recipe's final step such as SAC's final evaluation). MuJoCo envs
cannot be pickled reliably, but at an episode end none is needed: the next reset is a function of the env's
``np_random`` state, which is saved *before* that reset, and the resumed run performs the very same reset.
Saving consumes no random numbers, so when and how often checkpoints are taken never changes the data: the resumed
batch is byte-identical to an uninterrupted one (on the same machine, library versions and thread count).

Examples:
    >>> import tempfile, pathlib
    >>> ckpt = CollectionCheckpoint(pathlib.Path(tempfile.mkdtemp()) / "k", every_s=None, every_steps=100)
    >>> ckpt.due(99), ckpt.due(100), ckpt.load() is None
    (False, True, True)
"""

from __future__ import annotations

import logging
import random
import shutil
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase

from torchrl_bail.core import interrupts
from torchrl_bail.core.io import atomic_path
from torchrl_bail.data.locks import check_fence, partial_directory

__all__ = ["CollectionCheckpoint", "Resumable", "CheckpointableAgent", "global_rng_state", "set_global_rng_state"]

log = logging.getLogger("torchrl_bail")

STATE_FILE = "state.pt"
FORMAT = 2  # 2: segments are nested dicts (key order kept)


def global_rng_state() -> dict[str, Any]:
    """The torch, NumPy and ``random`` global generator states, as plain data (loadable with ``weights_only``)."""
    name, keys, pos, has_gauss, cached = np.random.get_state()
    return {"torch": torch.get_rng_state(), "numpy": [name, keys.tolist(), int(pos), int(has_gauss), float(cached)],
            "random": random.getstate()}


def set_global_rng_state(state: Mapping[str, Any]) -> None:
    torch.set_rng_state(state["torch"])
    name, keys, pos, has_gauss, cached = state["numpy"]
    np.random.set_state((name, np.asarray(keys, dtype=np.uint32), pos, has_gauss, cached))
    random.setstate(tuple(x if not isinstance(x, list) else tuple(x) for x in state["random"]))


class CheckpointableAgent:
    """``state_dict()`` / ``load_state_dict()`` for a behaviour agent: its loss module (networks, target networks,
    ``log_alpha``), the optimizers named in ``OPTIMIZERS`` and the update counter."""

    OPTIMIZERS: tuple[str, ...] = ()

    def state_dict(self) -> dict[str, Any]:
        return {"loss": self.loss.state_dict(), "updates": self.updates,
                **{name: getattr(self, name).state_dict() for name in self.OPTIMIZERS}}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.loss.load_state_dict(state["loss"])  # in place: optimizers and target updaters keep their tensors
        for name in self.OPTIMIZERS:
            getattr(self, name).load_state_dict(state[name])
        self.updates = int(state["updates"])


def _nested_copy(td) -> dict[str, Any]:
    """``td`` as nested dicts of plain tensors (copied out of the memmap), key order kept: a store refilled from
    it is laid out like the original, down to the batch's ``meta.json``."""
    return {k: _nested_copy(v) if isinstance(v, TensorDictBase) else torch.as_tensor(v).clone() for k, v in td.items()}


def _leading_dim(rows: Mapping[str, Any]) -> int:
    value = next(iter(rows.values()))
    return _leading_dim(value) if isinstance(value, Mapping) else value.shape[0]


class CollectionCheckpoint:
    """The checkpoint directory of one collection (see the module docstring).

    Args:
        directory: ``<data_dir>/.partial/<key>``.

    Keyword Args:
        every_s: seconds of work between checkpoints (``None``: not time-based).
        every_steps: env steps between checkpoints (``None``: not step-based). Both ``None``: never saves.

    Its clock (:attr:`wall_time_s`) starts when it is made, at the start of the collection's process, and a
    checkpoint carries it across a kill: a batch made in several parts records the time of all of them.
    """

    def __init__(self, directory: Path, *, every_s: float | None = 120.0, every_steps: int | None = None):
        self.directory = Path(directory)
        self.every_s = None if every_s is None else float(every_s)
        self.every_steps = None if every_steps is None else int(every_steps)
        self._last_time = time.monotonic()
        self._last_step = 0
        self._saved_rows: dict[str, int] = {}
        self._segments: dict[str, list[str]] = {}
        self.saves = 0
        self._part_start = time.perf_counter()
        #: the wall seconds of the earlier processes of this collection (restored from the checkpoint)
        self.earlier_wall_time_s = 0.0
        #: the env step from which :attr:`wall_time_s` counts: 0, unless the collection resumed from a checkpoint
        #: of an older version, which kept no time (its steps' time is then unknown)
        self.timed_from_step = 0

    @property
    def wall_time_s(self) -> float:
        """The collection's wall seconds so far: this process's since this object was made, plus the earlier
        processes' (from :attr:`timed_from_step` on) when it resumed from a checkpoint."""
        return self.earlier_wall_time_s + time.perf_counter() - self._part_start

    @classmethod
    def for_config(cls, cfg, data_dir: Path, key: str) -> CollectionCheckpoint:
        """The checkpoint ``<data_dir>/.partial/<key>`` every ``batch.checkpoint_every_s`` seconds and
        ``batch.checkpoint_every_steps`` env steps (``null``: never) of ``cfg``, a
        :class:`~torchrl_bail.configuration.config_builders.CollectionConfig`."""
        return cls(partial_directory(data_dir, key), every_s=cfg.batch.checkpoint_every_s,
                   every_steps=cfg.batch.checkpoint_every_steps)

    def due(self, t: int) -> bool:
        """Whether a checkpoint should be taken now, ``t`` env steps into the run."""
        if self.every_steps is not None and t - self._last_step >= self.every_steps:
            return True
        return self.every_s is not None and time.monotonic() - self._last_time >= self.every_s

    def load(self) -> dict[str, Any] | None:
        """The last complete checkpoint's state, or ``None`` (none, or one this version cannot read: logged)."""
        path = self.directory / STATE_FILE
        if not path.is_file():
            return None
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
            if state.get("format") != FORMAT:
                raise ValueError(f"checkpoint format {state.get('format')!r}, expected {FORMAT}")
            missing = [f for files in state["segments"].values() for f in files if not (self.directory / f).is_file()]
            if missing:
                raise FileNotFoundError(f"missing segments {missing[:3]}")
        except Exception as err:  # noqa: BLE001 - any unreadable checkpoint means: start over, say why
            log.warning("ignoring unreadable checkpoint %s (%s); collecting from the start", path, err)
            return None
        return state

    def save(self, state: dict[str, Any], stores: Mapping[str, Any]) -> None:
        """Writes the rows the ``stores`` (name -> :class:`~torchrl_bail.behaviour.buffers.EpisodeStore`) gained
        since the last checkpoint, then ``state`` (atomically, last). Raises
        :class:`~torchrl_bail.data.locks.LockLost` instead, before any file it would rename into place, if this
        job's lock was taken over meanwhile (the fence: the lock file no longer carries this job's token)."""
        check_fence()
        for name, store in stores.items():
            done, n = self._saved_rows.get(name, 0), len(store)
            if n > done:
                fname = f"segments/{name}_{done:012d}_{n:012d}.pt"
                with atomic_path(self.directory / fname) as tmp:
                    torch.save(_nested_copy(store.data()[done:n]), tmp)
                    check_fence()  # right before the rename: a fenced owner publishes nothing
                self._segments.setdefault(name, []).append(fname)
                self._saved_rows[name] = n
        state = {**state, "format": FORMAT, "segments": {k: list(v) for k, v in self._segments.items()},
                 "saved_rows": dict(self._saved_rows), "wall_time_s": self.wall_time_s,
                 "timed_from_step": self.timed_from_step}
        with atomic_path(self.directory / STATE_FILE) as tmp:
            torch.save(state, tmp)
            check_fence()
        self.saves += 1
        self._last_time = time.monotonic()
        self._last_step = int(state["loop"]["t"])

    def restore_stores(self, state: Mapping[str, Any], stores: Mapping[str, Any]) -> None:
        """Refills the (empty) ``stores`` from the segments ``state`` names, in order."""
        for name, store in stores.items():
            for fname in state["segments"].get(name, []):
                rows = torch.load(self.directory / fname, map_location="cpu", weights_only=True)
                store.extend(TensorDict(rows, batch_size=[_leading_dim(rows)]))
            if len(store) != state["saved_rows"].get(name, 0):
                raise RuntimeError(f"checkpoint {self.directory}: store {name} has {len(store)} rows after restore, "
                                   f"expected {state['saved_rows'].get(name, 0)}")
        self._segments = {k: list(v) for k, v in state["segments"].items()}
        self._saved_rows = dict(state["saved_rows"])
        self._last_step = int(state["loop"]["t"])
        if "wall_time_s" in state:
            self.earlier_wall_time_s, self.timed_from_step = float(state["wall_time_s"]), int(state["timed_from_step"])
        else:  # an older version's checkpoint: the time of the steps it holds is unknown
            self.earlier_wall_time_s, self.timed_from_step = 0.0, self._last_step
        self._last_time = time.monotonic()

    def remove(self) -> None:
        """Deletes the checkpoint (the batch or run it was for is saved)."""
        shutil.rmtree(self.directory, ignore_errors=True)


class Resumable:
    """Binds a :class:`CollectionCheckpoint` to one run: its loop, its buffers and the recipe's own state.

    Args:
        checkpoint: the checkpoint directory.
        runner: the :class:`~torchrl_bail.behaviour.loop.BehaviourRun`.
        buffers: the :class:`~torchrl_bail.behaviour.buffers.BehaviourBuffers`.

    Keyword Args:
        state: ``() -> dict`` the recipe's own state (agent, evaluations, timers), called at each save.
        load: ``(dict) -> None`` restores what ``state`` returned.
    """

    def __init__(self, checkpoint: CollectionCheckpoint, runner, buffers, *,
                 state: Callable[[], dict] | None = None, load: Callable[[dict], None] | None = None):
        self.checkpoint = checkpoint
        self.runner = runner
        self.buffers = buffers
        self._state = state
        self._load = load
        self.resumes: list[int] = []

    @property
    def resumed_from_step(self) -> int | None:
        """The env step this process resumed from (``None``: it started from scratch)."""
        return self.resumes[-1] if self.resumes else None

    def resume(self) -> int | None:
        """Loads the last checkpoint into the run, if there is one; returns its env step (else ``None``)."""
        state = self.checkpoint.load()
        if state is None:
            return None
        self.checkpoint.restore_stores(state, self.buffers.stores)
        self.buffers.load_state_dict(state["buffers"])
        self.runner.load_state_dict(state["loop"])
        if self._load is not None:
            self._load(state["recipe"])
        set_global_rng_state(state["rng"])
        self.resumes = [*state.get("resumes", []), int(state["loop"]["t"])]
        log.info("resuming the collection from its checkpoint at env step %d (%s)", state["loop"]["t"],
                 self.checkpoint.directory)
        return int(state["loop"]["t"])

    def maybe_save(self, t: int) -> None:
        """Saves a checkpoint if one is due or Ctrl-C/SIGTERM asked for one (:mod:`torchrl_bail.core.interrupts`), and
        then stops the run in the latter case (called by the loop at episode ends only)."""
        if interrupts.requested() is not None or self.checkpoint.due(t):
            self.save()
        self.stop_if_requested()

    def stop_if_requested(self) -> None:
        """Raises :class:`~torchrl_bail.core.interrupts.Interrupted` naming the checkpoint just saved, if a signal asked
        for a stop."""
        interrupts.stop_if_requested(f"the collection checkpoint at env step {self.runner.t} in "
                                     f"{self.checkpoint.directory}")

    def save(self) -> None:
        with interrupts.saving():  # segments and state.pt, whole, before a signal may stop the process
            state = {"loop": self.runner.state_dict(), "buffers": self.buffers.state_dict(),
                     "recipe": self._state() if self._state is not None else {}, "rng": global_rng_state(),
                     "resumes": list(self.resumes)}
            self.checkpoint.save(state, self.buffers.stores)

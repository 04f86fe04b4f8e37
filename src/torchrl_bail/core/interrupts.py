"""Ctrl-C and SIGTERM as "checkpoint now, then stop": a signal becomes a request that the loops honour at a safe point.

A leaf module (it imports nothing from the package), so that the training loop (:mod:`torchrl_bail.training.trainer`)
and the
collection loop (:mod:`torchrl_bail.behaviour.loop`) poll it without importing the entry points that install it.

* :func:`handled` installs the handlers; only the entry points (``train``, ``collect``, through
  :func:`torchrl_bail.cli.run_cli`) do. A signal whose handler is ``SIG_IGN`` (a job started in the background with
  ``nohup`` or ``&``) stays ignored. Without :func:`handled` nothing here changes how a signal behaves.
* Inside :func:`safe_points` (a loop that can checkpoint) the first signal only sets a request; the loop sees it
  (:func:`requested`) between two updates or at an episode end, writes its checkpoint and raises
  :class:`Interrupted` naming what it saved (:func:`stop`). Outside such a region, or at a second signal, the
  handler raises :class:`Interrupted` at once (nothing new saved; every file is written atomically, so nothing
  half-written is left either). Inside :func:`saving` (a checkpoint being written) every signal waits until the write
  is whole: a second signal never leaves a stacked run's seeds at different iterations.
* A region left normally while a request is pending raises :class:`Interrupted` on its way out.

:class:`Interrupted` is a :class:`BaseException` (like :class:`KeyboardInterrupt`): an ``except Exception`` on its
way up never swallows it. The entry point turns it into one line on stderr and exit status ``128 + signal``.

Examples:
    >>> with handled():
    ...     with safe_points():
    ...         signal.raise_signal(signal.SIGTERM)  # recorded, not raised: the loop checkpoints first
    ...         pending = requested()
    ...         try:
    ...             stop("checkpoint at step 7")
    ...         except Interrupted as err:
    ...             caught = err
    >>> pending == signal.SIGTERM, caught.exit_status, caught.saved
    (True, 143, 'checkpoint at step 7')

    (SIGTERM here: a shell starts a background job with SIGINT ignored, and :func:`handled` keeps it so.)
"""

from __future__ import annotations

import contextlib
import signal
from collections.abc import Iterator, Sequence

__all__ = ["SIGNALS", "Interrupted", "handled", "requested", "safe_points", "saving", "stop", "stop_if_requested"]

#: the signals an entry point turns into "checkpoint now, then stop"
SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Interrupted(BaseException):
    """The process was asked to stop by ``signum``; ``saved`` says what was written at that point (``None``:
    nothing new, the last checkpoint, if any, is what a rerun continues from)."""

    def __init__(self, signum: int, saved: str | None = None) -> None:
        self.signum, self.saved = int(signum), saved
        super().__init__(f"interrupted by {signal_name(signum)}" + (f"; saved {saved}" if saved else ""))

    @property
    def exit_status(self) -> int:
        """``128 + signum``, what a shell reports for a process the signal ended (130 for SIGINT, 143 for SIGTERM)."""
        return 128 + self.signum


class _State:
    installed = False
    pending: int | None = None  # the first signal not yet honoured
    depth = 0  # nested safe_points() regions
    saving = 0  # nested saving() sections


_STATE = _State()


def signal_name(signum: int) -> str:
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


def _handle(signum: int, frame) -> None:
    if _STATE.pending is None:
        _STATE.pending = signum
        if _STATE.depth > 0:
            return  # the loop checkpoints at its next safe point, then stops
    if _STATE.saving:
        return  # a checkpoint is being written: the stop comes once it is whole
    raise Interrupted(_STATE.pending)


@contextlib.contextmanager
def handled(signals: Sequence[int] = SIGNALS) -> Iterator[None]:
    """Turns ``signals`` into interrupt requests for the body (the previous handlers are put back afterwards).

    A signal that is ignored (``SIG_IGN``) when the body starts stays ignored."""
    previous = {}
    for sig in signals:
        if signal.getsignal(sig) is not signal.SIG_IGN:
            previous[sig] = signal.signal(sig, _handle)
    saved_state = (_STATE.installed, _STATE.pending, _STATE.depth, _STATE.saving)
    _STATE.installed, _STATE.pending, _STATE.depth, _STATE.saving = True, None, 0, 0
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        _STATE.installed, _STATE.pending, _STATE.depth, _STATE.saving = saved_state


def requested() -> int | None:
    """The signal waiting to be honoured, or ``None``."""
    return _STATE.pending


@contextlib.contextmanager
def safe_points() -> Iterator[None]:
    """A region whose code polls :func:`requested` at safe points: a first signal inside it waits for one.

    Leaving the outermost region normally with a request pending raises :class:`Interrupted` (nothing new saved)."""
    _STATE.depth += 1
    try:
        yield
    finally:
        _STATE.depth -= 1
    if _STATE.depth == 0 and _STATE.pending is not None:
        raise Interrupted(_STATE.pending)


@contextlib.contextmanager
def saving() -> Iterator[None]:
    """A checkpoint being written: signals that arrive meanwhile wait until the body is done.

    Inside :func:`safe_points` the request is then the caller's to honour (its next :func:`requested` poll, right
    after the write); outside one, a signal that arrived during the body is raised at its end."""
    _STATE.saving += 1
    try:
        yield
    finally:
        _STATE.saving -= 1
    if _STATE.saving == 0 and _STATE.depth == 0 and _STATE.pending is not None:
        raise Interrupted(_STATE.pending)


def stop(saved: str | None) -> None:
    """Raises :class:`Interrupted` for the pending request (which it consumes), saying what was ``saved`` at this
    safe point."""
    signum, _STATE.pending = _STATE.pending, None
    raise Interrupted(signal.SIGINT if signum is None else signum, saved)


def stop_if_requested(saved: str | None) -> None:
    """:func:`stop` when a request is pending; nothing otherwise."""
    if _STATE.pending is not None:
        stop(saved)

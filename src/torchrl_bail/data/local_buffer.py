"""Replay buffers that live in one process: every buffer the library builds for itself (training mini-batches,
BAIL's selection, a behaviour agent's replay).

TorchRL keeps a buffer's length and write cursor in ``multiprocessing.Value`` objects unless the storage and the writer
are built ``compilable``; under TorchRL's ``spawn`` start method each such Value carries a named semaphore registered
with Python's resource tracker. These buffers are never shared across processes, so plain tensors do: nothing is
left for the tracker, whose ``KeyError`` tracebacks a job that Slurm stops would otherwise print at exit (Slurm
signals every process of the job step, the tracker too). The numbers are the same either way.
"""

from __future__ import annotations

from torchrl.data import Storage, TensorDictReplayBuffer, TensorDictRoundRobinWriter

__all__ = ["local_replay_buffer"]


def local_replay_buffer(storage: type[Storage], *storage_args, storage_kwargs: dict | None = None,
                        **buffer_kwargs) -> TensorDictReplayBuffer:
    """``TensorDictReplayBuffer(storage=storage(*storage_args, compilable=True, **storage_kwargs), ...)`` with a
    compilable round-robin writer: a buffer for one process (see the module's docstring).

    >>> import torch
    >>> from tensordict import TensorDict
    >>> from torchrl.data import LazyTensorStorage
    >>> rb = local_replay_buffer(LazyTensorStorage, 4, batch_size=2)
    >>> rb.extend(TensorDict({"x": torch.arange(3.0)}, batch_size=[3]))
    tensor([0, 1, 2])
    >>> len(rb), rb.sample()["x"].shape
    (3, torch.Size([2]))
    """
    return TensorDictReplayBuffer(storage=storage(*storage_args, compilable=True, **(storage_kwargs or {})),
                                  writer=TensorDictRoundRobinWriter(compilable=True), **buffer_kwargs)

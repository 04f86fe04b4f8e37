"""Where a behaviour run's transitions go: a memmap episode store, the batch sink (plain or oracle cut, supp. D.1)
and the pair of them every recipe uses (:class:`BehaviourBuffers`).

Oracle mode (``batch.oracle.enabled=true``, supp. D.1): episodes run for ``oracle.horizon`` (2000) steps, the batch
keeps the first ``oracle.keep`` (1000) steps of each with ``truncated=True`` at ``t = keep - 1``, and stores
``oracle_return`` [N], the plain discounted return over the *real* continuation of the episode.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import LazyMemmapStorage

from torchrl_bail.data.local_buffer import local_replay_buffer
from torchrl_bail.data.returns import discounted_returns

__all__ = ["EpisodeStore", "BatchSink", "BehaviourBuffers"]


class EpisodeStore:
    """A preallocated memmap store of ``capacity`` transitions (the batch), filled one episode at a time.

    Backed by a TorchRL :class:`~torchrl.data.LazyMemmapStorage` in ``scratch`` so that 10^6 Humanoid-size rows
    live on disk (page cache), never twice in RAM; :meth:`sample` draws uniformly from what is stored so far.
    """

    def __init__(self, capacity: int, scratch: Path, *, batch_size: int | None = None):
        self.capacity = int(capacity)
        self.rb = local_replay_buffer(LazyMemmapStorage, self.capacity,
                                      storage_kwargs={"scratch_dir": scratch, "auto_cleanup": False},
                                      batch_size=batch_size)

    def __len__(self) -> int:
        return len(self.rb)

    def extend(self, episode: TensorDictBase) -> None:
        n = episode.shape[0]
        if len(self) + n > self.capacity:
            raise RuntimeError(f"episode store overflow: {len(self)} + {n} > {self.capacity}")
        self.rb.extend(episode)

    def sample(self, batch_size: int | None = None) -> TensorDictBase:
        """``batch_size`` rows (default: the store's) drawn uniformly with replacement from those stored so far.

        The same draw as TorchRL's :class:`~torchrl.data.RandomSampler` on this buffer (one
        ``torch.randint(0, len, (batch_size,))`` on the global generator, so the same rows for the same seed),
        gathered from plain-tensor views of the memmap storage: indexing the memmap TensorDict itself costs a
        collection run ~10 % of its time (``benchmarks/bench_collection.py``). No ``index`` key.
        """
        if len(self) == 0:
            raise RuntimeError("cannot sample from an empty episode store")
        n = self.rb._batch_size if batch_size is None else int(batch_size)
        index = torch.randint(0, len(self), (n,), generator=self.rb.storage._rng)
        return TensorDict({k: v[index] for k, v in self._columns().items()}, [n])

    def _columns(self) -> dict:
        """``{key: plain tensor}`` views of the memmap storage (made once; the storage is preallocated)."""
        storage = self.rb.storage._storage
        if getattr(self, "_viewed", None) is not storage:
            self._views = {k: v.as_subclass(torch.Tensor)
                           for k, v in storage.exclude("index").items(include_nested=True, leaves_only=True)}
            self._viewed = storage
        return self._views

    def data(self) -> TensorDictBase:
        """The stored rows as a memmapped TensorDict (no copy), without the buffer's bookkeeping ``index``."""
        storage = self.rb.storage._storage  # the memmap TensorDict LazyMemmapStorage allocated
        td = storage[: len(self)] if len(self) < self.capacity else storage
        return td.exclude("index")


class BatchSink:
    """Where finished episodes go: every transition (plain mode) or the oracle cut (supp. D.1).

    Plain mode: the store holds exactly ``steps`` transitions; the final episode may be unfinished.

    Oracle mode: each episode (up to ``horizon`` steps) contributes its first ``keep`` steps, with
    ``truncated=done=True`` at ``t = keep - 1`` when the episode went on, and ``oracle_return`` = the plain discounted
    return over the whole real episode. Once ``steps`` transitions are kept, the open episode is run to its end
    (for the returns) and only its rows up to the budget are kept -- that last episode is unfinished.
    """

    def __init__(self, store: EpisodeStore, steps: int, oracle: dict | None = None):
        self.store = store
        self.steps = int(steps)
        self.oracle = oracle
        self.episode_id = 0
        self.kept = 0

    @property
    def budget_reached(self) -> bool:
        """No more transitions are needed (oracle mode: the open episode still has to finish)."""
        return self.kept >= self.steps

    def add_episode(self, episode: TensorDictBase) -> None:
        """``episode``: the TED rows of one episode (finished, or cut by the budget in plain mode)."""
        n = episode.shape[0]
        if self.oracle is None:
            keep = min(n, self.steps - self.kept)
            rows = episode[:keep]
        else:
            g = discounted_returns(episode["next", "reward"], torch.zeros(n, dtype=torch.int64),
                                   float(self.oracle["gamma"])).float()
            keep_ep = min(n, int(self.oracle["keep"]))
            rows = episode[:keep_ep].clone()
            rows.set("oracle_return", g[:keep_ep])
            if n > keep_ep:  # the episode went on past `keep`: the kept part ends in a time-limit truncation
                rows["next", "truncated"][-1] = True
                rows["next", "done"][-1] = True
            keep = min(keep_ep, self.steps - self.kept)
            rows = rows[:keep]
        if keep <= 0:
            return
        rows.set("episode", torch.full((keep,), self.episode_id, dtype=torch.int64))
        self.store.extend(rows)
        self.kept += keep
        self.episode_id += 1



class BehaviourBuffers:
    """The agent's replay buffer and the batch, for plain or oracle collection of ``steps`` transitions.

    Plain mode: one memmap store is both the agent's replay buffer and the batch (the paper's "the batch IS the
    replay buffer"). Oracle mode: the agent replays every transition it saw (up to 2000-step episodes) from its
    own store; the batch keeps the oracle cut (:class:`BatchSink`).

    Args:
        steps: transitions in the batch.
        scratch: a scratch directory (removed by the caller).

    Keyword Args:
        oracle: :func:`oracle_settings` or ``None``.
        replay_batch_size: mini-batch size the agent samples (``None``: no agent, e.g. policy execution).
    """

    def __init__(self, steps: int, scratch: Path, *, oracle: dict | None, replay_batch_size: int | None):
        self.steps = int(steps)
        self.oracle = oracle
        self.batch_store = EpisodeStore(self.steps, scratch / "batch",
                                        batch_size=replay_batch_size if oracle is None else None)
        self.sink = BatchSink(self.batch_store, self.steps, oracle=oracle)
        self.replay: EpisodeStore | None = None
        if replay_batch_size is not None:
            if oracle is None:
                self.replay = self.batch_store
            else:
                ratio = math.ceil(int(oracle["horizon"]) / int(oracle["keep"]))
                self.replay = EpisodeStore(ratio * self.steps + int(oracle["horizon"]), scratch / "replay",
                                           batch_size=replay_batch_size)

    @property
    def sinks(self) -> list:
        return [self.sink] + ([self.replay] if self.replay is not None and self.replay is not self.batch_store else [])

    def until(self, open_rows: int) -> bool:
        if self.oracle is None:
            return self.sink.kept + open_rows >= self.steps
        return self.sink.kept + min(open_rows, int(self.oracle["keep"])) >= self.steps

    @property
    def stores(self) -> dict[str, EpisodeStore]:
        """The distinct stores by name (``batch``, and ``replay`` in oracle mode with an agent): what a checkpoint
        saves."""
        stores = {"batch": self.batch_store}
        if self.replay is not None and self.replay is not self.batch_store:
            stores["replay"] = self.replay
        return stores

    def state_dict(self) -> dict[str, int]:
        """The transitions kept so far, the batch's size (for progress reports: ``run_study.py --status``) and the
        next episode's id."""
        return {"kept": self.sink.kept, "steps": self.steps, "episode_id": self.sink.episode_id}

    def load_state_dict(self, state: dict[str, int]) -> None:
        self.sink.kept = int(state["kept"])
        self.sink.episode_id = int(state["episode_id"])

    def collect(self, runner, *, checkpoint=None) -> TensorDictBase:
        """Runs ``runner`` (a :class:`~torchrl_bail.behaviour.loop.BehaviourRun`) until the batch is full; returns
        the batch (memmapped, no copy). ``checkpoint``: see :meth:`BehaviourRun.run`."""
        runner.run(self.sinks, until=self.until, finish_open_episode=self.oracle is not None, checkpoint=checkpoint)
        if self.sink.kept != self.steps:
            raise RuntimeError(f"collected {self.sink.kept} transitions, expected {self.steps}")
        return self.batch_store.data()


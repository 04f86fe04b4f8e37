"""The step loop every behaviour recipe shares: seed, make the env, act, step, record, call hooks at episode ends.

Examples:
    >>> import torch
    >>> env = make_collection_env("Pendulum-v1", max_episode_steps=5, seed=0)
    >>> low, high = env_bounds(env)
    >>> seen = []
    >>> run = BehaviourRun(env, lambda obs, t: torch.zeros_like(low),
    ...                    on_episode_end=lambda length, ret, t: seen.append(length))
    >>> class Rows(list):
    ...     def extend(self, episode): self.append(episode.shape[0])
    >>> rows = Rows()
    >>> run.run([rows], until=lambda open_rows: sum(rows) + open_rows >= 12)
    >>> list(rows), seen, run.t
    ([5, 5, 2], [5, 5], 12)
    >>> env.close()
"""

from __future__ import annotations

import inspect
import random
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import DoubleToFloat, GymWrapper, TransformedEnv

from torchrl_bail.behaviour.buffers import BatchSink, BehaviourBuffers
from torchrl_bail.core import interrupts
from torchrl_bail.core.progress import tqdm
from torchrl_bail.data.cache import plain
from torchrl_bail.evaluation.simulator import make_guarded_env

__all__ = ["TRANSITION_KEYS", "agent_kwargs", "seed_all", "make_collection_env", "env_bounds", "ReturnTracker",
           "BehaviourRun", "collect_timed", "env_steps_per_s"]

#: the keys one stored transition carries (TED layout); ``episode`` (and ``oracle_return``) are added per episode
TRANSITION_KEYS = (
    "observation",
    "action",
    ("next", "observation"),
    ("next", "reward"),
    ("next", "done"),
    ("next", "terminated"),
    ("next", "truncated"),
)



def agent_kwargs(agent_cls: type, block: Any) -> dict[str, Any]:
    """The keyword-only arguments of ``agent_cls`` that the config ``block`` (``batch.agent``, ``batch.sac``) sets,
    as plain Python values; the agent's own defaults stand for the keys the block leaves out."""
    names = [p.name for p in inspect.signature(agent_cls).parameters.values() if p.kind is p.KEYWORD_ONLY]
    block = plain(block)
    return {name: block[name] for name in names if name in block}

def seed_all(seed: int) -> None:
    """Seeds Python, NumPy and torch from the behaviour seed."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def make_collection_env(env_id: str, *, max_episode_steps: int | None, seed: int):
    """One gymnasium env (``GymWrapper`` + ``DoubleToFloat``), seeded; never ``num_envs`` (zero terminal obs).

    The gymnasium env is wrapped in a :class:`~torchrl_bail.evaluation.simulator.SimulatorGuard`: a step on which MuJoCo
    flags an instability ends the episode (``terminated``) instead of continuing from MuJoCo's silent reset;
    ``env.simulator_guard`` keeps it (its ``unstable_episodes`` go into the batch's metadata). Healthy
    transitions are unchanged. ``set_seed`` resets the env with ``seed``; the first episode starts from the reset
    after that.
    """
    kwargs = {} if max_episode_steps is None else {"max_episode_steps": int(max_episode_steps)}
    guard = make_guarded_env(env_id, **kwargs)
    env = TransformedEnv(GymWrapper(guard), DoubleToFloat())
    env.set_seed(int(seed))
    env.simulator_guard = guard
    return env



def env_bounds(env) -> tuple[torch.Tensor, torch.Tensor]:
    """The env's action bounds ``(low, high)`` as float32 CPU copies."""
    spec = env.action_spec
    space = getattr(spec, "space", None)
    low = space.low if space is not None else spec.low
    high = space.high if space is not None else spec.high
    return low.detach().clone().float(), high.detach().clone().float()


class ReturnTracker:
    """tqdm progress (env steps/s, mean return of the last 10 episodes) and per-episode bookkeeping."""

    def __init__(self, total: int, *, desc: str, progress: bool, window: int = 10):
        self.returns: deque[float] = deque(maxlen=window)
        self.all_returns: list[float] = []
        self.lengths: list[int] = []
        self.bar = None
        self.postfix: dict[str, Any] = {}
        if progress:
            self.bar = tqdm(total=total, desc=desc, unit="step", dynamic_ncols=True, mininterval=0.5, smoothing=0.05)
        self._pending = 0

    def step(self, n: int = 1) -> None:
        if self.bar is not None:
            self._pending += n
            if self._pending >= 100:
                self.bar.update(self._pending)
                self._pending = 0

    def episode(self, ret: float, length: int) -> None:
        self.returns.append(ret)
        self.all_returns.append(ret)
        self.lengths.append(length)
        if self.bar is not None:
            self.postfix["ret10"] = f"{self.mean_recent:.1f}"
            self.postfix["ep"] = len(self.all_returns)
            self.bar.set_postfix(self.postfix, refresh=False)

    def note(self, **kv: Any) -> None:
        if self.bar is not None:
            self.postfix.update(kv)
            self.bar.set_postfix(self.postfix, refresh=False)

    def state_dict(self) -> dict[str, Any]:
        return {"returns": list(self.all_returns), "lengths": list(self.lengths)}

    def load_state_dict(self, state: dict[str, Any], t: int) -> None:
        """Restores the episode records of a resumed run; the progress bar jumps to env step ``t``."""
        self.all_returns = [float(r) for r in state["returns"]]
        self.lengths = [int(n) for n in state["lengths"]]
        self.returns.clear()
        self.returns.extend(self.all_returns[-(self.returns.maxlen or 0):])
        if self.bar is not None:
            self.bar.update(t)
            self.note(resumed=t)

    @property
    def mean_recent(self) -> float:
        return float(np.mean(self.returns)) if self.returns else float("nan")

    def close(self) -> None:
        if self.bar is not None:
            self.bar.update(self._pending)
            self._pending = 0
            self.bar.close()


class BehaviourRun:
    """The step loop every recipe shares: act, step one env, record, and call hooks at episode ends.

    Args:
        env: a seeded TorchRL env from :func:`make_collection_env`.
        act: ``act(observation [obs_dim], t) -> action [act_dim]`` (``t`` = env steps taken so far).

    Keyword Args:
        on_episode_end: ``f(length, episode_return, t)`` after an episode ends (DDPG/SAC train here).
        on_step: ``f(t)`` after every env step (SAC evaluates here).
        tracker: a :class:`ReturnTracker` (progress bar, recent returns).

    Order at an episode end: the episode goes to the sinks, ``on_episode_end``, ``on_step``, then the checkpoint
    (:class:`~torchrl_bail.behaviour.checkpoint.Resumable`, when :meth:`run` has one), and only then the env's
    reset: a checkpoint holds the env's random state from before that reset, so a resumed run resets the same way.
    """

    def __init__(self, env, act: Callable[[torch.Tensor, int], torch.Tensor], *,
                 on_episode_end: Callable[[int, float, int], None] | None = None,
                 on_step: Callable[[int], None] | None = None,
                 tracker: ReturnTracker | None = None):
        self.env = env
        self.act = act
        self.on_episode_end = on_episode_end
        self.on_step = on_step
        self.tracker = tracker
        self.t = 0
        self.episodes = 0
        self._unstable_before = 0  # unstable episodes of earlier (resumed) processes

    @property
    def _np_random(self):
        return self.env.simulator_guard.unwrapped.np_random

    @property
    def unstable_episodes(self) -> int:
        """Episodes the :class:`~torchrl_bail.evaluation.simulator.SimulatorGuard` ended on a simulator instability."""
        return self._unstable_before + self.env.simulator_guard.unstable_episodes

    def state_dict(self) -> dict[str, Any]:
        """Env steps, episodes, episode records and the env's random state (valid at an episode end)."""
        return {"t": self.t, "episodes": self.episodes, "unstable_episodes": self.unstable_episodes,
                "env_rng": self._np_random.bit_generator.state,
                "tracker": self.tracker.state_dict() if self.tracker is not None else None}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.t = int(state["t"])
        self.episodes = int(state["episodes"])
        self._unstable_before = int(state["unstable_episodes"]) - self.env.simulator_guard.unstable_episodes
        self._np_random.bit_generator.state = state["env_rng"]
        if self.tracker is not None and state["tracker"] is not None:
            self.tracker.load_state_dict(state["tracker"], self.t)

    def run(self, sinks: list, *, until: Callable[[int], bool], finish_open_episode: bool = False,
            checkpoint=None) -> None:
        """Steps until ``until(rows_in_open_episode)`` holds.

        When it holds mid-episode the open episode is handed to the sinks unfinished, or, with
        ``finish_open_episode`` (oracle continuation), first run to its end with no more hooks called.
        ``checkpoint``: a :class:`~torchrl_bail.behaviour.checkpoint.Resumable` offered every episode end.
        """
        env = self.env.simulator_guard  # the gymnasium env under the TorchRL wrapper, stepped directly (below)
        observation = _observation(env.reset()[0])
        rows = _EpisodeRows()
        ep_ret = 0.0
        finishing = False
        while True:
            if not finishing and until(len(rows)):
                if rows and finish_open_episode:
                    finishing = True
                else:
                    break
            next_observation, reward, done = self._step(env, observation, rows)
            ep_ret += float(reward)
            if done:
                length = len(rows)
                self._end_episode(rows, ep_ret, sinks)
                rows = _EpisodeRows()
                if finishing:
                    break
                if self.on_episode_end is not None and not until(0):  # no learning once the batch is full
                    self.on_episode_end(length, ep_ret, self.t)
                ep_ret = 0.0
            if not finishing and self.on_step is not None:
                self.on_step(self.t)
            if done:
                if checkpoint is not None and not until(0):
                    checkpoint.maybe_save(self.t)
                observation = _observation(env.reset()[0])
            else:
                observation = next_observation
        if rows:
            self._flush(rows.episode(), sinks)

    def _step(self, env, observation: torch.Tensor, rows: _EpisodeRows) -> tuple[torch.Tensor, np.float32, bool]:
        """One env step: acts on ``observation``, records the transition in ``rows``, counts it; returns
        ``(next observation, reward, done)``."""
        action = self.act(observation, self.t)
        next_observation, reward, terminated, truncated, _ = env.step(action.detach().numpy())
        next_observation = _observation(next_observation)
        reward = np.float32(reward)
        done = bool(terminated or truncated)
        rows.append(observation, action, next_observation, reward, bool(terminated), bool(truncated))
        self.t += 1
        if self.tracker is not None:
            self.tracker.step()
        return next_observation, reward, done

    def _end_episode(self, rows: _EpisodeRows, ep_ret: float, sinks) -> None:
        """Hands the ended episode to the sinks and counts it (episodes, the tracker's returns)."""
        length = len(rows)
        self._flush(rows.episode(), sinks)
        self.episodes += 1
        if self.tracker is not None:
            self.tracker.episode(ep_ret, length)

    @staticmethod
    def _flush(episode: TensorDictBase, sinks) -> None:
        for sink in sinks:
            if isinstance(sink, BatchSink):
                sink.add_episode(episode)
            else:
                sink.extend(episode)


def _observation(observation: np.ndarray) -> torch.Tensor:
    """A float32 observation, as TorchRL's ``GymWrapper`` + ``DoubleToFloat`` give it (one cast at the edge)."""
    return torch.as_tensor(observation, dtype=torch.float32)


class _EpisodeRows:
    """The transitions of the open episode, gathered into one TED TensorDict (:data:`TRANSITION_KEYS`) at its end.

    :class:`BehaviourRun` steps the gymnasium env itself instead of ``env.step(td)`` + ``step_mdp``: the same
    values, dtypes and shapes as the TorchRL env's transitions (batches are byte-identical), without a TensorDict
    per step (~3x a Hopper step's own cost on CPU, ``benchmarks/bench_collection.py``).
    """

    def __init__(self):
        self.observation, self.action, self.next_observation = [], [], []
        self.reward, self.terminated, self.truncated = [], [], []

    def __len__(self) -> int:
        return len(self.action)

    def append(self, observation, action, next_observation, reward, terminated, truncated) -> None:
        self.observation.append(observation)
        self.action.append(action)
        self.next_observation.append(next_observation)
        self.reward.append(reward)
        self.terminated.append(terminated)
        self.truncated.append(truncated)

    def episode(self) -> TensorDictBase:
        n = len(self)
        terminated = torch.tensor(self.terminated).unsqueeze(-1)
        truncated = torch.tensor(self.truncated).unsqueeze(-1)
        return TensorDict({
            "observation": torch.stack(self.observation),
            "action": torch.stack(self.action).detach(),
            "next": {"observation": torch.stack(self.next_observation),
                     "reward": torch.from_numpy(np.asarray(self.reward, dtype=np.float32)).unsqueeze(-1),
                     "done": terminated | truncated, "terminated": terminated, "truncated": truncated},
        }, [n])


def env_steps_per_s(runner: BehaviourRun, wall: float, resumable=None) -> float:
    """The collection's env steps per wall second, over the steps ``wall`` (:func:`collect_timed`'s) timed: all of
    them, or, for a collection resumed from an older version's checkpoint, which kept no time, those from its step
    on (:attr:`~torchrl_bail.behaviour.checkpoint.CollectionCheckpoint.timed_from_step`)."""
    timed_from = resumable.checkpoint.timed_from_step if resumable is not None else 0
    return (runner.t - timed_from) / max(wall, 1e-9)


def collect_timed(buffers: BehaviourBuffers, runner: BehaviourRun, *,
                  after: Callable[[], None] | None = None, resumable=None) -> tuple[TensorDictBase, float]:
    """``buffers.collect(runner)``, then ``after()`` (e.g. a final evaluation), closing the runner's progress bar
    in every case; returns ``(batch, wall seconds)``. With a ``resumable``
    (:class:`~torchrl_bail.behaviour.checkpoint.Resumable`) the run first resumes from its last checkpoint, if
    any, and saves checkpoints as it goes, and at an episode end after Ctrl-C or SIGTERM, before it stops
    (:mod:`torchrl_bail.core.interrupts`); the wall seconds then include those of the earlier processes the checkpoint
    carried (:attr:`~torchrl_bail.behaviour.checkpoint.CollectionCheckpoint.wall_time_s`)."""
    start = time.perf_counter()
    try:
        if resumable is not None:
            resumable.resume()
        data = buffers.collect(runner, checkpoint=resumable)
        if after is not None:
            if resumable is not None and interrupts.requested() is not None:
                # Ctrl-C/SIGTERM during the last episode: checkpoint the full batch, stop before `after`; a rerun
                # resumes here (the loop takes no step) and runs `after` from the same random state
                resumable.save()
                resumable.stop_if_requested()
            after()
    finally:
        if runner.tracker is not None:
            runner.tracker.close()
    earlier = resumable.checkpoint.earlier_wall_time_s if resumable is not None else 0.0
    return data, earlier + time.perf_counter() - start

"""Deterministic policy evaluation on a batched environment (spec section 7).

``N`` test episodes run side by side in one :class:`~torchrl.envs.SerialEnv`. Each episode's return is read
from :class:`~torchrl.envs.RewardSum` at that episode's *first* done, so episodes that end early are neither
cut short by the others (``break_when_any_done``) nor padded with repeated rewards (``break_when_all_done``);
see ``torchrl_idioms.md`` section 3.2.

A simulator failure (an exception raised while stepping) or a non-finite observation or reward scores that
episode 0 — as the paper does for MuJoCo errors — and is counted in :attr:`EvalResult.failures`; the run goes
on. When the batched rollout raises, the episodes are replayed one by one so that only the failing ones score 0.

The test env is seeded once with the run seed; successive evaluations continue its random stream.

Examples:
    >>> from torchrl_bail.modules import make_deterministic_actor
    >>> evaluator = Evaluator("Hopper-v5", episodes=2, seed=0, max_steps=20)
    >>> actor = make_deterministic_actor(evaluator.obs_dim, evaluator.action_spec, hidden=(8,))
    >>> result = evaluator(actor)
    >>> len(result.returns), result.failures
    (2, 0)
    >>> evaluator.close()
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import Compose, DoubleToFloat, GymEnv, RewardSum, SerialEnv, StepCounter, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

__all__ = ["EvalResult", "Evaluator", "make_env"]


def make_env(env_id: str, *, max_episode_steps: int | None = None, device="cpu") -> TransformedEnv:
    """A gymnasium MuJoCo env with float32 observations, an episode-return sum and a step counter."""
    kwargs = {} if max_episode_steps is None else {"max_episode_steps": int(max_episode_steps)}
    env = GymEnv(env_id, device=device, **kwargs)
    return TransformedEnv(env, Compose(DoubleToFloat(), RewardSum(), StepCounter()))


@dataclass
class EvalResult:
    """Returns and lengths of the evaluation episodes; failed episodes score 0."""

    returns: list[float]
    lengths: list[int]
    failures: int = 0
    failed_episodes: list[int] = field(default_factory=list)

    @property
    def mean_return(self) -> float:
        return float(sum(self.returns) / len(self.returns))

    @property
    def std_return(self) -> float:
        m = self.mean_return
        return float(math.sqrt(sum((r - m) ** 2 for r in self.returns) / len(self.returns)))


class Evaluator:
    """Runs ``episodes`` deterministic episodes of a policy in one batched env.

    Args:
        env_id: gymnasium id, e.g. ``"Hopper-v5"``.

    Keyword Args:
        episodes (int): number of test episodes. Defaults to ``10``.
        seed (int): seeds the env once; later evaluations continue the stream. Defaults to ``0``.
        max_steps (int): step budget of one evaluation (the env's time limit ends episodes first).
            Defaults to ``1000``.
        max_episode_steps (int, optional): overrides the env's time limit.
        device: device of the env outputs (the policy's device). Defaults to ``"cpu"``.
    """

    def __init__(
        self,
        env_id: str,
        *,
        episodes: int = 10,
        seed: int = 0,
        max_steps: int = 1000,
        max_episode_steps: int | None = None,
        device="cpu",
    ) -> None:
        if episodes < 1:
            raise ValueError(f"eval.episodes must be >= 1, got {episodes}")
        if max_steps < 1:
            raise ValueError(f"eval.max_steps must be >= 1, got {max_steps}")
        self.env_id = env_id
        self.episodes = int(episodes)
        self.max_steps = int(max_steps)
        self.seed = int(seed)
        self._env_kwargs = {"max_episode_steps": max_episode_steps, "device": device}
        self.env = SerialEnv(self.episodes, lambda: make_env(env_id, **self._env_kwargs))
        self.env.set_seed(self.seed)
        self._fallback_calls = 0

    @property
    def action_spec(self):
        return self.env.action_spec[0] if self.env.action_spec.ndim > 1 else self.env.action_spec

    @property
    def obs_dim(self) -> int:
        return int(self.env.observation_spec["observation"].shape[-1])

    @torch.no_grad()
    def __call__(self, policy: TensorDictModuleBase) -> EvalResult:
        try:
            with set_exploration_type(ExplorationType.DETERMINISTIC):
                rollout = self.env.rollout(
                    self.max_steps, policy, break_when_any_done=False, break_when_all_done=True,
                    auto_cast_to_device=True,
                )
        except Exception:  # noqa: BLE001 - any simulator error scores the affected episodes 0
            return self._episode_by_episode(policy)
        return _read_episodes(rollout)

    def _episode_by_episode(self, policy) -> EvalResult:
        """Replays each episode in its own env so that only the failing ones score 0."""
        returns, lengths, failed = [], [], []
        self._fallback_calls += 1
        for i in range(self.episodes):
            env = make_env(self.env_id, **self._env_kwargs)
            env.set_seed(self.seed + 1_000_003 * self._fallback_calls + i)
            try:
                with set_exploration_type(ExplorationType.DETERMINISTIC):
                    ro = env.rollout(self.max_steps, policy, break_when_any_done=True, auto_cast_to_device=True)
                res = _read_episodes(ro.unsqueeze(0))
                returns += res.returns
                lengths += res.lengths
                if res.failures:
                    failed.append(i)
            except Exception:  # noqa: BLE001
                returns.append(0.0)
                lengths.append(0)
                failed.append(i)
            finally:
                env.close()
        return EvalResult(returns, lengths, len(failed), failed)

    def close(self) -> None:
        if not self.env.is_closed:
            self.env.close()


def _read_episodes(rollout) -> EvalResult:
    """Reads each episode's return at its first done from a ``[n, T]`` rollout."""
    done = rollout["next", "done"].squeeze(-1)
    n, horizon = done.shape
    first = torch.where(done.any(-1), done.float().argmax(-1), torch.full((n,), horizon - 1))
    idx = torch.arange(n)
    returns = rollout["next", "episode_reward"][idx, first].squeeze(-1).double()
    lengths = rollout["next", "step_count"][idx, first].squeeze(-1)
    # Non-finite states or rewards before (or at) the episode's first done count as simulator failures.
    steps = torch.arange(horizon).expand(n, horizon)
    alive = steps <= first.unsqueeze(-1)
    obs = rollout["next", "observation"]
    bad_obs = ~torch.isfinite(obs).flatten(2).all(-1)
    bad_rew = ~torch.isfinite(rollout["next", "reward"]).flatten(2).all(-1)
    failed = ((bad_obs | bad_rew) & alive).any(-1) | ~torch.isfinite(returns)
    returns = torch.where(failed, torch.zeros_like(returns), returns)
    failed_idx = failed.nonzero().flatten().tolist()
    return EvalResult(returns.tolist(), lengths.tolist(), len(failed_idx), failed_idx)

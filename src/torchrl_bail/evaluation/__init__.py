"""Deterministic policy evaluation at simulator speed (arXiv:1910.12179, supplement C.4).

The ``N`` test episodes of an evaluation run side by side: ``N`` gymnasium envs, one policy call per step on the
stacked observations ``[N, obs_dim]`` (float64 -> float32 once, one host-to-device transfer and one back per step
when the policy runs on a GPU), then one simulator step per running episode. There is no per-step TensorDict
env machinery in between: the loop is as fast as a hand-written gymnasium loop (``benchmarks/bench_evaluation.py``).

Semantics:

* each episode's return is the undiscounted sum of its rewards up to its *own* first ``terminated`` or
  ``truncated`` (the env's time limit), or up to ``max_steps`` steps; an episode that ended is not stepped again,
  the others go on;
* beside it, each episode's *discounted* return from its start, ``sum_t gamma^t r_t`` over the same steps
  (:attr:`EvalResult.discounted_returns`), at the ``gamma`` off-policy evaluation estimates (FQE's,
  :data:`torchrl_bail.objectives.fqe.FQE_GAMMA`, ``0.99``, unless ``gamma=`` says otherwise): the value an FQE estimate
  of the same policy aims at, from this evaluation's start states rather than the batch's;
* the policy acts deterministically (:class:`~torchrl.envs.utils.ExplorationType` ``DETERMINISTIC``) and is
  always called on the whole ``[*batch_shape]`` batch (finished episodes keep their last observation), so its
  outputs never depend on which other episodes are still running;
* a simulator failure scores the episode 0 and is counted in :attr:`EvalResult.failures`: an exception raised by
  the env, or a step that :class:`~torchrl_bail.evaluation.simulator.SimulatorGuard` flags (a MuJoCo instability warning
  --
  MuJoCo >= 3 resets the simulation instead of raising -- or a non-finite observation or reward); the run goes on.

Seeding: the ``k``-th call (``k = 0, 1, ...``, :attr:`Evaluator.evaluations`) resets episode ``i`` with the seed
``numpy.random.SeedSequence(seed, spawn_key=(k, i)).generate_state(1)[0]``: every evaluation sees new start
states, the same ``seed`` always gives the same returns, and the ``k``-th evaluation does not depend on what the
earlier ones did (set :attr:`Evaluator.evaluations` to resume a stream).

Seeds: an evaluator plays the training seeds of a list, and :meth:`Evaluator.evaluate` returns one
:class:`EvalResult` per seed. ``Evaluator(..., seeds=[s_1, ..., s_S])`` runs ``S x N`` episodes in one step loop; the
policy sees observations of shape ``[S, N, obs_dim]`` (row ``s`` for seed ``s``, e.g. the seed-stacked policies of
:mod:`torchrl_bail.core.stacking`), and each seed's result equals what ``Evaluator(..., seeds=[s_j])`` gives for that
seed's policy (as long as the policy computes each row as it would alone: a matrix product's last bits can depend
on the batch shape). A list of one seed (``seed=s`` is ``seeds=[s]``) is played by one unstacked policy on
``[N, obs_dim]`` observations, as a single-seed run's policy always was.

Examples:
    >>> from torchrl_bail.modules import make_deterministic_actor
    >>> evaluator = Evaluator("Hopper-v5", episodes=2, seeds=[0], max_steps=20)
    >>> actor = make_deterministic_actor(evaluator.obs_dim, evaluator.action_spec, hidden=(8,))
    >>> (result,) = evaluator.evaluate(actor)
    >>> len(result.returns), len(result.discounted_returns), result.gamma, result.failures, evaluator.evaluations
    (2, 2, 0.99, 0, 1)
    >>> evaluator.close()
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_bail.evaluation.simulator import make_guarded_env
from torchrl_bail.modules import action_spec_from_bounds
from torchrl_bail.objectives.fqe import FQE_GAMMA

__all__ = ["EvalResult", "Evaluator", "episode_seed"]


def episode_seed(seed: int, evaluation: int, episode: int) -> int:
    """The reset seed of episode ``episode`` in the ``evaluation``-th evaluation of a run seeded ``seed``.

    >>> episode_seed(0, 0, 0) == episode_seed(0, 0, 0) != episode_seed(0, 1, 0)
    True
    """
    return int(np.random.SeedSequence(int(seed), spawn_key=(int(evaluation), int(episode))).generate_state(1)[0])


@dataclass
class EvalResult:
    """Returns and lengths (steps taken) of the evaluation episodes, and their discounted returns
    (``sum_t gamma^t r_t`` from each episode's start, at ``gamma``); failed episodes score 0 in both."""

    returns: list[float]
    lengths: list[int]
    failures: int = 0
    failed_episodes: list[int] = field(default_factory=list)
    discounted_returns: list[float] = field(default_factory=list)
    gamma: float | None = None

    @property
    def mean_return(self) -> float:
        return float(sum(self.returns) / len(self.returns))

    @property
    def mean_discounted_return(self) -> float | None:
        """The mean of :attr:`discounted_returns` (``None`` when the result has none)."""
        if not self.discounted_returns:
            return None
        return float(sum(self.discounted_returns) / len(self.discounted_returns))

    @property
    def std_return(self) -> float:
        m = self.mean_return
        return float(math.sqrt(sum((r - m) ** 2 for r in self.returns) / len(self.returns)))


class Evaluator:
    """Runs ``episodes`` deterministic episodes of a policy side by side and reads each one's return.

    Args:
        env_id: gymnasium id, e.g. ``"Hopper-v5"``.

    Keyword Args:
        episodes (int): number of test episodes (per seed). Defaults to ``10``.
        seed (int): shorthand for ``seeds=[seed]``. Defaults to ``0``.
        seeds (sequence of int, optional): the run seeds evaluated, ``S >= 1`` (``S x episodes`` episodes; see the
            module docstring for the per-episode reset seeds and the policy's batch); overrides ``seed``. Defaults
            to ``None`` (``[seed]``).
        max_steps (int): step budget of one episode (the env's time limit ends episodes first when shorter).
            Defaults to ``1000``.
        max_episode_steps (int, optional): overrides the env's time limit.
        device (str | torch.device): the policy's device; observations are sent there once per step. Defaults to
            ``"cpu"``.
        env_kwargs (dict, optional): extra keyword arguments of ``gymnasium.make`` (e.g.
            ``{"terminate_when_unhealthy": False}``). Defaults to ``None``.
        gamma (float): discount of :attr:`EvalResult.discounted_returns`, in ``[0, 1]``. Defaults to FQE's
            (:data:`torchrl_bail.objectives.fqe.FQE_GAMMA`, ``0.99``).
    """

    def __init__(
        self,
        env_id: str,
        *,
        episodes: int = 10,
        seed: int = 0,
        seeds: Sequence[int] | None = None,
        max_steps: int = 1000,
        max_episode_steps: int | None = None,
        device="cpu",
        env_kwargs: Mapping[str, Any] | None = None,
        gamma: float = FQE_GAMMA,
    ) -> None:
        if not 0.0 <= gamma <= 1.0:
            raise ValueError(f"gamma = {gamma!r}: expected a discount in [0, 1]")
        if episodes < 1:
            raise ValueError(f"eval.episodes must be >= 1, got {episodes}")
        if max_steps < 1:
            raise ValueError(f"eval.max_steps must be >= 1, got {max_steps}")
        if seeds is not None and len(seeds) < 1:
            raise ValueError("eval seeds must name at least one seed, got an empty list")
        self.env_id = env_id
        self.episodes = int(episodes)
        self.max_steps = int(max_steps)
        self.gamma = float(gamma)
        #: the seeds evaluated: ``seeds``, or ``[seed]``
        self.seeds = [int(seed)] if seeds is None else [int(s) for s in seeds]
        #: the policy's batch: ``[episodes]`` for one seed (an unstacked policy), ``[S, episodes]`` for ``S > 1``
        self.batch_shape = torch.Size([*([len(self.seeds)] if len(self.seeds) > 1 else []), self.episodes])
        self.device = torch.device(device)
        self.evaluations = 0
        make_kwargs = {"disable_env_checker": True, **(env_kwargs or {})}
        self.envs = [make_guarded_env(env_id, max_episode_steps=max_episode_steps, **make_kwargs)
                     for _ in range(self.batch_shape.numel())]
        space = self.envs[0].action_space
        self.action_spec = action_spec_from_bounds(space.low, space.high).to(self.device)
        self.obs_dim = int(self.envs[0].observation_space.shape[-1])

    @torch.no_grad()
    def evaluate(self, policy: TensorDictModuleBase) -> list[EvalResult]:
        """Plays one evaluation of the policy of every seed (:attr:`batch_shape` observations); returns one
        :class:`EvalResult` per seed, in the order of :attr:`seeds`."""
        n = len(self.envs)
        seeds = self.seeds
        obs = np.zeros((n, self.obs_dim), dtype=np.float32)
        returns = np.zeros(n)
        discounted = np.zeros(n)  # sum_t gamma^t r_t: discount[i] is gamma^t at episode i's step t
        discount = np.ones(n)
        lengths = np.zeros(n, dtype=np.int64)
        running = np.ones(n, dtype=bool)
        failed = np.zeros(n, dtype=bool)

        def fail(i: int) -> None:
            failed[i], running[i] = True, False

        for i, env in enumerate(self.envs):
            try:
                obs[i], _ = env.reset(seed=episode_seed(seeds[i // self.episodes], self.evaluations, i % self.episodes))
            except Exception:  # noqa: BLE001 - a simulator error scores the episode 0
                fail(i)
        self.evaluations += 1
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            for _ in range(self.max_steps):
                if not running.any():
                    break
                observation = torch.tensor(obs, device=self.device).view(*self.batch_shape, self.obs_dim)
                td = policy(TensorDict({"observation": observation}, batch_size=self.batch_shape, device=self.device))
                actions = td["action"].reshape(n, -1).cpu().numpy()
                for i in np.flatnonzero(running):
                    try:
                        o, r, terminated, truncated, info = self.envs[i].step(actions[i])
                    except Exception:  # noqa: BLE001
                        fail(i)
                        continue
                    lengths[i] += 1
                    if info["simulator_unstable"]:
                        fail(i)
                        continue
                    returns[i] += r
                    discounted[i] += discount[i] * r
                    discount[i] *= self.gamma
                    obs[i] = o
                    running[i] = not (terminated or truncated)
        returns[failed] = 0.0
        discounted[failed] = 0.0
        return [_result(returns[j], lengths[j], failed[j], discounted[j], self.gamma)
                for j in np.split(np.arange(n), len(seeds))]

    def state_dict(self) -> dict[str, int]:
        """What a checkpoint needs to continue the evaluation stream: the number of evaluations run so far (every
        episode's reset seed derives from it, see the module docstring)."""
        return {"evaluations": self.evaluations}

    def load_state_dict(self, state: dict[str, int]) -> None:
        self.evaluations = int(state["evaluations"])

    def close(self) -> None:
        for env in self.envs:
            env.close()
        self.envs = []

    def __enter__(self) -> Evaluator:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _result(returns: np.ndarray, lengths: np.ndarray, failed: np.ndarray, discounted: np.ndarray,
            gamma: float) -> EvalResult:
    failed_idx = np.flatnonzero(failed).tolist()
    return EvalResult([float(r) for r in returns], [int(x) for x in lengths], len(failed_idx), failed_idx,
                      [float(d) for d in discounted], gamma)

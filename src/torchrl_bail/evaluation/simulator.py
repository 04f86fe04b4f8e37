"""Simulator failures on MuJoCo >= 3: detect them, end the episode, say so.

The paper scores a test episode 0 when "we encounter an error signal from the MuJoCo environment, and thus are not
able to continue the episode" (arXiv:1910.12179, supplement C.4). Under mujoco-py that signal was an exception.
MuJoCo 3/4 raises nothing: when the state or acceleration becomes NaN, infinite or huge it prints a warning,
increments ``data.warning[mjWARN_BADQPOS | mjWARN_BADQVEL | mjWARN_BADQACC].number``, resets the simulation to the
model's initial state and keeps stepping. Without a check, a diverging policy is silently scored on the reset
continuation instead of 0.

:class:`SimulatorGuard` is a gymnasium wrapper that makes the failure visible again: on the first step in which one
of those counters grows (or the observation or reward is not finite) it sets ``terminated=True`` and
``info["simulator_unstable"] = True``; ``info["simulator_unstable"]`` is ``False`` on every other step and reset,
so the key is always present. The episode ends there because its continuation is not a successor of the previous
state: evaluation scores it 0, collection records the ended episode. :attr:`SimulatorGuard.unstable_episodes`
counts the episodes it ended since the wrapper was built.

Examples:
    >>> env = make_guarded_env("Hopper-v5")
    >>> _ = env.reset(seed=0)
    >>> env.unwrapped.data.qvel[:] = 1e20  # drive the simulation unstable
    >>> _, _, terminated, _, info = env.step(env.action_space.sample())
    >>> terminated, info["simulator_unstable"], env.unstable_episodes
    (True, True, 1)
    >>> env.close()
"""

from __future__ import annotations

import math

import gymnasium as gym
import mujoco
import numpy as np

__all__ = ["UNSTABLE_WARNINGS", "SimulatorGuard", "make_guarded_env", "simulator_warnings"]

#: the MuJoCo warnings that mean "the simulation diverged and was reset" (mujoco-py raised on these)
UNSTABLE_WARNINGS = (mujoco.mjtWarning.mjWARN_BADQPOS, mujoco.mjtWarning.mjWARN_BADQVEL,
                     mujoco.mjtWarning.mjWARN_BADQACC)


def simulator_warnings(env: gym.Env) -> int:
    """How many instability warnings MuJoCo raised since the env's last reset (``mj_resetData`` clears them).

    Returns 0 for an env without MuJoCo data (nothing to watch).
    """
    data = getattr(env.unwrapped, "data", None)
    if data is None or not hasattr(data, "warning"):
        return 0
    warning = data.warning
    return sum(int(warning[w].number) for w in UNSTABLE_WARNINGS)


class SimulatorGuard(gym.Wrapper):
    """Ends an episode at the first step on which the MuJoCo simulation went unstable.

    Unstable means: an instability warning (:data:`UNSTABLE_WARNINGS`) was raised during the step, or the
    observation or the reward is not finite. Such a step returns ``terminated=True`` and
    ``info["simulator_unstable"] = True``; every other step and reset returns ``info["simulator_unstable"] = False``.
    """

    def __init__(self, env: gym.Env):
        super().__init__(env)
        self._warnings = 0
        self.unstable_episodes = 0

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        self._warnings = simulator_warnings(self.env)
        info["simulator_unstable"] = False
        return obs, info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        warnings = simulator_warnings(self.env)
        unstable = warnings > self._warnings or not (math.isfinite(reward) and np.isfinite(obs).all())
        self._warnings = warnings
        if unstable:
            self.unstable_episodes += 1
            terminated = True
        info["simulator_unstable"] = unstable
        return obs, reward, terminated, truncated, info


def make_guarded_env(env_id: str, *, max_episode_steps: int | None = None, **kwargs) -> SimulatorGuard:
    """``gymnasium.make(env_id, ...)`` wrapped in a :class:`SimulatorGuard` (outside the time limit)."""
    if max_episode_steps is not None:
        kwargs["max_episode_steps"] = int(max_episode_steps)
    return SimulatorGuard(gym.make(env_id, **kwargs))

"""A small real Hopper-v5 batch for tests: seeded uniform-random actions under a 25-step time limit, so it has
episodes that fall (terminated), episodes cut by the limit (truncated) and a last episode still running."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch
from tensordict import TensorDict

from torchrl_bail.data import save_batch

LIMIT = 25


def hopper_rows(n: int = 160, seed: int = 0, limit: int = LIMIT) -> TensorDict:
    """``n`` TED rows of Hopper-v5 under seeded uniform-random actions; the last episode is left unfinished."""
    env = gym.make("Hopper-v5", max_episode_steps=limit)
    env.action_space.seed(seed)
    cols = {k: [] for k in ("obs", "act", "rew", "next", "term", "trunc", "ep")}
    obs, _ = env.reset(seed=seed)
    episode = 0
    for _ in range(n):
        act = env.action_space.sample()
        nxt, rew, term, trunc, _ = env.step(act)
        for key, value in zip(cols, (obs, act, rew, nxt, term, trunc, episode), strict=True):
            cols[key].append(value)
        obs = nxt
        if term or trunc:
            episode += 1
            obs, _ = env.reset(seed=seed + episode)
    env.close()

    def col(key, dtype):
        return torch.as_tensor(np.array(cols[key]), dtype=dtype)

    term, trunc = col("term", torch.bool).unsqueeze(-1), col("trunc", torch.bool).unsqueeze(-1)
    return TensorDict({"observation": col("obs", torch.float32), "action": col("act", torch.float32),
                       "episode": col("ep", torch.int64),
                       "next": {"observation": col("next", torch.float32),
                                "reward": col("rew", torch.float32).unsqueeze(-1),
                                "terminated": term, "truncated": trunc, "done": term | trunc}}, [n])


def native_batch(path, **kwargs):
    td = hopper_rows(**kwargs)
    meta = {"env_id": "Hopper-v5", "name": "hopper_random_b3", "kind": "random", "index": 3, "seed": 3,
            "recipe": {"recipe": "random", "steps": td.shape[0], "max_episode_steps": LIMIT}, "recipe_hash": "0badf00d"}
    return save_batch(td, path, meta)

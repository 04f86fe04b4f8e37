"""TorchRL 0.14.1's ``MinariExperienceReplay`` returns zeros: a minimal reproduction, and the reader that works.

    python docs/known_issues/torchrl_minari_zeros.py

It writes a tiny Minari dataset (3 random Pendulum-v1 episodes of 20 steps) in a temporary folder, reads it back
with Minari itself, with TorchRL's ``MinariExperienceReplay`` and with this package's ``import_dataset``, and prints
what each returns. Nothing is downloaded; it takes a few seconds.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
import warnings
from pathlib import Path

root = Path(tempfile.mkdtemp(prefix="minari_zeros_"))
os.environ["MINARI_DATASETS_PATH"] = str(root / "minari")  # before minari is imported: a private dataset folder
os.environ.setdefault("TQDM_DISABLE", "1")                   # TorchRL's progress bar while it reads

import gymnasium as gym  # noqa: E402
import minari  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from minari.data_collector import EpisodeBuffer  # noqa: E402
from torchrl.data.datasets import MinariExperienceReplay  # noqa: E402

from torchrl_bail.data.importers import import_dataset  # noqa: E402


def first(values) -> str:
    return "[" + ", ".join(f"{float(v):.3f}" for v in values) + "]"


def main() -> None:
    logging.getLogger("torchrl").setLevel(logging.WARNING)  # its INFO lines print the whole TensorDict
    # 1. A tiny local Minari dataset: 3 random Pendulum-v1 episodes of 20 steps, written by Minari itself.
    env = gym.make("Pendulum-v1", max_episode_steps=20)
    env.action_space.seed(0)
    buffers = []
    for episode in range(3):
        observations, actions, rewards = [env.reset(seed=episode)[0]], [], []
        for _ in range(20):
            actions.append(env.action_space.sample())
            observation, reward, *_ = env.step(actions[-1])
            observations.append(observation)
            rewards.append(reward)
        buffers.append(EpisodeBuffer(id=episode, observations=np.array(observations), actions=np.array(actions),
                                     rewards=rewards, terminations=[False] * 20, truncations=[False] * 19 + [True]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Minari warns about every optional field left out (author, e-mail, link)
        dataset = minari.create_dataset_from_buffers("tiny/pendulum-random-v0", buffers, env=env,
                                                     algorithm_name="random")
    episodes = list(dataset.iterate_episodes())
    rewards = torch.cat([torch.as_tensor(e.rewards, dtype=torch.float32) for e in episodes])
    print(f"minari:       {dataset.total_steps} steps, reward sum {rewards.sum():.2f}, "
          f"first observation {first(episodes[0].observations[0])}")

    # 2. TorchRL's reader: the right keys, shapes and dtypes, every value 0.
    replay = MinariExperienceReplay("tiny/pendulum-random-v0", batch_size=8, load_from_local_minari=True,
                                    root=root / "torchrl")
    data = replay[:]
    zeros = all(not data[key].any() for key in data.keys(True, True))
    print(f"torchrl:      {len(data)} steps, reward sum {data['next', 'reward'].sum():.2f}, "
          f"first observation {first(data['observation'][0])}; every value is zero: {zeros}")

    # 3. The reader that works: torchrl_bail's importer (the same TED layout, the file's values).
    batch = import_dataset(root / "minari" / "tiny" / "pendulum-random-v0", data_dir=root / "cache")
    same = torch.equal(batch.data["next", "reward"].flatten(), rewards)
    print(f"torchrl_bail: {batch.num_transitions} steps, reward sum {batch.data['next', 'reward'].sum():.2f}, "
          f"first observation {first(batch.data['observation'][0])}; rewards equal Minari's: {same}")


if __name__ == "__main__":
    try:
        main()
    finally:
        shutil.rmtree(root)

"""Train on a dataset you already have: a D4RL-layout HDF5 file or a local Minari dataset.

    python docs/tutorials/bring_your_own_data.py --d4rl ~/.d4rl/datasets/hopper_medium-v2.hdf5
    python docs/tutorials/bring_your_own_data.py --minari ~/.minari/datasets/mujoco/hopper/medium-v0
    python docs/tutorials/bring_your_own_data.py      # no file at hand: writes a small D4RL-layout file first

Nothing is downloaded: the files are read with h5py (neither d4rl nor mujoco-py is needed). Any further argument is
a Hydra override added to the training runs.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import h5py
import numpy as np

from torchrl_bail.data.importers import import_dataset


def sh(*args: str) -> None:
    print("$", " ".join(args).replace(sys.executable, "python"), flush=True)
    subprocess.run(args, check=True)


def write_d4rl_file(path: Path, steps: int, seed: int = 0) -> Path:
    """A stand-in for a file you have: ``steps`` random-action Hopper-v5 transitions in D4RL's layout
    (flat ``observations, actions, rewards, terminals, timeouts, next_observations``)."""
    env = gym.make("Hopper-v5", max_episode_steps=1000)
    rows = {k: [] for k in ("observations", "actions", "rewards", "terminals", "timeouts", "next_observations")}
    obs, _ = env.reset(seed=seed)
    env.action_space.seed(seed)
    for _ in range(steps):
        action = env.action_space.sample()
        next_obs, reward, terminated, truncated, _ = env.step(action)
        for key, value in zip(rows, (obs, action, reward, terminated, truncated, next_obs), strict=True):
            rows[key].append(value)
        obs = env.reset()[0] if terminated or truncated else next_obs
    with h5py.File(path, "w") as f:
        for key, values in rows.items():
            f[key] = np.asarray(values)
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--d4rl", type=Path, help="a D4RL-layout .hdf5 file (default: one written here)")
    parser.add_argument("--minari", type=Path, help="a local Minari dataset folder (or its data/ folder)")
    parser.add_argument("--env", default="hopper", help="the config's env= matching the data (sizes are checked)")
    parser.add_argument("--work-dir", type=Path, default=Path("tutorial_data"))
    parser.add_argument("--steps", type=int, default=20_000, help="size of the file written when --d4rl is absent")
    args, overrides = parser.parse_known_args()
    args.work_dir.mkdir(parents=True, exist_ok=True)
    if args.d4rl is None:
        args.d4rl = write_d4rl_file(args.work_dir / "hopper_random.hdf5", args.steps)
    datasets = {"d4rl": args.d4rl.expanduser()} | ({"minari": args.minari.expanduser()} if args.minari else {})
    env_id = {"hopper": "Hopper-v5", "walker": "Walker2d-v5", "halfcheetah": "HalfCheetah-v5", "ant": "Ant-v5",
              "humanoid": "Humanoid-v5"}[args.env]

    for name, path in datasets.items():
        # 1. Import: checks every key at the edge (one error line naming the file and key), builds episodes from
        #    terminals | timeouts, converts to the TED layout once and caches the result in the data directory.
        batch = import_dataset(path, env_id=env_id)
        meta = batch.metadata
        print(f"{name}: {batch.num_transitions} transitions, {batch.num_episodes} episodes, mean episode return "
              f"{float(batch.episode_returns().mean()):.1f}; dropped rows {meta.get('dropped_rows', 0)}, cached at "
              f"{batch.path}")

        # 2. Train on it: dataset= replaces the generated batch; env= says which env evaluates the policy.
        run_dir = args.work_dir / f"run_{name}"
        sh(sys.executable, "-m", "torchrl_bail.train", f"dataset={path}", f"env={args.env}", "algo=bail",
           "preset=quick", f"hydra.run.dir={run_dir}", "progress=false", *overrides)
        summary = json.loads((run_dir / "summary.json").read_text())
        print(f"{name}: final_return {summary['final_return']:.1f}, normalised "
              f"{summary.get('final_return_normalized', float('nan')):.1f} (D4RL's reference scores)")


if __name__ == "__main__":
    main()

"""Measures the v5 random-policy reference returns (Minari's ``ref_min_score``) and writes ``reference_scores.json``.

``python results/reference_scores.py [--episodes 100] [--envs Hopper-v5,...]``

For each env: ``gymnasium.make(env_id)`` with its registered time limit (1000 steps for every MuJoCo v5 env, as in
``conf/env``), actions drawn uniformly from the action space (``action_space.sample()``, seeded with ``seed``),
episode ``i`` reset with ``seed + i``; the reference is the mean undiscounted return over ``--episodes`` episodes.
This is the protocol of D4RL's ``REF_MIN_SCORE`` and of Minari's own default (``minari.utils.RandomPolicy``), here
on the gymnasium v5 envs the batches are collected on. The numbers are copied into
:data:`torchrl_bail.data.minari_export.V5_RANDOM_SCORES` (``tests/test_minari_export.py`` checks both agree).

The file also records ``ref_max_score``'s status: the best return this library's SAC run reaches. No paper-scale
(10^6-step) SAC run has been made yet, so every ``ref_max_score`` is ``null`` with that reason; the study-scale
(5 x 10^4-step) SAC runs of ``results/study`` are listed for information only (far from expert level, they would
make normalised scores exceed 100).
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import platform
import time
from pathlib import Path

import gymnasium as gym
import numpy as np

ENVS = ("Hopper-v5", "Walker2d-v5", "HalfCheetah-v5", "Ant-v5", "Humanoid-v5")
OUT = Path(__file__).with_name("reference_scores.json")
MAX_REASON = ("no paper-scale (10^6 env steps) SAC run of this library exists yet; pass --ref-max-score to the "
              "export, or take the best evaluation return_mean of policies/<env>_sac_b1-<hash>/run.json once one does")
#: study-scale SAC numbers (results/study, preset=study: a 5 x 10^4-step SAC run): the opt_det batch's mean episode
#: return is the final SAC policy's deterministic return; informational only, not a reference
STUDY_SAC = {
    "Hopper-v5": {"opt_det_batch_mean_return": 406.0, "source": "results/study/study.md, row hopper_opt_det_b1"},
    "Walker2d-v5": {"opt_det_batch_mean_return": 390.9, "source": "results/study/study.md, row walker_opt_det_b1"},
}


def random_returns(env_id: str, episodes: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    env = gym.make(env_id)
    env.action_space.seed(seed)
    returns, lengths = np.zeros(episodes), np.zeros(episodes, dtype=np.int64)
    try:
        for i in range(episodes):
            env.reset(seed=seed + i)
            done = False
            while not done:
                _, reward, terminated, truncated, _ = env.step(env.action_space.sample())
                returns[i] += float(reward)
                lengths[i] += 1
                done = terminated or truncated
    finally:
        env.close()
    return returns, lengths


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--envs", default=",".join(ENVS))
    parser.add_argument("--out", default=str(OUT))
    args = parser.parse_args()
    scores = {}
    for env_id in args.envs.split(","):
        start = time.process_time()
        returns, lengths = random_returns(env_id, args.episodes, args.seed)
        scores[env_id] = {
            "ref_min_score": round(float(returns.mean()), 3),
            "ref_min_score_std": round(float(returns.std(ddof=1)), 3),
            "ref_min_score_sem": round(float(returns.std(ddof=1) / np.sqrt(len(returns))), 3),
            "episodes": int(args.episodes),
            "mean_episode_length": float(lengths.mean()),
            "cpu_s": round(time.process_time() - start, 1),
            "ref_max_score": None,
            "ref_max_score_reason": MAX_REASON,
            **({"study_scale_sac": STUDY_SAC[env_id]} if env_id in STUDY_SAC else {}),
        }
        print(f"{env_id}: random policy {returns.mean():.3f} +- {returns.std(ddof=1) / np.sqrt(len(returns)):.3f} "
              f"(s.e.m.) over {args.episodes} episodes, mean length {lengths.mean():.1f}", flush=True)
    versions = {p: importlib.metadata.version(p) for p in ("gymnasium", "mujoco", "numpy")}
    record = {
        "protocol": ("uniform-random actions (action_space.sample(), seeded with 'seed'), episode i reset with "
                     "seed + i, the registered v5 time limit (1000 steps), mean undiscounted return"),
        "command": f"python results/reference_scores.py --episodes {args.episodes} --seed {args.seed}",
        "seed": args.seed,
        "versions": versions,
        "machine": f"{platform.machine()} {platform.processor() or ''}".strip(),
        "measured_at": time.strftime("%Y-%m-%d"),
        "scores": scores,
    }
    Path(args.out).write_text(json.dumps(record, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

"""Measures the v5 random-policy reference returns (Minari's ``ref_min_score``) and writes ``reference_scores.json``.

``python results/reference_scores.py [--episodes 100] [--envs Hopper-v5,...]``

For each env: ``gymnasium.make(env_id)`` with its registered time limit (1000 steps for every MuJoCo v5 env, as in
``conf/env``), actions drawn uniformly from the action space (``action_space.sample()``, seeded with ``seed``),
episode ``i`` reset with ``seed + i``; the reference is the mean undiscounted return over ``--episodes`` episodes.
This is the protocol of D4RL's ``REF_MIN_SCORE`` and of Minari's own default (``minari.utils.RandomPolicy``), here
on the gymnasium v5 envs the batches are collected on. The numbers are copied into
:data:`torchrl_bail.data.minari_export.V5_RANDOM_SCORES` (``tests/test_minari_export.py`` checks both agree).

``ref_max_score`` (``--expert-only [--expert-from results/paper_exec]``, which leaves the random references as they
are): the mean episode return of the env's ``<env>_opt_det_b1`` batch, whose metadata the execution-batch study keeps
in ``<DIR>/batches/``: the paper-scale (10^6-step) SAC run's final policy, run deterministically for 10^6 steps, so
the mean over hundreds of its episodes (D4RL's ``REF_MAX_SCORE`` is likewise an expert SAC policy's mean return).
An env without that batch keeps ``null`` with the reason. The numbers are copied into
:data:`torchrl_bail.data.scores.V5_EXPERT_SCORES` (a test checks both agree), and every ``summary.json`` made after
normalises by the v5 references where an env has both. The study-scale (5 x 10^4-step) SAC runs of ``results/study``
are listed for information only (far from expert level, they would make normalised scores exceed 100).
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
MAX_REASON = ("no paper-scale (10^6 env steps) SAC run of this library with its opt_det batch exists yet "
              "(results/paper_exec/batches/<env>_opt_det_b1-<hash>.metadata.json); until then pass --ref-max-score "
              "to the export")
MAX_PROTOCOL = ("the mean episode return of the env's opt_det_b1 batch: the paper-scale (10^6-step) SAC run's final "
                "policy run deterministically for 10^6 steps")
#: gymnasium id -> the name of this package's env (conf/env) in batch labels
ENV_NAMES = {"Hopper-v5": "hopper", "Walker2d-v5": "walker", "HalfCheetah-v5": "halfcheetah", "Ant-v5": "ant",
             "Humanoid-v5": "humanoid"}
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


def expert_scores(record: dict, study: Path) -> dict:
    """``record`` with each env's ``ref_max_score`` taken from ``study``'s kept ``<env>_opt_det_b1`` batch metadata
    (its ``episode_return_mean``, with the file as the source); an env without it keeps ``null`` and the reason."""
    out = json.loads(json.dumps(record))
    for env_id, entry in out["scores"].items():
        found = sorted((study / "batches").glob(f"{ENV_NAMES[env_id]}_opt_det_b1-*.metadata.json"))
        if not found:
            entry.update(ref_max_score=None, ref_max_score_reason=MAX_REASON)
            continue
        metadata = json.loads(found[-1].read_text())
        entry.pop("ref_max_score_reason", None)
        entry.update(ref_max_score=round(float(metadata["episode_return_mean"]), 3),
                     ref_max_score_protocol=MAX_PROTOCOL, ref_max_score_episodes=metadata.get("num_episodes"),
                     ref_max_score_source=f"results/{study.name}/batches/{found[-1].name}")
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--envs", default=",".join(ENVS))
    parser.add_argument("--out", default=str(OUT))
    parser.add_argument("--expert-only", action="store_true",
                        help="only (re)fill ref_max_score in --out from --expert-from's kept opt_det batches")
    parser.add_argument("--expert-from", type=Path, default=OUT.parent / "paper_exec",
                        help="the execution-batch study's results (default: results/paper_exec)")
    args = parser.parse_args(argv)
    if args.expert_only:
        record = expert_scores(json.loads(Path(args.out).read_text()), args.expert_from)
        Path(args.out).write_text(json.dumps(record, indent=2) + "\n")
        print(f"wrote {args.out}: " + ", ".join(f"{env} {s['ref_max_score']}" for env, s in record["scores"].items()))
        return
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

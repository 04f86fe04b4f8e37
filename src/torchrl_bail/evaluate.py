"""Run a trained policy: ``python -m torchrl_bail.evaluate RUN_DIR --episodes 10 [--seed S] [--video DIR]``.

Loads the run's ``policy.pt`` (``--best``: ``policy_best.pt``) with :func:`torchrl_bail.evaluation.policy.load_policy`
and
plays ``--episodes`` deterministic episodes with the training run's :class:`~torchrl_bail.evaluation.Evaluator`
(same env id, time limit and step budget as the run), printing ``mean ± std`` of the returns, then of the discounted
returns at FQE's gamma (``sum_t gamma^t r_t`` from each episode's start: the scale of ``python -m torchrl_bail.ope``'s
estimate).

``--reproduce`` replays the evaluation that scored the saved policy (:func:`replay_evaluation`): the run's seed,
episode count and step budget, and that evaluation's own episode seeds (the ``k``-th evaluation of a seed gets its
own; the Evaluator's stream is set to ``k``, the earlier evaluations are not played), so a deterministic policy
(BAIL, Progressive BAIL, BC, MARWIL, TD3+BC) scores exactly the return the run logged. BCQ and BEAR sample their
candidates from torch's random stream, which training also drew from, so their replayed return is a fresh draw,
not the logged one.

``--video DIR`` records one more episode per ``--episodes`` with gymnasium's ``RecordVideo`` (needs moviepy:
``pip install "torchrl_bail[video]"``; headless machines render through EGL, ``MUJOCO_GL=egl``).
``--export pt2|onnx|torchscript [--out FILE]`` writes a standalone policy file instead (see
:mod:`torchrl_bail.evaluation.policy` for which format supports which algorithm).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

__all__ = ["evaluate_policy", "record_video", "replay_evaluation", "main"]


def _run_settings(policy) -> dict:
    cfg = policy.record["config"]
    return {"env_id": policy.record["env_id"], "seed": int(cfg.get("seed", 0)),
            "episodes": int(cfg.get("eval", {}).get("episodes", 10)),
            "max_steps": int(cfg.get("eval", {}).get("max_steps", 1000)),
            "max_episode_steps": cfg.get("env", {}).get("max_episode_steps")}


def evaluate_policy(policy, *, episodes: int, seed: int, max_steps: int, max_episode_steps=None, env_id: str,
                    evaluation: int = 0):
    """The ``evaluation``-th evaluation (0-based) of ``policy`` by a fresh :class:`Evaluator` seeded ``seed``.

    The ``k``-th evaluation's episode seeds depend on ``(seed, k, episode)`` alone
    (:func:`~torchrl_bail.evaluation.episode_seed`), so the Evaluator's stream is set to ``evaluation``
    (:meth:`~torchrl_bail.evaluation.Evaluator.load_state_dict`, as a resumed run sets it) and that one evaluation
    is played: the same start states as the training run's, without playing the ``evaluation`` earlier ones.
    """
    from torchrl_bail.evaluation import Evaluator

    evaluator = Evaluator(env_id, episodes=episodes, seed=seed, max_steps=max_steps,
                          max_episode_steps=max_episode_steps, device="cpu")
    try:
        evaluator.load_state_dict({"evaluations": int(evaluation)})
        (result,) = evaluator.evaluate(policy)
        return result
    finally:
        evaluator.close()


def replay_evaluation(policy):
    """The evaluation that scored a saved ``policy`` (from :func:`~torchrl_bail.evaluation.policy.load_policy`),
    replayed: the
    run's env, seed, episode count and step budget (its recorded config) and the evaluation index its file records
    (``info["evaluation"]``; ``0`` when absent). Returns the :class:`~torchrl_bail.evaluation.EvalResult`: for a
    deterministic policy (BAIL, Progressive BAIL, BC, MARWIL, TD3+BC) its ``mean_return`` is the ``mean_return`` the
    file records, to the last digit; BCQ's and BEAR's candidates come from torch's random stream, so theirs is a
    fresh draw on the same start states."""
    evaluation = int(policy.record["info"].get("evaluation", 0))
    return evaluate_policy(policy, evaluation=evaluation, **_run_settings(policy))


def record_video(policy, directory: Path, *, episodes: int, seed: int, env_id: str, max_episode_steps=None) -> Path:
    """Plays ``episodes`` episodes (reset seeds ``seed``, ``seed + 1``...) into ``directory`` as MP4 files."""
    try:
        import moviepy  # noqa: F401  (gymnasium's RecordVideo writes through it)
    except ImportError:
        raise ImportError("--video needs the 'moviepy' package (gymnasium's RecordVideo writes through it): "
                          "pip install \"torchrl_bail[video]\"") from None
    os.environ.setdefault("MUJOCO_GL", "egl")
    import gymnasium as gym
    import torch
    from gymnasium.wrappers import RecordVideo

    from torchrl_bail.evaluation.policy import policy_actions

    kwargs = {} if max_episode_steps is None else {"max_episode_steps": int(max_episode_steps)}
    env = RecordVideo(gym.make(env_id, render_mode="rgb_array", **kwargs), str(directory),
                      episode_trigger=lambda _: True, name_prefix=env_id, disable_logger=True)
    try:
        for i in range(episodes):
            obs, _ = env.reset(seed=seed + i)
            done = False
            while not done:
                action = policy_actions(policy, torch.as_tensor(obs, dtype=torch.float32)[None])[0]
                obs, _, terminated, truncated, _ = env.step(action.numpy())
                done = terminated or truncated
    finally:
        env.close()
    return Path(directory)


def _sample_std(values) -> float:
    mean = sum(values) / len(values)
    return math.sqrt(sum((v - mean) ** 2 for v in values) / max(1, len(values) - 1))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m torchrl_bail.evaluate", description=__doc__.split("\n\n")[0])
    parser.add_argument("source", type=Path, help="a run directory or a policy file")
    parser.add_argument("--episodes", type=int, help="test episodes (default: the run's eval.episodes)")
    parser.add_argument("--seed", type=int, help="evaluation seed (default: the run's seed)")
    parser.add_argument("--best", action="store_true", help="the best-evaluated policy (policy_best.pt)")
    parser.add_argument("--reproduce", action="store_true",
                        help="replay the evaluation that scored the saved policy (the run's seed and settings)")
    parser.add_argument("--video", type=Path, metavar="DIR", help="also record the episodes as MP4 files in DIR")
    parser.add_argument("--export", choices=["pt2", "onnx", "torchscript"],
                        help="write a standalone policy file instead of evaluating")
    parser.add_argument("--out", type=Path, help="the exported file (default: beside the policy file)")
    args = parser.parse_args(argv)

    from torchrl_bail.evaluation.policy import (
        EXPORT_FORMATS,
        PolicyFileError,
        export_policy,
        load_policy,
        onnx_external_data,
    )

    try:
        policy = load_policy(args.source, best=args.best)
        if args.export:
            out = args.out or Path(policy.record["path"]).with_suffix(EXPORT_FORMATS[args.export])
            written = export_policy(policy, out, args.export)
            data = onnx_external_data(written)
            print(f"wrote {written}" + (f" and its weights {data} (keep the two files together)"
                                        if args.export == "onnx" and data.exists() else " (standalone)"))
            return 0
        settings = _run_settings(policy)
        if args.episodes is not None:
            if args.episodes < 1:
                parser.error(f"--episodes {args.episodes}: expected a positive number of episodes")
            settings["episodes"] = args.episodes
        if args.seed is not None:
            settings["seed"] = args.seed
        info = policy.record["info"]
        evaluation = int(info.get("evaluation", 0)) if args.reproduce else 0
        result = evaluate_policy(policy, evaluation=evaluation, **settings)
        print(f"{policy.record['algo']} on {settings['env_id']}: return {result.mean_return:.2f} ± "
              f"{_sample_std(result.returns):.2f} (sample std) over {len(result.returns)} episodes (seed "
              f"{settings['seed']})")
        print(f"discounted return (gamma {result.gamma}, the scale of an FQE estimate): "
              f"{result.mean_discounted_return:.2f} ± {_sample_std(result.discounted_returns):.2f} (sample std)")
        if args.reproduce and "mean_return" in info:
            print(f"logged by the run at evaluation {evaluation} (iteration {info.get('iteration')}): "
                  f"{info['mean_return']:.2f}")
        if args.video:
            folder = record_video(policy, args.video, episodes=settings["episodes"], seed=settings["seed"],
                                  env_id=settings["env_id"], max_episode_steps=settings["max_episode_steps"])
            print(f"videos in {folder}")
    except (PolicyFileError, ImportError, ValueError) as err:
        print(f"torchrl_bail.evaluate: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())

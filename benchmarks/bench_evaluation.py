"""Evaluation throughput: the library's ``Evaluator`` against a plain gymnasium loop playing the same episodes.

    python benchmarks/bench_evaluation.py [--env Hopper-v5] [--episodes 10] [--max-steps 1000] [--repeats 5]

Both sides play the same ``episodes`` deterministic episodes (same reset seeds, same time limit) with the same
TensorDict actor (400-300 deterministic actor, one call per step on the stacked observations), interleaved in one
process; the plain loop is what a user would write by hand: ``gymnasium.make`` envs, ``np.stack`` of the
observations, ``env.step`` per running episode. The episodes must score identical returns (checked). Unhealthy
termination is switched off (``terminate_when_unhealthy=False``) so that every episode runs its full
``--max-steps`` like a trained policy's does. ``ratio`` = Evaluator rate / plain rate (1.0 = no overhead;
the issue asks for >= 1/1.3 = 0.77). ``--serial-env`` adds the previous implementation (TorchRL ``SerialEnv``
rollout) for reference. The run's record goes to ``results/benchmarks/bench_evaluation.json`` (``--json``).
"""

from __future__ import annotations

import argparse
import os
import sys

os.environ.setdefault("RL_WARNINGS", "0")

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from _bench import Record, add_record_argument, compare, print_table  # noqa: E402
from tensordict import TensorDict  # noqa: E402
from torchrl.envs.utils import ExplorationType, set_exploration_type  # noqa: E402

from torchrl_bail.evaluation import Evaluator, episode_seed  # noqa: E402
from torchrl_bail.modules import make_deterministic_actor  # noqa: E402


class PlainLoop:
    """The hand-written twin: ``episodes`` gymnasium envs, one batched policy call per step, first-done returns."""

    def __init__(self, env_id: str, episodes: int, seed: int, max_steps: int, env_kwargs: dict):
        self.envs = [gym.make(env_id, **env_kwargs) for _ in range(episodes)]
        self.seed, self.max_steps, self.evaluations = seed, max_steps, 0

    @torch.no_grad()
    def __call__(self, policy) -> list[float]:
        n = len(self.envs)
        obs = [env.reset(seed=episode_seed(self.seed, self.evaluations, i))[0] for i, env in enumerate(self.envs)]
        self.evaluations += 1
        returns, running = [0.0] * n, [True] * n
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            for _ in range(self.max_steps):
                if not any(running):
                    break
                x = torch.as_tensor(np.stack(obs), dtype=torch.float32)
                action = policy(TensorDict({"observation": x}, batch_size=[n]))["action"].numpy()
                for i, env in enumerate(self.envs):
                    if running[i]:
                        obs[i], r, terminated, truncated, _ = env.step(action[i])
                        returns[i] += r
                        running[i] = not (terminated or truncated)
        return returns

    def close(self):
        for env in self.envs:
            env.close()


class SerialEnvEvaluation:
    """The previous implementation: TorchRL ``SerialEnv`` rollout, returns read from ``RewardSum`` at first done."""

    def __init__(self, env_id: str, episodes: int, seed: int, max_steps: int, env_kwargs: dict):
        from torchrl.envs import Compose, DoubleToFloat, GymEnv, RewardSum, SerialEnv, StepCounter, TransformedEnv

        def make():
            return TransformedEnv(GymEnv(env_id, **env_kwargs), Compose(DoubleToFloat(), RewardSum(), StepCounter()))

        self.env = SerialEnv(episodes, make)
        self.env.set_seed(seed)
        self.max_steps = max_steps

    @torch.no_grad()
    def __call__(self, policy):
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            ro = self.env.rollout(self.max_steps, policy, break_when_any_done=False, break_when_all_done=True)
        done = ro["next", "done"].squeeze(-1)
        first = torch.where(done.any(-1), done.float().argmax(-1), torch.full((done.shape[0],), done.shape[1] - 1))
        return ro["next", "episode_reward"][torch.arange(done.shape[0]), first].squeeze(-1).tolist()

    def close(self):
        self.env.close()


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--env", default="Hopper-v5")
    p.add_argument("--episodes", type=int, default=10)
    p.add_argument("--max-steps", type=int, default=1000)
    p.add_argument("--repeats", type=int, default=5, help="interleaved rounds (the median is reported)")
    p.add_argument("--serial-env", action="store_true", help="also time the previous SerialEnv evaluator")
    add_record_argument(p, __file__)
    args = p.parse_args(argv)
    record = Record(__file__, args.json, reference="plain gymnasium loop", settings=vars(args))
    env_kwargs = {"max_episode_steps": args.max_steps, "terminate_when_unhealthy": False}
    seed = 0
    evaluator = Evaluator(args.env, episodes=args.episodes, seed=seed, max_steps=args.max_steps,
                          env_kwargs={"terminate_when_unhealthy": False}, max_episode_steps=args.max_steps)
    plain = PlainLoop(args.env, args.episodes, seed, args.max_steps, env_kwargs)
    torch.manual_seed(0)
    actor = make_deterministic_actor(evaluator.obs_dim, evaluator.action_spec)

    (result,), reference = evaluator.evaluate(actor), plain(actor)
    if result.returns != reference or result.failures:
        raise SystemExit(f"Evaluator and the plain loop disagree: {result.returns} vs {reference}")
    steps = sum(result.lengths)
    name = f"{args.episodes} x {args.max_steps}-step {args.env} episodes"
    rows = [compare(name, lambda: evaluator.evaluate(actor), lambda: plain(actor), n=1, repeats=args.repeats,
                    unit="evaluations/s")]
    if args.serial_env:
        serial = SerialEnvEvaluation(args.env, args.episodes, seed, args.max_steps, env_kwargs)
        row = compare("previous SerialEnv evaluator", lambda: serial(actor), lambda: plain(actor), n=1,
                      repeats=args.repeats, unit="evaluations/s")
        rows.append(row)
        serial.close()
    for row in rows:  # evaluations/s -> env steps/s (both sides play the same steps), every round too
        row.update(torchrl_bail=row["torchrl_bail"] * steps, bare=row["bare"] * steps, unit="env steps/s",
                   wall_time_ratio=1 / row["ratio"], steps_per_evaluation=steps,
                   rounds={side: [r * steps for r in values] for side, values in row["rounds"].items()})
    print_table(rows, "Evaluation: torchrl_bail vs a plain gymnasium loop (ratio = torchrl_bail / plain)")
    for row in rows:
        print(f"{row['name']}: wall time {row['wall_time_ratio']:.2f}x the plain loop's")
    record.write(rows)
    evaluator.close()
    plain.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())

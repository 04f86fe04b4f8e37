"""BC in lockstep: torchrl_bail's and d3rlpy 2.8.1's behaviour cloning from the same initial weights on the same
mini-batches. Do the two follow one trajectory?

    OMP_NUM_THREADS=1 python benchmarks/bench_d3rlpy_lockstep.py --python .d3venv/bin/python \\
        --batch hopper_ddpg05_b1 --batch-overrides preset=quick --seeds 1,2,3 --json results/d3rlpy/lockstep.json

``bench_d3rlpy_returns.py`` compares the two libraries by their spread over seeds, since each draws its own initial
weights and mini-batches. This script takes both draws away. For each seed, our BC is built from the composed config
(``algo=bc``, ``--preset``, the seed) and d3rlpy's BC in its worker with the matched constants; d3rlpy's policy is
given our initial parameters. Both then run the run's number of updates on the same mini-batches: row ``u`` of an
index array drawn by NumPy's generator seeded with the seed (with replacement, over the batch's transitions). It
prints per seed:

* both sides' imitation loss at the first, middle and last update, and their largest relative difference;
* the largest difference between the two final policies' actions over the batch's first 5000 observations;
* each final policy's mean return over the same ``eval.episodes`` deterministic episodes (the start states of the
  run's first :class:`~torchrl_bail.evaluation.Evaluator` call).

Float rounding alone should part the two here (d3rlpy's per-tensor Adam against our fused one, another summation
order), and slowly. A bug on either side (another loss, network or optimizer step) would show as losses that part
from the first updates.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np  # noqa: E402
import torch  # noqa: E402
from _bench import Record, machine
from bench_d3rlpy_returns import (
    D3rlpyRun,
    add_run_arguments,
    compose_run,
    d3rlpy_arrays,
    env_name,
    matched_constants,
    schedule,
)
from tensordict import TensorDict  # noqa: E402

from torchrl_bail.algorithms import build_algorithm  # noqa: E402
from torchrl_bail.datasets import resolve_batch  # noqa: E402
from torchrl_bail.evaluation import Evaluator  # noqa: E402
from torchrl_bail.modules import action_spec_from_bounds  # noqa: E402
from torchrl_bail.train import seed_everything  # noqa: E402

#: the observations both final policies act on for the action comparison
COMPARED_OBSERVATIONS = 5000


def lockstep(python: str, cfg, batch, arrays: Path, scratch: Path, threads: int) -> dict:
    """One seed of the comparison (see the module doc)."""
    seed = int(cfg.seed)
    data = TensorDict({"observation": batch.data["observation"], "action": batch.data["action"]},
                      batch.data.batch_size)
    updates, _ = schedule(cfg)
    seed_everything(seed)
    spec = action_spec_from_bounds(batch.action_low, batch.action_high)
    ours = build_algorithm(cfg.algo, batch.obs_dim, spec, torch.device("cpu"))
    init, stream = scratch / f"init_{seed}.npz", scratch / f"stream_{seed}.npz"
    np.savez(init, **{f"p{i}": p.detach().numpy() for i, p in enumerate(ours.actor.parameters())})
    index = np.random.default_rng(seed).integers(0, len(data), (updates, int(cfg.algo.batch_size)))
    np.savez(stream, observations=data["observation"].numpy(), actions=data["action"].numpy(), index=index)
    peer = D3rlpyRun(python, matched_constants(cfg), algo="bc", seed=seed, dataset=arrays, threads=threads)

    def final_return(policy) -> float:  # a fresh evaluator each: both policies meet the same start states
        evaluator = Evaluator(cfg.env.id, episodes=cfg.eval.episodes, seed=seed, max_steps=cfg.eval.max_steps,
                              max_episode_steps=cfg.env.get("max_episode_steps"))
        try:
            return evaluator.evaluate(policy)[0].mean_return
        finally:
            evaluator.close()

    try:
        if peer._ask(f"set_policy {init}").strip() != "ok":
            raise SystemExit("the d3rlpy worker did not take our initial parameters")
        theirs_loss = json.loads(peer._ask(f"update_on {stream}"))
        ours_loss = [float(ours.update(data[torch.from_numpy(rows)])["loss_bc"]) for rows in index]
        probe = data[:COMPARED_OBSERVATIONS].select("observation")
        with torch.no_grad():
            ours_actions = ours.policy(probe.clone())["action"]
        theirs_actions = peer(probe.clone())["action"]
        returns = {"torchrl_bail": final_return(ours.policy), "d3rlpy": final_return(peer)}
    finally:
        peer.close()
    ours_loss, theirs_loss = np.asarray(ours_loss), np.asarray(theirs_loss)
    relative = np.abs(ours_loss - theirs_loss) / np.maximum(np.abs(ours_loss), 1e-12)
    picks = sorted({0, updates // 2, updates - 1})
    return {"seed": seed, "updates": updates, "loss_at": {int(u): [float(ours_loss[u]), float(theirs_loss[u])]
                                                          for u in picks},
            "loss_max_relative_difference": float(relative.max()),
            "loss_max_relative_difference_first_100": float(relative[:100].max()),
            "action_max_abs_difference": float((ours_actions - theirs_actions).abs().max()),
            "returns": returns}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--python", required=True, help="the interpreter of d3rlpy's virtual environment")
    parser.add_argument("--batch", required=True, help="a catalogue batch name (hopper_ddpg05_b1) or a batch path")
    parser.add_argument("--batch-overrides", nargs="*", default=[],
                        help="the collect overrides that name the cached batch (e.g. preset=quick)")
    add_run_arguments(parser, __file__)
    args = parser.parse_args()
    record = Record(__file__, args.json, reference="d3rlpy 2.8.1 (BC in lockstep)", settings=vars(args))
    torch.set_num_threads(args.threads)
    try:
        batch = resolve_batch(args.batch, overrides=args.batch_overrides)
    except (FileNotFoundError, ValueError) as err:
        raise SystemExit(f"bench_d3rlpy_lockstep: {err}") from None
    env = args.env or batch.metadata.get("env_name") or env_name(batch.env_id)
    rows = []
    print(f"BC in lockstep on {args.batch} ({machine()})")
    with tempfile.TemporaryDirectory(prefix="bench_d3rlpy_lockstep-") as tmp:
        arrays = Path(tmp) / "batch.npz"
        np.savez(arrays, **d3rlpy_arrays(batch))
        for seed in (int(s) for s in args.seeds.split(",")):
            cfg = compose_run(batch.path, env, "bc", seed, args.preset, args.overrides)
            row = lockstep(args.python, cfg, batch, arrays, Path(tmp), args.threads)
            rows.append({"batch": args.batch, **row})
            losses = "  ".join(f"update {u + 1}: {a:.5f} / {b:.5f}" for u, (a, b) in row["loss_at"].items())
            print(f"seed {seed}: loss ours / d3rlpy  {losses}; largest relative difference "
                  f"{row['loss_max_relative_difference']:.1e} (first 100 updates "
                  f"{row['loss_max_relative_difference_first_100']:.1e}); final actions differ by at most "
                  f"{row['action_max_abs_difference']:.1e}; return {row['returns']['torchrl_bail']:.1f} / "
                  f"{row['returns']['d3rlpy']:.1f}", flush=True)
    record.write(rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""BC, BCQ and BEAR trained by torchrl_bail and by d3rlpy 2.8.1 on the same batch: both libraries' final returns.

Usage (d3rlpy 2.8.1 pins gymnasium 1.0, so it lives in its own virtual environment; ``bench_d3rlpy.py`` says how
to make it)::

    # the results study's Hopper batches (50k transitions, B1), 3 seeds, the study's schedules
    OMP_NUM_THREADS=1 python benchmarks/bench_d3rlpy_returns.py --python .d3venv/bin/python \\
        --batch hopper_ddpg05_b1 --batch hopper_sac_b1 --batch-overrides preset=study --seeds 1,2,3 --preset study

    # a smoke run on any batch (a catalogue name or a path) at a tiny scale
    python benchmarks/bench_d3rlpy_returns.py --python .d3venv/bin/python --batch /path/to/batch --seeds 1 \\
        --overrides algo.epochs=0.002 eval.every_epochs=0.001 eval.episodes=2

For each batch, algorithm and seed, **torchrl_bail** trains through its own pipeline (``torchrl_bail.train.run``
with ``dataset=<the batch>``, ``algo=``, ``preset=``, ``seed=``, the ``--overrides``) and **d3rlpy** trains in
a subprocess (``_d3rlpy_worker.py`` under ``--python``, ``d3rlpy.seed(seed)``) with the constants read from the
same composed config: network sizes, batch size, learning rates, gamma, tau, lambda, perturbation range, KL weight,
sample counts, MMD kernel, threshold and warm start, and the same number of updates. Both are evaluated by the
same :class:`~torchrl_bail.evaluation.Evaluator` (this package's env, ``eval.episodes`` deterministic episodes with
the run seed's reset seeds, ``eval.max_steps``), at the same updates (every ``eval.every_epochs`` and at the end),
d3rlpy's policy through its ``predict`` (greedy action); each side's final return is the mean of its last
``eval.final_window`` evaluations, as in ``summary.json``.

The record (default ``results/d3rlpy/bench_d3rlpy_returns.json``, written after every row) holds per row both
final returns and both curves: ``torchrl_bail_evaluations`` (read from our run's CSV log) and
``d3rlpy_evaluations``, taken at ``evaluated_at_updates``. ``benchmarks/render_records.py`` renders the Benchmarks
page's tables from such records.

The data reach d3rlpy as the batch's own transitions: an episode that ends without a termination gets one padding
row holding its final next observation (flagged a timeout), so d3rlpy's transitions are exactly the batch's (its
``MDPDataset`` takes the next observation from the next row and drops a timeout episode's last row); a terminated
episode's next observation is never read by either side.

Constants that cannot be matched exactly (d3rlpy 2.8.1 source, ``algos/qlearning``):

* **BEAR** is d3rlpy's SAC-based variant, not the authors' version 0 this package implements: a squashed-Gaussian
  actor with log sigma clamped to [-20, 2] (ours: unclamped), an entropy term (switched off here as far as d3rlpy
  allows: temperature 1e-8, not learnt), no target actor, SAC's one-sample actor loss ``min_j Q_j`` (ours:
  ``min_j mean_m Q_j`` over the 5 MMD samples), the Lagrange multiplier starting at alpha = 1 (ours:
  ``log alpha ~ N(0, 1)``), and its warm start skips only the actor's Q term (ours too, the critics learn
  throughout).
* **BCQ**: d3rlpy's BCQ builds its VAE with the encoder's log sigma clamped to [-4, 15], as ours and the authors'
  (``algos/qlearning/bcq.py``: ``min_logstd=-4.0, max_logstd=15.0``; the [-20, 2] default of its builders is not
  used here); latent size 2|A| and latent clip 0.5 are the same. Its decoder head differs: ``VAEDecoder.forward``
  returns the *linear* output when ``with_squash`` is true, its default, and ``tanh`` only when it is false (the
  branches were swapped in d3rlpy's commit 4abdbd3f, 2023-08, in every release from 2.1.0), so its candidates
  are bounded only by the later clamp to the action bounds; ours and the authors' apply ``tanh``.
* **BC**: same network, loss (MSE), optimizer; nothing differs.
* **Sampling and seeds**: each library draws its own mini-batches and initial weights from its own generators, so
  the two are compared by their spread over seeds, never run by run.
* **Optimizers**: both Adam with torch's defaults (d3rlpy per-tensor, ours fused: equal up to float32 rounding).
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np  # noqa: E402
import torch  # noqa: E402
from _bench import Record, add_record_argument, machine
from bench_d3rlpy import start_worker
from hydra import compose, initialize_config_dir  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402
from tensordict import TensorDict  # noqa: E402

from torchrl_bail import config_dir  # noqa: E402
from torchrl_bail.datasets import resolve_batch  # noqa: E402
from torchrl_bail.evaluation import Evaluator  # noqa: E402
from torchrl_bail.reports.plots import read_eval_curve  # noqa: E402
from torchrl_bail.train import run  # noqa: E402

ALGOS = ("bc", "bcq", "bear")
#: d3rlpy's BEAR always has SAC's entropy term; this temperature (not learnt) makes it negligible
D3RLPY_BEAR_TEMPERATURE = 1e-8


def d3rlpy_arrays(batch) -> dict[str, np.ndarray]:
    """The batch's transitions as d3rlpy ``MDPDataset`` arrays (see the module doc: one padding row per episode
    that does not end in a termination, holding its final next observation)."""
    data = batch.data
    obs, act = data["observation"].numpy(), data["action"].numpy()
    nxt, rew = data["next", "observation"].numpy(), data["next", "reward"].numpy()
    term = data["next", "terminated"].numpy()[:, 0]
    episode = data["episode"].numpy()
    last = np.r_[episode[1:] != episode[:-1], True]
    pad = last & ~term  # truncated, or the batch's unfinished final episode
    rows = np.arange(len(obs)) + np.cumsum(np.r_[0, pad[:-1]])  # where each transition lands
    n = len(obs) + int(pad.sum())
    out = {"observations": np.zeros((n, obs.shape[1]), np.float32), "actions": np.zeros((n, act.shape[1]), np.float32),
           "rewards": np.zeros((n, 1), np.float32), "terminals": np.zeros(n, np.float32),
           "timeouts": np.zeros(n, np.float32)}
    out["observations"][rows], out["actions"][rows], out["rewards"][rows] = obs, act, rew
    out["terminals"][rows[term]] = 1.0
    pads = rows[pad] + 1
    out["observations"][pads] = nxt[pad]
    out["actions"][pads] = act[pad]  # never used: d3rlpy drops a timeout episode's last row
    out["timeouts"][pads] = 1.0
    return out


def matched_constants(cfg) -> dict:
    """The d3rlpy worker's constants, read from the composed ``algo`` config (one source for both sides)."""
    a = cfg.algo
    if a.name == "bc":
        return {"bc_hidden": list(a.policy.hidden), "lr": {"bc": a.policy.lr}, "bc_batch": a.batch_size}
    out = {"actor_hidden": list(a.actor.hidden), "critic_hidden": list(a.critic.hidden),
           "vae_hidden": list(a.vae.hidden), "batch": a.batch_size, "bc_batch": a.batch_size,
           "lr": {"actor": a.actor.lr, "critic": a.critic.lr, "vae": a.vae.lr}, "gamma": a.gamma, "tau": a.tau,
           "lmbda": a.lmbda, "kl_weight": a.kl_weight, "n_target": a.num_samples}
    if a.vae.latent_per_action != 2 or a.latent_clip != 0.5:
        raise SystemExit("d3rlpy's VAE has latent size 2|A| and latent clip 0.5: keep algo.vae.latent_per_action=2 "
                         "and algo.latent_clip=0.5")
    if a.name == "bcq":
        out["phi"] = a.phi
    else:
        out.update(n_match=a.num_samples_match, kernel_sigma=a.kernel_sigma, epsilon=a.epsilon,
                   warmup=a.warm_start_updates, temperature=D3RLPY_BEAR_TEMPERATURE)
        out["lr"]["alpha"] = a.lagrange_lr
    return out


def schedule(cfg) -> tuple[int, int]:
    """``(updates, evaluation interval)`` as :func:`torchrl_bail.training.trainer.train` counts them for these
    algorithms
    (one mini-batch of ``batch_size`` samples per update); checked against our run's ``summary.json``."""
    per_update = cfg.algo.batch_size
    updates = max(1, math.ceil(cfg.algo.epochs * cfg.samples_per_epoch / per_update))
    return updates, max(1, round(cfg.eval.every_epochs * cfg.samples_per_epoch / per_update))


class D3rlpyRun:
    """One d3rlpy algorithm in ``_d3rlpy_worker.py``: ``update(n)`` trains; calling it acts (an Evaluator policy)."""

    def __init__(self, python: str, constants: dict, *, algo: str, seed: int, dataset: Path, threads: int) -> None:
        cfg = {**constants, "mode": "train", "algo": algo, "seed": seed, "dataset": str(dataset)}
        self.proc, self.info = start_worker(python, cfg, threads)
        self.cpu_s = 0.0

    def _ask(self, *lines: str) -> str:
        self.proc.stdin.write("".join(f"{line}\n" for line in lines))
        self.proc.stdin.flush()
        return self.proc.stdout.readline()

    def update(self, n: int) -> None:
        self.cpu_s += float(self._ask(f"update {n}"))

    def __call__(self, td: TensorDict) -> TensorDict:
        obs = td["observation"]
        actions = json.loads(self._ask("act", json.dumps(obs.reshape(-1, obs.shape[-1]).tolist())))
        td["action"] = torch.tensor(actions, dtype=torch.float32).reshape(*obs.shape[:-1], -1)
        return td

    def close(self) -> None:
        self._ask("quit")
        self.proc.wait()


def env_name(env_id: str) -> str:
    for conf in sorted((config_dir() / "env").glob("*.yaml")):
        if OmegaConf.load(conf).id == env_id:
            return conf.stem
    raise SystemExit(f"no conf/env file has id {env_id}; pass --env NAME")


def compose_run(batch_path: Path, env: str, algo: str, seed: int, preset: str, overrides: list[str]):
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        return compose("config", overrides=[f"dataset={batch_path}", f"env={env}", f"algo={algo}", f"preset={preset}",
                                            f"seed={seed}", "progress=false", "checkpoint.enabled=false",
                                            "resume=false", *overrides])


def d3rlpy_final_return(python: str, cfg, arrays: Path, threads: int, decoder_tanh: bool = False) -> dict:
    updates, interval = schedule(cfg)
    constants = {**matched_constants(cfg), **({"decoder_tanh": True} if decoder_tanh else {})}
    peer = D3rlpyRun(python, constants, algo=cfg.algo.name, seed=int(cfg.seed), dataset=arrays, threads=threads)
    evaluator = Evaluator(cfg.env.id, episodes=cfg.eval.episodes, seed=int(cfg.seed), max_steps=cfg.eval.max_steps,
                          max_episode_steps=cfg.env.get("max_episode_steps"))
    returns, done = [], 0
    try:
        points = sorted({*range(interval, updates + 1, interval), updates})
        for point in points:
            peer.update(point - done)
            done = point
            returns.append(evaluator.evaluate(peer)[0].mean_return)
    finally:
        evaluator.close()
        peer.close()
    window = returns[-cfg.eval.final_window:]
    return {"final_return": sum(window) / len(window), "evaluations": returns, "evaluated_at": points,
            "updates": updates,
            "train_cpu_s": peer.cpu_s, "versions": {k: peer.info[k] for k in ("d3rlpy", "torch")},
            "transitions": peer.info["transitions"]}


def add_run_arguments(parser: argparse.ArgumentParser, script: str) -> None:
    """The options both sides' runs share (env, seeds, preset, overrides, threads, the JSON record of ``script``)."""
    parser.add_argument("--env", default=None, help="conf/env name (default: from the batch's env id)")
    parser.add_argument("--seeds", default="1,2,3")
    parser.add_argument("--preset", default="study", help="the training preset of both sides (schedules, eval)")
    parser.add_argument("--overrides", nargs="*", default=[], help="more training overrides, applied to both sides")
    parser.add_argument("--threads", type=int, default=1, help="torch threads on both sides")
    add_record_argument(parser, script)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--python", required=True, help="the interpreter of d3rlpy's virtual environment")
    parser.add_argument("--batch", action="append", required=True,
                        help="a catalogue batch name (hopper_ddpg05_b1) or a batch/Minari/D4RL path; repeatable")
    parser.add_argument("--batch-overrides", nargs="*", default=[],
                        help="the collect overrides that name the cached batch (e.g. preset=quick)")
    parser.add_argument("--algos", default=",".join(ALGOS), help="comma-separated subset of bc,bcq,bear")
    parser.add_argument("--d3rlpy-decoder-tanh", action="store_true",
                        help="patch d3rlpy's VAE decoder to apply tanh to its output, as the authors' BCQ does "
                             "(d3rlpy >= 2.1 leaves it linear; _d3rlpy_worker.restore_decoder_tanh); recorded in "
                             "each row as d3rlpy_patch")
    add_run_arguments(parser, __file__)
    # beside the other returns records, not among results/benchmarks' ratio records (render_records.D3RLPY_TABLES)
    parser.set_defaults(json="results/d3rlpy/bench_d3rlpy_returns.json")
    args = parser.parse_args()
    record = Record(__file__, args.json, reference="d3rlpy 2.8.1 (final returns)", settings=vars(args))
    torch.set_num_threads(args.threads)
    seeds = [int(s) for s in args.seeds.split(",")]
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_d3rlpy_returns-") as tmp:
        for name in args.batch:
            try:
                batch = resolve_batch(name, overrides=args.batch_overrides)
            except (FileNotFoundError, ValueError) as err:
                raise SystemExit(f"bench_d3rlpy_returns: {err}") from None
            env = args.env or batch.metadata.get("env_name") or env_name(batch.env_id)
            arrays = Path(tmp) / f"{Path(str(batch.path)).name}.npz"
            np.savez(arrays, **d3rlpy_arrays(batch))
            label = batch.metadata.get("name", Path(str(batch.path)).name)
            for algo in args.algos.split(","):
                for seed in seeds:
                    cfg = compose_run(batch.path, env, algo, seed, args.preset, args.overrides)
                    run_dir = Path(tmp) / f"{label}_{algo}_{seed}"
                    (ours,) = run(cfg, run_dir)
                    ours_curve = read_eval_curve(run_dir)
                    peer = d3rlpy_final_return(args.python, cfg, arrays, args.threads, args.d3rlpy_decoder_tanh)
                    if (ours["iterations"] != peer["updates"] or peer["transitions"] != batch.num_transitions
                            or ours_curve is None or len(ours_curve[1]) != len(peer["evaluations"])):
                        raise SystemExit(f"{label} {algo} seed {seed}: the two sides differ in updates "
                                         f"({ours['iterations']} vs {peer['updates']}), transitions "
                                         f"({batch.num_transitions} vs {peer['transitions']}) or evaluations "
                                         f"({'no CSV log' if ours_curve is None else len(ours_curve[1])} vs "
                                         f"{len(peer['evaluations'])})")
                    row = {"batch": label, "algo": algo, "seed": seed, "torchrl_bail": ours["final_return"],
                           "d3rlpy": peer["final_return"], "updates": peer["updates"],
                           "evaluated_at_updates": peer["evaluated_at"],
                           "torchrl_bail_evaluations": [float(r) for r in ours_curve[1]],
                           "d3rlpy_evaluations": peer["evaluations"], "d3rlpy_versions": peer["versions"],
                           "torchrl_bail_wall_s": ours["wall_time_s"], "d3rlpy_train_cpu_s": peer["train_cpu_s"],
                           "d3rlpy_patch": "VAE decoder tanh restored" if args.d3rlpy_decoder_tanh else None}
                    rows.append(row)
                    record.write(rows)  # after every row: a long comparison stopped midway keeps its rows
                    print(f"{label:<24} {algo:<5} seed {seed}: torchrl_bail {row['torchrl_bail']:8.1f}   "
                          f"d3rlpy {row['d3rlpy']:8.1f}   ({row['updates']} updates)", flush=True)
    print(f"\nfinal return, mean +- sample std over seeds {args.seeds} ({machine()}; d3rlpy "
          f"{rows[0]['d3rlpy_versions']['d3rlpy']} with torch {rows[0]['d3rlpy_versions']['torch']})")
    print(f"{'batch':<24} {'algo':<5} {'torchrl_bail':>20} {'d3rlpy':>20}")

    def cell(group, key):
        values = [r[key] for r in group]
        spread = statistics.stdev(values) if len(values) > 1 else 0.0
        return f"{statistics.mean(values):.1f} +- {spread:.1f}"

    for label in dict.fromkeys(r["batch"] for r in rows):
        for algo in dict.fromkeys(r["algo"] for r in rows):
            group = [r for r in rows if r["batch"] == label and r["algo"] == algo]
            print(f"{label:<24} {algo:<5} {cell(group, 'torchrl_bail'):>20} {cell(group, 'd3rlpy'):>20}")
    record.write(rows)


if __name__ == "__main__":
    sys.exit(main())

"""Train an offline RL algorithm on a batch: ``python -m torchrl_bail.train +exp=hopper_ddpg05``.

Data flows one way: batch (generated on demand, or imported from ``dataset=<path>``) -> Monte-Carlo returns
-> the algorithm's ``prepare`` (BAIL: envelope + best-action filter) -> the training loop -> evaluation.
The run directory receives the resolved ``config.yaml``, CSV scalars (``logs/``), ``learning_curve.png``,
``envelope.png`` (BAIL), ``checkpoint.pt``, ``policy.pt`` (the final policy), ``policy_best.pt`` (the
best-evaluated one; :func:`torchrl_bail.load_policy` rebuilds either) and ``summary.json``.
"""

from __future__ import annotations

import logging
import os
import random
import sys
import time
from pathlib import Path
from typing import Any

import hydra
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from torchrl_bail import config_dir
from torchrl_bail.algorithms import ALGORITHMS, PrepareContext, build_algorithm
from torchrl_bail.data import monte_carlo_returns
from torchrl_bail.evaluation import Evaluator
from torchrl_bail.io import write_json_atomic
from torchrl_bail.plots import plot_learning_curve
from torchrl_bail.policy import save_policy
from torchrl_bail.trainer import train

__all__ = ["run", "main", "ConfigError"]

log = logging.getLogger("torchrl_bail")


class ConfigError(ValueError):
    """A configuration value is missing or out of range; the message names the key."""


def validate_config(cfg: DictConfig) -> None:
    """Checks the values every run depends on, before any work starts."""

    def need(cond: bool, key: str, expected: str) -> None:
        if not cond:
            raise ConfigError(f"config key {key} = {OmegaConf.select(cfg, key)!r}: expected {expected}")

    need(cfg.algo.name in ALGORITHMS, "algo.name", f"one of {sorted(ALGORITHMS)}")
    need(0 < cfg.returns.gamma <= 1, "returns.gamma", "a discount in (0, 1]")
    need(cfg.returns.horizon >= 1, "returns.horizon", "an integer >= 1")
    need(cfg.returns.augment in ("gain", "none", "oracle"), "returns.augment", "gain | none | oracle")
    if cfg.returns.augment == "oracle" and not cfg.get("dataset"):
        need(bool(OmegaConf.select(cfg, "batch.oracle.enabled", default=False)), "returns.augment",
             "gain | none, or oracle together with batch.oracle.enabled=true (oracle returns come from an oracle "
             "batch's real continuations)")
    need(cfg.samples_per_epoch >= 1, "samples_per_epoch", "a positive integer")
    need(cfg.eval.episodes >= 1, "eval.episodes", "a positive integer")
    need(cfg.eval.every_epochs > 0, "eval.every_epochs", "a positive number of epochs")
    need(cfg.eval.final_window >= 1, "eval.final_window", "a positive integer")
    need(cfg.algo.batch_size >= 1, "algo.batch_size", "a positive integer")
    need(cfg.algo.epochs > 0, "algo.epochs", "a positive number of epochs")
    need(cfg.device in ("cpu", "cuda", "auto") or str(cfg.device).startswith("cuda:"), "device",
         "cpu | cuda | cuda:N | auto")
    if str(cfg.device).startswith("cuda"):
        need(torch.cuda.is_available(), "device", "a CUDA device, but torch sees none (use device=cpu or auto)")


def _device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def seed_everything(seed: int) -> torch.Generator:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)
    return torch.Generator().manual_seed(seed)


def load_training_batch(cfg: DictConfig):
    """The batch to train on: ``dataset=<path>`` (imported/native) or the generated one for env x batch."""
    if cfg.get("dataset"):
        from torchrl_bail.data.importers import import_dataset

        def absolute(p) -> str:
            return hydra.utils.to_absolute_path(str(Path(str(p)).expanduser()))

        data_dir = cfg.get("data_dir")
        return import_dataset(Path(absolute(cfg.dataset)), env_id=cfg.env.id,
                              data_dir=absolute(data_dir) if data_dir else None)
    from torchrl_bail.data.collection import ensure_batch

    return ensure_batch(cfg, progress=cfg.progress)


def _make_logger(cfg: DictConfig, run_dir: Path):
    from torchrl.record.loggers import get_logger

    return get_logger(cfg.logger.backend, logger_name=str(run_dir), experiment_name="logs",
                      **({"project": cfg.logger.project} if cfg.logger.backend == "wandb" else {}))


def run(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """Runs one training job described by ``cfg`` into ``run_dir`` and returns its summary."""
    start = time.perf_counter()
    validate_config(cfg)
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    OmegaConf.save(cfg, run_dir / "config.yaml", resolve=True)
    device = _device(cfg.device)
    generator = seed_everything(int(cfg.seed))

    batch = load_training_batch(cfg)
    evaluator = Evaluator(cfg.env.id, episodes=cfg.eval.episodes, seed=int(cfg.seed), max_steps=cfg.eval.max_steps,
                          max_episode_steps=cfg.env.get("max_episode_steps"), device="cpu")
    try:
        obs_dim, act_dim = evaluator.obs_dim, evaluator.action_spec.shape[-1]
        if (batch.obs_dim, batch.act_dim) != (obs_dim, act_dim):
            raise ConfigError(
                f"batch {batch.path} has observation/action sizes ({batch.obs_dim}, {batch.act_dim}) but env "
                f"{cfg.env.id} has ({obs_dim}, {act_dim}); pick the matching env= for this dataset"
            )
        data = batch.data
        returns = monte_carlo_returns(data, gamma=cfg.returns.gamma, horizon=cfg.returns.horizon,
                                      augment=cfg.returns.augment)
        data = data.select("observation", "action", "next", "episode").clone(False)
        data.set("return", returns)

        logger = _make_logger(cfg, run_dir)
        algorithm = build_algorithm(cfg.algo, obs_dim, evaluator.action_spec, device)
        ctx = PrepareContext(run_dir=run_dir, logger=logger, generator=generator, progress=cfg.progress)
        train_data = algorithm.prepare(data, ctx)
        best_policy: dict[str, Any] = {}

        def keep_best(point, index: int) -> None:
            taken = {"iteration": point.iteration, "epoch": point.epoch, "evaluation": index,
                     "mean_return": point.mean_return}
            save_policy(run_dir / "policy_best.pt", algorithm, cfg, obs_dim=obs_dim,
                        action_spec=evaluator.action_spec, **taken)
            best_policy.update(path="policy_best.pt", **taken)

        history = train(
            algorithm, train_data, evaluate=evaluator, samples_per_epoch=cfg.samples_per_epoch,
            eval_every_epochs=cfg.eval.every_epochs, logger=logger,
            checkpoint_path=run_dir / "checkpoint.pt" if cfg.checkpoint.enabled else None,
            progress=cfg.progress, on_new_best=keep_best,
        )
        last = history.evaluations[-1] if history.evaluations else None
        save_policy(run_dir / "policy.pt", algorithm, cfg, obs_dim=obs_dim, action_spec=evaluator.action_spec,
                    iteration=history.iterations, epoch=algorithm.epochs,
                    **({} if last is None else {"evaluation": len(history.evaluations) - 1,
                                                "mean_return": last.mean_return}))
    finally:
        evaluator.close()

    episode_returns = batch.episode_returns()
    summary = {
        "algo": cfg.algo.name,
        "env": cfg.env.id,
        "batch": batch.metadata.get("name", Path(str(batch.path)).name if batch.path else None),
        "batch_kind": None if cfg.get("dataset") else cfg.batch.kind,
        "batch_index": None if cfg.get("dataset") else int(cfg.batch.index),
        "seed": int(cfg.seed),
        "final_return": history.final_return(cfg.eval.final_window),
        "best_return": history.best_return(),
        "best_policy": best_policy or None,
        "dataset_mean_episode_return": float(episode_returns.mean()),
        "dataset_max_episode_return": float(episode_returns.max()),
        "num_transitions": int(batch.num_transitions),
        "num_episodes": int(batch.num_episodes),
        "iterations": history.iterations,
        "epochs": algorithm.epochs,
        "eval_failures": sum(e.failures for e in history.evaluations),
        "returns_augment": cfg.returns.augment,
        **algorithm.summary(),
        "wall_time_s": time.perf_counter() - start,
        "run_dir": str(run_dir),
        "batch_path": str(batch.path),
    }
    _add_normalized_scores(summary, cfg.env.id, batch.metadata)
    write_json_atomic(run_dir / "summary.json", summary)
    plot_learning_curve(
        [e.epoch for e in history.evaluations], [e.mean_return for e in history.evaluations],
        run_dir / "learning_curve.png", dataset_mean=summary["dataset_mean_episode_return"],
        title=f"{cfg.algo.name} on {summary['batch']} (seed {cfg.seed})",
    )
    log.info("final_return %.1f (best %.1f, batch mean %.1f) -> %s", summary["final_return"],
             summary["best_return"], summary["dataset_mean_episode_return"], run_dir / "summary.json")
    return summary


def _add_normalized_scores(summary: dict, env_id: str, metadata: dict | None = None) -> None:
    """``<key>_normalized`` (D4RL normalised score, or the dataset's own Minari reference) where one exists."""
    from torchrl_bail.data.importers import normalized_score, score_reference

    reference = score_reference(env_id, metadata)
    if reference is None:
        return
    for key in ("final_return", "best_return", "dataset_mean_episode_return"):
        summary[f"{key}_normalized"] = normalized_score(env_id, summary[key], metadata=metadata)
    summary["normalized_score_reference"] = {"random": reference[0], "expert": reference[1], "source": reference[2]}


def job_threads(cfg: DictConfig, launcher=None) -> int | None:
    """Torch threads for this job: the ``threads`` config key when set, else ``cores // n_jobs`` under the joblib
    launcher (so that side-by-side jobs do not oversubscribe the cores), else ``None`` (torch's default)."""
    threads = cfg.get("threads")
    if threads:
        return int(threads)
    if launcher is None or "joblib" not in str(launcher.get("_target_", "")):
        return None
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    n_jobs = int(launcher.get("n_jobs") or 1)
    return max(1, cores // (cores if n_jobs < 0 else n_jobs))


@hydra.main(config_path=str(config_dir()), config_name="config", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> float:
    from hydra.core.hydra_config import HydraConfig

    from torchrl_bail.data import BatchValidationError

    threads = job_threads(cfg, HydraConfig.get().get("launcher"))
    if threads is not None:
        torch.set_num_threads(threads)
        log.info("torch threads: %d", threads)
    try:
        summary = run(cfg, Path(HydraConfig.get().runtime.output_dir))
    except (ConfigError, BatchValidationError, FileNotFoundError) as err:  # a clear message, not a traceback
        print(f"torchrl_bail: {type(err).__name__}: {err}", file=sys.stderr)
        sys.exit(2)
    return summary["final_return"]


def main() -> None:
    """Console entry point (``torchrl-bail-train``)."""
    _hydra_main()


if __name__ == "__main__":
    main()

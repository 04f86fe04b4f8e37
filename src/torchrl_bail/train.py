"""Train an offline RL algorithm on a batch: ``python -m torchrl_bail.train +exp=hopper_ddpg05``.

Data flows one way: batch (generated on demand, or imported from ``dataset=<path>``) -> Monte-Carlo returns
-> the algorithm's ``prepare`` (BAIL: envelope + best-action filter) -> the training loop -> evaluation.
The run directory receives the resolved ``config.yaml``, CSV scalars (``logs/``), ``learning_curve.png``,
``envelope.png`` (BAIL), ``checkpoint.pt``, ``policy.pt`` (the final policy), ``policy_best.pt`` (the
best-evaluated one; :func:`torchrl_bail.load_policy` rebuilds either), with ``eval.snapshots=N`` the policies of
``N`` evaluations spread over training (``snapshots/policy_<iteration>.pt``, :func:`snapshot_path`), and
``summary.json``. Re-running the same command continues a killed run from its checkpoint
(:mod:`torchrl_bail.training.resume`).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import hydra
from omegaconf import DictConfig, OmegaConf, open_dict

from torchrl_bail import config_dir
from torchrl_bail.cli import checkpoint_before_requeue, exit_on_config_error, run_cli, use_job_threads
from torchrl_bail.configuration.config import ConfigError, validate_config

if TYPE_CHECKING:  # resume loads the lock module, and with it torch: imported where a run starts
    from torchrl_bail.training.resume import Resumption

# torch, torchrl and the algorithms are imported inside the functions below: a bad command line is reported
# (torchrl_bail.cli.run_cli) in about a second, before they load.

__all__ = ["run", "main", "ConfigError", "validate_config", "make_logger", "flat_hparams", "snapshot_path"]

log = logging.getLogger("torchrl_bail")


def _device(name: str):
    import torch

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)  # cuda without a GPU was refused by validate_config


def seed_everything(seed: int):
    """Seeds ``random``, NumPy and torch with the training seed; returns a torch generator seeded alike."""
    import random

    import numpy as np
    import torch

    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)
    return torch.Generator().manual_seed(seed)


def load_training_batch(cfg: DictConfig):
    """The batch to train on: ``dataset=<path>`` (imported/native) or the generated one for env x batch.

    Collecting a batch re-seeds the global generators with the behaviour seed: :func:`run` seeds training only
    after this returns, so the training streams are the same whether the batch was collected or cached.
    """
    if cfg.get("dataset"):
        from torchrl_bail.data.importers import import_dataset

        def absolute(p) -> str:
            return hydra.utils.to_absolute_path(str(Path(str(p)).expanduser()))

        data_dir = cfg.get("data_dir")
        return import_dataset(Path(absolute(cfg.dataset)), env_id=cfg.env.id,
                              data_dir=absolute(data_dir) if data_dir else None)
    from torchrl_bail.behaviour import ensure_batch

    return ensure_batch(cfg, progress=cfg.progress)


def flat_hparams(cfg: DictConfig) -> dict[str, Any]:
    """The resolved config as ``{"algo.envelope.lr": 0.003, ...}`` with scalar values (lists and null as text),
    the form every logger backend accepts as hyper-parameters.

    Examples:
        >>> flat_hparams(OmegaConf.create({"seed": 1, "algo": {"hidden": [4, 4], "init": None}}))
        {'seed': 1, 'algo.hidden': '[4, 4]', 'algo.init': 'null'}
    """
    flat: dict[str, Any] = {}

    def walk(node: Any, prefix: str) -> None:
        if isinstance(node, dict):
            for key, value in node.items():
                walk(value, f"{prefix}{key}" if not prefix else f"{prefix}.{key}")
        else:
            flat[prefix] = node if isinstance(node, (bool, int, float, str)) else (
                "null" if node is None else str(node))

    walk(OmegaConf.to_container(cfg, resolve=True), "")
    return flat


def make_logger(cfg: DictConfig, run_dir: Path):
    """The TorchRL logger ``cfg.logger`` asks for, with the resolved config logged as hyper-parameters.

    Run name: ``logger.name``, else ``<algo>_seed<seed>_<run dir name>``. wandb gets ``project``, ``group`` and
    the run name; mlflow files the run under the experiment ``project`` with the ``group`` and run name as tags;
    csv and tensorboard write into ``<run_dir>/logs`` (the run directory names the run).
    """
    from torchrl.record.loggers import get_logger

    backend, group = cfg.logger.backend, cfg.logger.group
    name = cfg.logger.name or f"{cfg.algo.name}_seed{cfg.seed}_{Path(run_dir).name}"
    kwargs: dict[str, Any] = {}
    experiment = "logs"
    if backend == "wandb":
        experiment = name
        kwargs["wandb_kwargs"] = {"project": cfg.logger.project, "group": group}
    elif backend == "mlflow":
        experiment = cfg.logger.project
        kwargs["mlflow_kwargs"] = {"tags": {"group": group, "mlflow.runName": name}}
    logger = get_logger(backend, logger_name=str(run_dir), experiment_name=experiment, **kwargs)
    logger.log_hparams(flat_hparams(cfg))
    return logger


def training_data(cfg: DictConfig, batch, evaluator):
    """The batch's transitions with their Monte-Carlo returns (``"return"``), after checking that the batch fits
    the evaluation env."""
    from torchrl_bail.data import monte_carlo_returns

    obs_dim, act_dim = evaluator.obs_dim, evaluator.action_spec.shape[-1]
    if (batch.obs_dim, batch.act_dim) != (obs_dim, act_dim):
        raise ConfigError("env", cfg.env.name, f"the env of batch {batch.path}, whose observation/action sizes are "
                          f"({batch.obs_dim}, {batch.act_dim}) where {cfg.env.id} has ({obs_dim}, {act_dim}); pick "
                          "the matching env= for this dataset")
    data = batch.data
    returns = monte_carlo_returns(data, gamma=cfg.returns.gamma, horizon=cfg.returns.horizon,
                                  augment=cfg.returns.augment)
    data = data.select("observation", "action", "next", "episode").clone(False)
    data.set("return", returns)
    return data


def finish_run(cfg: DictConfig, run_dir: Path, batch, algorithm, history, action_spec, obs_dim: int,
               resumption: Resumption, *, wall_time_s: float) -> dict[str, Any]:
    """After training: ``policy.pt``, ``summary.json`` (written last: it marks the run complete) and the learning
    curve of one seed's run; returns the summary."""
    import torch

    from torchrl_bail.core.io import write_json_atomic
    from torchrl_bail.data.batch import platform_record
    from torchrl_bail.evaluation.policy import save_policy
    from torchrl_bail.reports.plots import plot_learning_curve

    last = history.evaluations[-1] if history.evaluations else None
    save_policy(run_dir / "policy.pt", algorithm, cfg, obs_dim=obs_dim, action_spec=action_spec,
                iteration=history.iterations, epoch=algorithm.epochs,
                **({} if last is None else {"evaluation": len(history.evaluations) - 1,
                                            "mean_return": last.mean_return}))
    episode_returns = batch.episode_returns()
    summary = {
        "algo": cfg.algo.name,
        "env": cfg.env.id,
        "batch": batch.metadata.get("name", Path(str(batch.path)).name if batch.path else None),
        "batch_kind": None if cfg.get("dataset") else cfg.batch.kind,
        "batch_index": None if cfg.get("dataset") else int(cfg.batch.index),
        "seed": int(cfg.seed),
        "final_return": history.final_return(cfg.eval.final_window),
        # the same window's mean discounted return from each test episode's start, at the gamma OPE estimates
        "final_discounted_return": history.final_discounted_return(cfg.eval.final_window),
        "best_return": history.best_return(),
        "best_policy": _best_policy(history),
        **({"snapshots": _snapshots(history, cfg.eval.snapshots, run_dir)} if cfg.eval.snapshots else {}),
        "dataset_mean_episode_return": float(episode_returns.mean()),
        "dataset_max_episode_return": float(episode_returns.max()),
        "num_transitions": int(batch.num_transitions),
        "num_episodes": int(batch.num_episodes),
        "iterations": history.iterations,
        "epochs": algorithm.epochs,
        "eval_failures": sum(e.failures for e in history.evaluations),
        "returns_augment": cfg.returns.augment,
        **algorithm.summary(),
        **resumption.summary_fields(),
        "wall_time_s": wall_time_s,
        "torch_threads": torch.get_num_threads(),
        "run_dir": str(run_dir),
        "batch_path": str(batch.path),
        "platform": platform_record(),
    }
    _add_normalized_scores(summary, cfg.env.id, batch.metadata)
    plot_learning_curve(
        [e.epoch for e in history.evaluations], [e.mean_return for e in history.evaluations],
        run_dir / "learning_curve.png", dataset_mean=summary["dataset_mean_episode_return"],
        title=f"{cfg.algo.name} on {summary['batch']} (seed {cfg.seed})",
    )
    write_json_atomic(run_dir / "summary.json", summary)  # last: a summary marks the run complete (resume)
    log.info("final_return %.1f (best %.1f, batch mean %.1f) -> %s", summary["final_return"],
             summary["best_return"], summary["dataset_mean_episode_return"], run_dir / "summary.json")
    return summary


def seed_list(cfg: DictConfig) -> list[int]:
    """The seeds of a ``seeds=`` run: the list itself, or for a count ``S`` the seeds ``seed, ..., seed + S - 1``.

    Examples:
        >>> seed_list(OmegaConf.create({"seed": 4, "seeds": 3}))
        [4, 5, 6]
        >>> seed_list(OmegaConf.create({"seed": 1, "seeds": [7, 2]}))
        [7, 2]
    """
    seeds = cfg.get("seeds")
    if seeds is None:
        return [int(cfg.seed)]
    if isinstance(seeds, int):
        return list(range(int(cfg.seed), int(cfg.seed) + seeds))
    return [int(s) for s in seeds]


def seed_run_dir(run_dir: Path, seed: int, other: int) -> Path:
    """Where the single-seed run with seed ``other`` writes, given this command's run directory (made for
    ``seed``): the last path component's ``seed<seed>`` prefix becomes ``seed<other>``, so each seed of a stacked run
    lands exactly where ``seed=<other>`` alone would. A run directory named otherwise (``hydra.run.dir=...``) gets one
    sub-directory ``seed<other>`` per seed.

    Examples:
        >>> seed_run_dir(Path("outputs/hopper_ddpg_b1/bc/seed1,preset=quick"), 1, 3).as_posix()
        'outputs/hopper_ddpg_b1/bc/seed3,preset=quick'
        >>> seed_run_dir(Path("/tmp/run"), 1, 3).as_posix()
        '/tmp/run/seed3'
    """
    run_dir, prefix = Path(run_dir), f"seed{seed}"
    name = run_dir.name
    if name.startswith(prefix) and (len(name) == len(prefix) or not name[len(prefix)].isdigit()):
        return run_dir.parent / f"seed{other}{name[len(prefix):]}"
    return run_dir / f"seed{other}"


def run(cfg: DictConfig, run_dir: Path) -> list[dict[str, Any]]:
    """Runs the training job described by ``cfg`` into ``run_dir``: the seeds of :func:`seed_list` (``seed``, or
    those of ``seeds=``) in one process; returns one summary per seed.

    ``seeds`` null is the single-seed run in ``run_dir``. With ``seeds=``, each seed runs with the config of the
    single-seed run ``seed=<s>`` (``seeds`` null) in that run's directory (:func:`seed_run_dir`): the same
    ``config.yaml``, logs, ``checkpoint.pt``, ``policy.pt``, ``policy_best.pt`` and ``summary.json``. With
    ``resume=auto`` (default) a checkpoint is continued and a seed whose directory already holds a finished run is
    reported, not trained again (:mod:`torchrl_bail.training.resume`); the others train together (:func:`_train_seeds`:
    their networks stacked when there are several, :mod:`torchrl_bail.core.stacking`; one seed trains its algorithm
    unstacked, as it always has). The checkpoints are single-seed checkpoints: a killed stacked run continues from
    them when rerun (all its unfinished seeds stopped at the same iteration), and each can also be continued alone
    (``seed=<s>``).
    """
    import contextlib

    validate_config(cfg)  # before the heavy imports: in a multirun this is each job's first look at its config
    from torchrl_bail.algorithms import ALGORITHMS
    from torchrl_bail.training.resume import ResumeError

    seeds = seed_list(cfg)
    refusal = ALGORITHMS[cfg.algo.name].seed_stack_refusal
    if len(seeds) > 1 and refusal is not None:
        raise ConfigError("seeds", seeds, f"null with algo={cfg.algo.name}, whose seeds cannot be stacked ({refusal}); "
                          f"run them one by one: -m seed={','.join(map(str, seeds))}")
    configs, dirs = [cfg], [Path(run_dir)]  # a single-seed run (seeds null): its own config and directory
    if cfg.get("seeds") is not None:
        configs, dirs = [], []
        for seed in seeds:
            seed_cfg = cfg.copy()
            with open_dict(seed_cfg):
                seed_cfg.seed, seed_cfg.seeds = seed, None
            configs.append(seed_cfg)
            dirs.append(seed_run_dir(run_dir, int(cfg.seed), seed))
    from torchrl_bail.training.resume import Resumption

    summaries: dict[int, dict[str, Any]] = {}
    with contextlib.ExitStack() as stack:
        todo = []
        for i, (seed_cfg, seed_dir) in enumerate(zip(configs, dirs, strict=True)):
            resumption = stack.enter_context(Resumption(seed_cfg, seed_dir))
            if resumption.complete is not None:
                summaries[i] = resumption.complete
            else:
                todo.append((i, resumption))
        stopped = {seeds[i]: (r.checkpoint or {}).get("iteration") for i, r in todo}
        if len(set(stopped.values())) > 1:
            raise ResumeError(f"the unfinished seeds stopped at different points (seed: checkpoint iteration "
                              f"{stopped}); a stacked run continues seeds that stopped together: continue them one "
                              "by one (seed=<s>, without seeds=) or start over with resume=false")
        if todo:
            trained = _train_seeds([configs[i] for i, _ in todo], [dirs[i] for i, _ in todo], [r for _, r in todo])
            summaries.update(zip([i for i, _ in todo], trained, strict=True))
    return [summaries[i] for i in range(len(configs))]


def _train_seeds(configs: list[DictConfig], dirs: list[Path], resumptions: list[Resumption]) -> list[dict[str, Any]]:
    """The one run path: trains the seeds of ``configs`` (each with its run directory and resumption) together and
    finishes each; returns their summaries.

    Every step runs once for the list of seeds, whatever its length: configs, device, batch, evaluator, training
    data, loggers, then per seed the seeding, the algorithm and its prepared data (or what its checkpoint restores),
    the trainee and its compile, the best-policy callbacks, the training loop and the finish. Whether the seeds'
    networks are stacked is decided by the list-taking pieces themselves
    (:func:`~torchrl_bail.training.trainer.make_trainee`,
    :func:`~torchrl_bail.core.stacking.prepare_seeds`, the :class:`~torchrl_bail.evaluation.Evaluator` of the seeds): a
    list of one trains its algorithm unstacked, on the batch as TorchRL's replay buffer samples it (the single-seed
    run, to every digit); several train as one :class:`~torchrl_bail.core.stacking.SeedStack`, each seed drawing its
    single-seed run's mini-batch stream.
    """
    from torchrl_bail.algorithms import PrepareContext, build_algorithm
    from torchrl_bail.core.stacking import prepare_seeds
    from torchrl_bail.evaluation import Evaluator
    from torchrl_bail.evaluation.policy import save_policy
    from torchrl_bail.training.resume import record_config
    from torchrl_bail.training.trainer import make_trainee, train

    start = time.perf_counter()
    cfg = configs[0]
    for seed_cfg, seed_dir in zip(configs, dirs, strict=True):
        record_config(seed_cfg, seed_dir / "config.yaml")
    device = _device(cfg.device)
    batch = load_training_batch(cfg)
    seeds = [int(c.seed) for c in configs]
    evaluator = Evaluator(cfg.env.id, episodes=cfg.eval.episodes, max_steps=cfg.eval.max_steps,
                          max_episode_steps=cfg.env.get("max_episode_steps"), device=device, seeds=seeds)
    try:
        obs_dim, action_spec = evaluator.obs_dim, evaluator.action_spec
        data = training_data(cfg, batch, evaluator)
        for resumption in resumptions:
            resumption.check_data(data)
        checkpoints = [r.checkpoint for r in resumptions]
        resuming = checkpoints[0] is not None
        loggers = [make_logger(c, d) for c, d in zip(configs, dirs, strict=True)]
        algorithms, contexts, streams = [], [], []
        for seed_cfg, seed_dir, logger, checkpoint in zip(configs, dirs, loggers, checkpoints, strict=True):
            # seeded after the batch is loaded: generating it (first run) or reading it from the cache (every later
            # run, resumed ones included) leaves the training streams the same
            generator = seed_everything(int(seed_cfg.seed))
            algorithms.append(build_algorithm(seed_cfg.algo, obs_dim, action_spec, device))
            streams.append(_sampling_stream(int(seed_cfg.seed), device))  # its mini-batch stream, when stacked
            if checkpoint is not None:  # a checkpoint restores what prepare fitted: nothing is refitted or logged
                algorithms[-1].load_state_dict(checkpoint["algorithm"])
                contexts.append(PrepareContext(generator=generator))
            else:
                contexts.append(PrepareContext(run_dir=seed_dir, logger=logger, generator=generator,
                                               progress=cfg.progress))
        if resuming:
            prepared = [a.restore_prepared(data, ctx) for a, ctx in zip(algorithms, contexts, strict=True)]
        else:
            prepared = prepare_seeds(algorithms, data, contexts)
        trainee = make_trainee(algorithms, prepared, streams)  # one seed: its algorithm itself; several: their stack
        trainee.compile(cfg.compile)  # after the checkpoint's state is in place; a no-op for compile=false
        log.info("training seeds %s of %s in one process (%s)", seeds, cfg.algo.name, trainee.layout)

        def keep_best(i: int):  # policy_best.pt: the best-evaluated policy of seed i so far
            def save(point, index: int) -> None:
                save_policy(dirs[i] / "policy_best.pt", trainee.algorithms()[i], configs[i], obs_dim=obs_dim,
                            action_spec=action_spec, iteration=point.iteration, epoch=point.epoch, evaluation=index,
                            mean_return=point.mean_return)
            return save

        def keep_snapshot(i: int):  # snapshots/policy_<iteration>.pt: eval.snapshots evaluations' policies
            def save(point, index: int) -> None:
                save_policy(dirs[i] / snapshot_path(point.iteration), trainee.algorithms()[i], configs[i],
                            obs_dim=obs_dim, action_spec=action_spec, iteration=point.iteration, epoch=point.epoch,
                            evaluation=index, mean_return=point.mean_return)
            return save

        every_minutes = cfg.checkpoint.get("every_minutes")
        histories = train(
            trainee, evaluate=evaluator.evaluate, evaluation_state=evaluator, samples_per_epoch=cfg.samples_per_epoch,
            eval_every_epochs=cfg.eval.every_epochs, loggers=loggers, progress=cfg.progress,
            checkpoint_paths=[d / "checkpoint.pt" for d in dirs] if cfg.checkpoint.enabled else None,
            checkpoint_every_s=60.0 * every_minutes if every_minutes else None,
            checkpoint_extras=[r.checkpoint_extra for r in resumptions],
            resume_from=checkpoints if resuming else None,
            on_new_best=[keep_best(i) for i in range(len(configs))],
            snapshots=cfg.eval.snapshots, on_snapshot=[keep_snapshot(i) for i in range(len(configs))],
        )
        algorithms = trainee.algorithms()
    finally:
        evaluator.close()
    wall_time_s = time.perf_counter() - start + (checkpoints[0] or {}).get("wall_time_s", 0.0)
    return [finish_run(c, d, batch, a, h, action_spec, obs_dim, r, wall_time_s=wall_time_s)
            for c, d, a, h, r in zip(configs, dirs, algorithms, histories, resumptions, strict=True)]


def _sampling_stream(seed: int, device):
    """The generator seed ``seed``'s mini-batch indices come from: a copy of the global stream right after its
    algorithm was built (CPU), or a CUDA generator seeded like the default one ``torch.manual_seed`` seeds (the
    indices of a single-seed run are drawn on the data's device)."""
    import torch

    if device.type == "cpu":
        generator = torch.Generator()
        generator.set_state(torch.get_rng_state())
        return generator
    return torch.Generator(device=device).manual_seed(seed)


def snapshot_path(iteration: int) -> str:
    """Where a run keeps its policy snapshot of iteration ``iteration``, relative to the run directory.

    Examples:
        >>> snapshot_path(2500)
        'snapshots/policy_2500.pt'
    """
    return f"snapshots/policy_{int(iteration)}.pt"


def _snapshots(history, count: int, run_dir: Path) -> list[dict[str, Any]]:
    """The policy snapshots of ``eval.snapshots=count``, read from the history
    (:func:`~torchrl_bail.training.trainer.snapshot_indices`), so that a resumed run lists the same ones as an
    uninterrupted
    run: each with its path, iteration, epoch, evaluation index and evaluation return (``eval_return``, the mean test
    return the run measured for that policy)."""
    from torchrl_bail.training.trainer import snapshot_indices

    snapshots = []
    for index in snapshot_indices(len(history.evaluations), count):
        point = history.evaluations[index]
        path = snapshot_path(point.iteration)
        if not (run_dir / path).is_file():
            log.warning("%s is missing: its snapshot is listed in summary.json all the same", run_dir / path)
        snapshots.append({"path": path, "iteration": point.iteration, "epoch": point.epoch, "evaluation": index,
                          "eval_return": point.mean_return})
    return snapshots


def _best_policy(history) -> dict[str, Any] | None:
    """Where ``policy_best.pt`` came from: the first evaluation with the highest mean return (read from the
    history, so that a resumed run names the same one as an uninterrupted run)."""
    if not history.evaluations:
        return None
    index = max(range(len(history.evaluations)), key=lambda i: (history.evaluations[i].mean_return, -i))
    point = history.evaluations[index]
    return {"path": "policy_best.pt", "iteration": point.iteration, "epoch": point.epoch, "evaluation": index,
            "mean_return": point.mean_return}


def _add_normalized_scores(summary: dict, env_id: str, metadata: dict | None = None) -> None:
    """``<key>_normalized`` (D4RL normalised score, or the dataset's own Minari reference) where one exists."""
    from torchrl_bail.data.scores import normalized_score, score_reference

    reference = score_reference(env_id, metadata)
    if reference is None:
        return
    for key in ("final_return", "best_return", "dataset_mean_episode_return"):
        summary[f"{key}_normalized"] = normalized_score(env_id, summary[key], metadata=metadata)
    summary["normalized_score_reference"] = {"random": reference[0], "expert": reference[1], "source": reference[2]}


@hydra.main(config_path=str(config_dir()), config_name="config", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> float:
    from hydra.core.hydra_config import HydraConfig

    use_job_threads(cfg)
    with checkpoint_before_requeue(), exit_on_config_error():  # Slurm: checkpoint, then submitit requeues
        summaries = run(cfg, Path(HydraConfig.get().runtime.output_dir))
    return sum(s["final_return"] for s in summaries) / len(summaries)  # the sweeper's objective: the seeds' mean


def main() -> None:
    """Console entry point (``torchrl-bail-train``): a bad command line ends with one line on stderr, exit code 2."""
    run_cli(_hydra_main, command="python -m torchrl_bail.train")  # Ctrl-C/SIGTERM: checkpoint, one line, 130/143


if __name__ == "__main__":
    main()

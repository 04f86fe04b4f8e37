"""The shared SAC behaviour run (paper Sec. 5; supp. E): trained once per env, seed and ``batch.sac`` block, stored
with its policy at every evaluation, and the ``sac`` training batch it yields; the agent is
:class:`torchrl_bail.behaviour.sac.SACAgent`.

**One SAC run serves several batches.** A run is identified by the env, its time limit, the behaviour seed and the
``batch.sac`` block (:func:`sac_run_identity`). It trains for ``sac.train_steps`` env steps and records, atomically,
in ``<data_dir>/policies/<env>_sac_b<index>-<hash>/``: ``run.json`` (identity, every evaluation) and the actor's
weights at every evaluation (``evals/step_<t>.pt``). From it:

* the ``sac`` batch = the first ``batch.steps`` transitions of the run (the whole run with the defaults);
* the *optimal* behaviour policy = the weights at the final evaluation;
* the *mediocre* behaviour policy = the weights at the first evaluation whose mean return reaches
  ``env.mediocre_threshold`` (paper Sec. 5; supp. E; the threshold is applied when the policy is chosen, so changing
  it needs no retraining). If no evaluation reaches it, the best evaluation is used and the batch's metadata says so.

Whichever of the ``sac``/``med_*``/``opt_*`` batches is asked for first trains the run; the others reuse it. When an
execution batch triggers the run, the ``sac`` training batch it produces as a by-product is saved too.

**Execution batches** (:mod:`torchrl_bail.behaviour.execution`) run the chosen policy for ``batch.steps`` steps
(episodes limited as usual), deterministic (``stochastic: false``, sigma = 0: ``max_action * tanh(mu(s))``) or
stochastic (``sigma = sigma(s)``); the metadata keeps the policy file, its evaluation step and its measured return
(``behaviour_return``).
"""


from __future__ import annotations

import copy
import dataclasses
import json
import logging
import os
import shutil
import time
from pathlib import Path
from typing import Any, List

import torch
from omegaconf import MISSING
from tensordict import TensorDictBase
from torchrl.modules import ProbabilisticActor

from torchrl_bail.behaviour.buffers import BehaviourBuffers
from torchrl_bail.behaviour.checkpoint import CollectionCheckpoint, Resumable
from torchrl_bail.behaviour.loop import (
    BehaviourRun,
    ReturnTracker,
    agent_kwargs,
    collect_timed,
    env_bounds,
    env_steps_per_s,
    make_collection_env,
    seed_all,
)
from torchrl_bail.behaviour.recipes import Recipe, register_recipe
from torchrl_bail.behaviour.sac import SACAgent
from torchrl_bail.configuration.batch_schemas import BatchConfig, batch_schema, schema_block
from torchrl_bail.configuration.config import (
    Checked,
    at_least,
    discount,
    is_number,
    layers,
    learning_rate,
    one_of,
    positive,
    rule,
)
from torchrl_bail.core.errors import ConfigError
from torchrl_bail.core.io import atomic_path
from torchrl_bail.data.batch import save_batch
from torchrl_bail.data.cache import (
    batch_metadata,
    batch_path,
    behaviour_seed,
    data_dir_of,
    episode_limit,
    oracle_settings,
    plain,
    sac_identity,
    stable_hash,
)
from torchrl_bail.data.locks import (
    LOCKS,
    check_fence,
    clean_stale,
    file_lock,
    liveness_settings,
    owned_name,
    scratch_directory,
)
from torchrl_bail.evaluation import Evaluator
from torchrl_bail.modules import action_spec_from_bounds, make_sac_actor

__all__ = [
    "SACRun",
    "sac_run_identity",
    "sac_run_dir",
    "train_sac",
    "ensure_sac_run",
    "run_checkpoint",
    "sac_run_lock",
    "load_sac_run",
    "collect_sac",
]


# -- the schema (conf/batch, recipe: sac), read by torchrl_bail.configuration.batch_schemas without importing this
# module --


@schema_block
class SACAgentConfig(Checked):
    actor_hidden: List[int] = layers()
    critic_hidden: List[int] = layers()
    actor_lr: float = learning_rate()
    critic_lr: float = learning_rate()
    alpha_lr: float = learning_rate()
    gamma: float = discount()
    polyak: float = rule(lambda v: 0 <= v < 1, "a target-network decay in [0, 1) (0.995)")
    alpha_init: float = positive("a positive initial entropy coefficient")
    target_entropy: Any = rule(lambda v: v == "auto" or is_number(v), "auto or a number")
    log_std_min: float = MISSING
    log_std_max: float = MISSING
    batch_size: int = at_least(1)
    loss_function: str = one_of("l2", "smooth_l1", "l1")
    log_prob_on: str = one_of("tanh", "action")
    start_steps: int = at_least(0)
    train_steps: int = at_least(1)
    eval_every: int = at_least(1)
    eval_episodes: int = at_least(1)

    def check(self) -> None:
        self._ordered("log_std_min", "log_std_max")


@batch_schema("sac")
class SACBatchConfig(BatchConfig):
    sac: SACAgentConfig = MISSING

    def check(self) -> None:
        super().check()
        if self.steps > self.sac.train_steps:
            raise ConfigError("steps", self.steps, f"at most sac.train_steps = {self.sac.train_steps} (the batch is "
                              "the first steps transitions of the SAC run)")


log = logging.getLogger("torchrl_bail")

EVAL_SEED_OFFSET = 20_000  # evaluation envs too



def _is_run_batch(cfg) -> bool:
    """Whether ``cfg`` is the ``sac`` batch (the run's own first transitions), not an execution batch of the run."""
    return cfg.batch.recipe == SACRecipe.name


def _sac_block(cfg) -> dict:
    return dict(plain(cfg.batch.sac))


def sac_run_identity(cfg) -> dict:
    """What determines a SAC run: env id, its time limit, behaviour seed, the ``batch.sac`` block.

    A ``sac`` batch in oracle mode trains its own run on 2000-step episodes; execution batches always use the run
    on the env's normal time limit (oracle mode only changes how they are executed).
    """
    if _is_run_batch(cfg):
        limit = episode_limit(cfg)
    else:
        limit = cfg.env.max_episode_steps
        limit = 1000 if limit is None else int(limit)
    return {"env_id": cfg.env.id, "max_episode_steps": limit, "seed": behaviour_seed(cfg),
            "sac": sac_identity(_sac_block(cfg), cfg.env.id)}


def sac_run_dir(cfg, data_dir=None) -> Path:
    identity = sac_run_identity(cfg)
    name = f"{cfg.env.name}_sac_b{int(cfg.batch.index)}-{stable_hash(identity)}"
    return data_dir_of(cfg, data_dir) / "policies" / name


class SACRun:
    """A finished SAC run on disk: its evaluations and the policy weights saved at each of them."""

    def __init__(self, path: Path, record: dict):
        self.path = Path(path)
        self.record = record

    @property
    def evaluations(self) -> list[dict]:
        return self.record["evaluations"]

    def optimal(self) -> dict:
        """The final evaluation (the fully trained policy)."""
        return self.evaluations[-1]

    def mediocre(self, threshold: float) -> tuple[dict, bool]:
        """The first evaluation whose mean return reaches ``threshold`` (else the best one, flagged ``False``)."""
        for ev in self.evaluations:
            if ev["return_mean"] >= threshold:
                return ev, True
        return max(self.evaluations, key=lambda ev: ev["return_mean"]), False

    def load_actor(self, evaluation: dict) -> ProbabilisticActor:
        meta = self.record
        low = torch.tensor(meta["action_low"])
        high = torch.tensor(meta["action_high"])
        sac = meta["identity"]["sac"]
        actor = make_sac_actor(meta["obs_dim"], action_spec_from_bounds(low, high), sac["actor_hidden"],
                               log_std_min=sac["log_std_min"], log_std_max=sac["log_std_max"])
        state = torch.load(self.path / evaluation["file"], map_location="cpu", weights_only=True)
        actor.load_state_dict(state)
        return actor


def load_sac_run(path: Path) -> SACRun | None:
    path = Path(path)
    try:
        record = json.loads((path / "run.json").read_text())
    except (OSError, ValueError):
        return None
    if not record.get("evaluations") or not all((path / ev["file"]).is_file() for ev in record["evaluations"]):
        return None
    return SACRun(path, record)


def run_checkpoint(cfg, data_dir=None) -> CollectionCheckpoint:
    """Where the SAC run of ``cfg`` checkpoints: ``<data_dir>/.partial/<run name>[_oracle]`` (shared by the
    ``sac``, ``med_*`` and ``opt_*`` batches that need the same run; written under the run's lock)."""
    root = data_dir_of(cfg, data_dir)
    oracle = _is_run_batch(cfg) and oracle_settings(cfg) is not None
    return CollectionCheckpoint.for_config(cfg, root, sac_run_dir(cfg, root).name + ("_oracle" if oracle else ""))


def train_sac(cfg, *, scratch: Path, progress: bool = True, agent_hook=None,
              checkpoint: CollectionCheckpoint | None = None):
    """Runs the SAC behaviour run of ``cfg`` (``batch.sac``) on ``cfg.env``.

    With a ``checkpoint`` (:func:`run_checkpoint`) the run resumes from it and saves checkpoints there, with its
    evaluations and the policy weights saved at each (``evals/``); the caller removes it once all is saved.

    Returns:
        ``(data, record, snapshots)``: the memmapped transitions of the run ([train_steps], oracle-cut in oracle
        mode), the run record (identity, evaluations, speed) and ``{file name: actor state_dict}``.
    """
    sac = _sac_block(cfg)
    identity = sac_run_identity(cfg)
    seed = identity["seed"]
    train_steps = int(sac["train_steps"])
    start_steps = int(sac["start_steps"])
    eval_every = int(sac["eval_every"])
    oracle = oracle_settings(cfg) if _is_run_batch(cfg) else None
    seed_all(seed)
    env = make_collection_env(cfg.env.id, max_episode_steps=identity["max_episode_steps"], seed=seed)
    eval_limit = cfg.env.max_episode_steps
    evaluator = Evaluator(cfg.env.id, episodes=int(sac["eval_episodes"]), seed=seed + EVAL_SEED_OFFSET,
                          max_steps=int(eval_limit or 1000), max_episode_steps=eval_limit)
    try:
        low, high = env_bounds(env)
        obs_dim = env.observation_spec["observation"].shape[-1]
        act_dim = low.shape[-1]
        agent = SACAgent(obs_dim, action_spec_from_bounds(low, high), **agent_kwargs(SACAgent, sac))
        if agent_hook is not None:
            agent_hook(agent)
        buffers = BehaviourBuffers(train_steps, Path(scratch), oracle=oracle, replay_batch_size=agent.batch_size)
        span = high - low
        evaluations: list[dict] = []
        snapshots: dict[str, dict[str, torch.Tensor]] = {}
        desc = f"SAC {cfg.env.name} b{cfg.batch.index}"
        tracker = ReturnTracker(train_steps, desc=desc, progress=progress)
        timers = {"train": 0.0, "eval": 0.0}

        def act(observation: torch.Tensor, t: int) -> torch.Tensor:
            if t < start_steps:
                return low + span * torch.rand(act_dim)
            return agent.act(observation)

        def on_episode_end(length: int, ret: float, t: int) -> None:
            t0 = time.perf_counter()
            agent.train(buffers.replay, length)
            timers["train"] += time.perf_counter() - t0

        def evaluate(t: int) -> None:
            t0 = time.perf_counter()
            (result,) = evaluator.evaluate(agent.actor)
            fname = f"evals/step_{t:09d}.pt"
            snapshots[fname] = agent.policy_state()
            evaluations.append({"step": t, "return_mean": result.mean_return, "return_std": result.std_return,
                                "returns": [float(r) for r in result.returns], "failures": result.failures,
                                "gradient_steps": agent.updates, "file": fname})
            timers["eval"] += time.perf_counter() - t0
            tracker.note(eval=f"{result.mean_return:.0f}")
            log.info("SAC %s step %d: eval return %.1f +- %.1f", cfg.env.id, t, result.mean_return,
                     result.std_return)

        def on_step(t: int) -> None:
            if t % eval_every == 0:
                evaluate(t)

        def evaluate_final() -> None:  # the final policy is always evaluated and saved
            if not evaluations or evaluations[-1]["step"] != runner.t:
                evaluate(runner.t)

        runner = BehaviourRun(env, act, on_episode_end=on_episode_end, on_step=on_step, tracker=tracker)
        resumable = None
        if checkpoint is not None:
            resumable = _sac_resumable(checkpoint, runner, buffers, agent, evaluator, evaluations, snapshots, timers)
        data, wall = collect_timed(buffers, runner, after=evaluate_final, resumable=resumable)
    finally:
        env.close()
        evaluator.close()
    record = _sac_record(cfg, identity, obs_dim, low, high, agent, runner, evaluations, wall, timers, resumable)
    return data, record, snapshots


def _sac_resumable(checkpoint: CollectionCheckpoint, runner: BehaviourRun, buffers: BehaviourBuffers,
                   agent: SACAgent, evaluator: Evaluator, evaluations: list[dict],
                   snapshots: dict[str, dict[str, torch.Tensor]], timers: dict[str, float]) -> Resumable:
    """The run's :class:`~torchrl_bail.behaviour.checkpoint.Resumable`: beside the loop's state, the agent, the
    evaluations so far, the timers and each evaluation's policy snapshot (``evals/``, written once each)."""

    def state() -> dict:
        for fname, weights in snapshots.items():  # each policy snapshot is written once, before state.pt
            if not (checkpoint.directory / fname).is_file():
                with atomic_path(checkpoint.directory / fname) as tmp:
                    torch.save(weights, tmp)
                    check_fence()  # a job whose lock was taken over publishes nothing
        return {"agent": agent.state_dict(), "evaluations": copy.deepcopy(evaluations),
                "timers": dict(timers)}

    def load(saved: dict) -> None:
        agent.load_state_dict(saved["agent"])
        evaluations[:] = saved["evaluations"]
        timers.update(saved["timers"])
        for ev in evaluations:
            snapshots[ev["file"]] = torch.load(checkpoint.directory / ev["file"], map_location="cpu",
                                               weights_only=True)
        evaluator.evaluations = len(evaluations)  # the k-th evaluation's reset seeds depend on k

    return Resumable(checkpoint, runner, buffers, state=state, load=load)


def _sac_record(cfg, identity: dict, obs_dim: int, low: torch.Tensor, high: torch.Tensor, agent: SACAgent,
                runner: BehaviourRun, evaluations: list[dict], wall: float, timers: dict[str, float],
                resumable: Resumable | None) -> dict[str, Any]:
    """The run record (``run.json``): identity, sizes, bounds, evaluations, speed, final temperature."""
    return {
        "identity": identity,
        "name": sac_run_dir(cfg, "/").name,
        "obs_dim": int(obs_dim),
        "action_low": low.tolist(),
        "action_high": high.tolist(),
        "target_entropy": agent.target_entropy,
        "env_steps": runner.t,
        "episodes": runner.episodes,
        "gradient_steps": agent.updates,
        "evaluations": evaluations,
        "wall_time_s": wall,
        "train_time_s": timers["train"],
        "eval_time_s": timers["eval"],
        "env_steps_per_s": env_steps_per_s(runner, wall, resumable),
        "updates_per_s": agent.updates / max(timers["train"], 1e-9),
        "final_alpha": float(agent.loss.log_alpha.detach().exp()),
        "simulator_unstable_episodes": runner.unstable_episodes,
        "resumed_from_step": resumable.resumed_from_step if resumable is not None else None,
        "created_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }


def _save_run(path: Path, record: dict, snapshots: dict[str, dict]) -> SACRun:
    """Writes the run to a temporary directory beside ``path`` and renames it into place (atomic)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.parent / f".{owned_name(path.name)}"  # host and pid in the name: clean_stale can tell its owner
    try:
        (tmp / "evals").mkdir(parents=True)
        for fname, state in snapshots.items():
            torch.save(state, tmp / fname)
        (tmp / "run.json").write_text(json.dumps(record, indent=2) + "\n")
        if path.exists():  # a concurrent identical run finished first: keep it
            shutil.rmtree(tmp)
        else:
            check_fence()  # a job whose lock was taken over publishes nothing
            os.replace(tmp, path)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return SACRun(path, record)


def _run_cfg(cfg):
    """``cfg`` with ``batch`` replaced by the ``sac`` training batch this run produces: ``steps = train_steps``,
    oracle mode off, and the execution batch's collection settings (outside the hash)."""
    batch = cfg.batch
    shared = {f.name: getattr(batch, f.name) for f in dataclasses.fields(BatchConfig)}
    run_batch = SACBatchConfig(**{**shared, "kind": "sac", "recipe": "sac", "steps": int(batch.sac.train_steps),
                                  "oracle": dataclasses.replace(batch.oracle, enabled=False)}, sac=batch.sac)
    return dataclasses.replace(cfg, batch=run_batch)


def sac_run_lock(cfg, data_dir=None):
    """The lock of ``cfg``'s SAC run (held while it trains, checkpoints or is saved)."""
    root = data_dir_of(cfg, data_dir)
    stale, beat = liveness_settings(cfg)
    name = sac_run_dir(cfg, root).name
    return file_lock(root / LOCKS / f"policies-{name}.lock", stale_after_s=stale, heartbeat_every_s=beat,
                     what=f"SAC run {name}")


def ensure_sac_run(cfg, *, progress: bool = True, data_dir=None) -> SACRun:
    """The SAC run behind ``cfg``'s execution batch: loaded from ``policies/``, or trained once and saved.

    When it has to be trained, the ``sac`` training batch it produces (its first ``train_steps`` transitions) is
    saved as well, under the name and hash a ``batch=sac`` config with ``batch.steps = sac.train_steps`` gives.
    Training resumes from the run's checkpoint (:func:`run_checkpoint`) when an earlier attempt was killed.
    """
    path = sac_run_dir(cfg, data_dir)
    run = load_sac_run(path)
    if run is not None:
        return run
    root = data_dir_of(cfg, data_dir)
    stale, beat = liveness_settings(cfg)
    clean_stale(root, stale_after_s=stale)
    with sac_run_lock(cfg, root):
        run = load_sac_run(path)
        if run is not None:
            return run
        if path.exists():
            aside = path.with_name(f"{path.name}.broken-{time.strftime('%Y%m%d-%H%M%S')}")
            os.replace(path, aside)
        run_cfg = _run_cfg(cfg)
        checkpoint = run_checkpoint(run_cfg, root)
        with scratch_directory(root, path.name, heartbeat_every_s=beat) as scratch:
            data, record, snapshots = train_sac(run_cfg, scratch=scratch, progress=progress, checkpoint=checkpoint)
            run = _save_run(path, record, snapshots)
            by_product = batch_path(run_cfg, root)
            if not by_product.exists():
                extra = _sac_batch_extra(run, data.shape[0])
                meta = batch_metadata(run_cfg, extra, wall_time_s=checkpoint.wall_time_s,
                                      timed_from_step=checkpoint.timed_from_step)
                try:
                    save_batch(data, by_product, meta)
                    log.info("saved the SAC training batch of this run as %s", by_product)
                except (FileExistsError, OSError) as err:  # a concurrent job saved it first
                    log.info("SAC training batch %s not saved (%s)", by_product, err)
        checkpoint.remove()
    return run


def _sac_batch_extra(run: SACRun, steps: int) -> dict[str, Any]:
    """The metadata extras of a ``sac`` training batch (its first ``steps`` transitions) cut from ``run``."""
    rec = run.record
    final = run.optimal()
    return {
        "action_low": list(rec["action_low"]),
        "action_high": list(rec["action_high"]),
        "behaviour": "sac",
        "sac_run": str(run.path),
        "sac_run_train_steps": rec["env_steps"],
        "gradient_steps": rec["gradient_steps"],
        "evaluations": [{"step": e["step"], "return_mean": e["return_mean"]} for e in rec["evaluations"]
                        if e["step"] <= steps],
        "behaviour_final_eval_return": final["return_mean"],
        "env_steps_per_s": rec["env_steps_per_s"],
        "updates_per_s": rec["updates_per_s"],
        "simulator_unstable_episodes": rec.get("simulator_unstable_episodes", 0),
        "resumed_from_step": rec.get("resumed_from_step"),
    }


def collect_sac(cfg, *, scratch: Path, progress: bool = True, data_dir=None,
                checkpoint: CollectionCheckpoint | None = None) -> tuple[TensorDictBase, dict[str, Any]]:
    """The ``sac`` recipe: trains the SAC run (saving its policies) and returns its first ``batch.steps`` rows.

    ``checkpoint``: :func:`run_checkpoint` of ``cfg`` (resumed from, saved to; the caller removes it, under
    :func:`sac_run_lock`, once the batch is saved), or ``None``.
    """
    steps = int(cfg.batch.steps)
    root = data_dir_of(cfg, data_dir)
    path = sac_run_dir(cfg, root)
    with sac_run_lock(cfg, root):
        data, record, snapshots = train_sac(cfg, scratch=scratch, progress=progress, checkpoint=checkpoint)
        run = load_sac_run(path)
        if run is None:
            if path.exists():
                os.replace(path, path.with_name(f"{path.name}.broken-{time.strftime('%Y%m%d-%H%M%S')}"))
            run = _save_run(path, record, snapshots)
        else:  # the policies exist already (e.g. the batch was deleted): keep them, report this run's numbers
            run = SACRun(path, {**run.record, **{k: record[k] for k in ("env_steps_per_s", "updates_per_s")}})
    if steps < data.shape[0]:
        data = data[:steps]
    return data, _sac_batch_extra(SACRun(run.path, record), steps)


class SACRecipe(Recipe):
    """``batch.recipe=sac``: :func:`collect_sac`. It checkpoints as the SAC run (shared with every batch that needs
    the same run) and removes that checkpoint under the run's lock."""

    name = "sac"

    def collect(self, cfg, *, scratch, progress, data_dir, checkpoint):
        return collect_sac(cfg, scratch=scratch, progress=progress, data_dir=data_dir, checkpoint=checkpoint)

    def checkpoint(self, cfg, data_dir, name):
        return run_checkpoint(cfg, data_dir)

    def remove_checkpoint(self, cfg, data_dir, checkpoint):
        with sac_run_lock(cfg, data_dir):
            checkpoint.remove()


register_recipe(SACRecipe())

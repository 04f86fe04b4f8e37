"""SAC training batches (paper Sec. 5; supp. E) and the shared SAC behaviour run that execution batches (paper Sec. 5;
supp. E) reuse.

**The SAC agent** ("sac_adapt", the authors' data generator) on TorchRL's :class:`~torchrl.objectives.SACLoss`
(v2: no state-value net):

* tanh-Gaussian policy (:func:`~torchrl_bail.modules.make_sac_actor`) ``obs -> 256 -> 256 -> (mu, log sigma)``,
  ``log sigma`` clamped to [-20, 2], action ``max_action * tanh(mu + sigma * eps)``; its log-probability is that of
  the *unscaled* tanh output in [-1, 1], as in sac_adapt (``sac.log_prob_on: tanh``,
  :class:`~torchrl_bail.modules.TanhNormalScoredOnTanh`), in the actor loss, the alpha loss and the soft-Q target
  alike; the critics see the scaled action;
* twin critics ``(s, a) -> 256 -> 256 -> 1`` with target copies, squared TD error summed over the two critics,
  a TD(0) target with gamma 0.99 that bootstraps on ``terminated``, Polyak averaging 0.995
  (``SoftUpdate(eps=0.995)``);
* automatic entropy tuning, ``log alpha`` initialised to 0, target entropy ``-|A|`` (``target_entropy: auto``) on the
  tanh output. With ``log_prob_on: action`` (TorchRL's density of the scaled action) ``auto`` becomes
  ``-|A| + sum(log max_action)``, which re-centres alpha's tuning but leaves ``-alpha * sum(log max_action)`` in
  every soft-Q target (about ``+15.6 alpha`` per step on Humanoid, bound 0.4): not the authors' agent. With bound 1
  (Hopper, Walker2d, HalfCheetah, Ant) both settings are the same numbers, so ``log_prob_on`` enters the run's
  identity (and the batch hash) only when a bound differs from 1 (:func:`~torchrl_bail.data.cache.sac_identity`);
* Adam 3e-4 for the actor, the critics and alpha; batch 256 drawn uniformly from everything stored;
* ``start_steps`` (10^4) uniformly random actions, then actions sampled from the policy; at the end of every episode
  ``episode_length`` gradient steps; every ``eval_every`` (5000) env steps an evaluation of ``eval_episodes`` (10)
  deterministic episodes (``max_action * tanh(mu)``).

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
import json
import logging
import os
import shutil
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from omegaconf import OmegaConf, open_dict
from tensordict import TensorDict, TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor
from torchrl.objectives import SACLoss, ValueEstimators
from torchrl.objectives.utils import distance_loss
from torchrl.objectives.value.functional import td0_return_estimate

from torchrl_bail.behaviour.buffers import BehaviourBuffers
from torchrl_bail.behaviour.checkpoint import CheckpointableAgent, CollectionCheckpoint, Resumable
from torchrl_bail.behaviour.loop import (BehaviourRun, ReturnTracker, agent_kwargs, collect_timed, env_bounds,
                                         make_collection_env, seed_all)
from torchrl_bail.data.batch import save_batch
from torchrl_bail.data.cache import (
    LOCKS,
    OPERATIONAL_KEYS,
    batch_metadata,
    batch_path,
    behaviour_seed,
    clean_stale,
    config_value,
    data_dir_of,
    episode_limit,
    file_lock,
    liveness_settings,
    oracle_settings,
    owned_name,
    plain,
    sac_identity,
    scratch_directory,
    stable_hash,
)
from torchrl_bail.evaluation import Evaluator
from torchrl_bail.io import atomic_path
from torchrl_bail.modules import action_spec_from_bounds, fused_soft_update, make_qvalue_network, make_sac_actor

__all__ = [
    "SACAgent",
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

log = logging.getLogger("torchrl_bail")

EVAL_SEED_OFFSET = 20_000  # evaluation envs too



class SACAgent(CheckpointableAgent):
    """sac_adapt's SAC on TorchRL's :class:`~torchrl.objectives.SACLoss` (see the module docstring)."""

    OPTIMIZERS = ("actor_optim", "critic_optim", "alpha_optim")  # saved with the networks by state_dict()

    def __init__(self, obs_dim: int, action_spec, *, actor_hidden: Sequence[int] = (256, 256),
                 critic_hidden: Sequence[int] = (256, 256), actor_lr: float = 3e-4, critic_lr: float = 3e-4,
                 alpha_lr: float = 3e-4, gamma: float = 0.99, polyak: float = 0.995, alpha_init: float = 1.0,
                 target_entropy: float | str = "auto", log_std_min: float = -20.0, log_std_max: float = 2.0,
                 batch_size: int = 256, loss_function: str = "l2", log_prob_on: str = "tanh"):
        act_dim = action_spec.shape[-1]
        self.batch_size = int(batch_size)
        self.actor_hidden = list(actor_hidden)
        self.log_std_bounds = (float(log_std_min), float(log_std_max))
        self.log_prob_on = log_prob_on
        self.actor = make_sac_actor(obs_dim, action_spec, actor_hidden, log_std_min=log_std_min,
                                    log_std_max=log_std_max, log_prob_on=log_prob_on)
        self.qvalue = make_qvalue_network(obs_dim, act_dim, critic_hidden)
        if target_entropy == "auto":  # -|A| on the tanh output, wherever the log-probabilities are measured
            half_range = (action_spec.space.high - action_spec.space.low) / 2
            shift = float(torch.log(half_range).sum()) if log_prob_on == "action" else 0.0
            target_entropy = -float(act_dim) + shift
        self.target_entropy = float(target_entropy)
        self.loss = SACLoss(self.actor, self.qvalue, num_qvalue_nets=2, loss_function=loss_function,
                            alpha_init=alpha_init, target_entropy=self.target_entropy, delay_actor=False,
                            delay_qvalue=True, action_spec=action_spec,
                            deactivate_vmap=True)  # on CPU two plain critic calls beat one vmapped call
        self.loss.make_value_estimator(ValueEstimators.TD0, gamma=gamma)  # bootstraps on ~terminated
        self.target_updater = fused_soft_update(self.loss, eps=polyak)  # a SoftUpdate(eps=0.995)
        self.actor_optim = torch.optim.Adam(self.loss.actor_network_params.values(True, True), lr=actor_lr,
                                            foreach=True)
        self.critic_optim = torch.optim.Adam(self.loss.qvalue_network_params.values(True, True), lr=critic_lr,
                                             foreach=True)
        self.alpha_optim = torch.optim.Adam([self.loss.log_alpha], lr=alpha_lr, foreach=True)
        self.updates = 0
        self._fast = _FastSACTerms(self)

    @torch.no_grad()
    def act(self, observation: torch.Tensor, *, deterministic: bool = False) -> torch.Tensor:
        """An action of the policy: sampled (the same draw ``self.actor`` makes under ``RANDOM``, without its
        TensorDict plumbing), or with ``deterministic`` the mean action ``max_action * tanh(mu)``."""
        if not deterministic:
            return self._fast.distribution_at(observation).rsample()
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            td = TensorDict({"observation": observation}, batch_size=observation.shape[:-1])
            return self.actor(td)["action"]

    def losses(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        """``loss_qvalue``, ``loss_actor``, ``loss_alpha`` and ``alpha`` of ``self.loss`` (TorchRL's SACLoss v2) on
        ``batch``, computed without its TensorDict plumbing: the same networks, weights, draws (next-state action
        first, then the actor's) and formulas, about 20 % faster on CPU (benchmarks/bench_collection.py).
        ``tests/test_behaviour_agents.py`` checks it against ``self.loss(batch)``."""
        return self._fast(batch)

    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        """One gradient step on actor, critics and alpha (all from the same mini-batch), then Polyak averaging.

        Returns the detached losses and alpha as 0-d tensors (``float()`` them when logging: no sync per update).
        """
        out = self.losses(batch)
        total = out["loss_actor"] + out["loss_qvalue"] + out["loss_alpha"]
        self.actor_optim.zero_grad(set_to_none=True)
        self.critic_optim.zero_grad(set_to_none=True)
        self.alpha_optim.zero_grad(set_to_none=True)
        total.backward()  # actor loss sees detached critics, alpha loss detached log-probs: no cross-talk
        self.critic_optim.step()
        self.actor_optim.step()
        self.alpha_optim.step()
        self.target_updater.step()
        self.updates += 1
        return {k: out[k].detach() for k in ("loss_qvalue", "loss_actor", "alpha")}

    def train(self, replay, num_updates: int) -> dict[str, float] | None:
        """``num_updates`` gradient steps on mini-batches of ``replay``; the last one's losses as floats."""
        out = None
        for _ in range(int(num_updates)):
            out = self.update(replay.sample())
        return None if out is None else {k: float(v) for k, v in out.items()}

    def policy_state(self) -> dict[str, torch.Tensor]:
        return {k: v.detach().clone() for k, v in self.actor.state_dict().items()}


def _mlp_layers(params: TensorDictBase) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """``[(weight, bias), ...]`` of a TorchRL :class:`~torchrl.modules.MLP`'s parameters, in layer order."""
    leaves = dict(params.items(True, True))
    layers = sorted({key[:-1] for key in leaves}, key=lambda k: int(k[-1]))
    return [(leaves[(*k, "weight")], leaves[(*k, "bias")]) for k in layers]


class _FastSACTerms:
    """SACLoss v2's losses as plain tensor code over the loss module's own parameter tensors (no copies).

    The twin critics are the stacked ``[2, ...]`` parameters of ``SACLoss`` (and their targets), run as
    ``linear -> relu`` chains per critic; the actor is the agent's policy network and distribution class.
    """

    def __init__(self, agent: SACAgent):
        loss = agent.loss
        self.loss = loss
        self.critic = _mlp_layers(loss.qvalue_network_params)
        self.target_critic = _mlp_layers(loss.target_qvalue_network_params)
        self.params_net = agent.actor.module[0].module  # obs -> (loc, scale)
        kwargs = agent.actor.module[1].distribution_kwargs
        self.distribution = agent.actor.module[1].distribution_class
        self.low, self.high = kwargs["low"], kwargs["high"]
        self.num_critics = loss.num_qvalue_nets

    def _q(self, layers, observation: torch.Tensor, action: torch.Tensor, detach: bool = False) -> torch.Tensor:
        """``[num_critics, N]`` action values."""
        x0 = torch.cat([observation, action], -1)
        values = []
        for i in range(self.num_critics):
            x = x0
            for j, (weight, bias) in enumerate(layers):
                weight, bias = (weight[i].detach(), bias[i].detach()) if detach else (weight[i], bias[i])
                x = torch.nn.functional.linear(x, weight, bias)
                if j < len(layers) - 1:
                    x = torch.relu(x)
            values.append(x)
        return torch.stack(values).squeeze(-1)

    def distribution_at(self, observation: torch.Tensor):
        """The policy's action distribution at ``observation``."""
        loc, scale = self.params_net(observation)
        return self.distribution(loc, scale, low=self.low, high=self.high, tanh_loc=False)

    def _sample(self, observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.distribution_at(observation).rsample_and_log_prob()

    def __call__(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        loss = self.loss
        alpha = loss.log_alpha.detach().exp()
        observation, action = batch["observation"], batch["action"]
        with torch.no_grad():  # the soft TD(0) target on the target critics (bootstraps on ~terminated)
            next_observation = batch["next", "observation"]
            next_action, next_log_prob = self._sample(next_observation)
            next_q = self._q(self.target_critic, next_observation, next_action)
            next_value = (next_q - alpha * next_log_prob).min(0)[0]
            reward, terminated = batch["next", "reward"].squeeze(-1), batch["next", "terminated"].squeeze(-1)
            target = td0_return_estimate(loss.value_estimator.gamma, next_value, reward, terminated)
        predicted = self._q(self.critic, observation, action)
        loss_qvalue = distance_loss(predicted, target.expand_as(predicted),
                                    loss_function=loss.loss_function).sum(0).mean()
        new_action, log_prob = self._sample(observation)
        min_q = self._q(self.critic, observation, new_action, detach=True).min(0)[0]
        loss_actor = (alpha * log_prob - min_q).mean()
        loss_alpha = (-loss.log_alpha * (log_prob.detach() + loss.target_entropy)).mean()
        return {"loss_qvalue": loss_qvalue, "loss_actor": loss_actor, "loss_alpha": loss_alpha, "alpha": alpha}


# --------------------------------------------------------------------------------------------------------------
# the shared SAC run
# --------------------------------------------------------------------------------------------------------------


def _sac_block(cfg) -> dict:
    return dict(plain(config_value(cfg, "batch.sac")))


def sac_run_identity(cfg) -> dict:
    """What determines a SAC run: env id, its time limit, behaviour seed, the ``batch.sac`` block.

    A ``sac`` batch in oracle mode trains its own run on 2000-step episodes; execution batches always use the run
    on the env's normal time limit (oracle mode only changes how they are executed).
    """
    if config_value(cfg, "batch.recipe") == "sac":
        limit = episode_limit(cfg)
    else:
        limit = config_value(cfg, "env.max_episode_steps")
        limit = 1000 if limit is None else int(limit)
    return {"env_id": config_value(cfg, "env.id"), "max_episode_steps": limit, "seed": behaviour_seed(cfg),
            "sac": sac_identity(_sac_block(cfg), config_value(cfg, "env.id"))}


def sac_run_dir(cfg, data_dir=None) -> Path:
    identity = sac_run_identity(cfg)
    name = f"{config_value(cfg, 'env.name')}_sac_b{int(config_value(cfg, 'batch.index'))}-{stable_hash(identity)}"
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
    oracle = config_value(cfg, "batch.recipe") == "sac" and oracle_settings(cfg) is not None
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
    oracle = oracle_settings(cfg) if config_value(cfg, "batch.recipe") == "sac" else None
    seed_all(seed)
    env = make_collection_env(config_value(cfg, "env.id"), max_episode_steps=identity["max_episode_steps"], seed=seed)
    eval_limit = config_value(cfg, "env.max_episode_steps")
    evaluator = Evaluator(config_value(cfg, "env.id"), episodes=int(sac["eval_episodes"]), seed=seed + EVAL_SEED_OFFSET,
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
        desc = f"SAC {config_value(cfg, 'env.name')} b{config_value(cfg, 'batch.index')}"
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
            result = evaluator(agent.actor)
            fname = f"evals/step_{t:09d}.pt"
            snapshots[fname] = agent.policy_state()
            evaluations.append({"step": t, "return_mean": result.mean_return, "return_std": result.std_return,
                                "returns": [float(r) for r in result.returns], "failures": result.failures,
                                "gradient_steps": agent.updates, "file": fname})
            timers["eval"] += time.perf_counter() - t0
            tracker.note(eval=f"{result.mean_return:.0f}")
            log.info("SAC %s step %d: eval return %.1f +- %.1f", config_value(cfg, "env.id"), t, result.mean_return,
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
            def state() -> dict:
                for fname, weights in snapshots.items():  # each policy snapshot is written once, before state.pt
                    if not (checkpoint.directory / fname).is_file():
                        with atomic_path(checkpoint.directory / fname) as tmp:
                            torch.save(weights, tmp)
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

            resumable = Resumable(checkpoint, runner, buffers, state=state, load=load)
        data, wall = collect_timed(buffers, runner, after=evaluate_final, resumable=resumable)
    finally:
        env.close()
        evaluator.close()
    record = {
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
        "env_steps_per_s": runner.t / max(wall, 1e-9),
        "updates_per_s": agent.updates / max(timers["train"], 1e-9),
        "final_alpha": float(agent.loss.log_alpha.detach().exp()),
        "simulator_unstable_episodes": runner.unstable_episodes,
        "resumed_from_step": resumable.resumed_from_step if resumable is not None else None,
        "created_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    return data, record, snapshots


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
            os.replace(tmp, path)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return SACRun(path, record)


def _run_cfg(cfg):
    """``cfg`` with ``batch`` replaced by the ``sac`` training batch this run produces (steps = train_steps)."""
    run_cfg = copy.deepcopy(cfg)
    sac = _sac_block(cfg)
    batch = {"kind": "sac", "recipe": "sac", "index": int(config_value(cfg, "batch.index")),
             "seed": config_value(cfg, "batch.seed"), "steps": int(sac["train_steps"]), "sac": sac}
    batch.update({k: config_value(cfg, f"batch.{k}") for k in OPERATIONAL_KEYS  # how, not what: same hash
                  if config_value(cfg, f"batch.{k}") is not None})
    if OmegaConf.is_config(run_cfg):
        with open_dict(run_cfg):
            run_cfg.batch = OmegaConf.create(batch)
    else:
        run_cfg["batch"] = batch
    return run_cfg


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
            start = time.perf_counter()
            data, record, snapshots = train_sac(run_cfg, scratch=scratch, progress=progress, checkpoint=checkpoint)
            run = _save_run(path, record, snapshots)
            by_product = batch_path(run_cfg, root)
            if not by_product.exists():
                extra = _sac_batch_extra(run, data.shape[0])
                meta = batch_metadata(run_cfg, extra, wall_time_s=time.perf_counter() - start)
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
    steps = int(config_value(cfg, "batch.steps"))
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

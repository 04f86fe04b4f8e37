"""Behaviour-data collection throughput: env steps/s of the DDPG and SAC recipes, agent updates/s, and the same
updates written in bare PyTorch (same networks, same mini-batch, same optimizers) in the same process; then the
whole collection loop (the real ``collect_ddpg`` / ``train_sac`` recipes: env steps, replay writes, one update per
env step at episode ends) against a bare gymnasium + PyTorch loop doing the same work, interleaved.

    python benchmarks/bench_collection.py [--env Hopper-v5] [--steps 3000] [--updates 300] \
        [--loop-steps 1500 --loop-start 300 --loop-repeats 3]

Prints env steps/s per acting policy, the steady-state collection rate (one update per env step) with the hours a
10^6-step collection takes, and tables of updates/s and loop steps/s with ``ratio`` = torchrl_bail / bare (1.0 = no
overhead). ``--loop-steps 0`` skips the whole-loop comparison. The run's record (every round, the rates above)
goes to ``results/benchmarks/bench_collection.json`` (``--json``).
"""

from __future__ import annotations

import argparse
import copy
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("RL_WARNINGS", "0")

import gymnasium as gym  # noqa: E402
import torch  # noqa: E402
from _bench import Record, add_record_argument, bare_mlp, compare, print_table, summarise  # noqa: E402
from hydra import compose, initialize_config_dir  # noqa: E402
from tensordict import TensorDict  # noqa: E402
from torch import nn  # noqa: E402

from torchrl_bail import config_dir  # noqa: E402
from torchrl_bail.behaviour.buffers import EpisodeStore  # noqa: E402
from torchrl_bail.behaviour.ddpg import DDPGAgent, collect_ddpg  # noqa: E402
from torchrl_bail.behaviour.loop import BehaviourRun, make_collection_env  # noqa: E402
from torchrl_bail.behaviour.sac import SACAgent  # noqa: E402
from torchrl_bail.behaviour.sac_run import train_sac  # noqa: E402
from torchrl_bail.modules import action_spec_from_bounds  # noqa: E402


def _store(obs_dim: int, act_dim: int, n: int, batch_size: int, scratch: Path) -> EpisodeStore:
    store = EpisodeStore(n, scratch, batch_size=batch_size)
    g = torch.Generator().manual_seed(0)
    store.extend(TensorDict({
        "observation": torch.randn(n, obs_dim, generator=g),
        "action": torch.rand(n, act_dim, generator=g) * 2 - 1,
        "episode": torch.zeros(n, dtype=torch.int64),
        "next": {"observation": torch.randn(n, obs_dim, generator=g), "reward": torch.randn(n, 1, generator=g),
                 "done": torch.zeros(n, 1, dtype=torch.bool), "terminated": torch.rand(n, 1, generator=g) < 0.01,
                 "truncated": torch.zeros(n, 1, dtype=torch.bool)},
    }, [n]))
    return store


class BareDDPG:
    """The same DDPG update in plain PyTorch (late-action critic, critic then actor, Polyak on both)."""

    def __init__(self, obs_dim, act_dim, hidden=(400, 300)):
        self.actor = bare_mlp(obs_dim, act_dim, hidden)
        self.l1 = nn.Linear(obs_dim, hidden[0])
        self.l2 = nn.Linear(hidden[0] + act_dim, hidden[1])
        self.l3 = nn.Linear(hidden[1], 1)
        self.critic = nn.ModuleList([self.l1, self.l2, self.l3])
        self.actor_t, self.critic_t = copy.deepcopy(self.actor), copy.deepcopy(self.critic)
        self.oa = torch.optim.Adam(self.actor.parameters(), lr=1e-4)
        self.oc = torch.optim.Adam(self.critic.parameters(), lr=1e-3, weight_decay=1e-2)

    @staticmethod
    def q(c, s, a):
        h = torch.relu(c[0](s))
        return c[2](torch.relu(c[1](torch.cat([h, a], -1))))

    def update(self, b):
        s, a, r = b["observation"], b["action"], b["next", "reward"]
        s2, term = b["next", "observation"], b["next", "terminated"]
        with torch.no_grad():
            target = r + 0.99 * (~term) * self.q(self.critic_t, s2, torch.tanh(self.actor_t(s2)))
        loss_c = (self.q(self.critic, s, a) - target).pow(2).mean()
        self.oc.zero_grad()
        loss_c.backward()
        self.oc.step()
        loss_a = -self.q(self.critic, s, torch.tanh(self.actor(s))).mean()
        self.oa.zero_grad()
        loss_a.backward()
        self.oa.step()
        with torch.no_grad():
            src = list(self.actor.parameters()) + list(self.critic.parameters())
            tgt = list(self.actor_t.parameters()) + list(self.critic_t.parameters())
            torch._foreach_lerp_(tgt, src, 0.005)


class BareSAC:
    """The same SAC update in plain PyTorch (tanh-Gaussian actor, twin critics, auto alpha, Polyak 0.995)."""

    def __init__(self, obs_dim, act_dim, hidden=(256, 256)):
        self.actor = bare_mlp(obs_dim, 2 * act_dim, hidden)
        self.q1, self.q2 = bare_mlp(obs_dim + act_dim, 1, hidden), bare_mlp(obs_dim + act_dim, 1, hidden)
        self.q1_t, self.q2_t = copy.deepcopy(self.q1), copy.deepcopy(self.q2)
        self.log_alpha = torch.zeros((), requires_grad=True)
        self.target_entropy = -float(act_dim)
        self.oa = torch.optim.Adam(self.actor.parameters(), lr=3e-4)
        self.oq = torch.optim.Adam(list(self.q1.parameters()) + list(self.q2.parameters()), lr=3e-4)
        self.oal = torch.optim.Adam([self.log_alpha], lr=3e-4)

    def pi(self, s):
        mu, log_std = self.actor(s).chunk(2, -1)
        std = log_std.clamp(-20, 2).exp()
        u = mu + std * torch.randn_like(mu)
        a = torch.tanh(u)
        logp = torch.distributions.Normal(mu, std).log_prob(u).sum(-1)
        logp = logp - (2 * (torch.log(torch.tensor(2.0)) - u - nn.functional.softplus(-2 * u))).sum(-1)
        return a, logp

    def update(self, b):
        s, a, r = b["observation"], b["action"], b["next", "reward"].squeeze(-1)
        s2, term = b["next", "observation"], b["next", "terminated"].squeeze(-1)
        alpha = self.log_alpha.exp().detach()
        with torch.no_grad():
            a2, logp2 = self.pi(s2)
            sa2 = torch.cat([s2, a2], -1)
            q_t = torch.min(self.q1_t(sa2), self.q2_t(sa2)).squeeze(-1) - alpha * logp2
            target = r + 0.99 * (~term) * q_t
        sa = torch.cat([s, a], -1)
        loss_q = (self.q1(sa).squeeze(-1) - target).pow(2).mean() + (self.q2(sa).squeeze(-1) - target).pow(2).mean()
        a_pi, logp = self.pi(s)
        sa_pi = torch.cat([s, a_pi], -1)
        for p in list(self.q1.parameters()) + list(self.q2.parameters()):
            p.requires_grad_(False)
        loss_pi = (alpha * logp - torch.min(self.q1(sa_pi), self.q2(sa_pi)).squeeze(-1)).mean()
        for p in list(self.q1.parameters()) + list(self.q2.parameters()):
            p.requires_grad_(True)
        loss_alpha = -(self.log_alpha * (logp.detach() + self.target_entropy)).mean()
        for o in (self.oa, self.oq, self.oal):
            o.zero_grad()
        (loss_q + loss_pi + loss_alpha).backward()
        for o in (self.oa, self.oq, self.oal):
            o.step()
        with torch.no_grad():
            src = list(self.q1.parameters()) + list(self.q2.parameters())
            tgt = list(self.q1_t.parameters()) + list(self.q2_t.parameters())
            torch._foreach_lerp_(tgt, src, 0.005)


def bench_updates(obs_dim, act_dim, updates: int, scratch: Path) -> list[dict]:
    """Agent updates/s (replay sample + update) beside the bare-PyTorch twin, interleaved in one process."""
    spec = action_spec_from_bounds([-1.0] * act_dim, [1.0] * act_dim)
    rows = []
    for name, agent_cls, bare_cls, batch in (("DDPG update (batch 100)", DDPGAgent, BareDDPG, 100),
                                            ("SAC update (batch 256)", SACAgent, BareSAC, 256)):
        store = _store(obs_dim, act_dim, 20_000, batch, scratch / agent_cls.__name__)
        data = store.rb.storage._storage
        agent, bare = agent_cls(obs_dim, spec), bare_cls(obs_dim, act_dim)
        rows.append(compare(name, lambda a=agent, s=store: a.update(s.sample()),
                            lambda b=bare, d=data, k=batch: b.update(d[torch.randint(0, 20_000, (k,))]),
                            n=updates))
    return rows


def bench_env(env_id: str, steps: int, obs_dim: int, act_dim: int) -> dict:
    """Env steps/s of the collection loop without learning: random actions, DDPG actor + noise, SAC sampling."""

    out = {}
    spec = action_spec_from_bounds([-1.0] * act_dim, [1.0] * act_dim)
    ddpg = DDPGAgent(obs_dim, spec)
    sac = SACAgent(obs_dim, spec)
    policies = {
        "random": lambda o, t: torch.rand(act_dim) * 2 - 1,
        "ddpg_actor": lambda o, t: (ddpg.act(o) + 0.1 * torch.randn(act_dim)).clamp(-1, 1),
        "sac_actor": lambda o, t: sac.act(o),
    }
    for name, act in policies.items():
        env = make_collection_env(env_id, max_episode_steps=None, seed=0)
        run = BehaviourRun(env, act)
        t = time.perf_counter()
        run.run([], until=lambda open_rows, n=steps, r=run: r.t >= n)
        out[f"env_steps_per_s_{name}"] = steps / (time.perf_counter() - t)
        env.close()
    return out


ENV_NAMES = {"Hopper-v5": "hopper", "Walker2d-v5": "walker", "HalfCheetah-v5": "halfcheetah", "Ant-v5": "ant",
             "Humanoid-v5": "humanoid"}


def _recipe_cfg(env_id: str, batch: str, steps: int, start: int):
    overrides = [f"env={ENV_NAMES[env_id]}", f"batch={batch}", f"batch.steps={steps}"]
    if batch == "sac":  # no evaluation inside the loop; the one final evaluation is timed and subtracted
        overrides += [f"batch.sac.start_steps={start}", "batch.sac.eval_every=1000000000",
                      "batch.sac.eval_episodes=1"]
    else:
        overrides += [f"batch.start_steps={start}"]
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        return compose("config", overrides=overrides)


def bare_loop(env_id: str, steps: int, start: int, algo: str, seed: int, *, sigma: float = 0.5) -> float:
    """Seconds for ``steps`` env steps of a plain gymnasium loop + bare PyTorch agent doing the recipe's work:
    ``start`` random steps, then the policy (DDPG: ``mu(s)`` + N(0, sigma) clipped; SAC: a sample), transitions
    stored in preallocated tensors, ``length`` updates at the end of every episode (as the recipes)."""
    torch.manual_seed(seed)
    env = gym.make(env_id, max_episode_steps=1000)
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
    low = torch.as_tensor(env.action_space.low, dtype=torch.float32)
    high = torch.as_tensor(env.action_space.high, dtype=torch.float32)
    agent, batch = (BareDDPG(obs_dim, act_dim), 100) if algo == "ddpg" else (BareSAC(obs_dim, act_dim), 256)
    store = {"observation": torch.zeros(steps, obs_dim), "action": torch.zeros(steps, act_dim),
             ("next", "observation"): torch.zeros(steps, obs_dim), ("next", "reward"): torch.zeros(steps, 1),
             ("next", "terminated"): torch.zeros(steps, 1, dtype=torch.bool)}
    start_time = time.perf_counter()
    obs = torch.as_tensor(env.reset(seed=seed)[0], dtype=torch.float32)
    length = 0
    for t in range(steps):
        if t < start:
            action = low + (high - low) * torch.rand(act_dim)
        else:
            with torch.no_grad():
                if algo == "ddpg":
                    action = torch.tanh(agent.actor(obs)) * high + sigma * torch.randn(act_dim)
                    action = torch.maximum(torch.minimum(action, high), low)
                else:
                    action = agent.pi(obs)[0] * high
        next_obs, reward, terminated, truncated, _ = env.step(action.numpy())
        next_obs = torch.as_tensor(next_obs, dtype=torch.float32)
        for key, value in (("observation", obs), ("action", action), (("next", "observation"), next_obs),
                           (("next", "reward"), reward), (("next", "terminated"), terminated)):
            store[key][t] = value if isinstance(value, torch.Tensor) else torch.as_tensor(value)
        length += 1
        obs = next_obs
        if terminated or truncated:
            if t + 1 < steps:  # the recipes train at every episode end until the batch is full
                data = TensorDict({k: v[: t + 1] for k, v in store.items()}, [t + 1])
                for _ in range(length):
                    agent.update(data[torch.randint(0, t + 1, (batch,))])
            obs = torch.as_tensor(env.reset()[0], dtype=torch.float32)
            length = 0
    env.close()
    return time.perf_counter() - start_time


def library_loop(env_id: str, steps: int, start: int, algo: str, scratch: Path) -> float:
    """Seconds of the real recipe for ``steps`` env steps (SAC: minus its one final evaluation)."""
    cfg = _recipe_cfg(env_id, "ddpg05" if algo == "ddpg" else "sac", steps, start)
    run_dir = Path(tempfile.mkdtemp(dir=scratch))
    start_time = time.perf_counter()
    if algo == "ddpg":
        collect_ddpg(cfg, scratch=run_dir, progress=False)
        return time.perf_counter() - start_time
    _, record, _ = train_sac(cfg, scratch=run_dir, progress=False)
    return time.perf_counter() - start_time - record["eval_time_s"]


def bench_loops(env_id: str, steps: int, start: int, repeats: int, scratch: Path) -> list[dict]:
    """Whole collection loops, torchrl_bail vs bare, alternating rounds; medians of env steps/s."""
    rows = []
    for algo, name in (("ddpg", "DDPG collection loop"), ("sac", "SAC collection loop")):
        lib, bare = [], []
        for r in range(repeats):
            lib.append(steps / library_loop(env_id, steps, start, algo, scratch))
            bare.append(steps / bare_loop(env_id, steps, start, algo, seed=r))
        rows.append(summarise(f"{name} ({steps} steps, {start} random)", "env steps/s",
                              {"torchrl_bail": lib, "bare": bare}))
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--env", default="Hopper-v5")
    p.add_argument("--steps", type=int, default=3000, help="env steps per loop measurement")
    p.add_argument("--updates", type=int, default=300, help="updates per update measurement")
    p.add_argument("--loop-steps", type=int, default=1500, help="env steps per whole-loop run (0: skip)")
    p.add_argument("--loop-start", type=int, default=300, help="random steps before learning in the loop runs")
    p.add_argument("--loop-repeats", type=int, default=3)
    add_record_argument(p, __file__)
    args = p.parse_args(argv)
    record = Record(__file__, args.json, reference="bare PyTorch (+ bare gymnasium loop)", settings=vars(args))
    torch.manual_seed(0)
    env = make_collection_env(args.env, max_episode_steps=None, seed=0)
    obs_dim = env.observation_spec["observation"].shape[-1]
    act_dim = env.action_spec.shape[-1]
    env.close()
    res = {"env": args.env, "threads": torch.get_num_threads()}
    with tempfile.TemporaryDirectory() as d:
        res.update(bench_env(args.env, args.steps, obs_dim, act_dim))
        rows = bench_updates(obs_dim, act_dim, args.updates, Path(d))
        loops = bench_loops(args.env, args.loop_steps, args.loop_start, args.loop_repeats, Path(d)) \
            if args.loop_steps > 0 else []
    for algo, row in zip(("ddpg", "sac"), rows, strict=True):
        res[f"{algo}_updates_per_s"] = row["torchrl_bail"]
        res[f"{algo}_ratio_torchrl_bail_over_bare"] = row["ratio"]
        # one update per env step: the steady-state collection rate of the recipe
        env_rate = res["env_steps_per_s_ddpg_actor" if algo == "ddpg" else "env_steps_per_s_sac_actor"]
        res[f"{algo}_collection_steps_per_s"] = 1 / (1 / env_rate + 1 / row["torchrl_bail"])
        res[f"{algo}_hours_per_1e6_steps"] = 1e6 / res[f"{algo}_collection_steps_per_s"] / 3600
    width = max(len(k) for k in res)
    for k, v in res.items():
        print(f"{k:<{width}}  {v:.2f}" if isinstance(v, float) else f"{k:<{width}}  {v}")
    print_table(rows, "Behaviour-agent updates/s: torchrl_bail vs bare PyTorch (ratio = torchrl_bail / bare)")
    for row in loops:
        res[f"{row['name'].split()[0].lower()}_loop_ratio_torchrl_bail_over_bare"] = row["ratio"]
    if loops:
        print_table(loops, "Whole collection loop, env steps/s: the recipe vs a bare gymnasium + PyTorch loop")
    record.write([*rows, *loops], collection=res)
    return 0


if __name__ == "__main__":
    sys.exit(main())

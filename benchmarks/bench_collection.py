"""Behaviour-data collection throughput: env steps/s of the DDPG and SAC recipes, agent updates/s, and the same
updates written in bare PyTorch (same networks, same mini-batch, same optimizers) in the same process.

    python benchmarks/bench_collection.py [--env Hopper-v5] [--steps 3000] [--updates 300]

Prints env steps/s per acting policy, the steady-state collection rate (one update per env step) with the hours a
10^6-step collection takes, and a table of updates/s with ``ratio`` = torchrl_bail / bare (1.0 = no overhead).
With ``--json PATH`` the numbers are also written as JSON.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("RL_WARNINGS", "0")

import torch  # noqa: E402
from _bench import bare_mlp, compare, print_table  # noqa: E402
from tensordict import TensorDict  # noqa: E402
from torch import nn  # noqa: E402

from torchrl_bail.behaviour.buffers import EpisodeStore  # noqa: E402
from torchrl_bail.behaviour.ddpg import DDPGAgent  # noqa: E402
from torchrl_bail.behaviour.loop import BehaviourRun, make_collection_env  # noqa: E402
from torchrl_bail.behaviour.sac import SACAgent  # noqa: E402
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


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--env", default="Hopper-v5")
    p.add_argument("--steps", type=int, default=3000, help="env steps per loop measurement")
    p.add_argument("--updates", type=int, default=300, help="updates per update measurement")
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    torch.manual_seed(0)
    env = make_collection_env(args.env, max_episode_steps=None, seed=0)
    obs_dim = env.observation_spec["observation"].shape[-1]
    act_dim = env.action_spec.shape[-1]
    env.close()
    res = {"env": args.env, "threads": torch.get_num_threads()}
    with tempfile.TemporaryDirectory() as d:
        res.update(bench_env(args.env, args.steps, obs_dim, act_dim))
        rows = bench_updates(obs_dim, act_dim, args.updates, Path(d))
    for algo, row in zip(("ddpg", "sac"), rows):
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
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

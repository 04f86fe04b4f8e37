"""BCQ and BEAR throughput: one library update step per iteration beside a bare PyTorch loop doing the same math
(same networks, same mini-batch, same optimizers, same order) in the same process.

    python benchmarks/bench_bcq_bear.py [--updates 30] [--repeats 5] [--threads 1] [--json PATH]

Paper sizes (supp. C.2, BCQ, 8.4): VAE 750-750 (latent 2 |A|), actor and critics 400-300, batch 100, Hopper shapes
(obs 11, act 3), 10 next-state samples, BEAR with 5 MMD samples and its warm start over (the full objective).

The library side is exactly what a run executes per iteration (:func:`torchrl_bail.training.trainer.train`):
``TensorDictReplayBuffer.sample()`` of 100 with replacement, then :meth:`BCQ.update` / :meth:`BEAR.update`
(:class:`~torchrl_bail.objectives.BCQLoss` / :class:`~torchrl_bail.objectives.BEARLoss` sub-losses, four or
five Adam steps, the fused :class:`~torchrl.objectives.SoftUpdate`). The bare side indexes the same tensors and
runs plain ``nn.Sequential`` networks with hand-written losses and the same fused ``torch.optim.Adam`` as the
library (so the ratio measures the library's overhead, not the optimizer kernel; ``bench_d3rlpy.py`` compares
with d3rlpy 2.8, which uses torch's default per-tensor Adam).

Threads: one by default, as the authors' jobs ran (one CPU core each, supp. H). On a shared 2-core machine
two intra-op threads make every update wait on a descheduled thread, and the same code then swings between
ratios 0.6 and 1.0 from one round to the next; ``--threads 0`` keeps torch's default anyway.
"""

from __future__ import annotations

import argparse

import torch
from _bench import Record, add_record_argument, bare_mlp, compare, print_table
from tensordict import TensorDict
from torch import nn
from torchrl.data import RandomSampler, TensorDictReplayBuffer, TensorStorage

from torchrl_bail.algorithms.bcq import BCQ
from torchrl_bail.algorithms.bear import BEAR
from torchrl_bail.configuration.config_builders import algo_config
from torchrl_bail.modules import action_spec_from_bounds

OBS, ACT, BATCH, N_TARGET, N_MATCH = 11, 3, 100, 10, 5
LATENT = 2 * ACT


def synthetic_data(n: int) -> TensorDict:
    g = torch.Generator().manual_seed(0)
    return TensorDict({
        "observation": torch.randn(n, OBS, generator=g),
        "action": torch.rand(n, ACT, generator=g) * 2 - 1,
        "next": {"observation": torch.randn(n, OBS, generator=g), "reward": torch.randn(n, 1, generator=g),
                 "terminated": torch.rand(n, 1, generator=g) < 0.01,
                 "truncated": torch.zeros(n, 1, dtype=torch.bool)},
    }, [n])


class BareVAE(nn.Module):
    def __init__(self):
        super().__init__()
        self.enc = bare_mlp(OBS + ACT, 2 * LATENT, (750, 750))
        self.dec = bare_mlp(OBS + LATENT, ACT, (750, 750))

    def loss(self, s, a):
        mean, log_std = self.enc(torch.cat([s, a], -1)).chunk(2, -1)
        log_std = log_std.clamp(-4, 15)
        std = log_std.exp()
        recon = torch.tanh(self.dec(torch.cat([s, mean + std * torch.randn_like(std)], -1)))
        kl = -0.5 * (1 + torch.log(std.pow(2)) - mean.pow(2) - std.pow(2)).mean()
        return nn.functional.mse_loss(recon, a) + 0.5 * kl

    def decode_raw(self, s):
        z = torch.randn(*s.shape[:-1], LATENT).clamp(-0.5, 0.5)
        raw = self.dec(torch.cat([s, z], -1))
        return torch.tanh(raw), raw


class BareTwinCritic(nn.Module):
    def __init__(self):
        super().__init__()
        self.q1 = bare_mlp(OBS + ACT, 1, (400, 300))
        self.q2 = bare_mlp(OBS + ACT, 1, (400, 300))

    def forward(self, s, a):
        x = torch.cat([s, a], -1)
        return self.q1(x), self.q2(x)


class BareBase:
    """The VAE and critic steps and the Polyak update, shared by the two bare loops."""

    def __init__(self, actor: nn.Module, data: TensorDict):
        self.vae, self.critic, self.actor = BareVAE(), BareTwinCritic(), actor
        self.critic_t, self.actor_t = BareTwinCritic(), type(actor)()
        self.critic_t.load_state_dict(self.critic.state_dict())
        self.actor_t.load_state_dict(self.actor.state_dict())
        self.ov = torch.optim.Adam(self.vae.parameters(), lr=1e-3, fused=True)
        self.oc = torch.optim.Adam(self.critic.parameters(), lr=1e-3, fused=True)
        self.oa = torch.optim.Adam(self.actor.parameters(), lr=1e-3, fused=True)
        self.targets = list(self.critic_t.parameters()) + list(self.actor_t.parameters())
        self.sources = list(self.critic.parameters()) + list(self.actor.parameters())
        self.s, self.a = data["observation"], data["action"]
        self.s2, self.r = data["next", "observation"], data["next", "reward"]
        self.not_done = 1.0 - data["next", "terminated"].float()
        self.n = data.shape[0]

    def sample(self):
        i = torch.randint(self.n, (BATCH,))
        return self.s[i], self.a[i], self.r[i], self.s2[i], self.not_done[i]

    def vae_and_critic(self, s, a, r, s2, not_done):
        loss = self.vae.loss(s, a)
        self.ov.zero_grad()
        loss.backward()
        self.ov.step()
        with torch.no_grad():
            s2_rep = s2.repeat_interleave(N_TARGET, 0)
            t1, t2 = self.critic_t(s2_rep, self.target_actions(s2, s2_rep))
            tq = 0.75 * torch.min(t1, t2) + 0.25 * torch.max(t1, t2)
            y = r + not_done * 0.99 * tq.view(BATCH, -1).max(1)[0].view(-1, 1)
        q1, q2 = self.critic(s, a)
        loss = nn.functional.mse_loss(q1, y) + nn.functional.mse_loss(q2, y)
        self.oc.zero_grad()
        loss.backward()
        self.oc.step()

    def polyak(self):
        with torch.no_grad():
            torch._foreach_lerp_(self.targets, self.sources, 0.005)


class BarePerturbation(nn.Module):
    def __init__(self):
        super().__init__()
        self.net = bare_mlp(OBS + ACT, ACT, (400, 300))

    def forward(self, s, a):
        return (a + 0.05 * torch.tanh(self.net(torch.cat([s, a], -1)))).clamp(-1, 1)


class BareBCQ(BareBase):
    def __init__(self, data):
        super().__init__(BarePerturbation(), data)

    def target_actions(self, s2, s2_rep):
        return self.actor_t(s2_rep, self.vae.decode_raw(s2_rep)[0])

    def update(self):
        s, a, r, s2, not_done = self.sample()
        self.vae_and_critic(s, a, r, s2, not_done)
        with torch.no_grad():
            sampled = self.vae.decode_raw(s)[0]
        loss = -self.critic.q1(torch.cat([s, self.actor(s, sampled)], -1)).mean()
        self.oa.zero_grad()
        loss.backward()
        self.oa.step()
        self.polyak()


class BareGaussian(nn.Module):
    def __init__(self):
        super().__init__()
        self.net = bare_mlp(OBS, 2 * ACT, (400, 300))

    def forward(self, s):
        mean, log_std = self.net(s).chunk(2, -1)
        return mean, log_std.exp()


def laplacian_mmd(x, y, sigma=10.0):
    def k(u, v):
        return (-(u.unsqueeze(2) - v.unsqueeze(1)).abs().sum(-1) / (2.0 * sigma)).exp().mean((1, 2))

    return (k(x, x) + k(y, y) - 2.0 * k(x, y) + 1e-6).sqrt()


class BareBEAR(BareBase):
    def __init__(self, data):
        super().__init__(BareGaussian(), data)
        self.log_alpha = torch.randn((), requires_grad=True)
        self.ol = torch.optim.Adam([self.log_alpha], lr=1e-3, fused=True)

    def target_actions(self, s2, s2_rep):
        # the actor once per state and N noises (the library's equivalent of the authors' repeated states)
        mean, std = self.actor_t(s2)
        noise = torch.randn(BATCH, N_TARGET, ACT)
        return torch.tanh(mean.unsqueeze(1) + std.unsqueeze(1) * noise).reshape(BATCH * N_TARGET, ACT)

    def update(self):
        s, a, r, s2, not_done = self.sample()
        self.vae_and_critic(s, a, r, s2, not_done)
        with torch.no_grad():
            _, vae_raw = self.vae.decode_raw(s.unsqueeze(1).expand(BATCH, N_MATCH, OBS))
        mean, std = self.actor(s)
        raw = mean.unsqueeze(1) + std.unsqueeze(1) * torch.randn(BATCH, N_MATCH, ACT).clamp(-0.5, 0.5)
        actions = torch.tanh(raw)
        mmd = laplacian_mmd(vae_raw, raw)
        s_rep = s.unsqueeze(1).expand(BATCH, N_MATCH, OBS)
        q1, q2 = self.critic(s_rep, actions)  # the critic's gradients are discarded by its next zero_grad
        q = torch.min(q1.mean(1), q2.mean(1)).squeeze(-1)
        loss = (-q + self.log_alpha.exp().detach() * mmd).mean()
        self.oa.zero_grad()
        loss.backward()
        self.oa.step()
        lagrange = -(-q.detach() + self.log_alpha.exp() * (mmd.detach() - 0.05)).mean()
        self.ol.zero_grad()
        lagrange.backward()
        self.ol.step()
        with torch.no_grad():
            self.log_alpha.clamp_(-5.0, 10.0)
        self.polyak()


def bench(name: str, algo_cls, bare_cls, data: TensorDict, n_updates: int, repeats: int, **kwargs) -> dict:
    spec = action_spec_from_bounds([-1.0] * ACT, [1.0] * ACT)
    torch.manual_seed(0)
    algo = algo_cls(OBS, spec, algo_config(algo_cls.name, batch_size=BATCH, **kwargs))
    buffer = TensorDictReplayBuffer(storage=TensorStorage(data), sampler=RandomSampler(), batch_size=BATCH)
    torch.manual_seed(0)
    bare = bare_cls(data)
    return compare(name, lambda: algo.update(buffer.sample()), bare.update, n=n_updates, repeats=repeats)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--updates", type=int, default=30, help="updates per timed round")
    parser.add_argument("--repeats", type=int, default=5, help="alternating rounds per side")
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads (0: torch's default)")
    add_record_argument(parser, __file__)
    args = parser.parse_args()
    record = Record(__file__, args.json, reference="bare PyTorch", settings=vars(args))
    if args.threads:
        torch.set_num_threads(args.threads)
    data = synthetic_data(100_000)
    rows = [
        bench("BCQ update (batch 100)", BCQ, BareBCQ, data, args.updates, args.repeats),
        bench("BEAR update (batch 100)", BEAR, BareBEAR, data, args.updates, args.repeats, warm_start_updates=0),
    ]
    print_table(rows, "BCQ / BEAR updates/s: torchrl_bail vs bare PyTorch, same process (ratio = torchrl_bail / bare)")
    record.write(rows)


if __name__ == "__main__":
    main()

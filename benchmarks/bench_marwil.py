"""MARWIL throughput: the library's update step beside a bare PyTorch loop doing the same math (same network
sizes, same mini-batches, same optimizers) in the same process.

    python benchmarks/bench_marwil.py [--updates 1] [--repeats 301] [--threads N] [--json PATH]

Two rows on Hopper sizes (obs 11, act 3) with the paper configuration ``conf/algo/marwil.yaml`` (actor 400-300,
value 128-128, mini-batch 1000, beta, c^2, ...), the library side built by the registry exactly as a run does:

* ``update``: :meth:`torchrl_bail.algorithms.marwil.MARWIL.update` (one :class:`MARWILLoss` call with its
  diagnostics, one backward, an Adam step per network) on pre-drawn mini-batches, against the bare twin on the
  very same tensors;
* ``iteration``: what :func:`torchrl_bail.training.trainer.train` runs per iteration,
``TensorDictReplayBuffer.sample()``
  (with replacement) from the data :meth:`MARWIL.prepare` returns, then the update; the bare side indexes with
  ``torch.randint``.

``ratio`` = torchrl_bail updates/s / bare updates/s (1.0 = no overhead). By default every round is a single
update and the two sides alternate round by round (rates are medians over the rounds), so that a noisy neighbour
on a shared machine, whose load comes and goes within seconds, hits both sides alike.
"""

from __future__ import annotations

import argparse

import torch
from _bench import Record, add_record_argument, bare_mlp, compare, print_table
from tensordict import TensorDict
from torchrl.data import RandomSampler, TensorDictReplayBuffer, TensorStorage

from torchrl_bail.algorithms import PrepareContext
from torchrl_bail.algorithms.marwil import MARWIL
from torchrl_bail.configuration.config_builders import algo_config
from torchrl_bail.modules import action_spec_from_bounds

OBS, ACT = 11, 3  # Hopper-v5
CFG = algo_config("marwil")


class BareMARWIL:
    """The same update in plain PyTorch: tanh actor (bounds +-1), value net, running c^2, two Adams."""

    def __init__(self) -> None:
        self.actor = bare_mlp(OBS, ACT, CFG.policy.hidden)
        self.value = bare_mlp(OBS, 1, CFG.value.hidden)
        with torch.no_grad():  # the library's value head init (default x 0.1, bias 0)
            self.value[-1].weight.mul_(0.1)
            self.value[-1].bias.zero_()
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=CFG.policy.lr)
        self.value_opt = torch.optim.Adam(self.value.parameters(), lr=CFG.value.lr)
        self.c2 = torch.tensor(CFG.c2_init, dtype=torch.float64)

    def update(self, obs: torch.Tensor, act: torch.Tensor, ret: torch.Tensor) -> None:
        adv = ret - self.value(obs).squeeze(-1)
        loss_value = CFG.vf_coeff * 0.5 * adv.square().mean()
        with torch.no_grad():
            a = adv.detach()
            self.c2 += CFG.c2_rate * (a.square().mean().double() - self.c2)
            weight = (CFG.beta * a / (self.c2.sqrt().float() + 1e-8)).clamp_max(CFG.max_exponent).exp()
        loss_actor = (weight * (torch.tanh(self.actor(obs)) - act).square().mean(-1)).mean()
        self.actor_opt.zero_grad(set_to_none=True)
        self.value_opt.zero_grad(set_to_none=True)
        (loss_actor + loss_value).backward()
        self.actor_opt.step()
        self.value_opt.step()


def make_data(n: int, seed: int) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    return TensorDict({"observation": torch.randn(n, OBS, generator=g),
                       "action": torch.rand(n, ACT, generator=g) * 2 - 1,
                       "return": torch.rand(n, generator=g) * 300,
                       "episode": torch.zeros(n, dtype=torch.int64)}, [n])


def make_library() -> MARWIL:
    torch.manual_seed(0)
    return MARWIL(OBS, action_spec_from_bounds([-1.0] * ACT, [1.0] * ACT), CFG)


def bench_update(n_updates: int, repeats: int) -> dict:
    pool = make_data(CFG.batch_size * 8, seed=1).select("observation", "action", "return").split(CFG.batch_size)
    plain = [(b["observation"], b["action"], b["return"]) for b in pool]
    algo, bare_algo = make_library(), BareMARWIL()
    cursor = {"lib": 0, "bare": 0}

    def library():
        cursor["lib"] = (cursor["lib"] + 1) % len(pool)
        algo.update(pool[cursor["lib"]])

    def bare():
        cursor["bare"] = (cursor["bare"] + 1) % len(plain)
        bare_algo.update(*plain[cursor["bare"]])

    return compare(f"MARWIL update (batch {CFG.batch_size})", library, bare, n=n_updates, repeats=repeats)


def bench_iteration(n_updates: int, repeats: int) -> dict:
    n = 300_000
    data = make_data(n, seed=2)
    algo, bare_algo = make_library(), BareMARWIL()
    prepared = algo.prepare(data, PrepareContext())
    buffer = TensorDictReplayBuffer(storage=TensorStorage(prepared), sampler=RandomSampler(),
                                    batch_size=algo.batch_size)
    obs, act, ret = data["observation"], data["action"], data["return"]

    def library():
        algo.update(buffer.sample())

    def bare():
        index = torch.randint(n, (CFG.batch_size,))
        bare_algo.update(obs[index], act[index], ret[index])

    return compare("MARWIL iteration (sample + update)", library, bare, n=n_updates, repeats=repeats)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--updates", type=int, default=1, help="updates per timed round")
    parser.add_argument("--repeats", type=int, default=301, help="alternating rounds per side")
    parser.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    add_record_argument(parser, __file__)
    args = parser.parse_args()
    record = Record(__file__, args.json, reference="bare PyTorch", settings=vars(args))
    if args.threads:
        torch.set_num_threads(args.threads)
    print(f"actor {list(CFG.policy.hidden)}, value {list(CFG.value.hidden)}, batch {CFG.batch_size}, obs {OBS}, "
          f"act {ACT}, beta {CFG.beta}, c2 {CFG.c2_init} (rate {CFG.c2_rate})")
    rows = [bench_update(args.updates, args.repeats), bench_iteration(args.updates, args.repeats)]
    print_table(rows, "MARWIL updates/s: torchrl_bail vs bare PyTorch, same process (ratio = torchrl_bail / bare)")
    record.write(rows)


if __name__ == "__main__":
    main()

"""FQE throughput: the fit of ``python -m torchrl_bail.ope`` beside a bare PyTorch twin doing the same math (same
network sizes, mini-batch, Adam, target copy period) in the same process.

    python benchmarks/bench_fqe.py [--updates 100] [--repeats 21] [--fit-updates 2000] [--fit-repeats 5]
                                   [--threads N] [--json PATH]

At the defaults of :class:`torchrl_bail.ope.FQESettings` (Q network ``(s, a) -> 256 -> 256 -> 1``, Adam at
``1e-4``, mini-batches of 100 drawn with replacement, the target copied every 100 updates, ``gamma = 0.99``), on
Hopper sizes (obs 11, act 3) and a synthetic batch of 10^5 transitions (100 episodes of 1000 steps), the policy
evaluated being BAIL's deterministic actor (400-300):

* ``update``: what :func:`~torchrl_bail.ope.fit_fqe` runs per update: the mini-batch index from its generator, the
  rows gathered from the TensorDict that holds the policy's actions (:meth:`FQELoss.add_policy_actions`), then
  :func:`~torchrl_bail.ope.fqe_update` (:meth:`FQELoss.qvalue_loss`, one backward, an Adam step, TorchRL's
  :class:`~torchrl.objectives.HardUpdate`) and the TD-loss sum of the curve; the bare side indexes plain tensors,
  runs an ``nn.Sequential`` and its target copy (``load_state_dict`` every 100 updates). Each timed round is
  ``--updates`` updates (100: one target copy per round on both sides);
* ``fit``: a whole :func:`~torchrl_bail.ope.fit_fqe` of ``--fit-updates`` updates (the network built, the policy's
  actions at every state and next state, the loop, the estimate over the episode starts at the end) against the
  same fit written in plain PyTorch; its rate is updates per second of the whole fit.

``ratio`` = torchrl_bail updates/s / bare updates/s (1.0 = no overhead). The two sides alternate round by round
(rates are medians over the rounds), so that a noisy neighbour on a shared machine hits both alike.
"""

from __future__ import annotations

import argparse
import time

import torch
from _bench import Record, add_record_argument, bare_mlp, print_table, summarise
from tensordict import TensorDict
from torchrl.objectives import HardUpdate

from torchrl_bail.modules import action_spec_from_bounds, make_deterministic_actor, make_qvalue_network
from torchrl_bail.objectives.fqe import FQELoss, episode_starts
from torchrl_bail.ope import FQESettings, fit_fqe, fqe_update

OBS, ACT = 11, 3  # Hopper-v5
N, EPISODE = 100_000, 1000
SETTINGS = FQESettings()
POLICY_HIDDEN = (400, 300)  # BAIL's actor (supp. C.3)


def make_data(seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    episode = torch.arange(N) // EPISODE
    return TensorDict({
        "observation": torch.randn(N, OBS, generator=g), "action": torch.rand(N, ACT, generator=g) * 2 - 1,
        "episode": episode,
        "next": {"observation": torch.randn(N, OBS, generator=g), "reward": torch.randn(N, 1, generator=g),
                 "terminated": torch.zeros(N, 1, dtype=torch.bool)},
    }, [N])


def make_policy():
    torch.manual_seed(1)
    policy = make_deterministic_actor(OBS, action_spec_from_bounds([-1.0] * ACT, [1.0] * ACT), POLICY_HIDDEN)
    return policy.eval().requires_grad_(False)


class LibraryFQE:
    """:func:`fit_fqe`'s state and update, as it builds them."""

    def __init__(self, policy, data: TensorDict, seed: int = 0) -> None:
        torch.manual_seed(seed)
        self.loss = FQELoss(make_qvalue_network(OBS, ACT, SETTINGS.hidden), policy, gamma=SETTINGS.gamma)
        self.updater = HardUpdate(self.loss, value_network_update_interval=SETTINGS.target_update_period - 1)
        self.data = self.loss.add_policy_actions(data.clone())
        self.optimizer = torch.optim.Adam(self.loss.parameters(), lr=SETTINGS.lr)
        self.generator = torch.Generator().manual_seed(seed)
        self.td_sum = torch.zeros((), dtype=torch.float64)

    def update(self) -> None:
        index = torch.randint(N, (SETTINGS.batch_size,), generator=self.generator)
        self.td_sum += fqe_update(self.loss, self.optimizer, self.updater, self.data[index])


class BareFQE:
    """The same fit in plain PyTorch: ``nn.Sequential`` Q network and target, the policy's actions computed once."""

    def __init__(self, policy, data: TensorDict, seed: int = 0) -> None:
        torch.manual_seed(seed)
        self.q = bare_mlp(OBS + ACT, 1, SETTINGS.hidden)
        self.target = bare_mlp(OBS + ACT, 1, SETTINGS.hidden).requires_grad_(False)
        self.target.load_state_dict(self.q.state_dict())
        self.optimizer = torch.optim.Adam(self.q.parameters(), lr=SETTINGS.lr)
        self.generator = torch.Generator().manual_seed(seed)
        self.td_sum = torch.zeros((), dtype=torch.float64)
        self.count = 0
        with torch.no_grad():
            act = torch.cat([policy(TensorDict({"observation": o}, [len(o)]))["action"]
                             for o in data["observation"].split(65536)])
            next_act = torch.cat([policy(TensorDict({"observation": o}, [len(o)]))["action"]
                                  for o in data["next", "observation"].split(65536)])
        self.obs, self.action = data["observation"], data["action"]
        self.next_obs, self.next_act = data["next", "observation"], next_act
        self.reward = data["next", "reward"].squeeze(-1)
        self.not_terminated = (~data["next", "terminated"].squeeze(-1)).float()
        starts = episode_starts(data["episode"])
        self.start_obs, self.start_act = self.obs[starts], act[starts]

    def update(self) -> None:
        index = torch.randint(N, (SETTINGS.batch_size,), generator=self.generator)
        with torch.no_grad():
            next_q = self.target(torch.cat([self.next_obs[index], self.next_act[index]], -1)).squeeze(-1)
            y = self.reward[index] + SETTINGS.gamma * self.not_terminated[index] * next_q
        q = self.q(torch.cat([self.obs[index], self.action[index]], -1)).squeeze(-1)
        loss = (q - y).square().mean()
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        self.count += 1
        if self.count % SETTINGS.target_update_period == 0:
            self.target.load_state_dict(self.q.state_dict())
        self.td_sum += loss.detach()

    @torch.no_grad()
    def estimate(self) -> float:
        return float(self.q(torch.cat([self.start_obs, self.start_act], -1)).mean())


def _timed(fn, n: int) -> float:
    start = time.perf_counter()
    for _ in range(n):
        fn()
    return n / (time.perf_counter() - start)


def bench_update(policy, data: TensorDict, updates: int, repeats: int) -> dict:
    library, bare = LibraryFQE(policy, data), BareFQE(policy, data)
    _timed(library.update, updates)  # warm-up: one round each
    _timed(bare.update, updates)
    rounds: dict[str, list[float]] = {"torchrl_bail": [], "bare": []}
    for _ in range(repeats):
        rounds["torchrl_bail"].append(_timed(library.update, updates))
        rounds["bare"].append(_timed(bare.update, updates))
    return summarise(f"FQE update (sample + update, batch {SETTINGS.batch_size}, Q 256-256)", "updates/s", rounds,
                     updates_per_round=updates)


def bare_fit(policy, data: TensorDict, updates: int, seed: int = 0) -> float:
    fit = BareFQE(policy, data, seed)
    for _ in range(updates):
        fit.update()
    return fit.estimate()


def bench_fit(policy, data: TensorDict, updates: int, repeats: int) -> dict:
    settings = FQESettings(updates=updates, log_every=updates)

    def library() -> None:
        fit_fqe(policy, data, settings, seed=0)

    def bare() -> None:
        bare_fit(policy, data, updates, seed=0)

    library()  # warm-up
    bare()
    rounds: dict[str, list[float]] = {"torchrl_bail": [], "bare": []}
    for _ in range(repeats):
        rounds["torchrl_bail"].append(updates * _timed(library, 1))
        rounds["bare"].append(updates * _timed(bare, 1))
    return summarise(f"FQE whole fit ({updates} updates on {N} transitions)", "updates/s", rounds,
                     updates_per_round=updates)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--updates", type=int, default=100, help="updates per timed round of the update row")
    parser.add_argument("--repeats", type=int, default=21, help="alternating rounds per side of the update row")
    parser.add_argument("--fit-updates", type=int, default=2000, help="updates of each whole fit")
    parser.add_argument("--fit-repeats", type=int, default=5, help="alternating whole fits per side")
    parser.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    add_record_argument(parser, __file__)
    args = parser.parse_args()
    record = Record(__file__, args.json, reference="bare PyTorch", settings=vars(args))
    if args.threads:
        torch.set_num_threads(args.threads)
    print(f"Q {list(SETTINGS.hidden)}, batch {SETTINGS.batch_size}, Adam lr {SETTINGS.lr}, target copy every "
          f"{SETTINGS.target_update_period}, obs {OBS}, act {ACT}, {N} transitions, policy {list(POLICY_HIDDEN)}")
    policy, data = make_policy(), make_data()
    rows = [bench_update(policy, data, args.updates, args.repeats)]
    record.write(rows)  # the first row is kept if the whole fits are interrupted
    rows.append(bench_fit(policy, data, args.fit_updates, args.fit_repeats))
    print_table(rows, "FQE updates/s: torchrl_bail vs bare PyTorch, same process (ratio = torchrl_bail / bare)")
    record.write(rows)


if __name__ == "__main__":
    main()

"""BAIL and Progressive BAIL throughput: Monte-Carlo returns on 10^6 transitions, and envelope / policy /
Progressive BAIL updates per second beside a bare PyTorch loop doing the same math (same networks, same
mini-batch, same optimizer) in the same process.

    python benchmarks/bench_bail.py [--transitions 1000000] [--updates 300] [--repeats 5] [--json PATH]

The library side is exactly what a run executes per iteration:

* envelope: the body of :func:`torchrl_bail.training.envelope.train_one_epoch` (index a mini-batch of 800 from the
  training split, :func:`~torchrl_bail.training.envelope.envelope_step`: :class:`UpperEnvelopeLoss`, Adam with coupled
  weight
  decay);
* policy: :func:`torchrl_bail.training.trainer.train`'s iteration (``TensorDictReplayBuffer.sample()`` of 1000 with
  replacement, then :meth:`BehaviourCloning.update`: TorchRL ``BCLoss`` + Adam);
* Progressive BAIL: the same sample, then :meth:`ProgressiveBAIL.update` (envelope step on the non-validation
  rows, selection of the top 25 % inside the mini-batch under the selection envelope, imitation step).
"""

from __future__ import annotations

import argparse
import time

import torch
from _bench import Record, add_record_argument, bare_mlp, compare, print_table
from tensordict import TensorDict
from torchrl.data import RandomSampler, TensorDictReplayBuffer, TensorStorage

from torchrl_bail.algorithms.base import PrepareContext
from torchrl_bail.algorithms.bc import BehaviourCloning
from torchrl_bail.algorithms.pbail import ProgressiveBAIL
from torchrl_bail.configuration.config_builders import algo_config
from torchrl_bail.data import monte_carlo_returns
from torchrl_bail.modules import action_spec_from_bounds, make_value_network
from torchrl_bail.objectives.upper_envelope import UpperEnvelopeLoss
from torchrl_bail.training.envelope import envelope_step

OBS, ACT = 11, 3  # Hopper-v5


def synthetic_batch(n: int, generator: torch.Generator) -> TensorDict:
    """Hopper-sized TED rows: 1000-step (time-limit) episodes mixed with falls of 20-400 steps."""
    lengths, total = [], 0
    while total < n:
        fell = torch.rand((), generator=generator) < 0.5
        length = int(torch.randint(20, 400, (), generator=generator)) if fell else 1000
        length = min(length, n - total)
        lengths.append(length)
        total += length
    episode = torch.repeat_interleave(torch.arange(len(lengths)), torch.tensor(lengths))
    last = torch.ones(n, dtype=torch.bool)
    last[:-1] = episode[1:] != episode[:-1]
    last[-1] = False  # the batch's final episode is unfinished
    full = torch.tensor([length == 1000 for length in lengths])[episode]
    truncated = (last & full).unsqueeze(-1)
    terminated = (last & ~full).unsqueeze(-1)
    return TensorDict({
        "observation": torch.randn(n, OBS, generator=generator),
        "action": torch.rand(n, ACT, generator=generator) * 2 - 1,
        "episode": episode,
        "next": {"reward": torch.rand(n, 1, generator=generator) * 3, "terminated": terminated,
                 "truncated": truncated, "done": terminated | truncated},
    }, [n])


def bench_returns(n: int) -> dict:
    """Seconds of one Monte-Carlo returns pass with gain augmentation and one without (no ratio: two variants of the
    library's own computation, one round each)."""
    data = synthetic_batch(n, torch.Generator().manual_seed(0))
    monte_carlo_returns(data[:20_000])  # warm-up
    start = time.perf_counter()
    monte_carlo_returns(data, gamma=0.99, horizon=1000, augment="gain")
    gain = time.perf_counter() - start
    start = time.perf_counter()
    monte_carlo_returns(data, gamma=0.99, horizon=1000, augment="none")
    plain = time.perf_counter() - start
    episodes = int(data["episode"][-1]) + 1
    print(f"\nMonte-Carlo returns on {n:,} transitions ({episodes} episodes): "
          f"gain augmentation {gain:.2f} s, plain {plain:.2f} s")
    return {"name": f"Monte-Carlo returns, {n:,} transitions ({episodes} episodes)", "unit": "s",
            "transitions": n, "gain_s": gain, "plain_s": plain, "rounds": {"gain_s": [gain], "plain_s": [plain]}}


def bench_envelope(n_updates: int, repeats: int) -> dict:
    n, batch = 200_000, 800
    g = torch.Generator().manual_seed(1)
    observations, returns = torch.randn(n, OBS, generator=g), torch.rand(n, generator=g) * 300
    train_index = torch.randperm(n, generator=g)[: int(0.8 * n)]

    # library: the inner loop of train_one_epoch
    torch.manual_seed(0)
    value = make_value_network(OBS)
    loss_module = UpperEnvelopeLoss(value, penalty=1000.0)
    optimizer = torch.optim.Adam(loss_module.parameters(), lr=3e-3, weight_decay=0.02)
    cursor = {"i": 0}

    def library():
        start = cursor["i"] = (cursor["i"] + batch) % (len(train_index) - batch)
        index = train_index[start:start + batch]
        obs_b = observations.index_select(0, index)
        td = TensorDict({"observation": obs_b, "return": returns.index_select(0, index)}, batch_size=obs_b.shape[:1])
        envelope_step(loss_module, optimizer, td)

    # bare: the same math on a plain nn.Sequential
    torch.manual_seed(0)
    net = bare_mlp(OBS, 1, (128, 128))
    with torch.no_grad():
        net[-1].weight.mul_(0.1)
        net[-1].bias.zero_()
    bare_opt = torch.optim.Adam(net.parameters(), lr=3e-3, weight_decay=0.02)
    bare_cursor = {"i": 0}

    def bare():
        start = bare_cursor["i"] = (bare_cursor["i"] + batch) % (len(train_index) - batch)
        index = train_index[start:start + batch]
        gap = net(observations[index]).squeeze(-1) - returns[index]
        loss = torch.where(gap < 0, 1000.0 * gap.square(), gap.square()).mean()
        bare_opt.zero_grad(set_to_none=True)
        loss.backward()
        bare_opt.step()

    return compare("envelope update (batch 800)", library, bare, n=n_updates, repeats=repeats)


def bench_policy(n_updates: int, repeats: int) -> dict:
    n, batch = 300_000, 1000
    g = torch.Generator().manual_seed(2)
    data = TensorDict({"observation": torch.randn(n, OBS, generator=g),
                       "action": torch.rand(n, ACT, generator=g) * 2 - 1}, [n])
    spec = action_spec_from_bounds([-1.0] * ACT, [1.0] * ACT)

    torch.manual_seed(0)
    algo = BehaviourCloning(OBS, spec, algo_config("bc", batch_size=batch))
    buffer = TensorDictReplayBuffer(storage=TensorStorage(data), sampler=RandomSampler(), batch_size=batch)

    def library():
        algo.update(buffer.sample())

    torch.manual_seed(0)
    actor = bare_mlp(OBS, ACT, (400, 300))
    bare_opt = torch.optim.Adam(actor.parameters(), lr=1e-3)
    obs, act = data["observation"], data["action"]

    def bare():
        index = torch.randint(n, (batch,))
        loss = (torch.tanh(actor(obs[index])) - act[index]).square().mean()
        bare_opt.zero_grad(set_to_none=True)
        loss.backward()
        bare_opt.step()

    return compare("policy update (BC, batch 1000, replay sample included)", library, bare, n=n_updates,
                   repeats=repeats)


def bench_progressive(n_updates: int, repeats: int) -> dict:
    n, batch = 300_000, 1000
    g = torch.Generator().manual_seed(3)
    data = TensorDict({"observation": torch.randn(n, OBS, generator=g),
                       "action": torch.rand(n, ACT, generator=g) * 2 - 1,
                       "return": torch.rand(n, generator=g) * 300}, [n])
    spec = action_spec_from_bounds([-1.0] * ACT, [1.0] * ACT)

    torch.manual_seed(0)
    # validation (1 in 1250 updates) is not timed
    algo = ProgressiveBAIL(OBS, spec, algo_config("pbail", batch_size=batch, envelope={"validate_every": 10**9}))
    prepared = algo.prepare(data, PrepareContext(generator=torch.Generator().manual_seed(0)))
    buffer = TensorDictReplayBuffer(storage=TensorStorage(prepared), sampler=RandomSampler(), batch_size=batch)

    def library():
        algo.update(buffer.sample())

    torch.manual_seed(0)
    envelope, selector = bare_mlp(OBS, 1, (128, 128)), bare_mlp(OBS, 1, (128, 128))
    actor = bare_mlp(OBS, ACT, (400, 300))
    env_opt = torch.optim.Adam(envelope.parameters(), lr=3e-3, weight_decay=0.02)
    act_opt = torch.optim.Adam(actor.parameters(), lr=1e-3)
    obs, act, ret = data["observation"], data["action"], data["return"]
    is_val = torch.rand(n, generator=g) < 0.2
    k = int(0.25 * batch)

    def bare():
        index = torch.randint(n, (batch,))
        s, a, r, train_rows = obs[index], act[index], ret[index], (~is_val[index]).float()
        gap = envelope(s).squeeze(-1) - r
        loss_env = (torch.where(gap < 0, 1000.0 * gap.square(), gap.square()) * train_rows).sum() / train_rows.sum()
        env_opt.zero_grad(set_to_none=True)
        loss_env.backward()
        env_opt.step()
        with torch.no_grad():
            v = selector(s).squeeze(-1)
            v = torch.where(v < 1, torch.exp(v - 1), v)
            ratio = r / v
            selected = ratio >= torch.topk(ratio, k).values[-1]
        loss_bc = ((torch.tanh(actor(s)) - a).square() * selected.float().unsqueeze(-1)).mean()
        act_opt.zero_grad(set_to_none=True)
        loss_bc.backward()
        act_opt.step()

    return compare("Progressive BAIL update (batch 1000)", library, bare, n=n_updates, repeats=repeats)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--transitions", type=int, default=1_000_000)
    parser.add_argument("--updates", type=int, default=300, help="updates per timed round")
    parser.add_argument("--repeats", type=int, default=5, help="alternating rounds per side")
    add_record_argument(parser, __file__)
    args = parser.parse_args()
    record = Record(__file__, args.json, reference="bare PyTorch", settings=vars(args))
    returns_row = bench_returns(args.transitions)
    rows = [bench_envelope(args.updates, args.repeats), bench_policy(args.updates, args.repeats),
            bench_progressive(args.updates, args.repeats)]
    print_table(rows, "BAIL updates/s: torchrl_bail vs bare PyTorch, same process (ratio = torchrl_bail / bare)")
    record.write([returns_row, *rows])


if __name__ == "__main__":
    main()

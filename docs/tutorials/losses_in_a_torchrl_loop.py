"""BAIL in a training loop of your own: ``UpperEnvelopeLoss``, ``BestActionFilter`` and TorchRL's ``BCLoss``.

    python docs/tutorials/losses_in_a_torchrl_loop.py                          # random-policy Hopper data
    python docs/tutorials/losses_in_a_torchrl_loop.py --dataset ~/.d4rl/datasets/hopper_medium-v2.hdf5

It trains no Hydra run, so it takes no overrides: its own options are its knobs. The trained envelope and actor
weights go to ``--work-dir`` (``tutorial_losses/``).

Everything but the two BAIL components is plain TorchRL: a ``GymEnv`` rollout makes the data (or a file you have is
imported), replay buffers sample it, TorchRL's ``MLP``, ``ValueOperator`` and ``Actor`` are the networks, and the
policy is evaluated by ``env.rollout``.
"""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

import torch
from tensordict import TensorDict
from torch import nn
from torchrl.data import LazyTensorStorage, SamplerWithoutReplacement, TensorDictReplayBuffer
from torchrl.envs import DoubleToFloat, GymEnv, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import MLP, Actor, ValueOperator
from torchrl.objectives import BCLoss

from torchrl_bail.data import monte_carlo_returns
from torchrl_bail.data.importers import import_dataset
from torchrl_bail.objectives import UpperEnvelopeLoss
from torchrl_bail.transforms import BestActionFilter


def random_batch(env: TransformedEnv, steps: int) -> TensorDict:
    """``steps`` transitions of a uniformly random policy, in TorchRL's TED layout, with episode ids."""
    data = env.rollout(steps, break_when_any_done=False)  # resets by itself after every episode end
    done = data["next", "done"].squeeze(-1)
    data["episode"] = torch.cat([torch.zeros(1, dtype=torch.long), done[:-1].long().cumsum(0)])
    return data


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", help="a D4RL .hdf5 file or Minari folder for Hopper-v5 (default: random data)")
    parser.add_argument("--steps", type=int, default=20_000, help="transitions of random data")
    parser.add_argument("--envelope-epochs", type=int, default=20)
    parser.add_argument("--updates", type=int, default=5_000, help="imitation updates")
    parser.add_argument("--eval-steps", type=int, default=1_000)
    parser.add_argument("--work-dir", type=Path, default=Path("tutorial_losses"), help="where the weights go")
    args = parser.parse_args()
    torch.manual_seed(0)
    env = TransformedEnv(GymEnv("Hopper-v5"), DoubleToFloat())  # MuJoCo observations are float64
    env.set_seed(0)
    obs_dim, act_dim = env.observation_spec["observation"].shape[-1], env.action_spec.shape[-1]

    # 1. The batch (TED layout) and its Monte-Carlo returns, with the paper's augmentation for time-limited episodes.
    data = import_dataset(args.dataset, env_id="Hopper-v5").data if args.dataset else random_batch(env, args.steps)
    data = data.select("observation", "action", "next", "episode").clone()
    data["return"] = monte_carlo_returns(data, gamma=0.99, horizon=1000, augment="gain")

    # 2. The upper envelope V(s) >= G: a TorchRL value network trained with UpperEnvelopeLoss (K = 1000: points
    #    below the envelope weigh 1000 times more), mini-batches of 800 drawn without replacement.
    envelope = ValueOperator(MLP(in_features=obs_dim, out_features=1, num_cells=[128, 128]), in_keys=["observation"])
    envelope_loss = UpperEnvelopeLoss(envelope, penalty=1000.0)
    optim = torch.optim.Adam(envelope_loss.parameters(), lr=3e-3, weight_decay=0.02)
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(len(data)), batch_size=800,
                                    sampler=SamplerWithoutReplacement())
    buffer.extend(data)
    for epoch in range(args.envelope_epochs):
        for batch in buffer:  # one pass over the data
            loss = envelope_loss(batch)["loss_envelope"]
            optim.zero_grad()
            loss.backward()
            optim.step()
        print(f"envelope epoch {epoch + 1}: loss {loss.item():.1f}")

    # 3. The best actions: BestActionFilter, a replay-buffer transform, keeps the pairs whose return comes closest
    #    to the envelope (the top 30 % of G / V) as they are written into the buffer.
    with torch.no_grad():
        data["state_value"] = envelope(data.select("observation"))["state_value"].squeeze(-1)
    best = TensorDictReplayBuffer(storage=LazyTensorStorage(len(data)), batch_size=256,
                                  transform=BestActionFilter(percentile=0.3))
    best.extend(data)
    print(f"selected {len(best)} of {len(data)} pairs")

    # 4. Imitation: TorchRL's BCLoss (mean squared error) on a deterministic tanh actor.
    actor = Actor(nn.Sequential(MLP(in_features=obs_dim, out_features=act_dim, num_cells=[400, 300]), nn.Tanh()),
                  in_keys=["observation"], spec=env.action_spec)
    with warnings.catch_warnings():  # torchrl 0.14's BCLoss warns about an annotation of its own when built
        warnings.filterwarnings("ignore", message=".*target_actor_network_params.*")
        bc_loss = BCLoss(actor, loss_function="l2")
    optim = torch.optim.Adam(actor.parameters(), lr=1e-3)
    for update in range(args.updates):
        loss = bc_loss(best.sample())["loss_bc"]
        optim.zero_grad()
        loss.backward()
        optim.step()
        if (update + 1) % max(1, args.updates // 5) == 0:
            print(f"imitation update {update + 1}: loss {loss.item():.4f}")

    # 5. Evaluation: one deterministic episode with TorchRL's rollout.
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        episode = env.rollout(args.eval_steps, actor)
    print(f"evaluation: return {episode['next', 'reward'].sum().item():.1f} over {episode.shape[0]} steps "
          f"(the batch's transitions average {data['next', 'reward'].mean().item():.2f} reward per step)")

    # 6. The weights, as plain state dicts: load them into the same TorchRL modules to reuse them.
    args.work_dir.mkdir(parents=True, exist_ok=True)
    torch.save(envelope.state_dict(), args.work_dir / "envelope.pt")
    torch.save(actor.state_dict(), args.work_dir / "actor.pt")
    print(f"weights: {args.work_dir / 'envelope.pt'}, {args.work_dir / 'actor.pt'}")


if __name__ == "__main__":
    main()

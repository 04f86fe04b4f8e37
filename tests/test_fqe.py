"""FQE (torchrl_bail.objectives.fqe, torchrl_bail.ope.fit_fqe) against values known in closed form.

The contract suite (tests/test_contract.py, case ``fqe``) covers gradients, targets, keys, reductions and state dicts;
here: the fit recovers the discounted value of a fixed policy on tiny deterministic batches, bootstraps through a
time-limit truncation and not through a termination, and the target is copied on every period-th update.
"""

from __future__ import annotations

import pytest
import torch
from _batch_rl_testing import one_thread  # noqa: F401 (autouse fixture)
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.objectives import HardUpdate

from torchrl_bail.modules import make_qvalue_network
from torchrl_bail.objectives.fqe import FQELoss, episode_starts
from torchrl_bail.ope import FQESettings, fit_fqe

GAMMA = 0.9
#: the fits below: 1000-1500 updates of a 32-32 network on mini-batches larger than the batch (about a second each
#: on one core); their estimates land within 1e-3 of the chain's value and 0.02 of the loop's (seeds 0-2)
SETTINGS = FQESettings(updates=1000, batch_size=32, lr=1e-3, hidden=(32, 32), target_update_period=25, gamma=GAMMA,
                       log_every=250)


class ConstantAction(nn.Module):
    """``pi(s) = +1`` for every state."""

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("value", torch.ones(1))

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return self.value.expand(*observation.shape[:-1], 1)


def always_plus_one() -> TensorDictModule:
    return TensorDictModule(ConstantAction(), in_keys=["observation"], out_keys=["action"])


def chain_batch(states: int, episodes: int, *, truncate: bool = False) -> TensorDict:
    """Episodes through a chain ``s_0 -> s_1 -> ... -> s_{K-1} -> end`` (one-hot states): whatever the action,
    the next state is the following one; the reward is ``1`` for action ``+1`` and ``0`` for ``-1``; the behaviour
    alternates the two actions (both are taken at every state across episodes). The last step ends the episode:
    terminated (its next observation is ``s_0``'s, so a target that bootstraps through the end is visibly wrong),
    or with ``truncate`` a time-limit truncation of an endless loop at ``s_0`` (``states = 1``: the one state)."""
    eye = torch.eye(states)
    rows = []
    for e in range(episodes):
        for k in range(states if not truncate else 10):
            s = k % states
            action = 1.0 if (k + e) % 2 == 0 else -1.0
            rows.append((eye[s], action, eye[(s + 1) % states], (1.0 + action) / 2, e))
    n = len(rows)
    last = torch.tensor([i == n - 1 or rows[i + 1][4] != rows[i][4] for i in range(n)]).unsqueeze(-1)
    return TensorDict({
        "observation": torch.stack([r[0] for r in rows]),
        "action": torch.tensor([[r[1]] for r in rows]),
        "episode": torch.tensor([r[4] for r in rows]),
        "next": {"observation": torch.stack([r[2] for r in rows]), "reward": torch.tensor([[r[3]] for r in rows]),
                 "terminated": last & (not truncate), "truncated": last & truncate, "done": last},
    }, [n])


def test_the_discounted_value_of_a_chain():
    """``V^pi(s_0) = sum_{k<K} gamma^k`` for the policy that always takes ``+1`` (the behaviour's own value is
    half of it): FQE's estimate, the mean of ``Q(s_0, pi(s_0))`` over the episode starts, within 1 %."""
    states = 5
    exact = sum(GAMMA**k for k in range(states))  # 4.0951
    result = fit_fqe(always_plus_one(), chain_batch(states, episodes=4), SETTINGS, seed=0)
    assert result["num_episode_starts"] == 4
    assert abs(result["estimate"] - exact) < 0.01 * exact, (result["estimate"], exact)  # within 1 %
    assert result["curve"][-1]["td_loss"] < 1e-3


def test_a_time_limit_truncation_is_bootstrapped():
    """One state, reward 1 for ``+1``, episodes cut by a time limit after 10 steps (not terminal): ``V^pi = 1 /
    (1 - gamma) = 10``, not the 10-step ``(1 - gamma^10) / (1 - gamma) = 6.51`` a target stopped at ``done``
    gives."""
    exact = 1.0 / (1.0 - GAMMA)
    settings = FQESettings(**{**vars(SETTINGS), "updates": 1500})
    result = fit_fqe(always_plus_one(), chain_batch(1, episodes=2, truncate=True), settings, seed=0)
    assert abs(result["estimate"] - exact) < 0.01 * exact, (result["estimate"], exact)  # within 1 %


def test_the_target_is_copied_on_every_period_th_update():
    """The fit's ``HardUpdate(value_network_update_interval=period - 1)``: TorchRL copies on the ``interval + 1``-th
    ``step()``, so the target equals the network after update ``period`` and not before."""
    period = 4
    torch.manual_seed(0)
    loss = FQELoss(make_qvalue_network(5, 1, (8,)), always_plus_one())
    updater = HardUpdate(loss, value_network_update_interval=period - 1)

    def target_is_current() -> bool:
        return all(torch.equal(a, b) for a, b in zip(loss.qvalue_network_params.values(True, True),
                                                     loss.target_qvalue_network_params.values(True, True),
                                                     strict=True))

    for update in range(1, 2 * period + 1):
        with torch.no_grad():
            for p in loss.parameters():
                p.add_(0.1)  # an optimizer step
        updater.step()
        assert target_is_current() == (update % period == 0), update


def test_stored_policy_actions_are_the_policys():
    """:meth:`FQELoss.add_policy_actions` stores what the policy computes; the loss then gives the same numbers."""
    torch.manual_seed(0)
    data = chain_batch(3, episodes=2)
    data["next", "observation"] = torch.randn_like(data["next", "observation"])
    from torchrl_bail.modules import action_spec_from_bounds, make_deterministic_actor

    loss = FQELoss(make_qvalue_network(3, 1, (8,)), make_deterministic_actor(3, action_spec_from_bounds([-1.0], [1.0]),
                                                                             (8,)))
    expected = loss(data)
    stored = loss.add_policy_actions(data.clone(), chunk=4)
    torch.testing.assert_close(stored["next", "policy_action"], loss.policy_actions(data["next", "observation"]))
    torch.testing.assert_close(loss(stored)["loss_qvalue"], expected["loss_qvalue"])
    torch.testing.assert_close(loss.policy_value(stored), loss.policy_value(data))


def test_episode_starts_and_bad_input():
    assert episode_starts(torch.tensor([3, 3, 4, 4, 4, 7])).tolist() == [True, False, True, False, False, True]
    with pytest.raises(ValueError, match="episode ids"):
        episode_starts(torch.zeros(2, 3, dtype=torch.long))


def test_gamma_out_of_range_is_refused():
    with pytest.raises(ValueError, match=r"gamma must be in \[0, 1\]"):
        FQELoss(make_qvalue_network(3, 1, (8,)), always_plus_one(), gamma=1.5)

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


def test_fqelosss_default_discount_is_fqesettings():
    """FQE's discount has one default, ``objectives.fqe.FQE_GAMMA``: FQELoss' own; :attr:`FQESettings.gamma` repeats
    it (ope loads no torch at import, so it cannot import the loss' module) and is held equal to it here."""
    import inspect

    from torchrl_bail.objectives.fqe import FQE_GAMMA

    assert inspect.signature(FQELoss).parameters["gamma"].default == FQE_GAMMA == FQESettings.gamma


# -- issue 53, item 2: the stopping rule and several fits -------------------------------------------------------
def test_the_stopping_rule_stops_a_settled_curve_and_not_a_rising_one():
    """:func:`curve_converged` compares the mean of the last ``window`` points with the mean of the ``window`` points
    ending at half the curve: a curve that has settled stops, one that keeps rising (linearly, or as a logarithm,
    whose doubling always adds the same amount) never does, and a plateau shorter than half the curve is not taken
    for the limit."""
    import math

    from torchrl_bail.ope import curve_converged

    settled = [200.0 * (1.0 - math.exp(-k / 10.0)) for k in range(1, 201)]
    stops = [n for n in range(1, 201) if curve_converged(settled[:n], 20, 0.02)]
    assert stops and 40 <= stops[0] < 200, "a settled curve stops before its end"
    assert abs(settled[stops[0] - 1] - 200.0) < 0.02 * 200.0, "and its estimate there is within the tolerance"
    rising = [100.0 + 0.5 * k for k in range(1, 201)]
    logarithmic = [50.0 * math.log(k + 1.0) for k in range(1, 201)]
    for curve in (rising, logarithmic):
        assert not any(curve_converged(curve[:n], 20, 0.02) for n in range(1, 201))
    plateau = [100.0 + min(k, 60) + max(0, k - 90) for k in range(1, 121)]  # rising, flat for 30 points, rising
    assert not any(curve_converged(plateau[:n], 20, 0.02) for n in range(1, 121))
    assert not curve_converged(settled, 0, 0.02), "window 0: no rule"
    assert not curve_converged(settled[:39], 20, 0.5), "it waits until half the curve holds a window"


def test_a_fit_stops_once_its_curve_settles_and_runs_to_the_cap_otherwise():
    """The chain's fit settles long before a cap of 4000 updates: with the rule it stops there (recorded as
    converged), within 1 % of the exact value; without it (``stop_window = 0``) it runs to the cap, not converged."""
    states = 5
    exact = sum(GAMMA**k for k in range(states))
    ruled = FQESettings(**{**vars(SETTINGS), "updates": 4000, "log_every": 50, "stop_window": 5, "stop_tol": 0.005})
    stopped = fit_fqe(always_plus_one(), chain_batch(states, episodes=4), ruled, seed=0)
    assert stopped["converged"] and stopped["updates"] < 4000 and stopped["updates"] == stopped["curve"][-1]["update"]
    assert abs(stopped["estimate"] - exact) < 0.01 * exact, (stopped["estimate"], exact)
    capped = fit_fqe(always_plus_one(), chain_batch(states, episodes=4),
                     FQESettings(**{**vars(ruled), "stop_window": 0}), seed=0)
    assert not capped["converged"] and capped["updates"] == 4000
    assert capped["curve"][:len(stopped["curve"])] == stopped["curve"], "the same fit, stopped earlier"


def test_several_fits_give_one_curve_each_their_mean_and_spread(tmp_path, monkeypatch):
    """:func:`fit_fqe_fits`: ``K`` fits of seeds ``seed .. seed + K - 1``, each the single fit of its seed, the
    estimate their mean and the spread their standard deviation; a finished fit's checkpoint holds its result, so
    the same call keeps it without fitting again."""
    import statistics

    from torchrl_bail.ope import fit_fqe_fits

    data = chain_batch(5, episodes=4)
    settings = FQESettings(**{**vars(SETTINGS), "updates": 200, "log_every": 50})
    result = fit_fqe_fits(always_plus_one(), data, settings, fits=3, seed=7,
                          checkpoint_path=tmp_path / "c_checkpoint.pt")
    fits = result["fits"]
    assert [fit["seed"] for fit in fits] == [7, 8, 9] and all(len(fit["curve"]) == 4 for fit in fits)
    assert len({fit["estimate"] for fit in fits}) == 3, "three seeds, three estimates"
    assert fits[1]["curve"] == fit_fqe(always_plus_one(), data, settings, seed=8)["curve"]
    estimates = [fit["estimate"] for fit in fits]
    assert result["estimate"] == pytest.approx(statistics.mean(estimates), abs=1e-12)
    assert result["spread"] == pytest.approx(statistics.stdev(estimates), abs=1e-12) and result["spread"] > 0
    assert fit_fqe_fits(always_plus_one(), data, settings, fits=1, seed=7)["spread"] is None
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c_checkpoint.pt", "c_fit1_checkpoint.pt",
                                                          "c_fit2_checkpoint.pt"]
    import torchrl_bail.ope as ope_module

    monkeypatch.setattr(ope_module, "fqe_update", lambda *a, **k: pytest.fail("a finished fit was fitted again"))
    monkeypatch.setattr(FQELoss, "add_policy_actions", lambda *a, **k: pytest.fail("the actions were drawn again"))
    kept = fit_fqe_fits(always_plus_one(), data, settings, fits=3, seed=7, checkpoint_path=tmp_path / "c_checkpoint.pt")
    assert kept["fits"] == fits and kept["estimate"] == result["estimate"]

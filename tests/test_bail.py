"""BAIL and Progressive BAIL end to end on a crafted batch whose best actions are known.

Every state allows a return ``c(s) = 5 + 4 s_0`` (from 1 to 9): 30 % of the pairs take the best action
``a*(s)`` and earn ``c(s)``, the others take a random action and earn ``0.3 c(s)``. A good pair in a poor state
earns less than a bad pair in a rich one, so ranking by return alone mixes them up; the ratio ``G / V`` to a
fitted upper envelope does not. BAIL must keep exactly the good pairs, and its imitation must recover ``a*``.
"""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict

from torchrl_bail.algorithms import BAIL, BehaviourCloning, PrepareContext, ProgressiveBAIL
from torchrl_bail.configuration.config_builders import algo_config
from torchrl_bail.modules import action_spec_from_bounds
from torchrl_bail.training.trainer import make_trainee, train
from torchrl_bail.transforms.best_action import best_action_mask

SPEC = action_spec_from_bounds([-1.0, -1.0], [1.0, 1.0])
N, GOOD = 400, 0.3
#: the imitation's config overrides (every algorithm here)
NETS = {"policy": {"hidden": [32, 32], "lr": 3e-3}, "batch_size": 64, "epochs": 1}
UPDATES = 300
ENVELOPE = {"hidden": [32, 32], "epochs": 25, "batch_size": 50, "lr": 1e-2}


def best_action(observation: torch.Tensor) -> torch.Tensor:
    return torch.stack([torch.tanh(2 * observation[:, 0] - observation[:, 1]), 0.5 * observation[:, 2]], -1)


def crafted_batch(seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    observation = torch.rand(N, 3, generator=g) * 2 - 1
    good = torch.zeros(N, dtype=torch.bool)
    good[torch.randperm(N, generator=g)[: int(GOOD * N)]] = True
    random_action = torch.rand(N, 2, generator=g) * 2 - 1
    action = torch.where(good.unsqueeze(-1), best_action(observation), random_action)
    allowed = 5 + 4 * observation[:, 0]
    returns = torch.where(good, allowed, 0.3 * allowed) + 0.02 * torch.randn(N, generator=g)
    return TensorDict({"observation": observation, "action": action, "return": returns, "good": good}, [N])


def _context(seed: int = 0) -> PrepareContext:
    return PrepareContext(generator=torch.Generator().manual_seed(seed))


def _bail(**overrides) -> BAIL:
    torch.manual_seed(0)
    return BAIL(3, SPEC, algo_config("bail", envelope=ENVELOPE, **{"selection.percentile": GOOD}, **NETS, **overrides))


def _imitation_error(algo, updates: int) -> float:
    """Trains ``algo`` on its prepared data for ``updates`` mini-batches; the policy's MSE to ``a*`` on new states."""
    torch.manual_seed(1)
    data = algo.prepare(crafted_batch(), _context())
    algo.epochs = updates * algo.samples_per_update / 1e6
    train(make_trainee([algo], [data]), progress=False)
    test_states = torch.rand(500, 3, generator=torch.Generator().manual_seed(9)) * 2 - 1
    with torch.no_grad():
        action = algo.policy(TensorDict({"observation": test_states}, [500]))["action"]
    return float((action - best_action(test_states)).square().mean())


def test_bail_keeps_exactly_the_best_actions_and_the_percentile():
    data = crafted_batch()
    algo = _bail()
    selected = algo.prepare(data, _context())
    kept = torch.isin(data["return"], selected["return"])
    assert torch.equal(kept, data["good"])  # every good pair, and nothing else
    summary = algo.summary()
    assert summary["num_selected"] == len(selected) == math.floor(GOOD * N)
    assert summary["selected_fraction"] == GOOD
    # the selection is the ratio to the fitted envelope, with the border reported
    values = algo.value_network(data.select("observation"))["state_value"].squeeze(-1).detach()
    mask, border = best_action_mask(data["return"], values, GOOD, return_border=True)
    assert torch.equal(mask, kept) and summary["selection_border"] == pytest.approx(float(border))
    assert summary["envelope_fraction_below"] < 0.1


def test_ranking_by_return_alone_mixes_good_and_bad_pairs():
    """Ablation D.2 keeps the top 30 % by return: rich states' bad pairs push out poor states' good ones."""
    data = crafted_batch()
    selected = _bail(**{"selection.by": "return"}).prepare(data, _context())
    kept = torch.isin(data["return"], selected["return"])
    assert len(selected) == math.floor(GOOD * N) and selected["return"].min() >= data["return"][~kept].max()
    assert (kept & ~data["good"]).sum() > 10 and (~kept & data["good"]).sum() > 10


def _pbail(**overrides) -> ProgressiveBAIL:
    return ProgressiveBAIL(3, SPEC, algo_config("pbail", **{"selection.percentile": 0.25}, **NETS, **overrides))


@pytest.fixture(scope="module")
def bc_error() -> float:
    torch.manual_seed(0)
    return _imitation_error(BehaviourCloning(3, SPEC, algo_config("bc", **NETS)), updates=UPDATES)


@pytest.mark.parametrize("make", [
    _bail,
    lambda: _pbail(envelope={"hidden": [32, 32], "validate_every": 100, "lr": 1e-2}),
], ids=["bail", "pbail"])
def test_imitation_recovers_the_best_actions_where_bc_does_not(make, bc_error):
    error = _imitation_error(make(), updates=UPDATES)
    assert error < 0.05 and error < bc_error / 4, (error, bc_error)


def _pbail_after_one_update(actions: torch.Tensor | None = None):
    """A fresh Progressive BAIL (same seed every call), one update on the first 64 prepared pairs (``actions``
    replacing theirs); returns the algorithm, that mini-batch and the update's metrics."""
    torch.manual_seed(0)
    algo = _pbail(envelope={"hidden": [16], "validate_every": 1})
    batch = algo.prepare(crafted_batch(), _context())[:64]
    if actions is not None:
        batch["action"] = actions
    return algo, batch, algo.update(batch)


def test_pbail_imitates_only_the_pairs_it_selects_in_each_mini_batch():
    algo, batch, metrics = _pbail_after_one_update()
    assert metrics["selected_fraction"].item() == 16 / 64  # floor(0.25 * 64) of 64 distinct ratios
    with torch.no_grad():  # the selection network the update selected with (validation runs before it)
        values = algo.selection_network(batch.select("observation"))["state_value"].squeeze(-1)
    selected = best_action_mask(batch["return"], values, 0.25, nonpositive_value="project").unsqueeze(-1)
    assert int(selected.sum()) == 16

    def imitation_gradient(algo):  # the actor's gradient of the update's imitation step (Adam's first step is
        return [p.grad for p in algo.actor.parameters()]  # sign-like, so the weights would hide a difference

    reference = imitation_gradient(algo)
    assert all(g is not None and g.abs().sum() > 0 for g in reference)
    noise = torch.rand(64, 2, generator=torch.Generator().manual_seed(5)) * 2 - 1
    unselected_changed = imitation_gradient(_pbail_after_one_update(torch.where(selected, batch["action"], noise))[0])
    selected_changed = imitation_gradient(_pbail_after_one_update(torch.where(selected, noise, batch["action"]))[0])
    assert all(torch.equal(g, h) for g, h in zip(unselected_changed, reference, strict=True))
    assert not any(torch.equal(g, h) for g, h in zip(selected_changed, reference, strict=True))

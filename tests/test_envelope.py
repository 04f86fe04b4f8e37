"""The one envelope engine: the early-stopping tracker BAIL and Progressive BAIL share, the fit built on it, and
Progressive BAIL's switches and checkpoints."""

from __future__ import annotations

import copy
import math

import pytest
import torch
from tensordict import TensorDict

from torchrl_bail.algorithms.base import PrepareContext
from torchrl_bail.algorithms.pbail import ProgressiveBAIL
from torchrl_bail.envelope import BestWeights, EarlyStoppingTracker, fit_upper_envelope
from torchrl_bail.modules import action_spec_from_bounds, make_value_network


def _weights(module: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in module.state_dict().items()}


def _equal(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def _perturb(module: torch.nn.Module) -> None:
    with torch.no_grad():
        for p in module.parameters():
            p.add_(1.0)


def test_tracker_reverts_to_a_real_copy_and_restarts_the_count():
    net = torch.nn.Linear(3, 1)
    tracker = EarlyStoppingTracker(net, patience=2)
    assert tracker.observe(1.0) == "improved"
    best = _weights(net)
    events = []
    for loss in (2.0, 3.0, 2.0, 4.0, 2.0):
        _perturb(net)
        events.append(tracker.observe(loss))
        if events[-1] == "reverted":
            assert _equal(_weights(net), best)
    # the count restarts after each revert: every second non-improving validation reverts
    assert events == ["worse", "reverted", "worse", "reverted", "worse"]
    assert tracker.reverts == [3, 5] and tracker.best_step == 1 and tracker.best_loss == 1.0


def test_as_coded_tracker_aliases_the_live_weights_and_never_reverts():
    net = torch.nn.Linear(3, 1)
    tracker = EarlyStoppingTracker(net, patience=1, revert=False, copy_best=False)
    tracker.observe(1.0)
    _perturb(net)
    assert tracker.observe(2.0) == "worse" and tracker.observe(3.0) == "worse"
    assert _equal(tracker.best.state, _weights(net))  # the "best" record is the current weights
    assert tracker.reverts == [] and tracker.increases == 2


def test_a_diverged_envelope_counts_as_non_improving():
    net = torch.nn.Linear(1, 1)
    tracker = EarlyStoppingTracker(net, patience=2)
    tracker.observe(1.0)
    best = _weights(net)
    _perturb(net)
    assert [tracker.observe(math.nan) for _ in range(2)] == ["worse", "reverted"]
    assert _equal(_weights(net), best)


def test_pbail_without_validation_set_never_reverts():
    algo, data = _pbail(envelope={"val_fraction": 0.0})
    _updates(algo, data, 10, seed=1)
    assert algo.early_stopping.step == 0 and algo.summary()["envelope_reverts"] == 0


def test_tracker_state_round_trip():
    net = torch.nn.Linear(2, 1)
    tracker = EarlyStoppingTracker(net, patience=3)
    for loss in (2.0, 1.0, 1.5):
        tracker.observe(loss)
    state = tracker.state_dict()
    other_net = torch.nn.Linear(2, 1)
    other = EarlyStoppingTracker(other_net, patience=3)
    other.load_state_dict(state)
    assert (other.best_loss, other.best_step, other.increases, other.step) == (1.0, 2, 1, 3)
    assert _equal(other.best.state, tracker.best.state)
    with pytest.raises(RuntimeError, match="no best weights"):
        BestWeights(net).load_into(net)


def _fit(mode: str, snapshots: list):
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(0)
    obs = torch.randn(300, 3, generator=g)
    returns = obs[:, 0] * 10 + torch.randn(300, generator=g)
    net = make_value_network(3, (16, 16))

    def record(epoch, info):
        snapshots.append(_weights(net))

    fit = fit_upper_envelope(net, obs, returns, epochs=12, patience=2, batch_size=32, lr=3e-2,
                             early_stopping=mode, progress=False, generator=torch.Generator().manual_seed(1),
                             callback=record)
    return fit, net


def test_fit_returns_the_best_weights_in_paper_mode_and_the_last_as_coded():
    snapshots: list = []
    fit, net = _fit("paper", snapshots)
    assert fit.returned == "best" and 1 <= fit.best_epoch <= fit.epochs
    assert fit.best_val_loss == min(fit.val_loss[: fit.best_epoch])
    assert _equal(_weights(net), snapshots[fit.best_epoch - 1])

    snapshots = []
    fit, net = _fit("as_coded", snapshots)
    assert fit.returned == "last" and fit.revert_epochs == []
    assert _equal(_weights(net), snapshots[-1])


def _pbail(envelope: dict | None = None, **kwargs) -> tuple[ProgressiveBAIL, TensorDict]:
    torch.manual_seed(0)
    spec = action_spec_from_bounds([-1.0, -1.0], [1.0, 1.0])
    envelope = {"hidden": (16, 16), "validate_every": 1, "patience": 2, "lr": 0.05, **(envelope or {})}
    algo = ProgressiveBAIL(obs_dim=3, action_spec=spec, hidden=(16, 16), batch_size=40, epochs=1,
                           envelope=envelope, **kwargs)
    g = torch.Generator().manual_seed(0)
    data = TensorDict({"observation": torch.randn(200, 3, generator=g), "action": torch.rand(200, 2, generator=g),
                       "return": torch.rand(200, generator=g) * 100}, [200])
    return algo, algo.prepare(data, PrepareContext(generator=torch.Generator().manual_seed(0)))


def _updates(algo: ProgressiveBAIL, data: TensorDict, n: int, seed: int) -> list[float]:
    g = torch.Generator().manual_seed(seed)
    out = []
    for _ in range(n):
        batch = data[torch.randint(len(data), (40,), generator=g)]
        out.append(float(algo.update(batch)["loss_bc"]))
    return out


def test_pbail_checkpoint_carries_the_early_stopping_state():
    algo, data = _pbail()
    _updates(algo, data, 30, seed=1)
    assert algo.early_stopping.step == 30
    state = copy.deepcopy(algo.state_dict())  # as through torch.save: nothing shared with the live run
    assert state["iteration"] == 30 and state["early_stopping"]["step"] == 30

    resumed, _ = _pbail()
    resumed.load_state_dict(state)
    assert resumed.early_stopping.state_dict()["best_loss"] == algo.early_stopping.best_loss
    assert resumed.early_stopping.reverts == algo.early_stopping.reverts
    # the same next updates, revert decisions included
    assert _updates(resumed, data, 15, seed=2) == _updates(algo, data, 15, seed=2)
    assert resumed.summary() == algo.summary()


@pytest.mark.parametrize("selection_envelope, selects_with", [("best", "selection_network"),
                                                               ("training", "value_network")])
def test_pbail_selection_envelope_switch(selection_envelope, selects_with):
    algo, data = _pbail(selection_envelope=selection_envelope)
    calls = {"value_network": 0, "selection_network": 0}
    for name in calls:
        getattr(algo, name).register_forward_hook(lambda *a, name=name: calls.__setitem__(name, calls[name] + 1))
    _updates(algo, data, 5, seed=1)
    # the training envelope also runs in the envelope step and the validations; the selection net only selects
    assert calls["selection_network"] == (5 if selects_with == "selection_network" else 0)
    baseline, _ = _pbail()
    baseline_calls = [0]
    baseline.value_network.register_forward_hook(lambda *a: baseline_calls.__setitem__(0, baseline_calls[0] + 1))
    _updates(baseline, data, 5, seed=1)
    assert calls["value_network"] == baseline_calls[0] + (5 if selects_with == "value_network" else 0)


def test_pbail_as_coded_selection_keeps_its_init_until_the_first_increase():
    algo, data = _pbail(best_envelope="as_coded")
    init = _weights(algo.selection_network)
    g = torch.Generator().manual_seed(1)
    while algo.early_stopping.increases == 0 and algo.early_stopping.step < 200:
        assert _equal(_weights(algo.selection_network), init)
        validated = _weights(algo.value_network)  # validation runs first in update(), before the envelope step
        algo.update(data[torch.randint(len(data), (40,), generator=g)])
    assert algo.early_stopping.increases == 1, "the envelope's validation loss never got worse"
    # at the increase the selection envelope got the current (worse) training weights, and no revert happened
    assert _equal(_weights(algo.selection_network), validated)
    assert algo.early_stopping.reverts == []


def test_pbail_rejects_unknown_selection_envelope():
    with pytest.raises(ValueError, match="selection_envelope"):
        _pbail(selection_envelope="latest")

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
from torchrl_bail.configuration.config_builders import algo_config
from torchrl_bail.modules import action_spec_from_bounds, make_value_network
from torchrl_bail.training import envelope as envelope_module
from torchrl_bail.training.envelope import BestWeights, EarlyStoppingTracker, envelope_split, fit_upper_envelope


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


#: a crafted validation curve: improvements at epochs 1, 2 and 5; with patience 2 the paper modes revert after
#: epochs 4 and 7 (two non-improving epochs each, the count restarting after a revert)
CURVE = [5.0, 4.0, 6.0, 7.0, 3.0, 8.0, 9.0, 10.0]


def _fit_on_curve(mode: str, monkeypatch, stop_at: int | None = None):
    """A real fit whose validation losses are :data:`CURVE`; returns the fit, the net and its weights after every
    epoch (as the callback sees them: after any revert of that epoch)."""
    scripted = iter(CURVE)
    monkeypatch.setattr(envelope_module, "validation_loss", lambda loss_module, validation: [next(scripted)])
    torch.manual_seed(0)
    obs = torch.randn(60, 3, generator=torch.Generator().manual_seed(0))
    net = make_value_network(3, (8,))
    snapshots = []

    def record(epoch, info):
        snapshots.append(_weights(net))
        return epoch == stop_at

    (fit,) = fit_upper_envelope([net], obs, obs[:, 0] * 10, epochs=len(CURVE), patience=2, batch_size=16, lr=3e-2,
                                early_stopping=mode, progress=False, generators=[torch.Generator().manual_seed(1)],
                                callback=record)
    return fit, net, snapshots


@pytest.mark.parametrize("mode, reverts, returned, final_epoch", [
    ("paper", [4, 7], "best", 5), ("paper_best", [4, 7], "best", 5), ("paper_revert", [4, 7], "last", 8),
    ("as_coded", [], "last", 8), ("as_coded_last", [], "last", 8),
])
def test_every_early_stopping_mode_on_a_crafted_validation_curve(mode, reverts, returned, final_epoch, monkeypatch):
    fit, net, snapshots = _fit_on_curve(mode, monkeypatch)
    assert fit.epochs == 8 and fit.val_loss == CURVE
    assert (fit.best_epoch, fit.best_val_loss) == (5, 3.0)
    assert fit.revert_epochs == reverts and fit.returned == returned
    # the returned weights are the recorded ones: those after the best epoch, or after the last
    assert _equal(_weights(net), snapshots[final_epoch - 1])
    if reverts:  # a revert really loads the copy: after epoch 4 the weights are those after epoch 2
        assert _equal(snapshots[3], snapshots[1]) and _equal(snapshots[6], snapshots[4])
    else:  # as coded, training never jumps back
        assert not _equal(snapshots[3], snapshots[1])


def test_a_truthy_callback_stops_the_fit_with_the_best_weights_so_far(monkeypatch):
    fit, net, snapshots = _fit_on_curve("paper", monkeypatch, stop_at=3)
    assert fit.epochs == 3 and fit.best_epoch == 2
    assert _equal(_weights(net), snapshots[1])


def test_split_forces_the_largest_return_into_training():
    for seed in range(5):
        g = torch.Generator().manual_seed(seed)
        returns = torch.randn(101, generator=g)
        best = int(returns.argmax())
        train, val = envelope_split(returns, 0.2, generator=g)
        assert int(train[0]) == best and best not in val.tolist()
        assert (len(train), len(val)) == (math.floor(0.8 * 101) + 1, 101 - math.floor(0.8 * 101) - 1)
        assert sorted(torch.cat([train, val]).tolist()) == list(range(101))
    # through the fit: the peak is trained on however the rest is shuffled
    obs = torch.randn(40, 2, generator=torch.Generator().manual_seed(0))
    returns = torch.zeros(40)
    returns[17] = 100.0
    (fit,) = fit_upper_envelope([make_value_network(2, (8,))], obs, returns, epochs=1, progress=False,
                                generators=[torch.Generator().manual_seed(3)])
    assert 17 in fit.train_index.tolist() and 17 not in fit.val_index.tolist()


def test_without_a_validation_set_the_last_weights_come_back():
    obs = torch.randn(30, 2, generator=torch.Generator().manual_seed(0))
    net = make_value_network(2, (8,))
    snapshots = []
    (fit,) = fit_upper_envelope([net], obs, obs[:, 0], epochs=3, val_fraction=0.0, progress=False,
                                callback=lambda epoch, info: snapshots.append(_weights(net)))
    assert len(fit.val_index) == 0 and fit.best_epoch == 3 and fit.returned == "last"
    assert all(math.isnan(v) for v in fit.val_loss) and _equal(_weights(net), snapshots[-1])
    with pytest.warns(UserWarning, match="no validation point"):
        fit_upper_envelope([make_value_network(2, (8,))], obs[:3], obs[:3, 0], epochs=1, progress=False)


def _pbail(envelope: dict | None = None, **kwargs) -> tuple[ProgressiveBAIL, TensorDict]:
    torch.manual_seed(0)
    spec = action_spec_from_bounds([-1.0, -1.0], [1.0, 1.0])
    envelope = {"hidden": [16, 16], "validate_every": 1, "patience": 2, "lr": 0.05, **(envelope or {})}
    config = algo_config("pbail", policy={"hidden": [16, 16]}, batch_size=40, envelope=envelope, **kwargs)
    algo = ProgressiveBAIL(3, spec, config)
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

"""The one training loop (one seed: a list of one): schedule in epochs of samples, evaluation cadence, scores,
checkpoints."""

from __future__ import annotations

import torch
from tensordict import TensorDict

from torchrl_bail.algorithms.bc import BehaviourCloning
from torchrl_bail.configuration.config_builders import algo_config
from torchrl_bail.modules import action_spec_from_bounds
from torchrl_bail.training.trainer import AlgorithmTrainee, EvalPoint, TrainHistory, make_trainee, train


def _bc(epochs: float, batch_size: int = 10) -> BehaviourCloning:
    config = algo_config("bc", policy={"hidden": [16]}, batch_size=batch_size, epochs=epochs)
    return BehaviourCloning(3, action_spec_from_bounds([-1.0], [1.0]), config)


def _data(n: int = 200) -> TensorDict:
    g = torch.Generator().manual_seed(0)
    obs = torch.randn(n, 3, generator=g)
    return TensorDict({"observation": obs, "action": torch.tanh(obs[:, :1] - 0.5 * obs[:, 1:2])}, [n])


def test_schedule_counts_samples_not_iterations():
    algo = _bc(epochs=1000 / 1e6, batch_size=10)  # 1000 samples = 100 updates
    calls = []
    (history,) = train(make_trainee([algo], [_data()]), evaluate=lambda p: [float(len(calls.append(1) or calls))],
                       eval_every_epochs=250 / 1e6, progress=False)
    assert history.iterations == 100
    assert [e.iteration for e in history.evaluations] == [25, 50, 75, 100]
    assert [round(e.epoch * 1e6) for e in history.evaluations] == [250, 500, 750, 1000]
    assert history.final_return(window=2) == 3.5 and history.best_return() == 4.0


def test_final_evaluation_happens_even_off_cadence():
    algo = _bc(epochs=95 / 1e6, batch_size=10)  # 10 updates (ceil), evaluation every 4
    (history,) = train(make_trainee([algo], [_data()]), evaluate=lambda p: [0.0], eval_every_epochs=40 / 1e6,
                       progress=False)
    assert [e.iteration for e in history.evaluations] == [4, 8, 10]


def test_bc_fits_the_behaviour_and_checkpoints(tmp_path):
    torch.manual_seed(0)
    data = _data(500)
    algo = _bc(epochs=40_000 / 1e6, batch_size=50)
    before = algo.bc_loss(data)["loss_bc"].item()
    train(make_trainee([algo], [data]), evaluate=lambda p: [0.0], eval_every_epochs=20_000 / 1e6, progress=False,
          checkpoint_paths=[tmp_path / "checkpoint.pt"])
    after = algo.bc_loss(data)["loss_bc"].item()
    assert after < 0.2 * before
    state = torch.load(tmp_path / "checkpoint.pt", weights_only=False)
    assert state["iteration"] == 800 and len(state["evaluations"]) == 2
    fresh = _bc(epochs=1.0)
    fresh.load_state_dict(state["algorithm"])
    assert fresh.bc_loss(data)["loss_bc"].item() == after
    assert not list(tmp_path.glob(".*tmp"))  # no temp files left behind


def test_final_return_window_is_the_mean_of_the_last_evaluations():
    h = TrainHistory(evaluations=[EvalPoint(i, i / 2, float(i)) for i in range(1, 21)])
    assert h.final_return(10) == sum(range(11, 21)) / 10
    assert h.final_return(50) == sum(range(1, 21)) / 20


def test_each_evaluation_keeps_and_logs_its_discounted_return(tmp_path):
    """The evaluation's mean discounted return (at FQE's gamma) goes into each evaluation point, the eval logs
    (``eval/discounted_return`` beside ``eval/return``) and the checkpoint; a float score has none."""
    from torchrl_bail.evaluation import EvalResult

    class Logger:
        def __init__(self):
            self.scalars = {}

        def log_scalar(self, name, value, step):
            self.scalars.setdefault(name, []).append((step, value))

    logger, results = Logger(), iter([EvalResult([3.0, 5.0], [4, 4], discounted_returns=[2.0, 3.0], gamma=0.99),
                                      EvalResult([7.0, 9.0], [4, 4], discounted_returns=[6.0, 7.0], gamma=0.99)])
    algo = _bc(epochs=20 / 1e6, batch_size=10)  # 2 updates, an evaluation after each
    (history,) = train(make_trainee([algo], [_data()]), evaluate=lambda p: [next(results)], loggers=[logger],
                       eval_every_epochs=10 / 1e6, progress=False, checkpoint_paths=[tmp_path / "checkpoint.pt"])
    assert [e.discounted_return for e in history.evaluations] == [2.5, 6.5]
    assert logger.scalars["eval/discounted_return"] == [(1, 2.5), (2, 6.5)]
    assert logger.scalars["eval/return"] == [(1, 4.0), (2, 8.0)]
    assert history.final_discounted_return(window=2) == 4.5 and history.final_discounted_return(window=1) == 6.5
    state = torch.load(tmp_path / "checkpoint.pt", weights_only=False)
    assert [e["discounted_return"] for e in state["evaluations"]] == [2.5, 6.5]
    assert EvalPoint(**{k: v for k, v in state["evaluations"][0].items() if k != "discounted_return"}) == \
        EvalPoint(1, history.evaluations[0].epoch, 4.0, [3.0, 5.0], 0)  # a checkpoint from before: None
    (floats,) = train(make_trainee([_bc(epochs=10 / 1e6)], [_data()]), evaluate=lambda p: [1.0], progress=False)
    assert floats.evaluations[0].discounted_return is None and floats.final_discounted_return() is None


def test_empty_data_is_a_clear_error():
    import pytest

    with pytest.raises(ValueError, match="empty"):
        make_trainee([_bc(1.0)], [_data(0)])


def test_checkpoints_before_the_first_update_and_on_a_clock(tmp_path, monkeypatch):
    """A kill before the first evaluation keeps what prepare produced; the time cadence adds checkpoints."""
    from torchrl_bail.training import trainer

    saved = []
    monkeypatch.setattr(trainer, "save_checkpoint", lambda path, state: saved.append(state["iteration"]))
    train(AlgorithmTrainee(_bc(epochs=100 / 1e6), _data()), evaluate=lambda p: [0.0], eval_every_epochs=50 / 1e6,
          progress=False, checkpoint_paths=[tmp_path / "c.pt"])
    assert saved == [0, 5, 10]  # before the first update, then at each evaluation
    saved.clear()
    train(AlgorithmTrainee(_bc(epochs=100 / 1e6), _data()), evaluate=lambda p: [0.0], eval_every_epochs=50 / 1e6,
          progress=False, checkpoint_paths=[tmp_path / "c.pt"], checkpoint_every_s=0.0)
    assert saved == list(range(11))

"""Policy snapshots (``eval.snapshots=N``) and the offline checkpoint selection of ``python -m torchrl_bail.ope``.

A tiny BC run of 6 iterations evaluated after each keeps 3 snapshots (iterations 2, 4, 6) listed in its summary; a
run killed twice (once between a snapshot and its checkpoint) ends with the same files and summary; ``ope`` fits
each snapshot, selects the highest estimate and writes the same ``fqe_selected`` into ``ope.json`` and
``summary.json`` (its ``online_return`` is the evaluation return the run recorded for that snapshot); the report
carries it. A run at the default ``eval.snapshots=0`` keeps none and its summary has no new key.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch
from _summaries import comparable
from hydra import compose, initialize_config_dir

import torchrl_bail.algorithms as algorithms_module
import torchrl_bail.training.trainer as trainer_module
from torchrl_bail import config_dir
from torchrl_bail.configuration.config import ConfigError, validate_config
from torchrl_bail.training.resume import comparable_config, diff_configs
from torchrl_bail.training.trainer import evaluation_count, snapshot_indices

ROOT = Path(__file__).resolve().parents[1]
TINY = ["+exp=hopper_ddpg05", "preset=quick", "batch.steps=1000", "batch.start_steps=200",
        "batch.agent.actor_hidden=[32,32]", "batch.agent.critic_hidden=[32,32]", "env.max_episode_steps=50",
        "eval.episodes=2", "eval.max_steps=50", "returns.horizon=50", "progress=false"]
#: 6 iterations of 1000 samples, an evaluation after each
BC = ["algo=bc", "algo.epochs=0.006", "eval.every_epochs=0.001"]
#: a fit of seconds (as tests/test_ope.py)
FAST = ["--updates", "60", "--log-every", "20", "--hidden", "16,16", "--no-progress", "--fits", "1"]  # one fit a policy


class _Kill(BaseException):
    """Stands in for SIGKILL: raised mid-run, caught by nothing, leaves the disk as it is."""


def _cfg(data_dir, *overrides):
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        return compose("config", overrides=[*TINY, f"data_dir={data_dir}", *overrides])


def _summary(run_dir) -> dict:
    return json.loads((run_dir / "summary.json").read_text())


def _logged_returns(run_dir) -> dict[int, float]:
    lines = (run_dir / "logs" / "scalars" / "eval" / "return.csv").read_text().splitlines()
    return {int(step): float(value) for step, value in (line.split(",") for line in lines)}


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("batches")


@pytest.fixture(scope="module")
def snapshot_run(data_dir, tmp_path_factory):
    from torchrl_bail.train import run

    run_dir = tmp_path_factory.mktemp("runs") / "snapshots3"
    run(_cfg(data_dir, *BC, "eval.snapshots=3"), run_dir)
    return run_dir


def test_snapshots_are_spread_evenly_and_the_last_is_the_final_evaluation():
    assert snapshot_indices(6, 3) == [1, 3, 5] and snapshot_indices(10, 3) == [3, 6, 9]
    assert snapshot_indices(20, 1) == [19] and snapshot_indices(3, 5) == [0, 1, 2] and snapshot_indices(7, 0) == []
    assert all(snapshot_indices(e, n)[-1] == e - 1 for e in range(1, 30) for n in range(1, 12))
    assert all(len(set(snapshot_indices(e, n))) == min(e, n) for e in range(1, 30) for n in range(12))
    assert evaluation_count(6, 1) == 6 and evaluation_count(10, 3) == 4


def test_eval_snapshots_is_checked_and_a_run_of_its_own(data_dir):
    with pytest.raises(ConfigError, match=r"eval\.snapshots = -1: expected an integer >= 0"):
        validate_config(_cfg(data_dir, "eval.snapshots=-1"))
    default, three = _cfg(data_dir), _cfg(data_dir, "eval.snapshots=3")
    assert default.eval.snapshots == 0
    # at 0 the key is left out of the comparison: checkpoints written before it existed resume; 3 is another run
    assert "snapshots" not in comparable_config(default)["eval"]
    assert diff_configs(comparable_config(default), comparable_config(three)) == ["eval.snapshots: (absent) -> 3"]


def test_a_run_keeps_its_snapshots_and_lists_them_in_its_summary(snapshot_run):
    from torchrl_bail.evaluation.policy import load_policy

    summary = _summary(snapshot_run)
    assert summary["iterations"] == 6 and len(summary["snapshots"]) == 3
    logged = _logged_returns(snapshot_run)
    assert [s["iteration"] for s in summary["snapshots"]] == [2, 4, 6]
    assert sorted(p.name for p in (snapshot_run / "snapshots").iterdir()) == [f"policy_{i}.pt" for i in (2, 4, 6)]
    for entry in summary["snapshots"]:
        assert entry["path"] == f"snapshots/policy_{entry['iteration']}.pt"
        assert entry["eval_return"] == logged[entry["iteration"]]  # the return evaluated at that point
        info = load_policy(snapshot_run / entry["path"]).record["info"]
        assert (info["iteration"], info["evaluation"], info["mean_return"]) == \
            (entry["iteration"], entry["evaluation"], entry["eval_return"])
    final, last = load_policy(snapshot_run), load_policy(snapshot_run / summary["snapshots"][-1]["path"])
    for key, value in final.state_dict().items():
        assert torch.equal(value, last.state_dict()[key]), "the last snapshot is the final policy"
    first = load_policy(snapshot_run / summary["snapshots"][0]["path"])
    assert any(not torch.equal(v, first.state_dict()[k]) for k, v in final.state_dict().items())


def test_a_killed_run_ends_with_the_snapshots_of_an_uninterrupted_one(snapshot_run, data_dir, tmp_path,
                                                                       monkeypatch):
    """Killed while writing the checkpoint of iteration 4 (its snapshot already on disk), then in update 6; the
    finished run's snapshot files are byte for byte the reference's, and so is its summary."""
    from torchrl_bail import train as train_module

    cfg = _cfg(data_dir, *BC, "eval.snapshots=3")
    run_dir = tmp_path / "killed"
    save = trainer_module.save_checkpoint

    def dying_save(path, state):
        if state["iteration"] == 4:
            assert (run_dir / "snapshots" / "policy_4.pt").is_file()
            raise _Kill
        save(path, state)

    monkeypatch.setattr(trainer_module, "save_checkpoint", dying_save)
    with pytest.raises(_Kill):
        train_module.run(cfg, run_dir)
    monkeypatch.setattr(trainer_module, "save_checkpoint", save)
    assert torch.load(run_dir / "checkpoint.pt", weights_only=False)["iteration"] == 3

    build = algorithms_module.build_algorithm

    def dying_build(*args, **kwargs):  # the next process continues from iteration 3: its third update is 6
        algo = build(*args, **kwargs)
        update, calls = algo.update, [0]

        def dying_update(batch):
            calls[0] += 1
            if calls[0] == 3:
                raise _Kill
            return update(batch)

        algo.update = dying_update
        return algo

    monkeypatch.setattr(algorithms_module, "build_algorithm", dying_build)
    with pytest.raises(_Kill):
        train_module.run(cfg, run_dir)
    monkeypatch.setattr(algorithms_module, "build_algorithm", build)
    (summary,) = train_module.run(cfg, run_dir)
    assert summary["resumed_from_iteration"] == [3, 5]
    reference = _summary(snapshot_run)
    assert comparable(summary) == comparable(reference)
    for entry in reference["snapshots"]:
        assert (run_dir / entry["path"]).read_bytes() == (snapshot_run / entry["path"]).read_bytes(), entry["path"]
    assert sorted(p.name for p in (run_dir / "snapshots").iterdir()) == \
        sorted(p.name for p in (snapshot_run / "snapshots").iterdir())


def test_ope_selects_a_snapshot_and_records_it_in_ope_json_and_the_summary(snapshot_run, tmp_path, monkeypatch,
                                                                          capsys):
    import torchrl_bail.ope as ope_module
    from torchrl_bail.report import find_runs, fqe_selected_return, group_runs, summarise

    run_dir = tmp_path / "run"
    shutil.copytree(snapshot_run, run_dir)
    fit_fqe = ope_module.fit_fqe
    assert ope_module.main([str(run_dir), "--seed", "2", *FAST]) == 0
    assert "FQE selects snapshots/policy_" in capsys.readouterr().out
    ope, summary = json.loads((run_dir / "ope.json").read_text()), _summary(run_dir)
    selected = ope["fqe_selected"]
    assert summary["fqe_selected"] == selected and set(selected) == {"path", "iteration", "fqe_estimate",
                                                                     "online_return"}
    ranked = ope["snapshots"]
    assert [(c["path"], c["iteration"], c["eval_return"]) for c in ranked] == \
        [(s["path"], s["iteration"], s["eval_return"]) for s in summary["snapshots"]]
    best = max(ranked, key=lambda c: c["fqe_estimate"])
    assert (selected["path"], selected["iteration"], selected["fqe_estimate"]) == \
        (best["path"], best["iteration"], best["fqe_estimate"]) and best["rank"] == 1
    assert sorted(c["rank"] for c in ranked) == [1, 2, 3]
    recorded = {s["path"]: s["eval_return"] for s in summary["snapshots"]}
    assert selected["online_return"] == recorded[selected["path"]]
    assert selected["online_return"] == _logged_returns(run_dir)[selected["iteration"]]
    # the last snapshot is the final policy: its estimate is ope.json's own fit; the others have their own records
    assert ranked[-1]["fitted_in"] == "ope.json" and ranked[-1]["fqe_estimate"] == ope["estimate"]
    for candidate in ranked[:-1]:
        record = json.loads((run_dir / candidate["fitted_in"]).read_text())
        assert record["estimate"] == candidate["fqe_estimate"] and record["seed"] == 2
        assert record["policy"] == Path(candidate["path"]).name
    assert len({c["fqe_estimate"] for c in ranked}) == 3  # three policies, three estimates
    assert not list(run_dir.rglob("*_checkpoint.pt"))
    # kept: nothing is fitted again; a summary that lost its selection gets it back from ope.json
    monkeypatch.setattr(ope_module, "fit_fqe", lambda *a, **k: pytest.fail("a finished fit was redone"))
    del summary["fqe_selected"]
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    assert ope_module.main([str(run_dir), "--seed", "2", *FAST]) == 0
    assert _summary(run_dir)["fqe_selected"] == selected
    # so is a snapshot's record when ope.json is refitted
    (run_dir / "ope.json").unlink()
    fitted = []
    monkeypatch.setattr(ope_module, "fit_fqe", lambda *a, **k: fitted.append(1) or fit_fqe(*a, **k))
    assert ope_module.main([str(run_dir), "--seed", "2", *FAST]) == 0
    assert len(fitted) == 1 and json.loads((run_dir / "ope.json").read_text())["fqe_selected"] == selected
    # the report carries the selected snapshot's return beside final_return and best_return
    (row,) = summarise(group_runs(find_runs([run_dir])), reps=50)
    assert fqe_selected_return(_summary(run_dir)) == selected["online_return"]
    assert row["fqe_selected_return_mean"] == selected["online_return"] and row["fqe_selected_runs"] == 1


def test_a_killed_selection_continues_to_the_same_choice(snapshot_run, tmp_path, monkeypatch, capsys):
    """SIGTERM during the fit of the second snapshot (``snapshots/policy_4.pt``): the command stops with that fit's
    checkpoint; the same command keeps the finished fits, continues that one and selects what an uninterrupted
    command selects."""
    import signal

    import torchrl_bail.ope as ope_module
    from torchrl_bail.core import interrupts

    reference, run_dir = tmp_path / "reference", tmp_path / "run"
    shutil.copytree(snapshot_run, reference)
    shutil.copytree(snapshot_run, run_dir)
    args = ["--seed", "1", *FAST]
    assert ope_module.main([str(reference), *args]) == 0
    expected = json.loads((reference / "ope.json").read_text())
    calls = {"n": 0}

    def sigterm_in_the_third_fit():  # polled once per update: 60 of ope.json's fit, 60 of policy_2's, then 30
        calls["n"] += 1
        return signal.SIGTERM if calls["n"] >= 150 else None

    monkeypatch.setattr(interrupts, "requested", sigterm_in_the_third_fit)
    assert ope_module.main([str(run_dir), *args]) == 128 + signal.SIGINT  # the poll is faked (tests/test_ope.py)
    assert "saved the FQE fit at update 30" in capsys.readouterr().err
    assert (run_dir / "snapshots" / "ope_policy_4_checkpoint.pt").is_file()
    assert "fqe_selected" not in _summary(run_dir) and "fqe_selected" not in json.loads(
        (run_dir / "ope.json").read_text())
    monkeypatch.undo()
    assert ope_module.main([str(run_dir), *args]) == 0
    again = json.loads((run_dir / "ope.json").read_text())
    assert again["fqe_selected"] == expected["fqe_selected"] == _summary(run_dir)["fqe_selected"]
    assert [c["fqe_estimate"] for c in again["snapshots"]] == [c["fqe_estimate"] for c in expected["snapshots"]]
    assert json.loads((run_dir / "snapshots" / "ope_policy_4.json").read_text())["resumed_at"] == 30
    assert json.loads((run_dir / "snapshots" / "ope_policy_2.json").read_text())["resumed_at"] == 0
    assert not list(run_dir.rglob("*_checkpoint.pt"))


def test_stacked_seeds_keep_each_seeds_snapshots(data_dir, tmp_path):
    from torchrl_bail.evaluation.policy import load_policy
    from torchrl_bail.train import run

    summaries = run(_cfg(data_dir, *BC, "eval.snapshots=2", "seeds=[1,2]"), tmp_path / "seed1")
    for seed, summary in zip((1, 2), summaries, strict=True):
        run_dir = tmp_path / f"seed{seed}"
        assert [s["iteration"] for s in summary["snapshots"]] == [3, 6]
        assert sorted(p.name for p in (run_dir / "snapshots").iterdir()) == ["policy_3.pt", "policy_6.pt"]
        final, last = load_policy(run_dir), load_policy(run_dir / "snapshots" / "policy_6.pt")
        assert all(torch.equal(v, last.state_dict()[k]) for k, v in final.state_dict().items())
        assert summary["snapshots"][0]["eval_return"] == _logged_returns(run_dir)[3]


def test_a_default_run_keeps_no_snapshot_and_its_summary_is_unchanged(data_dir, tmp_path, capsys):
    """``eval.snapshots=0``: no snapshots folder, no new summary key (the keys of a default run, in their order, are
    those of the kept getting-started run's summary, BAIL's own aside), and ``ope`` leaves the summary alone."""
    from torchrl_bail.ope import main as ope_main
    from torchrl_bail.train import run

    run_dir = tmp_path / "default"
    (summary,) = run(_cfg(data_dir, *BC), run_dir)
    assert not (run_dir / "snapshots").exists()
    kept = json.loads((ROOT / "results" / "getting_started" / "summary.json").read_text())
    bail_keys = {"envelope_fraction_below", "envelope_best_epoch", "envelope_median_gap", "selected_fraction",
                 "num_selected", "selection_border"}
    # keys every run has gained since the kept run was made (its discounted return, its thread count)
    newer = {"final_discounted_return", "torch_threads", "platform"}
    assert [k for k in summary if k not in newer] == [k for k in kept if k not in bail_keys | {"platform"}]
    text = (run_dir / "summary.json").read_text()
    assert ope_main([str(run_dir), *FAST]) == 0
    assert "selects" not in capsys.readouterr().out
    assert (run_dir / "summary.json").read_text() == text
    assert "fqe_selected" not in json.loads((run_dir / "ope.json").read_text())

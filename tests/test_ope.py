"""``python -m torchrl_bail.ope`` end to end on a tiny trained run: ope.json, same seed same estimate, kept unless
--force, a killed fit continues to the uninterrupted numbers, and bad arguments stop it in one line (exit status 2)."""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from _batch_rl_testing import one_thread  # noqa: F401 (autouse fixture)
from _contract import ALGO_CASES, TINY_RUN
from hydra import compose, initialize_config_dir

from torchrl_bail import config_dir, interrupts
from torchrl_bail.ope import main

#: a fit of seconds: 60 updates of a 16-16 network, a curve point every 20
FAST = ["--updates", "60", "--log-every", "20", "--hidden", "16,16", "--no-progress"]


def _train_tiny(algo: str, data_dir, run_dir: Path) -> Path:
    """A run of ``algo`` through the config on the session's tiny batch (``_contract.TINY_RUN``), in ``run_dir``."""
    from torchrl_bail.train import run

    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("config", overrides=[*TINY_RUN, f"algo={algo}", *ALGO_CASES[algo].cli, f"data_dir={data_dir}"])
    run(cfg, run_dir)
    return run_dir


@pytest.fixture(scope="module")
def tiny_run(tiny_run_data_dir, tmp_path_factory):
    """A BC run on the session's tiny batch."""
    return _train_tiny("bc", tiny_run_data_dir, tmp_path_factory.mktemp("bc_run"))


def _ope(run_dir, name="ope.json") -> dict:
    return json.loads((run_dir / name).read_text())


def test_ope_writes_a_finite_estimate_and_the_same_seed_gives_the_same_one(tiny_run, capsys):
    assert main([str(tiny_run), "--seed", "3", *FAST]) == 0
    assert "FQE estimate" in capsys.readouterr().out
    first = _ope(tiny_run)
    assert math.isfinite(first["estimate"]) and first["updates"] == 60 and first["seed"] == 3
    assert [p["update"] for p in first["curve"]] == [20, 40, 60]
    assert all(math.isfinite(p["estimate"]) and math.isfinite(p["td_loss"]) for p in first["curve"])
    assert first["estimate"] == first["curve"][-1]["estimate"] and first["algo"] == "bc"
    assert first["num_transitions"] == 600 and first["num_episode_starts"] >= 1
    assert first["platform"] == json.loads((tiny_run / "summary.json").read_text())["platform"], \
        "the fit records the platform as the run's summary does"
    assert not (tiny_run / "ope_checkpoint.pt").exists()

    text = (tiny_run / "ope.json").read_text()
    assert main([str(tiny_run), "--seed", "4", *FAST]) == 0  # kept: a finished ope.json is not redone
    assert "kept" in capsys.readouterr().out and (tiny_run / "ope.json").read_text() == text

    assert main([str(tiny_run), "--seed", "3", "--force", *FAST]) == 0
    again = _ope(tiny_run)
    assert again["estimate"] == first["estimate"] and again["curve"] == first["curve"]

    assert main([str(tiny_run), "--seed", "4", "--force", *FAST]) == 0
    assert _ope(tiny_run)["estimate"] != first["estimate"]


@pytest.mark.parametrize("algo", ["bcq", "bear", "iql", "pbail"])
def test_every_algorithms_policy_is_scored_and_a_sampling_one_by_its_seed(algo, tiny_run_data_dir, tmp_path):
    """The policies the OPE study scores at paper scale include BCQ's and BEAR's best-of-N, which sample: their fit
    is as reproducible as a deterministic policy's (one seeded draw per state), and each algorithm's ``policy.pt``
    loads and scores (BC's is the module's ``tiny_run``; BAIL's, MARWIL's and TD3+BC's are BC-shaped actors)."""
    run_dir = _train_tiny(algo, tiny_run_data_dir, tmp_path)
    assert main([str(run_dir), "--seed", "3", *FAST]) == 0
    first = _ope(run_dir)
    assert first["algo"] == algo and math.isfinite(first["estimate"]) and math.isfinite(first["action_gap"])
    assert main([str(run_dir), "--seed", "3", "--force", *FAST]) == 0
    assert _ope(run_dir)["estimate"] == first["estimate"], "the same seed, the same estimate"


def test_the_action_gap_is_recorded_and_added_to_an_older_record_without_a_new_fit(tiny_run, monkeypatch, capsys):
    """``ope.json`` carries how far the policy acts from the batch (:func:`torchrl_bail.ope.action_gap`); a record
    written before ope recorded it gets it on the next call, from the policy and batch alone: no fit runs again."""
    import torchrl_bail.ope as ope_module
    from torchrl_bail.data.cache import load_cached_batch
    from torchrl_bail.policy import load_policy

    assert main([str(tiny_run), "--seed", "3", "--force", *FAST]) == 0
    fitted = _ope(tiny_run)
    batch = load_cached_batch(Path(fitted["batch"]), remedy="")
    assert fitted["action_gap"] == ope_module.action_gap(load_policy(tiny_run), batch.data, seed=3)
    assert 0.0 < fitted["action_gap"] < 2.0

    older = {k: v for k, v in fitted.items() if k != "action_gap"}
    (tiny_run / "ope.json").write_text(json.dumps(older))
    monkeypatch.setattr(ope_module, "fit_fqe", lambda *a, **k: pytest.fail("a kept fit was fitted again"))
    assert main([str(tiny_run), "--seed", "3", *FAST]) == 0
    assert _ope(tiny_run) == fitted
    assert main([str(tiny_run), "--seed", "3", *FAST]) == 0  # now whole: kept as it is
    assert "kept" in capsys.readouterr().out and _ope(tiny_run) == fitted


def test_a_killed_fit_continues_to_the_uninterrupted_numbers(tiny_run, monkeypatch, capsys):
    """A SIGTERM arriving at update 30 (seen by the loop's poll): the fit writes its checkpoint and stops (exit
    status 143, no ope_best.json); the same command continues from update 30 to the numbers of an uninterrupted fit."""
    args = [str(tiny_run), "--best", "--seed", "5", "--force", *FAST]
    assert main(args) == 0
    reference = _ope(tiny_run, "ope_best.json")
    (tiny_run / "ope_best.json").unlink()

    calls = {"n": 0}

    def sigterm_at_update_30():  # the loop polls once per update
        calls["n"] += 1
        return signal.SIGTERM if calls["n"] >= 30 else None

    monkeypatch.setattr(interrupts, "requested", sigterm_at_update_30)
    assert main(args) == 128 + signal.SIGINT  # the poll is faked: stop() finds no real pending signal
    assert "saved the FQE fit at update 30" in capsys.readouterr().err
    assert (tiny_run / "ope_best_checkpoint.pt").exists() and not (tiny_run / "ope_best.json").exists()
    monkeypatch.undo()

    assert main(args) == 0
    resumed = _ope(tiny_run, "ope_best.json")
    assert resumed["resumed_at"] == 30 and reference["resumed_at"] == 0
    assert resumed["estimate"] == reference["estimate"] and resumed["curve"] == reference["curve"]
    assert not (tiny_run / "ope_best_checkpoint.pt").exists()


def test_a_fit_stopped_before_its_first_timed_checkpoint_never_draws_the_policys_actions_again(
        tiny_run_data_dir, tmp_path, monkeypatch):
    """BCQ's best-of-N draws at every state and next state take minutes at 10^6 transitions: they are checkpointed
    as soon as they are drawn, so a fit killed at its first update (long before the first timed checkpoint)
    continues without running the policy again, to the uninterrupted fit's numbers."""
    import torchrl_bail.ope as ope_module
    from torchrl_bail.objectives.fqe import FQELoss

    run_dir = _train_tiny("bcq", tiny_run_data_dir, tmp_path)
    args = [str(run_dir), "--seed", "2", *FAST]
    assert main(args) == 0
    reference = _ope(run_dir)
    (run_dir / "ope.json").unlink()

    def killed(*args, **kwargs):
        raise interrupts.Interrupted(signal.SIGTERM)

    with monkeypatch.context() as patch:
        patch.setattr(ope_module, "fqe_update", killed)
        assert main(args) == 128 + signal.SIGTERM
    assert (run_dir / "ope_checkpoint.pt").exists() and not (run_dir / "ope.json").exists()

    monkeypatch.setattr(FQELoss, "add_policy_actions", lambda *a, **k: pytest.fail("the actions were drawn again"))
    assert main(args) == 0
    resumed = _ope(run_dir)
    assert resumed["estimate"] == reference["estimate"] and resumed["curve"] == reference["curve"]
    assert not (run_dir / "ope_checkpoint.pt").exists()


def test_a_run_whose_batch_is_not_in_the_cache(tiny_run, tmp_path, capsys):
    assert main([str(tiny_run), "--force", "--data-dir", str(tmp_path), *FAST]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "is not in the data cache" in err and str(tiny_run) in err


@pytest.mark.parametrize(("args", "message"), [
    (["--updates", "0"], "--updates 0: expected an integer >= 1"),
    (["--lr", "-1"], "--lr -1.0: expected a positive learning rate"),
    (["--gamma", "2"], "--gamma 2.0: expected a discount in [0, 1]"),
    (["--hidden", "16,x"], "expected layer sizes like 256,256"),
    (["--threads", "0"], "--threads 0: expected a positive number of threads"),
])
def test_bad_numbers_stop_the_command(tiny_run, args, message, capsys):
    with pytest.raises(SystemExit) as stop:
        main([str(tiny_run), *args])
    assert stop.value.code == 2 and message in capsys.readouterr().err


def test_bad_paths_stop_the_command_in_one_line(tiny_run, tmp_path, capsys):
    (tmp_path / "not_a_run").mkdir()
    unfinished = tmp_path / "unfinished"
    unfinished.mkdir()
    (unfinished / "config.yaml").write_text("seed: 1\n")
    for args, message in [([str(tmp_path / "nowhere")], "no such run directory"),
                          ([str(tmp_path / "not_a_run")], "not a run directory (no config.yaml)"),
                          ([str(tiny_run), str(unfinished)], "no policy.pt (a finished run directory holds it)"),
                          ([str(tiny_run), "--data-dir", str(tmp_path / "nowhere")], "--data-dir")]:
        assert main(args) == 2, args
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and message in err, err


def test_the_module_refuses_a_bad_path_before_loading_torch(tmp_path):
    """The command line is checked before torch loads (about 4 s): the process that refused it never imported it."""
    nowhere = str(tmp_path / "nowhere")
    code = ("import runpy, sys\n"
            f"sys.argv = ['torchrl_bail.ope', {nowhere!r}]\n"
            "try:\n"
            "    runpy.run_module('torchrl_bail.ope', run_name='__main__', alter_sys=True)\n"
            "except SystemExit as end:\n"
            "    print(end.code, 'torch' in sys.modules)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False)
    assert proc.stderr.strip() == f"torchrl_bail.ope: {nowhere}: no such run directory", proc.stderr
    assert proc.stdout.split() == ["2", "False"], proc.stdout

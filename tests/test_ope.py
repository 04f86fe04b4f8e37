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

from torchrl_bail import config_dir
from torchrl_bail.core import interrupts
from torchrl_bail.ope import main

#: a fit of seconds: 60 updates of a 16-16 network, a curve point every 20 (too few for the stopping rule), one fit
FAST = ["--updates", "60", "--log-every", "20", "--hidden", "16,16", "--no-progress", "--fits", "1"]


def _train_tiny(algo: str, data_dir, run_dir: Path, *extra: str) -> Path:
    """A run of ``algo`` through the config on the session's tiny batch (``_contract.TINY_RUN``), in ``run_dir``."""
    from torchrl_bail.train import run

    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("config", overrides=[*TINY_RUN, f"algo={algo}", *ALGO_CASES[algo].cli, f"data_dir={data_dir}",
                                           *extra])
    run(cfg, run_dir)
    return run_dir


@pytest.fixture(scope="module")
def tiny_run(tiny_run_data_dir, tmp_path_factory):
    """A BC run on the session's tiny batch."""
    return _train_tiny("bc", tiny_run_data_dir, tmp_path_factory.mktemp("bc_run"))


def _ope(run_dir, name="ope.json") -> dict:
    return json.loads((run_dir / name).read_text())


def _numbers(fits: list[dict]) -> list[dict]:
    """A record's fits without their wall times (the numbers a seed fixes)."""
    return [{k: v for k, v in fit.items() if k != "wall_time_s"} for fit in fits]


def test_ope_writes_a_finite_estimate_and_the_same_seed_gives_the_same_one(tiny_run, capsys):
    assert main([str(tiny_run), "--seed", "3", *FAST]) == 0
    assert "FQE estimate" in capsys.readouterr().out
    first = _ope(tiny_run)
    assert math.isfinite(first["estimate"]) and first["updates"] == 60 and first["seed"] == 3
    (fit,) = first["fits"]
    assert [p["update"] for p in fit["curve"]] == [20, 40, 60] and fit["seed"] == 3 and not fit["converged"]
    assert all(math.isfinite(p["estimate"]) and math.isfinite(p["td_loss"]) for p in fit["curve"])
    assert first["estimate"] == fit["estimate"] == fit["curve"][-1]["estimate"] and first["algo"] == "bc"
    assert first["num_fits"] == 1 and first["spread"] is None and first["converged_fits"] == 0
    assert first["num_transitions"] == 600 and first["num_episode_starts"] >= 1
    assert first["platform"] == json.loads((tiny_run / "summary.json").read_text())["platform"], \
        "the fit records the platform as the run's summary does"
    assert not (tiny_run / "ope_checkpoint.pt").exists()

    text = (tiny_run / "ope.json").read_text()
    assert main([str(tiny_run), "--seed", "4", *FAST]) == 0  # kept: a finished ope.json is not redone
    assert "kept" in capsys.readouterr().out and (tiny_run / "ope.json").read_text() == text

    assert main([str(tiny_run), "--seed", "3", "--force", *FAST]) == 0
    again = _ope(tiny_run)
    assert again["estimate"] == first["estimate"] and _numbers(again["fits"]) == _numbers(first["fits"])

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
    from torchrl_bail.evaluation.policy import load_policy

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
    assert resumed["estimate"] == reference["estimate"] and resumed["fits"][0]["curve"] == reference["fits"][0]["curve"]
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
    assert resumed["estimate"] == reference["estimate"] and resumed["fits"][0]["curve"] == reference["fits"][0]["curve"]
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
    (["--fits", "0"], "--fits 0: expected an integer >= 1"),
    (["--stop-window", "-1"], "--stop-window -1: expected an integer >= 0"),
    (["--stop-tol", "-0.1"], "--stop-tol -0.1: expected a tolerance >= 0"),
    (["--rule", "lower_bound", "--fits", "1"], "--rule lower_bound needs a spread, so --fits 2 or more"),
    (["--rule-lambda", "-1"], "--rule-lambda -1.0: expected a finite number >= 0"),
])
def test_bad_numbers_stop_the_command(tiny_run, args, message, capsys):
    with pytest.raises(SystemExit) as stop:
        main([str(tiny_run), *args])
    assert stop.value.code == 2 and message in capsys.readouterr().err


def test_bad_paths_stop_the_command_in_one_line(tiny_run, tmp_path, capsys):
    """A run that cannot be scored alone (or a bad --data-dir) stops the command in one line; beside a run that can
    be, see test_every_run_that_can_be_scored_is_scored_and_each_other_named."""
    (tmp_path / "not_a_run").mkdir()
    unfinished = tmp_path / "unfinished"
    unfinished.mkdir()
    (unfinished / "config.yaml").write_text("seed: 1\n")
    for args, message in [([str(tmp_path / "nowhere")], "no such run directory"),
                          ([str(tmp_path / "not_a_run")], "not a run directory (no config.yaml)"),
                          ([str(unfinished)], "no policy.pt (a finished run directory holds it)"),
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


# -- issue 53, item 4 ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("args", [["--updates", "-5"], ["--gamma", "2"], ["--updates", "x"], ["--lr", "0"]])
def test_a_bad_number_is_one_line_not_the_usage(tiny_run, args, capsys):
    """The guide promises one line and exit status 2 for a bad number: argparse's usage block (a dozen lines of
    options) is not printed, the option and its value are."""
    with pytest.raises(SystemExit) as stop:
        main([str(tiny_run), *args])
    err = capsys.readouterr().err.strip()
    assert stop.value.code == 2 and len(err.splitlines()) == 1, err
    assert err.startswith("torchrl_bail.ope: ") and args[0] in err and "usage:" not in err, err


def _copy_config(tiny_run: Path, run_dir: Path) -> Path:
    run_dir.mkdir()
    (run_dir / "config.yaml").write_text((tiny_run / "config.yaml").read_text())
    return run_dir


@pytest.mark.parametrize("damage", ["random_bytes", "truncated"])
def test_a_corrupt_policy_file_is_named_as_such(tiny_run, tmp_path, damage, capsys):
    """A policy.pt of random bytes, or cut short, is reported as a damaged file at its path, without torch's advice
    to load it with weights_only=False (right for a trusted file in another format, wrong for a damaged one)."""
    import os

    run_dir = _copy_config(tiny_run, tmp_path / "damaged")
    data = (tiny_run / "policy.pt").read_bytes()
    (run_dir / "policy.pt").write_bytes(os.urandom(4096) if damage == "random_bytes" else data[:len(data) // 2])
    assert main([str(run_dir), *FAST]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert str(run_dir / "policy.pt") in err and "corrupt or truncated" in err and "weights_only" not in err, err
    assert not (run_dir / "ope.json").exists()


@pytest.mark.parametrize("bad", ["no_policy", "corrupt_policy", "no_config"])
def test_every_run_that_can_be_scored_is_scored_and_each_other_named(tiny_run, tmp_path, bad, capsys):
    """A run that cannot be scored, whatever the reason (no policy.pt, a damaged one, no config.yaml), is reported
    in one line with its reason; every other run is scored all the same, and the command exits with status 2."""
    (tiny_run / "ope.json").unlink(missing_ok=True)
    broken = tmp_path / bad
    if bad == "no_config":
        broken.mkdir()
    else:
        _copy_config(tiny_run, broken)
    if bad == "corrupt_policy":
        (broken / "policy.pt").write_bytes(b"\x00" * 100)
    assert main([str(broken), str(tiny_run), *FAST]) == 2
    captured = capsys.readouterr()
    assert (tiny_run / "ope.json").is_file() and f"{tiny_run}: FQE estimate" in captured.out
    reasons = [line for line in captured.err.splitlines() if str(broken) in line]
    assert reasons and all(line.startswith("torchrl_bail.ope: ") for line in reasons), captured.err
    assert "1 of 2 runs could not be scored" in captured.err, captured.err


def test_a_kept_estimate_prints_as_a_fitted_one(tiny_run, capsys):
    """The estimate reads the same, to 3 decimals, whether the command fits it or keeps it."""
    import re

    assert main([str(tiny_run), "--seed", "3", "--force", *FAST]) == 0
    fitted = re.search(r"FQE estimate (\S+)", capsys.readouterr().out).group(1)
    assert main([str(tiny_run), "--seed", "3", *FAST]) == 0
    kept = capsys.readouterr().out
    assert "kept" in kept and re.search(r"FQE estimate (\S+)", kept).group(1) == fitted, (fitted, kept)
    assert fitted == f"{_ope(tiny_run)['estimate']:.3f}"


def _guide_snippet() -> str:
    import re

    page = (Path(__file__).resolve().parents[1] / "docs" / "guides" / "ope.md").read_text()
    section = page[page.index("## In your own code"):]
    return re.search(r"```python\n(.*?)```", section, flags=re.DOTALL).group(1)


def test_the_guides_own_code_snippet_runs_as_written(tiny_run, tmp_path, monkeypatch, capsys):
    """The guide's "In your own code" example runs as written, from the directory the README's first command ran in:
    its run directory (here the module's tiny run, linked at that path) and every name it uses are its own. Only
    the number of updates is cut, to keep the test short."""
    snippet = _guide_snippet()
    assert "updates=20_000" in snippet
    names = {}
    monkeypatch.chdir(tmp_path)
    match = next(line for line in snippet.splitlines() if line.startswith("run_dir = "))
    exec(compile(match, "run_dir", "exec"), {"Path": Path}, names)
    link = tmp_path / names["run_dir"]
    link.parent.mkdir(parents=True)
    link.symlink_to(tiny_run, target_is_directory=True)
    namespace = {"__name__": "__guide__"}
    exec(compile(snippet.replace("updates=20_000", "updates=20"), "ope.md example", "exec"), namespace)
    assert math.isfinite(namespace["result"]["estimate"]) and namespace["result"]["curve"][-1]["update"] == 20
    assert "FQE estimate" in capsys.readouterr().out


def test_the_fit_leaves_the_callers_random_stream_as_it_was(tiny_run):
    """fit_fqe and action_gap seed a generator of their own: the caller's torch stream goes on as without them."""
    import torch

    from torchrl_bail.data.cache import load_cached_batch
    from torchrl_bail.evaluation.policy import load_policy
    from torchrl_bail.ope import FQESettings, action_gap, fit_fqe

    main([str(tiny_run), "--seed", "3", *FAST])
    data = load_cached_batch(Path(_ope(tiny_run)["batch"]), remedy="").data
    policy = load_policy(tiny_run)
    settings = FQESettings(updates=5, hidden=(8,), log_every=5)
    torch.manual_seed(11)
    expected = torch.rand(4)
    torch.manual_seed(11)
    before = torch.rand(2)
    first = fit_fqe(policy, data, settings, seed=3)
    action_gap(policy, data, seed=3)
    assert torch.equal(torch.cat([before, torch.rand(2)]), expected), "the caller's stream changed"
    torch.manual_seed(999)  # and the fit's own numbers do not depend on the caller's stream
    assert fit_fqe(policy, data, settings, seed=3)["curve"] == first["curve"]


# -- issue 53, items 2 and 3: several fits per policy, the selection rules ------------------------------------------
SEVERAL = [arg for arg in FAST if arg not in ("--fits", "1")]


def test_several_fits_are_recorded_each_with_its_curve(tiny_run, capsys):
    """``--fits 2``: two fits of seeds 3 and 4, each the single fit of its seed; the estimate is their mean, the
    spread their standard deviation, and ``ope.json`` keeps every fit's curve."""
    import statistics

    assert main([str(tiny_run), "--seed", "3", "--force", *FAST]) == 0
    one = _ope(tiny_run)["fits"][0]
    assert main([str(tiny_run), "--seed", "4", "--force", *FAST]) == 0
    other = _ope(tiny_run)["fits"][0]
    assert main([str(tiny_run), "--seed", "3", "--force", *SEVERAL, "--fits", "2"]) == 0
    assert "std " in capsys.readouterr().out
    record = _ope(tiny_run)
    assert record["num_fits"] == 2 and _numbers(record["fits"]) == _numbers([one, other])
    assert [len(fit["curve"]) for fit in record["fits"]] == [3, 3]
    assert record["estimate"] == pytest.approx(statistics.mean([one["estimate"], other["estimate"]]), abs=1e-12)
    assert record["spread"] == pytest.approx(statistics.stdev([one["estimate"], other["estimate"]]), abs=1e-12)
    assert not list(tiny_run.glob("*_checkpoint.pt"))


def test_a_command_killed_in_its_second_fit_keeps_the_first(tiny_run, monkeypatch, capsys):
    """SIGTERM at update 30 of the second fit: the first fit's result is kept in its checkpoint, the second continues
    from its own, and the record equals an uninterrupted command's."""
    args = [str(tiny_run), "--best", "--seed", "5", "--force", *SEVERAL, "--fits", "2"]
    assert main(args) == 0
    reference = _ope(tiny_run, "ope_best.json")
    (tiny_run / "ope_best.json").unlink()
    calls = {"n": 0}

    def sigterm_in_the_second_fit():  # polled once per update: 60 of the first fit, then 30 of the second
        calls["n"] += 1
        return signal.SIGTERM if calls["n"] >= 90 else None

    monkeypatch.setattr(interrupts, "requested", sigterm_in_the_second_fit)
    assert main(args) == 128 + signal.SIGINT  # the poll is faked: stop() finds no real pending signal
    assert "saved the FQE fit at update 30" in capsys.readouterr().err
    assert (tiny_run / "ope_best_checkpoint.pt").is_file() and (tiny_run / "ope_best_fit1_checkpoint.pt").is_file()
    monkeypatch.undo()
    polls = {"n": 0}
    real_requested = interrupts.requested
    monkeypatch.setattr(interrupts, "requested", lambda: polls.update(n=polls["n"] + 1) or real_requested())
    assert main(args) == 0
    assert polls["n"] == 30, "only the second fit's last 30 updates ran: the first fit was kept"
    resumed = _ope(tiny_run, "ope_best.json")
    assert [fit["resumed_at"] for fit in resumed["fits"]] == [0, 30] and resumed["resumed_at"] == 30
    assert [fit["curve"] for fit in resumed["fits"]] == [fit["curve"] for fit in reference["fits"]]
    assert resumed["estimate"] == reference["estimate"] and resumed["spread"] == reference["spread"]
    assert not list(tiny_run.glob("*_checkpoint.pt"))


def test_each_rule_picks_its_own_policy_on_a_case_where_they_differ():
    """Three policies: the first has the highest estimate but fits that disagree, the second acts far from the
    batch, the third is the best. ``mean`` deploys the first, ``lower_bound`` (k = 1) the second, ``gap_penalised``
    (lambda = 1, scale = the median estimate 9) the third; a rule's regret is 0 exactly when it deploys the best."""
    from torchrl_bail.ope import compare_rules, rule_scores, select_by_rule

    means, spreads, gaps, truth = [10.0, 9.0, 8.0], [5.0, 0.5, 0.5], [0.5, 0.9, 0.0], [1.0, 2.0, 3.0]
    assert rule_scores(means, rule="lower_bound", spreads=spreads) == [5.0, 8.5, 7.5]
    assert rule_scores(means, rule="gap_penalised", gaps=gaps) == pytest.approx([5.5, 0.9, 8.0])
    picks = {rule: select_by_rule(means, rule=rule, spreads=spreads, gaps=gaps)
             for rule in ("mean", "lower_bound", "gap_penalised")}
    assert picks == {"mean": 0, "lower_bound": 1, "gap_penalised": 2}
    report = compare_rules(means, {"true": truth, "reversed": truth[::-1]}, spreads=spreads, gaps=gaps, interval=False)
    assert {rule: report[rule]["true"]["regret"] for rule in picks} == {"mean": 2.0, "lower_bound": 1.0,
                                                                         "gap_penalised": 0.0}
    assert report["mean"]["reversed"]["regret"] == 0.0 and report["mean"]["reversed"]["spearman"] == 1.0
    assert report["mean"]["true"]["spearman"] == -1.0
    assert {rule: report[rule]["selected"] for rule in picks} == picks
    missing = compare_rules(means, {"true": truth}, gaps=gaps, interval=False)
    assert missing["lower_bound"] == {"available": False, "reason": missing["lower_bound"]["reason"]}
    assert "spread" in missing["lower_bound"]["reason"] and missing["gap_penalised"]["available"]
    with pytest.raises(ValueError, match="2 fits or more"):
        rule_scores(means, rule="lower_bound", spreads=[None, None, None])


def test_the_rule_chooses_among_a_runs_snapshots_and_a_new_rule_reranks_without_refitting(tiny_run_data_dir, tmp_path,
                                                                                          monkeypatch, capsys):
    """A run with 3 snapshots scored with ``--rule gap_penalised --fits 2``: the candidates carry their estimate,
    spread, action gap and score, and the selection is the highest score. The same command with ``--rule mean``
    ranks them again from the kept fits (nothing is fitted) and selects the highest estimate."""
    import torchrl_bail.ope as ope_module

    run_dir = _train_tiny("bc", tiny_run_data_dir, tmp_path / "run", "eval.snapshots=3")
    args = [str(run_dir), "--seed", "1", *SEVERAL, "--fits", "2"]
    assert main([*args, "--rule", "gap_penalised", "--rule-lambda", "2"]) == 0
    record = _ope(run_dir)
    candidates, selection = record["snapshots"], record["selection"]
    assert selection["rule"] == "gap_penalised" and selection["rule_lambda"] == 2.0 and selection["num_fits"] == 2
    scale = sorted(c["fqe_estimate"] for c in candidates)[1]
    for c in candidates:
        assert c["fqe_spread"] > 0 and 0 < c["action_gap"] < 2
        assert c["score"] == pytest.approx(c["fqe_estimate"] - 2.0 * c["action_gap"] * abs(scale))
    chosen = max(candidates, key=lambda c: c["score"])
    assert record["fqe_selected"]["path"] == chosen["path"] and chosen["rank"] == 1
    monkeypatch.setattr(ope_module, "fit_fqe", lambda *a, **k: pytest.fail("a kept fit was fitted again"))
    assert main([*args, "--rule", "mean"]) == 0
    again = _ope(run_dir)
    assert again["selection"]["rule"] == "mean"
    assert again["fqe_selected"]["path"] == max(again["snapshots"], key=lambda c: c["fqe_estimate"])["path"]
    assert [c["fqe_estimate"] for c in again["snapshots"]] == [c["fqe_estimate"] for c in candidates]
    assert "highest estimate" in capsys.readouterr().out


def test_the_guide_quotes_the_truth_record_and_the_defaults_are_its_measurement():
    """The OPE guide's figures on both truths, the selection rules and the stopping rule are
    ``results/ope_headline/truth.json``'s, and the command's defaults (4 fits, window 20, tolerance 0.02) are the
    ones that record measures; ``truth.py --check`` finds the record to be what the kept files give."""
    from torchrl_bail.ope import DEFAULT_FITS, FQESettings

    root = Path(__file__).resolve().parents[1]
    truth = json.loads((root / "results" / "ope_headline" / "truth.json").read_text())
    page = " ".join((root / "docs" / "guides" / "ope.md").read_text().split())

    def interval(q):
        return f"{q['spearman']:.2f} [{q['spearman_ci'][0]:.2f}, {q['spearman_ci'][1]:.2f}]"

    single = truth["ranking"]["single_fit"]
    assert f"| discounted, `γ = 0.99` | {interval(single['against_discounted'])} |" in page
    assert f"| undiscounted | {interval(single['against_undiscounted'])} |" in page
    rules = truth["ranking"]["rules"]["final_policies"]
    for rule in ("mean", "gap_penalised"):
        disc, und = rules[rule]["discounted"], rules[rule]["undiscounted"]
        assert (f"| {interval(disc)} | {disc['regret']:.2f} | {interval(und)} | {und['regret']:.1f} |") in page, rule
    assert not rules["lower_bound"]["available"] and "`lower_bound` | not computed" in page
    snaps = truth["ranking"]["rules"]["snapshots"]["mean_over_runs"]
    for quoted in (f"mean return of {snaps['mean']['mean_selected_return']:.1f}",
                   f"final policy's mean is {snaps['mean']['mean_final_return']:.1f}",
                   f"mean regret is {snaps['mean']['mean_regret']:.1f}",
                   f"`mean` gives {snaps['mean_every_run']['mean_selected_return']:.1f} on average"):
        assert quoted in page, quoted
    curves = truth["curves"]
    assert curves["fits_for_half_the_tolerance"] == DEFAULT_FITS
    assert f"{100 * curves['noise']['median']:.2f} % of the estimate" in page
    assert (FQESettings.stop_window, FQESettings.stop_tol) == (20, 0.02)
    default = next(r for r in curves["rules"] if (r["rule"], r["window"], r["tol"]) == ("half_the_fit", 20, 0.02))
    (stop,) = default["stops"].values()
    assert f"1 of 40, BEAR's at {stop['update'] / 1e4:.1f} × 10^4 | {100 * stop['from_last']:.1f} % |" in page
    proc = subprocess.run([sys.executable, str(root / "results" / "ope_headline" / "truth.py"), "--check"],
                          capture_output=True, text=True, timeout=600, check=False)
    assert proc.returncode == 0, proc.stdout + proc.stderr[-2000:]

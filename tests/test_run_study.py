"""The results study's script (``results/run_study.py``): the jobs it runs and its learning-curve check."""

from __future__ import annotations

import importlib.util
import json
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from torchrl_bail.configuration.algo_schemas import ALGO_SCHEMAS, study_algorithms

SCRIPT = Path(__file__).resolve().parents[1] / "results" / "run_study.py"


@pytest.fixture(scope="module")
def run_study():
    spec = importlib.util.spec_from_file_location("run_study", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules["run_study"] = module  # its dataclasses look their module up while it loads
    spec.loader.exec_module(module)
    yield module
    sys.modules.pop("run_study", None)


def test_the_study_covers_every_cell_the_readme_lists(run_study):
    jobs = run_study.study_jobs()
    names = [j.name for j in jobs]
    every_batch = study_algorithms("all")
    # 11 batches; 3 seeds of: 2 envs x 5 batches x every_batch, 4 ablations, MARWIL with V fitted first on 3 Hopper
    # batches, 2 envs x 2 DDPG batches x BCQ/BEAR; then seeds 4 and 5 of BAIL and BC on Hopper's 2 DDPG batches
    assert len(names) == len(set(names)) == 11 + 3 * (2 * 5 * len(every_batch) + 4 + 3 + 2 * 2 * 2) + 2 * 2 * 2
    assert [j.name for j in jobs[-8:]] == [f"hopper_{kind}/{algo}/seed{s}" for algo in ("bail", "bc")
                                           for kind in ("ddpg01", "ddpg05") for s in (4, 5)], \
        "the first finding's seeds 4 and 5 run last"
    assert "walker_ddpg05/bail/seed4" not in names
    assert {"bail", "pbail", "bc", "marwil"} <= set(every_batch)
    collects = [j for j in jobs if j.module == "torchrl_bail.collect"]
    assert len(collects) == 11 and jobs[:11] == collects  # batches first
    for env in ("hopper", "walker"):
        for kind in ("ddpg01", "ddpg05", "sac", "med_stoch", "opt_det"):
            for algo in every_batch:
                assert {f"{env}_{kind}/{algo}/seed{s}" for s in (1, 2, 3)} <= set(names)
    for env in ("hopper", "walker"):
        for kind in ("ddpg01", "ddpg05"):
            for algo in ("bcq", "bear"):
                assert {f"{env}_{kind}/{algo}/seed{s}" for s in (1, 2, 3)} <= set(names)
            assert f"{env}_sac/bcq/seed1" not in names
    by_name = {j.name: j for j in jobs}
    assert by_name["hopper_opt_det/marwil/value_warmup/seed3"].args[-1] == "algo.value_warmup_updates=200"
    assert by_name["hopper_ddpg05/bail/D1_oracle/seed2"].args == [
        "+exp=hopper_ddpg05", "algo=bail", "seed=2", "preset=study", "batch.oracle.enabled=true",
        "returns.augment=oracle"]
    assert by_name["hopper_ddpg05/bail/D3_regression/seed1"].args[-1] == "algo.envelope.penalty=1"


def test_one_registry_line_puts_an_algorithm_in_the_study_or_keeps_it_out(run_study, monkeypatch):
    """The study's job lists read each schema's registry entry (``study``, ``paper_study``, ``cost``): IQL is out,
    TD3+BC is in on every batch, BCQ/BEAR on the DDPG batches; flipping one class variable moves the jobs."""
    names = {j.name for j in run_study.study_jobs()}
    assert not any("/iql/" in n for n in names) and "walker_opt_det/td3bc/seed3" in names
    assert study_algorithms("ddpg") == ["bcq", "bear"] and "iql" not in study_algorithms("all")
    monkeypatch.setattr(ALGO_SCHEMAS["iql"], "study", "ddpg")
    monkeypatch.setattr(run_study, "DDPG_ONLY", tuple(study_algorithms("ddpg")))
    names = {j.name for j in run_study.study_jobs()}
    assert {f"{env}_{kind}/iql/seed{s}" for env in ("hopper", "walker") for kind in ("ddpg01", "ddpg05")
            for s in (1, 2, 3)} == {n for n in names if "/iql/" in n}
    monkeypatch.setattr(ALGO_SCHEMAS["iql"], "paper_study", True)
    paper = [j for j in run_study.paper_hopper_jobs() if "/iql/" in j.name]
    assert [j.name for j in paper] == [f"hopper_ddpg05/iql/seed{s}" for s in (1, 2, 3)]  # DDPG batches only, 3 seeds
    assert "algo.epochs=25.6" in paper[0].args  # its cost class: 10^5 updates (of 256, its yaml's batch size)


def _run(root: Path, name: str, returns: list[float], algo: str = "bail", envelope_best_epoch: int | None = None,
         envelope_epochs: int = 50) -> None:
    run = root / "runs" / "hopper_ddpg05_b1" / algo / name
    scalars = run / "logs" / "scalars" / "eval"
    scalars.mkdir(parents=True)
    if envelope_best_epoch is not None:
        (run / "summary.json").write_text(json.dumps({"envelope_best_epoch": envelope_best_epoch}))
        (run / "config.yaml").write_text(f"algo:\n  envelope:\n    epochs: {envelope_epochs}\n    patience: 4\n")
    steps = [100 * (i + 1) for i in range(len(returns))]
    (scalars / "return.csv").write_text("".join(f"{s},{r}\n" for s, r in zip(steps, returns, strict=True)))
    (scalars / "epoch.csv").write_text("".join(f"{s},{0.2 * (i + 1)}\n" for i, s in enumerate(steps)))


def test_curve_check_tells_a_flat_curve_from_a_rising_one(run_study, tmp_path):
    # flat: the second half (evaluations 5..9) alternates around 500 -> no fitted change
    # their envelope fits: best epochs 12 and 46 of 50 (patience 4: both settled before the cap)
    _run(tmp_path, "seed1,preset=study", [100, 200, 300, 400, 500, 490, 510, 490, 510, 500], envelope_best_epoch=12)
    _run(tmp_path, "seed2,preset=study", [100, 200, 300, 400, 500, 510, 490, 510, 490, 500], envelope_best_epoch=46)
    # rising by 50 per evaluation over the second half: +200 across it, exactly on the line (spread 0); its envelope
    # had its best epoch 47 of 50: fewer than the patience's 4 epochs before the cap, still improving
    _run(tmp_path, "seed1,algo.envelope.penalty=1,preset=study", [0, 0, 0, 0, 0, 100, 150, 200, 250, 300],
         envelope_best_epoch=47)
    _run(tmp_path, "seed1,preset=study", [0, 100, 200, 300], algo="bc")  # a second half of 2 points: left out
    rows = {r["overrides"]: r for r in run_study.curve_check(tmp_path)}
    assert len(rows) == 2 and {r["algo"] for r in rows.values()} == {"bail"}
    flat, rising = rows[""], rows["algo.envelope.penalty=1"]
    assert flat["seeds"] == 2 and flat["evaluations"] == 10 and flat["second_half_mean"] == pytest.approx(500)
    assert flat["second_half_change"] == pytest.approx(0, abs=1e-9) and not flat["still_moving"]
    assert rising["second_half_change"] == pytest.approx(200)
    assert rising["residual_spread"] == pytest.approx(0, abs=1e-9)
    assert rising["still_moving"] and rising["second_half_mean"] == pytest.approx(200)
    assert flat["envelope_best_epochs"] == [12, 46] and flat["envelope_settled"] and flat["envelope_fits_at_cap"] == 0
    assert rising["envelope_fits_at_cap"] == 1 and not rising["envelope_settled"]
    assert json.loads((tmp_path / "curves.json").read_text()) == list(rows.values())
    table = (tmp_path / "curves.md").read_text()
    assert "| hopper_ddpg05_b1 | bail | algo.envelope.penalty=1 | 200.0 | +200.0 | 0.0 | **rising** | " \
           "47 of 50: **at the cap** |" in table
    assert "| 12, 46 of 50: stopped early |" in table and "(1 of 3 fits here)" in table


def test_the_paper_hopper_study_lands_the_final_buffer_first(run_study):
    jobs = run_study.paper_hopper_jobs()
    names = [j.name for j in jobs]
    assert len(names) == len(set(names))
    assert names[0] == "collect/hopper_ddpg05" and jobs[0].args == ["+exp=hopper_ddpg05"]  # the paper's 10^6 batch
    first_other_batch = names.index("collect/hopper_sac")
    ddpg05 = {n for n in names[:first_other_batch]}
    seeds = {algo: sum(n.startswith(f"hopper_ddpg05/{algo}/seed") for n in ddpg05)
             for algo in ("bail", "bc", "pbail", "marwil", "bcq", "bear")}
    assert seeds == {"bail": 5, "bc": 5, "pbail": 3, "marwil": 3, "bcq": 3, "bear": 3}
    assert sum(n.startswith("hopper_ddpg05/marwil/value_warmup/") for n in ddpg05) == 3
    by_name = {j.name: j for j in jobs}
    assert "algo.epochs=10" in by_name["hopper_ddpg05/bcq/seed1"].args  # 10^5 updates of 100
    assert [n for n in names[:first_other_batch] if "td3bc" in n] == [f"hopper_ddpg05/td3bc/seed{s}" for s in (1, 2, 3)]
    assert names.index("hopper_ddpg05/td3bc/seed1") > max(names.index(f"hopper_ddpg05/{a}/seed3") for a in seeds)
    assert by_name["hopper_ddpg05/bail/seed5"].args == ["+exp=hopper_ddpg05", "algo=bail", "seed=5"]  # the paper's
    assert all("preset=study" not in j.args for j in jobs)
    assert {f"hopper_sac/{a}/seed5" for a in ("bail", "bc")} <= set(names)
    assert "hopper_opt_det/bcq/seed3" in names and "collect/hopper_med_det" in names


@pytest.mark.parametrize("algo", ["bcq", "bear", "td3bc"])
def test_every_actor_critic_of_the_paper_cell_gets_10_5_updates_and_20_evaluations(run_study, algo):
    """Epochs count 10^6 samples, so an equal number of updates is a different number of epochs for TD3+BC's
    batches of 256 than for BCQ's and BEAR's of 100: the schedule is computed from each yaml's batch size, and the
    trainer's own arithmetic turns it into 10^5 updates with an evaluation every 5000."""
    import math

    from torchrl_bail.configuration.config_builders import algo_config

    overrides = dict(arg.split("=") for arg in run_study.paper_schedule(algo))
    batch_size = algo_config(algo).batch_size
    updates = math.ceil(float(overrides["algo.epochs"]) * 10**6 / batch_size)
    every = round(float(overrides["eval.every_epochs"]) * 10**6 / batch_size)
    assert (updates, every) == (10**5, 5000)
    if batch_size == 100:  # the names of the kept runs: BCQ's and BEAR's jobs must stay done
        assert overrides == {"algo.epochs": "10", "eval.every_epochs": "0.5"}
    assert run_study.paper_schedule("bail") == []


def test_status_reports_done_running_and_left_with_checkpoint_progress(run_study, tmp_path, capsys):
    import torch

    from torchrl_bail.behaviour.checkpoint import CollectionCheckpoint

    jobs = {j.name: j for j in run_study.paper_hopper_jobs()}
    outputs = tmp_path / "outputs" / "hopper_ddpg05_b1"
    done = outputs / "bail" / "seed1"
    done.mkdir(parents=True)
    (done / "summary.json").write_text("{}")
    half = outputs / "bc" / "seed1"
    half.mkdir(parents=True)
    torch.save({"iteration": 2500, "iterations": 10000}, half / "checkpoint.pt")
    (tmp_path / "logs").mkdir()
    collect_log = tmp_path / "logs" / "collect__hopper_ddpg05.log"
    data_dir = tmp_path / "data"
    partial = data_dir / ".partial" / "hopper_ddpg05_b1-1234"
    checkpoint = CollectionCheckpoint(partial, every_s=None)
    # what an older version's collection checkpoint at env step 21195 records: no batch size, so no time left
    checkpoint.save({"loop": {"t": 21195}, "buffers": {"kept": 21195, "episode_id": 80}}, {})
    collect_log.write_text("collecting hopper_ddpg05_b1\n")
    collect_log.with_suffix(".pid").write_text(f"{os.getpid()}\n")  # a live process: this one
    collect = jobs["collect/hopper_ddpg05"]
    assert str(run_study.job_status(collect, tmp_path, data_dir)) == "running (21195 steps collected)"
    collect_log.with_suffix(".pid").write_text("999999999\n")  # a pid no process has
    assert str(run_study.job_status(collect, tmp_path, data_dir)) == "left (21195 steps collected)"
    # today's: the batch's size, and 600 s for the first 200000 transitions (earlier processes of the collection):
    # the 800000 left take 40 min at that pace, counted in the work left
    checkpoint.earlier_wall_time_s = 600.0
    checkpoint.save({"loop": {"t": 200000}, "buffers": {"kept": 200000, "steps": 10**6, "episode_id": 900}}, {})
    state = run_study.job_status(collect, tmp_path, data_dir)
    assert state.transitions == (200000, 10**6) and str(state) == "left (200000/1000000 transitions, about 40 min left)"
    assert run_study.work_left([("collect/b", state)], run_study.seconds_left([("collect/b", state)], {})).startswith(
        "left to run: about 0.7 h of one core for 1 of the 1")
    collect_log.with_suffix(".pid").unlink()
    collect_log.write_text("hopper_ddpg05_b1: collected at /d/hopper_ddpg05_b1-1234\n")
    assert str(run_study.job_status(jobs["hopper_ddpg05/bail/seed1"], tmp_path)) == "done"
    assert str(run_study.job_status(jobs["hopper_ddpg05/bail/seed2"], tmp_path)) == "left"
    assert str(run_study.job_status(jobs["hopper_ddpg05/bc/seed1"], tmp_path)) == "left (2500/10000 updates)"
    (tmp_path / "logs" / "hopper_ddpg05__bc__seed1.log").write_text("training\n")  # written just now
    assert str(run_study.job_status(jobs["hopper_ddpg05/bc/seed1"], tmp_path)) == "running (2500/10000 updates)"
    # with the training seconds its checkpoint records: the updates left at the run's pace (7500 x 0.2 s = 25 min)
    torch.save({"iteration": 2500, "iterations": 10000, "wall_time_s": 500.0}, half / "checkpoint.pt")
    assert str(run_study.job_status(jobs["hopper_ddpg05/bc/seed1"], tmp_path)) == (
        "running (2500/10000 updates, about 25 min left)")
    os.utime(half / "checkpoint.pt", (time.time() - 600, time.time() - 600))  # saved 10 min ago, still running
    assert str(run_study.job_status(jobs["hopper_ddpg05/bc/seed1"], tmp_path)) == (
        "running (2500/10000 updates, about 15 min left)")
    # resumed 4 min ago from that checkpoint (its .pid file written as it started): 4 min done since, not 10
    bc_pid = tmp_path / "logs" / "hopper_ddpg05__bc__seed1.pid"
    bc_pid.write_text(f"{os.getpid()}\n")
    os.utime(bc_pid, (time.time() - 240, time.time() - 240))
    assert str(run_study.job_status(jobs["hopper_ddpg05/bc/seed1"], tmp_path)) == (
        "running (2500/10000 updates, about 21 min left)")
    bc_pid.unlink()
    (tmp_path / "logs" / "hopper_ddpg05__bc__seed1.log").write_text("training\n")
    os.utime(tmp_path / "logs" / "hopper_ddpg05__bc__seed1.log", (time.time() - 900, time.time() - 900))
    assert str(run_study.job_status(jobs["hopper_ddpg05/bc/seed1"], tmp_path)) == (
        "left (2500/10000 updates, about 25 min left)")  # nothing runs: the whole remainder
    (tmp_path / "logs" / "hopper_ddpg05__bc__seed1.log").write_text("training\n")
    assert str(run_study.job_status(jobs["collect/hopper_ddpg05"], tmp_path)) == "done"
    results = tmp_path / "results"
    assert run_study.main(["--study", "paper_hopper", "--status", "--workdir", str(tmp_path),
                           "--results", str(results), "--jobs", "3"]) == 0
    out = capsys.readouterr().out
    assert "2 done, 1 running, 120 left of 123 jobs" in out
    assert "with --jobs 3, as the queue dispatches them" in out
    # a run gathered into the results by an earlier call (its workdir gone) is done, and does not run again
    kept = results / "runs" / "hopper_ddpg05_b1" / "bail" / "seed2"
    kept.mkdir(parents=True)
    (kept / "summary.json").write_text("{}")
    assert str(run_study.job_status(jobs["hopper_ddpg05/bail/seed2"], tmp_path, results=results)) == "done"
    assert run_study.landed(jobs["hopper_ddpg05/bail/seed2"], results)
    assert not run_study.landed(jobs["hopper_ddpg05/bail/seed3"], results)
    assert str(run_study.job_status(jobs["hopper_ddpg05/bail/seed3"], tmp_path, results=results)) == "left"


def _kept(results: Path, algo: str, finals: list[float]) -> None:
    for seed, final in enumerate(finals, 1):
        run = results / "runs" / "hopper_ddpg05_b1" / algo / f"seed{seed}"
        run.mkdir(parents=True)
        envelope = {"envelope_best_epoch": 40 + seed, "envelope_fraction_below": 0.0125,
                    "envelope_median_gap": 48.0} if algo == "bail" else {}
        (run / "summary.json").write_text(json.dumps({"final_return": final, "iterations": 50000,
                                                      "wall_time_s": 500.0, **envelope}))
        (run / "config.yaml").write_text("threads: 1\nalgo:\n  envelope:\n    epochs: 50\n")


def test_the_paper_cell_report_gives_a_verdict_per_claim_and_the_cost_of_each_run(run_study, tmp_path):
    results = tmp_path / "results"
    _kept(results, "bail", [2000.0, 2100.0, 1900.0])
    _kept(results, "bc", [300.0, 350.0, 400.0])
    _kept(results, "pbail", [1950.0, 2150.0])  # 2 seeds: no verdict yet

    def row(algo, finals, low, high):
        return {"algo": algo, "overrides": {}, "seeds": len(finals), "final_return_mean": sum(finals) / len(finals),
                "final_return_std": 1.0, "final_return_iqm": sum(finals) / len(finals),
                "final_return_iqm_ci_low": low, "final_return_iqm_ci_high": high, "best_return_mean": 3000.0,
                "run_dirs": [str(results / "runs" / "hopper_ddpg05_b1" / algo / f"seed{s}")
                             for s in range(1, len(finals) + 1)]}
    groups = [row("bail", [2000.0, 2100.0, 1900.0], 1900.0, 2100.0), row("bc", [300.0, 350.0, 400.0], 300.0, 400.0),
              row("pbail", [1950.0, 2150.0], 1950.0, 2150.0)]
    (results / "study.json").write_text(json.dumps({"groups": groups}))
    (results / "timings.json").write_text(json.dumps({
        "hopper_ddpg05/bail/seed1": {"wall_s": 250.0, "threads": 1, "start": {"load": [1.0, 0.9, 0.5]},
                                     "end": {"load": [1.1, 1.0, 0.8]}},
        "hopper_ddpg05/bc/seed1": 1000.0}))  # an older entry: wall seconds alone
    text = run_study.paper_cell_report(results, run_study.paper_hopper_jobs())
    cell = json.loads((results / "cell.json").read_text())
    verdicts = {c["claim"]: c["verdict"] for c in cell["claims"]}
    assert verdicts["BAIL ≫ BC"] == "holds (above: the IQM intervals are disjoint)"
    assert verdicts["Progressive BAIL ≈ BAIL"].startswith("pending (seeds so far: 2 and 3")
    assert verdicts["MARWIL above BC"].startswith("pending (seeds so far: 0 and 3")
    assert "| bail | 3 | 2000.0 / 2100.0 / 1900.0 | 2000.0 ± 1.0 | 2000.0 [1900.0, 2100.0] | 3000.0 | 2054 ± 158 |" \
        in text
    costs = {c["job"]: c for c in cell["costs"]}
    assert costs["hopper_ddpg05/bail/seed1"]["updates_per_s"] == pytest.approx(200.0)  # 50000 updates in 250 s
    assert "| hopper_ddpg05/bail/seed1 | 250 | 1 | 50000 | 200.0 | 1.0 → 1.1 | timings.json |" in text
    assert costs["hopper_ddpg05/bc/seed1"]["wall_s"] == 1000.0 and costs["hopper_ddpg05/bc/seed2"]["wall_s"] == 500.0
    assert costs["hopper_ddpg05/bc/seed2"]["recorded"] == "summary.json" and len(costs) == 8
    assert costs["hopper_ddpg05/bc/seed2"]["threads"] == 1  # read from the run's config where timings has none
    assert [f["best_epoch"] for f in cell["envelope_fits"]] == [41, 42, 43]
    assert "| hopper_ddpg05_b1/bail/seed2 | 42 of 50 | 1.25 % | 48.0 |  |" in text


def test_two_groups_under_one_cell_label_are_refused(run_study, tmp_path):
    """A group at the yaml's value and one without the key both read "marwil": a claim would take either."""
    groups = [{"algo": "marwil", "overrides": {"algo.value_warmup_updates": 0}}, {"algo": "marwil", "overrides": {}}]
    (tmp_path / "study.json").write_text(json.dumps({"groups": groups}))
    with pytest.raises(ValueError, match=r"report groups share a cell label: \['marwil'\]"):
        run_study.paper_cell_report(tmp_path, run_study.paper_hopper_jobs())


def test_a_resumed_job_is_charged_its_whole_training_time_not_its_last_part(run_study, tmp_path):
    """A job killed (a session's end) and finished by a later call: its timings record takes the run's accumulated
    wall_time_s, keeping the last part's seconds and where it resumed; an uninterrupted job keeps its own record."""
    job = next(j for j in run_study.paper_hopper_jobs() if j.name == "hopper_ddpg05/bear/seed1")
    run = tmp_path / "outputs" / "hopper_ddpg05_b1" / "bear" / "seed1,algo.epochs=10,eval.every_epochs=0.5"
    run.mkdir(parents=True)
    assert run_study.run_dir_of(job, tmp_path / "outputs") == run  # the job's own run directory
    record = {"wall_s": 1200.0, "threads": 1, "start": {"load": [1.0, 1.0, 1.0]}}
    (run / "summary.json").write_text(json.dumps({"wall_time_s": 4100.0, "resumed_from_iteration": []}))
    assert run_study.whole_job_record(job, record, tmp_path) == record
    (run / "summary.json").write_text(json.dumps({"wall_time_s": 4100.0, "resumed_from_iteration": [61000]}))
    assert run_study.whole_job_record(job, record, tmp_path) == {
        **record, "wall_s": 4100.0, "last_part_s": 1200.0, "resumed_from_iteration": [61000]}

    # a collection: its batch's metadata (the batch its log names) carries the time of all its parts
    collect = next(j for j in run_study.paper_batches_jobs() if j.module == "torchrl_bail.collect")
    batch = tmp_path / "data" / "hopper_ddpg01_b1-0123abcd"
    batch.mkdir(parents=True)
    (tmp_path / "logs").mkdir()
    (tmp_path / "logs" / (collect.name.replace("/", "__") + ".log")).write_text(
        f"collecting...\nhopper_ddpg01_b1: collected at {batch}\n")
    meta = {"collection_wall_time_s": 7900.0, "resumed_from_step": None, "collection_timed_from_step": 0}
    (batch / "metadata.json").write_text(json.dumps(meta))
    assert run_study.whole_job_record(collect, record, tmp_path) == record
    (batch / "metadata.json").write_text(json.dumps({**meta, "resumed_from_step": 412000,
                                                     "collection_timed_from_step": 10837}))
    assert run_study.whole_job_record(collect, record, tmp_path) == {
        **record, "wall_s": 7900.0, "last_part_s": 1200.0, "resumed_from_step": 412000, "timed_from_step": 10837}


def test_each_marwil_claim_reads_its_own_group_when_both_variants_ran(run_study):
    """The report names ``value_warmup_updates`` on both MARWIL groups once one overrides it; the faithful one (the
    yaml's 0) must still be the group of "MARWIL above BC"."""
    faithful = {"algo": "marwil", "overrides": {"algo.value_warmup_updates": 0}}
    warmed = {"algo": "marwil", "overrides": {"algo.value_warmup_updates": 1000}}
    labels = {run_study.cell_label(faithful), run_study.cell_label(warmed)}
    claims = {claim: a for claim, a, _b, _kind in run_study.PAPER_CLAIMS}
    assert labels == {claims["MARWIL above BC"], claims["MARWIL with V fitted first above BC"]}
    assert run_study.cell_label({"algo": "bail", "overrides": {}}) == claims["BAIL ≫ BC"]


def test_claim_verdicts_read_the_iqm_intervals(run_study):
    def row(seeds, low, high):
        return {"seeds": seeds, "final_return_iqm_ci_low": low, "final_return_iqm_ci_high": high}
    assert run_study.claim_verdict(row(5, 10, 20), row(5, 0, 9), "above").startswith("holds (above")
    assert run_study.claim_verdict(row(5, 0, 9), row(5, 10, 20), "above").startswith("does not hold (below")
    # a's interval starts above b's start but they overlap: no difference shown
    assert run_study.claim_verdict(row(5, 12, 30), row(5, 10, 20), "above").startswith(
        "does not hold (no difference")
    assert run_study.claim_verdict(row(5, 0, 15), row(5, 10, 20), "above").startswith("does not hold (no difference")
    assert run_study.claim_verdict(row(3, 0, 15), row(3, 10, 20), "similar").startswith("holds (no difference")
    assert run_study.claim_verdict(row(3, 0, 9), row(3, 10, 20), "similar").startswith("does not hold (below")
    assert run_study.claim_verdict(None, row(3, 10, 20), "above").startswith("pending (seeds so far: 0 and 3")


# ---------------------------------------------------------------------------------------------------------------
# the cross-batch report (--study paper_batches): a fake results tree of kept runs and kept batch metadata
# ---------------------------------------------------------------------------------------------------------------

HEADLINE_META = {"episode_return_mean": 500.0, "episode_return_min": 100.0, "episode_return_max": 3100.0,
                 "behaviour_final_return_mean10": 1234.5, "collection_wall_time_s": 9000.0,
                 "num_transitions": 10**6, "recipe_hash": "abcd1234"}
WALKER_META = {"episode_return_mean": 400.0, "episode_return_min": 50.0, "episode_return_max": 2050.0,
               "behaviour_final_return_mean10": 1500.0, "collection_wall_time_s": 3600.0,
               "num_transitions": 10**6, "recipe_hash": "1234abcd"}
HEADLINE_RUNS = {"bail": [2200.0, 2300.0, 2100.0, 2250.0, 2150.0], "bc": [400.0, 450.0, 500.0, 420.0, 480.0],
                 "bcq": [2600.0, 2700.0, 2650.0], "pbail": [2150.0, 2250.0, 2200.0]}
WALKER_RUNS = {"bail": [1100.0, 1200.0, 1000.0, 1150.0, 1050.0], "bc": [300.0, 350.0]}  # BC: 2 of 5 seeds so far


def _fake_batch(run_study, root: Path, label: str, recipe: str, runs: dict[str, list[float]],
                metadata: dict | None) -> None:
    """Kept runs of one batch in the layout the runner gathers (``runs/<batch>/<algo>/seed<s>[,<schedule>]`` with
    summary.json, config.yaml and CSV evaluation logs), and its kept ``batches/<batch>-<hash>.metadata.json``."""
    for algo, finals in runs.items():
        suffix = "".join("," + o for o in sorted(run_study.paper_schedule(algo)))
        for seed, final in enumerate(finals, 1):
            run = root / "runs" / label / algo / f"seed{seed}{suffix}"
            scalars = run / "logs" / "scalars" / "eval"
            scalars.mkdir(parents=True)
            (run / "summary.json").write_text(json.dumps({
                "algo": algo, "seed": seed, "final_return": final, "best_return": final + 100.0, "iterations": 10000,
                "wall_time_s": 60.0, "batch": label, "batch_path": f"/data/{label}-{recipe}"}))
            (run / "config.yaml").write_text(f"threads: 1\nseed: {seed}\n")
            (scalars / "return.csv").write_text(f"5000,{final - 200.0}\n10000,{final}\n")
            (scalars / "epoch.csv").write_text("5000,0.5\n10000,1.0\n")
    if metadata is not None:
        (root / "batches").mkdir(parents=True, exist_ok=True)
        (root / "batches" / f"{label}-{recipe}.metadata.json").write_text(json.dumps(metadata))


@pytest.fixture(scope="module")
def cross_batch(run_study, tmp_path_factory):
    """The report over the headline batch (every central cell complete) and walker_ddpg05_b1 (BAIL's 5 seeds, BC's
    first 2), the two other batches not begun."""
    root = tmp_path_factory.mktemp("cross_batch")
    headline, results = root / "paper_hopper", root / "paper_batches"
    _fake_batch(run_study, headline, "hopper_ddpg05_b1", "abcd1234", HEADLINE_RUNS, HEADLINE_META)
    _fake_batch(run_study, results, "walker_ddpg05_b1", "1234abcd", WALKER_RUNS, WALKER_META)
    # the headline batch made twice again with the same data: once from scratch, once resumed from an older
    # version's checkpoint (its first steps untimed: not a collection time)
    (headline / "batches" / "hopper_ddpg05_b1-abcd1234.remakes.json").write_text(json.dumps({"same": [], "remakes": [
        {"created_at": "later", "collection_wall_time_s": 5400.0, "collection_timed_from_step": 0},
        {"created_at": "later still", "collection_wall_time_s": 60.0, "collection_timed_from_step": 990000}]}))
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(run_study, "CROSS_BATCH_REPS", 300)
        out = run_study.cross_batch_report(results, headline)
    return out, results


def test_the_cross_batch_table_has_a_row_per_batch_with_its_metadata_and_pending_cells(run_study, cross_batch):
    out, results = cross_batch
    text = (results / "cross_batch.md").read_text()
    assert [b["batch"] for b in out["batches"]] == ["hopper_ddpg05_b1", "walker_ddpg05_b1", "hopper_ddpg01_b1",
                                                     "hopper_ddpg05_b2"]
    assert "| batch | data: mean episode return | behaviour agent's final return | collection time | bail | pbail | " \
           "bc | bcq | published BAIL (gym -v2) |" in text  # no run of BEAR, TD3+BC or IQL: no column
    assert ("| hopper_ddpg05_b1 | 500.0 | 1234.5 | 2.5 h; made again: 1.5 h | 2200.0 ± 79.1 | 2200.0 ± 50.0 | "
            "450.0 ± 41.2 | 2650.0 ± 50.0 | 2054 ± 158 |") in text
    assert ("| walker_ddpg05_b1 | 400.0 | 1500.0 | 1.0 h | 1100.0 ± 79.1 | pending (0 of 3 seeds) | "
            "325.0 ± 35.4 (2 of 5 seeds) | pending (0 of 3 seeds) | 2522 ± 51 |") in text
    assert ("| hopper_ddpg01_b1 | pending | pending | pending | pending (0 of 5 seeds) | pending (0 of 3 seeds) | "
            "pending (0 of 5 seeds) | pending (0 of 3 seeds) | 2173 ± 291 |") in text
    assert "| walker_ddpg05_b1 | " in text.split("Interquartile mean")[0].split("| batch | bail |")[1]
    assert "pending (2 of 5 seeds)" in text  # BC's IQM on walker: below 3 seeds
    assert "gym's -v2" in text and "Gymnasium's -v5" in text and "README table" in text
    assert [r["created_at"] for r in out["batches"][0]["remakes"]] == ["later", "later still"]
    assert out["batches"][1]["remakes"] == []
    assert out["complete_batches"] == ["hopper_ddpg05_b1"] and "1 of 4 (hopper_ddpg05_b1)" in out["status"]
    assert sorted(p.name for p in results.glob("curves_*.png")) == ["curves_hopper_ddpg05_b1.png",
                                                                     "curves_walker_ddpg05_b1.png"]
    assert json.loads((results / "cross_batch.json").read_text()) == json.loads(json.dumps(out))


def test_each_batchs_verdicts_follow_the_paper_cells_rule(run_study, cross_batch):
    out, _ = cross_batch
    headline, walker = out["batches"][:2]
    verdicts = {c["claim"]: c["verdict"] for c in headline["claims"]}
    cells = headline["cells"]
    assert verdicts["BAIL ≫ BC"] == run_study.claim_verdict(cells["bail"], cells["bc"], "above")
    assert verdicts["BAIL ≫ BC"] == "holds (above: the IQM intervals are disjoint)"
    assert cells["bail"]["final_return_iqm_ci_low"] > cells["bc"]["final_return_iqm_ci_high"]
    assert verdicts["BAIL above BCQ (BCQ at 10^5 of the paper's 10^6 updates)"].startswith("does not hold (below")
    assert verdicts["Progressive BAIL ≈ BAIL"].startswith("holds (no difference shown")
    walker_verdicts = {c["claim"]: c["verdict"] for c in walker["claims"]}
    assert walker_verdicts["BAIL ≫ BC"].startswith("pending (seeds so far: 5 and 2")
    across = {c["claim"]: c for c in out["claims_across_batches"]}
    assert across["BAIL ≫ BC"] == {"claim": "BAIL ≫ BC", "holds": 1, "does not hold": 0, "pending": 3}


def test_the_aggregate_normalises_by_each_batchs_own_episodes(run_study, cross_batch):
    """Min-max by the batch's worst and best episode (its metadata): BAIL's IQM over both batches with 5 seeds is
    the trimmed mean of the hand-normalised returns; P(BAIL > BC) > 0.5 with its interval, on the one batch where
    both have 3 seeds; P(BAIL > BCQ) < 0.5 there."""
    from scipy.stats import trim_mean

    out, results = cross_batch
    norm = [(x - 100.0) / 3000.0 for x in HEADLINE_RUNS["bail"]] + [(x - 50.0) / 2000.0 for x in WALKER_RUNS["bail"]]
    assert out["batches"][0]["cells"]["bail"]["per_seed_normalised"] == pytest.approx(norm[:5])
    bail = out["aggregate"]["iqm"]["bail"]
    assert bail["batches"] == ["hopper_ddpg05_b1", "walker_ddpg05_b1"] and bail["seeds_per_batch"] == 5
    assert bail["iqm"] == pytest.approx(trim_mean(norm, 0.25))
    assert bail["ci_low"] <= bail["iqm"] <= bail["ci_high"]
    assert out["aggregate"]["iqm"]["bc"]["batches"] == ["hopper_ddpg05_b1"]  # walker's BC has 2 seeds
    poi = {(p["a"], p["b"]): p for p in out["aggregate"]["probability_of_improvement"]}
    over_bc, over_bcq = poi[("bail", "bc")], poi[("bail", "bcq")]
    assert over_bc["batches"] == ["hopper_ddpg05_b1"] and over_bc["seeds"] == [5, 5]
    assert over_bc["p"] > 0.5 and 0.5 < over_bc["ci_low"] <= over_bc["p"] <= over_bc["ci_high"]
    assert over_bcq["p"] < 0.5 and over_bcq["ci_high"] < 0.5 and over_bcq["seeds"] == [5, 3]
    assert over_bc["reading"].startswith("pending (1 of 4 batches entered")
    assert over_bc["per_batch"] == {"hopper_ddpg05_b1": pytest.approx(over_bc["p"])}  # one batch: its own value
    text = (results / "cross_batch.md").read_text()
    assert f"| hopper_ddpg05_b1 {over_bcq['p']:.2f} | pending (1 of 4" in text


def test_a_batch_made_by_the_same_recipe_is_set_beside_the_first(run_study, tmp_path, monkeypatch):
    """hopper_ddpg05_b2 (the headline recipe with another behaviour seed) beside hopper_ddpg05_b1: per algorithm,
    where its IQM interval lies against B1's; per claim, whether the two batches' verdicts agree. Here BCQ's place
    against BAIL turns over with the batch drawn while BAIL ≫ BC holds on both."""
    monkeypatch.setattr(run_study, "CROSS_BATCH_REPS", 300)
    headline, results = tmp_path / "paper_hopper", tmp_path / "paper_batches"
    _fake_batch(run_study, headline, "hopper_ddpg05_b1", "abcd1234", HEADLINE_RUNS, HEADLINE_META)
    b2 = {"bail": [1300.0, 1350.0, 1250.0, 1320.0, 1280.0], "bc": [420.0, 470.0, 440.0, 460.0, 430.0],
          "bcq": [900.0, 950.0, 1000.0], "pbail": [1290.0, 1310.0, 1330.0]}
    _fake_batch(run_study, results, "hopper_ddpg05_b2", "ef567890", b2,
                {**HEADLINE_META, "episode_return_mean": 700.0, "behaviour_final_return_mean10": 900.0})
    out = run_study.cross_batch_report(results, headline)
    [same] = out["same_recipe"]  # walker and hopper_ddpg01 have one batch of their recipe each: nothing beside
    assert same["recipe"] == "hopper_ddpg05" and same["batches"] == ["hopper_ddpg05_b1", "hopper_ddpg05_b2"]
    assert list(same["algorithms"]) == ["bail", "pbail", "bc", "bcq"]
    assert same["algorithms"]["bail"] == "below: the IQM intervals are disjoint"  # 1250-1350 against 2100-2300
    assert same["algorithms"]["bc"] == "no difference shown: the IQM intervals overlap"  # 420-470 against 400-500
    readings = {c["claim"]: c for c in same["claims"]}
    assert readings["BAIL ≫ BC"]["reading"] == "the same verdict"
    bcq = readings["BAIL above BCQ (BCQ at 10^5 of the paper's 10^6 updates)"]
    assert bcq["verdicts"][0].startswith("does not hold (below") and bcq["verdicts"][1].startswith("holds (above")
    assert bcq["reading"] == "the verdicts differ"
    text = (results / "cross_batch.md").read_text()
    assert "**Same recipe, another behaviour seed: hopper_ddpg05_b1 and hopper_ddpg05_b2.**" in text
    assert "(hopper_ddpg05_b1: data 500.0, behaviour agent 1234.5; hopper_ddpg05_b2: data 700.0, behaviour agent " \
           "900.0)" in text
    assert "| bc | 450.0 [" in text and "| no difference shown: the IQM intervals overlap |" in text
    assert ("| BAIL above BCQ (BCQ at 10^5 of the paper's 10^6 updates) | does not hold (below: the IQM intervals "
            "are disjoint) | holds (above: the IQM intervals are disjoint) | the verdicts differ |") in text
    assert text.index("**Same recipe") < text.index("**Over all batches.**")


def test_a_same_recipe_batch_without_its_seeds_reads_pending(cross_batch):
    out, results = cross_batch  # hopper_ddpg05_b2 not begun
    [same] = out["same_recipe"]
    assert all(c["reading"] == "pending" for c in same["claims"])
    assert all(order.startswith("pending (seeds so far: 0 and") for order in same["algorithms"].values())
    assert "| bail | 2200.0 [" in (results / "cross_batch.md").read_text().split("**Same recipe")[1]
    assert "| pending (0 of 5 seeds) | pending |" in (results / "cross_batch.md").read_text()


def test_the_cross_batch_report_with_no_runs_is_all_pending(run_study, tmp_path):
    out = run_study.cross_batch_report(tmp_path / "paper_batches", tmp_path / "paper_hopper")
    assert out["complete_batches"] == [] and "0 of 4" in out["status"]
    assert out["aggregate"]["iqm"] == {} and all(p["p"] is None for p in out["aggregate"]["probability_of_improvement"])
    assert all(c["verdict"].startswith("pending (seeds so far: 0 and 0") for b in out["batches"] for c in b["claims"])
    text = (tmp_path / "paper_batches" / "cross_batch.md").read_text()
    assert "| bail | pending (no batch with 3 seeds) |" in text and "none yet" in text
    assert not list((tmp_path / "paper_batches").glob("*.png"))


def test_report_only_keeps_the_collected_batchs_metadata_and_rebuilds_from_kept_files_alone(run_study, tmp_path,
                                                                                             monkeypatch):
    """``--report-only`` copies a collect job's batch metadata from the cache entry its log names (the data dir)
    into ``results/batches``; with the workdir and the data dir gone, it rebuilds the same report."""
    import shutil

    monkeypatch.setattr(run_study, "CROSS_BATCH_REPS", 300)
    monkeypatch.setattr(run_study, "report", lambda *a, **k: None)  # torchrl_bail.report's own tables: not here
    headline, results, work, data = (tmp_path / d for d in ("paper_hopper", "paper_batches", "work", "data"))
    _fake_batch(run_study, headline, "hopper_ddpg05_b1", "abcd1234", HEADLINE_RUNS, HEADLINE_META)
    _fake_batch(run_study, results, "walker_ddpg05_b1", "1234abcd", WALKER_RUNS, None)
    entry = data / "walker_ddpg05_b1-1234abcd"
    entry.mkdir(parents=True)
    (entry / "metadata.json").write_text(json.dumps(WALKER_META))
    (work / "logs").mkdir(parents=True)
    (work / "logs" / "collect__walker_ddpg05_b1.log").write_text(
        f"walker_ddpg05_b1: collected at {entry}\n  env Walker2d-v5: 1000000 transitions\n")
    args = ["--study", "paper_batches", "--report-only", "--results", str(results), "--headline", str(headline)]
    assert run_study.main([*args, "--workdir", str(work)]) == 0
    kept = results / "batches" / "walker_ddpg05_b1-1234abcd.metadata.json"
    assert json.loads(kept.read_text()) == WALKER_META
    first = (results / "cross_batch.md").read_text()
    assert "| walker_ddpg05_b1 | 400.0 | 1500.0 | 1.0 h | 1100.0 ± 79.1 |" in first
    shutil.rmtree(work)
    shutil.rmtree(data)
    for made in [*results.glob("cross_batch.*"), *results.glob("curves_*.png")]:
        made.unlink()
    assert run_study.main([*args, "--workdir", str(tmp_path / "another")]) == 0
    assert (results / "cross_batch.md").read_text() == first
    assert (results / "curves_walker_ddpg05_b1.png").is_file() and not (tmp_path / "another" / "outputs").exists()


def _made_again(work: Path, data: Path, meta: dict) -> Path:
    """The data dir entry of walker_ddpg05_b1 made again with ``meta``, and its collect job's log naming it."""
    entry = data / "walker_ddpg05_b1-1234abcd"
    entry.mkdir(parents=True)
    (entry / "metadata.json").write_text(json.dumps(meta))
    (work / "logs").mkdir(parents=True, exist_ok=True)
    (work / "logs" / "collect__walker_ddpg05_b1.log").write_text(f"walker_ddpg05_b1: collected at {entry}\n")
    return entry


def test_a_batch_made_again_keeps_the_first_record_when_its_data_match_and_is_refused_when_not(run_study,
                                                                                               tmp_path):
    """Made again with the same statistics (another collection time, another date), the kept metadata stays, the
    record of the batch the kept runs trained on, and the remaking's own fields are listed beside it (once, however
    often it is gathered); with another mean return, :class:`BatchMismatch` names it."""
    results, work, data = (tmp_path / d for d in ("results", "work", "data"))
    kept = results / "batches" / "walker_ddpg05_b1-1234abcd.metadata.json"
    kept.parent.mkdir(parents=True)
    kept.write_text(json.dumps(WALKER_META))
    entry = _made_again(work, data, {**WALKER_META, "collection_wall_time_s": 4000.0, "created_at": "today"})
    collect = run_study.Job("collect/walker_ddpg05_b1", [], "torchrl_bail.collect")
    remakes = results / "batches" / "walker_ddpg05_b1-1234abcd.remakes.json"
    assert run_study.keep_batch_metadata(work, results, [collect]) == [remakes]
    assert run_study.keep_batch_metadata(work, results, [collect]) == []
    assert json.loads(kept.read_text()) == WALKER_META
    record = json.loads(remakes.read_text())
    assert record["remakes"] == [{"collection_wall_time_s": 4000.0, "created_at": "today"}]
    assert "episode_return_mean" in record["same"] and "num_transitions" in record["same"]
    (entry / "metadata.json").write_text(json.dumps({**WALKER_META, "episode_return_mean": 412.5}))
    with pytest.raises(run_study.BatchMismatch, match=r"episode_return_mean 412\.5 here, 400\.0 kept"):
        run_study.keep_batch_metadata(work, results, [collect])
    assert json.loads(kept.read_text()) == WALKER_META


def test_a_batch_made_again_with_other_data_stops_the_queue_and_the_report(run_study, tmp_path, monkeypatch, capsys):
    """The queue's collect job makes walker_ddpg05_b1 again (its data dir lost) and it comes out other than the kept
    one: the job fails, naming the difference, no training job starts on it, and no report is rebuilt."""
    headline, results, work, data = (tmp_path / d for d in ("paper_hopper", "paper_batches", "work", "data"))
    _fake_batch(run_study, headline, "hopper_ddpg05_b1", "abcd1234", HEADLINE_RUNS, HEADLINE_META)
    _fake_batch(run_study, results, "walker_ddpg05_b1", "1234abcd", {}, WALKER_META)
    entry = _made_again(work, data, {**WALKER_META, "episode_return_mean": 412.5})
    started = []

    class Process:  # what run_job starts: the collect job only logs the entry it made, as collect does
        pid = 1

        def __init__(self, argv, stdout, **kwargs):
            started.append(argv[2])
            stdout.write(f"walker_ddpg05_b1: collected at {entry}\n")
            stdout.flush()

        def wait(self):
            return 0

    monkeypatch.setattr(run_study.subprocess, "Popen", Process)
    assert run_study.main(["--study", "paper_batches", "--only", "walker_ddpg05_b1", "--jobs", "1",
                           "--workdir", str(work), "--results", str(results), "--headline", str(headline)]) == 1
    assert started == ["torchrl_bail.collect"]
    out, err = capsys.readouterr()
    assert "collect/walker_ddpg05_b1: FAILED (" in out and "no other job starts" in out
    assert "episode_return_mean 412.5 here, 400.0 kept" in out and "nothing gathered, no report written" in err
    assert not (results / "cross_batch.md").exists()
    assert json.loads((results / "batches" / "walker_ddpg05_b1-1234abcd.metadata.json").read_text()) == WALKER_META


def test_gather_keeps_the_paper_scale_policies_and_never_a_checkpoint(run_study, tmp_path):
    """A paper-scale study keeps each finished run's ``policy.pt`` beside its summary (what ``torchrl_bail.ope``
    scores later); the 50k study keeps none; neither keeps a checkpoint."""
    run = tmp_path / "work" / "outputs" / "walker_ddpg05_b1" / "bail" / "seed1"
    (run / "logs").mkdir(parents=True)
    for name, text in (("summary.json", "{}"), ("config.yaml", "seed: 1\n"), ("policy.pt", "weights"),
                       ("checkpoint.pt", "state")):
        (run / name).write_text(text)
    for policies, results in ((True, tmp_path / "paper"), (False, tmp_path / "study")):
        (kept,) = run_study.gather(tmp_path / "work", results, policies=policies)
        assert sorted(p.name for p in kept.iterdir()) == sorted(
            ["summary.json", "config.yaml", "logs", *(["policy.pt"] if policies else [])])


# ---------------------------------------------------------------------------------------------------------------
# the execution-batch report (--study paper_exec): supp. Table 2's rows from a fake results tree
# ---------------------------------------------------------------------------------------------------------------

def _exec_meta(mean: float, behaviour: float, which: str, **policy) -> dict:
    return {"episode_return_mean": mean, "episode_return_min": mean - 500.0, "episode_return_max": mean + 100.0,
            "num_transitions": 10**6, "behaviour_return": behaviour, "recipe_hash": "feed0001",
            "behaviour_policy": {"which": which, "stochastic": False, "eval_step": 600000, "run": "/machine/sac_run",
                                 "file": "/machine/sac_run/evals/step_600000.pt", "threshold_reached": True,
                                 **policy}}


#: Hopper O σ = 0: BAIL and MARWIL on the behaviour policy's 3000, BC ~3 % below it (its interval apart), BCQ far
#: below; Hopper M σ = σ(s): BAIL far below BC, MARWIL level with BC; Hopper M σ = 0: BC at 2 of 3 seeds; Walker's
#: SAC batch: BAIL ≫ BC. The other batches not begun.
EXEC_RUNS = {
    "hopper_opt_det_b1": ({"bail": [2990.0, 3000.0, 3010.0], "bcq": [2000.0, 2100.0, 2200.0],
                           "bc": [2900.0, 2905.0, 2910.0], "marwil": [2996.0, 3006.0, 3001.0], "bear": [1500.0]},
                          _exec_meta(2990.0, 3000.0, "optimal")),
    "hopper_med_stoch_b1": ({"bail": [400.0, 420.0, 440.0], "bcq": [900.0, 925.0, 950.0],
                             "bc": [1000.0, 1010.0, 1020.0], "marwil": [1004.0, 1014.0, 1009.0]},
                            _exec_meta(900.0, 1010.0, "mediocre", mediocre_threshold=1000.0,
                                       threshold_reached=False)),
    "hopper_med_det_b1": ({"bail": [1000.0, 1001.0, 1002.0], "bc": [990.0, 1010.0]}, None),
    "walker_sac_b1": ({"bail": [2000.0, 2100.0, 2200.0], "bc": [500.0, 600.0, 700.0]},
                      {"episode_return_mean": 1500.0, "episode_return_min": -5.0, "episode_return_max": 4000.0,
                       "behaviour_final_eval_return": 3500.0, "recipe_hash": "feed0002",
                       # the SAC run's record (Walker2d's mediocre threshold: 500): crossed at its third evaluation
                       "evaluations": [{"step": 5000, "return_mean": 120.0}, {"step": 10000, "return_mean": 499.9},
                                       {"step": 15000, "return_mean": 510.5}, {"step": 20000, "return_mean": 3700.0},
                                       {"step": 25000, "return_mean": 3500.0}],
                       "sac_run_train_steps": 25000, "gradient_steps": 15000, "env_steps_per_s": 104.2,
                       "updates_per_s": 120.5, "resumed_from_step": None}),
}


def _exec_tree(run_study, root: Path) -> Path:
    results = root / "paper_exec"
    for label, (runs, meta) in EXEC_RUNS.items():
        _fake_batch(run_study, results, label, (meta or {}).get("recipe_hash", "feed0003"), runs, meta)
    return results


@pytest.fixture(scope="module")
def exec_table(run_study, tmp_path_factory):
    results = _exec_tree(run_study, tmp_path_factory.mktemp("exec"))
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(run_study, "CROSS_BATCH_REPS", 300)
        out = run_study.exec_table_report(results)
    return out, results


def test_the_table2_report_has_a_row_per_batch_with_the_papers_figure_beside_each_cell(exec_table):
    out, results = exec_table
    text = (results / "table2.md").read_text()
    assert [b["batch"] for b in out["batches"]] == [f"{env}_{kind}_b1" for env in ("hopper", "walker") for kind in
                                                     ("sac", "med_det", "med_stoch", "opt_det", "opt_stoch")]
    assert ("| batch | paper's row | data: mean episode return | behaviour policy's return | BAIL | BCQ | BC | MARWIL "
            "| BEAR |") in text  # BEAR: a run of it is kept
    # supp. Table 2's Hopper O σ = 0 B1 row beside ours; BEAR at 1 of 3 seeds
    assert ("| hopper_opt_det_b1 | O σ = 0 | 2990.0 | 3000.0 (optimal policy at step 600,000) | 3000.0 ± 10.0; paper "
            "2602 ± 5 | 2100.0 ± 100.0; paper 1976 ± 383 | 2905.0 ± 5.0; paper 2594 ± 8 | 3001.0 ± 5.0; paper "
            "2603 ± 4 | 1500.0 (1 of 3 seeds); paper 1904 ± 321 |") in text
    assert ("| hopper_med_stoch_b1 | M σ = σ(s) | 900.0 | 1010.0 (mediocre policy at step 600,000; threshold 1000 "
            "not reached: the best evaluation) |") in text
    # no metadata, cells without runs: pending, with the paper's figure (a published number, named as such)
    assert ("| hopper_med_det_b1 | M σ = 0 | pending | pending | 1001.0 ± 1.0; paper 1026 ± 0 | pending (0 of 3 "
            "seeds); paper 901 ± 132 | 1000.0 ± 14.1 (2 of 3 seeds); paper 1026 ± 0 | pending (0 of 3 seeds); paper "
            "1026 ± 0 | pending (0 of 3 seeds); paper 4 ± 1 |") in text
    assert ("| walker_opt_stoch_b1 | O σ = σ(s) | pending | pending | pending (0 of 3 seeds); paper 2834 ± 120 | "
            "pending (0 of 3 seeds); paper 3386 ± 196 | pending (0 of 3 seeds); paper 2024 ± 131 | pending (0 of 3 "
            "seeds); paper 1987 ± 114 | not run; paper 3278 ± 128 |") in text  # BEAR runs on Hopper's alone
    # the SAC training batches: Table 1 rows, the authors' BAIL alone published
    assert ("| walker_sac_b1 | SAC training batch (Table 1) | 1500.0 | 3500.0 (SAC run's final evaluation) | "
            "2100.0 ± 100.0; paper 2455 ± 211 | pending (0 of 3 seeds) | 600.0 ± 100.0 | pending (0 of 3 seeds) | "
            "not run |") in text
    assert ("| hopper_sac_b1 | SAC training batch (Table 1) | pending | pending | pending (0 of 3 seeds); paper "
            "3296 ± 105 |") in text
    iqm = text.split("Interquartile mean")[0].split("| batch | BAIL | BCQ | BC | MARWIL | BEAR |")[1]
    assert "| hopper_med_det_b1 | 1001.0 [" in iqm and "pending (2 of 3 seeds)" in iqm  # no IQM below 3 seeds
    assert "supp. Table 2 (arXiv:1910.12179)" in text and "gym's -v2" in text and "Gymnasium's -v5" in text
    assert "/machine" not in (results / "table2.json").read_text()  # the policy's paths stay out
    assert out["batches"][3]["metadata"]["behaviour_policy"]["which"] == "optimal"
    assert sorted(p.name for p in results.glob("curves_*.png")) == [
        f"curves_{label}.png" for label in sorted(EXEC_RUNS)]
    assert json.loads((results / "table2.json").read_text()) == json.loads(json.dumps(out))


def test_the_table2_report_records_each_sac_run_its_pace_crossing_and_final_evaluation(exec_table):
    """Issue 51's record of a SAC behaviour run, from its SAC batch's kept metadata: pace, the first evaluation at or
    above the env's mediocre threshold (conf/env: Walker2d 500; 499.9 is below it), the final and best evaluations,
    and one figure; a run whose metadata is not kept (Hopper's here) is absent, not made up."""
    out, results = exec_table
    (run,) = out["sac_runs"]
    assert (run["env"], run["mediocre_threshold"], run["crossed_at_step"], run["crossed_with_return"]) == (
        "walker", 500.0, 15000, 510.5)
    assert (run["final_eval_return"], run["best_eval_return"], run["env_steps_per_s"]) == (3500.0, 3700.0, 104.2)
    text = (results / "table2.md").read_text()
    assert "| walker | 25,000 | 104.2 | 120.5 | 500 | 15,000: 510.5 | 3500.0 | 3700.0 |" in text
    assert "Figure: `sac_runs.png`." in text and (results / "sac_runs.png").is_file()


def test_the_table2_claims_follow_the_paper_cells_rule(run_study, exec_table):
    out, _ = exec_table
    verdicts = {(c["batch"], c["claim"]): c for c in out["claims"]}
    opt = "hopper_opt_det_b1"
    assert verdicts[(opt, "BAIL ≈ the behaviour policy")]["verdict"] == (
        "holds (no difference shown: the IQM intervals overlap)")  # 3000 inside BAIL's interval
    bc = verdicts[(opt, "BC ≈ the behaviour policy")]
    assert bc["verdict"] == "does not hold (below: the IQM intervals are disjoint)"
    assert bc["gap"] == pytest.approx(100 * (2905 - 3000) / 3000)
    assert verdicts[(opt, "MARWIL ≈ the behaviour policy")]["verdict"].startswith("holds")
    assert verdicts[("hopper_med_stoch_b1", "BAIL below BC")]["verdict"] == (
        "holds (below: the IQM intervals are disjoint)")
    assert verdicts[("hopper_med_stoch_b1", "MARWIL ≈ BC")]["verdict"].startswith("holds (no difference")
    assert verdicts[("hopper_med_det_b1", "MARWIL ≈ BC")]["verdict"] == (
        "pending (seeds so far: 0 and 2; 3 each needed)")
    assert verdicts[("walker_sac_b1", "BAIL ≫ BC (Table 1)")]["verdict"].startswith("holds (above")
    assert verdicts[("walker_opt_det_b1", "BAIL ≈ the behaviour policy")]["verdict"].startswith(
        "pending (the batch's metadata")
    assert ("walker_med_stoch_b1", "BAIL below BC") not in verdicts  # the paper's claim is Hopper's
    # each verdict is the training-batch cells' rule on the same rows
    cells = out["batches"][3]["cells"]
    assert bc["verdict"] == run_study.claim_verdict(cells["bc"], run_study.reference_row(3000.0), "similar")


def test_the_table2_rankings_read_wins_and_orderings_against_the_papers(run_study, exec_table):
    """The two ranked rows: on Hopper O σ = 0 MARWIL has the best IQM and BAIL's interval overlaps it (a tie), the
    paper's best mean is MARWIL's, and the two orders agree (tau 1); on Hopper M σ = σ(s) BC and MARWIL tie, as in the
    paper, whose equal means tie the pair (tau-b below 1, one tied pair). Six rows unranked: the most-wins verdict and
    the average are pending."""
    out, results = exec_table
    rankings = out["rankings"]
    rows = {r["batch"]: r for r in rankings["rows"]}
    opt, stoch = rows["hopper_opt_det_b1"], rows["hopper_med_stoch_b1"]
    assert opt["winners"] == ["bail", "marwil"] and opt["paper_winners"] == ["marwil"]
    assert opt["ordering"]["ours"] == opt["ordering"]["paper"] == ["marwil", "bail", "bc", "bcq"]
    assert opt["ordering"]["tau"] == pytest.approx(1.0) and opt["ordering"]["reading"] == "the same order"
    assert stoch["winners"] == ["bc", "marwil"] and stoch["paper_winners"] == ["bc", "marwil"]
    assert stoch["ordering"]["pairs"] == {"concordant": 5, "discordant": 0, "tied": 1}
    assert stoch["ordering"]["tau"] == pytest.approx(5 / 30 ** 0.5)  # tau-b with the paper's tie
    assert rows["hopper_med_det_b1"]["winners"] is None and rows["hopper_med_det_b1"]["ordering"]["tau"] is None
    assert rankings["ordering"]["tau_pooled"] == pytest.approx(11 / 12) and rankings["ordering"]["same_order"] == 1
    assert {a: w["ours"] for a, w in rankings["wins"].items()} == {"bail": 1, "bcq": 0, "bc": 1, "marwil": 2,
                                                                    "bear": 0}
    assert rankings["wins"]["bc"]["paper_all_rows"] == 14 and rankings["wins"]["marwil"]["paper_all_rows"] == 14
    assert rankings["most_wins_verdict"] == "pending (2 of 8 execution batches ranked)"
    assert rankings["average_verdict"].startswith("pending (2 of 8 batches entered")
    text = (results / "table2.md").read_text()
    assert ("| hopper_opt_det_b1 | BAIL, MARWIL | MARWIL | MARWIL > BAIL > BC > BCQ | MARWIL > BAIL > BC > BCQ | "
            "1.00 | the same order |") in text
    assert "| walker_opt_stoch_b1 | pending | pending |" in text
    assert "| BC and MARWIL win the most rows | pending (2 of 8 execution batches ranked) |" in text


def _ranked_cell(values: list[float]) -> dict:
    """A report cell of three or more seeds as the rankings read it: IQM (here the mean) with the seeds' range as its
    interval."""
    return {"seeds": len(values), "per_seed": values, "final_return_iqm": sum(values) / len(values),
            "final_return_iqm_ci_low": min(values), "final_return_iqm_ci_high": max(values)}


@pytest.mark.parametrize("winner, verdict", [("bc", "holds (the most wins, 8 of 8: BC)"),
                                             ("bail", "does not hold (the most wins, 8 of 8: BAIL)")])
def test_the_most_wins_verdict_names_who_wins_the_most_rows(run_study, monkeypatch, winner, verdict):
    monkeypatch.setattr(run_study, "CROSS_BATCH_REPS", 200)
    batches = []
    for env, kind in run_study.exec_batches():
        if kind == "sac":
            continue
        levels = {"bail": 100.0, "bcq": 100.0, "bc": 100.0, "marwil": 100.0, winner: 500.0}
        batches.append({"batch": f"{env}_{kind}_b1", "env": env, "kind": kind, "metadata": None,
                        "paper": run_study.PAPER_TABLE2[(env, kind, 1)],
                        "cells": {a: _ranked_cell([x - 1.0, x, x + 1.0]) for a, x in levels.items()}})
    rankings = run_study.exec_rankings(batches)
    assert rankings["most_wins_verdict"] == verdict
    # BAIL and BCQ level on every batch (a run of each on both sides of the other): no difference shown
    assert rankings["average_verdict"].startswith("holds (P(BAIL > BCQ) = 0.50 [") != (winner == "bail")


def test_supp_table_2_is_transcribed_whole(run_study):
    """40 rows (5 envs x 4 kinds x B1/B2), five columns each; spot checks of rows the report reads and the
    summary supp. E gives (BC and MARWIL win the most rows; BAIL's mean above BCQ's over the 40)."""
    table = run_study.PAPER_TABLE2
    assert len(table) == 40 and {len(row) for row in table.values()} == {5}
    assert {env for env, _, _ in table} == {"hopper", "walker", "halfcheetah", "ant", "humanoid"}
    assert table[("hopper", "med_stoch", 1)] == {"bail": (375, 52), "bcq": (881, 155), "bear": (0, 0),
                                                 "bc": (1026, 0), "marwil": (1026, 0)}
    assert table[("walker", "opt_stoch", 1)]["bcq"] == (3386, 196) and table[("humanoid", "opt_det", 1)][
        "marwil"] == (5503, 1)
    wins = {a: sum(a in run_study.paper_winners(row, run_study.PAPER_TABLE2_COLUMNS) for row in table.values())
            for a in run_study.PAPER_TABLE2_COLUMNS}
    assert max(wins, key=wins.get) in ("bc", "marwil") and wins["bc"] == wins["marwil"] > wins["bcq"] > wins["bail"]
    means = {a: sum(row[a][0] for row in table.values()) / 40 for a in ("bail", "bcq")}
    assert means["bail"] > means["bcq"]


def test_the_table2_report_is_the_same_bytes_twice_and_all_pending_with_no_runs(run_study, tmp_path, monkeypatch):
    monkeypatch.setattr(run_study, "CROSS_BATCH_REPS", 300)
    results = _exec_tree(run_study, tmp_path)
    run_study.exec_table_report(results)
    first = {p.name: p.read_bytes() for p in results.iterdir() if p.is_file()}
    run_study.exec_table_report(results)
    assert {p.name: p.read_bytes() for p in results.iterdir() if p.is_file()} == first
    assert {"table2.md", "table2.json", "curves_hopper_opt_det_b1.png"} <= set(first)
    empty = run_study.exec_table_report(tmp_path / "none")
    text = (tmp_path / "none" / "table2.md").read_text()
    assert empty["complete_batches"] == [] and "0 of 10" in empty["status"] and "none yet" in text
    assert all(c["verdict"].startswith("pending") for c in empty["claims"])
    assert "| BAIL ≈ BCQ on average" in text and "| BC | MARWIL |\n" in text and "| BEAR |\n" not in text


def test_report_only_writes_the_table2_report_for_the_exec_study(run_study, tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(run_study, "exec_table_report", lambda results: calls.append(results))
    monkeypatch.setattr(run_study, "report", lambda results, ablations=True: None)
    monkeypatch.setattr(run_study, "curve_check", lambda results: [])
    assert run_study.write_reports("paper_exec", tmp_path, tmp_path) == "study.md, table2.md" and calls == [tmp_path]


def test_the_ope_study_scores_20_headline_policies_of_every_algorithm_each_right_after_its_training(run_study):
    """Issue 38's study: >= 20 final policies on the headline batch over every algorithm of the headline cell, each
    training job the paper_hopper study's own (same overrides: its kept summary is the reference), BAIL keeping
    snapshots, and each FQE job right after the training job whose run it scores."""
    jobs = run_study.ope_headline_jobs()
    trains = [j for j in jobs if j.module == "torchrl_bail.train"]
    assert len(trains) >= 20 and len(jobs) == 2 * len(trains)
    for train, ope in zip(jobs[::2], jobs[1::2], strict=True):
        assert ope.module == "torchrl_bail.ope" and ope.name == f"ope/{train.name}" and ope.args == train.args
    paper = {j.name: j for j in run_study.paper_hopper_jobs()}
    cell = {j.name.split("/")[1] for j in paper.values() if j.name.startswith("hopper_ddpg05/")}
    assert {j.name.split("/")[1] for j in trains} == cell  # every algorithm of the headline cell
    for train in trains:
        extra = run_study.OPE_SNAPSHOTS.get(train.name.split("/")[1], [])
        assert train.args == paper[train.name].args + extra
    assert all(j.args[-1] == "eval.snapshots=5" for j in trains if "/bail/" in j.name)
    assert [j.name for j in trains[:5]] == [f"hopper_ddpg05/{a}/seed1" for a in ("bail", "bc", "td3bc", "marwil",
                                                                                 "pbail")]


def test_an_ope_job_scores_its_training_jobs_run_once_and_gather_keeps_its_records(run_study, tiny_run_data_dir,
                                                                                    tmp_path, monkeypatch):
    """An FQE job runs ``torchrl_bail.ope`` on the run its training job made (snapshots ranked), is done after it
    (status, a second call runs nothing), refuses to start before its training has finished, and ``gather`` keeps
    ``ope.json`` and the snapshots' fit records but never a snapshot's policy."""
    from _contract import ALGO_CASES, TINY_RUN
    from hydra import compose, initialize_config_dir

    from torchrl_bail import config_dir
    from torchrl_bail.train import run

    workdir = tmp_path / "work"
    train = run_study.Job("hopper_ddpg05/bc/seed1", ["+exp=hopper_ddpg05", "algo=bc", "seed=1", "eval.snapshots=2"])
    ope = run_study.Job(f"ope/{train.name}", train.args, "torchrl_bail.ope")
    _, rc, _, _ = run_study.run_job(ope, workdir, tiny_run_data_dir)
    assert rc == 1 and "has not finished" in (workdir / "logs" / "ope__hopper_ddpg05__bc__seed1.log").read_text()
    run_dir = workdir / "outputs" / "hopper_ddpg05_b1" / "bc" / "seed1,eval.snapshots=2"
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("config", overrides=[*TINY_RUN, "algo=bc", *ALGO_CASES["bc"].cli, "eval.snapshots=2",
                                           f"data_dir={tiny_run_data_dir}"])
    run(cfg, run_dir)
    log = workdir / "logs" / "ope__hopper_ddpg05__bc__seed1.log"
    os.utime(log, (time.time() - 900, time.time() - 900))  # no runner has written it for 15 min
    assert str(run_study.job_status(ope, workdir)) == "left (0 of 2 fits)"
    import torch

    torch.save({"update": 20, "identity": {"settings": {"updates": 40}}}, run_dir / "ope_checkpoint.pt")
    assert str(run_study.job_status(ope, workdir)) == "left (0 of 2 fits, 20/40 updates)"
    (run_dir / "ope_checkpoint.pt").unlink()
    monkeypatch.setattr(run_study, "OPE_FLAGS", [*run_study.OPE_FLAGS, "--updates", "40", "--hidden", "16,16"])
    _, rc, _, record = run_study.run_job(ope, workdir, tiny_run_data_dir)
    assert rc == 0, log.read_text()
    assert record["threads"] == 1 and run_study.ope_finished(run_dir)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["fqe_selected"] == json.loads((run_dir / "ope.json").read_text())["fqe_selected"]
    assert str(run_study.job_status(ope, workdir)) == "done"
    assert run_study.run_job(ope, workdir, tiny_run_data_dir)[1] is None  # nothing runs again
    results = tmp_path / "results"
    (kept,) = run_study.gather(workdir, results, policies=True)
    assert (kept / "ope.json").read_bytes() == (run_dir / "ope.json").read_bytes()
    snapshot_fits = sorted(p.name for p in (run_dir / "snapshots").glob("ope_*.json"))
    assert snapshot_fits and sorted(p.name for p in (kept / "snapshots").iterdir()) == snapshot_fits
    assert run_study.landed(ope, results) and str(run_study.job_status(ope, tmp_path / "elsewhere", results=results)) \
        == "done"


def _ope_kept_run(run: Path, final: float, best: float, last_eval: float, estimate: float | None,
                  snapshots: list[tuple[int, float, float]] = (), action_gap: float | None = None) -> None:
    """A kept run of the OPE study: summary, its evaluation CSV ending at ``last_eval``, and a finished ``ope.json``
    (with ``snapshots`` as ``(iteration, eval_return, estimate)`` ranked, FQE choosing the highest estimate)."""
    (run / "logs" / "scalars" / "eval").mkdir(parents=True)
    (run / "logs" / "scalars" / "eval" / "return.csv").write_text(f"500,{best}\n1000,{last_eval}\n")
    summary = {"final_return": final, "best_return": best}
    if snapshots:
        summary["snapshots"] = [{"path": f"snapshots/policy_{i}.pt", "iteration": i, "eval_return": r}
                                for i, r, _ in snapshots]
    (run / "summary.json").write_text(json.dumps(summary))
    if estimate is None:
        return
    ope = {"estimate": estimate} if action_gap is None else {"estimate": estimate, "action_gap": action_gap}
    if snapshots:
        order = sorted(snapshots, key=lambda s: -s[2])
        ope["snapshots"] = [{"path": f"snapshots/policy_{i}.pt", "iteration": i, "eval_return": r, "fqe_estimate": e,
                             "rank": order.index((i, r, e)) + 1} for i, r, e in snapshots]
        ope["fqe_selected"] = {"path": f"snapshots/policy_{order[0][0]}.pt", "iteration": order[0][0],
                               "fqe_estimate": order[0][2], "online_return": order[0][1]}
    (run / "ope.json").write_text(json.dumps(ope))


def test_the_ope_report_ranks_the_scored_policies_and_checks_each_against_the_paper_cells_run(run_study, tmp_path):
    """Spearman's rho and the regret over the scored final policies (true return: each policy's own last
    evaluation), the algorithms' ranking, a BAIL run's FQE-selected snapshot beside final and best return, every
    retrained run compared with the paper_hopper study's kept run of the same job, the rest pending."""
    from scipy.stats import spearmanr

    results, headline = tmp_path / "ope", tmp_path / "paper_hopper"
    cell = headline / "runs" / "hopper_ddpg05_b1"
    kept = results / "runs" / "hopper_ddpg05_b1"
    # (algo, run name, final, best, last evaluation, estimate); bc seed 1 is no reproduction of the cell's run
    # ... and action gap (td3bc's record is older than the gap: none)
    rows = [("bail", "seed1,eval.snapshots=5", 1500.0, 3000.0, 1400.0, 90.0, 0.5),
            ("bc", "seed1", 900.0, 1200.0, 950.0, 95.0, 0.9),
            ("td3bc", "seed1,algo.epochs=25.6,eval.every_epochs=1.28", 1200.0, 2000.0, 1300.0, 80.0, None),
            ("marwil", "seed1", 400.0, 700.0, 350.0, 60.0, 0.6)]
    for algo, name, final, best, last, estimate, gap in rows:
        snapshots = [(10000, 2500.0, 70.0), (30000, 3000.0, 85.0), (50000, last, estimate)] if algo == "bail" else ()
        _ope_kept_run(kept / algo / name, final, best, last, estimate, snapshots, gap)
        reference = cell / algo / name.replace(",eval.snapshots=5", "")
        reference.mkdir(parents=True)
        (reference / "summary.json").write_text(json.dumps({"final_return": final + (algo == "bc"),
                                                            "best_return": best}))
    _ope_kept_run(kept / "pbail" / "seed1", 1800.0, 2600.0, 1900.0, None)  # trained, FQE still to run
    (cell / "pbail" / "seed1").mkdir(parents=True)
    # marwil seed 1: both runs record one platform and one code revision, and still differ (a bug, not rounding);
    # pbail seed 1: one platform, but the code changed between them
    for path, final, commit in ((kept / "marwil" / "seed1" / "summary.json", 400.0, "a"),
                                (cell / "marwil" / "seed1" / "summary.json", 401.0, "a"),
                                (kept / "pbail" / "seed1" / "summary.json", 1800.0, "a"),
                                (cell / "pbail" / "seed1" / "summary.json", 1801.0, "b")):
        path.write_text(json.dumps({"final_return": final, "best_return": 700.0,
                                    "platform": {"cpu": "x", "source": {"commit": commit, "modified": False}}}))
    out = run_study.ope_headline_report(results, headline)
    assert json.loads((results / "ope.json").read_text()) == json.loads(json.dumps(out))
    by_job = {p["job"]: p for p in out["policies"]}
    assert [by_job[f"hopper_ddpg05/{a}/seed1"]["reproduces"] for a in ("bail", "bc", "td3bc", "marwil", "pbail")] \
        == [True, False, True, False, False]
    assert by_job["hopper_ddpg05/bail/seed2"]["run"] is by_job["hopper_ddpg05/bail/seed2"]["reproduces"] is None
    ranking = out["ranking"]
    estimates, truths = [90.0, 95.0, 80.0, 60.0], [1400.0, 950.0, 1300.0, 350.0]  # the last evaluations, not final
    assert ranking["n"] == 4 and ranking["spearman"] == pytest.approx(spearmanr(estimates, truths).statistic)
    assert ranking["selected"] == "hopper_ddpg05/bc/seed1" and ranking["best"] == "hopper_ddpg05/bail/seed1"
    assert ranking["regret"] == pytest.approx(1400.0 - 950.0)
    assert ranking["spearman_ci"][0] <= ranking["spearman"] <= ranking["spearman_ci"][1]
    assert out["algorithm_ranking"]["selected"] == "bc" and out["algorithm_ranking"]["best"] == "bail"
    # the gaps against FQE's overrating (rank by estimate minus rank by true return) of bail, bc and marwil
    over = [2 - 3, 3 - 2, 1 - 1]  # ranks among the three: estimates 90, 95, 60; true returns 1400, 950, 350
    assert out["gap_overrating"] == {"n": 3, "spearman": pytest.approx(spearmanr([0.5, 0.9, 0.6], over).statistic)}
    assert out["gap_overrating"]["spearman"] == pytest.approx(1.0)  # the most overrated policy strays furthest
    assert [a["mean_action_gap"] for a in out["algorithms"]] == [0.5, 0.9, None, 0.6]
    assert out["snapshot_selection"] == {"fqe_selected_return": 1400.0, "final_return": 1500.0, "best_return": 3000.0,
                                         "final_policy_return": 1400.0, "best_candidate_return": 3000.0}
    text = (results / "ope.md").read_text()
    assert text.startswith("Policies scored by FQE: 4 of 20 planned (trained: 5); BAIL runs with their snapshots "
                           "ranked: 1 of 5. Retrained runs equal to the paper_hopper study's kept run of the same job "
                           "(final and best return): 2 of 5.")
    assert "| bc seed 1 | 95.00 | 0.90 | 950.0 | 900.0 | 901.0 | no (a platform unrecorded) |" in text
    assert "| marwil seed 1 | 60.00 | 0.60 | 350.0 | 400.0 | 401.0 | **no** (same platform) |" in text
    assert "| pbail seed 1 | pending | pending | 1900.0 | 1800.0 | 1801.0 | no (another code revision) |" in text
    assert "| td3bc seed 1 | 80.00 | pending | 1300.0 |" in text
    assert "| bail seed 2 | pending | pending | pending | pending | pending | pending |" in text
    assert "| seed 1 | 3 | 50000 | 1400.0 | 1400.0 | 1500.0 | 3000.0 | 3000.0 |" in text
    assert (results / "ope.png").is_file()


def test_the_ope_report_with_no_runs_is_all_pending(run_study, tmp_path):
    out = run_study.ope_headline_report(tmp_path / "ope", tmp_path / "no_headline")
    assert out["ranking"] is None and out["snapshot_selection"] is None and out["figure"] == "ope.png"
    assert "Ranking: pending" in (tmp_path / "ope" / "ope.md").read_text()


def _batch(name: str, **cells: list[float]) -> dict:
    """A cross-batch report's batch entry with only what the aggregate reads: per algorithm its normalised (and, the
    same, raw) final returns."""
    return {"batch": name, "metadata": {"episode_return_min": 0.0, "episode_return_max": 1.0},
            "cells": {algo: {"seeds": len(xs), "per_seed_normalised": xs, "per_seed": xs}
                      for algo, xs in cells.items()}}


def test_the_probability_of_improvement_over_batches_that_disagree_has_the_width_of_their_disagreement(run_study):
    """Four batches, BAIL above BCQ on three (every BAIL run above every BCQ run) and below on one: the aggregate is
    0.75. Over seeds alone its interval is the point [0.75, 0.75] (clean batches give 1 or 0 whatever seeds are
    drawn); the hierarchical bootstrap draws the batches too, so the interval spans what four batches drawn from
    these could give, and the reading is no difference shown. The per-batch values show the split."""
    up, down = ([0.6, 0.7, 0.8], [0.2, 0.3, 0.4]), ([0.2, 0.3, 0.4], [0.6, 0.7, 0.8])

    def pair(batches):
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(run_study, "CROSS_BATCH_REPS", 500)
            out = run_study.cross_batch_aggregate(batches)
        return out, next(p for p in out["probability_of_improvement"] if (p["a"], p["b"]) == ("bail", "bcq"))

    batches = [_batch(f"b{i}", bail=xs, bcq=ys) for i, (xs, ys) in enumerate((up, down, up, up), 1)]
    out, row = pair(batches)
    assert row["per_batch"] == {"b1": 1.0, "b2": 0.0, "b3": 1.0, "b4": 1.0}
    assert row["p"] == pytest.approx(0.75) and row["seeds_only"] == [pytest.approx(0.75)] * 2
    # four batches drawn with replacement from three 1s and one 0: 2.5 % and 97.5 % of the mean land at 0.25 and 1
    assert (row["ci_low"], row["ci_high"]) == (pytest.approx(0.25), pytest.approx(1.0))
    assert row["n_batches"] == 4 and row["reading"] == "no difference shown (the interval contains 0.5)"
    assert "hierarchical bootstrap" in out["bootstrap"] and "batches with replacement" in out["bootstrap"]
    assert pair(batches)[1] == row  # seeded: the same numbers on every rerun
    # every batch agrees: the interval stays above 0.5, whatever batches are drawn
    _, row = pair([_batch(name, bail=up[0], bcq=up[1]) for name in ("b1", "b2", "b3", "b4")])
    assert row["reading"] == "bail above bcq across batches (the interval lies above 0.5)"
    assert (row["p"], row["ci_low"], row["ci_high"]) == (1.0, 1.0, 1.0)


def test_the_iqm_over_batches_at_different_levels_is_as_wide_as_their_spread(run_study):
    """BAIL's seeds agree closely within each batch, but the batches sit at 0.2, 0.4, 0.6 and 0.8: over seeds alone
    the IQM's interval is narrow (±0.01 or so); drawing the batches too, it spans most of 0.2 to 0.8."""
    levels = (0.2, 0.4, 0.6, 0.8)
    batches = [_batch(f"b{i}", bail=[x - 0.01, x, x + 0.01]) for i, x in enumerate(levels, 1)]
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(run_study, "CROSS_BATCH_REPS", 500)
        bail = run_study.cross_batch_aggregate(batches)["iqm"]["bail"]
    assert bail["iqm"] == pytest.approx(0.5) and bail["n_batches"] == 4
    assert bail["seeds_only"][1] - bail["seeds_only"][0] < 0.05
    assert bail["ci_low"] < 0.35 and bail["ci_high"] > 0.65


def test_the_hierarchical_bootstrap_draws_the_batches_once_for_both_sides_of_a_comparison(run_study):
    """A comparison stays within a batch: the batches drawn are the same for both algorithms. Here every batch has
    BAIL above BCQ but at levels far apart, so P(BAIL > BCQ) is 1 in every replication; drawing each side's batches
    apart would set one batch's BAIL against another's BCQ and give less. With one batch it is the bootstrap over
    seeds alone."""
    from rliable import metrics

    x = np.array([[10.0, 100.0, 1000.0], [11.0, 101.0, 1001.0], [12.0, 102.0, 1002.0]])
    y = x - 5.0
    assert run_study.hierarchical_interval([x, y], metrics.probability_of_improvement, reps=500) == (1.0, 1.0, 1.0)
    point, low, high = run_study.hierarchical_interval([x[:, :1]], metrics.aggregate_iqm, reps=500)
    assert point == pytest.approx(11.0) and 10.0 <= low < 11.0 < high <= 12.0
    with pytest.raises(ValueError, match="same batches"):
        run_study.hierarchical_interval([x, y[:, :2]], metrics.probability_of_improvement)


def test_status_estimates_the_work_left_from_the_recorded_costs(run_study):
    """``--status``'s last line: a running job's own time left, any other job its kind's median recorded cost (its
    batch first, then the study's other batches, then the peer studies), scaled by the updates its checkpoint has
    left; a kind nothing recorded is counted apart."""
    timings = {"b1/bail/seed1": {"wall_s": 1000.0}, "b1/bail/seed2": {"wall_s": 3000.0},
               "b2/bail/seed1": {"wall_s": 9000.0}, "b1/bc/seed1": 2000.0, "collect/b1": {"wall_s": 7200.0}}
    elsewhere = {"hopper/bcq/seed1": 3600.0, "hopper/bc/seed1": 99999.0}  # the study's own bc record comes first
    state = run_study.JobState
    states = [("b1/bail/seed3", state("left")),                          # its batch's median: 2000 s
              ("b2/bail/seed2", state("left", (2500, 10000))),           # 9000 x 3/4 = 6750 s
              ("b3/bc/seed1", state("left")),                            # the study's other batch: 2000 s
              ("b3/bcq/seed1", state("left")),                           # the peer study: 3600 s
              ("b3/iql/seed1", state("left")),                           # nothing recorded
              ("b1/bc/seed2", state("running", (10, 100), 1500.0)),      # its own pace: 1500 s (not 2000 x 0.9)
              ("b1/bail/seed1", state("done"))]
    line = run_study.work_left(states, run_study.seconds_left(states, timings, elsewhere))
    assert line.startswith(f"left to run: about {(2000 + 6750 + 2000 + 3600 + 1500) / 3600:.1f} h of one core for 5 "
                           "of the 6 unfinished jobs") and line.endswith("; 1 of a kind with no recorded cost")
    partial = [("collect/b2", state("left", steps_collected=500))]
    line = run_study.work_left(partial, run_study.seconds_left(partial, timings))
    assert line.startswith("left to run: about 2.0 h") and line.endswith("; 1 partial collection priced whole")
    assert run_study.work_left([("b1/bail/seed1", state("done"))], {}) == "nothing left to run"


def test_status_prices_a_collection_by_how_its_batch_is_made(run_study):
    """A SAC run's collection (10^6 SAC updates) and an execution batch's (a frozen policy acting) are priced from
    collections made the same way, never from DDPG's: with only DDPG collections recorded they have no recorded cost."""
    timings = {"collect/hopper_ddpg05_b1": 1600.0, "collect/hopper_ddpg01_b1": 1500.0}
    state = run_study.JobState
    states = [("collect/walker_ddpg05_b1", state("left")), ("collect/hopper_sac_b1", state("left")),
              ("collect/hopper_med_det_b1", state("left"))]
    seconds = run_study.seconds_left(states, timings)
    assert seconds == {"collect/walker_ddpg05_b1": 1550.0, "collect/hopper_sac_b1": None,
                       "collect/hopper_med_det_b1": None}
    timings |= {"collect/hopper_sac_b1": 10000.0, "collect/hopper_opt_det_b1": 6000.0}
    seconds = run_study.seconds_left([("collect/walker_sac_b1", state("left")),
                                      ("collect/walker_med_stoch_b1", state("left"))], timings)
    assert seconds == {"collect/walker_sac_b1": 10000.0, "collect/walker_med_stoch_b1": 6000.0}


def test_status_prices_the_queue_in_wall_time_as_its_workers_would_run_it(run_study):
    """``--status``'s wall-time line: a running job holds its worker for its time left, a free worker takes the
    first job :func:`next_ready` allows, so a batch's jobs wait for its collection while the other worker goes on."""
    state, Job = run_study.JobState, run_study.Job

    def train(batch: str, algo: str, seed: int) -> Job:
        return Job(f"{batch}_b1/{algo}/seed{seed}", [f"+exp={batch}", f"algo={algo}", f"seed={seed}"])

    jobs = [Job("collect/a_b1", ["+exp=a"], "torchrl_bail.collect"),
            Job("collect/b_b1", ["+exp=b"], "torchrl_bail.collect"),
            train("a", "bail", 1), train("a", "bail", 2), train("b", "bc", 1), train("a", "iql", 1)]
    states = {"collect/a_b1": state("running", transitions=(10, 20), seconds_left=100.0),
              **{job.name: state("left") for job in jobs[1:]}}
    seconds = {"collect/a_b1": 100.0, "collect/b_b1": 300.0, "a_b1/bail/seed1": 50.0, "a_b1/bail/seed2": 50.0,
               "b_b1/bc/seed1": 10.0}  # iql: no recorded cost, left out
    # two workers: collect a (to 100) | collect b (0-300); bail 1 (100-150), bail 2 (150-200); bc waits for b: 300-310
    assert run_study.queue_wall_seconds(jobs, states, seconds, 2) == 310.0
    assert run_study.queue_wall_seconds(jobs, states, seconds, 1) == 510.0  # one after another
    assert run_study.queue_wall_seconds(jobs, states, seconds, 8) == 310.0  # more workers than jobs: b's collection
    done = {name: state("done") for name in states}
    assert run_study.queue_wall_seconds(jobs, done, seconds, 2) == 0.0


def test_the_aggregate_figure_puts_each_batch_beside_the_interval(run_study, cross_batch):
    """``cross_batch_aggregate.png``: per algorithm the aggregate IQM's interval and one marker per batch it entered,
    at the IQM of that batch's normalised returns alone (skewed seeds here, so a mean would sit elsewhere); per
    comparison, a marker per batch at its own probability of improvement. Kept beside the report, named in it."""
    import numpy as np
    from rliable import metrics

    out, results = cross_batch
    assert out["aggregate_figure"] == "cross_batch_aggregate.png" and (results / "cross_batch_aggregate.png").is_file()
    assert "cross_batch_aggregate.png`." in (results / "cross_batch.md").read_text()

    def batch(name: str, bail: list[float], bcq: list[float]) -> dict:
        return {"batch": name, "metadata": {}, "cells": {"bail": {"seeds": len(bail), "per_seed_normalised": bail},
                                                          "bcq": {"seeds": len(bcq), "per_seed_normalised": bcq}}}

    batches = [batch("b1", [0.1, 0.5, 0.52, 0.54, 0.95], [0.3, 0.4, 0.45]),
               batch("b2", [0.6, 0.62, 0.64, 0.66, 0.0], [0.7, 0.2, 0.75, 0.8]), batch("b3", [0.5, 0.6], [0.1] * 3)]
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(run_study, "CROSS_BATCH_REPS", 200)
        aggregate = run_study.cross_batch_aggregate(batches)
    left, right = run_study.cross_batch_aggregate_figure(batches, aggregate).axes
    assert [t.get_text() for t in left.get_yticklabels()] == ["bail", "bcq"]

    def markers(ax) -> list[tuple[float, int]]:
        return sorted((round(float(line.get_xdata()[0]), 9), int(line.get_ydata()[0])) for line in ax.get_lines()
                      if line.get_linestyle() == "None" and line.get_marker() in run_study.BATCH_MARKERS)

    iqm = [round(float(metrics.aggregate_iqm(np.array(b["cells"][algo]["per_seed_normalised"]))), 9)
           for algo in ("bail", "bcq") for b in batches[:2]]  # b3's BAIL has 2 seeds: not entered
    assert markers(left) == sorted([(iqm[0], 0), (iqm[1], 0), (iqm[2], 1), (iqm[3], 1), (0.1, 1)])
    assert iqm[0] != round(float(np.mean(batches[0]["cells"]["bail"]["per_seed_normalised"])), 9)
    poi = next(p for p in aggregate["probability_of_improvement"] if (p["a"], p["b"]) == ("bail", "bcq"))
    assert markers(right) == sorted((round(v, 9), 0) for v in poi["per_batch"].values()) and len(poi["per_batch"]) == 2


PROBE = '''
import json, os, sys, time
from pathlib import Path
here = Path(sys.argv[1])
(here / (sys.argv[2] + ".json")).write_text(json.dumps(sorted(os.sched_getaffinity(0))))
deadline = time.monotonic() + 30
while len(list(here.glob("*.json"))) < int(sys.argv[3]) and time.monotonic() < deadline:
    time.sleep(0.05)  # every job of the round starts before any ends: each must hold its own CPU
'''


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="pinning two jobs at once needs two CPUs")
def test_pin_runs_each_of_the_parallel_jobs_alone_on_its_own_cpu_and_records_it(run_study, tmp_path, capsys):
    """``--jobs 2 --pin``: two jobs running at once each see one CPU, not the same one, and ``timings.json`` records
    that CPU; a third job, started when one ends, reuses a freed CPU. Without ``--pin`` a job sees all of them."""
    work, results, seen = tmp_path / "work", tmp_path / "results", tmp_path / "seen"
    for d in (work, results, seen):
        d.mkdir()
    (work / "affinity_probe.py").write_text(PROBE)  # `python -m affinity_probe` from the job's cwd
    jobs = [run_study.Job(f"probe/seed{k}", [str(seen), f"seed{k}", "2" if k < 3 else "3"], "affinity_probe")
            for k in (1, 2, 3)]
    cpus = run_study.pin_cpus(2)
    assert run_study.run_queue(jobs, work, None, results, 2, cpus) == []
    affinity = {p.stem: json.loads(p.read_text()) for p in seen.glob("*.json")}
    mine = sorted(os.sched_getaffinity(0))
    assert all(len(a) == 1 and a[0] in mine[:2] for a in affinity.values()), affinity
    assert affinity["seed1"] != affinity["seed2"], "two jobs running at once shared one CPU"
    timings = json.loads((results / "timings.json").read_text())
    assert {k: timings[f"probe/{k}"]["cpus"] for k in affinity} == affinity
    assert "ok in" in capsys.readouterr().out

    unpinned = run_study.Job("probe/seed4", [str(seen), "seed4", "4"], "affinity_probe")
    assert run_study.run_queue([unpinned], work, None, results, 1) == []
    assert json.loads((seen / "seed4.json").read_text()) == mine


def test_pin_refuses_more_jobs_than_cpus_and_a_queue_of_no_jobs(run_study, tmp_path, capsys):
    """``--pin`` with more jobs than the runner's CPUs, and ``--jobs 0``, are refused before any job starts."""
    many = len(os.sched_getaffinity(0)) + 1
    common = ["--only", "^$", "--workdir", str(tmp_path / "w"), "--results", str(tmp_path / "r")]
    with pytest.raises(SystemExit):
        run_study.main(["--jobs", str(many), "--pin", *common])
    assert f"--jobs {many} needs {many} CPUs" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        run_study.main(["--jobs", "0", *common])
    assert "--jobs must be at least 1, got 0" in capsys.readouterr().err
    assert not (tmp_path / "w").exists()


def test_a_free_worker_passes_over_jobs_on_a_batch_being_collected(run_study, tmp_path, monkeypatch):
    """``--jobs 2``, queue [collect A, train on A, train on B]: while A is being collected the second worker starts
    the job on B, not the one on A (which would only wait on A's lock); the job on A starts once A is made."""
    started, b_started = [], threading.Event()

    class Process:  # what run_job starts: the collect job ends only once the job on B has started (or after 10 s)
        pid = 1

        def __init__(self, argv, **kwargs):
            self.job = " ".join(a for a in argv if a.startswith(("-m", "torchrl_bail", "+exp=", "algo=")))
            started.append(self.job)
            if "+exp=walker_ddpg05" in self.job:
                b_started.set()

        def wait(self):
            if "collect" in self.job:
                b_started.wait(10)
            return 0

    monkeypatch.setattr(run_study.subprocess, "Popen", Process)
    jobs = [run_study.Job("collect/hopper_ddpg05_b1", ["+exp=hopper_ddpg05", "preset=paper"], "torchrl_bail.collect"),
            run_study.Job("hopper_ddpg05_b1/bc/seed1", ["+exp=hopper_ddpg05", "algo=bc", "seed=1", "preset=paper"]),
            run_study.Job("walker_ddpg05_b1/bc/seed1", ["+exp=walker_ddpg05", "algo=bc", "seed=1", "preset=paper"])]
    (tmp_path / "results").mkdir()
    assert run_study.run_queue(jobs, tmp_path / "work", None, tmp_path / "results", 2) == []
    assert sorted(started[:2]) == ["-m torchrl_bail.collect +exp=hopper_ddpg05",  # the two workers, in either order
                                   "-m torchrl_bail.train +exp=walker_ddpg05 algo=bc"]
    assert started[2] == "-m torchrl_bail.train +exp=hopper_ddpg05 algo=bc"
    assert run_study.batch_key(jobs[0]) == run_study.batch_key(jobs[1]) != run_study.batch_key(jobs[2])

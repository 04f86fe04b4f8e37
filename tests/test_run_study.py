"""The results study's script (``results/run_study.py``): the jobs it runs, its queue and status, and the reports it
keeps (the paper cell's, the OPE study's); the report code it imports from :mod:`torchrl_bail.study` is tested in
tests/test_study_reports.py."""

from __future__ import annotations

import importlib.util
import json
import os
import sys
import threading
import time
from pathlib import Path

import pytest
from test_study_reports import HEADLINE_META, HEADLINE_RUNS, WALKER_META, WALKER_RUNS, fake_batch, made_again

from torchrl_bail.configuration.algo_schemas import ALGO_SCHEMAS, study_algorithms
from torchrl_bail.study import tables

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


# ---------------------------------------------------------------------------------------------------------------
# the paper_batches and paper_exec studies through the script (their reports: tests/test_study_reports.py)
# ---------------------------------------------------------------------------------------------------------------


def test_report_only_keeps_the_collected_batchs_metadata_and_rebuilds_from_kept_files_alone(run_study, tmp_path,
                                                                                             monkeypatch):
    """``--report-only`` copies a collect job's batch metadata from the cache entry its log names (the data dir)
    into ``results/batches``; with the workdir and the data dir gone, it rebuilds the same report."""
    import shutil

    monkeypatch.setattr(tables, "BOOTSTRAP_REPS", 300)
    monkeypatch.setattr(run_study, "report_runs", lambda *a, **k: None)  # torchrl_bail.report's own tables: not here
    headline, results, work, data = (tmp_path / d for d in ("paper_hopper", "paper_batches", "work", "data"))
    fake_batch(headline, "hopper_ddpg05_b1", "abcd1234", HEADLINE_RUNS, HEADLINE_META)
    fake_batch(results, "walker_ddpg05_b1", "1234abcd", WALKER_RUNS, None)
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


def test_a_batch_made_again_with_other_data_stops_the_queue_and_the_report(run_study, tmp_path, monkeypatch, capsys):
    """The queue's collect job makes walker_ddpg05_b1 again (its data dir lost) and it comes out other than the kept
    one: the job fails, naming the difference, no training job starts on it, and no report is rebuilt."""
    headline, results, work, data = (tmp_path / d for d in ("paper_hopper", "paper_batches", "work", "data"))
    fake_batch(headline, "hopper_ddpg05_b1", "abcd1234", HEADLINE_RUNS, HEADLINE_META)
    fake_batch(results, "walker_ddpg05_b1", "1234abcd", {}, WALKER_META)
    entry = made_again(work, data, {**WALKER_META, "episode_return_mean": 412.5})
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


def test_report_only_writes_the_table2_report_for_the_exec_study(run_study, tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(run_study, "exec_table_report", lambda results: calls.append(results))
    monkeypatch.setattr(run_study, "report_runs", lambda results, ablations=True: None)
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

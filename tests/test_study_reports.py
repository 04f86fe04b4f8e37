"""The reports of the paper_batches and paper_exec studies (:mod:`torchrl_bail.study`): gathering the kept runs and
batch metadata, the verdicts and the bootstrap the reports share, the cross-batch report and supp. Table 2's, each
from a fake results tree of kept runs, and every study's learning-curve check."""

from __future__ import annotations

import functools
import json
from pathlib import Path

import numpy as np
import pytest

from torchrl_bail.study import StudyJob, load_study, tables
from torchrl_bail.study.cross_batch import (
    BATCH_MARKERS,
    cross_batch_aggregate,
    cross_batch_aggregate_figure,
    cross_batch_report,
    kept_run_jobs,
)
from torchrl_bail.study.exec_table import (
    PAPER_TABLE2,
    PAPER_TABLE2_COLUMNS,
    exec_batches,
    exec_rankings,
    exec_table_report,
    paper_winners,
)
from torchrl_bail.study.gather import BatchMismatch, gather, keep_batch_metadata, run_dir_of
from torchrl_bail.study.reports import curve_check
from torchrl_bail.study.tables import claim_verdict, hierarchical_interval, reference_row


@functools.cache
def schedule(algo: str) -> tuple[str, ...]:
    """The overrides the declared paper-scale studies give ``algo``'s jobs beside its batch, algorithm and seed (the
    actor-critics' run length; none for the imitation learners), sorted as a run directory's name lists them."""
    job = next(j for name in ("paper_batches", "paper_exec") for j in load_study(name).jobs
               if j.overrides.get("algo") == algo)
    return tuple(sorted(a for a in job.args if not a.startswith(("+exp=", "algo=", "seed=", "batch.index="))))


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


def test_curve_check_tells_a_flat_curve_from_a_rising_one(tmp_path):
    # flat: the second half (evaluations 5..9) alternates around 500 -> no fitted change
    # their envelope fits: best epochs 12 and 46 of 50 (patience 4: both settled before the cap)
    _run(tmp_path, "seed1,preset=study", [100, 200, 300, 400, 500, 490, 510, 490, 510, 500], envelope_best_epoch=12)
    _run(tmp_path, "seed2,preset=study", [100, 200, 300, 400, 500, 510, 490, 510, 490, 500], envelope_best_epoch=46)
    # rising by 50 per evaluation over the second half: +200 across it, exactly on the line (spread 0); its envelope
    # had its best epoch 47 of 50: fewer than the patience's 4 epochs before the cap, still improving
    _run(tmp_path, "seed1,algo.envelope.penalty=1,preset=study", [0, 0, 0, 0, 0, 100, 150, 200, 250, 300],
         envelope_best_epoch=47)
    _run(tmp_path, "seed1,preset=study", [0, 100, 200, 300], algo="bc")  # a second half of 2 points: left out
    rows = {r["overrides"]: r for r in curve_check(tmp_path)}
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


def test_claim_verdicts_read_the_iqm_intervals():
    def row(seeds, low, high):
        return {"seeds": seeds, "final_return_iqm_ci_low": low, "final_return_iqm_ci_high": high}
    assert claim_verdict(row(5, 10, 20), row(5, 0, 9), "above").startswith("holds (above")
    assert claim_verdict(row(5, 0, 9), row(5, 10, 20), "above").startswith("does not hold (below")
    # a's interval starts above b's start but they overlap: no difference shown
    assert claim_verdict(row(5, 12, 30), row(5, 10, 20), "above").startswith(
        "does not hold (no difference")
    assert claim_verdict(row(5, 0, 15), row(5, 10, 20), "above").startswith("does not hold (no difference")
    assert claim_verdict(row(3, 0, 15), row(3, 10, 20), "similar").startswith("holds (no difference")
    assert claim_verdict(row(3, 0, 9), row(3, 10, 20), "similar").startswith("does not hold (below")
    assert claim_verdict(None, row(3, 10, 20), "above").startswith("pending (seeds so far: 0 and 3")


# ---------------------------------------------------------------------------------------------------------------
# the cross-batch report (paper_batches): a fake results tree of kept runs and kept batch metadata
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


def fake_batch(root: Path, label: str, recipe: str, runs: dict[str, list[float]],
                metadata: dict | None) -> None:
    """Kept runs of one batch in the layout the runner gathers (``runs/<batch>/<algo>/seed<s>[,<schedule>]`` with
    summary.json, config.yaml and CSV evaluation logs), and its kept ``batches/<batch>-<hash>.metadata.json``."""
    for algo, finals in runs.items():
        suffix = "".join("," + o for o in schedule(algo))
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
def cross_batch(tmp_path_factory):
    """The report over the headline batch (every central cell complete) and walker_ddpg05_b1 (BAIL's 5 seeds, BC's
    first 2), the two other batches not begun."""
    root = tmp_path_factory.mktemp("cross_batch")
    headline, results = root / "paper_hopper", root / "paper_batches"
    fake_batch(headline, "hopper_ddpg05_b1", "abcd1234", HEADLINE_RUNS, HEADLINE_META)
    fake_batch(results, "walker_ddpg05_b1", "1234abcd", WALKER_RUNS, WALKER_META)
    # the headline batch made twice again with the same data: once from scratch, once resumed from an older
    # version's checkpoint (its first steps untimed: not a collection time)
    (headline / "batches" / "hopper_ddpg05_b1-abcd1234.remakes.json").write_text(json.dumps({"same": [], "remakes": [
        {"created_at": "later", "collection_wall_time_s": 5400.0, "collection_timed_from_step": 0},
        {"created_at": "later still", "collection_wall_time_s": 60.0, "collection_timed_from_step": 990000}]}))
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(tables, "BOOTSTRAP_REPS", 300)
        out = cross_batch_report(results, headline)
    return out, results


def test_the_cross_batch_table_has_a_row_per_batch_with_its_metadata_and_pending_cells(cross_batch):
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


def test_each_batchs_verdicts_follow_the_paper_cells_rule(cross_batch):
    out, _ = cross_batch
    headline, walker = out["batches"][:2]
    verdicts = {c["claim"]: c["verdict"] for c in headline["claims"]}
    cells = headline["cells"]
    assert verdicts["BAIL ≫ BC"] == claim_verdict(cells["bail"], cells["bc"], "above")
    assert verdicts["BAIL ≫ BC"] == "holds (above: the IQM intervals are disjoint)"
    assert cells["bail"]["final_return_iqm_ci_low"] > cells["bc"]["final_return_iqm_ci_high"]
    assert verdicts["BAIL above BCQ (BCQ at 10^5 of the paper's 10^6 updates)"].startswith("does not hold (below")
    assert verdicts["Progressive BAIL ≈ BAIL"].startswith("holds (no difference shown")
    walker_verdicts = {c["claim"]: c["verdict"] for c in walker["claims"]}
    assert walker_verdicts["BAIL ≫ BC"].startswith("pending (seeds so far: 5 and 2")
    across = {c["claim"]: c for c in out["claims_across_batches"]}
    assert across["BAIL ≫ BC"] == {"claim": "BAIL ≫ BC", "holds": 1, "does not hold": 0, "pending": 3}


def test_the_aggregate_normalises_by_each_batchs_own_episodes(cross_batch):
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


def test_a_batch_made_by_the_same_recipe_is_set_beside_the_first(tmp_path, monkeypatch):
    """hopper_ddpg05_b2 (the headline recipe with another behaviour seed) beside hopper_ddpg05_b1: per algorithm,
    where its IQM interval lies against B1's; per claim, whether the two batches' verdicts agree. Here BCQ's place
    against BAIL turns over with the batch drawn while BAIL ≫ BC holds on both."""
    monkeypatch.setattr(tables, "BOOTSTRAP_REPS", 300)
    headline, results = tmp_path / "paper_hopper", tmp_path / "paper_batches"
    fake_batch(headline, "hopper_ddpg05_b1", "abcd1234", HEADLINE_RUNS, HEADLINE_META)
    b2 = {"bail": [1300.0, 1350.0, 1250.0, 1320.0, 1280.0], "bc": [420.0, 470.0, 440.0, 460.0, 430.0],
          "bcq": [900.0, 950.0, 1000.0], "pbail": [1290.0, 1310.0, 1330.0]}
    fake_batch(results, "hopper_ddpg05_b2", "ef567890", b2,
                {**HEADLINE_META, "episode_return_mean": 700.0, "behaviour_final_return_mean10": 900.0})
    out = cross_batch_report(results, headline)
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


def test_the_cross_batch_report_with_no_runs_is_all_pending(tmp_path):
    out = cross_batch_report(tmp_path / "paper_batches", tmp_path / "paper_hopper")
    assert out["complete_batches"] == [] and "0 of 4" in out["status"]
    assert out["aggregate"]["iqm"] == {} and all(p["p"] is None for p in out["aggregate"]["probability_of_improvement"])
    assert all(c["verdict"].startswith("pending (seeds so far: 0 and 0") for b in out["batches"] for c in b["claims"])
    text = (tmp_path / "paper_batches" / "cross_batch.md").read_text()
    assert "| bail | pending (no batch with 3 seeds) |" in text and "none yet" in text
    assert not list((tmp_path / "paper_batches").glob("*.png"))


def test_the_headline_batchs_jobs_are_read_from_its_kept_runs(tmp_path):
    """The headline batch's study (paper_hopper) is not declared in the package: the cross-batch report reads its
    jobs from its kept runs, each an algorithm paper_batches trains with the overrides paper_batches gives it (the
    actor-critics' schedule), a variant and an algorithm paper_batches does not train left out."""
    fake_batch(tmp_path, "hopper_ddpg05_b1", "abcd1234", {"bail": [1.0, 2.0], "bcq": [3.0], "marwil": [4.0]}, None)
    variant = tmp_path / "runs" / "hopper_ddpg05_b1" / "bail" / "seed1,algo.selection.by=return"
    variant.mkdir()
    (variant / "summary.json").write_text("{}")
    jobs = kept_run_jobs(tmp_path, "hopper_ddpg05_b1", load_study("paper_batches").jobs)
    assert [j.name for j in jobs] == ["hopper_ddpg05_b1/bail/seed1", "hopper_ddpg05_b1/bail/seed2",
                                      "hopper_ddpg05_b1/bcq/seed1"]
    bcq = jobs[2]
    assert bcq.args[:3] == ("+exp=hopper_ddpg05", "algo=bcq", "seed=1") and bcq.module == "torchrl_bail.train"
    assert run_dir_of(bcq, tmp_path / "runs").name == ",".join(("seed1", *schedule("bcq")))
    assert run_dir_of(jobs[0], tmp_path / "runs").name == "seed1"


def made_again(work: Path, data: Path, meta: dict) -> Path:
    """The data dir entry of walker_ddpg05_b1 made again with ``meta``, and its collect job's log naming it."""
    entry = data / "walker_ddpg05_b1-1234abcd"
    entry.mkdir(parents=True)
    (entry / "metadata.json").write_text(json.dumps(meta))
    (work / "logs").mkdir(parents=True, exist_ok=True)
    (work / "logs" / "collect__walker_ddpg05_b1.log").write_text(f"walker_ddpg05_b1: collected at {entry}\n")
    return entry


def test_a_batch_made_again_keeps_the_first_record_when_its_data_match_and_is_refused_when_not(tmp_path):
    """Made again with the same statistics (another collection time, another date), the kept metadata stays, the
    record of the batch the kept runs trained on, and the remaking's own fields are listed beside it (once, however
    often it is gathered); with another mean return, :class:`BatchMismatch` names it."""
    results, work, data = (tmp_path / d for d in ("results", "work", "data"))
    kept = results / "batches" / "walker_ddpg05_b1-1234abcd.metadata.json"
    kept.parent.mkdir(parents=True)
    kept.write_text(json.dumps(WALKER_META))
    entry = made_again(work, data, {**WALKER_META, "collection_wall_time_s": 4000.0, "created_at": "today"})
    collect = StudyJob("collect/walker_ddpg05_b1", (), "collect")
    remakes = results / "batches" / "walker_ddpg05_b1-1234abcd.remakes.json"
    assert keep_batch_metadata(work, results, [collect]) == [remakes]
    assert keep_batch_metadata(work, results, [collect]) == []
    assert json.loads(kept.read_text()) == WALKER_META
    record = json.loads(remakes.read_text())
    assert record["remakes"] == [{"collection_wall_time_s": 4000.0, "created_at": "today"}]
    assert "episode_return_mean" in record["same"] and "num_transitions" in record["same"]
    (entry / "metadata.json").write_text(json.dumps({**WALKER_META, "episode_return_mean": 412.5}))
    with pytest.raises(BatchMismatch, match=r"episode_return_mean 412\.5 here, 400\.0 kept"):
        keep_batch_metadata(work, results, [collect])
    assert json.loads(kept.read_text()) == WALKER_META


def test_the_study_commands_report_gathers_its_runs_and_the_batches_it_made_in_the_data_dir(tmp_path, monkeypatch):
    """``build_report`` (``python -m torchrl_bail.study report``) keeps the metadata of each batch the study's collect
    jobs made (found in the data dir by the recipe its config composes to) and every finished run of the work dir,
    then rebuilds the report from the kept files alone: the same report with the work dir and the data dir gone."""
    import shutil

    from hydra import compose, initialize_config_dir

    from torchrl_bail.configuration.config_builders import collection_config
    from torchrl_bail.configuration.hydra_setup import config_dir
    from torchrl_bail.data.cache import batch_path
    from torchrl_bail.study import reports

    monkeypatch.setattr(tables, "BOOTSTRAP_REPS", 300)
    monkeypatch.setattr(reports, "report_runs", lambda *a, **k: [])  # torchrl_bail.report's own tables: not here
    study = load_study("paper_batches")
    headline, results, work, data = (tmp_path / d for d in ("paper_hopper", "paper_batches", "work", "data"))
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        entry = batch_path(collection_config(compose("config", overrides=["+exp=walker_ddpg05", f"data_dir={data}"])))
    entry.mkdir(parents=True)
    fake_batch(headline, "hopper_ddpg05_b1", "abcd1234", HEADLINE_RUNS, HEADLINE_META)
    fake_batch(tmp_path / "made", "walker_ddpg05_b1", entry.name.rsplit("-", 1)[1], WALKER_RUNS, None)
    work.mkdir()
    (tmp_path / "made" / "runs").rename(work / "outputs")  # the runs as the study's run left them
    (entry / "metadata.json").write_text(json.dumps(WALKER_META))
    written = reports.build_report(study, work, results, data, headline=headline)
    assert json.loads((results / "batches" / f"{entry.name}.metadata.json").read_text()) == WALKER_META
    assert len(list((results / "runs" / "walker_ddpg05_b1").glob("*/*/summary.json"))) == 7
    assert {results / "cross_batch.md", results / "curves.md", results / "curves_walker_ddpg05_b1.png"} <= set(written)
    first = (results / "cross_batch.md").read_text()
    assert "| walker_ddpg05_b1 | 400.0 | 1500.0 | 1.0 h | 1100.0 ± 79.1 |" in first
    shutil.rmtree(work)
    shutil.rmtree(data)
    reports.build_report(study, tmp_path / "another", results, tmp_path / "no data", headline=headline)
    assert (results / "cross_batch.md").read_text() == first


def test_gather_keeps_the_paper_scale_policies_and_never_a_checkpoint(tmp_path):
    """A paper-scale study keeps each finished run's ``policy.pt`` beside its summary (what ``torchrl_bail.ope``
    scores later); the 50k study keeps none; neither keeps a checkpoint."""
    run = tmp_path / "work" / "outputs" / "walker_ddpg05_b1" / "bail" / "seed1"
    (run / "logs").mkdir(parents=True)
    for name, text in (("summary.json", "{}"), ("config.yaml", "seed: 1\n"), ("policy.pt", "weights"),
                       ("checkpoint.pt", "state")):
        (run / name).write_text(text)
    for policies, results in ((True, tmp_path / "paper"), (False, tmp_path / "study")):
        (kept,) = gather(tmp_path / "work", results, policies=policies)
        assert sorted(p.name for p in kept.iterdir()) == sorted(
            ["summary.json", "config.yaml", "logs", *(["policy.pt"] if policies else [])])


# ---------------------------------------------------------------------------------------------------------------
# the execution-batch report (paper_exec): supp. Table 2's rows from a fake results tree
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


def _exec_tree(root: Path) -> Path:
    results = root / "paper_exec"
    for label, (runs, meta) in EXEC_RUNS.items():
        fake_batch(results, label, (meta or {}).get("recipe_hash", "feed0003"), runs, meta)
    return results


@pytest.fixture(scope="module")
def exec_table(tmp_path_factory):
    results = _exec_tree(tmp_path_factory.mktemp("exec"))
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(tables, "BOOTSTRAP_REPS", 300)
        out = exec_table_report(results)
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


def test_the_table2_claims_follow_the_paper_cells_rule(exec_table):
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
    assert bc["verdict"] == claim_verdict(cells["bc"], reference_row(3000.0), "similar")


def test_the_table2_rankings_read_wins_and_orderings_against_the_papers(exec_table):
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
def test_the_most_wins_verdict_names_who_wins_the_most_rows(monkeypatch, winner, verdict):
    monkeypatch.setattr(tables, "BOOTSTRAP_REPS", 200)
    batches = []
    for env, kind in exec_batches():
        if kind == "sac":
            continue
        levels = {"bail": 100.0, "bcq": 100.0, "bc": 100.0, "marwil": 100.0, winner: 500.0}
        batches.append({"batch": f"{env}_{kind}_b1", "env": env, "kind": kind, "metadata": None,
                        "paper": PAPER_TABLE2[(env, kind, 1)],
                        "cells": {a: _ranked_cell([x - 1.0, x, x + 1.0]) for a, x in levels.items()}})
    rankings = exec_rankings(batches)
    assert rankings["most_wins_verdict"] == verdict
    # BAIL and BCQ level on every batch (a run of each on both sides of the other): no difference shown
    assert rankings["average_verdict"].startswith("holds (P(BAIL > BCQ) = 0.50 [") != (winner == "bail")


def test_supp_table_2_is_transcribed_whole():
    """40 rows (5 envs x 4 kinds x B1/B2), five columns each; spot checks of rows the report reads and the
    summary supp. E gives (BC and MARWIL win the most rows; BAIL's mean above BCQ's over the 40)."""
    table = PAPER_TABLE2
    assert len(table) == 40 and {len(row) for row in table.values()} == {5}
    assert {env for env, _, _ in table} == {"hopper", "walker", "halfcheetah", "ant", "humanoid"}
    assert table[("hopper", "med_stoch", 1)] == {"bail": (375, 52), "bcq": (881, 155), "bear": (0, 0),
                                                 "bc": (1026, 0), "marwil": (1026, 0)}
    assert table[("walker", "opt_stoch", 1)]["bcq"] == (3386, 196) and table[("humanoid", "opt_det", 1)][
        "marwil"] == (5503, 1)
    wins = {a: sum(a in paper_winners(row, PAPER_TABLE2_COLUMNS) for row in table.values())
            for a in PAPER_TABLE2_COLUMNS}
    assert max(wins, key=wins.get) in ("bc", "marwil") and wins["bc"] == wins["marwil"] > wins["bcq"] > wins["bail"]
    means = {a: sum(row[a][0] for row in table.values()) / 40 for a in ("bail", "bcq")}
    assert means["bail"] > means["bcq"]


def test_the_table2_report_is_the_same_bytes_twice_and_all_pending_with_no_runs(tmp_path, monkeypatch):
    monkeypatch.setattr(tables, "BOOTSTRAP_REPS", 300)
    results = _exec_tree(tmp_path)
    exec_table_report(results)
    first = {p.name: p.read_bytes() for p in results.iterdir() if p.is_file()}
    exec_table_report(results)
    assert {p.name: p.read_bytes() for p in results.iterdir() if p.is_file()} == first
    assert {"table2.md", "table2.json", "curves_hopper_opt_det_b1.png"} <= set(first)
    empty = exec_table_report(tmp_path / "none")
    text = (tmp_path / "none" / "table2.md").read_text()
    assert empty["complete_batches"] == [] and "0 of 10" in empty["status"] and "none yet" in text
    assert all(c["verdict"].startswith("pending") for c in empty["claims"])
    assert "| BAIL ≈ BCQ on average" in text and "| BC | MARWIL |\n" in text and "| BEAR |\n" not in text


def _batch(name: str, **cells: list[float]) -> dict:
    """A cross-batch report's batch entry with only what the aggregate reads: per algorithm its normalised (and, the
    same, raw) final returns."""
    return {"batch": name, "metadata": {"episode_return_min": 0.0, "episode_return_max": 1.0},
            "cells": {algo: {"seeds": len(xs), "per_seed_normalised": xs, "per_seed": xs}
                      for algo, xs in cells.items()}}


def test_the_probability_of_improvement_over_batches_that_disagree_has_the_width_of_their_disagreement():
    """Four batches, BAIL above BCQ on three (every BAIL run above every BCQ run) and below on one: the aggregate is
    0.75. Over seeds alone its interval is the point [0.75, 0.75] (clean batches give 1 or 0 whatever seeds are
    drawn); the hierarchical bootstrap draws the batches too, so the interval spans what four batches drawn from
    these could give, and the reading is no difference shown. The per-batch values show the split."""
    up, down = ([0.6, 0.7, 0.8], [0.2, 0.3, 0.4]), ([0.2, 0.3, 0.4], [0.6, 0.7, 0.8])

    def pair(batches):
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(tables, "BOOTSTRAP_REPS", 500)
            out = cross_batch_aggregate(batches)
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


def test_the_iqm_over_batches_at_different_levels_is_as_wide_as_their_spread():
    """BAIL's seeds agree closely within each batch, but the batches sit at 0.2, 0.4, 0.6 and 0.8: over seeds alone
    the IQM's interval is narrow (±0.01 or so); drawing the batches too, it spans most of 0.2 to 0.8."""
    levels = (0.2, 0.4, 0.6, 0.8)
    batches = [_batch(f"b{i}", bail=[x - 0.01, x, x + 0.01]) for i, x in enumerate(levels, 1)]
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(tables, "BOOTSTRAP_REPS", 500)
        bail = cross_batch_aggregate(batches)["iqm"]["bail"]
    assert bail["iqm"] == pytest.approx(0.5) and bail["n_batches"] == 4
    assert bail["seeds_only"][1] - bail["seeds_only"][0] < 0.05
    assert bail["ci_low"] < 0.35 and bail["ci_high"] > 0.65


def test_the_hierarchical_bootstrap_draws_the_batches_once_for_both_sides_of_a_comparison():
    """A comparison stays within a batch: the batches drawn are the same for both algorithms. Here every batch has
    BAIL above BCQ but at levels far apart, so P(BAIL > BCQ) is 1 in every replication; drawing each side's batches
    apart would set one batch's BAIL against another's BCQ and give less. With one batch it is the bootstrap over
    seeds alone."""
    from rliable import metrics

    x = np.array([[10.0, 100.0, 1000.0], [11.0, 101.0, 1001.0], [12.0, 102.0, 1002.0]])
    y = x - 5.0
    assert hierarchical_interval([x, y], metrics.probability_of_improvement, reps=500) == (1.0, 1.0, 1.0)
    point, low, high = hierarchical_interval([x[:, :1]], metrics.aggregate_iqm, reps=500)
    assert point == pytest.approx(11.0) and 10.0 <= low < 11.0 < high <= 12.0
    with pytest.raises(ValueError, match="same batches"):
        hierarchical_interval([x, y[:, :2]], metrics.probability_of_improvement)


def test_the_aggregate_figure_puts_each_batch_beside_the_interval(cross_batch):
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
        patch.setattr(tables, "BOOTSTRAP_REPS", 200)
        aggregate = cross_batch_aggregate(batches)
    left, right = cross_batch_aggregate_figure(batches, aggregate).axes
    assert [t.get_text() for t in left.get_yticklabels()] == ["bail", "bcq"]

    def markers(ax) -> list[tuple[float, int]]:
        return sorted((round(float(line.get_xdata()[0]), 9), int(line.get_ydata()[0])) for line in ax.get_lines()
                      if line.get_linestyle() == "None" and line.get_marker() in BATCH_MARKERS)

    iqm = [round(float(metrics.aggregate_iqm(np.array(b["cells"][algo]["per_seed_normalised"]))), 9)
           for algo in ("bail", "bcq") for b in batches[:2]]  # b3's BAIL has 2 seeds: not entered
    assert markers(left) == sorted([(iqm[0], 0), (iqm[1], 0), (iqm[2], 1), (iqm[3], 1), (0.1, 1)])
    assert iqm[0] != round(float(np.mean(batches[0]["cells"]["bail"]["per_seed_normalised"])), 9)
    poi = next(p for p in aggregate["probability_of_improvement"] if (p["a"], p["b"]) == ("bail", "bcq"))
    assert markers(right) == sorted((round(v, 9), 0) for v in poi["per_batch"].values()) and len(poi["per_batch"]) == 2


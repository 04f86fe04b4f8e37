"""``python -m torchrl_bail.study``: studies declared as data, run step by step through Hydra launchers, resumed, and
followed (``status``). The same tiny study on a real Slurm: tests/test_slurm.py."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
import yaml
from _study import run_study, summaries, tiny_study

from torchrl_bail.study import StudyError, load_study
from torchrl_bail.study.__main__ import main as study_main

ROOT = Path(__file__).resolve().parents[1]


def test_the_declared_studies_are_the_campaigns_job_lists():
    """paper_exec and paper_batches declared as data give, job for job and in order, the queues results/run_study.py
    runs (the campaign can switch to the study command at a job boundary: same names, same overrides, same run
    directories)."""
    sys.path.insert(0, str(ROOT / "results"))
    try:
        import run_study
    finally:
        sys.path.remove(str(ROOT / "results"))
    for name in ("paper_exec", "paper_batches"):
        declared = [(j.name, j.module, sorted(j.args)) for j in load_study(name).jobs]
        assert declared == [(j.name, j.module, sorted(j.args)) for j in run_study.STUDIES[name]()], name


def test_a_cells_grid_runs_its_first_key_outermost_and_a_schedule_sets_only_the_actor_critics_length():
    study = load_study("paper_exec")
    trainings = study.steps[1].jobs
    assert [j.name for j in trainings[:5]] == ["hopper_sac_b1/bail/seed1", "hopper_sac_b1/bc/seed1",
                                                "hopper_sac_b1/marwil/seed1", "hopper_sac_b1/bcq/seed1",
                                                "hopper_med_det_b1/bail/seed1"]
    assert {j.name.rsplit("seed", 1)[1] for j in trainings[:20]} == {"1"}
    by_name = {j.name: j for j in trainings}
    assert "algo.epochs=10" in by_name["hopper_sac_b1/bcq/seed2"].args  # 10^5 updates of 100
    assert not any(a.startswith("algo.epochs") for a in by_name["hopper_sac_b1/bail/seed2"].args)


@pytest.mark.parametrize("change, message", [
    ({"colour": "blue"}, "unknown key 'colour'"),
    ({"steps": [{"name": "x", "command": "evaluate", "cells": []}]}, "command 'evaluate' is not one of"),
    ({"steps": [{"name": "x", "command": "train", "cells": [
        {"grid": {"batch": ["hopper_ddpg05_b1"], "algo": ["bial"], "seed": [1]}}]}]}, "unknown algorithm 'bial'"),
    ({"steps": [{"name": "x", "command": "collect", "cells": [{"grid": {"batch": ["hopper_ddpg05"]}}]}]},
     "expected a batch label"),
    ({"steps": [{"name": "x", "command": "collect", "cells": [{"grid": {"batch": ["hopper_ddpg05_b1"]}},
                                                                {"grid": {"batch": ["hopper_ddpg05_b1"]}}]}]},
     "declared twice"),
    ({"steps": [{"name": "x", "command": "train", "cells": [{"grid": {"batch": ["hopper_ddpg05_b1"]}}]}]},
     "names 'batch', 'algo' and 'seed'"),
])
def test_a_malformed_study_is_refused_with_where_and_what(tmp_path, change, message, capsys):
    path = tiny_study(tmp_path / "bad.yaml")
    spec = yaml.safe_load(path.read_text())
    spec.update(change)
    path.write_text(yaml.safe_dump(spec))
    with pytest.raises(StudyError, match=message):
        load_study(path)
    assert study_main(["list", str(path)]) == 2
    assert message.split("'")[0] in capsys.readouterr().err


def test_a_study_runs_resumes_and_equals_the_same_jobs_on_joblib(tmp_path):
    """The tiny study through the basic launcher (one job after another), then again (nothing is left: no job
    runs), then through joblib with two workers in another work dir: the same runs, summary for summary; ``status``
    says every job is done, and ``report`` gathers the 8 runs and writes the same table from either work dir."""
    study = tiny_study(tmp_path / "tiny.yaml")
    data = tmp_path / "data"
    first = run_study("run", str(study), "--workdir", str(tmp_path / "basic"), "--data-dir", str(data))
    assert first.returncode == 0, first.stderr[-3000:]
    assert "step 2 (trainings): 0 of 8 jobs done, launching 8" in first.stdout
    again = run_study("run", str(study), "--workdir", str(tmp_path / "basic"), "--data-dir", str(data))
    assert again.returncode == 0 and "step 1 (batches): 2 of 2 jobs done, launching 0" in again.stdout
    assert "step 2 (trainings): 8 of 8 jobs done, launching 0" in again.stdout
    joblib = run_study("run", str(study), "--workdir", str(tmp_path / "joblib"), "--data-dir", str(data),
                       "hydra/launcher=joblib", "hydra.launcher.n_jobs=2")
    assert joblib.returncode == 0, joblib.stderr[-3000:]
    basic_runs, joblib_runs = summaries(tmp_path / "basic" / "outputs"), summaries(tmp_path / "joblib" / "outputs")
    assert len(basic_runs) == 8 and basic_runs == joblib_runs
    status = run_study("status", str(study), "--workdir", str(tmp_path / "basic"), "--data-dir", str(data))
    assert status.stdout.splitlines()[-1] == "10 done, 0 running, 0 left of 10 jobs", status.stdout
    for launcher in ("basic", "joblib"):
        report = run_study("report", str(study), "--workdir", str(tmp_path / launcher), "--data-dir", str(data),
                           "--results", str(tmp_path / f"results_{launcher}"))
        assert report.returncode == 0, report.stderr[-3000:]
    tables = [(tmp_path / f"results_{launcher}" / "study.md").read_text() for launcher in ("basic", "joblib")]
    assert tables[0] == tables[1] and "| hopper_ddpg05_b2 |" in tables[0]
    assert len(list((tmp_path / "results_basic" / "runs").glob("*/*/*/summary.json"))) == 8


def test_a_study_stopped_by_sigterm_mid_job_resumes_where_it_stopped(tmp_path):
    """SIGTERM to the study command (its process alone) while a training job is past update 2000 of 20000: the
    command passes it on, the job checkpoints, and the command ends with exit code 143; ``status`` shows the job
    left with its progress; running the study again resumes the job from its checkpoint and it ends as an
    uninterrupted run of the same job."""
    study = tiny_study(tmp_path / "tiny.yaml", ["algo.epochs=20", "eval.every_epochs=1",
                                                  "checkpoint.every_minutes=null", "algo.policy.hidden=[16,16]"],
                       seeds=(1,), algos=("bc",))
    spec = yaml.safe_load(study.read_text())
    spec["steps"][1]["cells"][0]["grid"]["batch"] = ["hopper_ddpg05_b1"]
    study.write_text(yaml.safe_dump(spec))
    data, stopped, reference = tmp_path / "data", tmp_path / "stopped", tmp_path / "reference"
    proc = subprocess.Popen([sys.executable, "-m", "torchrl_bail.study", "run", str(study), "--workdir",
                             str(stopped), "--data-dir", str(data)], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    deadline = time.monotonic() + 300
    while True:
        checkpoints = list((stopped / "outputs").rglob("checkpoint.pt")) if (stopped / "outputs").is_dir() else []
        if checkpoints and torch.load(checkpoints[0], map_location="cpu",
                                      weights_only=False)["iteration"] >= 2000:
            break
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.2)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 143 and "stopped by SIGTERM in step 2" in err, err[-3000:]
    assert f"continue with: python -m torchrl_bail.study run {study} --workdir {stopped}" in err  # not the step's
    iteration = torch.load(checkpoints[0], map_location="cpu", weights_only=False)["iteration"]
    assert 2000 <= iteration < 20000
    status = run_study("status", str(study), "--workdir", str(stopped), "--data-dir", str(data))
    assert f"hopper_ddpg05_b1/bc/seed1  left ({iteration}/20000 updates" in status.stdout, status.stdout
    resumed = run_study("run", str(study), "--workdir", str(stopped), "--data-dir", str(data))
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert run_study("run", str(study), "--workdir", str(reference), "--data-dir", str(data)).returncode == 0
    (run, summary), = summaries(stopped / "outputs").items()
    assert json.loads((stopped / "outputs" / run / "summary.json").read_text())["resumed_from_iteration"] == [
        iteration]
    assert summaries(reference / "outputs") == {run: summary}

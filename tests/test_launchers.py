"""Launcher configs compose, side-by-side joblib jobs split the cores instead of oversubscribing them, and a joblib
sweep runs its jobs in other processes."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
from _contract import ALGO_CASES, TINY_RUN
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from torchrl_bail import config_dir
from torchrl_bail.cli import job_threads


def _compose(*overrides):
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        return compose("config", overrides=["+exp=hopper_ddpg05", *overrides], return_hydra_config=True)


def test_joblib_jobs_share_the_cores():
    pytest.importorskip("hydra_plugins.hydra_joblib_launcher")
    assert _compose().threads == 1  # the default: one thread per job, whatever the launcher
    cfg = _compose("hydra/launcher=joblib", "hydra.launcher.n_jobs=2", "threads=null")
    launcher = cfg.hydra.launcher
    assert job_threads(_compose("hydra/launcher=joblib", "hydra.launcher.n_jobs=2"), launcher) == 1
    assert "JoblibLauncher" in launcher._target_
    cores = len(os.sched_getaffinity(0))
    assert job_threads(cfg, launcher) == max(1, cores // 2)
    assert job_threads(cfg, OmegaConf.merge(launcher, {"n_jobs": 4 * cores})) == 1  # never 0
    assert job_threads(cfg, OmegaConf.merge(launcher, {"n_jobs": -1})) == 1  # one job per core
    assert job_threads(OmegaConf.create({"threads": 3}), launcher) == 3  # an explicit key wins
    assert job_threads(cfg, _compose().hydra.launcher) is None  # threads=null, basic launcher: torch's default


def test_the_joblib_launcher_runs_two_jobs_by_default_without_hydras_schema_warning():
    """``hydra/launcher=joblib`` is the project's ConfigStore node over the plugin's (2 jobs, not the plugin's 10), so
    no yaml file shares the plugin's schema name, which Hydra warned about on every composition (8 times a sweep)."""
    pytest.importorskip("hydra_plugins.hydra_joblib_launcher")
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # Hydra's "validated against ConfigStore schema" is a UserWarning
        launcher = _compose("hydra/launcher=joblib").hydra.launcher
    assert launcher.n_jobs == 2 and "JoblibLauncher" in launcher._target_
    assert not (config_dir() / "hydra" / "launcher" / "joblib.yaml").exists()


def test_slurm_gpu_launcher_asks_for_one_gpu():
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    launcher = _compose("hydra/launcher=slurm_gpu").hydra.launcher
    assert launcher.gpus_per_node == 1 and "SlurmLauncher" in launcher._target_
    assert launcher.timeout_min == _compose("hydra/launcher=slurm").hydra.launcher.timeout_min  # the rest as slurm


def test_a_joblib_sweep_trains_its_jobs_in_worker_processes(tiny_run_data_dir, tmp_path):
    """The joblib launcher ships each job's config to a worker with cloudpickle; the schemas, read from their
    modules without importing them, must arrive as the registered classes (they failed every job with a
    StopIteration at the worker's config check until the command line imported their modules first)."""
    pytest.importorskip("hydra_plugins.hydra_joblib_launcher")
    cmd = [sys.executable, "-m", "torchrl_bail.train", "-m", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2",
           *TINY_RUN, f"data_dir={tiny_run_data_dir}", "algo=bc", *ALGO_CASES["bc"].cli, "seed=1,2",
           f"hydra.sweep.dir={tmp_path}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr[-3000:]
    summaries = sorted(tmp_path.rglob("summary.json"))
    assert [json.loads(p.read_text())["seed"] for p in summaries] == [1, 2]

"""End to end through the command line, on a tiny batch the project generates itself."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from _contract import ALGO_CASES
from _summaries import comparable

TINY = [
    "+exp=hopper_ddpg05", "preset=quick",
    "batch.steps=1500", "batch.start_steps=300", "batch.agent.actor_hidden=[32,32]",
    "batch.agent.critic_hidden=[32,32]", "env.max_episode_steps=200",
    "eval.episodes=2", "eval.max_steps=200", "eval.every_epochs=0.002", "samples_per_epoch=1000000",
    "returns.horizon=200", "progress=false",
]
REPO = Path(__file__).resolve().parents[1]
#: each algorithm's tiny run: the contract's (tests/_contract.py), except BAIL's (an envelope fitted well enough for
#: the selection and ablation checks below) and BC's (5 evaluations, tests/test_policy.py)
ALGO_TINY = {**{name: list(case.cli) for name, case in ALGO_CASES.items()},
             "bail": ["algo.epochs=0.01", "algo.envelope.epochs=5", "algo.envelope.batch_size=100"],
             "bc": ["algo.epochs=0.01"]}


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("batches")


def _train(run_dir, data_dir, *overrides, check=True):
    cmd = [sys.executable, "-m", "torchrl_bail.train", *TINY, f"data_dir={data_dir}",
           f"hydra.run.dir={run_dir}", *overrides]
    env = {**os.environ, "RL_WARNINGS": "0", "HYDRA_FULL_ERROR": "1"}
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    if check:
        assert proc.returncode == 0, proc.stderr[-4000:]
    return proc


def _summary(run_dir) -> dict:
    return json.loads((run_dir / "summary.json").read_text())


def test_bail_end_to_end_writes_every_artifact(tmp_path, data_dir):
    run_dir = tmp_path / "run"
    _train(run_dir, data_dir, "seed=1", *ALGO_TINY["bail"])
    s = _summary(run_dir)
    for key in ("algo", "env", "batch", "batch_index", "seed", "final_return", "best_return",
                "dataset_mean_episode_return", "envelope_fraction_below", "selected_fraction",
                "num_transitions", "wall_time_s"):
        assert key in s, key
    assert (s["algo"], s["env"], s["batch_index"], s["seed"], s["num_transitions"]) == ("bail", "Hopper-v5", 1, 1, 1500)
    # one torch thread by default (conf/config.yaml: threads), said among the run's first lines and kept
    assert s["torch_threads"] == 1
    assert "torch threads: 1 (threads=1)" in "\n".join((run_dir / "train.log").read_text().splitlines()[:3])
    assert 0.29 <= s["selected_fraction"] <= 0.32
    for name in ("config.yaml", "learning_curve.png", "envelope.png", "summary.json", "policy.pt",
                 "checkpoint.pt"):
        assert (run_dir / name).stat().st_size > 0, name
    assert (run_dir / "logs" / "scalars" / "eval" / "return.csv").exists()
    # Getting started's table of what a run writes names every entry of the run dir, and each entry it names exists
    section = (REPO / "docs" / "getting-started.md").read_text().split("## What a run writes")[1]
    table = next(block for block in section.split("\n\n") if block.startswith("| file |"))
    named = [path for line in table.splitlines()[2:] for path in re.findall(r"`([^`]+)`", line.split(" | ")[0])]
    for entry in run_dir.iterdir():
        assert any(path.split("/")[0] == entry.name for path in named), f"{entry.name} is not in Getting started"
    for path in named:
        if "{" in path:  # logs/scalars/{eval,train,envelope,selection}/*.csv: the folders a BAIL run writes
            folder, options = re.match(r"(.*)/\{(.*)\}/", path).groups()
            assert {p.name for p in (run_dir / folder).iterdir()} <= set(options.split(",")), path
        else:
            assert (run_dir / path.rstrip("/")).exists(), f"Getting started names {path}, which the run lacks"


@pytest.mark.parametrize("algo", ["bail", "bcq"])
def test_same_seed_gives_the_same_summary_whether_the_batch_was_collected_or_cached(tmp_path, algo):
    """Collection re-seeds the global generators with the behaviour seed; training must not notice."""
    fresh = tmp_path / "fresh"  # run a collects the batch, run b loads it from the cache
    a, b = tmp_path / "a", tmp_path / "b"
    _train(a, fresh, "seed=3", "batch.steps=600", "batch.start_steps=200", f"algo={algo}", *ALGO_TINY[algo])
    _train(b, fresh, "seed=3", "batch.steps=600", "batch.start_steps=200", f"algo={algo}", *ALGO_TINY[algo])
    assert comparable(_summary(a)) == comparable(_summary(b))


@pytest.mark.parametrize("algo", [name for name in ALGO_CASES if name != "bail"])  # BAIL: the tests above
def test_every_algo_runs_from_the_cli(tmp_path, data_dir, algo):
    run_dir = tmp_path / algo
    _train(run_dir, data_dir, f"algo={algo}", *ALGO_TINY[algo])
    s = _summary(run_dir)
    assert s["algo"] == algo and s["final_return"] == s["final_return"]  # not NaN


def test_config_error_is_one_clear_line(tmp_path, data_dir):
    proc = _train(tmp_path / "bad", data_dir, "returns.augment=magic", check=False)
    assert proc.returncode != 0
    assert "returns.augment" in proc.stderr and "Traceback" not in proc.stderr


@pytest.mark.parametrize("ablation", ["oracle", "by_return", "plain_regression"])
def test_ablations_are_config_switches(tmp_path, data_dir, ablation):
    """Supp D.1-D.3: oracle returns, top-p by return without an envelope, ordinary regression (K = 1)."""
    switches = {
        "oracle": ["returns.augment=oracle", "batch.oracle.enabled=true", "batch.oracle.horizon=300",
                   "batch.oracle.keep=200"],
        "by_return": ["algo.selection.by=return"],
        "plain_regression": ["algo.envelope.penalty=1"],
    }[ablation]
    run_dir = tmp_path / ablation
    _train(run_dir, data_dir, "seed=1", *ALGO_TINY["bail"], *switches)
    s = _summary(run_dir)
    assert 0.29 <= s["selected_fraction"] <= 0.32
    if ablation == "oracle":
        assert s["returns_augment"] == "oracle" and s["batch"] == "hopper_ddpg05_oracle_b1"
    elif ablation == "by_return":
        assert s["envelope_fraction_below"] is None and not (run_dir / "envelope.png").exists()
    else:  # a least-squares fit sits in the middle of the returns: far from an upper envelope
        assert s["envelope_fraction_below"] > 0.2


def test_comparable_summaries_differ_in_any_result_and_in_nothing_else():
    """What the same-seed checks compare (tests/_summaries.py): every key but the run's wall time, paths, resume
    points and the checkout's commit; any result that differs still shows."""
    summary = {"final_return": 1.5, "selected_fraction": 0.3, "wall_time_s": 12.0, "run_dir": "/a", "batch_path": "/b",
               "resumed_from_iteration": [], "platform": {"cpu": "x", "source": {"commit": "abc", "modified": False}}}
    again = {**summary, "wall_time_s": 99.0, "run_dir": "/c", "batch_path": "/d", "resumed_from_iteration": [5],
             "platform": {"cpu": "x", "source": {"commit": "def", "modified": True}}}
    assert comparable(summary) == comparable(again) == {"final_return": 1.5, "selected_fraction": 0.3,
                                                         "platform": {"cpu": "x"}}
    assert comparable({**again, "final_return": 1.25}) != comparable(summary)
    assert comparable({**again, "platform": {"cpu": "y", "source": {}}}) != comparable(summary)

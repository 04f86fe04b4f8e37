"""A tiny study and the helpers that run it and read its runs (tests/test_study.py, tests/test_slurm.py)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import yaml
from _contract import TINY_RUN
from _summaries import comparable

ROOT = Path(__file__).resolve().parents[1]
#: the tiny batches' recipe and evaluation (tests/_contract.py's TINY_RUN less its experiment)
EVERY_JOB = [arg for arg in TINY_RUN if not arg.startswith("+exp=")]
TINY_TRAINING = ["algo.epochs=0.005", "algo.policy.hidden=[16,16]"]


def tiny_study(path: Path, trainings: list[str] = TINY_TRAINING, seeds=(1, 2), algos=("bc", "bail")) -> Path:
    """A 2 batches x 2 algorithms x 2 seeds study of tiny runs, written to ``path``."""
    batches = ["hopper_ddpg05_b1", "hopper_ddpg05_b2"]
    path.write_text(yaml.safe_dump({
        "description": "a tiny study of the tests", "results": str(path.parent / "results"), "report": None,
        "every_job": EVERY_JOB,
        "steps": [{"name": "batches", "command": "collect", "cells": [{"grid": {"batch": batches}}]},
                  {"name": "trainings", "command": "train",
                   "cells": [{"grid": {"seed": list(seeds), "batch": batches, "algo": list(algos)},
                              "overrides": trainings}]}],
    }, sort_keys=False))
    return path


def run_study(*args: str, env: dict[str, str] | None = None, timeout: float = 600) -> subprocess.CompletedProcess:
    """``python -m torchrl_bail.study <args>``, one torch thread a job."""
    return subprocess.run([sys.executable, "-m", "torchrl_bail.study", *args], cwd=ROOT, capture_output=True,
                          text=True, env={**(env or os.environ), "OMP_NUM_THREADS": "1"}, timeout=timeout)


def summaries(outputs: Path) -> dict[str, dict]:
    """Every training run's comparable summary under ``outputs``, by its directory relative to ``outputs``."""
    return {p.parent.relative_to(outputs).as_posix(): comparable(json.loads(p.read_text()))
            for p in sorted(outputs.rglob("summary.json"))}

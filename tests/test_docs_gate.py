"""The docs step of ``.ci/run`` fails on a broken link and a broken anchor (run as ``.ci/run`` writes it)."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def ci_docs_command() -> str:
    """The one line of ``.ci/run`` that builds the docs site."""
    lines = [line for line in (ROOT / ".ci" / "run").read_text().splitlines() if "mkdocs build" in line]
    assert len(lines) == 1, lines
    return lines[0]


def test_the_ci_docs_step_counts_warnings():
    assert "--strict" in ci_docs_command() and not re.search(r"--quiet|\s-q\b", ci_docs_command())


@pytest.mark.skipif(shutil.which("mkdocs") is None, reason="the docs extra is not installed")
def test_the_ci_docs_step_fails_on_a_planted_broken_link_and_anchor(tmp_path):
    for name in ("docs", "src", "results", "conf"):
        shutil.copytree(ROOT / name, tmp_path / name, ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    for name in ("mkdocs.yml", "README.md", "pyproject.toml"):
        shutil.copy2(ROOT / name, tmp_path / name)
    index = tmp_path / "docs" / "index.md"
    index.write_text(index.read_text() + "\n[gone](no-such-page.md) and [lost](concepts.md#no-such-anchor)\n")
    done = subprocess.run(["bash", "-c", ci_docs_command()], cwd=tmp_path, capture_output=True, text=True,
                          timeout=600, env=dict(os.environ, PYTHONPATH=str(tmp_path / "src")))
    output = done.stdout + done.stderr
    assert done.returncode != 0, output
    assert "no-such-page.md" in output and "no-such-anchor" in output

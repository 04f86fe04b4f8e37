"""The examples of the docs page "The losses in your own code" run as written (each block in a fresh namespace)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

PAGE = Path(__file__).resolve().parents[1] / "docs" / "guides" / "losses-in-your-own-code.md"


def _blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", PAGE.read_text(), flags=re.DOTALL)


def test_the_section_has_its_examples():
    blocks = _blocks()
    assert len(blocks) >= 3 and any("GymEnv" in block and "BCLoss" in block for block in blocks)


@pytest.mark.parametrize("index", range(len(_blocks())))
def test_example_runs(index, capsys):
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        exec(compile(_blocks()[index], f"{PAGE.name} example {index + 1}", "exec"), {"__name__": "__readme__"})
    finally:
        torch.set_num_threads(threads)
    out = capsys.readouterr().out
    if "test return" in _blocks()[index]:
        assert re.search(r"kept \d+ of \d+ pairs; test return -?\d+\.\d", out), out


def test_the_readmes_results_table_is_the_studys_report():
    """The README's results table is a copy of rows of ``results/study/study.md`` (the report the runs make): a row
    changed by hand, or a report made again without updating the README, fails here."""
    root = Path(__file__).resolve().parents[1]
    readme = (root / "README.md").read_text().split("## Results", 1)[1]
    rows = re.findall(r"^\| (?:hopper|walker)_\w+ \|.*\|$", readme, flags=re.MULTILINE)
    report = (root / "results" / "study" / "study.md").read_text().splitlines()
    assert len(rows) == 10 and all(row in report for row in rows), [r for r in rows if r not in report]

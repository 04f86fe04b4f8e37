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

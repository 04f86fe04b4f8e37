"""Atomic writes never leave a half-written file (the report itself is tested in test_report.py)."""

from __future__ import annotations

import json

import pytest

from torchrl_bail.core.io import atomic_path, write_json_atomic


def test_interrupted_write_leaves_the_old_file_untouched(tmp_path):
    target = tmp_path / "summary.json"
    write_json_atomic(target, {"v": 1})
    with pytest.raises(KeyboardInterrupt):
        with atomic_path(target) as tmp:
            tmp.write_text('{"v": 2, "trunc')
            raise KeyboardInterrupt
    assert json.loads(target.read_text()) == {"v": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["summary.json"]

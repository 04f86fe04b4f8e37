"""Atomic writes never leave a half-written file; the report aggregates seeds into mean ± std."""

from __future__ import annotations

import json

import pytest

from torchrl_bail.io import atomic_path, write_json_atomic
from torchrl_bail.report import aggregate, format_table, main


def test_interrupted_write_leaves_the_old_file_untouched(tmp_path):
    target = tmp_path / "summary.json"
    write_json_atomic(target, {"v": 1})
    with pytest.raises(KeyboardInterrupt):
        with atomic_path(target) as tmp:
            tmp.write_text('{"v": 2, "trunc')
            raise KeyboardInterrupt
    assert json.loads(target.read_text()) == {"v": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["summary.json"]


def test_report_table_from_run_dirs(tmp_path, capsys):
    for algo, scores in {"bail": [300.0, 500.0], "bc": [200.0, 200.0, 260.0]}.items():
        for seed, score in enumerate(scores):
            write_json_atomic(tmp_path / f"{algo}{seed}" / "summary.json", {
                "algo": algo, "batch": "hopper_ddpg05_b1", "seed": seed, "final_return": score,
                "dataset_mean_episode_return": 150.0, "wall_time_s": 10.0})
    rows = aggregate([json.loads(p.read_text()) for p in tmp_path.rglob("summary.json")])
    assert [(r["algo"], r["mean"], r["seeds"]) for r in rows] == [("bail", 400.0, 2), ("bc", 220.0, 3)]
    assert rows[0]["std"] == 100.0
    assert "| hopper_ddpg05_b1 | bail | 400.0 ± 100.0 | 2 | 150.0 | 10 s |" in format_table(rows)
    assert main([str(tmp_path), "--out", str(tmp_path / "t.md"), "--plot", str(tmp_path / "t.png")]) == 0
    assert "bail" in capsys.readouterr().out and (tmp_path / "t.png").stat().st_size > 0


def test_report_errors(tmp_path, capsys):
    assert main([str(tmp_path / "missing")]) == 2
    assert main([str(tmp_path)]) == 1
    assert "no summary.json" in capsys.readouterr().err

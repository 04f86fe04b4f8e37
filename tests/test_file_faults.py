"""The file system as it really behaves: damaged files, a run directory that cannot be made, a disk that fills.

Each fault of a tiny BC run (in process, on the session's tiny batch) ends in one line naming the file and the
remedy with exit status 2, or recovers where that is safe: a damaged checkpoint is set aside and the run starts
over, a damaged summary of a finished run is set aside and written again from the finished checkpoint. A full disk
is a patched ``open`` in :mod:`torchrl_bail.core.io` whose writes stop, with ``ENOSPC``, once the disk's free bytes are
spent: it never leaves a checkpoint or a summary that loads but is not whole, and a rerun once space is free ends
where an undisturbed run ends.
"""

from __future__ import annotations

import builtins
import errno
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from _contract import ALGO_CASES, TINY_RUN
from _summaries import comparable
from hydra import compose, initialize_config_dir

import torchrl_bail.core.io as io_module
import torchrl_bail.training.trainer as trainer_module
from torchrl_bail import config_dir
from torchrl_bail.cli import exit_on_config_error
from torchrl_bail.train import run as train_run
from torchrl_bail.training.resume import ResumeError

REPO = Path(__file__).resolve().parents[1]
def run(cfg, run_dir: Path) -> dict:
    """The single-seed run's summary."""
    (summary,) = train_run(cfg, run_dir)
    return summary


def _cfg(data_dir, *overrides):
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        return compose("config", overrides=[*TINY_RUN, "algo=bc", *ALGO_CASES["bc"].cli, f"data_dir={data_dir}",
                                            *overrides])


def _result(summary: dict) -> dict:
    return comparable(summary)


def _summary(run_dir: Path) -> dict:
    return json.loads((run_dir / "summary.json").read_text())


def _one_line_exit(capsys, fn) -> str:
    """Runs ``fn`` as a command line does (:func:`exit_on_config_error`): it must end with status 2 and one line."""
    with pytest.raises(SystemExit) as stop, exit_on_config_error():
        fn()
    assert stop.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("torchrl_bail: "), lines
    return lines[0]


@pytest.fixture(scope="module")
def reference(tiny_run_data_dir, tmp_path_factory) -> dict:
    return _result(run(_cfg(tiny_run_data_dir), tmp_path_factory.mktemp("reference") / "run"))


# -- damaged files --------------------------------------------------------------------------------------------
def test_a_truncated_checkpoint_is_set_aside_and_the_run_starts_over(tiny_run_data_dir, tmp_path, reference, caplog):
    run_dir = tmp_path / "run"
    cfg = _cfg(tiny_run_data_dir)
    run(cfg, run_dir)
    (run_dir / "summary.json").unlink()  # an unfinished run ...
    whole = (run_dir / "checkpoint.pt").read_bytes()
    (run_dir / "checkpoint.pt").write_bytes(whole[: len(whole) // 2])  # ... whose checkpoint was cut short
    with pytest.raises(ResumeError, match=r"checkpoint\.pt is damaged and cannot be continued .*resume=false"):
        run(_cfg(tiny_run_data_dir, "resume=true"), run_dir)
    with caplog.at_level("WARNING", logger="torchrl_bail"):
        summary = run(cfg, run_dir)
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1 and "checkpoint.pt is damaged" in warnings[0]
    assert "set aside as checkpoint.pt.corrupt; the run starts over" in warnings[0]
    assert (run_dir / "checkpoint.pt.corrupt").read_bytes() == whole[: len(whole) // 2]
    assert _result(summary) == reference and summary["resumed_from_iteration"] == []


def test_an_invalid_summary_is_written_again_from_the_finished_checkpoint(tiny_run_data_dir, tmp_path, reference,
                                                                         caplog, monkeypatch):
    run_dir = tmp_path / "run"
    run(_cfg(tiny_run_data_dir), run_dir)
    (run_dir / "summary.json").write_text('{"algo": "bc", "final_ret')
    with caplog.at_level("WARNING", logger="torchrl_bail"):
        summary = run(_cfg(tiny_run_data_dir), run_dir)
    assert "summary.json is damaged (JSONDecodeError" in caplog.text and "summary.json.corrupt" in caplog.text
    assert _result(_summary(run_dir)) == _result(summary) == reference
    # without a checkpoint to write it from: one line, and the remedy
    run_dir = tmp_path / "unchecked"
    run(_cfg(tiny_run_data_dir, "checkpoint.enabled=false"), run_dir)
    (run_dir / "summary.json").write_text("[]")
    monkeypatch.setattr(trainer_module, "train", lambda *a, **k: pytest.fail("the run was trained again"))
    with pytest.raises(ResumeError, match=r"summary\.json is damaged .*train the run again with resume=false"):
        run(_cfg(tiny_run_data_dir, "checkpoint.enabled=false"), run_dir)


# -- a run directory that cannot be made ------------------------------------------------------------------------
def test_a_run_directory_that_cannot_be_made_is_one_line(tiny_run_data_dir, tmp_path, capsys, monkeypatch):
    # a file where the directory should be: the real command line, whose Hydra makes the directory first
    (tmp_path / "taken").write_text("")
    env = {**os.environ, "RL_WARNINGS": "0",
           "PYTHONPATH": os.pathsep.join([str(REPO / "src"), os.environ.get("PYTHONPATH", "")])}
    env.pop("HYDRA_FULL_ERROR", None)
    proc = subprocess.run([sys.executable, "-m", "torchrl_bail.train", *TINY_RUN, "algo=bc",
                           f"data_dir={tiny_run_data_dir}", f"hydra.run.dir={tmp_path / 'taken' / 'run'}"],
                          capture_output=True, text=True, env=env, timeout=300, cwd=tmp_path, check=False)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    (line,) = proc.stderr.strip().splitlines()
    assert str(tmp_path / "taken") in line and "choose another hydra.run.dir" in line
    # no permission (root ignores mode bits, so the refusal is patched in)
    refused = tmp_path / "locked" / "run"
    real_mkdir = Path.mkdir

    def mkdir(self, *args, **kwargs):
        if self == refused:
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(self))
        return real_mkdir(self, *args, **kwargs)

    monkeypatch.setattr(Path, "mkdir", mkdir)
    line = _one_line_exit(capsys, lambda: run(_cfg(tiny_run_data_dir), refused))
    assert f"cannot write {refused}: Permission denied" in line and "another hydra.run.dir" in line


# -- a disk that fills -----------------------------------------------------------------------------------------
class _Disk:
    """The free bytes of the disk every file written through :mod:`torchrl_bail.core.io` lands on: the write that
    exceeds them writes what fits, then fails with ``ENOSPC`` (as a full disk does). Records what was written."""

    def __init__(self, free: float) -> None:
        self.free = free
        self.written: list[tuple[str, int]] = []

    def open(self, file, mode="r", *args, **kwargs):
        handle = builtins.open(file, mode, *args, **kwargs)  # noqa: SIM115 - closed by its _FillingFile or caller
        return handle if "w" not in mode else _FillingFile(handle, self, Path(file).name)


class _FillingFile:
    def __init__(self, handle, disk: _Disk, name: str) -> None:
        self._handle, self._disk = handle, disk
        disk.written.append((name, 0))

    def write(self, data) -> int:
        data = memoryview(data).cast("B")
        name, size = self._disk.written[-1]
        if len(data) > self._disk.free:
            fits = int(self._disk.free)
            self._handle.write(data[:fits])
            self._disk.free = 0
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        self._disk.free -= len(data)
        self._disk.written[-1] = (name, size + len(data))
        return self._handle.write(data)

    def __getattr__(self, name):
        return getattr(self._handle, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self._handle.close()


def _final_name(temporary: str) -> str:
    """``.checkpoint.pt.abc123.tmp`` -> ``checkpoint.pt``."""
    return temporary[1:].rsplit(".", 2)[0]


def test_a_disk_that_fills_ends_in_one_line_leaves_nothing_half_written_and_resumes(
        tiny_run_data_dir, tmp_path, reference, capsys, monkeypatch):
    disk = _Disk(float("inf"))
    monkeypatch.setattr(io_module, "open", disk.open, raising=False)
    run(_cfg(tiny_run_data_dir), tmp_path / "measured")
    writes = [(_final_name(name), size) for name, size in disk.written]
    checkpoints = [i for i, (name, _) in enumerate(writes) if name == "checkpoint.pt"]
    assert len(checkpoints) >= 3 and writes[-1][0] == "summary.json"
    # the disk fills in the middle of the first checkpoint, of a later one, and of the summary (written last)
    for target in (checkpoints[0], checkpoints[2], len(writes) - 1):
        name = writes[target][0]
        run_dir = tmp_path / f"full_at_{target}"
        disk.free = sum(size for _, size in writes[:target]) + writes[target][1] // 2
        line = _one_line_exit(capsys, lambda run_dir=run_dir: run(_cfg(tiny_run_data_dir), run_dir))
        assert f"cannot write {run_dir / name}: No space left on device; free space on that disk" in line
        assert not [p.name for p in run_dir.iterdir() if p.name.startswith(".") and p.name != ".lock"]
        assert not (run_dir / "summary.json").exists()
        if target != checkpoints[0]:  # the checkpoint there is an earlier, whole one
            assert torch.load(run_dir / "checkpoint.pt", weights_only=False)["iteration"] >= 0
        else:
            assert not (run_dir / "checkpoint.pt").exists()
        disk.free = float("inf")  # space is freed: the same command ends where an undisturbed run ends
        assert _result(run(_cfg(tiny_run_data_dir), run_dir)) == reference


def test_a_full_disk_under_a_write_without_a_file_names_the_run_directory(tiny_run_data_dir, tmp_path, capsys,
                                                                         monkeypatch):
    def full(*args, **kwargs):  # e.g. a logger's own write, which reports no file
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(trainer_module, "train", full)  # the loop train.run drives
    line = _one_line_exit(capsys, lambda: run(_cfg(tiny_run_data_dir), tmp_path / "run"))
    assert f"cannot write {tmp_path / 'run'}: No space left on device" in line

"""``results/campaign.sh``, which keeps ``python -m torchrl_bail.study run`` going in the background and commits
what it makes: what it refuses and what ``stop`` reaches.

Its whole path (a worktree, the runner, the watcher's commit after each finished job) is the one the paper-scale
campaigns run on; these tests hold the parts that guard it, in seconds and with no job run."""

import subprocess
import sys
import time
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "results" / "campaign.sh"

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="campaign.sh runs on Linux (setsid, nproc, taskset)")


def _campaign(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", str(SCRIPT), *args], capture_output=True, text=True, timeout=60)


def _session(tmp_path: Path, name: str) -> subprocess.Popen:
    """A stand-in for the runner or watcher: a process leading its own session, with a child in it (a job)."""
    proc = subprocess.Popen(["bash", "-c", "sleep 120 & wait"], start_new_session=True)
    (tmp_path / f"{name}.pid").write_text(f"{proc.pid}\n")
    return proc


def _ended(pid: int, within: float = 10.0) -> bool:
    """Whether ``pid`` is gone or a zombie (killed, not yet reaped by whoever adopted it) within ``within`` s."""
    stat = Path(f"/proc/{pid}/stat")
    deadline = time.monotonic() + within
    while time.monotonic() < deadline:
        try:
            if stat.read_text().rsplit(")", 1)[1].split()[0] == "Z":
                return True
        except FileNotFoundError:
            return True
        time.sleep(0.05)
    return False


def test_without_a_command_it_prints_its_usage():
    done = _campaign()
    assert done.returncode == 2
    assert "campaign.sh start STUDY DIR" in done.stderr and "campaign.sh stop DIR" in done.stderr


def test_start_refuses_while_a_runner_of_the_dir_is_alive(tmp_path):
    """A second runner on the same work dir would run the same jobs twice and move the worktree under the first.
    (The study named is no study: were the refusal gone, ``start`` would stop at the study's check, not start one.)"""
    runner = _session(tmp_path, "runner")
    try:
        done = _campaign("start", "no_such_study", str(tmp_path))
        assert done.returncode == 1
        assert f"a runner of {tmp_path.resolve()} is alive (pid {runner.pid}); stop it first" in done.stderr
        assert not (tmp_path / "tree").exists() and not (tmp_path / "watcher.pid").exists()
    finally:
        runner.kill()
        runner.wait()


def test_stop_sends_the_runner_sigterm_and_ends_the_watchers_session(tmp_path):
    """The runner (``python -m torchrl_bail.study run``) gets SIGTERM, which it passes on to the running job, which
    checkpoints (tests/test_study.py); the watcher's whole session ends, a report under way included, so nothing
    commits after the stop."""
    runner, watcher = _session(tmp_path, "runner"), _session(tmp_path, "watcher")
    for _ in range(100):  # the watcher's child's start
        child = subprocess.run(["pgrep", "-s", str(watcher.pid), "sleep"], capture_output=True, text=True)
        if child.stdout.strip():
            break
        time.sleep(0.05)
    try:
        done = _campaign("stop", str(tmp_path))
        assert done.returncode == 0 and f"stopped {tmp_path.resolve()}" in done.stdout
        assert runner.wait(timeout=10) == -15 and watcher.wait(timeout=10) == -15
        [child_pid] = child.stdout.split()
        assert _ended(int(child_pid)), "the report under way in the watcher's session did not get the SIGTERM"
    finally:
        for proc in (runner, watcher):
            proc.kill()
            proc.wait()


@pytest.mark.slow
def test_the_watcher_commits_the_studys_results_alone_when_a_run_has_finished(tmp_path):
    """In a clone of this checkout: a finished run in the campaign's work dir (a kept run of the cross-batch study,
    copied there) and the runner ended make the watcher rebuild the study's report with the clone's code and commit
    ``results/paper_batches`` alone, named by the run; a file staged elsewhere stays uncommitted. (A minute or two:
    one report of the cross-batch study.)"""
    import shutil

    root = Path(__file__).resolve().parents[1]
    clone, campaign = tmp_path / "clone", tmp_path / "campaign"
    subprocess.run(["git", "clone", "-q", "--shared", str(root), str(clone)], check=True)
    for key, value in (("user.name", "test"), ("user.email", "test@example.com")):
        subprocess.run(["git", "-C", str(clone), "config", key, value], check=True)
    shutil.copy2(SCRIPT, clone / "results" / "campaign.sh")  # the script under test, as this checkout has it
    subprocess.run(["git", "-C", str(clone), "commit", "-q", "--allow-empty", "-m", "the script under test", "--",
                    "results/campaign.sh"], check=True)
    run = "walker_ddpg05_b1/bail/seed1"
    shutil.copytree(clone / "results" / "paper_batches" / "runs" / run, campaign / "work" / "outputs" / run)
    (clone / "README.md").write_text("changed and staged, not the study's\n")
    subprocess.run(["git", "-C", str(clone), "add", "README.md"], check=True)
    done = subprocess.run(["bash", str(clone / "results" / "campaign.sh"), "watch", "paper_batches", str(campaign)],
                          capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    assert f"committed: {run}" in done.stdout
    assert (campaign / "committed.list").read_text() == f"{run}/summary.json\n"
    status = subprocess.run(["git", "-C", str(clone), "status", "--short"], capture_output=True, text=True).stdout
    assert status.split() == ["M", "README.md"]

"""``results/campaign.sh``, the background runner of a study's long queue: what it refuses and what ``stop`` reaches.

Its whole path (a worktree, the runner, the watcher's commit after each job) is the one the paper-scale campaigns
run on; these tests hold the parts that guard the queue, in seconds and with no job run."""

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
    assert "campaign.sh start STUDY DIR [REGEX ...]" in done.stderr and "campaign.sh stop DIR" in done.stderr


def test_start_refuses_while_a_runner_of_the_dir_is_alive(tmp_path):
    """A second runner on the same work dir would run the same jobs twice and move the worktree under the first.
    (The study named is no study: were the refusal gone, ``start`` would stop at the study's check, not start one.)"""
    runner = _session(tmp_path, "runner")
    try:
        done = _campaign("start", "no_such_study", str(tmp_path), "^collect/")
        assert done.returncode == 1
        assert f"a runner of {tmp_path.resolve()} is alive (pid {runner.pid}); stop it first" in done.stderr
        assert not (tmp_path / "tree").exists() and not (tmp_path / "watcher.pid").exists()
    finally:
        runner.kill()
        runner.wait()


def test_stop_ends_the_runners_whole_session_and_the_watcher(tmp_path):
    """SIGTERM reaches every process of the runner's session (the jobs, which checkpoint on it), not the runner
    alone; the watcher stops too, so nothing commits after the stop."""
    runner, watcher = _session(tmp_path, "runner"), _session(tmp_path, "watcher")
    for _ in range(100):  # the job's start
        job = subprocess.run(["pgrep", "-s", str(runner.pid), "sleep"], capture_output=True, text=True)
        if job.stdout.strip():
            break
        time.sleep(0.05)
    try:
        done = _campaign("stop", str(tmp_path))
        assert done.returncode == 0 and f"stopped {tmp_path.resolve()}" in done.stdout
        assert runner.wait(timeout=10) == -15 and watcher.wait(timeout=10) == -15
        [job_pid] = job.stdout.split()
        assert _ended(int(job_pid)), "the job in the runner's session did not get the SIGTERM"
    finally:
        for proc in (runner, watcher):
            proc.kill()
            proc.wait()


@pytest.mark.slow
def test_the_watcher_commits_the_studys_results_alone_after_a_job_ends(tmp_path):
    """In a clone of this checkout: a job's line in the queue log and its cost in the worktree's ``timings.json``
    (the runner ended) make the watcher merge the cost into the clone's record, rebuild the reports there with the
    clone's code and commit ``results/<study>`` alone, named by that line; a file staged elsewhere stays uncommitted.
    (About a minute: one ``--report-only`` of the paper cell.)"""
    import json
    import shutil

    root = Path(__file__).resolve().parents[1]
    clone, campaign = tmp_path / "clone", tmp_path / "campaign"
    subprocess.run(["git", "clone", "-q", "--shared", str(root), str(clone)], check=True)
    for key, value in (("user.name", "test"), ("user.email", "test@example.com")):
        subprocess.run(["git", "-C", str(clone), "config", key, value], check=True)
    shutil.copy2(SCRIPT, clone / "results" / "campaign.sh")  # the script under test, as this checkout has it
    subprocess.run(["git", "-C", str(clone), "commit", "-q", "--allow-empty", "-m", "the script under test", "--",
                    "results/campaign.sh"], check=True)
    ran = campaign / "tree" / "results" / "paper_hopper" / "timings.json"
    ran.parent.mkdir(parents=True)
    kept = json.loads((clone / "results" / "paper_hopper" / "timings.json").read_text())
    ran.write_text(json.dumps({**kept, "planted/job": {"wall_s": 1.0}}))
    (campaign / "queue.log").write_text("[1/1] planted/job: ok in 1 s\n")
    (clone / "README.md").write_text("changed and staged, not the study's\n")
    subprocess.run(["git", "-C", str(clone), "add", "README.md"], check=True)
    done = subprocess.run(["bash", str(clone / "results" / "campaign.sh"), "watch", "paper_hopper", str(campaign)],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    assert "committed: [1/1] planted/job: ok in 1 s" in done.stdout
    log = subprocess.run(["git", "-C", str(clone), "show", "--name-only", "--format=%s", "HEAD"], capture_output=True,
                         text=True, check=True).stdout.split("\n")
    assert log[0].startswith("Campaign (paper_hopper): [1/1] planted/job: ok in 1 s")
    assert [f for f in log[1:] if f] == ["results/paper_hopper/timings.json"]  # the reports rebuilt the same
    merged = json.loads((clone / "results" / "paper_hopper" / "timings.json").read_text())
    assert merged == {**kept, "planted/job": {"wall_s": 1.0}}
    status = subprocess.run(["git", "-C", str(clone), "status", "--short"], capture_output=True, text=True).stdout
    assert status.split() == ["M", "README.md"]

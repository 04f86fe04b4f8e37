"""Runs the tutorial scripts at their default scale and keeps what they print: the record behind the tutorial pages.

    python results/run_tutorials.py                       # every tutorial, one after the other
    python results/run_tutorials.py --only losses_in_a_torchrl_loop load_evaluate_export

Each script (``docs/tutorials/<name>.py``) runs in a fresh temporary folder (removed afterwards) with its default
``--work-dir``; its stdout and stderr together are kept as ``results/tutorials/<name>.txt``, with that folder's
path written ``…`` as the pages write it. ``results/tutorials/record.json``
holds per script: the command, exit status, wall seconds, the load average at its start and end, the UTC start
time, the CPUs it could run on, and the commit of the checkout (with the files of ``src/``, ``conf/`` and
``docs/tutorials/`` that differed from it). The tutorial pages quote these outputs and the index
quotes the times (``tests/test_docs.py`` checks both against this folder).

The scripts need the Hopper DDPG σ = 0.5 batch; the first that needs it collects it (Getting started's first
command leaves it in the cache), and a collection inside a run is part of its time.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TUTORIALS = ROOT / "docs" / "tutorials"
OUT = ROOT / "results" / "tutorials"


def _git() -> dict:
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=True)
    status = subprocess.run(["git", "status", "--porcelain", "--", "src", "conf", "docs/tutorials"], cwd=ROOT,
                            capture_output=True, text=True, check=True)
    return {"commit": head.stdout.strip(), "uncommitted": [line[3:] for line in status.stdout.splitlines()]}


def run(name: str, cwd: Path) -> dict:
    """Runs ``docs/tutorials/<name>.py`` in ``cwd`` and keeps its output; returns its record."""
    command = [sys.executable, str(TUTORIALS / f"{name}.py")]
    started = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    load = list(os.getloadavg())
    t0 = time.perf_counter()
    proc = subprocess.run(command, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    seconds = time.perf_counter() - t0
    text = proc.stdout.replace(str(cwd), "…")
    OUT.mkdir(parents=True, exist_ok=True)
    tmp = OUT / f".{name}.txt.tmp"
    tmp.write_text(text)
    tmp.replace(OUT / f"{name}.txt")
    return {"command": f"python docs/tutorials/{name}.py", "exit_status": proc.returncode,
            "wall_s": round(seconds, 1), "load": {"start": load, "end": list(os.getloadavg())}, "started": started,
            "git": _git(), "cpus": sorted(os.sched_getaffinity(0))}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    names = sorted(p.stem for p in TUTORIALS.glob("*.py"))
    parser.add_argument("--only", nargs="+", choices=names, default=names, help="the tutorials to run")
    args = parser.parse_args(argv)
    record_path = OUT / "record.json"
    failed = []
    for name in args.only:
        cwd = Path(tempfile.mkdtemp(prefix="tutorials_"))
        try:
            print(f"{name} ...", flush=True)
            entry = run(name, cwd)
        finally:
            shutil.rmtree(cwd, ignore_errors=True)
        print(f"{name}: exit {entry['exit_status']} in {entry['wall_s']:.0f} s -> {OUT / (name + '.txt')}", flush=True)
        failed += [name] if entry["exit_status"] else []
        record = json.loads(record_path.read_text()) if record_path.exists() else {}
        record[name] = entry
        tmp = record_path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(dict(sorted(record.items())), indent=1) + "\n")
        tmp.replace(record_path)
    if failed:
        print("failed: " + ", ".join(failed), file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

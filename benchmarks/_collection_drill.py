"""Kill drill for behaviour collection: SIGKILL a small collection after at least one checkpoint, resume it in a
new process, and compare the batch's bytes with an uninterrupted run's.

    python benchmarks/_collection_drill.py [--trials 5] [--recipe ddpg|sac] [--seed 0] [--max-delay 8]

The batch's data files (memmapped tensors and layout) must match byte for byte. Prints one line per trial (killed or
finished first, the step it resumed from, match or not) and ``matched k/n``; exits 1 unless every trial matched.
:func:`collection_trial` is the hook ``kill_drill.py --target collection`` calls. Every process runs with
``OMP_NUM_THREADS=1`` (bit-identity holds for a fixed thread count).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"

#: small but real: several checkpoints, episodes that end by falls and time limits, gradient steps at episode ends
DRILL_OVERRIDES = {
    "ddpg": ["+exp=hopper_ddpg05", "batch.steps=1500", "batch.start_steps=200", "env.max_episode_steps=50",
             "batch.agent.actor_hidden=[32,32]", "batch.agent.critic_hidden=[32,32]", "batch.agent.batch_size=32",
             "batch.checkpoint_every_steps=150"],
    "sac": ["+exp=hopper_sac", "batch.steps=900", "env.max_episode_steps=50", "batch.sac.start_steps=200",
            "batch.sac.eval_every=300", "batch.sac.eval_episodes=2", "batch.sac.actor_hidden=[32,32]",
            "batch.sac.critic_hidden=[32,32]", "batch.sac.batch_size=32", "batch.checkpoint_every_steps=150"],
}

_CHILD = """
import json, sys, logging
sys.path.insert(0, {src!r})
import torch
torch.set_num_threads(1)
from hydra import compose, initialize_config_dir
from torchrl_bail import config_dir
from torchrl_bail.behaviour import ensure_batch
logging.basicConfig(level=logging.INFO, format="%(message)s")
with initialize_config_dir(str(config_dir()), version_base="1.3"):
    cfg = compose("config", overrides={overrides!r})
batch = ensure_batch(cfg, progress=False, data_dir={data_dir!r})
print("BATCH", json.dumps({{"path": str(batch.path), "resumed_from_step": batch.metadata.get("resumed_from_step")}}),
      flush=True)
"""


def child_env() -> dict[str, str]:
    return {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "RL_WARNINGS": "0",
            "PYTHONPATH": os.pathsep.join([str(SRC), os.environ.get("PYTHONPATH", "")])}


def start_collection(overrides: list[str], data_dir: Path) -> subprocess.Popen:
    """A child process collecting the batch of ``overrides`` into ``data_dir``."""
    code = textwrap.dedent(_CHILD.format(src=str(SRC), overrides=list(overrides), data_dir=str(data_dir)))
    return subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=child_env())


def finish_collection(overrides: list[str], data_dir: Path, timeout: float = 600) -> dict:
    """Collects (or resumes) in a child process; returns ``{"path", "resumed_from_step"}``."""
    proc = start_collection(overrides, data_dir)
    out, err = proc.communicate(timeout=timeout)
    for line in out.splitlines():
        if line.startswith("BATCH "):
            return json.loads(line[6:])
    raise RuntimeError(f"collection failed (rc {proc.returncode}): {err[-3000:]}")


def batch_digest(path: str | os.PathLike) -> dict[str, str]:
    """SHA-256 of every file of the batch's ``data/`` (the memmapped tensors and their layout); ``metadata.json``
    is left out (timestamps, speeds and ``resumed_from_step`` differ)."""
    root = Path(path) / "data"
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def checkpoints(data_dir: Path) -> list[Path]:
    partial = data_dir / ".partial"
    return list(partial.glob("*/state.pt")) if partial.is_dir() else []


_REFERENCE: dict[tuple[str, str], dict[str, str]] = {}


def reference_digest(overrides: list[str], workdir: Path) -> dict[str, str]:
    """The digest of an uninterrupted collection (computed once per config and work directory)."""
    key = (tuple(overrides), str(workdir))
    if key not in _REFERENCE:
        result = finish_collection(overrides, Path(tempfile.mkdtemp(prefix="reference-", dir=workdir)))
        _REFERENCE[key] = batch_digest(result["path"])
    return _REFERENCE[key]


def collection_trial(rng: random.Random, workdir: str | os.PathLike, *, recipe: str = "ddpg",
                     overrides: list[str] | None = None, max_delay_s: float = 3.0, log=print) -> bool:
    """One kill-and-resume trial; ``True`` when the resumed batch's bytes equal the uninterrupted batch's.

    Starts a collection, waits for its first checkpoint, SIGKILLs it ``uniform(0, max_delay_s)`` seconds later
    (a trial whose child finished before the kill, or saved its batch before it, says so and is checked all the
    same), resumes it in a new
    process and compares the batch with :func:`reference_digest`. ``overrides``: the config (default
    :data:`DRILL_OVERRIDES` of ``recipe``).
    """
    workdir = Path(workdir)
    overrides = list(DRILL_OVERRIDES[recipe] if overrides is None else overrides)
    reference = reference_digest(overrides, workdir)
    data_dir = Path(tempfile.mkdtemp(prefix=f"trial-{recipe}-", dir=workdir))
    proc = start_collection(overrides, data_dir)
    killed = False
    try:
        deadline = time.time() + 600
        while not checkpoints(data_dir) and proc.poll() is None and time.time() < deadline:
            time.sleep(0.05)
        if proc.poll() is None:
            time.sleep(rng.uniform(0.0, max_delay_s))
            if proc.poll() is None:
                proc.send_signal(signal.SIGKILL)
                killed = True
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    # a child killed after its batch was saved (while removing its checkpoint or exiting) had finished: the batch's
    # directory appears whole, by one rename of its .tmp- directory, so a metadata.json outside one tells
    killed = killed and not any(".tmp-" not in p.parent.name for p in data_dir.glob("*/metadata.json"))
    result = finish_collection(overrides, data_dir)
    match = batch_digest(result["path"]) == reference
    log(f"{recipe}: {'killed' if killed else 'finished before the kill'}, resumed from step "
        f"{result['resumed_from_step']}, {'MATCH' if match else 'MISMATCH'}")
    return match and (not killed or result["resumed_from_step"] is not None)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=5)
    parser.add_argument("--recipe", choices=sorted(DRILL_OVERRIDES), default="ddpg")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workdir", default=None)
    parser.add_argument("--max-delay", type=float, default=8.0, help="kill up to this many seconds after the first "
                        "checkpoint")
    args = parser.parse_args()
    sys.path.insert(0, str(SRC))
    rng = random.Random(args.seed)
    workdir = Path(args.workdir or tempfile.mkdtemp(prefix="collection-drill-"))
    matched = sum(collection_trial(rng, workdir, recipe=args.recipe, max_delay_s=args.max_delay)
                  for _ in range(args.trials))
    print(f"matched {matched}/{args.trials}")
    return 0 if matched == args.trials else 1


if __name__ == "__main__":
    raise SystemExit(main())

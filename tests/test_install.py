"""Installing a hosted batch: an intact copy lands in the cache whole; a damaged or altered one never does."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from test_batch import make_td

from torchrl_bail.data import BatchValidationError, load_batch, save_batch
from torchrl_bail.data.cache import stable_hash
from torchrl_bail.data.install import CHECKSUMS, install_batch

IDENTITY = {"env_id": "Toy-v0", "max_episode_steps": 5, "batch": {"recipe": "ddpg", "index": 1, "steps": 9}}


def write_sums(root: Path) -> None:
    lines = [f"{hashlib.sha256(p.read_bytes()).hexdigest()}  ./{p.relative_to(root)}"
             for p in sorted(root.rglob("*")) if p.is_file() and p.name != CHECKSUMS]
    (root / CHECKSUMS).write_text("\n".join(lines) + "\n")


@pytest.fixture
def hosted(tmp_path) -> Path:
    """A hosted folder as ``shared/data`` keeps one: ``<name>-<hash>/`` and ``SHA256SUMS``."""
    root = tmp_path / "hosted"
    name = f"toy_ddpg05_b1-{stable_hash(IDENTITY)}"
    save_batch(make_td(), root / name, {"env_id": "Toy-v0", "name": "toy_ddpg05_b1", "identity": IDENTITY,
                                        "recipe_hash": stable_hash(IDENTITY)})
    write_sums(root)
    return root


def entry(root: Path) -> Path:
    return next(p for p in root.iterdir() if p.is_dir())


def test_an_intact_copy_is_installed_whole_and_loads(hosted, tmp_path):
    path, copied = install_batch(hosted, tmp_path / "cache")
    assert copied and path == tmp_path / "cache" / entry(hosted).name
    batch = load_batch(path)
    assert batch.num_transitions == 9 and batch.num_episodes == 3
    assert torch.equal(batch.data["action"], load_batch(entry(hosted)).data["action"])
    assert [p.name for p in (tmp_path / "cache").iterdir()] == [path.name]  # no scratch folder left behind
    assert install_batch(hosted, tmp_path / "cache") == (path, False)  # a second install checks, copies nothing


def test_an_altered_cached_entry_is_reported_on_a_second_install(hosted, tmp_path):
    path, _ = install_batch(hosted, tmp_path / "cache")
    with open(path / "data" / "action.memmap", "r+b") as f:
        f.write(b"\x00\x00\x80\x7f")
    with pytest.raises(BatchValidationError, match="action.memmap: sha256 .* does not match"):
        install_batch(hosted, tmp_path / "cache")


def _flip_a_byte(root):
    target = entry(root) / "data" / "observation.memmap"
    data = bytearray(target.read_bytes())
    data[5] ^= 0xFF
    target.write_bytes(bytes(data))


def _drop_a_file(root):
    (entry(root) / "data" / "next" / "reward.memmap").unlink()


def _add_a_file(root):
    (entry(root) / "data" / "stray.memmap").write_bytes(b"x")


def _drop_the_sums(root):
    (root / CHECKSUMS).unlink()


def _recount_episodes(root):  # metadata altered and the checksums made to match it: only the data can tell
    meta_path = entry(root) / "metadata.json"
    meta = json.loads(meta_path.read_text())
    meta["num_episodes"] = 4
    meta_path.write_text(json.dumps(meta))
    write_sums(root)


def _change_the_mean(root):
    meta_path = entry(root) / "metadata.json"
    meta = json.loads(meta_path.read_text())
    meta["episode_return_mean"] += 1e-6
    meta_path.write_text(json.dumps(meta))
    write_sums(root)


def _rename_the_hash(root):  # a folder whose name no recipe leads to
    entry(root).rename(root / "toy_ddpg05_b1-00000000")
    write_sums(root)


@pytest.mark.parametrize("damage, message", [
    (_flip_a_byte, r"observation.memmap: sha256 .* does not match SHA256SUMS"),
    (_drop_a_file, r"not whole: missing \['toy_ddpg05_b1-[0-9a-f]{8}/data/next/reward.memmap'\]"),
    (_add_a_file, r"not whole: missing none, not in SHA256SUMS \['toy.*stray.memmap'\]"),
    (_drop_the_sums, "no SHA256SUMS beside the batch"),
    (_recount_episodes, "num_episodes is 3 in the data, 4 in its metadata"),
    (_change_the_mean, "mean episode return is 3.0 in the data"),
    (_rename_the_hash, "recipe hash disagrees: folder suffix '00000000'"),
])
def test_a_damaged_or_altered_copy_is_refused_and_nothing_is_installed(hosted, tmp_path, damage, message):
    damage(hosted)
    with pytest.raises(BatchValidationError, match=message):
        install_batch(hosted, tmp_path / "cache")
    assert not (tmp_path / "cache").exists() or not any((tmp_path / "cache").iterdir())


def test_the_command_reports_a_refusal_in_one_line(hosted, tmp_path):
    _flip_a_byte(hosted)
    done = subprocess.run([sys.executable, "-m", "torchrl_bail.collect", "--install", str(hosted),
                           "--data-dir", str(tmp_path / "cache")], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    assert done.stderr.count("\n") == 1 and "does not match SHA256SUMS" in done.stderr
    assert "nothing was installed" in done.stderr and "Traceback" not in done.stderr

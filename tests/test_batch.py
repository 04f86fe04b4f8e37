"""The batch format: every validation error is clear, writes are atomic, loads are memory-mapped."""

from __future__ import annotations

import json
import os

import pytest
import torch
from tensordict import MemoryMappedTensor, TensorDict

from torchrl_bail.data import BatchValidationError, load_batch, save_batch, validate_batch


def make_td(lengths=(3, 2, 4), obs_dim=3, act_dim=2, last_unfinished=True, truncate_first=False) -> TensorDict:
    episode = torch.cat([torch.full((n,), i) for i, n in enumerate(lengths)])
    n = episode.numel()
    last = torch.ones(n, dtype=torch.bool)
    last[:-1] = episode[1:] != episode[:-1]
    if last_unfinished:
        last[-1] = False
    truncated = torch.zeros(n, dtype=torch.bool)
    if truncate_first:
        truncated[lengths[0] - 1] = True
    terminated = last & ~truncated
    g = torch.Generator().manual_seed(0)
    return TensorDict({
        "observation": torch.randn(n, obs_dim, generator=g), "action": torch.rand(n, act_dim, generator=g),
        "episode": episode,
        "next": {"observation": torch.randn(n, obs_dim, generator=g), "reward": torch.ones(n, 1),
                 "done": (terminated | truncated).unsqueeze(-1), "terminated": terminated.unsqueeze(-1),
                 "truncated": truncated.unsqueeze(-1)},
    }, [n])


def test_round_trip_is_memory_mapped_with_metadata(tmp_path):
    td = make_td(truncate_first=True)
    batch = save_batch(td, tmp_path / "b", {"env_id": "Toy-v0", "recipe": {"kind": "test"}, "seed": 3})
    loaded = load_batch(tmp_path / "b", obs_dim=3, act_dim=2)
    assert isinstance(loaded.data["observation"], MemoryMappedTensor)
    assert loaded.num_transitions == 9 and loaded.num_episodes == 3
    assert torch.equal(loaded.data["observation"], td["observation"])
    meta = loaded.metadata
    assert meta["env_id"] == "Toy-v0" and meta["seed"] == 3 and meta["recipe"] == {"kind": "test"}
    assert meta["num_episodes"] == 3 and meta["episode_return_mean"] == 3.0 and meta["episode_return_max"] == 4.0
    assert {"torch", "torchrl", "tensordict"} <= set(meta["library_versions"]) and "created_at" in meta
    assert batch.episode_returns().tolist() == [3.0, 2.0, 4.0]


def test_float64_is_converted_once_at_the_edge(tmp_path):
    td = make_td()
    td["observation"] = td["observation"].double()
    td["next", "observation"] = td["next", "observation"].double()
    saved = save_batch(td, tmp_path / "b", {"env_id": "Toy-v0"})
    assert load_batch(saved.path).data["observation"].dtype == torch.float32
    with pytest.raises(BatchValidationError, match="observation.*float32"):
        validate_batch(td)  # validation itself is strict


def _breaks(mutate, match):
    td = make_td()
    mutate(td)
    with pytest.raises(BatchValidationError, match=match):
        validate_batch(td, source="some/batch")


def test_missing_key():
    _breaks(lambda td: td.del_(("next", "terminated")), r"some/batch: key 'next/terminated' expected this key")


def test_ragged_lengths():
    td = make_td()
    ragged = TensorDict({"observation": td["observation"], "action": td["action"][:5]}, [])
    with pytest.raises(BatchValidationError, match="one batch dimension"):
        validate_batch(ragged)


def test_nan_names_key_and_index():
    def nan(td):
        td["next", "reward"][4, 0] = float("nan")
    _breaks(nan, r"'next/reward' expected finite values, found a non-finite value at index 4")


def test_done_must_be_terminated_or_truncated():
    def bad(td):
        td["next", "done"][0, 0] = True
    _breaks(bad, "done == terminated")


def test_episode_ids_contiguous():
    def bad(td):
        td["episode"][5:] += 1  # skip an id
    _breaks(bad, "increase by exactly 1")


def test_done_inside_an_episode_and_unfinished_middle_episode():
    def inside(td):
        for k in ("done", "terminated"):
            td["next", k][0, 0] = True
    _breaks(inside, "done only on the last transition")

    def unfinished(td):
        for k in ("done", "terminated"):
            td["next", k][2, 0] = False
    _breaks(unfinished, "every episode but the batch's last")


def test_wrong_sizes_for_the_env_and_dtypes():
    with pytest.raises(BatchValidationError, match="11 features"):
        validate_batch(make_td(), obs_dim=11)
    with pytest.raises(BatchValidationError, match="3 dimensions"):
        validate_batch(make_td(), act_dim=3)
    _breaks(lambda td: td.set("episode", td["episode"].int()), "int64")
    _breaks(lambda td: td.set(("next", "truncated"), td["next", "truncated"].float()), "bool")


def test_metadata_is_checked(tmp_path):
    with pytest.raises(BatchValidationError, match="env_id"):
        save_batch(make_td(), tmp_path / "b", {})
    batch = save_batch(make_td(), tmp_path / "b", {"env_id": "Toy-v0"})
    meta_file = batch.path / "metadata.json"
    meta = json.loads(meta_file.read_text())
    meta["num_transitions"] = 10
    meta_file.write_text(json.dumps(meta))
    with pytest.raises(BatchValidationError, match="num_transitions == 9"):
        load_batch(batch.path)
    meta_file.write_text("{not json")
    with pytest.raises(BatchValidationError, match="not valid JSON"):
        load_batch(batch.path)


def test_interrupted_write_never_loads_and_nothing_is_lost(tmp_path, monkeypatch):
    first = save_batch(make_td(), tmp_path / "b", {"env_id": "Toy-v0", "seed": 1})
    with pytest.raises(FileExistsError):
        save_batch(make_td(), tmp_path / "b", {"env_id": "Toy-v0"})

    def crash(*args, **kwargs):
        raise KeyboardInterrupt  # interrupted while writing the metadata

    monkeypatch.setattr("torchrl_bail.data.batch.write_json_atomic", crash)
    with pytest.raises(KeyboardInterrupt):
        save_batch(make_td(lengths=(2, 2)), tmp_path / "b", {"env_id": "Toy-v0", "seed": 2}, overwrite=True)
    assert sorted(os.listdir(tmp_path)) == ["b"]  # no temp dir left, the old batch intact
    assert load_batch(first.path).metadata["seed"] == 1
    monkeypatch.undo()
    replaced = save_batch(make_td(lengths=(2, 2)), tmp_path / "b", {"env_id": "Toy-v0", "seed": 2}, overwrite=True)
    assert replaced.num_transitions == 4 and sorted(os.listdir(tmp_path)) == ["b"]


def test_incomplete_directories_are_not_batches(tmp_path):
    (tmp_path / "half").mkdir()
    with pytest.raises(BatchValidationError, match="incomplete batch"):
        load_batch(tmp_path / "half")
    (tmp_path / "b.tmp-1-abc").mkdir()
    with pytest.raises(BatchValidationError, match="interrupted"):
        load_batch(tmp_path / "b.tmp-1-abc")
    with pytest.raises(FileNotFoundError):
        load_batch(tmp_path / "nothing")


def test_the_source_revision_names_the_checkouts_commit_and_whether_its_code_was_changed(tmp_path):
    """A run records the git commit of the checkout it ran from, and whether ``src/`` or ``conf/`` differed from it
    (the package version alone does not tell two states of the code apart); a package that is no checkout's
    ``src/torchrl_bail`` (an install, even inside another repository) records none."""
    import shutil
    import subprocess

    from torchrl_bail.data import source_revision

    if shutil.which("git") is None:
        pytest.skip("no git")

    def git(repo, *args):
        return subprocess.run(["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t", *args],
                              capture_output=True, text=True, check=True).stdout.strip()

    def repository(package_path):
        repo = tmp_path / package_path.split("/")[0]
        package = repo / package_path.split("/", 1)[1]
        package.mkdir(parents=True)
        (package / "__init__.py").write_text("x = 1\n")
        (repo / "conf").mkdir()
        (repo / "conf" / "config.yaml").write_text("a: 1\n")
        git(repo, "init", "-q")
        git(repo, "add", ".")
        git(repo, "commit", "-qm", "first")
        return repo, package

    repo, package = repository("checkout/src/torchrl_bail")
    assert source_revision(package) == {"commit": git(repo, "rev-parse", "HEAD"), "modified": False}
    (package / "__pycache__").mkdir()
    (package / "__pycache__" / "__init__.cpython-311.pyc").write_bytes(b"untracked: no change of the code")
    assert source_revision(package)["modified"] is False
    (repo / "conf" / "config.yaml").write_text("a: 2\n")
    assert source_revision(package)["modified"] is True
    git(repo, "commit", "-qam", "second")
    assert source_revision(package) == {"commit": git(repo, "rev-parse", "HEAD"), "modified": False}
    (package / "__init__.py").write_text("x = 2\n")
    assert source_revision(package)["modified"] is True
    _, installed = repository("project/.venv/lib/site-packages/torchrl_bail")
    assert source_revision(installed) is None
    loose = tmp_path / "unpacked" / "torchrl_bail"
    loose.mkdir(parents=True)
    assert source_revision(loose) is None

"""Importing datasets users already have: D4RL-layout HDF5 files, local Minari datasets, native batch dirs.

Every file here is written by the test itself with h5py, in the layout someone else's code would produce.
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys

import h5py
import numpy as np
import pytest
import torch

from torchrl_bail.data import BatchValidationError, importers, load_batch, save_batch
from torchrl_bail.data.formats import FORMATS, Conversion, DatasetFormat, register_format, transitions
from torchrl_bail.data.formats.d4rl import D4RLFormat
from torchrl_bail.data.importers import DatasetImportError, import_cache_path, import_dataset
from torchrl_bail.data.scores import D4RL_REF_SCORES, normalized_score

HOPPER_OBS, HOPPER_ACT = 11, 3


def d4rl_arrays(lengths=(3, 2, 4), ends=("terminal", "timeout", None), obs_dim=HOPPER_OBS, act_dim=HOPPER_ACT,
                next_obs=True, seed=0) -> dict[str, np.ndarray]:
    """Flat D4RL arrays (float64, as D4RL ships them). ``observations[i, j] = i + j / 100`` so that every row is
    recognisable; a recorded ``next_observations`` row at an episode's end is ``1000 + i`` (the true final state)."""
    n = sum(lengths)
    rng = np.random.default_rng(seed)
    obs = np.arange(n, dtype=np.float64)[:, None] + np.arange(obs_dim)[None, :] / 100
    terminals = np.zeros(n, dtype=bool)
    timeouts = np.zeros(n, dtype=bool)
    nxt = np.empty_like(obs)
    nxt[:-1] = obs[1:]
    start = 0
    for length, end in zip(lengths, ends, strict=True):
        last = start + length - 1
        nxt[last] = 1000 + last + np.arange(obs_dim) / 100
        if end == "terminal":
            terminals[last] = True
        elif end == "timeout":
            timeouts[last] = True
        start += length
    arrays = {"observations": obs, "actions": rng.uniform(-1, 1, (n, act_dim)),
              "rewards": np.arange(n, dtype=np.float64) + 0.5, "terminals": terminals, "timeouts": timeouts}
    if next_obs:
        arrays["next_observations"] = nxt
    return arrays


def write_hdf5(path, arrays: dict) -> str:
    with h5py.File(path, "w") as f:
        for key, value in arrays.items():
            f.create_dataset(key, data=value)
        f.create_dataset("infos/qpos", data=np.zeros((1, 2)))  # extra D4RL keys are ignored
        f.create_dataset("metadata/algorithm", data="SAC")
    return str(path)


def imported_dirs(data_dir) -> list:
    return sorted(p.name for p in data_dir.glob("import_*")) if data_dir.exists() else []


# ----------------------------------------------------------------------------------------------------------------
# D4RL round trips
# ----------------------------------------------------------------------------------------------------------------


def test_d4rl_with_next_observations_round_trip(tmp_path):
    arrays = d4rl_arrays()
    path = write_hdf5(tmp_path / "hopper-toy-v2.hdf5", arrays)
    batch = import_dataset(path, env_id="Hopper-v5", data_dir=tmp_path / "data")
    data = batch.data
    assert batch.num_transitions == 9 and batch.num_episodes == 3
    assert data["episode"].tolist() == [0, 0, 0, 1, 1, 2, 2, 2, 2]
    assert data["next", "terminated"].flatten().tolist() == [0, 0, 1, 0, 0, 0, 0, 0, 0]
    assert data["next", "truncated"].flatten().tolist() == [0, 0, 0, 0, 1, 0, 0, 0, 0]
    assert torch.equal(data["next", "done"], data["next", "terminated"] | data["next", "truncated"])
    for key in ("observation", "action", ("next", "observation"), ("next", "reward")):
        assert data[key].dtype == torch.float32, key
    assert data["episode"].dtype == torch.int64
    assert torch.equal(data["observation"], torch.from_numpy(arrays["observations"]).float())
    assert torch.equal(data["next", "observation"], torch.from_numpy(arrays["next_observations"]).float())
    assert torch.equal(data["next", "reward"].flatten(), torch.from_numpy(arrays["rewards"]).float())
    # the trailing unfinished episode is kept whole, as the batch's final unfinished episode
    assert not bool(data["next", "done"][-1])
    assert batch.episode_returns().tolist() == [4.5, 8.0, 28.0]
    meta = batch.metadata
    assert meta["env_id"] == "Hopper-v5" and meta["name"] == "hopper-toy-v2"
    assert meta["dropped_rows"] == 0 and meta["unfinished_final_episode"] is True
    assert meta["action_low"] == [-1.0] * 3 and meta["source"]["format"] == "d4rl_hdf5"
    assert sorted(meta["ignored_keys"]) == ["infos", "metadata"]
    # the cached copy is a valid batch on disk, under the data dir
    assert batch.path.parent == tmp_path / "data" and batch.path.name.startswith("import_hopper-toy-v2-")
    assert load_batch(batch.path, obs_dim=HOPPER_OBS, act_dim=HOPPER_ACT).num_transitions == 9


def test_d4rl_without_next_observations_drops_only_unknown_next_states(tmp_path):
    arrays = d4rl_arrays(next_obs=False)
    obs = torch.from_numpy(arrays["observations"]).float()
    batch = import_dataset(write_hdf5(tmp_path / "toy.hdf5", arrays), data_dir=tmp_path / "data")
    data = batch.data
    # rows 0-2: episode ending in a terminal (kept); rows 3-4: timeout episode (row 4 dropped, row 3 now truncated);
    # rows 5-8: trailing unfinished episode (row 8 dropped: its next observation is unknown)
    kept = [0, 1, 2, 3, 5, 6, 7]
    assert torch.equal(data["observation"], obs[kept])
    assert data["episode"].tolist() == [0, 0, 0, 1, 2, 2, 2]
    assert data["next", "terminated"].flatten().tolist() == [0, 0, 1, 0, 0, 0, 0]
    assert data["next", "truncated"].flatten().tolist() == [0, 0, 0, 1, 0, 0, 0]
    assert not bool(data["next", "done"][-1])  # still the batch's final unfinished episode
    # next observation = the next row's observation within the episode; the terminal's is a placeholder copy
    assert torch.equal(data["next", "observation"], obs[[1, 2, 2, 4, 6, 7, 8]])
    assert data["next", "reward"].flatten().tolist() == [0.5, 1.5, 2.5, 3.5, 5.5, 6.5, 7.5]
    meta = batch.metadata
    assert (meta["dropped_rows"], meta["placeholder_next_observation_rows"]) == (2, 1)
    assert meta["next_observation"] == "shifted observations" and meta["env_id"] is None


def test_d4rl_file_ending_with_a_done_keeps_every_episode_finished(tmp_path):
    arrays = d4rl_arrays(lengths=(2, 3), ends=("timeout", "terminal"))
    batch = import_dataset(write_hdf5(tmp_path / "t.h5", arrays), data_dir=tmp_path / "data")
    assert bool(batch.data["next", "done"][-1]) and batch.metadata["unfinished_final_episode"] is False
    assert batch.data["episode"].tolist() == [0, 0, 1, 1, 1]


def test_float_flags_and_column_rewards_are_accepted(tmp_path):
    arrays = d4rl_arrays()
    arrays["terminals"] = arrays["terminals"].astype(np.float32)
    arrays["timeouts"] = arrays["timeouts"].astype(np.int64)
    arrays["rewards"] = arrays["rewards"][:, None]
    batch = import_dataset(write_hdf5(tmp_path / "f.hdf5", arrays), data_dir=tmp_path / "data")
    assert batch.data["next", "terminated"].dtype == torch.bool
    assert batch.data["next", "terminated"].flatten().tolist()[2] is True


# ----------------------------------------------------------------------------------------------------------------
# clear errors at the edge
# ----------------------------------------------------------------------------------------------------------------


def _missing(a):
    del a["timeouts"]


def _ragged(a):
    a["rewards"] = a["rewards"][:-1]


def _nan(a):
    a["observations"][4, 3] = np.nan


def _inf_next(a):
    a["next_observations"][6, 0] = np.inf


def _bad_flag(a):
    a["terminals"] = a["terminals"].astype(np.float64)
    a["terminals"][1] = 0.5


def _one_d_obs(a):
    a["observations"] = a["observations"][:, 0]


def _empty_rows(a):
    for key in list(a):
        a[key] = a[key][:0]


@pytest.mark.parametrize("mutate, match", [
    (_missing, r"key 'timeouts': expected this key to be present"),
    (_ragged, r"key 'rewards': expected 9 rows \(as many as 'observations'\), found 8 rows"),
    (_nan, r"key 'observations': expected finite values, found NaN at row 4"),
    (_inf_next, r"key 'next_observations': expected finite values, found inf.* at row 6"),
    (_bad_flag, r"key 'terminals': expected boolean flags \(0/1\), found 0.5 at row 1"),
    (_one_d_obs, r"key 'observations': expected a 2-D array"),
    (_empty_rows, r"key 'observations': expected at least one transition, found 0 rows"),
])
def test_bad_d4rl_files_give_one_clear_error(tmp_path, mutate, match):
    arrays = d4rl_arrays()
    mutate(arrays)
    path = write_hdf5(tmp_path / "bad.hdf5", arrays)
    with pytest.raises(DatasetImportError, match=match) as err:
        import_dataset(path, env_id="Hopper-v5", data_dir=tmp_path / "data")
    assert str(err.value).startswith(str(tmp_path / "bad.hdf5"))
    assert isinstance(err.value, BatchValidationError)  # train's CLI turns it into one line, exit code 2
    assert imported_dirs(tmp_path / "data") == []  # nothing half-written is left behind


@pytest.mark.parametrize("obs_dim, act_dim, match", [
    (10, 3, r"key 'observations': expected 11 observation features \(the observation size of env Hopper-v5\), "
            r"found 10"),
    (11, 6, r"key 'actions': expected 3 action dimensions \(the action size of env Hopper-v5\), found 6"),
])
def test_wrong_sizes_for_the_env_are_named(tmp_path, obs_dim, act_dim, match):
    path = write_hdf5(tmp_path / "walker.hdf5", d4rl_arrays(obs_dim=obs_dim, act_dim=act_dim))
    with pytest.raises(DatasetImportError, match=match):
        import_dataset(path, env_id="Hopper-v5", data_dir=tmp_path / "data")
    # without an env, the sizes are not checked
    assert import_dataset(path, data_dir=tmp_path / "data").obs_dim == obs_dim


def test_empty_and_unreadable_files(tmp_path):
    empty = tmp_path / "empty.hdf5"
    h5py.File(empty, "w").close()
    with pytest.raises(DatasetImportError, match=r"empty.hdf5: expected a D4RL dataset .* found an empty HDF5 file"):
        import_dataset(empty, data_dir=tmp_path / "data")
    junk = tmp_path / "junk.hdf5"
    junk.write_text("not hdf5")
    with pytest.raises(DatasetImportError, match=r"junk.hdf5: expected a readable HDF5 file"):
        import_dataset(junk, data_dir=tmp_path / "data")
    with pytest.raises(FileNotFoundError, match="nope.hdf5"):
        import_dataset(tmp_path / "nope.hdf5", data_dir=tmp_path / "data")
    (tmp_path / "data.csv").write_text("a,b\n")
    with pytest.raises(DatasetImportError, match=r"data.csv: expected a D4RL-layout HDF5 file"):
        import_dataset(tmp_path / "data.csv", data_dir=tmp_path / "data")


def test_unknown_env_id_is_a_clear_error(tmp_path):
    path = write_hdf5(tmp_path / "x.hdf5", d4rl_arrays())
    with pytest.raises(DatasetImportError, match=r"x.hdf5: cannot check the data's sizes against env 'NoSuchEnv-v0'"):
        import_dataset(path, env_id="NoSuchEnv-v0", data_dir=tmp_path / "data")


# ----------------------------------------------------------------------------------------------------------------
# the cache
# ----------------------------------------------------------------------------------------------------------------


def test_second_import_is_a_cache_hit_and_a_changed_file_is_converted_again(tmp_path, monkeypatch):
    data_dir = tmp_path / "data"
    path = write_hdf5(tmp_path / "d.hdf5", d4rl_arrays())
    first = import_dataset(path, env_id="Hopper-v5", data_dir=data_dir)
    assert import_cache_path(path, data_dir) == first.path
    stamp = (first.path / "metadata.json").stat().st_mtime_ns

    def no_conversion(*args, **kwargs):
        raise AssertionError("converted again although the file did not change")

    with monkeypatch.context() as m:
        m.setattr(D4RLFormat, "convert", no_conversion)
        second = import_dataset(path, env_id="Hopper-v5", data_dir=data_dir)
        assert second.path == first.path and second.num_transitions == 9
        # relative and absolute spellings of the same file share the cache entry
        monkeypatch.chdir(tmp_path)
        assert import_dataset("d.hdf5", env_id="Hopper-v5", data_dir=data_dir).path == first.path
    assert (first.path / "metadata.json").stat().st_mtime_ns == stamp

    arrays = d4rl_arrays()
    arrays["rewards"] = arrays["rewards"] * 2
    write_hdf5(path, arrays)
    os.utime(path, ns=(stamp + 10**9, stamp + 10**9))  # a new modification time even on coarse clocks
    third = import_dataset(path, env_id="Hopper-v5", data_dir=data_dir)
    assert third.path != first.path
    assert third.data["next", "reward"].flatten()[0].item() == 1.0
    assert len(imported_dirs(data_dir)) == 2  # the stale conversion is kept, not silently deleted
    # a cached conversion that lost its data is converted again instead of crashing
    (third.path / "metadata.json").unlink()
    assert import_dataset(path, data_dir=data_dir).num_transitions == 9


def test_cache_hit_still_checks_the_env_sizes(tmp_path):
    path = write_hdf5(tmp_path / "d.hdf5", d4rl_arrays())
    import_dataset(path, env_id="Hopper-v5", data_dir=tmp_path / "data")
    with pytest.raises(DatasetImportError, match=r"d.hdf5: key 'observations': expected 17 observation features"):
        import_dataset(path, env_id="Walker2d-v5", data_dir=tmp_path / "data")


def test_default_data_dir_comes_from_the_environment(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCHRL_BAIL_DATA_DIR", str(tmp_path / "env_dir"))
    batch = import_dataset(write_hdf5(tmp_path / "d.hdf5", d4rl_arrays()))
    assert batch.path.parent == tmp_path / "env_dir"


# ----------------------------------------------------------------------------------------------------------------
# Minari and native batches
# ----------------------------------------------------------------------------------------------------------------


def write_minari(root, episodes, *, dataset_id="mujoco/hopper/tiny-v0", data_format="hdf5", extra_meta=None):
    """A local Minari dataset in Minari's on-disk layout: ``<root>/<id>/data/{metadata.json, main_data.hdf5}``."""
    data = root / dataset_id / "data"
    data.mkdir(parents=True)
    box = {"type": "Box", "dtype": "float32", "shape": [HOPPER_ACT], "low": [-1.0] * 3, "high": [1.0] * 3}
    meta = {"dataset_id": dataset_id, "total_episodes": len(episodes),
            "total_steps": sum(len(e["rewards"]) for e in episodes), "data_format": data_format,
            "observation_space": json.dumps({"type": "Box", "dtype": "float64", "shape": [HOPPER_OBS],
                                             "low": [-np.inf] * HOPPER_OBS, "high": [np.inf] * HOPPER_OBS}),
            "action_space": json.dumps(box), "env_spec": json.dumps({"id": "Hopper-v5", "max_episode_steps": 1000}),
            "minari_version": "0.5.3", **(extra_meta or {})}
    (data / "metadata.json").write_text(json.dumps(meta))
    if data_format == "hdf5":
        with h5py.File(data / "main_data.hdf5", "w") as f:
            for i, ep in enumerate(episodes):
                g = f.create_group(f"episode_{i}")
                g.attrs["id"], g.attrs["total_steps"] = i, len(ep["rewards"])
                for key, value in ep.items():
                    if isinstance(value, dict):
                        for sub, v in value.items():
                            g.create_dataset(f"{key}/{sub}", data=v)
                    else:
                        g.create_dataset(key, data=value)
                g.create_group("infos").create_dataset("x", data=np.zeros(len(ep["rewards"])))
    return root / dataset_id


def minari_episode(steps, end, start=0.0):
    obs = start + np.arange(steps + 1, dtype=np.float64)[:, None] + np.arange(HOPPER_OBS)[None, :] / 100
    term, trunc = np.zeros(steps, dtype=bool), np.zeros(steps, dtype=bool)
    if end == "terminal":
        term[-1] = True
    elif end == "timeout":
        trunc[-1] = True
    return {"observations": obs, "actions": np.full((steps, HOPPER_ACT), 0.25, dtype=np.float32),
            "rewards": np.ones(steps), "terminations": term, "truncations": trunc}


def test_minari_hdf5_layout_is_read_without_the_minari_package(tmp_path):
    eps = [minari_episode(3, "terminal"), minari_episode(2, "timeout", 100), minari_episode(2, None, 200)]
    folder = write_minari(tmp_path / "minari", eps, extra_meta={"ref_min_score": -10.0, "ref_max_score": 90.0})
    batch = import_dataset(folder, data_dir=tmp_path / "data")
    data = batch.data
    assert data["episode"].tolist() == [0, 0, 0, 1, 1, 2, 2]
    assert data["next", "terminated"].flatten().tolist() == [0, 0, 1, 0, 0, 0, 0]
    # the third episode stops without a flag: a truncation (its final observation is in the file)
    assert data["next", "truncated"].flatten().tolist() == [0, 0, 0, 0, 1, 0, 1]
    obs = np.concatenate([e["observations"][:-1] for e in eps])
    nxt = np.concatenate([e["observations"][1:] for e in eps])
    assert torch.equal(data["observation"], torch.from_numpy(obs).float())
    assert torch.equal(data["next", "observation"], torch.from_numpy(nxt).float())
    assert data["observation"].dtype == torch.float32
    meta = batch.metadata
    assert meta["env_id"] == "Hopper-v5" and meta["name"] == "mujoco/hopper/tiny-v0"
    assert meta["episodes_without_end_flag"] == 1 and meta["action_high"] == [1.0] * 3
    assert normalized_score("Humanoid-v5", 40.0, metadata=meta) == 50.0  # the dataset's own reference
    # its data/ folder names the same dataset (and the same cache entry)
    assert import_dataset(folder / "data", env_id="Hopper-v5", data_dir=tmp_path / "data").path == batch.path


def test_minari_errors_name_the_episode_and_key(tmp_path):
    bad = minari_episode(3, "terminal")
    bad["observations"] = bad["observations"][:-1]  # the final observation is missing
    folder = write_minari(tmp_path / "a", [minari_episode(2, "timeout"), bad])
    with pytest.raises(DatasetImportError, match=r"main_data.hdf5: key 'episode_1/observations': expected 4 rows"):
        import_dataset(folder, data_dir=tmp_path / "data")

    dict_obs = minari_episode(2, "terminal")
    dict_obs["observations"] = {"achieved_goal": np.zeros((3, 2)), "observation": np.zeros((3, 4))}
    folder = write_minari(tmp_path / "b", [dict_obs])
    with pytest.raises(DatasetImportError, match=r"key 'episode_0/observations': expected a flat array"):
        import_dataset(folder, data_dir=tmp_path / "data")

    nan = minari_episode(2, "terminal")
    nan["rewards"][1] = np.nan
    with pytest.raises(DatasetImportError,
                       match=r"key 'episode_0/rewards': expected finite values, found NaN at row 1"):
        import_dataset(write_minari(tmp_path / "c", [nan]), data_dir=tmp_path / "data")

    with pytest.raises(DatasetImportError, match=r"key 'episode_0/observations': expected 17 observation features"):
        import_dataset(write_minari(tmp_path / "d", [minari_episode(2, None)]), env_id="Walker2d-v5",
                       data_dir=tmp_path / "data")


@pytest.mark.skipif(importlib.util.find_spec("minari") is not None, reason="minari is installed")
def test_minari_arrow_storage_without_minari_names_the_install_command(tmp_path):
    folder = write_minari(tmp_path / "m", [minari_episode(2, "terminal")], data_format="arrow")
    with pytest.raises(DatasetImportError, match=r"arrow.*pip install -e \"\.\[minari\]\""):
        import_dataset(folder, data_dir=tmp_path / "data")


def test_native_batch_directory_is_used_in_place(tmp_path):
    source = import_dataset(write_hdf5(tmp_path / "d.hdf5", d4rl_arrays()), data_dir=tmp_path / "cache")
    native = save_batch(source.data, tmp_path / "mine", {"env_id": "Hopper-v5"})
    batch = import_dataset(native.path, env_id="Hopper-v5", data_dir=tmp_path / "data")
    assert batch.path == native.path and imported_dirs(tmp_path / "data") == []
    with pytest.raises(DatasetImportError, match=r"mine: key 'observations': expected 17 observation features"):
        import_dataset(native.path, env_id="HalfCheetah-v5")


# ----------------------------------------------------------------------------------------------------------------
# the format registry
# ----------------------------------------------------------------------------------------------------------------

KNOWN_FORMATS = (r"expected a D4RL-layout HDF5 file \(\*\.hdf5 or \*\.h5\), a Minari dataset directory "
                 r"\(data/metadata\.json \+ data/main_data\.hdf5\) or a native batch directory "
                 r"\(metadata\.json \+ data/\)")


def test_a_path_no_format_claims_is_one_error_naming_every_format(tmp_path):
    """No fallback: an unknown file or folder is never handed to the Minari (or any) reader."""
    (tmp_path / "data.csv").write_text("a,b\n")
    with pytest.raises(DatasetImportError, match=rf"data.csv: {KNOWN_FORMATS}, found a file with suffix '.csv'$"):
        import_dataset(tmp_path / "data.csv", data_dir=tmp_path / "data")
    folder = tmp_path / "folder"
    folder.mkdir()
    (folder / "metadata.json").write_text("{}")  # neither Minari's (no main_data.hdf5 / data_format) nor a batch
    for path in (folder, tmp_path / "data.csv"):
        with pytest.raises(DatasetImportError, match=KNOWN_FORMATS):
            import_cache_path(path, tmp_path / "data")
    found = r"found a directory with \['metadata.json'\]"
    with pytest.raises(DatasetImportError, match=rf"folder: {KNOWN_FORMATS}, {found}"):
        import_dataset(folder, data_dir=tmp_path / "data")
    assert not (tmp_path / "data").exists()  # nothing converted, nothing cached


class NpzFormat(DatasetFormat):
    """A format registered by a test: ``*.npz`` with ``obs [N+1, d]``, ``act [N, a]``, ``rew [N]`` (one episode that
    ends in a terminal). The dispatcher is not edited to read it."""

    name = "test_npz"
    expects = "a test .npz file (obs, act, rew)"

    def locate(self, path):
        return path if path.is_file() and path.suffix == ".npz" else None

    def convert(self, location, check):
        with np.load(location) as f:
            obs, act, rew = (np.asarray(f[k], dtype=np.float32) for k in ("obs", "act", "rew"))
        check.sizes("obs", obs.shape[1], "act", act.shape[1])
        term = np.zeros(rew.shape[0], dtype=bool)
        term[-1] = True
        data = transitions(obs[:-1], act, obs[1:], rew, term, np.zeros_like(term))
        return Conversion(data, {"rows_in_file": int(rew.shape[0])}, env_id="Pendulum-v1", action_low=[-2.0],
                          action_high=[2.0])


@pytest.fixture
def npz_format():
    fmt = register_format(NpzFormat())
    try:
        yield fmt
    finally:
        FORMATS.pop(fmt.name)


def test_a_format_registered_elsewhere_is_read_cached_and_listed(tmp_path, npz_format):
    path = tmp_path / "pendulum.npz"
    np.savez(path, obs=np.arange(12, dtype=np.float64).reshape(4, 3), act=np.zeros((3, 1)), rew=np.ones(3))
    batch = import_dataset(path, data_dir=tmp_path / "data")
    assert importers.detect_format(path) == ("test_npz", path)
    assert batch.path == import_cache_path(path, tmp_path / "data")
    assert batch.path.name.startswith("import_pendulum-") and batch.num_transitions == 3
    assert batch.data["next", "observation"][0].tolist() == [3.0, 4.0, 5.0]
    assert batch.data["next", "terminated"].flatten().tolist() == [False, False, True]
    meta = batch.metadata
    assert meta["env_id"] == "Pendulum-v1" and meta["action_low"] == [-2.0] and meta["source"]["format"] == "test_npz"
    assert importers.describe_import(meta).startswith("import test_npz ")
    assert import_dataset(path, data_dir=tmp_path / "data").path == batch.path  # a cache hit
    with pytest.raises(DatasetImportError, match=r"pendulum.npz: key 'obs': expected 11 observation features"):
        import_dataset(path, env_id="Hopper-v5", data_dir=tmp_path / "other")
    # the unknown-format error now names it too, after the built-in ones
    (tmp_path / "data.csv").write_text("a,b\n")
    listed = r"a native batch directory \(metadata\.json \+ data/\) or a test \.npz file \(obs, act, rew\), found"
    with pytest.raises(DatasetImportError, match=rf"HDF5 file .*, {listed}"):
        import_dataset(tmp_path / "data.csv")
    with pytest.raises(ValueError, match="'test_npz' is already registered"):
        register_format(NpzFormat())


# ----------------------------------------------------------------------------------------------------------------
# normalised scores
# ----------------------------------------------------------------------------------------------------------------


def test_normalized_score_uses_the_published_d4rl_references():
    # by hand from D4RL's infos.py: hopper REF_MIN_SCORE -20.272305, REF_MAX_SCORE 3234.3
    assert normalized_score("Hopper-v5", 1000.0) == pytest.approx(100 * 1020.272305 / 3254.572305)
    assert normalized_score("hopper", -20.272305) == pytest.approx(0.0)
    assert normalized_score("Walker2d-v5", 4592.3) == pytest.approx(100.0)
    assert normalized_score("walker", 2296.9645) == pytest.approx(100 * 2295.335492 / 4590.670992)
    assert normalized_score("halfcheetah-medium-v2", 5927.4105235) == pytest.approx(50.0)
    assert normalized_score("HalfCheetah-v5", 12135.0) == pytest.approx(100.0)
    assert normalized_score("mujoco/ant/expert-v0", 3879.7) == pytest.approx(100.0)
    assert normalized_score("Ant-v5", -325.6 - 42.053) == pytest.approx(-1.0)
    assert D4RL_REF_SCORES["ant"] == (-325.6, 3879.7)
    for no_reference in ("Humanoid-v5", "antmaze-umaze-v2", "InvertedPendulum-v5", None):
        assert normalized_score(no_reference, 100.0) is None
    assert normalized_score("Hopper-v5", None) is None


# ----------------------------------------------------------------------------------------------------------------
# command lines
# ----------------------------------------------------------------------------------------------------------------


def test_collect_import_converts_caches_and_lists(tmp_path, capsys):
    from torchrl_bail.collect import _list_main, import_main

    path = write_hdf5(tmp_path / "hopper-x.hdf5", d4rl_arrays())
    data_dir = str(tmp_path / "data")
    assert import_main(["--import", path, "--env", "hopper", "--data-dir", data_dir]) == 0
    out = capsys.readouterr().out
    assert "hopper-x: converted at" in out and "env Hopper-v5: 9 transitions, 3 episodes" in out
    assert f"dataset={path} env=hopper" in out
    assert import_main([f"--import={path}", f"--data-dir={data_dir}"]) == 0
    assert "already cached" in capsys.readouterr().out
    assert _list_main(["--list", "--data-dir", data_dir]) == 0
    listing = capsys.readouterr().out
    assert "import_hopper-x-" in listing and f"import d4rl_hdf5 {path}" in listing
    assert import_main(["--import", path, "--env", "Walker2d-v5", "--data-dir", data_dir]) == 2
    assert "expected 17 observation features" in capsys.readouterr().err
    assert import_main(["--import", path, "--bogus"]) == 2


def _hopper_sized_random_file(tmp_path, *, drop=None) -> str:
    """410 transitions of Hopper-v5-sized random data: 5 timeout episodes, 2 falls, a trailing unfinished one."""
    rng = np.random.default_rng(0)
    arrays = d4rl_arrays(lengths=[60] * 5 + [40, 30, 40], ends=["timeout"] * 5 + ["terminal", "terminal", None])
    arrays["observations"] = rng.normal(size=arrays["observations"].shape)
    arrays["next_observations"] = rng.normal(size=arrays["observations"].shape)
    arrays["rewards"] = rng.uniform(0, 3, size=arrays["rewards"].shape)
    if drop:
        del arrays[drop]
    return write_hdf5(tmp_path / ("hopper-random-tiny.hdf5" if drop is None else "bad.hdf5"), arrays)


def _train_on(path, tmp_path, run_dir) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "torchrl_bail.train", f"dataset={path}", "env=hopper", "algo=bc",
           "preset=quick", "algo.epochs=0.002", "algo.batch_size=100", "algo.policy.hidden=[32,32]",
           "eval.episodes=2", "eval.max_steps=100", "env.max_episode_steps=100", "eval.every_epochs=0.001",
           "returns.horizon=60", "progress=false", "checkpoint.enabled=false",
           f"data_dir={tmp_path / 'data'}", f"hydra.run.dir={run_dir}"]
    env = {**os.environ, "RL_WARNINGS": "0", "HYDRA_FULL_ERROR": "1"}
    return subprocess.run(cmd, check=False, capture_output=True, text=True, env=env, timeout=300)


def test_train_on_an_imported_d4rl_file_end_to_end(tmp_path):
    run_dir = tmp_path / "run"
    proc = _train_on(_hopper_sized_random_file(tmp_path), tmp_path, run_dir)
    assert proc.returncode == 0, proc.stderr[-4000:]
    s = json.loads((run_dir / "summary.json").read_text())
    assert s["algo"] == "bc" and s["env"] == "Hopper-v5" and s["num_transitions"] == 410 and s["num_episodes"] == 8
    assert s["batch"] == "hopper-random-tiny" and s["batch_kind"] is None
    assert s["final_return"] == s["final_return"]  # not NaN
    assert s["final_return_normalized"] == pytest.approx(normalized_score("Hopper-v5", s["final_return"]))
    assert s["best_return_normalized"] == pytest.approx(normalized_score("Hopper-v5", s["best_return"]))
    assert s["dataset_mean_episode_return_normalized"] == pytest.approx(
        normalized_score("Hopper-v5", s["dataset_mean_episode_return"]))
    assert s["normalized_score_reference"] == {"random": -20.272305, "expert": 3234.3, "source": "d4rl"}
    assert imported_dirs(tmp_path / "data")  # converted into data_dir=, not into ~/.cache


def test_train_on_a_broken_file_is_one_clear_line(tmp_path):
    bad = _hopper_sized_random_file(tmp_path, drop="terminals")
    proc = _train_on(bad, tmp_path, tmp_path / "run")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert f"{bad}: key 'terminals': expected this key to be present" in proc.stderr


@pytest.mark.parametrize("next_obs", [True, False])
def test_a_row_both_terminal_and_timeout_is_a_true_terminal(tmp_path, next_obs):
    arrays = d4rl_arrays(next_obs=next_obs)
    arrays["timeouts"][2] = True  # row 2 ends the first episode with a fall: now on the time limit's last step too
    batch = import_dataset(write_hdf5(tmp_path / "both.hdf5", arrays), env_id="Hopper-v5", data_dir=tmp_path / "d")
    data = batch.data
    assert bool(data["next", "terminated"][2]) and not bool(data["next", "truncated"][2])
    assert bool(data["next", "done"][2]) and data["episode"][:4].tolist() == [0, 0, 0, 1]
    assert batch.metadata["terminal_and_timeout_rows"] == 1

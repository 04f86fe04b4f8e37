"""The local Minari dataset format: ``<root>/<dataset_id>/`` or its ``data/`` folder (``metadata.json`` and, for
Minari's HDF5 storage, ``main_data.hdf5`` with groups ``episode_<i>``). The HDF5 storage is parsed with h5py; the
``arrow``/``parquet`` storages need the optional ``minari`` package. The rules: :mod:`torchrl_bail.data.importers`."""

from __future__ import annotations

import json
import re
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
from tensordict import TensorDict

from torchrl_bail.data.formats.base import (
    Checker,
    Conversion,
    DatasetFormat,
    DatasetImportError,
    open_hdf5,
    register_format,
    terminal_wins,
    transitions,
)

__all__ = ["EXPORT_KEY", "MINARI_INSTALL", "MinariFormat", "convert_minari"]

#: the metadata block this package writes into the Minari datasets it exports (:mod:`torchrl_bail.data.minari_export`)
EXPORT_KEY = "torchrl_bail"
MINARI_INSTALL = 'pip install -e ".[minari]"'


class MinariFormat(DatasetFormat):
    """A local Minari dataset: its folder, its ``data/`` folder or its ``main_data.hdf5`` (location: ``data/``)."""

    name = "minari"
    expects = "a Minari dataset directory (data/metadata.json + data/main_data.hdf5)"
    priority = 10

    def locate(self, path: Path) -> Path | None:
        if path.is_file() and path.name == "main_data.hdf5" and (path.parent / "metadata.json").is_file():
            return path.parent
        if path.is_dir():
            for candidate in (path / "data", path):
                meta = candidate / "metadata.json"
                if meta.is_file() and (
                    (candidate / "main_data.hdf5").is_file() or _json_has(meta, "data_format")
                ):
                    return candidate
        return None

    def source_name(self, location: Path) -> str:
        try:
            dataset_id = json.loads((location / "metadata.json").read_text()).get("dataset_id")
        except (OSError, ValueError):
            dataset_id = None
        return str(dataset_id) if dataset_id else (location.parent.name if location.name == "data" else location.name)

    def convert(self, location: Path, check: Checker) -> Conversion:
        td, info = convert_minari(location, check)
        return Conversion(td, info, env_id=info.get("minari_env_id"), action_low=info.get("minari_action_low"),
                          action_high=info.get("minari_action_high"))


def _json_has(path: Path, key: str) -> bool:
    try:
        return key in json.loads(path.read_text())
    except (OSError, ValueError):
        return False


def _minari_metadata(data_dir: Path) -> dict[str, Any]:
    meta_file = data_dir / "metadata.json"
    try:
        meta = json.loads(meta_file.read_text())
    except ValueError as err:
        raise DatasetImportError(f"{meta_file}: expected valid JSON (Minari dataset metadata), found {err}") from None
    if not isinstance(meta, dict):
        raise DatasetImportError(f"{meta_file}: expected a JSON object, found {type(meta).__name__}")
    return meta


def _space(meta: Mapping[str, Any], key: str) -> dict | None:
    value = meta.get(key)
    if isinstance(value, str):
        try:
            value = json.loads(value)
        except ValueError:
            return None
    return value if isinstance(value, dict) else None


def _minari_env_id(meta: Mapping[str, Any]) -> str | None:
    spec = meta.get("env_spec")
    if isinstance(spec, str):
        try:
            spec = json.loads(spec)
        except ValueError:
            return None
    return spec.get("id") if isinstance(spec, dict) else None


def _minari_hdf5_episodes(data_dir: Path, check: Checker) -> Iterator[tuple[str, dict[str, Any]]]:
    import h5py

    main = data_dir / "main_data.hdf5"
    if not main.is_file():
        check.fail(None, "main_data.hdf5 beside metadata.json (Minari's HDF5 storage)", "no such file")
    with open_hdf5(main) as f:
        names = [k for k in f if re.fullmatch(r"episode_\d+", k)]
        if not names:
            check.fail(None, "groups episode_<i> (Minari's HDF5 layout)", f"keys {sorted(f)[:10]}")
        for name in sorted(names, key=lambda k: int(k.split("_")[1])):
            group = f[name]
            episode: dict[str, Any] = {}
            for key in ("observations", "actions", "rewards", "terminations", "truncations"):
                if key not in group:
                    check.fail(f"{name}/{key}", "this key to be present", f"keys {sorted(group.keys())}")
                node = group[key]
                if not isinstance(node, h5py.Dataset):
                    check.fail(f"{name}/{key}", "a flat array (Box observation/action spaces only)",
                               f"a group with keys {sorted(node.keys())[:10]} (a Dict/Tuple space)")
                episode[key] = node[()]
            yield name, episode


def _minari_package_episodes(data_dir: Path, fmt: str) -> Iterator[tuple[str, dict[str, Any]]]:
    try:
        import minari
    except ImportError:
        raise DatasetImportError(
            f"{data_dir}: this Minari dataset is stored as {fmt!r}; reading it needs the optional minari package: "
            f"{MINARI_INSTALL} (HDF5-format Minari datasets are read without it)"
        ) from None
    dataset = minari.MinariDataset(data_dir)
    for episode in dataset.iterate_episodes():
        yield f"episode_{episode.id}", {key: getattr(episode, key) for key in
                                        ("observations", "actions", "rewards", "terminations", "truncations")}


def convert_minari(data_dir: Path, check: Checker) -> tuple[TensorDict, dict[str, Any]]:
    """The Minari dataset in ``data_dir`` as ``(transitions, info)`` (the rules: :mod:`torchrl_bail.data.importers`)."""
    meta = _minari_metadata(data_dir)
    fmt = str(meta.get("data_format", "hdf5"))
    source = data_dir / "main_data.hdf5" if fmt == "hdf5" else data_dir
    check.source = str(source)
    episodes = _minari_hdf5_episodes(data_dir, check) if fmt == "hdf5" else _minari_package_episodes(data_dir, fmt)
    parts: dict[str, list[np.ndarray]] = {k: [] for k in ("obs", "act", "next", "rew", "term", "trunc")}
    export = meta.get(EXPORT_KEY) if isinstance(meta.get(EXPORT_KEY), Mapping) else {}
    rows = empty = unflagged = 0
    last_unflagged = False
    sizes: tuple[int, int] | None = None
    for name, ep in episodes:
        obs, act, rew, term, trunc = _minari_episode_arrays(name, ep, check)
        sizes = _check_minari_sizes(name, obs, act, sizes, check)
        steps = rew.shape[0]
        if steps == 0:
            empty += 1
            continue
        trunc, last_unflagged = _minari_episode_end(name, term, trunc, bool(export), check)
        unflagged += last_unflagged
        obs32 = check.finite32(f"{name}/observations", obs)
        parts["obs"].append(obs32[:-1])
        parts["next"].append(obs32[1:])
        parts["act"].append(check.finite32(f"{name}/actions", act))
        parts["rew"].append(check.finite32(f"{name}/rewards", rew))
        parts["term"].append(term)
        parts["trunc"].append(trunc)
        rows += steps
    if rows == 0:
        check.fail(None, "at least one transition", f"no steps in any episode ({empty} empty episodes)")
    unfinished = bool(export.get("unfinished_final_episode")) and last_unflagged
    if unfinished:  # exported from a batch whose last episode was still running: it stays unfinished
        parts["trunc"][-1][-1] = False
        unflagged -= 1
    cat = {k: np.concatenate(v) for k, v in parts.items()}
    td = transitions(cat["obs"], cat["act"], cat["next"], cat["rew"], cat["term"], cat["trunc"])
    info: dict[str, Any] = {
        "rows_in_file": int(rows), "dropped_rows": 0, "placeholder_next_observation_rows": 0,
        "next_observation": "episode observations[t + 1]", "empty_episodes_skipped": empty,
        "episodes_without_end_flag": unflagged, "minari_data_format": fmt,
        "unfinished_final_episode": unfinished,
    }
    info.update(_minari_info(meta))
    return td, info


def _minari_episode_arrays(name: str, ep: Mapping[str, Any], check: Checker) -> tuple[np.ndarray, ...]:
    """One Minari episode's ``(observations, actions, rewards, terminations, truncations)``, checked: flat arrays,
    ``steps + 1`` observations and ``steps`` of everything else, boolean flags."""
    for key in ("observations", "actions"):
        if not isinstance(ep[key], np.ndarray):
            check.fail(f"{name}/{key}", "a flat array (Box observation/action spaces only)",
                       f"{type(ep[key]).__name__} (a Dict/Tuple space)")
    obs = check.matrix(f"{name}/observations", np.asarray(ep["observations"]))
    act = check.matrix(f"{name}/actions", np.asarray(ep["actions"]))
    rew = check.vector(f"{name}/rewards", np.asarray(ep["rewards"]))
    steps = rew.shape[0]
    check.rows(f"{name}/observations", obs, steps + 1, f"{name}/rewards' plus the final observation")
    for key, value in (("actions", act), ("terminations", ep["terminations"]),
                       ("truncations", ep["truncations"])):
        check.rows(f"{name}/{key}", np.asarray(value), steps, f"{name}/rewards")
    term = check.flags(f"{name}/terminations", np.asarray(ep["terminations"]))
    trunc = check.flags(f"{name}/truncations", np.asarray(ep["truncations"]))
    return obs, act, rew, term, trunc


def _check_minari_sizes(name: str, obs: np.ndarray, act: np.ndarray, sizes: tuple[int, int] | None,
                        check: Checker) -> tuple[int, int]:
    """The first episode's observation and action sizes (checked against the env's, when given); every later
    episode must have the same. Returns them."""
    if sizes is None:
        check.sizes(f"{name}/observations", obs.shape[1], f"{name}/actions", act.shape[1])
        return obs.shape[1], act.shape[1]
    if (obs.shape[1], act.shape[1]) != sizes:
        check.fail(f"{name}/observations", f"the sizes of the first episode ({sizes[0]} observation features, "
                   f"{sizes[1]} action dimensions)", f"({obs.shape[1]}, {act.shape[1]})")
    return sizes


def _minari_episode_end(name: str, term: np.ndarray, trunc: np.ndarray, exported: bool,
                        check: Checker) -> tuple[np.ndarray, bool]:
    """A non-empty episode's end flags: a flag on its last step only; one recorded without any gets a truncation.
    Returns ``(truncations, whether the last step had no flag)``."""
    if not exported:  # this package's own exports keep the batch's flags as recorded (gymnasium's, both may be set)
        trunc, _ = terminal_wins(term, trunc)
    early = (term | trunc)[:-1]
    if early.any():
        key = f"{name}/terminations" if term[:-1].any() else f"{name}/truncations"
        check.fail(key, "a flag only on an episode's last step", f"one at step {int(np.flatnonzero(early)[0])} "
                   f"of {term.shape[0]}")
    unflagged = not (term[-1] or trunc[-1])
    if unflagged:
        trunc = trunc.copy()
        trunc[-1] = True  # the recording stopped here: a truncation (the final observation is known)
    return trunc, unflagged


def _minari_info(meta: Mapping[str, Any]) -> dict[str, Any]:
    """What the batch records of the Minari dataset's metadata: its id, reference scores, algorithm, version, env
    and Box action bounds (the keys it has)."""
    info: dict[str, Any] = {}
    for key in ("dataset_id", "ref_min_score", "ref_max_score", "algorithm_name", "minari_version"):
        if meta.get(key) is not None:
            info[key] = meta[key]
    env_id = _minari_env_id(meta)
    if env_id:
        info["minari_env_id"] = env_id
    space = _space(meta, "action_space")
    if space and space.get("type") == "Box" and "low" in space and "high" in space:
        info["minari_action_low"] = [float(x) for x in np.ravel(space["low"])]
        info["minari_action_high"] = [float(x) for x in np.ravel(space["high"])]
    return info


register_format(MinariFormat())

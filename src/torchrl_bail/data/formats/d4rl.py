"""The D4RL-layout HDF5 format (``*.hdf5`` / ``*.h5``): flat ``observations``, ``actions``, ``rewards``,
``terminals``, ``timeouts`` and optionally ``next_observations``; read with h5py. How rows become transitions (episode
ends, dropped rows, placeholders) is described in :mod:`torchrl_bail.data.importers`."""

from __future__ import annotations

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

__all__ = ["D4RL_KEYS", "HDF5_SUFFIXES", "D4RLFormat", "convert_d4rl"]

#: the keys a D4RL-layout file must hold (``next_observations`` is optional)
D4RL_KEYS = ("observations", "actions", "rewards", "terminals", "timeouts")
HDF5_SUFFIXES = (".hdf5", ".h5")


class D4RLFormat(DatasetFormat):
    """A D4RL-layout HDF5 file; a ``.hdf5`` holding Minari's ``episode_<i>`` groups is sent to its Minari folder."""

    name = "d4rl"
    label = "d4rl_hdf5"
    expects = "a D4RL-layout HDF5 file (*.hdf5 or *.h5)"
    priority = 20

    def locate(self, path: Path) -> Path | None:
        return path if path.is_file() and path.suffix.lower() in HDF5_SUFFIXES else None

    def check(self, location: Path) -> None:
        if _is_minari_layout(location):
            raise DatasetImportError(
                f"{location}: expected D4RL keys {list(D4RL_KEYS)}, found Minari episode_<i> groups; pass the Minari "
                "dataset folder (the one holding data/metadata.json and data/main_data.hdf5) instead"
            )

    def convert(self, location: Path, check: Checker) -> Conversion:
        return Conversion(*convert_d4rl(location, check))


def _is_minari_layout(path: Path) -> bool:
    """A ``.hdf5`` with ``episode_<i>`` groups and no ``observations``: Minari's ``main_data.hdf5`` layout."""
    with open_hdf5(path) as f:
        keys = list(f.keys())
    return "observations" not in keys and bool(keys) and all(k.startswith("episode_") for k in keys)


def _read_dataset(f, key: str, check: Checker) -> np.ndarray:
    import h5py

    node = f[key]
    if not isinstance(node, h5py.Dataset):
        check.fail(key, "an array (HDF5 dataset)", f"a {type(node).__name__}")
    return node[()]


def _d4rl_is_minari(path: Path) -> bool:
    """A ``.hdf5`` with ``episode_<i>`` groups and no ``observations``: Minari's ``main_data.hdf5`` layout."""
    with open_hdf5(path) as f:
        keys = list(f.keys())
    return "observations" not in keys and bool(keys) and all(k.startswith("episode_") for k in keys)


def convert_d4rl(path: Path, check: Checker) -> tuple[TensorDict, dict[str, Any]]:
    """The D4RL-layout file at ``path`` as ``(transitions, info)`` (the rules: :mod:`torchrl_bail.data.importers`)."""
    with open_hdf5(path) as f:
        keys = sorted(f.keys())
        if not keys:
            check.fail(None, f"a D4RL dataset with keys {list(D4RL_KEYS)}", "an empty HDF5 file (no keys)")
        for key in D4RL_KEYS:
            if key not in f:
                extra = (" (timeouts mark time-limit truncations; without them the episode boundaries are unknown)"
                         if key == "timeouts" else "")
                check.fail(key, f"this key to be present{extra}", f"keys {keys}")
        raw = {key: _read_dataset(f, key, check) for key in D4RL_KEYS}
        has_next = "next_observations" in f
        if has_next:
            raw["next_observations"] = _read_dataset(f, "next_observations", check)
    ignored = [k for k in keys if k not in raw]

    obs = check.matrix("observations", raw["observations"])
    n = obs.shape[0]
    if n == 0:
        check.fail("observations", "at least one transition", "0 rows (an empty dataset)")
    act = check.matrix("actions", raw["actions"])
    rew = check.vector("rewards", raw["rewards"])
    for key, value in (("actions", act), ("rewards", rew), ("terminals", raw["terminals"]),
                       ("timeouts", raw["timeouts"])):
        check.rows(key, value, n, "observations")
    term = check.flags("terminals", raw["terminals"])
    trunc = check.flags("timeouts", raw["timeouts"])
    if has_next:
        nxt = check.matrix("next_observations", raw["next_observations"])
        check.rows("next_observations", nxt, n, "observations")
        if nxt.shape[1] != obs.shape[1]:
            check.fail("next_observations", f"{obs.shape[1]} features (as many as 'observations')",
                       f"{nxt.shape[1]}")
    check.sizes("observations", obs.shape[1], "actions", act.shape[1])
    trunc, both = terminal_wins(term, trunc)
    obs = check.finite32("observations", obs)
    act = check.finite32("actions", act)
    rew = check.finite32("rewards", rew)

    done = term | trunc
    info: dict[str, Any] = {"rows_in_file": int(n), "ignored_keys": ignored, "terminal_and_timeout_rows": both,
                            "unfinished_final_episode": not bool(done[-1])}
    if has_next:
        nxt = check.finite32("next_observations", nxt)
        info.update(next_observation="next_observations", dropped_rows=0, placeholder_next_observation_rows=0)
        return transitions(obs, act, nxt, rew, term, trunc), info

    # no next_observations: the next row's observation within the episode (see the module doc for episode ends)
    nxt = np.empty_like(obs)
    nxt[:-1] = obs[1:]
    nxt[-1] = obs[-1]
    nxt[term] = obs[term]  # placeholder: a terminal's next state is never bootstrapped from
    drop = trunc.copy()
    drop[-1] |= not done[-1]  # the trailing unfinished episode's last row: its next observation is unknown
    new_trunc = np.zeros(n, dtype=bool)
    new_trunc[:-1] = trunc[1:] & ~done[:-1]  # the row before a dropped timeout row ends its (shortened) episode
    keep = ~drop
    if not keep.any():
        check.fail(None, "at least one transition with a known next observation (the file has no "
                         "'next_observations')", f"{n} rows, every one the last step of a timeout episode")
    info.update(next_observation="shifted observations", dropped_rows=int(drop.sum()),
                placeholder_next_observation_rows=int(term.sum()))
    td = transitions(obs[keep], act[keep], nxt[keep], rew[keep], term[keep], new_trunc[keep])
    return td, info


register_format(D4RLFormat())

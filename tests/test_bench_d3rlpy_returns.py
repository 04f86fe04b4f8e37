"""The side-by-side benchmark's two matching steps, without d3rlpy: the data it hands d3rlpy and the constants."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from _hopper_batches import native_batch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from bench_d3rlpy_returns import compose_run, d3rlpy_arrays, matched_constants, schedule  # noqa: E402


def d3rlpy_transitions(arrays: dict) -> tuple[np.ndarray, ...]:
    """The transitions d3rlpy 2.8's MDPDataset makes of these arrays: episodes end at terminals | timeouts; a
    terminated episode keeps every row, a timeout episode drops its last row, which only provides the final next
    observation (d3rlpy's ``Episode.transition_count`` and ``BasicTransitionPicker``)."""
    ends = np.flatnonzero((arrays["terminals"] + arrays["timeouts"]) > 0)
    obs, act, rew, nxt, term = [], [], [], [], []
    start = 0
    for end in ends:
        terminal = bool(arrays["terminals"][end])
        stop = end + 1 if terminal else end
        rows = np.arange(start, stop)
        obs.append(arrays["observations"][rows])
        act.append(arrays["actions"][rows])
        rew.append(arrays["rewards"][rows])
        following = arrays["observations"][np.minimum(rows + 1, end)]
        if terminal:
            following[-1] = 0.0  # d3rlpy puts zeros there; never bootstrapped from
        nxt.append(following)
        term.append(np.r_[np.zeros(len(rows) - 1), float(terminal)])
        start = end + 1
    return tuple(np.concatenate(x) for x in (obs, act, rew, nxt, term))


def test_d3rlpy_gets_exactly_the_batch_transitions(tmp_path):
    batch = native_batch(tmp_path / "batch")  # terminated, truncated and a final unfinished episode
    obs, act, rew, nxt, term = d3rlpy_transitions(d3rlpy_arrays(batch))
    data = batch.data
    terminated = data["next", "terminated"].numpy()[:, 0]
    assert np.array_equal(obs, data["observation"].numpy()) and np.array_equal(act, data["action"].numpy())
    assert np.array_equal(rew, data["next", "reward"].numpy()) and np.array_equal(term, terminated)
    assert np.array_equal(nxt[~terminated], data["next", "observation"].numpy()[~terminated])


@pytest.mark.parametrize("algo, updates, interval", [("bc", 2000, 200), ("bcq", 5000, 500), ("bear", 5000, 500)])
def test_d3rlpy_gets_the_study_constants_and_schedule(tmp_path, algo, updates, interval):
    batch = native_batch(tmp_path / "batch")
    cfg = compose_run(batch.path, "hopper", algo, 1, "study", [])
    assert schedule(cfg) == (updates, interval)
    constants = matched_constants(cfg)
    if algo == "bc":
        assert constants == {"bc_hidden": [400, 300], "lr": {"bc": 1e-3}, "bc_batch": 1000}
        return
    assert (constants["actor_hidden"], constants["vae_hidden"], constants["batch"]) == ([400, 300], [750, 750], 100)
    assert constants["lr"]["critic"] == 1e-3 and constants["n_target"] == 10 and constants["lmbda"] == 0.75
    if algo == "bear":
        assert (constants["n_match"], constants["kernel_sigma"], constants["warmup"]) == (5, 10.0, 500)

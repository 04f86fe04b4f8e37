"""Monte-Carlo returns and the authors' "gain" augmentation (paper Sec. 4, augmented returns), against hand values and
brute force."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from tensordict import TensorDict

from torchrl_bail.data import monte_carlo_returns


def _td(obs, rewards, episode) -> TensorDict:
    obs = torch.as_tensor(obs, dtype=torch.float32)
    obs = obs.unsqueeze(-1) if obs.ndim == 1 else obs
    n = obs.shape[0]
    return TensorDict({"observation": obs, "episode": torch.as_tensor(episode, dtype=torch.int64),
                       "next": {"reward": torch.as_tensor(rewards, dtype=torch.float32).reshape(n, 1)}}, [n])


def _brute_force(td, gamma, horizon):
    """Direct transcription of paper Sec. 4, augmented returns: T real-or-borrowed rewards for episodes with L >= T."""
    obs = td["observation"].double()
    r = td["next", "reward"].reshape(-1).double().tolist()
    ep = td["episode"].tolist()
    out, i, n = [], 0, len(r)
    while i < n:
        j = i
        while j + 1 < n and ep[j + 1] == ep[i]:
            j += 1
        length = j - i + 1
        rr, o = r[i:j + 1], obs[i:j + 1]
        g = [sum(gamma ** (u - t) * rr[u] for u in range(t, length)) for t in range(length)] + [0.0]
        for t in range(length):
            if length >= horizon and t >= 1:
                remaining = length - t
                dist = [float((o[u] - o[length - 1]).norm()) for u in range(remaining + 1)]
                k = min(range(remaining + 1), key=lambda u: (dist[u], u))  # first argmin
                if length == horizon:  # exactly T rewards: the real ones, then t borrowed from s_k
                    value = g[t] + gamma**remaining * sum(gamma ** (u - k) * rr[u] for u in range(k, k + t))
                else:  # L > T: the code's formula with the gamma^T correction
                    value = g[t] + gamma**remaining * g[k] - gamma**horizon * g[k + t]
                out.append(value)
            else:
                out.append(g[t])
        i = j + 1
    return torch.tensor(out, dtype=torch.float64)


def test_spec_worked_example():
    td = _td([0.0, 3.0, 1.0, 2.0], [1.0, 2.0, 3.0, 4.0], [0, 0, 0, 0])
    assert monte_carlo_returns(td, gamma=0.5, horizon=4).tolist() == [3.25, 5.0, 5.875, 6.25]
    assert monte_carlo_returns(td, gamma=0.5, horizon=4, augment="none").tolist() == [3.25, 4.5, 5.0, 4.0]


def test_every_augmented_return_sums_exactly_T_rewards():
    # G_2 of the worked example = 3 + 0.5 * 4 + 0.25 * (2 + 0.5 * 3): the borrowed rewards start at s_1
    td = _td([0.0, 3.0, 1.0, 2.0], [1.0, 2.0, 3.0, 4.0], [0, 0, 0, 0])
    assert monte_carlo_returns(td, gamma=0.5, horizon=4)[2] == pytest.approx(3 + 0.5 * 4 + 0.25 * (2 + 0.5 * 3))


@pytest.mark.parametrize("horizon", [3, 5, 6])
def test_matches_brute_force_on_mixed_episodes(horizon):
    g = torch.Generator().manual_seed(horizon)
    lengths = [5, 2, 6, 3, 8, 1, 5, 4]  # some == T, some < T, some > T; the last one is unfinished
    episode = torch.cat([torch.full((n,), i) for i, n in enumerate(lengths)])
    n = episode.numel()
    obs = torch.randint(0, 3, (n, 2), generator=g).float()  # small integer states: many distance ties
    td = _td(obs, torch.randn(n, generator=g), episode)
    expected = _brute_force(td, 0.9, horizon)
    assert torch.allclose(monte_carlo_returns(td, gamma=0.9, horizon=horizon).double(), expected, atol=1e-5)


def test_short_episodes_true_terminals_and_the_unfinished_tail_are_plain_returns():
    # a fall (terminal after 2 steps), then an unfinished 3-step tail: both shorter than T
    td = _td([0.0, 1.0, 5.0, 6.0, 7.0], [1.0, 1.0, 2.0, 2.0, 2.0], [0, 0, 1, 1, 1])
    expected = [1 + 0.5, 1.0, 2 + 0.5 * 2 + 0.25 * 2, 2 + 0.5 * 2, 2.0]
    assert monte_carlo_returns(td, gamma=0.5, horizon=4).tolist() == expected


def test_first_state_untouched_and_t1_borrows_the_last_reward():
    td = _td([0.0, 3.0, 1.0, 2.0], [1.0, 2.0, 3.0, 4.0], [0, 0, 0, 0])
    plain = monte_carlo_returns(td, gamma=0.5, horizon=4, augment="none")
    gain = monte_carlo_returns(td, gamma=0.5, horizon=4)
    assert gain[0] == plain[0]
    assert gain[1] == pytest.approx(plain[1] + 0.5**3 * 4.0)  # k_1 = L-1: G_1 = g_1 + gamma^(L-1) r_(L-1)


def test_ties_go_to_the_first_index():
    # distances to the last state (0): 1, 1, 1, 0 -> window {0, 1, 2} for t=1.. picks k=0 on ties
    td = _td([1.0, -1.0, 1.0, 0.0], [1.0, 10.0, 100.0, 1000.0], [0, 0, 0, 0])
    gamma = 0.5
    g = monte_carlo_returns(td, gamma=gamma, horizon=4, augment="none").double()
    gain = monte_carlo_returns(td, gamma=gamma, horizon=4)
    # t=2: window {0, 1, 2}, all at distance 1 -> k = 0: borrows r_0, r_1
    assert gain[2] == pytest.approx(float(g[2] + gamma**2 * (1.0 + gamma * 10.0)))


def test_oracle_returns_and_errors():
    td = _td([0.0, 1.0], [1.0, 1.0], [0, 0])
    with pytest.raises(KeyError, match="oracle_return"):
        monte_carlo_returns(td, augment="oracle")
    td.set("oracle_return", torch.tensor([7.0, 8.0]))
    assert monte_carlo_returns(td, augment="oracle").tolist() == [7.0, 8.0]
    with pytest.raises(ValueError, match="augment"):
        monte_carlo_returns(td, augment="magic")
    with pytest.raises(ValueError, match="gamma"):
        monte_carlo_returns(td, gamma=0.0)
    with pytest.raises(ValueError, match="horizon"):
        monte_carlo_returns(td, horizon=0)


# -- any episode layout ----------------------------------------------------------------------------------------
def test_interleaved_episodes_get_their_own_returns():
    td = _td([0.0] * 6, [1.0] * 6, [0, 1, 0, 1, 0, 1])  # two envs stepped side by side
    assert monte_carlo_returns(td, gamma=1.0, horizon=100, augment="none").tolist() == [3, 3, 2, 2, 1, 1]


@settings(max_examples=40, deadline=None)
@given(lengths=st.lists(st.integers(1, 8), min_size=1, max_size=6), horizon=st.integers(2, 6),
       seed=st.integers(0, 2**16))
def test_any_interleaving_equals_a_plain_per_episode_loop(lengths, horizon, seed):
    g = torch.Generator().manual_seed(seed)
    # a random interleaving that keeps each episode's rows in time order; ids need not be sorted or dense
    labels = torch.cat([torch.full((n,), i) for i, n in enumerate(lengths)])
    labels = labels[torch.randperm(len(labels), generator=g)]
    ids = torch.randperm(50, generator=g)[: len(lengths)][labels] * 3
    n = len(ids)
    td = _td(torch.randint(0, 3, (n, 2), generator=g).float(), torch.randn(n, generator=g), ids)
    expected = torch.empty(n, dtype=torch.float64)
    for episode in ids.unique():
        rows = (ids == episode).nonzero().flatten()
        expected[rows] = _brute_force(td[rows], 0.9, horizon)
    for augment in ("gain", "none"):
        got = monte_carlo_returns(td, gamma=0.9, horizon=horizon, augment=augment)
        if augment == "gain":
            assert torch.allclose(got.double(), expected, atol=1e-5)
        # exactly the numbers of the same episodes laid out in blocks
        order = torch.argsort(ids, stable=True)
        blocks = monte_carlo_returns(td[order], gamma=0.9, horizon=horizon, augment=augment)
        assert torch.equal(got[order], blocks)


def test_collector_ids_column_ids_and_batched_rollouts():
    td = _td([0.0] * 6, [1.0] * 6, [0, 1, 0, 1, 0, 1])
    expected = monte_carlo_returns(td, gamma=0.5, horizon=2)
    column = td.clone().set("episode", td["episode"].unsqueeze(-1))  # [N, 1] ids
    assert torch.equal(monte_carlo_returns(column, gamma=0.5, horizon=2), expected)
    collector = td.exclude("episode").set(("collector", "traj_ids"), td["episode"])
    assert torch.equal(monte_carlo_returns(collector, gamma=0.5, horizon=2), expected)
    # a [envs, time] rollout: read row by row, the returns come back in its shape
    rollout = _td([0.0] * 6, [1.0, 2.0, 3.0, 4.0, 5.0, 6.0], [0, 0, 0, 1, 1, 1]).reshape(2, 3)
    assert monte_carlo_returns(rollout, gamma=1.0, horizon=10).tolist() == [[6, 5, 3], [15, 11, 6]]


def test_missing_or_misshapen_ids_are_named():
    td = _td([0.0, 1.0], [1.0, 1.0], [0, 0])
    with pytest.raises(ValueError, match=r"no episode ids: expected an 'episode' entry .*'traj_ids'"):
        monte_carlo_returns(td.exclude("episode"))
    with pytest.raises(ValueError, match=r"episode ids 'episode' have shape \(2, 2\)"):
        monte_carlo_returns(td.set("episode", torch.zeros(2, 2, dtype=torch.int64)))

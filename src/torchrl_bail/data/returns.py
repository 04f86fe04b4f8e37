"""Monte-Carlo returns ``G_i`` of an offline batch (paper Sec. 4, augmented returns).

``augment="none"`` gives the plain discounted return of each episode (no bootstrapping; a true terminal simply
ends the sum). ``augment="gain"`` is the authors' final heuristic for time-limit episodes: every state of an
episode of length ``L >= horizon`` gets a return of exactly ``horizon`` rewards, the ``L - t`` real ones that
remain, followed by ``t`` rewards borrowed from the same episode, starting at the early state ``s_k`` closest
(Euclidean, raw observations) to the episode's last observation, with ``k`` the *first* minimiser over the
prefix window ``{0, ..., L - t}``::

    G_t = g_t + gamma^(L-t) * g_k  -  gamma^horizon * g_(k+t)        (t >= 1; G_0 = g_0; g_L := 0)

The decision uses the episode length only; episodes shorter than ``horizon`` — falls, and the unfinished
episode at the end of the batch — keep their plain returns. ``augment="oracle"`` returns the batch's stored
``oracle_return`` (collected from the real continuation, supp. D.1).

Episodes are told apart by their ids (``episode``, or TorchRL collectors' ``("collector", "traj_ids")``), not by
where they sit: the rows of one episode must be in time order, but episodes may be interleaved (several envs
stepped side by side, rows gathered from a buffer in write order). Ids must therefore name one episode each
(what both keys do). A contiguous layout (each episode one block, as :func:`~torchrl_bail.data.validate_batch`
guarantees) is computed as it is; any other is brought into episode order and the returns put back in place.

Examples:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> done = torch.tensor([False, False, False, True]).unsqueeze(-1)
    >>> td = TensorDict({"observation": torch.tensor([[0.0], [3.0], [1.0], [2.0]]),
    ...                  "episode": torch.zeros(4, dtype=torch.int64),
    ...                  "next": {"reward": torch.tensor([[1.0], [2.0], [3.0], [4.0]]), "done": done}}, [4])
    >>> monte_carlo_returns(td, gamma=0.5, horizon=4).tolist()
    [3.25, 5.0, 5.875, 6.25]
    >>> monte_carlo_returns(td, gamma=0.5, horizon=4, augment="none").tolist()
    [3.25, 4.5, 5.0, 4.0]
"""

from __future__ import annotations

from typing import Literal

import torch
from tensordict import TensorDictBase

__all__ = ["EPISODE_KEYS", "discounted_returns", "episode_order", "episode_segments", "monte_carlo_returns"]

#: where the episode ids are read, first found first: this package's batches, then TorchRL collectors' output
EPISODE_KEYS = ("episode", ("collector", "traj_ids"))

_CHUNK_ELEMENTS = 2**25  # observations processed at once when augmenting (float64): ~256 MB


def episode_segments(episode: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Start index and length of each contiguous episode block of ``episode`` ids ``[N]``."""
    change = torch.ones_like(episode, dtype=torch.bool)
    change[1:] = episode[1:] != episode[:-1]
    starts = change.nonzero().flatten()
    ends = torch.cat([starts[1:], torch.tensor([episode.numel()])])
    return starts, ends - starts


def episode_order(episode: torch.Tensor) -> torch.Tensor | None:
    """``None`` when every episode id of ``episode`` ``[N]`` fills one contiguous block; otherwise the permutation
    (a stable sort by id) that makes them so, keeping each episode's rows in their order."""
    starts, _ = episode_segments(episode)
    if len(starts) == episode.unique().numel():
        return None
    return torch.argsort(episode, stable=True)


def discounted_returns(rewards: torch.Tensor, episode: torch.Tensor, gamma: float) -> torch.Tensor:
    """Plain discounted reward-to-go within each episode, float64 ``[N]`` (episodes may be interleaved: see the
    module doc).

    Vectorised over episodes: the backward recursion ``g_t = r_t + gamma * g_(t+1)`` runs once per distance
    to the episode's end, each step updating every episode at once (``max episode length`` small tensor ops,
    ``O(N)`` work). Episode ends come from the ``episode`` ids, so the unfinished episode at the end of a batch
    is summed to its last stored reward.
    """
    rewards = rewards.reshape(-1).double()
    order = episode_order(episode)
    if order is not None:
        out = torch.empty_like(rewards)
        out[order] = discounted_returns(rewards[order], episode[order], gamma)
        return out
    starts, lengths = episode_segments(episode)
    last_row = torch.repeat_interleave(starts + lengths - 1, lengths)
    to_end = last_row - torch.arange(rewards.numel())
    order = torch.argsort(to_end, stable=True)
    counts = torch.bincount(to_end)
    g = rewards.clone()
    for rows in order.split(counts.tolist())[1:]:  # distance 0 (the last rows) keeps g = r
        g[rows] += gamma * g[rows + 1]
    return g


def _prefix_first_argmin(dist: torch.Tensor) -> torch.Tensor:
    """For ``dist [E, L]``: ``idx[e, u]`` = the first index of the minimum of ``dist[e, :u+1]``."""
    running_min = torch.cummin(dist, dim=1).values
    record = torch.ones_like(dist, dtype=torch.bool)
    record[:, 1:] = dist[:, 1:] < running_min[:, :-1]  # strictly below all earlier: a new first minimum
    positions = torch.arange(dist.shape[1]).expand_as(dist)
    return torch.cummax(torch.where(record, positions, torch.zeros_like(positions)), dim=1).values


def _gain(obs: torch.Tensor, g: torch.Tensor, gamma: float, horizon: int) -> torch.Tensor:
    """Augmented returns of ``E`` episodes of one length ``L``: ``obs [E, L, d]``, ``g [E, L]`` -> ``[E, L]``."""
    n_eps, length = g.shape
    dist = torch.linalg.vector_norm(obs - obs[:, -1:], dim=-1)
    first_argmin = _prefix_first_argmin(dist)
    t = torch.arange(1, length)
    remaining = length - t  # n_t
    k = first_argmin[:, remaining]  # [E, L-1]
    g_ext = torch.cat([g, torch.zeros(n_eps, 1, dtype=g.dtype)], dim=1)  # g_L := 0
    borrowed = g_ext.gather(1, k) * gamma ** remaining.double() - gamma**horizon * g_ext.gather(1, k + t)
    out = g.clone()
    out[:, 1:] += borrowed
    return out


def _episode_ids(td: TensorDictBase) -> torch.Tensor:
    """The episode ids ``[N]`` of a flat batch, from the first of :data:`EPISODE_KEYS` it holds."""
    for key in EPISODE_KEYS:
        ids = td.get(key, None)
        if ids is not None:
            break
    else:
        raise ValueError(
            "monte_carlo_returns: the batch has no episode ids: expected an 'episode' entry (one id per episode) or "
            "TorchRL collectors' ('collector', 'traj_ids'); keys present: "
            f"{sorted(map(str, td.keys(True, True)))}"
        )
    if ids.shape == td.batch_size + (1,):
        ids = ids.squeeze(-1)
    if ids.shape != td.batch_size:
        raise ValueError(f"monte_carlo_returns: episode ids {key!r} have shape {tuple(ids.shape)}; expected the "
                         f"batch shape {tuple(td.batch_size)} (or with a trailing 1)")
    return ids


def monte_carlo_returns(
    td: TensorDictBase,
    *,
    gamma: float = 0.99,
    horizon: int = 1000,
    augment: Literal["gain", "none", "oracle"] = "gain",
) -> torch.Tensor:
    """Monte-Carlo returns ``G`` (float32, the batch shape) of a TED batch, as the module doc describes.

    Args:
        td: a TED TensorDict with ``observation``, ``("next", "reward")`` and episode ids (``episode`` or
            ``("collector", "traj_ids")``, shaped like the batch or with a trailing 1). A batch of more than
            one dimension (e.g. ``[envs, time]``) is read row by row (``td.reshape(-1)``).

    Keyword Args:
        gamma (float): discount in ``(0, 1]``. Defaults to ``0.99``.
        horizon (int): ``T``; episodes of length ``>= T`` are augmented. Defaults to ``1000``.
        augment (str): ``"gain"`` (the authors' final heuristic), ``"none"`` or ``"oracle"``.
            Defaults to ``"gain"``.
    """
    if augment not in ("gain", "none", "oracle"):
        raise ValueError(f"augment must be 'gain', 'none' or 'oracle', got {augment!r}")
    if not 0.0 < gamma <= 1.0:
        raise ValueError(f"gamma must be in (0, 1], got {gamma}")
    if int(horizon) < 1:
        raise ValueError(f"horizon must be >= 1, got {horizon}")
    if augment == "oracle":
        if "oracle_return" not in td.keys():
            raise KeyError("augment='oracle' needs the batch's 'oracle_return' key; collect an oracle batch "
                           "(batch.oracle.enabled=true) or use returns.augment=gain")
        return td.get("oracle_return").reshape(td.batch_size).to(torch.float32)
    if td.batch_dims != 1:
        return monte_carlo_returns(td.reshape(-1), gamma=gamma, horizon=horizon,
                                   augment=augment).reshape(td.batch_size)
    episode = _episode_ids(td)
    order = episode_order(episode)
    if order is not None:
        out = torch.empty(td.batch_size, dtype=torch.float32)
        needed = td.select("observation", ("next", "reward"), strict=False)
        out[order] = _block_returns(needed[order], episode[order], gamma, int(horizon), augment)
        return out
    return _block_returns(td, episode, gamma, int(horizon), augment)


def _block_returns(td: TensorDictBase, episode: torch.Tensor, gamma: float, horizon: int, augment: str) -> torch.Tensor:
    """:func:`monte_carlo_returns` of a batch whose episodes are contiguous blocks."""
    g = discounted_returns(td.get(("next", "reward")), episode, gamma)
    if augment == "none":
        return g.to(torch.float32)
    starts, lengths = episode_segments(episode)
    long_eps = (lengths >= horizon).nonzero().flatten()
    obs = td.get("observation")
    out = g.clone()
    for length in lengths[long_eps].unique().tolist():
        same = long_eps[lengths[long_eps] == length]
        per_chunk = max(1, _CHUNK_ELEMENTS // (length * obs.shape[-1]))
        for chunk in same.split(per_chunk):
            rows = (starts[chunk].unsqueeze(1) + torch.arange(length)).reshape(-1)
            ep_obs = obs[rows].double().reshape(len(chunk), length, -1)
            out[rows] = _gain(ep_obs, g[rows].reshape(len(chunk), length), gamma, horizon).reshape(-1)
    return out.to(torch.float32)

"""Normalised scores: ``100 * (return - random) / (expert - random)`` against this library's own gymnasium v5
references where an env has both (:data:`V5_RANDOM_SCORES`, :data:`V5_EXPERT_SCORES`), else D4RL's published reference
returns (hopper, walker2d, halfcheetah, ant), or a dataset's own ``ref_min_score`` / ``ref_max_score`` (a Minari
dataset's, e.g. for Humanoid, which D4RL does not cover). ``summary.json`` carries them (``<key>_normalized``, with
``normalized_score_reference`` naming the source) and the report averages them.

Examples:
    >>> normalized_score("Hopper-v5", 3234.3)
    100.0
    >>> round(normalized_score("walker", 1.629008), 6), normalized_score("Humanoid-v5", 5000.0)
    (0.0, None)
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any

__all__ = ["D4RL_REF_SCORES", "V5_EXPERT_SCORES", "V5_RANDOM_SCORES", "normalized_score", "score_reference"]

#: uniform-random policy, mean undiscounted return over 100 episodes on the gymnasium v5 envs (1000-step limit),
#: measured by ``python results/reference_scores.py`` (the record, with seeds and versions:
#: ``results/reference_scores.json``; a test checks the two agree)
V5_RANDOM_SCORES: dict[str, float] = {
    "Hopper-v5": 16.669,
    "Walker2d-v5": 1.77,
    "HalfCheetah-v5": -282.487,
    "Ant-v5": -48.048,
    "Humanoid-v5": 112.599,
}
#: the expert reference on the gymnasium v5 envs: the mean episode return of the env's ``opt_det`` batch (this
#: library's paper-scale SAC run's final policy, deterministic, over its 10^6 steps), copied from
#: ``results/reference_scores.json``'s ``ref_max_score`` (``python results/reference_scores.py --expert-only``; a test
#: checks the two agree). Empty until an env's paper-scale SAC run and its ``opt_det`` batch exist: until then scores on
#: that env are normalised by D4RL's -v2 references
V5_EXPERT_SCORES: dict[str, float] = {}

#: D4RL reference returns (random policy, expert policy) per MuJoCo env, as published in D4RL's ``d4rl/infos.py``
#: (``REF_MIN_SCORE`` / ``REF_MAX_SCORE``; identical for every dataset of an env and for v0/v1/v2). They were measured
#: on the mujoco-py ``-v2`` envs: on gymnasium v5 the normalised score is an approximation (rewards are alike, but
#: not bit-identical), good for comparing with published D4RL tables, not for exact claims.
D4RL_REF_SCORES: dict[str, tuple[float, float]] = {
    # env          REF_MIN_SCORE  REF_MAX_SCORE
    "hopper": (-20.272305, 3234.3),
    "walker2d": (1.629008, 4592.3),
    "halfcheetah": (-280.178953, 12135.0),
    "ant": (-325.6, 3879.7),
}
#: names this package uses for the same envs (``conf/env/walker.yaml`` is ``walker``)
_ENV_ALIASES = {"walker": "walker2d"}


def _d4rl_env(env_id: str | None) -> str | None:
    """``Hopper-v5`` / ``hopper`` / ``hopper-medium-v2`` / ``mujoco/hopper/expert-v0`` -> ``hopper``; else None."""
    if not env_id:
        return None
    for token in re.split(r"[/\-_\s]+", str(env_id).lower()):
        token = _ENV_ALIASES.get(token, token)
        if token in D4RL_REF_SCORES:
            return token
    return None


def score_reference(env_id: str | None, metadata: Mapping[str, Any] | None = None) -> tuple[float, float, str] | None:
    """``(random, expert, source)`` reference returns for ``env_id``, or ``None`` when there is none.

    A gymnasium v5 id with both v5 references measured here (:data:`V5_RANDOM_SCORES`, :data:`V5_EXPERT_SCORES`):
    those (source ``"v5"``); else the D4RL table (:data:`D4RL_REF_SCORES`) for hopper, walker2d, halfcheetah and ant;
    otherwise the ``ref_min_score`` / ``ref_max_score`` a Minari dataset stores in its metadata (copied into the
    imported batch's metadata), e.g. for Humanoid, which D4RL does not cover.
    """
    if env_id in V5_EXPERT_SCORES and env_id in V5_RANDOM_SCORES:
        return V5_RANDOM_SCORES[env_id], V5_EXPERT_SCORES[env_id], "v5"
    name = _d4rl_env(env_id)
    if name is not None:
        low, high = D4RL_REF_SCORES[name]
        return low, high, "d4rl"
    if metadata is not None:
        low, high = metadata.get("ref_min_score"), metadata.get("ref_max_score")
        if low is not None and high is not None and float(high) != float(low):
            return float(low), float(high), "dataset"
    return None


def normalized_score(env_id: str | None, score: float | None, *,
                     metadata: Mapping[str, Any] | None = None) -> float | None:
    """D4RL normalised score ``100 * (score - random) / (expert - random)``; ``None`` without a reference.

    ``env_id`` may be a gymnasium id (``Hopper-v5``), this package's env name (``walker``), a D4RL dataset name
    (``halfcheetah-medium-v2``) or a Minari id (``mujoco/ant/expert-v0``). See :func:`score_reference`.

    Examples:
        >>> normalized_score("HalfCheetah-v5", -280.178953)
        0.0
        >>> round(normalized_score("ant-medium-v2", 1777.05), 3)
        50.0
        >>> normalized_score("Hopper-v5", None) is None, normalized_score("InvertedPendulum-v5", 10.0)
        (True, None)
        >>> normalized_score("Humanoid-v5", 60.0, metadata={"ref_min_score": 10.0, "ref_max_score": 110.0})
        50.0
    """
    if score is None:
        return None
    ref = score_reference(env_id, metadata)
    if ref is None:
        return None
    low, high, _ = ref
    return 100.0 * (float(score) - low) / (high - low)

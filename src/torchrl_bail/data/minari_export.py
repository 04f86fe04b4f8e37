"""Export a batch as a Minari dataset, through Minari's own API (``minari.create_dataset_from_buffers``).

``python -m torchrl_bail.collect --export-minari bail/hopper-ddpg05-b1-v0 +exp=hopper_ddpg05`` makes or finds the
batch and calls :func:`export_minari`; the dataset lands in Minari's data path (``$MINARI_DATASETS_PATH``, else
``~/.minari/datasets``), where ``minari.load_dataset``, TorchRL's ``MinariExperienceReplay(...,
load_from_local_minari=True)`` and this package's ``dataset=`` importer read it.

How a batch becomes Minari episodes (nothing is re-simulated):

* Episodes are the batch's ``episode`` blocks, and each ends exactly where the batch's flags say:
  ``terminations`` = ``("next", "terminated")``, ``truncations`` = ``("next", "truncated")``.
* ``observations`` of an episode of ``T`` steps is ``[T + 1, obs]``: the ``T`` observations and the last row's
  ``("next", "observation")``. Inside an episode ``("next", "observation")[t]`` must equal ``observation[t + 1]``
  (Minari stores one observation sequence per episode); a batch where it does not cannot be exported and the
  error names the row.
* A batch's last episode may be unfinished (a collection stops after ``batch.steps`` transitions): it is exported
  with neither flag on its last step, and the metadata says so (``torchrl_bail.unfinished_final_episode``), so the
  importer reads it back as the same unfinished episode instead of a truncation.
* Values are stored as the batch holds them: float32 observations, actions and rewards. The dataset's observation
  space is therefore the env's with ``dtype=float32`` (same shape and bounds); its action space is the env's.
  Keys beyond the TED transition (e.g. an oracle batch's ``oracle_return``) are not exported; the metadata lists
  them (``torchrl_bail.keys_not_exported``).

Metadata: Minari's own fields (``dataset_id``, ``env_spec`` with the collection's time limit so that
``recover_environment()`` gives the v5 env the batch came from, ``eval_env_spec`` = the registered env,
``algorithm_name``, ``description``, ``author``, ``requirements``, ``ref_min_score`` / ``ref_max_score``), and a
``torchrl_bail`` block: the batch's complete ``metadata.json`` (recipe, recipe hash, behaviour seed, library
versions at collection, or the import's source), the library versions of the export, how the reference scores were
obtained, the unfinished final episode, the keys left out.

Reference scores (v5, measured here; see ``results/reference_scores.json``): ``ref_min_score`` is the mean return
of a uniform-random policy over 100 episodes (:data:`V5_RANDOM_SCORES`); ``ref_max_score`` is the mean return of this
library's paper-scale SAC run's final policy (:data:`~torchrl_bail.data.scores.V5_EXPERT_SCORES`), written once the
env has one, or when given (``--ref-max-score``); for an env outside the table, a given ``ref_max_score`` makes Minari
measure ``ref_min_score`` itself (its random policy, 100 episodes). Minari itself stores ``ref_min_score`` only
together with ``ref_max_score``; here the random reference is written either way (Minari's
``get_normalized_score`` still needs both).

Writes are atomic: the dataset is built under a hidden temporary root beside Minari's data path (Minari lists
neither it nor anything in it) and renamed into place; ``force=True`` replaces an existing dataset only once the new
one is complete. A malformed id, an existing id without ``force``, an env gymnasium cannot make, or a batch that
breaks the rules above raise :class:`MinariExportError` before anything is written.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as _dt
import os
import shutil
import uuid
import warnings
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from torchrl_bail.data.batch import REQUIRED_KEYS, OfflineBatch, library_versions
from torchrl_bail.data.importers import EXPORT_KEY, MINARI_INSTALL
from torchrl_bail.data.scores import V5_EXPERT_SCORES, V5_RANDOM_SCORES

__all__ = [
    "EXPORT_KEY",
    "V5_RANDOM_SCORES",
    "MinariExportError",
    "check_dataset_id",
    "export_minari",
    "minari_episodes",
    "reference_scores",
]

MINARI_ROOT_ENV = "MINARI_DATASETS_PATH"
RANDOM_HOW = ("uniform-random policy, mean return over 100 episodes on the registered v5 env "
              "(results/reference_scores.json, python results/reference_scores.py)")
MAX_MISSING = ("not set: it is the mean return of this library's paper-scale SAC run's final policy on the env (its "
               "opt_det batch), and none exists yet for this env (give one with --ref-max-score)")
EXPERT_HOW = ("the mean episode return of the env's opt_det batch: this library's paper-scale SAC run's final policy, "
              "deterministic, over 10^6 steps (results/reference_scores.json)")


class MinariExportError(ValueError):
    """A batch cannot be exported as the Minari dataset asked for; the message names the id or the row and a fix."""


@contextlib.contextmanager
def _minari_root(path: Path) -> Iterator[None]:
    """Minari's data path set to ``path`` for the body (Minari reads it from the environment on every call)."""
    old = os.environ.get(MINARI_ROOT_ENV)
    os.environ[MINARI_ROOT_ENV] = str(path)
    try:
        yield
    finally:
        if old is None:
            os.environ.pop(MINARI_ROOT_ENV, None)
        else:
            os.environ[MINARI_ROOT_ENV] = old


def _minari():
    try:
        import minari
    except ImportError:
        raise MinariExportError(f"exporting to Minari needs the optional minari package: {MINARI_INSTALL}") from None
    return minari


def check_dataset_id(dataset_id: str, *, force: bool = False) -> Path:
    """The folder ``dataset_id`` will occupy in Minari's data path; :class:`MinariExportError` for a malformed id
    or, without ``force``, one that exists already.

    Examples:
        >>> check_dataset_id("bail/hopper ddpg05")  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        torchrl_bail.data.minari_export.MinariExportError: Minari dataset id 'bail/hopper ddpg05': expected ...
    """
    _minari()
    from minari.dataset.minari_dataset import parse_dataset_id
    from minari.storage import get_dataset_path

    try:
        parse_dataset_id(dataset_id)
    except (ValueError, TypeError):  # a missing -v<version> is a TypeError inside minari 0.5
        raise MinariExportError(
            f"Minari dataset id {dataset_id!r}: expected (namespace/)name-v<version> with letters, digits, '-' and "
            "'_', e.g. bail/hopper-ddpg05-b1-v0"
        ) from None
    path = Path(get_dataset_path(dataset_id))
    if path.exists() and not force:
        raise MinariExportError(f"Minari dataset {dataset_id!r} already exists at {path}; pass --force to replace "
                                "it, or choose another id or version")
    return path


def reference_scores(env_id: str, ref_max_score: float | None = None) -> dict[str, Any]:
    """``{"ref_min_score", "ref_max_score", "how"}`` for ``env_id``: the measured random reference
    (:data:`V5_RANDOM_SCORES`, ``None`` for another env) and ``ref_max_score`` as given, else the measured expert
    reference (:data:`~torchrl_bail.data.scores.V5_EXPERT_SCORES`, once the env's paper-scale SAC run exists), else
    ``None``.

    Examples:
        >>> reference_scores("Hopper-v5")["ref_min_score"], reference_scores("Hopper-v5")["ref_max_score"]
        (16.669, None)
        >>> reference_scores("Pendulum-v1", 3.0)["ref_min_score"] is None
        True
    """
    low, expert = V5_RANDOM_SCORES.get(env_id), V5_EXPERT_SCORES.get(env_id)
    high = ref_max_score if ref_max_score is not None else expert
    return {
        "ref_min_score": low,
        "ref_max_score": None if high is None else float(high),
        "how": {
            "ref_min_score": RANDOM_HOW if low is not None else f"not measured for {env_id}",
            "ref_max_score": ("given at export (--ref-max-score)" if ref_max_score is not None else
                              MAX_MISSING if expert is None else EXPERT_HOW),
        },
    }


def minari_episodes(batch: OfflineBatch) -> tuple[list, bool]:
    """The batch as Minari ``EpisodeBuffer``\\ s (see the module doc) and whether its last episode is unfinished."""
    from minari.data_collector import EpisodeBuffer

    data = batch.data
    arrays = {key: data.get(key).numpy() for key in REQUIRED_KEYS}
    obs, nxt = arrays["observation"], arrays[("next", "observation")]
    episode = arrays["episode"]
    term, trunc = arrays[("next", "terminated")][:, 0], arrays[("next", "truncated")][:, 0]
    starts = np.flatnonzero(np.r_[True, episode[1:] != episode[:-1]])
    ends = np.r_[starts[1:], len(episode)]
    inside = np.ones(len(episode), dtype=bool)
    inside[ends - 1] = False  # an episode's last row has no successor row in it
    rows = np.flatnonzero(inside)
    mismatch = rows[(nxt[rows] != obs[rows + 1]).any(-1)]
    if mismatch.size:
        i = int(mismatch[0])
        raise MinariExportError(
            f"{batch.path}: row {i} (episode {int(episode[i])}): next/observation differs from the observation of "
            f"row {i + 1}, the next step of the same episode; Minari stores one observation sequence per episode, "
            "so this batch cannot be exported"
        )
    buffers = []
    for k, (start, end) in enumerate(zip(starts, ends, strict=True)):
        buffers.append(EpisodeBuffer(
            id=k,
            observations=np.concatenate([obs[start:end], nxt[end - 1:end]]),
            actions=arrays["action"][start:end],
            rewards=arrays[("next", "reward")][start:end, 0],
            terminations=term[start:end],
            truncations=trunc[start:end],
        ))
    unfinished = not bool(term[-1] or trunc[-1])
    return buffers, unfinished


def _env_specs(env_id: str | None, max_episode_steps: int | None, source: str):
    """``(collection spec with the batch's time limit, registered spec, env)``; :class:`MinariExportError` when
    gymnasium cannot make ``env_id``."""
    if not env_id:
        raise MinariExportError(f"{source}: the batch names no env (metadata 'env_id'); import it with --env "
                                "NAME, or export with env=NAME, so that the dataset can recover its environment")
    try:
        registered = gym.spec(env_id)
        env = gym.make(registered)
    except Exception as err:  # noqa: BLE001 - any failure to make the env means it cannot be recovered
        raise MinariExportError(f"{source}: env {env_id!r} cannot be made by gymnasium ({type(err).__name__}: "
                                f"{err}); a Minari dataset must name an env it can recover") from None
    collection = registered
    if max_episode_steps is not None and max_episode_steps != registered.max_episode_steps:
        collection = dataclasses.replace(registered, max_episode_steps=int(max_episode_steps))
    return collection, registered, env


def _float32_box(space):
    if not isinstance(space, gym.spaces.Box):
        raise MinariExportError(f"observation space {space}: only Box spaces can be exported")
    return gym.spaces.Box(low=space.low.astype(np.float32), high=space.high.astype(np.float32),
                          shape=space.shape, dtype=np.float32)


def _describe(meta: Mapping[str, Any], num_episodes: int, num_transitions: int) -> tuple[str, str]:
    """``(algorithm_name, description)`` for Minari's metadata."""
    name = str(meta.get("name", "batch"))
    recipe = meta.get("recipe") if isinstance(meta.get("recipe"), Mapping) else None
    if recipe is not None:
        algorithm = f"torchrl_bail {meta.get('kind', recipe.get('recipe'))} ({recipe.get('recipe')} recipe)"
        origin = (f"collected by torchrl_bail, recipe {recipe.get('recipe')}, kind {meta.get('kind')}, behaviour "
                  f"seed {meta.get('seed')}, recipe hash {meta.get('recipe_hash')}")
    else:
        source = meta.get("source") if isinstance(meta.get("source"), Mapping) else {}
        algorithm = f"torchrl_bail import ({source.get('format', 'native batch')})"
        origin = f"imported by torchrl_bail from {source.get('path', 'a native batch')}"
    description = (f"{name}: {num_transitions} transitions in {num_episodes} episodes on {meta.get('env_id')}, "
                   f"{origin}. The metadata block '{EXPORT_KEY}' holds the batch's complete metadata.json.")
    return algorithm, description


def export_minari(batch: OfflineBatch, dataset_id: str, *, force: bool = False,
                  ref_max_score: float | None = None) -> Path:
    """Writes ``batch`` as the Minari dataset ``dataset_id`` (see the module doc); returns its folder.

    Raises:
        MinariExportError: a malformed or (without ``force``) existing id, an env gymnasium cannot make, a batch
            whose episodes break Minari's one-observation-sequence rule. Nothing is written in these cases.
    """
    minari = _minari()
    from minari.namespace import create_namespace, list_local_namespaces
    from minari.storage import get_dataset_path

    final = check_dataset_id(dataset_id, force=force)
    meta = batch.metadata
    limit = meta.get("recipe", {}).get("max_episode_steps") if isinstance(meta.get("recipe"), Mapping) else None
    collection_spec, eval_spec, env = _env_specs(meta.get("env_id"), limit, str(batch.path))
    try:
        observation_space, action_space = _float32_box(env.observation_space), env.action_space
    finally:
        env.close()
    if tuple(observation_space.shape) != (batch.obs_dim,) or tuple(action_space.shape) != (batch.act_dim,):
        raise MinariExportError(
            f"{batch.path}: the batch has {batch.obs_dim} observation features and {batch.act_dim} action "
            f"dimensions, env {eval_spec.id} has {observation_space.shape} and {action_space.shape}"
        )
    buffers, unfinished = minari_episodes(batch)
    scores = reference_scores(eval_spec.id, ref_max_score)
    algorithm, description = _describe(meta, len(buffers), batch.num_transitions)
    extra_keys = sorted("/".join(k) if isinstance(k, tuple) else k
                        for k in batch.data.keys(include_nested=True, leaves_only=True)
                        if k not in REQUIRED_KEYS and k != ("next", "done"))
    block = {
        "batch_metadata": dict(meta),
        "export": {"library_versions": {**library_versions(), "minari": minari.__version__},
                   "exported_at": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")},
        "reference_scores": scores["how"],
        "unfinished_final_episode": unfinished,
        "keys_not_exported": extra_keys,
        "observation_dtype": str(batch.data.get("observation").dtype).replace("torch.", ""),
    }
    requirements = ["gymnasium>=1.0"]
    if "mujoco" in str(eval_spec.entry_point):
        requirements.append("mujoco>=3.1")

    root = Path(get_dataset_path())
    tmp_root = root / f".export-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    old = None
    try:
        with _minari_root(tmp_root), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # Minari warns about every optional field left out (e-mail, link)
            dataset = minari.create_dataset_from_buffers(
                dataset_id, buffers, env=collection_spec, eval_env=eval_spec, algorithm_name=algorithm,
                author="torchrl_bail", description=description, observation_space=observation_space,
                action_space=action_space, ref_min_score=scores["ref_min_score"],
                ref_max_score=scores["ref_max_score"], requirements=requirements, data_format="hdf5",
            )
            extra: dict[str, Any] = {EXPORT_KEY: block}
            if scores["ref_max_score"] is None and scores["ref_min_score"] is not None:
                extra["ref_min_score"] = scores["ref_min_score"]  # Minari keeps it only beside ref_max_score
            dataset.storage.update_metadata(extra)
        namespace = dataset.spec.namespace
        if namespace is not None and namespace not in list_local_namespaces():
            create_namespace(namespace)
        final.parent.mkdir(parents=True, exist_ok=True)
        if final.exists():
            old = final.with_name(f".{final.name}.old-{os.getpid()}-{uuid.uuid4().hex[:8]}")
            os.replace(final, old)
        os.replace(tmp_root / dataset_id, final)
    except BaseException:
        if old is not None and not final.exists():
            os.replace(old, final)
        raise
    finally:
        shutil.rmtree(tmp_root, ignore_errors=True)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    return final

"""Every one of the paper's 62 batch recipes, made at reduced size on all five environments, and BAIL trained on each
for a few updates (slow: kept out of the default run; ``python -m pytest -m slow tests/test_all_recipes.py``).

Sizes: the tiny DDPG and SAC budgets of ``test_catalogue`` (hundreds of env steps, 16-32 unit networks); the
execution batches come from each (env, index) SAC run as in the paper, one SAC run serving its five batches. With
``TORCHRL_BAIL_RECIPE_RECORD=<file.json>`` the test writes one row per recipe (shapes, behaviour return, episode
count, BAIL's selected fraction and final return, wall seconds); ``results/all_recipes/`` keeps the record of the
run made for the README.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from test_catalogue import ENVS, TINY_DDPG, TINY_SAC, _paper_exps

from torchrl_bail import config_dir
from torchrl_bail.behaviour import ensure_batch

pytestmark = pytest.mark.slow

#: BAIL for a few updates: a 2-epoch envelope, 3 mini-batches of imitation, one 50-step evaluation episode
TINY_BAIL = [
    "algo=bail", "algo.envelope.epochs=2", "algo.envelope.batch_size=100", "algo.batch_size=100",
    "samples_per_epoch=100", "algo.epochs=3", "eval.every_epochs=3", "eval.episodes=1", "eval.max_steps=50",
    "eval.final_window=1", "returns.horizon=50", "progress=false", "checkpoint.enabled=false",
]
#: (env, kind, index) in collection order: each env's SAC-family batches right after one another
RECIPES = [(env, kind, index) for env, kind in _paper_exps() for index in (1, 2)]
OBS_ACT = {"hopper": (11, 3), "walker": (17, 6), "halfcheetah": (17, 6), "ant": (105, 8), "humanoid": (348, 17)}


def _compose(*overrides: str):
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        return compose("config", overrides=list(overrides))


@pytest.fixture(scope="module")
def shared_data_dir(tmp_path_factory):
    """One data directory for the module: each (env, index) SAC run is trained once and serves five batches."""
    return tmp_path_factory.mktemp("all_recipes")


@pytest.fixture(scope="module")
def record():
    rows: list[dict] = []
    yield rows
    target = os.environ.get("TORCHRL_BAIL_RECIPE_RECORD")
    if target:
        Path(target).parent.mkdir(parents=True, exist_ok=True)
        Path(target).write_text(json.dumps(rows, indent=1) + "\n")


def test_the_recipe_list_is_the_papers_62_over_five_envs():
    assert len(RECIPES) == 62 and {env for env, _, _ in RECIPES} == set(ENVS)


@pytest.mark.parametrize(("env", "kind", "index"), RECIPES, ids=[f"{e}_{k}_b{i}" for e, k, i in RECIPES])
def test_recipe_collects_and_bail_trains_on_it(env, kind, index, shared_data_dir, record, tmp_path):
    from torchrl_bail.train import run

    tiny = TINY_DDPG if kind.startswith("ddpg") else TINY_SAC
    overrides = [f"+exp={env}_{kind}", f"batch.index={index}", *tiny, f"data_dir={shared_data_dir}"]
    start = time.perf_counter()
    batch = ensure_batch(_compose(*overrides), progress=False, data_dir=shared_data_dir)
    collect_s = time.perf_counter() - start
    obs_dim, act_dim = OBS_ACT[env]
    assert (batch.obs_dim, batch.act_dim) == (obs_dim, act_dim)
    steps = 300 if kind.startswith("ddpg") else 600
    assert batch.num_transitions == steps
    data = batch.data
    assert data["observation"].dtype.is_floating_point and data["observation"].dtype.itemsize == 4
    assert int(data["episode"].unique().numel()) == batch.metadata["num_episodes"]

    start = time.perf_counter()
    (summary,) = run(_compose(*overrides, *TINY_BAIL, "seed=1"), tmp_path / "run")
    train_s = time.perf_counter() - start
    assert summary["num_transitions"] == steps
    assert 0 < summary["selected_fraction"] <= 0.5
    assert summary["final_return"] == summary["final_return"]  # not NaN
    record.append({
        "batch": f"{env}_{kind}_b{index}", "obs_dim": obs_dim, "act_dim": act_dim, "transitions": steps,
        "episodes": int(batch.metadata["num_episodes"]),
        "behaviour_return": batch.metadata.get("behaviour_return"),
        "selected_fraction": summary["selected_fraction"], "bail_final_return": summary["final_return"],
        "collect_s": round(collect_s, 2), "train_s": round(train_s, 2),
    })

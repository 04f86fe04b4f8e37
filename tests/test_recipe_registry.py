"""The behaviour-recipe registry: every recipe registers itself beside its code, and collection dispatches through
the registry (a recipe put there by a test is the one that runs)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from torchrl_bail import config_dir
from torchrl_bail.behaviour import ddpg, execution, sac_run
from torchrl_bail.behaviour.catalogue import ensure_batch
from torchrl_bail.behaviour.checkpoint import CollectionCheckpoint
from torchrl_bail.behaviour.recipes import RECIPES, Recipe, recipe_of, register_recipe
from torchrl_bail.configuration.batch_schemas import BATCH_SCHEMAS
from torchrl_bail.core.errors import ConfigError
from torchrl_bail.data.cache import batch_path, recipe_hash
from torchrl_bail.data.formats import transitions

TINY = ["+exp=hopper_ddpg05", "batch.steps=400", "batch.start_steps=100", "env.max_episode_steps=20",
        "batch.agent.actor_hidden=[32,32]", "batch.agent.critic_hidden=[32,32]", "batch.agent.batch_size=16"]


def test_every_recipe_registers_itself_beside_its_code_and_has_a_schema():
    assert tuple(RECIPES) == tuple(BATCH_SCHEMAS) == ("ddpg", "sac", "sac_exec")
    homes = {"ddpg": ddpg, "sac": sac_run, "sac_exec": execution}
    for name, recipe in RECIPES.items():
        assert recipe.name == name and type(recipe).__module__ == homes[name].__name__
    with pytest.raises(ValueError, match="'ddpg' is already registered"):
        register_recipe(ddpg.DDPGRecipe())
    with pytest.raises(ConfigError, match=r"batch.recipe = 'dqn': expected one of ddpg, sac, sac_exec"):
        recipe_of(SimpleNamespace(batch=SimpleNamespace(recipe="dqn")))


class _Checkpoint(CollectionCheckpoint):
    """A checkpoint that is never written (a recipe's ``checkpoint`` returns a ``CollectionCheckpoint``: its clock
    times the collection); records its removal."""

    removed = False

    def __init__(self):
        super().__init__(Path("never-written"), every_s=None, every_steps=None)

    def remove(self):
        self.removed = True


class FakeRecipe(Recipe):
    """Stands in for ``ddpg``: five Hopper-sized transitions of reward 7, recorded calls."""

    name = "ddpg"

    def __init__(self):
        self.calls, self.made = [], _Checkpoint()

    def checkpoint(self, cfg, data_dir, name):
        self.calls.append(("checkpoint", name))
        return self.made

    def collect(self, cfg, *, scratch, progress, data_dir, checkpoint):
        self.calls.append(("collect", checkpoint is self.made))
        n = 5
        obs = np.arange(n * 11, dtype=np.float32).reshape(n, 11)
        term = np.array([0, 0, 1, 0, 1], dtype=bool)
        data = transitions(obs, np.zeros((n, 3), np.float32), obs + 1, np.full(n, 7.0, np.float32), term,
                           np.zeros(n, dtype=bool))
        return data, {"action_low": [-1.0] * 3, "action_high": [1.0] * 3}

    def remove_checkpoint(self, cfg, data_dir, checkpoint):
        self.calls.append(("remove", checkpoint is self.made))
        checkpoint.remove()


def test_collection_runs_the_registered_recipe(tmp_path, monkeypatch):
    fake = FakeRecipe()
    monkeypatch.setitem(RECIPES, "ddpg", fake)
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("config", overrides=[*TINY, f"data_dir={tmp_path}"])
    batch = ensure_batch(cfg, progress=False)
    path = batch_path(cfg)
    assert [c[0] for c in fake.calls] == ["checkpoint", "collect", "remove"] and all(c[1] for c in fake.calls[1:])
    assert fake.calls[0][1] == path.name and fake.made.removed
    assert batch.path == path and batch.metadata["recipe_hash"] == recipe_hash(cfg)
    assert batch.num_transitions == 5 and batch.data["next", "reward"].flatten().tolist() == [7.0] * 5

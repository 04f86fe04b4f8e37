"""The ``bail:`` source in TorchRL's dataset registry (``torchrl.data.datasets.load_dataset``)."""

from __future__ import annotations

import pytest
import torch
from _hopper_batches import hopper_rows
from hydra import compose, initialize_config_dir
from torchrl.data.datasets import load_dataset
from torchrl.data.datasets.common import BaseDatasetExperienceReplay

import torchrl_bail.datasets  # noqa: F401  (registers "bail:")
from torchrl_bail import config_dir
from torchrl_bail.data import save_batch
from torchrl_bail.data.cache import batch_metadata, batch_path


def cached_catalogue_batch(data_dir, overrides):
    """Rows saved where the catalogue keeps the batch of ``overrides`` (as a collection would leave them)."""
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("config", overrides=[*overrides, f"data_dir={data_dir}"])
    meta = batch_metadata(cfg, {"action_low": [-1.0] * 3, "action_high": [1.0] * 3}, wall_time_s=0.0)
    return save_batch(hopper_rows(n=70), batch_path(cfg), meta)


def test_a_catalogue_batch_is_a_torchrl_replay_buffer_in_one_line(tmp_path):
    batch = cached_catalogue_batch(tmp_path, ["+exp=hopper_ddpg05", "batch.index=2", "preset=quick"])
    buffer = load_dataset("bail:hopper_ddpg05_b2", batch_size=16, overrides=["preset=quick"], data_dir=tmp_path)
    assert isinstance(buffer, BaseDatasetExperienceReplay) and len(buffer) == 70
    assert buffer.sample().batch_size == (16,)
    assert torch.equal(buffer[:]["next", "reward"], batch.data["next", "reward"])
    assert buffer.metadata["recipe_hash"] == batch.metadata["recipe_hash"] and buffer.data_path == batch.path
    with pytest.raises(RuntimeError, match="doesn't allow writing"):
        buffer.extend(buffer.sample())
    by_path = load_dataset(f"bail:{batch.path}", batch_size=4)
    assert torch.equal(by_path[:]["observation"], batch.data["observation"])


def test_a_batch_not_collected_or_not_named_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"bail:hopper_sac_b1: not collected yet .*make it with python -m "
                                                r"torchrl_bail.collect \+exp=hopper_sac batch.index=1 preset=quick"):
        load_dataset("bail:hopper_sac_b1", batch_size=8, overrides=["preset=quick"], data_dir=tmp_path)
    with pytest.raises(ValueError, match=r"bail:hopper_b1: expected an existing path or a batch name "
                                         r"<env>_<kind>_b<index>"):
        load_dataset("bail:hopper_b1", batch_size=8)

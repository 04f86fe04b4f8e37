"""BAIL's best-action selection (transforms/best_action.py): the border, ties, [S, B] rows, every way V <= 0 may
enter the ratio, and the write-time filter agreeing with the in-batch mask on the same data."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from torchrl_bail.transforms.best_action import (
    BestActionFilter,
    best_action_mask,
    project_values,
    select_best_actions,
)

MODES = ("raw", "project", "error")


def _data(n: int = 50, seed: int = 0, nonpositive: bool = False) -> TensorDict:
    """Distinct ratios; with ``nonpositive`` some envelope values are <= 0 (and one is exactly 0)."""
    g = torch.Generator().manual_seed(seed)
    returns = 100 * torch.rand(n, generator=g) - 20
    values = 150 * torch.rand(n, generator=g) + 1
    if nonpositive:
        values[: n // 5] = -5 * torch.rand(n // 5, generator=g)
        values[0] = 0.0
    return TensorDict({"observation": torch.randn(n, 3, generator=g), "return": returns,
                       "state_value": values.unsqueeze(-1)}, [n])


# -- the mask --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("n, percentile, kept", [(10, 0.3, 3), (7, 0.3, 2), (10, 0.01, 1), (10, 1.0, 10),
                                                 (1000, 0.3, 300), (3, 0.5, 1)])
def test_border_is_the_floor_pn_th_largest_ratio(n, percentile, kept):
    ratio = torch.randperm(n, generator=torch.Generator().manual_seed(n)).float() + 1
    values = torch.rand(n, generator=torch.Generator().manual_seed(1)) + 0.5
    returns = ratio * values
    mask, border = best_action_mask(returns, values, percentile, return_border=True)
    assert int(mask.sum()) == kept  # floor(p N), at least 1 (0.3 * 10 is 3.0000000000000004 in floats)
    torch.testing.assert_close(border, torch.tensor(float(n - kept + 1)))
    assert (ratio[mask] >= border - 1e-4).all() and (ratio[~mask] < border - 1e-4).all()


def test_ties_at_the_border_are_all_kept():
    returns = torch.tensor([1.0, 2.0, 2.0, 2.0, 3.0, 0.5])
    mask, border = best_action_mask(returns, torch.ones(6), 0.4, return_border=True)  # k = floor(2.4) = 2
    assert border.item() == 2.0
    assert mask.tolist() == [False, True, True, True, True, False]  # 4 > 2 kept: the tie is not broken


@pytest.mark.parametrize("mode", ["raw", "project"])
def test_seed_rows_select_like_separate_calls(mode):
    data = [_data(20, seed=s, nonpositive=True) for s in range(3)]
    returns = torch.stack([d["return"] for d in data])
    values = torch.stack([d["state_value"] for d in data])  # [S, B, 1]: the trailing singleton is accepted
    mask, border = best_action_mask(returns, values, 0.3, nonpositive_value=mode, return_border=True)
    assert mask.shape == (3, 20) and border.shape == (3,)
    for s in range(3):
        row_mask, row_border = best_action_mask(returns[s], values[s, :, 0], 0.3, nonpositive_value=mode,
                                                return_border=True)
        assert torch.equal(mask[s], row_mask) and border[s] == row_border


def test_raw_mode_is_the_plain_ratio_even_where_v_is_not_positive():
    # ratios: 5/10 = 0.5, -1/-1 = 1 (a negative return over a negative envelope), 3/0 = inf, 0/0 = nan, 1/2 = 0.5
    returns = torch.tensor([5.0, -1.0, 3.0, 0.0, 1.0])
    values = torch.tensor([10.0, -1.0, 0.0, 0.0, 2.0])
    assert best_action_mask(returns, values, 0.2).tolist() == [False, False, True, False, False]
    assert best_action_mask(returns, values, 0.4).tolist() == [False, True, True, False, False]
    # 0 / 0 is never selected, even when everything else is
    assert best_action_mask(returns, values, 1.0).tolist() == [True, True, True, False, True]


def test_project_mode_maps_small_values_to_exp_v_minus_one():
    returns = torch.tensor([5.0, -1.0, 3.0, 0.0, 1.0])
    values = torch.tensor([10.0, -1.0, 0.0, 0.5, 2.0])
    projected = torch.tensor([10.0, math.exp(-2.0), math.exp(-1.0), math.exp(-0.5), 2.0])
    torch.testing.assert_close(project_values(values), projected)
    ratio = returns / projected  # 0.5, -7.39, 8.15, 0, 0.5: the negative return now ranks last
    for p in (0.2, 0.4, 0.6, 1.0):
        k = max(1, math.floor(p * 5))
        expected = ratio >= ratio.sort(descending=True).values[k - 1]
        assert torch.equal(best_action_mask(returns, values, p, nonpositive_value="project"), expected), p
    assert best_action_mask(returns, values, 0.2, nonpositive_value="project").tolist() == [
        False, False, True, False, False]


def test_error_mode_refuses_any_value_at_or_below_zero():
    returns = torch.tensor([1.0, 2.0, 3.0])
    assert best_action_mask(returns, torch.tensor([1.0, 2.0, 0.5]), 0.5, nonpositive_value="error").sum() == 1
    for bad in ([1.0, 0.0, 2.0], [1.0, -3.0, 2.0]):
        with pytest.raises(ValueError, match="1 of 3 envelope values are <= 0"):
            best_action_mask(returns, torch.tensor(bad), 0.5, nonpositive_value="error")


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="percentile"):
        best_action_mask(torch.ones(4), torch.ones(4), 0.0)
    with pytest.raises(ValueError, match="nonpositive_value"):
        best_action_mask(torch.ones(4), torch.ones(4), 0.3, nonpositive_value="clip")
    with pytest.raises(ValueError, match="same shape"):
        best_action_mask(torch.ones(4), torch.ones(5), 0.3)
    with pytest.raises(ValueError, match="flat batch"):
        BestActionFilter(percentile=0.3).inv(TensorDict({"return": torch.ones(2, 3)}, [2, 3]))
    with pytest.raises(KeyError, match="state_value"):
        BestActionFilter(percentile=0.3).inv(TensorDict({"return": torch.ones(4)}, [4]))
    with pytest.raises(KeyError, match="return"):
        BestActionFilter(percentile=0.3).inv(TensorDict({"state_value": torch.ones(4)}, [4]))


# -- the write-time filter and the in-batch mask agree -------------------------------------------------------------
@pytest.mark.parametrize("mode", MODES)
def test_write_time_filter_keeps_what_the_mask_selects(mode):
    data = _data(200, nonpositive=mode != "error")
    mask, border = best_action_mask(data["return"], data["state_value"], 0.3, nonpositive_value=mode,
                                    return_border=True)
    transform = BestActionFilter(percentile=0.3, nonpositive_value=mode)
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(200), transform=transform, batch_size=16)
    buffer.extend(data)
    stored = buffer.storage[: len(buffer)]
    assert torch.equal(stored["return"], data["return"][mask])  # the same rows, in the batch's order
    assert (transform.num_selected, transform.border) == (int(mask.sum()), float(border))
    assert transform.selected_fraction == int(mask.sum()) / 200 == 0.3
    # sample time: the batch size never changes, every stored row is tagged, and so is exactly the mask on the data
    sample = buffer.sample()
    assert sample.shape == (16,) and sample["best_action"].all()
    assert torch.equal(transform(data.clone())["best_action"], mask)
    assert torch.equal(select_best_actions(data, percentile=0.3, nonpositive_value=mode)["return"],
                       stored["return"])


def test_before_any_write_the_tag_is_the_in_batch_mask():
    data = _data(40, nonpositive=True)
    tagged = BestActionFilter(percentile=0.25, nonpositive_value="project")(data.clone())
    expected = best_action_mask(data["return"], data["state_value"], 0.25, nonpositive_value="project")
    assert torch.equal(tagged["best_action"], expected) and tagged.shape == data.shape


def test_values_computed_by_the_envelope_in_chunks_equal_stored_values():
    data = _data(23)
    envelope = TensorDictModule(torch.nn.Linear(3, 1), in_keys=["observation"], out_keys=["state_value"])
    with torch.no_grad():
        envelope.module.bias.fill_(10.0)  # positive values
        data["state_value"] = envelope(data.select("observation"))["state_value"]
    from_network = select_best_actions(data.exclude("state_value"), envelope, percentile=0.3, chunk_size=4)
    assert torch.equal(from_network["return"], select_best_actions(data, percentile=0.3)["return"])
    torch.testing.assert_close(from_network["state_value"], select_best_actions(data, percentile=0.3)["state_value"])
    original = data.clone()
    select_best_actions(data, percentile=0.3)
    assert (data == original).all()  # the input is not modified


# -- the filter's state, chunks and environments ---------------------------------------------------------------
def _filtered_buffer(data: TensorDict, transform: BestActionFilter) -> TensorDictReplayBuffer:
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(len(data)), transform=transform, batch_size=8)
    buffer.extend(data)
    return buffer


def test_dumps_loads_round_trip_keeps_every_tag(tmp_path):
    data = _data(60)
    buffer = _filtered_buffer(data, BestActionFilter(percentile=0.3))
    buffer.dumps(tmp_path / "rb")
    loaded = TensorDictReplayBuffer(storage=LazyTensorStorage(60), transform=BestActionFilter(percentile=0.3),
                                    batch_size=8)
    loaded.loads(tmp_path / "rb")
    stored = loaded.storage[: len(loaded)]
    assert len(stored) == 18 and bool(loaded.transform[0](stored.clone())["best_action"].all())
    # a filter rebuilt from the state tags what the original tags, on any data
    rebuilt = BestActionFilter(percentile=0.3)
    rebuilt.load_state_dict(buffer.transform[0].state_dict())
    assert (rebuilt.border, rebuilt.num_seen, rebuilt.num_selected, rebuilt.selected_fraction) == \
        (buffer.transform[0].border, 60, 18, 0.3)
    other = _data(40, seed=3)
    assert torch.equal(rebuilt(other.clone())["best_action"], buffer.transform[0](other.clone())["best_action"])


def test_a_second_extend_warns_once_and_every_stored_row_stays_tagged():
    data = _data(90)
    transform = BestActionFilter(percentile=0.3)
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(90), transform=transform, batch_size=8)
    buffer.extend(data[:30])
    with pytest.warns(UserWarning, match="selects the top 0.3 of its own 30 rows") as caught:
        buffer.extend(data[30:60])
        buffer.extend(data[60:])
    assert len(caught) == 1
    chunks = [best_action_mask(data["return"][i:i + 30], data["state_value"][i:i + 30], 0.3, return_border=True)
              for i in (0, 30, 60)]
    assert (transform.num_seen, transform.num_selected) == (90, 27)
    assert transform.border == min(float(border) for _, border in chunks)
    assert bool(transform(buffer.storage[: len(buffer)].clone())["best_action"].all())


def test_inside_an_env_the_filter_is_a_no_op():
    from torchrl.envs import GymEnv, TransformedEnv
    from torchrl.envs.utils import check_env_specs

    base = GymEnv("Pendulum-v1")
    env = TransformedEnv(GymEnv("Pendulum-v1"), BestActionFilter(percentile=0.3))
    check_env_specs(env, seed=0)
    assert env.observation_spec == base.observation_spec and env.full_action_spec == base.full_action_spec
    base.set_seed(1)
    env.set_seed(1)
    torch.manual_seed(0)
    expected = base.rollout(5)
    torch.manual_seed(0)
    assert (env.rollout(5) == expected).all()

"""TorchRL's generic checks of losses and transforms, applied to every case registered in tests/_contract.py.

TorchRL holds each of its own losses to one base of checks and each of its transforms to one set of checks. They
are written here in this project's words, over :data:`LOSS_CASES` and :data:`TRANSFORM_CASES`, so that a loss or a
replay-buffer transform registered there gets them with no line more:

* losses (this package's; TorchRL tests its own ``BCLoss``): the default keys, ``set_keys`` refusing an unknown key,
  ``reset_parameters_recursive`` drawing every network and target afresh, every coefficient taking a float (an
  in-place update of its buffer, TorchRL's ``_schedulable_buffers``), and a deep copy made after a forward computing
  from its own tensors only;
* transforms: ``check_env_specs`` in an env, in each env of a ``SerialEnv`` and around a ``SerialEnv`` (TorchRL also
  runs the ``ParallelEnv`` variants; they need worker processes and run the same transform code), a call without
  an env, inside ``Compose``, after a module in ``nn.Sequential``, in a replay buffer (extend, then sample), the
  inverse alone and inside ``Compose``, the ``state_dict`` into a fresh transform, and ``clone``.

The checks TorchRL's base shares with this project's own contract (keyword calls, reductions, ``[S, B]`` batches,
gradients, ``state_dict``) live in tests/test_contract.py.
"""

from __future__ import annotations

import copy
import dataclasses

import pytest
import torch
from _batch_rl_testing import one_thread  # noqa: F401 (autouse fixture)
from _contract import LOSS_CASES, TRANSFORM_CASES, loss_batch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import Compose, GymEnv, SerialEnv, Transform, TransformedEnv
from torchrl.envs.utils import check_env_specs

import torchrl_bail.transforms

own_losses = pytest.mark.parametrize("case", [c for c in LOSS_CASES if not c.torchrl_own], ids=repr)
transform_cases = pytest.mark.parametrize("case", TRANSFORM_CASES, ids=repr)


def _build(case):
    torch.manual_seed(0)
    return case.build()


def _call(loss, seed: int = 1) -> TensorDictBase:
    torch.manual_seed(seed)  # stochastic losses draw from torch's global generator
    return loss(loss_batch())


def _assert_same(a: TensorDictBase, b: TensorDictBase) -> None:
    assert set(a.keys(True, True)) == set(b.keys(True, True))
    for key in a.keys(True, True):
        torch.testing.assert_close(a[key], b[key], rtol=0, atol=0, msg=str(key))


# -- losses -----------------------------------------------------------------------------------------------------
@own_losses
def test_default_keys_and_an_unknown_key(case):
    loss = _build(case)
    assert dataclasses.asdict(loss.tensor_keys) == dataclasses.asdict(loss.default_keys())
    with pytest.raises(ValueError):
        loss.set_keys(no_such_key="x")


def _network_tensors(loss) -> dict[tuple, torch.Tensor]:
    """Copies of every parameter of the loss' networks and of their targets (``<net>_params``,
    ``target_<net>_params``; buffers such as action bounds are left out)."""
    out = {}
    for group, params in loss.named_children():
        if not group.endswith("_network_params") or group.startswith("target_"):
            continue
        keys = [key for key, value in params.items(True, True) if isinstance(value, nn.Parameter)]
        for prefix in ("", "target_"):
            tensors = getattr(loss, prefix + group, None)
            if tensors is not None:
                out.update({(prefix + group, key): tensors.get(key).detach().clone() for key in keys})
    return out


@own_losses
def test_reset_parameters_recursive_draws_every_network_afresh(case):
    loss = _build(case)
    before = _network_tensors(loss)
    assert before
    loss.reset_parameters_recursive()
    after = _network_tensors(loss)
    assert after.keys() == before.keys()
    unchanged = [name for name in before if torch.equal(before[name], after[name])]
    assert not unchanged, f"reset_parameters_recursive left {unchanged} as they were"


@own_losses
def test_every_coefficient_takes_a_float(case):
    loss = _build(case)
    coefficients = {name for name, buffer in loss.named_buffers(recurse=False)
                    if buffer.ndim == 0 and buffer.is_floating_point()} - case.running
    assert coefficients == set(type(loss)._all_schedulable_buffers)
    for name in sorted(coefficients):
        buffer = getattr(loss, name)
        value = float(buffer) * 0.5 + 0.25
        setattr(loss, name, value)  # e.g. loss.penalty = 10.0, as a schedule would
        assert getattr(loss, name) is buffer, f"{name}: the buffer was replaced, not updated"
        assert buffer.dtype == loss.state_dict()[name].dtype and float(loss.state_dict()[name]) == pytest.approx(value)
    _call(loss)  # still a working loss


@own_losses
def test_a_copy_made_after_a_forward_computes_from_its_own_tensors(case):
    loss = _build(case)
    fresh = copy.deepcopy(loss)  # nothing cached yet
    reference = _call(loss)
    used = copy.deepcopy(loss)  # whatever the forward cached
    for other in (fresh, used):
        with torch.no_grad():
            for parameter in other.parameters():
                parameter.add_(0.1)  # an optimizer step of the copy alone
    _assert_same(_call(used), _call(fresh))
    _assert_same(_call(loss), reference)  # and the original is untouched


# -- transforms -------------------------------------------------------------------------------------------------
def test_every_transform_has_a_case():
    transforms = {obj for name in torchrl_bail.transforms.__all__
                  if isinstance(obj := getattr(torchrl_bail.transforms, name), type) and issubclass(obj, Transform)}
    covered = {type(case.build()) for case in TRANSFORM_CASES}
    assert transforms <= covered, f"register a TransformCase for {sorted(t.__name__ for t in transforms - covered)}"


def _env():
    return GymEnv("Pendulum-v1")


@transform_cases
@pytest.mark.parametrize("layout", ["single", "serial_of_transformed", "around_serial"])
def test_env_specs_hold_and_nothing_is_added(case, layout):
    if layout == "single":
        env, bare = TransformedEnv(_env(), case.build()), _env()
    elif layout == "serial_of_transformed":
        env, bare = SerialEnv(2, lambda: TransformedEnv(_env(), case.build())), SerialEnv(2, _env)
    else:
        env, bare = TransformedEnv(SerialEnv(2, _env), case.build()), SerialEnv(2, _env)
    try:
        check_env_specs(env, seed=0)
        assert env.full_observation_spec == bare.full_observation_spec
        assert set(env.rollout(3).keys(True, True)) == set(bare.rollout(3).keys(True, True))
    finally:
        env.close()
        bare.close()


@transform_cases
def test_without_an_env_in_compose_and_after_a_module(case):
    data = case.data(20, 0)
    alone = case.build()(data.clone())
    assert set(alone.keys(True, True)) == set(data.keys(True, True)) | set(case.adds)
    assert alone.batch_size == data.batch_size
    _assert_same(Compose(case.build())(data.clone()), alone)
    module = TensorDictModule(nn.Identity(), in_keys=["observation"], out_keys=["observation_seen"])
    through = nn.Sequential(module, case.build())(data.clone())
    _assert_same(through.exclude("observation_seen"), alone)


@transform_cases
def test_in_a_replay_buffer(case):
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(50), batch_size=8)
    buffer.append_transform(case.build())
    buffer.extend(case.data(50, 0))
    sample = buffer.sample()
    assert sample.batch_size == (8,) and all(key in sample.keys(True, True) for key in case.adds)


@transform_cases
def test_the_inverse_alone_and_in_compose(case):
    data = case.data(50, 0)
    _assert_same(Compose(case.build()).inv(data.clone()), case.build().inv(data.clone()))


@transform_cases
def test_state_dict_into_a_fresh_transform_and_clone(case):
    transform = case.build()
    transform.inv(case.data(50, 0))
    fresh = case.build()
    fresh.load_state_dict(transform.state_dict())
    other = case.data(30, 1)
    _assert_same(fresh(other.clone()), transform(other.clone()))
    clone = transform.clone()
    _assert_same(clone(other.clone()), transform(other.clone()))
    state = {key: value.clone() for key, value in transform.state_dict().items()}
    clone.inv(case.data(40, 2))  # the clone's own state moves, the original's stays
    assert all(torch.equal(value, state[key]) for key, value in transform.state_dict().items())

"""The one table every loss and every algorithm registers in to get the contract suite (tests/test_contract.py).

A new loss: add a :class:`LossCase` to :data:`LOSS_CASES` (a builder taking ``reduction``, the loss terms and the
parameter groups each must reach, the keys ``set_keys`` may rename); a new replay-buffer transform: a
:class:`TransformCase` to :data:`TRANSFORM_CASES`. Both also get TorchRL's generic loss and transform checks
(tests/test_torchrl_checks.py). A new algorithm needs nothing here: its :class:`AlgoCase` in :data:`ALGO_CASES`
derives from its registry entry (:func:`algo_case`: the networks of its schema, its ``tiny`` overrides), and only
what the contract's own checks need of it beyond that goes in :data:`CONTRACT_OVERRIDES` and :data:`NOT_UPDATED`.
The suite then checks gradients, target networks, ``set_keys``, reductions, ``[S, B]`` batches, ``state_dict`` round
trips, seeds and a tiny end-to-end run; the per-algorithm test files keep only what is specific to each.

The tiny inputs come from :mod:`_batch_rl_testing` (4-d observations, 2-d actions with unequal bounds, 8-8 nets).
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
from _batch_rl_testing import HIDDEN, OBS, SPEC, batch, bcq_loss, bear_loss, vae
from omegaconf import OmegaConf
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import EnsembleModule

from torchrl_bail.algorithms import ALGORITHMS
from torchrl_bail.algorithms.bc import make_bc_loss
from torchrl_bail.configuration.algo_schemas import ALGO_SCHEMAS, blocks_with
from torchrl_bail.configuration.config_builders import algo_config, tiny_run_overrides
from torchrl_bail.modules import make_deterministic_actor, make_qvalue_network, make_value_network
from torchrl_bail.objectives import FQELoss, MARWILLoss, UpperEnvelopeLoss, VAELoss
from torchrl_bail.transforms import BestActionFilter


def loss_batch(shape=(6,), seed: int = 0) -> TensorDict:
    """Every key any case reads: a TED transition batch plus a Monte-Carlo ``return`` of MuJoCo-like size."""
    td = batch(shape, seed=seed)
    td.set("return", 10 * torch.randn(*td.batch_size, generator=torch.Generator().manual_seed(seed + 100)))
    return td


@dataclass(frozen=True)
class LossCase:
    """How the contract suite builds and feeds one loss.

    Attributes:
        name: the test id.
        build: ``build(reduction=...) -> LossModule``; the suite seeds torch before calling it.
        reaches: each back-propagated output -> the parameter groups (first component of the parameter's name,
            e.g. ``"actor_network_params"`` or ``"log_alpha"``) it must reach, and no other.
        rename: ``tensor_keys`` field -> a new data key for ``set_keys`` (the data entry is moved there).
        stochastic: the loss draws from torch's global generator (latents, actor noise).
        torchrl_own: TorchRL's own loss (BC): what TorchRL tests (keys, masks, keyword calls, argument checks) is
            not tested again here.
        build_ensemble: ``build_ensemble(seeds)`` -> the loss on seed-ensembled networks (``EnsembleModule``).
        running: scalar float buffers the loss updates itself (running statistics), not coefficients: every other
            one must take a float assignment (TorchRL's ``_schedulable_buffers``).
    """

    name: str
    build: Callable[..., torch.nn.Module]
    reaches: dict[str, frozenset[str]]
    rename: dict[str, str] = field(default_factory=dict)
    stochastic: bool = False
    torchrl_own: bool = False
    build_ensemble: Callable[[int], torch.nn.Module] | None = None
    running: frozenset[str] = frozenset()

    def __repr__(self) -> str:  # the test id
        return self.name


def _actor():
    return make_deterministic_actor(OBS, SPEC, HIDDEN)


def _value():
    return make_value_network(OBS, HIDDEN)


def _ensemble(module, seeds: int):
    return EnsembleModule(module, num_copies=seeds, expand_input=False)


def _groups(*names: str) -> frozenset[str]:
    return frozenset(names)


_TWIN_CRITIC_TERMS = {"loss_vae": _groups("vae_network_params"), "loss_qvalue": _groups("qvalue_network_params"),
                      "loss_actor": _groups("actor_network_params")}
#: the critics read the loss' observation/action keys, so BCQ and BEAR rename what they read under "next"
_BOOTSTRAP_RENAME = {"reward": "r", "terminated": "true_end"}

LOSS_CASES = [
    LossCase("upper_envelope", lambda reduction="mean": UpperEnvelopeLoss(_value(), reduction=reduction),
             {"loss_envelope": _groups("value_network_params")}, rename={"value_target": "mc_return"},
             build_ensemble=lambda seeds: UpperEnvelopeLoss(_ensemble(_value(), seeds), reduction="none")),
    LossCase("marwil", lambda reduction="mean": MARWILLoss(_actor(), _value(), reduction=reduction),
             {"loss_actor": _groups("actor_network_params"), "loss_value": _groups("value_network_params")},
             rename={"value_target": "mc_return"},
             build_ensemble=lambda seeds: MARWILLoss(_ensemble(_actor(), seeds), _ensemble(_value(), seeds),
                                                     reduction="none"),
             running=frozenset({"c2"})),
    LossCase("vae", lambda reduction="mean": VAELoss(vae(), reduction=reduction),
             {"loss_vae": _groups("vae_network_params")},
             rename={"observation": "state", "action": "behaviour_action"}, stochastic=True),
    LossCase("bc", lambda reduction="mean": make_bc_loss(_actor(), reduction=reduction),
             {"loss_bc": _groups("actor_network_params")}, torchrl_own=True),
    LossCase("bcq", lambda reduction="mean": bcq_loss(reduction=reduction), _TWIN_CRITIC_TERMS,
             rename=_BOOTSTRAP_RENAME, stochastic=True),
    # BEAR's actor objective switches after the warm start: both objectives must keep to the actor
    LossCase("bear_warm_start", lambda reduction="mean": bear_loss(reduction=reduction),
             {**_TWIN_CRITIC_TERMS, "loss_alpha": _groups("log_alpha")}, rename=_BOOTSTRAP_RENAME, stochastic=True),
    LossCase("bear", lambda reduction="mean": bear_loss(reduction=reduction, warm_start_updates=0),
             {**_TWIN_CRITIC_TERMS, "loss_alpha": _groups("log_alpha")}, rename=_BOOTSTRAP_RENAME, stochastic=True),
    # the evaluated policy is frozen (buffers): only the Q network trains
    LossCase("fqe", lambda reduction="mean": FQELoss(make_qvalue_network(OBS, SPEC.shape[-1], HIDDEN), _actor(),
                                                     reduction=reduction),
             {"loss_qvalue": _groups("qvalue_network_params")}, rename=_BOOTSTRAP_RENAME),
]


@dataclass(frozen=True)
class TransformCase:
    """How the transform checks (tests/test_torchrl_checks.py) build and feed one replay-buffer transform.

    Attributes:
        name: the test id.
        build: ``build() -> Transform``.
        data: ``data(n, seed) -> TensorDict [n]`` holding what the transform reads.
        adds: the entries its ``forward`` writes (none inside an env).
    """

    name: str
    build: Callable[[], torch.nn.Module]
    data: Callable[[int, int], TensorDict]
    adds: tuple = ()

    def __repr__(self) -> str:
        return self.name


def _filter_data(n: int, seed: int = 0) -> TensorDict:
    td = loss_batch((n,), seed=seed)
    td.set("state_value", 20 + 5 * torch.rand(n, 1, generator=torch.Generator().manual_seed(seed)))
    return td


TRANSFORM_CASES = [
    TransformCase("best_action_filter", lambda: BestActionFilter(percentile=0.3), _filter_data, adds=("best_action",)),
]


@dataclass(frozen=True)
class AlgoCase:
    """How the contract suite builds one algorithm of the registry ``ALGORITHMS`` (:func:`algo_case` derives it).

    Attributes:
        name: the registry name (``algo.name``).
        overrides: :func:`~torchrl_bail.configuration.config_builders.algo_config` overrides for tiny networks
        (:meth:`build` adds
            mini-batches of :data:`ALGO_BATCH`).
        cli: the config overrides that make a run through the config and ``run`` take seconds.
        not_updated: modules outside the optimizers of :meth:`update` (BAIL's envelope is fitted in ``prepare``,
            Progressive BAIL's selection envelope receives copied weights).
    """

    name: str
    overrides: dict
    cli: tuple[str, ...]
    not_updated: frozenset[str] = frozenset()

    def build(self, device="cpu", **overrides):
        """The algorithm with tiny networks (and ``overrides``, dotted keys into a block: ``**{"envelope.patience":
        1}``) on ``device``; the suite seeds torch before calling it."""
        config = algo_config(self.name, batch_size=ALGO_BATCH, epochs=1, **{**self.overrides, **overrides})
        return ALGORITHMS[self.name](OBS, SPEC, config, device)

    def __repr__(self) -> str:
        return self.name


ALGO_BATCH = 16
#: the updates of every tiny run through the config, and its networks' width
TINY_UPDATES, TINY_HIDDEN = 5, (16, 16)
#: what the contract's own checks need beyond an algorithm's tiny run (its registry entry), each for its reason
CONTRACT_OVERRIDES = {
    "marwil": {"c2_rate": 0.01},  # c2 moves visibly in a few updates: a checkpoint that lost it would show
    # the actor steps at every update here, so that every optimizer steps in one (tests/test_td3bc.py: the delay)
    "td3bc": {"policy_delay": 1},
    # the contract's batches are one episode, whose returns have no spread to scale by (tests/test_iql.py: the scale)
    "iql": {"reward_scale": "none"},
}
#: modules that no optimizer of ``update`` steps (:attr:`AlgoCase.not_updated`); every other algorithm has none
NOT_UPDATED = {"bail": frozenset({"envelope"}), "pbail": frozenset({"selection_envelope"})}


def algo_case(name: str) -> AlgoCase:
    """The contract case of a registered algorithm, from its registry entry
    (:mod:`torchrl_bail.configuration.algo_schemas`): its
    ``tiny`` overrides, every network of its schema :data:`HIDDEN` wide, every block's mini-batch :data:`ALGO_BATCH`,
    then :data:`CONTRACT_OVERRIDES`; its tiny run through the config is
    :func:`~torchrl_bail.configuration.config_builders.tiny_run_overrides` at :data:`TINY_UPDATES`."""
    overrides = OmegaConf.from_dotlist(list(ALGO_SCHEMAS[name].tiny))
    for key, value in [*((f"{block}.hidden", list(HIDDEN)) for block in blocks_with(name, "hidden")),
                       *((f"{block}.batch_size", ALGO_BATCH) for block in blocks_with(name, "batch_size")),
                       *CONTRACT_OVERRIDES.get(name, {}).items()]:
        OmegaConf.update(overrides, key, value)
    return AlgoCase(name, OmegaConf.to_container(overrides), tuple(tiny_run_overrides(name, TINY_UPDATES, TINY_HIDDEN)),
                    NOT_UPDATED.get(name, frozenset()))


#: every registered algorithm's case (:func:`algo_case`); one without a schema or without its entry's ``tiny`` has
#: none, and tests/test_contract.py says what it lacks
ALGO_CASES = {name: algo_case(name) for name in ALGORITHMS if getattr(ALGO_SCHEMAS.get(name), "tiny", None) is not None}
#: BC's tiny policy, for the tutorials' tiny runs (tests/test_docs.py)
_SMALL_POLICY = next(o for o in ALGO_CASES["bc"].cli if o.startswith("algo.policy.hidden="))

#: transitions in the tiny batch every tiny end-to-end run shares
TINY_STEPS = 600
#: the tiny run: a batch of a tiny DDPG's 600 Hopper transitions (its updates dominate the cost), one evaluation
TINY_RUN = (
    "+exp=hopper_ddpg05", "preset=quick", "progress=false", "samples_per_epoch=1000000",
    f"batch.steps={TINY_STEPS}", "batch.start_steps=300", "batch.agent.actor_hidden=[8,8]",
    "batch.agent.critic_hidden=[8,8]", "batch.agent.batch_size=16", "env.max_episode_steps=100",
    "returns.horizon=100", "eval.episodes=1", "eval.max_steps=100", "eval.every_epochs=0.002",
)



def refusal_line(*overrides: str) -> str:
    """The one stderr line with which ``python -m torchrl_bail.train +exp=hopper_ddpg05 <overrides>`` refuses to start,
    after asserting how it ends: exit status 2, that one line, no traceback (its run directory cannot be written)."""
    cmd = [sys.executable, "-m", "torchrl_bail.train", "+exp=hopper_ddpg05", *overrides,
           "hydra.run.dir=/nonexistent/never_written", "progress=false"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, check=False,
                          env={**os.environ, "HYDRA_FULL_ERROR": "1"})
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    return lines[0]

def row_noise(*size, dtype=None, device=None, **_) -> torch.Tensor:
    """A stand-in for ``torch.randn`` whose values depend only on an element's last two indices.

    A loss evaluated on ``[S, B]`` then draws, for each seed, the very numbers ``S`` separate ``[B]`` calls draw,
    so per-seed results of stochastic losses can be compared exactly.
    """
    shape = tuple(size[0]) if len(size) == 1 and not isinstance(size[0], int) else tuple(size)
    rows, cols = (shape[-2] if len(shape) > 1 else 1), (shape[-1] if shape else 1)
    grid = torch.arange(rows).unsqueeze(-1) * 0.37 + torch.arange(cols) * 0.91 + 0.2
    noise = torch.sin(grid).to(dtype=dtype or torch.get_default_dtype(), device=device)
    return noise.reshape((rows, cols)[-len(shape):] if shape else ()).expand(shape).contiguous()


def row_noise_like(tensor: torch.Tensor, **kwargs) -> torch.Tensor:
    return row_noise(tensor.shape, dtype=kwargs.get("dtype", tensor.dtype), device=tensor.device)


def equal_trees(a, b, path: str = "state") -> None:
    """Asserts that two (nested) state dicts hold the same values, tensors and arrays bit for bit (whatever an
    algorithm's ``state_dict`` grows to hold: dicts, lists, tensordicts, generator states, plain values)."""
    if isinstance(a, TensorDictBase):
        assert isinstance(b, TensorDictBase), path
        equal_trees(a.to_dict(), b.to_dict(), path)
    elif isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray) and np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), path
    elif isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), f"{path}: keys {sorted(a)} != {sorted(b)}"
        for key in a:
            equal_trees(a[key], b[key], f"{path}[{key!r}]")
    elif isinstance(a, (list, tuple)):
        assert isinstance(b, (list, tuple)) and len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            equal_trees(x, y, f"{path}[{i}]")
    elif isinstance(a, torch.Tensor):
        assert isinstance(b, torch.Tensor) and a.shape == b.shape and a.dtype == b.dtype, path
        assert torch.equal(a, b) or (a.is_floating_point() and torch.equal(a.isnan(), b.isnan())
                                     and torch.equal(a.nan_to_num(), b.nan_to_num())), path
    elif isinstance(a, float) and math.isnan(a):
        assert isinstance(b, float) and math.isnan(b), path
    else:
        assert a == b, f"{path}: {a!r} != {b!r}"

"""Compiled updates agree with eager ones, and an update never waits for the host.

``compile=true`` (:meth:`~torchrl_bail.algorithms.Algorithm.compile`): from the same weights, batches and random
streams, compiled updates produce the eager losses and weights to float rounding, keep the
``state_dict`` keys (a compiled run checkpoints and resumes like an eager one) and load into an eager twin that
continues identically. Compiling on a 2-core CPU is slow (inductor writes and builds C++ for every graph: ~40 s for
BC alone), so inductor itself is exercised on BC (BAIL's update is BC's method) and the other algorithms go through
``aot_eager``: the same Dynamo capture, graph breaks, guards and AOT autograd graphs as inductor, executed by eager
kernels. Even so a compile costs 15-70 s per algorithm on the shared 2-core machine (Dynamo tracing the TensorDict
code dominates), so the default suite compares BC (inductor), MARWIL (aot_eager: its float64 running normaliser is
the in-place buffer update torch 2.13 loses in compiled graphs) and BEAR (aot_eager: the most involved update, with
all of BCQ's VAE/critic machinery); ``TORCHRL_BAIL_FULL_COMPILE_TESTS=1`` adds Progressive BAIL, BCQ and IQL.
``benchmarks/bench_compile.py`` runs every algorithm under inductor.

``device=cuda`` (checked on the CPU here, and on a GPU by ``benchmarks/gpu_check.sh`` with
``TORCHRL_BAIL_TEST_DEVICE=cuda``): between two log points the training loop (sampling and updates) reads nothing
back to the host (no ``.item()``, ``float(tensor)``, ``.cpu()``, ``bool(tensor)``; on a GPU also no implicit sync,
``torch.cuda.set_sync_debug_mode("error")``); every tensor an update creates is made on the algorithm's device (the
updates run with ``meta`` as the default device, where a tensor made without an explicit device cannot compute);
evaluation moves the observations to the device in one transfer per step and the actions back in one.
"""

from __future__ import annotations

import contextlib
import io
import os
import shutil

import pytest
import torch
from _contract import ALGO_CASES
from tensordict import TensorDict

from torchrl_bail.algorithms import PrepareContext
from torchrl_bail.modules import make_deterministic_actor
from torchrl_bail.training.trainer import make_trainee, train

#: the device under test, with its index (``cuda:0``): the device a tensor made there reports
DEVICE = torch.empty(0, device=os.environ.get("TORCHRL_BAIL_TEST_DEVICE", "cpu")).device
#: the contract's tiny configs (tests/_contract.py); Progressive BAIL validates every 2 updates, may stop after one
#: validation without progress, and BEAR leaves its warm start after 2 updates, so the updates compared cross both
#: switches
SWITCHES = {"pbail": {"envelope.patience": 1}}
#: inductor where it is affordable on 2 cores, aot_eager elsewhere (module docstring); BAIL updates with BC's method.
#: Progressive BAIL, BCQ and IQL run with TORCHRL_BAIL_FULL_COMPILE_TESTS=1 only (see the module docstring)
#: (a machine without a C++ compiler, which inductor needs on CPU, runs BC through aot_eager too)
_CXX = any(shutil.which(c) for c in (os.environ.get("CXX", "g++"), "c++", "clang++"))
BACKENDS = {"bc": "inductor" if _CXX else "aot_eager", "marwil": "aot_eager", "bear": "aot_eager"}
if os.environ.get("TORCHRL_BAIL_FULL_COMPILE_TESTS") == "1":
    BACKENDS.update(pbail="aot_eager", bcq="aot_eager", iql="aot_eager")


def _data(n: int = 200, seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(n, 4, generator=g)
    return TensorDict({
        "observation": obs, "action": torch.rand(n, 2, generator=g) * 2 - 1,
        "return": obs[:, 0] * 3 + torch.rand(n, generator=g) + 2,
        "next": {"observation": torch.randn(n, 4, generator=g), "reward": torch.randn(n, 1, generator=g),
                 "terminated": (end := torch.rand(n, 1, generator=g) < 0.05), "done": end},
    }, [n])


def _prepared(name: str, device=DEVICE):
    """A freshly built algorithm (seeded init) and the data it trains on."""
    torch.manual_seed(0)
    algo = ALGO_CASES[name].build(device, **SWITCHES.get(name, {}))
    data = algo.prepare(_data(), PrepareContext(generator=torch.Generator().manual_seed(1))).to(device)
    return algo, data


def _updates(algo, data, n: int, seed: int) -> list[dict]:
    torch.manual_seed(seed)
    out = []
    for _ in range(n):
        batch = data[torch.randint(len(data), (algo.batch_size,), device=data.device)]
        out.append({k: v.clone() for k, v in algo.update(batch).items()})
    return out


def _leaves(state, prefix: str = "") -> dict:
    if isinstance(state, dict):
        return {k: v for key, sub in state.items() for k, v in _leaves(sub, f"{prefix}/{key}").items()}
    if isinstance(state, (list, tuple)):
        return {k: v for i, sub in enumerate(state) for k, v in _leaves(sub, f"{prefix}/{i}").items()}
    return {prefix: state}


def _assert_close(a, b, atol: float = 1e-5, rtol: float = 1e-4) -> None:
    la, lb = _leaves(a), _leaves(b)
    assert la.keys() == lb.keys()
    for key in la:
        if torch.is_tensor(la[key]) and la[key].is_floating_point():
            torch.testing.assert_close(la[key], lb[key], rtol=rtol, atol=atol, msg=lambda m, key=key: f"{key}: {m}")
        elif torch.is_tensor(la[key]):
            assert torch.equal(la[key], lb[key]), key


@pytest.mark.parametrize("name", sorted(BACKENDS))
def test_compiled_updates_agree_with_eager_and_checkpoint_alike(name):
    eager, data = _prepared(name)
    compiled, _ = _prepared(name)
    compiled.compile(backend=BACKENDS[name], cudagraphs=False)
    _assert_close(_updates(compiled, data, 5, seed=2), _updates(eager, data, 5, seed=2))
    state = compiled.state_dict()
    assert not any("_orig_mod" in key for key in _leaves(state))
    _assert_close(state, eager.state_dict(), atol=1e-4)  # Adam's moments: near-zero entries round differently
    # the compiled run's checkpoint continues in an eager twin exactly as the compiled run continues
    buffer = io.BytesIO()
    torch.save(state, buffer)  # as a checkpoint does (a live state_dict shares the optimizers' moment tensors)
    twin, _ = _prepared(name)
    twin.load_state_dict(torch.load(io.BytesIO(buffer.getvalue()), weights_only=False))
    _assert_close(_updates(twin, data, 2, seed=3), _updates(compiled, data, 2, seed=3))


@pytest.mark.skipif(DEVICE.type != "cuda", reason="CUDA graphs need TORCHRL_BAIL_TEST_DEVICE=cuda and a GPU")
@pytest.mark.parametrize("name", ["bear", "marwil", "pbail"])  # the most involved updates; each costs a compile
def test_whole_update_cuda_graph_agrees_with_eager(name):
    """``compile=true`` on a GPU: inductor plus one CUDA graph of the whole update (optimizer steps included).

    BEAR draws random numbers inside the graph, where the generator advances by graph replays rather than by
    kernel launches, so its draws are not eager's: its graph must run and stay finite and its weights remain
    checkpointable; the deterministic updates (Progressive BAIL, MARWIL) must agree with eager.
    """
    eager, data = _prepared(name)
    compiled, _ = _prepared(name)
    compiled.compile(True)
    out = _updates(compiled, data, 8, seed=2)  # 5 warm-up calls (compiling), then captured and replayed
    state = compiled.state_dict()
    assert not any("_orig_mod" in key for key in _leaves(state))
    if name == "bear":
        assert all(torch.isfinite(v).all() for metrics in out for v in metrics.values())
    else:  # GPU kernels (inductor's and cuBLAS's) sum in other orders than the eager ones
        _assert_close(out, _updates(eager, data, 8, seed=2), atol=1e-4, rtol=1e-3)
        _assert_close(state["modules"], eager.state_dict()["modules"], atol=1e-4, rtol=1e-3)


def test_compile_setting_is_checked():
    algo, _ = _prepared("bc")
    with pytest.raises(ValueError, match="compile must be false, true or one of"):
        algo.compile("fast")
    if DEVICE.type != "cuda":
        with pytest.raises(ValueError, match="CUDA graphs need a CUDA device"):
            algo.compile(True, cudagraphs=True)
    algo.compile(False)
    assert "update" not in vars(algo)  # compile=false leaves the eager update in place


def test_compile_key_is_checked_and_names_its_own_run():
    from hydra import compose, initialize_config_dir

    from torchrl_bail import config_dir
    from torchrl_bail.configuration.config import ConfigError, validate_config
    from torchrl_bail.training.resume import RUN_ONLY_KEYS, comparable_config, diff_configs

    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("config", overrides=["+exp=hopper_ddpg05", "compile=true"], return_hydra_config=True)
        eager = compose("config", overrides=["+exp=hopper_ddpg05"])
        compiled = compose("config", overrides=["+exp=hopper_ddpg05", "compile=true"])
        for setting in ("reduce-overhead", "max-autotune"):
            validate_config(compose("config", overrides=["+exp=hopper_ddpg05", f"compile={setting}"]))
        bad = compose("config", overrides=["+exp=hopper_ddpg05", "compile=fast"])
    assert cfg.compile is True and eager.compile is False
    # compiled kernels round differently: another run directory, and a checkpoint of the other setting is refused
    assert "compile" not in RUN_ONLY_KEYS and "compile" not in cfg.hydra.job.config.override_dirname.exclude_keys
    assert diff_configs(comparable_config(eager), comparable_config(compiled)) == ["compile: (absent) -> True"]
    with pytest.raises(ConfigError, match="compile"):
        validate_config(bad)


class _HostReads:
    """Counts the calls that read a tensor back to the host, except the optimizers' step counters (non-fused Adam
    keeps them on the host on every device, so reading them moves nothing)."""

    METHODS = ("item", "tolist", "cpu", "numpy", "__float__", "__int__", "__bool__", "__index__")

    def __init__(self, monkeypatch, optimizers) -> None:
        self.optimizers, self.reads = optimizers, []
        for method in self.METHODS:
            original = getattr(torch.Tensor, method)

            def counted(tensor, *args, _original=original, _method=method, **kwargs):
                if not any(tensor is state.get("step") for opt in self.optimizers for state in opt.state.values()):
                    self.reads.append(_method)
                return _original(tensor, *args, **kwargs)

            monkeypatch.setattr(torch.Tensor, method, counted)


class _Logger:
    def __init__(self) -> None:
        self.scalars: list[tuple[str, float, int]] = []

    def log_scalar(self, name: str, value: float, step: int) -> None:
        self.scalars.append((name, value, step))


@pytest.mark.parametrize("name", list(ALGO_CASES))
def test_training_loop_reads_back_only_at_log_points(name, monkeypatch):
    algo, data = _prepared(name)
    if name == "pbail":  # its early stopping reads the validation loss once every validate_every updates
        algo.validate_every = 10**6
    _updates(algo, data, 1, seed=0)  # optimizer states exist; Progressive BAIL has validated once
    eager_update = algo.update

    def update_on_meta_default(batch):
        # a tensor made without an explicit device lands on "meta" and the update fails or returns meta values
        sync_debug = torch.cuda.set_sync_debug_mode if DEVICE.type == "cuda" else None
        with torch.device("meta"), contextlib.ExitStack() as stack:
            if sync_debug is not None:
                sync_debug("error")
                stack.callback(sync_debug, "default")
            metrics = eager_update(batch)
        assert all(v.device == DEVICE for v in metrics.values())
        return metrics

    algo.update = update_on_meta_default
    algo.epochs = 8 * algo.samples_per_update / 1e6
    logger = _Logger()
    reads = _HostReads(monkeypatch, algo.optimizers.values())
    train(make_trainee([algo], [data]), loggers=[logger], log_every=4, progress=False)
    monkeypatch.undo()
    logged = [scalar for scalar in logger.scalars if scalar[0].startswith("train/")]
    assert len(logged) == 2 * len(algo.update(data[:16])) and {s[2] for s in logged} == {4, 8}
    assert reads.reads == ["__float__"] * len(logged)  # float(sum) / log_every at each log point, nothing else
    state = _leaves(algo.state_dict())
    assert all(v.device.type in (DEVICE.type, "cpu") for v in state.values() if torch.is_tensor(v))


def test_evaluation_transfers_once_each_way_per_step(monkeypatch):
    from torchrl_bail.evaluation import Evaluator

    evaluator = Evaluator("Hopper-v5", episodes=3, seeds=[0], max_steps=7, device=DEVICE)
    actor = make_deterministic_actor(evaluator.obs_dim, evaluator.action_spec, hidden=(8,)).to(DEVICE)
    seen = []

    def policy(td):
        seen.append((td.device, td["observation"].device, td["observation"].shape))
        return actor(td)

    to_host, made = [], []
    original_cpu, original_tensor = torch.Tensor.cpu, torch.tensor
    monkeypatch.setattr(torch.Tensor, "cpu", lambda t, *a, **k: to_host.append(t.device) or original_cpu(t, *a, **k))
    monkeypatch.setattr(torch, "tensor", lambda *a, **k: made.append(k.get("device")) or original_tensor(*a, **k))
    with evaluator:
        (result,) = evaluator.evaluate(policy)
    monkeypatch.undo()
    steps = max(result.lengths)
    assert len(seen) == steps == 7
    assert all(d == DEVICE and o == DEVICE and s == (3, evaluator.obs_dim) for d, o, s in seen)
    assert made == [DEVICE] * steps  # the stacked observations: one host-to-device transfer per step
    assert to_host == [DEVICE] * steps  # the actions: one device-to-host transfer per step

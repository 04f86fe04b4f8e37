"""Many seeds in one process (torchrl_bail.core.stacking): seed s of a stacked run is the single-seed run with seed s,
and a
list of one seed is the single-seed run to every digit."""

from __future__ import annotations

import copy
import dataclasses
import math

import pytest
import torch
from _contract import ALGO_BATCH, ALGO_CASES, OBS, TINY_RUN, loss_batch, row_noise, row_noise_like
from hydra import compose, initialize_config_dir
from tensordict import TensorDict

from torchrl_bail import config_dir
from torchrl_bail.algorithms import ALGORITHMS, PrepareContext
from torchrl_bail.configuration.config_builders import algo_config
from torchrl_bail.core.stacking import SeedBatchSampler, SeedStack, StackedTrainee, prepare_seeds
from torchrl_bail.training.trainer import make_trainee, train

SEEDS = (3, 7, 11)
#: the stacked run computes each seed's numbers with batched matrix products: equal up to float rounding
TOL = {"rtol": 1e-4, "atol": 1e-5}


def _built(case, seed: int):
    torch.manual_seed(seed)
    return case.build()


def _context(seed: int) -> PrepareContext:
    return PrepareContext(generator=torch.Generator().manual_seed(seed))


def _parameters(algorithm) -> dict[str, torch.Tensor]:
    return {f"{key}.{name}": p.detach() for key, module in algorithm.modules.items()
            for name, p in module.named_parameters()}


def _actions(algorithm_or_stack, seeds: int | None = None) -> torch.Tensor:
    observation = torch.randn(4, OBS, generator=torch.Generator().manual_seed(5))
    if seeds is not None:
        observation = observation.expand(seeds, 4, OBS)
    torch.manual_seed(0)
    with torch.no_grad():
        return algorithm_or_stack.policy(TensorDict({"observation": observation}, observation.shape[:-1]))["action"]


def _assert_close_trees(got, expected, path: str) -> None:
    """Nested state dicts equal, tensors and floats to :data:`TOL`."""
    if isinstance(expected, dict):
        assert isinstance(got, dict) and got.keys() == expected.keys(), path
        for key in expected:
            _assert_close_trees(got[key], expected[key], f"{path}[{key!r}]")
    elif isinstance(expected, (list, tuple)):
        assert len(got) == len(expected), path
        for i, (g, e) in enumerate(zip(got, expected, strict=True)):
            _assert_close_trees(g, e, f"{path}[{i}]")
    elif torch.is_tensor(expected):
        torch.testing.assert_close(got, expected, **TOL, msg=lambda m: f"{path}: {m}")
    elif isinstance(expected, float):
        assert math.isclose(got, expected, rel_tol=TOL["rtol"], abs_tol=TOL["atol"]), path
    else:
        assert got == expected, path


def _assert_close_per_seed(singles, stack) -> None:
    """After :meth:`SeedStack.unstack`, each seed's algorithm holds its single-seed twin's whole state: weights,
    targets, buffers, optimizer moments and the algorithm's own attributes (early stopping...)."""
    stack.unstack()
    for seed, single, stacked in zip(SEEDS, singles, stack.algorithms, strict=True):
        _assert_close_trees(stacked.state_dict(), single.state_dict(), f"seed {seed}")


def _vmapped_critics(case):
    """The case with its critics run by ``torch.vmap`` (the default on accelerators) instead of a loop."""
    return dataclasses.replace(case, overrides={**case.overrides, "critic": {**case.overrides["critic"], "vmap": True}})


#: every algorithm that stacks seeds, and those with a critic ``vmap`` switch once more with it on
STACKED = [case for name, case in ALGO_CASES.items() if ALGORITHMS[name].seed_stack_refusal is None]
CASES = [*(pytest.param(case, id=case.name) for case in STACKED),
         *(pytest.param(_vmapped_critics(case), id=f"{case.name}_vmap") for case in STACKED
           if "vmap" in algo_config(case.name).get("critic", {}))]


@pytest.mark.parametrize("case", CASES)
def test_stacked_seeds_start_and_update_as_their_single_seed_runs(case, monkeypatch):
    """Same initialisation, same prepared data, same mini-batches -> per seed the same losses and weights over the
    first updates (stochastic losses draw ``row_noise``, the same numbers for every seed's rows)."""
    monkeypatch.setattr(torch, "randn", row_noise)
    monkeypatch.setattr(torch, "randn_like", row_noise_like)
    data = loss_batch((120,), seed=0)
    singles = [_built(case, seed) for seed in SEEDS]
    single_data = [a.prepare(data, _context(seed)) for a, seed in zip(singles, SEEDS, strict=True)]
    algorithms = [_built(case, seed) for seed in SEEDS]
    stack = SeedStack(algorithms)
    # the stack leaves the seeds' own objects untouched
    for single, stacked in zip(singles, stack.algorithms, strict=True):
        assert _parameters(single).keys() == _parameters(stacked).keys()
    stacked_data = prepare_seeds(algorithms, data, [_context(seed) for seed in SEEDS])
    stack.restack()  # what prepare fitted (BAIL's envelope) into the stack
    # BAIL: each seed's envelope selected the same actions
    for single, stacked in zip(single_data, stacked_data, strict=True):
        assert single.batch_size == stacked.batch_size
        torch.testing.assert_close(stacked["return"], single["return"])
    torch.testing.assert_close(_actions(stack, len(SEEDS)), torch.stack([_actions(a) for a in singles]), **TOL)
    draws = [torch.Generator().manual_seed(100 + seed) for seed in SEEDS]
    for _ in range(4):
        index = [torch.randint(len(d), (ALGO_BATCH,), generator=g) for d, g in zip(single_data, draws, strict=True)]
        single_metrics = [a.update(d[i]) for a, d, i in zip(singles, single_data, index, strict=True)]
        metrics = stack.update(torch.stack([d[i] for d, i in zip(stacked_data, index, strict=True)]))
        for key, value in metrics.items():
            expected = torch.stack([torch.as_tensor(m[key], dtype=value.dtype) for m in single_metrics])
            # per-seed diagnostics come back [S]; the losses' values are their means over the seeds
            torch.testing.assert_close(value, expected if value.ndim else expected.mean(), **TOL, msg=key)
    _assert_close_per_seed(singles, stack)
    torch.testing.assert_close(_actions(stack, len(SEEDS)), torch.stack([_actions(a) for a in singles]), **TOL)


def test_training_loop_draws_each_seeds_single_seed_stream():
    """Through :func:`train`: each seed's mini-batches come from a copy of the global stream its single-seed run
    samples from, so the stacked run ends where the three single-seed runs end."""
    case = ALGO_CASES["bc"]
    data = loss_batch((200,), seed=1)
    singles = []
    for seed in SEEDS:
        algorithm = _built(case, seed)
        train(make_trainee([algorithm], [data]), samples_per_epoch=ALGO_BATCH * 6, progress=False)
        singles.append(algorithm)
    algorithms, streams = [], []
    for seed in SEEDS:
        algorithms.append(_built(case, seed))
        streams.append(torch.Generator())
        streams[-1].set_state(torch.get_rng_state())
    stack = SeedStack(algorithms)
    sampler = SeedBatchSampler([data] * len(SEEDS), ALGO_BATCH, streams)
    assert len(sampler) == len(data)  # one storage for seeds that share their data
    scores = iter(range(100))
    histories = train(StackedTrainee(stack, sampler), evaluate=lambda p: [float(next(scores)) for _ in SEEDS],
                      samples_per_epoch=ALGO_BATCH * 6, eval_every_epochs=0.5, progress=False)
    assert [h.iterations for h in histories] == [6] * len(SEEDS)
    assert [[e.mean_return for e in h.evaluations] for h in histories] == [[0, 3], [1, 4], [2, 5]]
    _assert_close_per_seed(singles, stack)


def test_a_subclass_overriding_prepare_is_called_not_bypassed_by_its_parents_prepare_seeds():
    """The loop prepares every run's data through ``prepare_seeds``; a BAIL of a user's own that overrides
    ``prepare`` alone must still have it called (it was bypassed by BAIL's ``prepare_seeds``)."""
    from torchrl_bail.algorithms import BAIL

    class Parent:
        def prepare(self, data, ctx):
            return "parent", ctx

        @staticmethod
        def prepare_seeds(algorithms, data, contexts):
            return [("seeds", ctx) for ctx in contexts]

    class Child(Parent):
        def prepare(self, data, ctx):
            return "child", ctx

    class Both(Child):
        @staticmethod
        def prepare_seeds(algorithms, data, contexts):
            return [("both", ctx) for ctx in contexts]

    assert prepare_seeds([Parent(), Parent()], None, [1, 2]) == [("seeds", 1), ("seeds", 2)]
    assert prepare_seeds([Child(), Child()], None, [1, 2]) == [("child", 1), ("child", 2)]
    assert prepare_seeds([Both()], None, [1]) == [("both", 1)]

    class MyBAIL(BAIL):
        def prepare(self, data, ctx):
            return "mine"

    assert prepare_seeds([object.__new__(MyBAIL)], None, [None]) == ["mine"]


def test_seed_batch_sampler_rows_and_checkpoint_state():
    a = loss_batch((10,), seed=0)
    b = loss_batch((4,), seed=1)
    sampler = SeedBatchSampler([a, b], 6, [torch.Generator().manual_seed(0), torch.Generator().manual_seed(1)])
    state = sampler.state_dict()
    batch = sampler.sample()
    assert batch.batch_size == (2, 6)
    torch.testing.assert_close(batch[0]["return"], a["return"][torch.randint(10, (6,), generator=torch.Generator()
                                                                             .manual_seed(0))])
    torch.testing.assert_close(batch[1]["return"], b["return"][torch.randint(4, (6,), generator=torch.Generator()
                                                                            .manual_seed(1))])
    sampler.load_state_dict(state)
    assert (sampler.sample() == batch).all()


def _tiny_config(*overrides):
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        return compose("config", overrides=[*TINY_RUN, *overrides])


def test_seeds_on_the_command_line_write_single_seed_summaries(tiny_run_data_dir, tmp_path):
    """``seeds=[1,2]``: one run directory and summary.json per seed, equal (wall time and paths aside, numbers to
    float tolerance) to what ``seed=2`` alone writes; a second call reports the finished seeds."""
    from torchrl_bail.train import run

    common = ("algo=bc", *ALGO_CASES["bc"].cli, f"data_dir={tiny_run_data_dir}")
    stacked = run(_tiny_config(*common, "seeds=[1,2]"), tmp_path / "stacked")
    (single,) = run(_tiny_config(*common, "seed=2"), tmp_path / "single")
    assert [s["seed"] for s in stacked] == [1, 2]
    for name in ("summary.json", "policy.pt", "policy_best.pt", "config.yaml", "learning_curve.png"):
        assert (tmp_path / "stacked" / "seed2" / name).stat().st_size > 0, name
    stacked_config = (tmp_path / "stacked" / "seed2" / "config.yaml").read_text()
    assert stacked_config == (tmp_path / "single" / "config.yaml").read_text()
    got, expected = stacked[1], single
    assert got.keys() == expected.keys()
    for key in expected.keys() - {"wall_time_s", "run_dir"}:
        if isinstance(expected[key], float):
            assert math.isclose(got[key], expected[key], rel_tol=1e-4, abs_tol=1e-4), key
        elif key != "best_policy":
            assert got[key] == expected[key], key
    again = run(_tiny_config(*common, "seeds=2", "seed=1"), tmp_path / "stacked")  # a count: seeds 1, 2
    assert again == stacked


def _envelope_problem():
    observations = torch.randn(300, OBS, generator=torch.Generator().manual_seed(0))
    returns = observations[:, 0] * 3 + torch.randn(300, generator=torch.Generator().manual_seed(1))
    return observations, returns


def _envelope(seed: int):
    from torchrl_bail.modules import make_value_network

    torch.manual_seed(seed)
    return make_value_network(OBS, (16, 16))


@pytest.mark.parametrize("name", ["bail", "bcq"])
def test_a_list_of_one_seed_on_the_command_line_is_the_single_seed_run_to_every_digit(tiny_run_data_dir, tmp_path,
                                                                                     name):
    """``seeds=[2]`` writes what ``seed=2`` writes, to every digit: summary, policies and checkpoint (BAIL: the
    envelope fit of a list of one; BCQ: noise and mini-batches from the one global stream)."""
    from _contract import equal_trees

    from torchrl_bail.train import run

    common = (f"algo={name}", *ALGO_CASES[name].cli, f"data_dir={tiny_run_data_dir}")
    (listed,) = run(_tiny_config(*common, "seeds=[2]"), tmp_path / "listed")
    (single,) = run(_tiny_config(*common, "seed=2"), tmp_path / "single")
    volatile = {"wall_time_s", "run_dir"}
    assert {k: v for k, v in listed.items() if k not in volatile} == {k: v for k, v in single.items()
                                                                      if k not in volatile}
    for file in ("policy.pt", "policy_best.pt", "checkpoint.pt"):
        got = torch.load(tmp_path / "listed" / "seed2" / file, weights_only=False)
        expected = torch.load(tmp_path / "single" / file, weights_only=False)
        for key in ("state_dict", "info") if file.startswith("policy") else ("algorithm", "evaluations", "rng"):
            equal_trees(got[key], expected[key], f"{file}[{key!r}]")


@pytest.mark.parametrize("early_stopping", ["paper", "as_coded"])
def test_stacked_envelope_fit_is_each_seeds_own_fit(early_stopping):
    """BAIL's envelope, S seeds in one fit: own split, shuffles, validation losses, patience counts, reverts and
    returned weights per seed (a high learning rate makes the validation loss wander, so reverts happen).

    Compared exactly, against the same batched computation: seed s's row of the stack equals every row of a stack
    of S copies of seed s (the same batched product per layer, so the same rounding on any CPU). Against the plain
    fit of one network only what rounding cannot move is compared: a batched and a plain product round differently,
    and 14 epochs at this learning rate amplify that beyond any fixed tolerance (1.2e-3 relative on an AVX-512 CPU).
    """
    from torchrl_bail.training.envelope import fit_upper_envelope

    observations, returns = _envelope_problem()
    kwargs = dict(epochs=14, patience=2, batch_size=32, lr=0.05, early_stopping=early_stopping, progress=False)

    def fit(seeds, **overrides):
        networks = [_envelope(seed) for seed in seeds]
        fits = fit_upper_envelope(networks, observations, returns, **{**kwargs, **overrides},
                                  generators=[torch.Generator().manual_seed(seed) for seed in seeds])
        assert [f.value_network for f in fits] == networks  # each seed's own network holds its fitted envelope
        return list(zip(fits, networks, strict=True))

    mixed = fit(SEEDS)
    assert any(fit.revert_epochs for fit, _ in mixed) or early_stopping == "as_coded"
    for seed, (got, net) in zip(SEEDS, mixed, strict=True):
        for alone, alone_net in fit([seed] * len(SEEDS)):
            assert torch.equal(got.train_index, alone.train_index) and torch.equal(got.val_index, alone.val_index)
            assert (got.best_epoch, got.revert_epochs, got.returned) == \
                (alone.best_epoch, alone.revert_epochs, alone.returned)
            assert got.val_loss == alone.val_loss and got.train_loss == alone.train_loss
            for (name, p), q in zip(net.named_parameters(), alone_net.parameters(), strict=True):
                assert torch.equal(p, q), name
    # the stack against one plain network: the same split and, with the weights held still (lr=0), the same
    # validation losses to float32's rounding of three products of at most 16 terms and a mean over the
    # validation points (relative, about (3 * 16 + n) * 2^-24; 3x that is allowed)
    held = dict(epochs=2, lr=0.0)
    for seed, (got, _) in zip(SEEDS, fit(SEEDS, **held), strict=True):
        ((single, _),) = fit([seed], **held)
        assert torch.equal(got.train_index, single.train_index) and torch.equal(got.val_index, single.val_index)
        rtol = 3 * (3 * 16 + len(single.val_index)) * torch.finfo(torch.float32).eps / 2
        torch.testing.assert_close(torch.tensor(got.val_loss), torch.tensor(single.val_loss), rtol=rtol, atol=0)


def test_a_one_seed_envelope_fit_is_the_plain_fit_to_every_digit():
    """``fit_upper_envelope`` of a list of one network is the fit of that network written out with plain tensors (the
    fit as it was before seeds could be stacked): no seed dimension, TorchRL's mean reduction, the epoch's loss
    divided in Python's float. The same losses, reverts and weights bit for bit (a seed dimension of size 1 would
    send every layer through a batched matrix product and round differently)."""
    from torchrl_bail.objectives import UpperEnvelopeLoss
    from torchrl_bail.training.envelope import EarlyStoppingTracker, envelope_split, fit_upper_envelope

    observations, returns = _envelope_problem()
    epochs, batch_size, lr = 8, 32, 0.05
    (fit,) = fit_upper_envelope([_envelope(3)], observations, returns, epochs=epochs, batch_size=batch_size, lr=lr,
                                patience=2, generators=[torch.Generator().manual_seed(3)], progress=False)
    net, generator = _envelope(3), torch.Generator().manual_seed(3)
    loss_module = UpperEnvelopeLoss(net, penalty=1000.0)  # reduction "mean"
    optimizer = torch.optim.Adam(loss_module.parameters(), lr=lr, weight_decay=0.02)
    obs_key, return_key = net.in_keys[0], loss_module.tensor_keys.value_target

    def batch(index):
        return TensorDict({obs_key: observations[index], return_key: returns[index]}, [len(index)])

    train_index, val_index = envelope_split(returns, 0.2, generator=generator)
    tracker = EarlyStoppingTracker(net, patience=2)
    train_losses, val_losses = [], []
    for _ in range(epochs):
        order, running = train_index[torch.randperm(len(train_index), generator=generator)], 0
        for start in range(0, len(order), batch_size):
            index = order[start:start + batch_size]
            loss, _ = loss_module.envelope_loss(batch(index))
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            running = running + loss.detach() * len(index)
        train_losses.append(float(running) / len(train_index))
        with torch.no_grad():  # the mean over the validation points, weighted by its size and divided back
            val_losses.append(float(loss_module.envelope_loss(batch(val_index))[0] * len(val_index) / len(val_index)))
        tracker.observe(val_losses[-1])
    tracker.best.load_into(net)
    assert fit.reverted and (fit.train_loss, fit.val_loss, fit.revert_epochs) == (train_losses, val_losses,
                                                                                  tracker.reverts)
    for (name, got), expected in zip(fit.value_network.state_dict().items(), net.state_dict().values(), strict=True):
        assert torch.equal(got, expected), name


class _Kill(BaseException):
    """Stands in for SIGKILL in the middle of a run."""


@pytest.mark.parametrize(("name", "seeds"), [("bc", SEEDS), ("pbail", SEEDS), ("bc", (7,))],
                         ids=["bc", "pbail", "bc_one_seed"])
def test_killed_stacked_run_resumes_from_its_per_seed_checkpoints(tmp_path, name, seeds):
    """The stack writes one single-seed checkpoint per seed; the stacked run continued from them ends where the
    uninterrupted stacked run ends, and each of them also continues alone as that seed's single-seed run. A list of
    one seed (``seeds=1``, or the one unfinished seed of a stacked command) checkpoints and resumes the same way,
    bit for bit."""
    from _contract import equal_trees
    case = ALGO_CASES[name]
    data = loss_batch((200,), seed=2)
    observation = torch.randn(5, OBS, generator=torch.Generator().manual_seed(3))

    def evaluate(policy):  # one seed's policy is unstacked: observations [5, OBS]
        obs = observation.expand(len(evaluate.seeds), 5, OBS) if len(evaluate.seeds) > 1 else observation
        with torch.no_grad():
            actions = policy(TensorDict({"observation": obs}, obs.shape[:-1]))["action"]
        return actions.sum((-2, -1)).reshape(-1).tolist()

    kwargs = dict(evaluate=evaluate, samples_per_epoch=ALGO_BATCH * 12, eval_every_epochs=0.25, log_every=5,
                  progress=False)

    def fresh_trainee(checkpoints=None):
        algorithms, streams = [], []
        for j, seed in enumerate(seeds):
            algorithms.append(_built(case, seed))
            streams.append(torch.Generator())
            streams[-1].set_state(torch.get_rng_state())
            if checkpoints is not None:
                algorithms[-1].load_state_dict(checkpoints[j]["algorithm"])
        if checkpoints is None:
            prepared = prepare_seeds(algorithms, data, [_context(seed) for seed in seeds])
        else:
            prepared = [a.restore_prepared(data, _context(seed)) for a, seed in zip(algorithms, seeds, strict=True)]
        return make_trainee(algorithms, prepared, streams)

    evaluate.seeds = seeds
    reference = fresh_trainee()
    reference_histories = train(reference, **kwargs)

    paths = [tmp_path / f"seed{seed}.pt" for seed in seeds]
    killed = fresh_trainee()
    update, calls = killed.update, [0]

    def dying_update(batch):
        calls[0] += 1
        if calls[0] == 8:
            raise _Kill
        return update(batch)

    killed.update = dying_update
    with pytest.raises(_Kill):
        train(killed, checkpoint_paths=paths, checkpoint_every_s=0.0, **kwargs)
    checkpoints = [torch.load(p, weights_only=False) for p in paths]
    assert [c["iteration"] for c in checkpoints] == [7] * len(seeds)
    last = copy.deepcopy(checkpoints[-1])  # a resumed optimizer steps the moments it loaded in place
    torch.manual_seed(99)  # the checkpoints' streams replace whatever the process has
    resumed = fresh_trainee(checkpoints)
    histories = train(resumed, checkpoint_paths=paths, resume_from=checkpoints, **kwargs)
    assert [h.evaluations for h in histories] == [h.evaluations for h in reference_histories]
    for got, expected in zip(resumed.algorithms(), reference.algorithms(), strict=True):
        equal_trees(got.state_dict(), expected.state_dict())

    evaluate.seeds = seeds[-1:]  # the last seed's checkpoint, continued by its single-seed run
    single = _built(case, seeds[-1])
    single_data = single.prepare(data, _context(seeds[-1]))
    (single_reference,) = train(make_trainee([single], [single_data]), **kwargs)
    alone = _built(case, seeds[-1])
    alone.load_state_dict(last["algorithm"])
    (history,) = train(make_trainee([alone], [alone.restore_prepared(data, _context(seeds[-1]))]), resume_from=[last],
                       **kwargs)
    assert len(history.evaluations) == len(single_reference.evaluations)
    for got, expected in zip(history.evaluations, single_reference.evaluations, strict=True):
        assert math.isclose(got.mean_return, expected.mean_return, rel_tol=1e-4, abs_tol=1e-4)
    _assert_close_trees(alone.state_dict(), single.state_dict(), "alone")


@pytest.mark.parametrize("seeds", ["[1,1]", "0", "[]", "[-1]", "abc"])
def test_bad_seeds_are_refused_naming_the_key(seeds):
    from torchrl_bail.configuration.config import ConfigError, validate_config

    with pytest.raises(ConfigError, match=r"config key seeds = .*expected null, a count S >= 1"):
        validate_config(_tiny_config(f"seeds={seeds}"))


def test_compiled_stack_updates_like_the_eager_stack():
    """``seeds=`` with ``compile``: the host's one update is compiled (aot_eager here: the same Dynamo capture as
    inductor, cheap on CPU), the per-seed gradient hooks included; weights agree with the eager stack's."""
    from torchrl_bail.algorithms.bc import BehaviourCloning
    from torchrl_bail.configuration.config_builders import algo_config
    from torchrl_bail.modules import action_spec_from_bounds

    config = algo_config("bc", batch_size=8, policy={"hidden": [16]})
    spec = action_spec_from_bounds([-1.0] * 2, [1.0] * 2)

    def build(seed):
        torch.manual_seed(seed)
        return BehaviourCloning(4, spec, config)

    g = torch.Generator().manual_seed(0)
    batch = TensorDict({"observation": torch.randn(2, 8, 4, generator=g),
                        "action": torch.rand(2, 8, 2, generator=g) * 2 - 1}, [2, 8])
    eager, compiled = SeedStack([build(1), build(2)]), SeedStack([build(1), build(2)])
    compiled.host.compile(True, backend="aot_eager")
    for _ in range(4):
        expected, got = eager.update(batch), compiled.update(batch)
    assert torch.allclose(got["loss_bc"], expected["loss_bc"], rtol=1e-5)
    eager.unstack()
    compiled.unstack()
    for a, b in zip(eager.algorithms, compiled.algorithms, strict=True):
        for p, q in zip(a.modules["actor"].parameters(), b.modules["actor"].parameters(), strict=True):
            torch.testing.assert_close(q, p, rtol=1e-5, atol=1e-6)
    assert not torch.equal(next(eager.algorithms[0].modules["actor"].parameters()),
                           next(eager.algorithms[1].modules["actor"].parameters()))

"""Many seeds in one process (torchrl_bail.stacking): seed s of a stacked run is the single-seed run with seed s."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from _contract import ALGO_BATCH, ALGO_CASES, OBS, TINY_RUN, loss_batch, row_noise, row_noise_like
from hydra import compose, initialize_config_dir

from torchrl_bail import config_dir
from torchrl_bail.algorithms import ALGORITHMS, PrepareContext
from torchrl_bail.config_builders import algo_config
from torchrl_bail.stacking import SeedBatchSampler, SeedStack, StackedTrainee, prepare_seeds
from torchrl_bail.trainer import train, train_seeds

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
    from tensordict import TensorDict

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
        train(algorithm, data, samples_per_epoch=ALGO_BATCH * 6, progress=False)
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
    histories = train_seeds(StackedTrainee(stack, sampler), evaluate=lambda p: [float(next(scores)) for _ in SEEDS],
                            samples_per_epoch=ALGO_BATCH * 6, eval_every_epochs=0.5, progress=False)
    assert [h.iterations for h in histories] == [6] * len(SEEDS)
    assert [[e.mean_return for e in h.evaluations] for h in histories] == [[0, 3], [1, 4], [2, 5]]
    _assert_close_per_seed(singles, stack)


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


@pytest.mark.parametrize("early_stopping", ["paper", "as_coded"])
def test_stacked_envelope_fit_is_each_seeds_own_fit(early_stopping):
    """BAIL's envelope, S seeds in one fit: own split, shuffles, validation losses, patience counts, reverts and
    returned weights per seed (a high learning rate makes the validation loss wander, so reverts happen).

    Compared exactly, against the same batched computation: seed s's row of the stack equals every row of a stack
    of S copies of seed s (the same batched product per layer, so the same rounding on any CPU). Against the plain
    fit of one network only what rounding cannot move is compared: a batched and a plain product round differently,
    and 14 epochs at this learning rate amplify that beyond any fixed tolerance (1.2e-3 relative on an AVX-512 CPU).
    """
    from torchrl_bail.envelope import fit_upper_envelope, fit_upper_envelopes
    from torchrl_bail.modules import make_value_network
    from torchrl_bail.stacking import stack_modules, unstack_modules

    observations = torch.randn(300, OBS, generator=torch.Generator().manual_seed(0))
    returns = observations[:, 0] * 3 + torch.randn(300, generator=torch.Generator().manual_seed(1))
    kwargs = dict(epochs=14, patience=2, batch_size=32, lr=0.05, early_stopping=early_stopping, progress=False)

    def network(seed):
        torch.manual_seed(seed)
        return make_value_network(OBS, (16, 16))

    def stacked_fit(seeds, **overrides):
        networks = [network(seed) for seed in seeds]
        stacked = stack_modules(networks)
        fits = fit_upper_envelopes(stacked, observations, returns, **{**kwargs, **overrides},
                                   generators=[torch.Generator().manual_seed(seed) for seed in seeds])
        unstack_modules(stacked, networks)
        return list(zip(fits, networks, strict=True))

    mixed = stacked_fit(SEEDS)
    assert any(fit.revert_epochs for fit, _ in mixed) or early_stopping == "as_coded"
    for seed, (fit, net) in zip(SEEDS, mixed, strict=True):
        for alone, alone_net in stacked_fit([seed] * len(SEEDS)):
            assert torch.equal(fit.train_index, alone.train_index) and torch.equal(fit.val_index, alone.val_index)
            assert (fit.best_epoch, fit.revert_epochs, fit.returned) == \
                (alone.best_epoch, alone.revert_epochs, alone.returned)
            assert fit.val_loss == alone.val_loss and fit.train_loss == alone.train_loss
            for (name, p), q in zip(net.named_parameters(), alone_net.parameters(), strict=True):
                assert torch.equal(p, q), name
    # the stack against one plain network: the same split and, with the weights held still (lr=0), the same
    # validation losses to float32's rounding of three products of at most 16 terms and a mean over the
    # validation points (relative, about (3 * 16 + n) * 2^-24; 3x that is allowed)
    held = dict(epochs=2, lr=0.0)
    for seed, (fit, _) in zip(SEEDS, stacked_fit(SEEDS, **held), strict=True):
        single = fit_upper_envelope(network(seed), observations, returns, generator=torch.Generator().manual_seed(seed),
                                    **{**kwargs, **held})
        assert torch.equal(fit.train_index, single.train_index) and torch.equal(fit.val_index, single.val_index)
        rtol = 3 * (3 * 16 + len(single.val_index)) * torch.finfo(torch.float32).eps / 2
        torch.testing.assert_close(torch.tensor(fit.val_loss), torch.tensor(single.val_loss), rtol=rtol, atol=0)


class _Kill(BaseException):
    """Stands in for SIGKILL in the middle of a run."""


@pytest.mark.parametrize(("name", "seeds"), [("bc", SEEDS), ("pbail", SEEDS), ("bc", (7,))],
                         ids=["bc", "pbail", "bc_one_seed"])
def test_killed_stacked_run_resumes_from_its_per_seed_checkpoints(tmp_path, name, seeds):
    """The stack writes one single-seed checkpoint per seed; the stacked run continued from them ends where the
    uninterrupted stacked run ends, and each of them also continues alone as that seed's single-seed run. A
    one-seed stack (``seeds=1``, or the one unfinished seed of a stacked command) checkpoints and resumes the same
    way."""
    from _contract import equal_trees
    from tensordict import TensorDict

    case = ALGO_CASES[name]
    data = loss_batch((200,), seed=2)
    observation = torch.randn(5, OBS, generator=torch.Generator().manual_seed(3))

    def evaluate(policy):
        obs = observation.expand(len(seeds), 5, OBS) if evaluate.stacked else observation
        with torch.no_grad():
            actions = policy(TensorDict({"observation": obs}, obs.shape[:-1]))["action"]
        sums = actions.sum((-2, -1))
        return [float(v) for v in sums] if evaluate.stacked else float(sums)

    kwargs = dict(evaluate=evaluate, samples_per_epoch=ALGO_BATCH * 12, eval_every_epochs=0.25, log_every=5,
                  progress=False)

    def fresh_stack(checkpoints=None):
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
        stack = SeedStack(algorithms)
        return stack, SeedBatchSampler(prepared, ALGO_BATCH, streams)

    evaluate.stacked = True
    reference, sampler = fresh_stack()
    reference_histories = train_seeds(StackedTrainee(reference, sampler), **kwargs)
    reference.unstack()

    paths = [tmp_path / f"seed{seed}.pt" for seed in seeds]
    killed, sampler = fresh_stack()
    update, calls = killed.update, [0]

    def dying_update(batch):
        calls[0] += 1
        if calls[0] == 8:
            raise _Kill
        return update(batch)

    killed.update = dying_update
    with pytest.raises(_Kill):
        train_seeds(StackedTrainee(killed, sampler), checkpoint_paths=paths, checkpoint_every_s=0.0, **kwargs)
    checkpoints = [torch.load(p, weights_only=False) for p in paths]
    assert [c["iteration"] for c in checkpoints] == [7] * len(seeds)
    torch.manual_seed(99)  # the checkpoints' streams replace whatever the process has
    resumed, sampler = fresh_stack(checkpoints)
    histories = train_seeds(StackedTrainee(resumed, sampler), checkpoint_paths=paths, resume_from=checkpoints, **kwargs)
    assert [h.evaluations for h in histories] == [h.evaluations for h in reference_histories]
    resumed.unstack()
    for got, expected in zip(resumed.algorithms, reference.algorithms, strict=True):
        equal_trees(got.state_dict(), expected.state_dict())

    evaluate.stacked = False  # the last seed's checkpoint, continued by its single-seed run
    single = _built(case, seeds[-1])
    single_data = single.prepare(data, _context(seeds[-1]))
    single_reference = train(single, single_data, **kwargs)
    alone = _built(case, seeds[-1])
    alone.load_state_dict(checkpoints[-1]["algorithm"])
    history = train(alone, alone.restore_prepared(data, _context(seeds[-1])), resume_from=checkpoints[-1], **kwargs)
    assert len(history.evaluations) == len(single_reference.evaluations)
    for got, expected in zip(history.evaluations, single_reference.evaluations, strict=True):
        assert math.isclose(got.mean_return, expected.mean_return, rel_tol=1e-4, abs_tol=1e-4)
    _assert_close_trees(alone.state_dict(), single.state_dict(), "alone")


@pytest.mark.parametrize("seeds", ["[1,1]", "0", "[]", "[-1]", "abc"])
def test_bad_seeds_are_refused_naming_the_key(seeds):
    from torchrl_bail.config import ConfigError, validate_config

    with pytest.raises(ConfigError, match=r"config key seeds = .*expected null, a count S >= 1"):
        validate_config(_tiny_config(f"seeds={seeds}"))


def test_compiled_stack_updates_like_the_eager_stack():
    """``seeds=`` with ``compile``: the host's one update is compiled (aot_eager here: the same Dynamo capture as
    inductor, cheap on CPU), the per-seed gradient hooks included; weights agree with the eager stack's."""
    from tensordict import TensorDict

    from torchrl_bail.algorithms.bc import BehaviourCloning
    from torchrl_bail.config_builders import algo_config
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

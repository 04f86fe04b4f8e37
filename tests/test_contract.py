"""The contract every loss and every algorithm keeps, run over the cases registered in tests/_contract.py.

Losses: each back-propagated term reaches only its own parameters and never a target network; ``set_keys`` renames
what the loss reads; the three reductions agree; an ``[S, B]`` batch gives, seed by seed, what ``S`` separate
``[B]`` calls give (masks and seed-ensembled networks included); keyword calls equal tensordict calls; a
``state_dict`` round trip gives identical outputs.

Algorithms (every entry of the registry ``ALGORITHMS``): optimizers own disjoint parameters and all step; the
policy acts within the bounds; ``conf/algo/<name>.yaml`` holds every default (no constructor restates one); same
seed, same numbers; a checkpoint round trip continues identically; a tiny run
through the config and ``torchrl_bail.train.run`` writes its artifacts.
"""

from __future__ import annotations

import copy
import functools
import importlib
import importlib.util
import inspect
import io
import json
import math
from pathlib import Path

import pytest
import torch
from _batch_rl_testing import ACT, HIDDEN, OBS, SPEC, one_thread  # noqa: F401 (autouse fixture)
from _contract import (
    ALGO_BATCH,
    ALGO_CASES,
    LOSS_CASES,
    TINY_HIDDEN,
    TINY_RUN,
    TINY_STEPS,
    TINY_UPDATES,
    equal_trees,
    loss_batch,
    row_noise,
    row_noise_like,
)
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from tensordict import TensorDict
from torchrl.envs import Transform
from torchrl.objectives import BCLoss, LossModule

import torchrl_bail.objectives
from torchrl_bail import config_dir
from torchrl_bail.algorithms import ALGORITHMS, Algorithm, PrepareContext
from torchrl_bail.configuration.algo_schemas import ALGO_SCHEMAS, blocks_with, entry_gaps
from torchrl_bail.configuration.config import ConfigError, validate_config
from torchrl_bail.configuration.config_builders import algo_config, tiny_run_overrides
from torchrl_bail.evaluation.policy import load_policy
from torchrl_bail.modules import action_spec_from_bounds

REDUCTIONS = ("none", "mean", "sum")
loss_cases = pytest.mark.parametrize("case", LOSS_CASES, ids=repr)
algo_cases = pytest.mark.parametrize("case", list(ALGO_CASES.values()), ids=repr)


# -- helpers ----------------------------------------------------------------------------------------------------
def _build(case, seed: int = 0, **kwargs):
    torch.manual_seed(seed)
    return case.build(**kwargs)


def _call(loss, td, seed: int = 1):
    """The loss' outputs on ``td`` with torch's global generator at ``seed`` (stochastic losses draw from it)."""
    torch.manual_seed(seed)
    return loss(td)


def _group(name: str) -> str:
    return name.split(".")[0]


def _groups_with_grad(loss) -> set[str]:
    return {_group(name) for name, p in loss.named_parameters() if p.grad is not None and p.grad.abs().sum() > 0}


def _target_tensors(loss) -> list[torch.Tensor]:
    groups = {_group(name) for name, _ in loss.named_parameters()}
    out = []
    for group in groups:
        target = getattr(loss, f"target_{group}", None)
        if target is not None:
            out.extend(target.values(True, True))
    return out


def _assert_outputs_equal(a, b) -> None:
    assert set(a.keys()) == set(b.keys())
    for key in a.keys():
        torch.testing.assert_close(a[key], b[key], msg=lambda m, key=key: f"{key}: {m}")


def _rename_entries(td: TensorDict, old: str, new: str) -> TensorDict:
    """Moves every entry whose last key is ``old`` (at the root or under ``"next"``) to ``new``."""
    td = td.clone(False)
    for key in list(td.keys(True, True)):
        path = key if isinstance(key, tuple) else (key,)
        if path[-1] == old:
            td.rename_key_(key, (*path[:-1], new) if len(path) > 1 else new)
    return td


def _leaf(key) -> str:
    return key[-1] if isinstance(key, tuple) else key


# -- the registry is covered ------------------------------------------------------------------------------------
def test_every_loss_and_algorithm_has_a_contract_case():
    losses = {obj for name in torchrl_bail.objectives.__all__
              if isinstance(obj := getattr(torchrl_bail.objectives, name), type) and issubclass(obj, LossModule)}
    covered = {type(_build(case)) for case in LOSS_CASES}
    missing = {cls.__name__ for cls in losses | {BCLoss}} - {cls.__name__ for cls in covered}
    assert not missing, f"register a LossCase for {sorted(missing)} in tests/_contract.py"
    assert list(ALGORITHMS) == list(ALGO_SCHEMAS), "every algorithm class needs its schema in ALGO_SCHEMAS and back"
    uncovered = sorted(set(ALGORITHMS) - set(ALGO_CASES))
    assert not uncovered, (f"no contract case for {uncovered}: each derives from its registry entry; state its "
                           "schema's `tiny` in its module (torchrl_bail/algorithms/<name>.py)")


@pytest.mark.parametrize("name", list(ALGO_SCHEMAS))
def test_every_registry_entry_is_complete(name):
    """What the tiny runs and the docs' table read of an algorithm (``tiny``, ``description``, ``losses``) has no
    default: each schema states it, and each loss module it names imports."""
    gaps = entry_gaps(name)
    assert not gaps, f"state {', '.join(gaps)} in {ALGO_SCHEMAS[name].__module__} (AlgoConfig says what each is)"
    for path in ALGO_SCHEMAS[name].losses:
        module, _, attr = path.rpartition(".")
        assert hasattr(importlib.import_module(module), attr), f"{ALGO_SCHEMAS[name].__name__}.losses: {path}"



@algo_cases
def test_every_contract_case_is_its_registry_entrys_tiny_run(case):
    """The case derives from the registry entry: every network of the schema tiny, its ``tiny`` overrides (the
    mini-batches aside: :data:`ALGO_BATCH` here), and the tiny run through the config is the entry's."""
    config = case.build().config
    for block in blocks_with(case.name, "hidden"):
        assert list(OmegaConf.select(config, f"{block}.hidden")) == list(HIDDEN), block
    for override in ALGO_SCHEMAS[case.name].tiny:
        key = override.split("=", 1)[0]
        expected = OmegaConf.select(OmegaConf.from_dotlist([override]), key)
        expected = ALGO_BATCH if key.endswith("batch_size") else expected
        assert OmegaConf.select(config, key) == expected, override
    assert list(case.cli) == tiny_run_overrides(case.name, TINY_UPDATES, TINY_HIDDEN)

@pytest.mark.parametrize("name", list(ALGO_SCHEMAS))
def test_the_registry_names_every_loss_module_the_algorithm_holds(name):
    """Each loss module and transform a built algorithm holds (the paper's networks, before ``prepare``) is in its
    registry entry's ``losses``, the docs' column (those made in ``prepare`` or inside another, like BCQ's
    ``VAELoss``, cannot be seen here)."""
    algo = ALGORITHMS[name](OBS, SPEC, algo_config(name))
    modules = [v for value in vars(algo).values() for v in (value.values() if isinstance(value, dict) else [value])
               if isinstance(v, torch.nn.Module)]
    held = {type(m) for module in modules for m in module.modules() if isinstance(m, (LossModule, Transform))}
    named = {getattr(importlib.import_module(module), attr)
             for module, _, attr in (path.rpartition(".") for path in ALGO_SCHEMAS[name].losses)}
    assert held, f"{name} holds no loss module"
    assert held <= named, f"{ALGO_SCHEMAS[name].__name__}.losses lacks {sorted(c.__name__ for c in held - named)}"


@pytest.mark.parametrize("name", list(ALGORITHMS))
def test_every_algorithm_has_its_yaml_and_presets(name):
    """``conf/algo/<name>.yaml`` (the paper's values) and the quick and study presets, each shorter than the paper's
    schedule and valid."""
    epochs = {}
    for preset in ("paper", "quick", "study"):
        if preset != "paper":
            assert (config_dir() / "algo_preset" / f"{name}_{preset}.yaml").is_file(), f"{name}_{preset}.yaml"
        with initialize_config_dir(str(config_dir()), version_base="1.3"):
            cfg = compose("config", overrides=["+exp=hopper_ddpg05", f"algo={name}", f"preset={preset}"])
        validate_config(cfg)
        epochs[preset] = cfg.algo.epochs
    assert epochs["quick"] < epochs["paper"] and epochs["study"] < epochs["paper"], epochs



# -- the docs' algorithm table: the registry and the yaml -------------------------------------------------------------
def _table_generator():
    path = Path(__file__).resolve().parents[1] / "docs" / "gen_algorithm_table.py"
    spec = importlib.util.spec_from_file_location("gen_algorithm_table", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


table_generator = _table_generator()


def test_the_docs_table_has_a_row_per_registered_algorithm_with_its_yamls_schedule():
    rows = {line.split("|")[1].strip().strip("`"): line for line in table_generator.table().splitlines()[2:]}
    assert list(rows) == list(ALGO_SCHEMAS)
    for name, row in rows.items():
        algo = algo_config(name)
        assert f"| {algo.batch_size} · {algo.epochs:g} epochs (" in row, row
        assert ALGO_SCHEMAS[name].description.split(":")[0] in row, row
    assert "(125k updates)" in rows["pbail"]  # its updates count 0.8 of a batch each: the algorithm says so, not 10^5
    assert "best 30% by G/V" in rows["bail"] and "envelope 800 · 50 passes" in rows["bail"]  # filled from the yaml
    page = (Path(__file__).resolve().parents[1] / "docs" / table_generator.PAGE).read_text()
    assert page.count(table_generator.MARKER) == 1, "the Algorithms page lost the table's place"


@pytest.mark.parametrize(("variable", "value", "message"), [
    ("description", None, r"without what the Algorithms page shows: IQLConfig\.description"),
    ("losses", (), r"without what the Algorithms page shows: IQLConfig\.losses"),
    ("tiny", None, r"without what the Algorithms page shows: IQLConfig\.tiny"),
    ("description", "IQL, {no_such_key}", r"IQLConfig\.description names algo\.no_such_key,")])
def test_a_registry_entry_without_its_table_data_stops_the_table(monkeypatch, variable, value, message):
    monkeypatch.setattr(ALGO_SCHEMAS["iql"], variable, value)
    with pytest.raises(table_generator.MissingEntry, match=message):
        table_generator.table()


# -- one default per constant: the yaml --------------------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(ALGORITHMS))
def test_no_constructor_restates_a_default_of_the_yaml(name):
    for cls in ALGORITHMS[name].__mro__:
        if issubclass(cls, Algorithm) and "__init__" in vars(cls):
            defaults = [p.name for p in inspect.signature(cls.__init__).parameters.values()
                        if p.default is not p.empty and p.name != "device"]
            assert not defaults, f"{cls.__name__}.__init__ restates defaults of conf/algo/{name}.yaml: {defaults}"
    algo = ALGORITHMS[name](OBS, SPEC, algo_config(name))
    yaml = OmegaConf.load(config_dir() / "algo" / f"{name}.yaml")
    yaml.pop("defaults")
    assert OmegaConf.to_container(algo.config) == OmegaConf.to_container(yaml)


@pytest.mark.parametrize("name", sorted(ALGORITHMS))
def test_every_state_attribute_exists(name):
    """What ``state_attributes`` lists is real state: each name is an attribute of a freshly built algorithm (a
    listed name that exists nowhere would silently leave its state out of every checkpoint)."""
    algo = ALGORITHMS[name](OBS, SPEC, algo_config(name))
    missing = [k for k in type(algo).state_attributes if not hasattr(algo, k)]
    assert not missing, f"{type(algo).__name__}.state_attributes names attributes that do not exist: {missing}"
    assert set(algo.state_dict()["attributes"]) == set(type(algo).state_attributes)


def test_a_mapping_takes_the_yaml_values_it_leaves_out_and_is_checked():
    algo = ALGORITHMS["bc"](OBS, SPEC, {"policy": {"hidden": [8]}, "batch_size": 4})
    assert algo.config == algo_config("bc", batch_size=4, **{"policy.hidden": [8]})
    assert algo.config.policy.lr == algo_config("bc").policy.lr and algo.batch_size == 4
    with pytest.raises(ConfigError, match=r"algo\.policy\.lr = -1\.0: expected a positive learning rate"):
        ALGORITHMS["bc"](OBS, SPEC, {"policy": {"lr": -1.0}})
    with pytest.raises(ConfigError, match=r"algo\.name = 'bc': expected bail"):
        ALGORITHMS["bail"](OBS, SPEC, algo_config("bc"))


# -- losses ---------------------------------------------------------------------------------------------------------
@loss_cases
def test_loss_outputs_and_which_parameters_each_term_reaches(case):
    loss = _build(case)
    out = _call(loss, loss_batch())
    assert {key for key in out.keys() if key.startswith("loss")} == set(case.reaches)
    for key, value in out.items():
        assert value.shape == (), key
        assert value.requires_grad == (key in case.reaches), key
    params = list(loss.parameters())
    assert len({id(p) for p in params}) == len(params), "a parameter is listed twice"
    targets = _target_tensors(loss)
    for term, groups in case.reaches.items():
        loss.zero_grad(set_to_none=True)
        _call(loss, loss_batch())[term].backward()
        assert _groups_with_grad(loss) == groups, term
        assert all(not t.requires_grad and t.grad is None for t in targets), f"{term} reached a target network"
    loss.zero_grad(set_to_none=True)
    out = _call(loss, loss_batch())
    sum(out[term] for term in case.reaches).backward()
    untrained = [name for name, p in loss.named_parameters() if p.grad is None or p.grad.abs().sum() == 0]
    assert not untrained, f"parameters no term trains: {untrained}"


@loss_cases
def test_set_keys_renames_what_the_loss_reads(case):
    if not case.rename:
        pytest.skip(f"{case.name} reads no key it could rename")
    td = loss_batch()
    expected = _call(_build(case), td)
    loss = _build(case)
    defaults = {field: getattr(loss.tensor_keys, field) for field in case.rename}
    loss.set_keys(**case.rename)
    renamed = td
    for field, new in case.rename.items():
        renamed = _rename_entries(renamed, defaults[field], new)
    leaves = {_leaf(key) for key in loss.in_keys}
    assert set(case.rename.values()) <= leaves and not set(defaults.values()) & leaves, loss.in_keys
    _assert_outputs_equal(_call(loss, renamed), expected)
    with pytest.raises(KeyError):
        _call(loss, td)  # the old names are no longer read
    with pytest.raises(ValueError):
        loss.set_keys(no_such_key="x")
    loss.set_keys(**dict.fromkeys(case.rename))
    assert {field: getattr(loss.tensor_keys, field) for field in case.rename} == defaults


@loss_cases
def test_reductions_agree(case):
    td = loss_batch()
    outs = {reduction: _call(_build(case, reduction=reduction), td) for reduction in REDUCTIONS}
    for key in outs["none"].keys():
        none, mean, total = outs["none"][key], outs["mean"][key], outs["sum"][key]
        if key in case.reaches:
            assert none.shape[0] == td.shape[0], key
            torch.testing.assert_close(mean, none.mean())
            torch.testing.assert_close(total, none.sum())
        else:  # diagnostics do not depend on the reduction
            torch.testing.assert_close(mean, none)
            torch.testing.assert_close(total, none)
    if not case.torchrl_own:
        with pytest.raises(ValueError, match="reduction"):
            _build(case, reduction="max")


@loss_cases
@pytest.mark.parametrize("reduction", REDUCTIONS)
def test_seed_batch_equals_separate_calls(case, reduction, monkeypatch):
    """``[S, B]`` -> per seed what ``S`` separate ``[B]`` calls give (in eval mode: no running statistic moves)."""
    loss = _build(case, reduction=reduction).eval()
    td = loss_batch((3, 5))
    if case.stochastic:  # the same noise for a seed's rows whether it runs alone or beside the others
        monkeypatch.setattr(torch, "randn", row_noise)
        monkeypatch.setattr(torch, "randn_like", row_noise_like)
    out = loss(td)
    separate = [loss(td[s]) for s in range(3)]
    for key, value in out.items():
        per_seed = torch.stack([sep[key] for sep in separate])
        if key in case.reaches and reduction != "none":
            expected = per_seed.mean() if reduction == "mean" else per_seed.sum()
        elif value.shape == separate[0][key].shape:  # one value for all seeds (e.g. BEAR's alpha)
            assert (per_seed == per_seed[0]).all(), key
            expected = separate[0][key]
        else:
            expected = per_seed
        torch.testing.assert_close(value, expected, msg=lambda m, key=key: f"{key}: {m}")


@pytest.mark.parametrize("case", [c for c in LOSS_CASES if not c.torchrl_own], ids=repr)
def test_masks_reduce_each_seed_over_its_own_points(case):
    td = loss_batch((2, 3))
    td["valid"] = torch.tensor([[True, True, False], [True, False, False]])
    outs = {}
    for reduction in ("none", "mean"):
        loss = _build(case, reduction=reduction)
        loss.loss_mask_key = "valid"
        outs[reduction] = _call(loss, td)
    for term in case.reaches:
        none = outs["none"][term]
        assert (none[~td["valid"]] == 0).all(), term
        expected = ((none[0, 0] + none[0, 1]) / 2 + none[1, 0]) / 2
        torch.testing.assert_close(outs["mean"][term], expected, msg=term)


@pytest.mark.parametrize("case", [c for c in LOSS_CASES if not c.torchrl_own], ids=repr)
def test_keyword_call_matches_the_tensordict_call(case):
    loss = _build(case)
    td = loss_batch()
    expected = _call(loss, td)
    terms = sorted(case.reaches)
    loss.select_out_keys(*terms)
    kwargs = {"_".join(key) if isinstance(key, tuple) else key: td.get(key) for key in loss.in_keys}
    torch.manual_seed(1)
    got = loss(**kwargs)
    got = got if isinstance(got, tuple) else (got,)
    for term, value in zip(terms, got, strict=True):
        torch.testing.assert_close(value, expected[term], msg=term)


@loss_cases
def test_loss_state_dict_round_trip(case):
    loss = _build(case, seed=0)
    with torch.no_grad():
        for p in loss.parameters():
            p.add_(0.1 * torch.randn_like(p))
    buffer = io.BytesIO()
    torch.save(loss.state_dict(), buffer)
    buffer.seek(0)
    other = _build(case, seed=1)
    other.load_state_dict(torch.load(buffer))
    equal_trees(other.state_dict(), loss.state_dict())
    _assert_outputs_equal(_call(other, loss_batch()), _call(loss, loss_batch()))


@pytest.mark.parametrize("case", [c for c in LOSS_CASES if c.build_ensemble], ids=repr)
def test_seed_ensemble_gradients_stay_in_their_seed(case):
    seeds = 3
    torch.manual_seed(0)
    loss = case.build_ensemble(seeds)
    out = loss(loss_batch((seeds, 7)))
    for term in case.reaches:
        loss.zero_grad(set_to_none=True)
        assert out[term].shape == (seeds, 7), term
        out[term].mean(-1)[1].backward(retain_graph=True)
        stacked = [p for p in loss.parameters() if p.grad is not None and p.grad.abs().sum() > 0]
        assert stacked, term
        for p in stacked:  # the [S, ...] copies: only seed 1's slice moves
            assert p.shape[0] == seeds and p.grad[0].abs().sum() == 0 and p.grad[2].abs().sum() == 0, term


# -- algorithms -----------------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=1)
def _algo_data() -> TensorDict:
    return loss_batch((64,), seed=3)


def _prepared(case, init_seed: int = 0, data_seed: int = 0):
    """The algorithm built under ``init_seed`` and its training data, prepared with a ``data_seed`` generator."""
    torch.manual_seed(init_seed)
    algo = case.build()
    data = algo.prepare(_algo_data().clone(), PrepareContext(generator=torch.Generator().manual_seed(data_seed)))
    return algo, data


def _updates(algo, data, n: int, seed: int) -> list[dict]:
    g = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    return [algo.update(data[torch.randint(len(data), (ALGO_BATCH,), generator=g)]) for _ in range(n)]


@torch.no_grad()
def _act(algo, seed: int = 5) -> torch.Tensor:
    """The policy's actions on four fixed observations, evaluated as the evaluator does (without gradient)."""
    torch.manual_seed(seed)
    observation = torch.randn(4, OBS, generator=torch.Generator().manual_seed(seed))
    return algo.policy(TensorDict({"observation": observation}, [4]))["action"]


def _metrics_equal(a: list[dict], b: list[dict]) -> bool:
    return len(a) == len(b) and all(x.keys() == y.keys() and all(torch.equal(x[k], y[k]) for k in x)
                                    for x, y in zip(a, b, strict=True))


@algo_cases
def test_optimizers_own_disjoint_parameters_and_every_one_steps(case):
    algo, data = _prepared(case)
    owner = {}
    for name, optimizer in algo.optimizers.items():
        for group in optimizer.param_groups:
            for p in group["params"]:
                assert id(p) not in owner, f"a parameter is in optimizers {owner.get(id(p))} and {name}"
                owner[id(p)] = name
    for module_name, module in algo.modules.items():
        for key, tensor in module.state_dict(keep_vars=True).items():
            if "target_" in key:
                assert id(tensor) not in owner, f"target {module_name}.{key} is in an optimizer"
        for key, p in module.named_parameters():
            updated = id(p) in owner
            assert updated != (module_name in case.not_updated), f"{module_name}.{key} in an optimizer: {updated}"
    before = {name: [p.detach().clone() for g in o.param_groups for p in g["params"]]
              for name, o in algo.optimizers.items()}
    metrics = _updates(algo, data, 1, seed=1)[0]
    for name, optimizer in algo.optimizers.items():
        after = [p for g in optimizer.param_groups for p in g["params"]]
        stepped = any(not torch.equal(x, y) for x, y in zip(before[name], after, strict=True))
        assert stepped, f"optimizer {name} did not step"
    for key, value in metrics.items():
        assert isinstance(value, torch.Tensor) and not value.requires_grad and value.numel() == 1, key
        assert torch.isfinite(value), key


@algo_cases
def test_policy_acts_within_the_bounds(case):
    algo, _ = _prepared(case)
    action = _act(algo)
    assert action.shape == (4, ACT)
    assert ((action >= SPEC.space.low) & (action <= SPEC.space.high)).all()
    single = algo.policy(TensorDict({"observation": torch.zeros(OBS)}, []))["action"]
    assert single.shape == (ACT,)


@algo_cases
def test_same_seed_same_numbers(case):
    def run(seed):
        algo, data = _prepared(case, init_seed=seed, data_seed=seed)
        return _updates(algo, data, 3, seed=seed), _act(algo), algo.summary()

    (m1, a1, s1), (m2, a2, s2), (m3, a3, _) = run(0), run(0), run(1)
    assert _metrics_equal(m1, m2) and torch.equal(a1, a2)
    equal_trees(s1, s2, "summary")
    assert not (_metrics_equal(m1, m3) and torch.equal(a1, a3)), "another seed gave the same numbers"


@algo_cases
def test_checkpoint_round_trip_continues_identically(case):
    """Through bytes, as the trainer's checkpoint: whatever ``state_dict`` holds comes back, and the next updates
    (and actions) are those of the uninterrupted run. A resumed run prepares its data with the same seed."""
    algo, data = _prepared(case, init_seed=0)
    _updates(algo, data, 2, seed=1)
    buffer = io.BytesIO()
    torch.save(algo.state_dict(), buffer)
    buffer.seek(0)
    resumed, _ = _prepared(case, init_seed=1)
    resumed.load_state_dict(torch.load(buffer, weights_only=False))
    equal_trees(resumed.state_dict(), algo.state_dict())
    assert _metrics_equal(_updates(resumed, data, 2, seed=2), _updates(algo, data, 2, seed=2))
    assert torch.equal(_act(resumed), _act(algo))


@algo_cases
def test_a_deep_copy_trains_on_its_own(case):
    """``copy.deepcopy`` of a prepared, trained algorithm continues as the original would (same updates, same
    actions) and updates only its own networks: TensorDict's clone-on-deepcopy used to leave the copy's losses
    holding parameters apart from its networks, so the copy's optimizers never moved them."""
    algo, data = _prepared(case, init_seed=0)
    _updates(algo, data, 2, seed=1)
    rng = torch.get_rng_state()
    twin = copy.deepcopy(algo)
    assert torch.equal(torch.get_rng_state(), rng), "copying consumed the caller's random numbers"
    equal_trees(twin.state_dict(), algo.state_dict(), "copied")
    assert _metrics_equal(_updates(twin, data, 2, seed=2), _updates(algo, data, 2, seed=2))
    assert torch.equal(_act(twin), _act(algo))
    equal_trees(twin.state_dict(), algo.state_dict(), "updated alike")
    before = copy.deepcopy(algo.state_dict())
    _updates(twin, data, 2, seed=3)
    equal_trees(algo.state_dict(), before, "original")  # the copy's updates leave the original alone
    trained = [name for name in twin.modules if name not in case.not_updated]
    assert trained and all(not torch.equal(p, q) for name in trained for p, q in
                           zip(twin.modules[name].parameters(), algo.modules[name].parameters(), strict=True))


@algo_cases
def test_tiny_run_through_the_config(case, tiny_run_data_dir, tmp_path):
    from torchrl_bail.train import run

    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("config", overrides=[*TINY_RUN, f"algo={case.name}", *case.cli, f"data_dir={tiny_run_data_dir}"])
    (summary,) = run(cfg, tmp_path)
    assert (summary["algo"], summary["num_transitions"]) == (case.name, TINY_STEPS)
    assert math.isfinite(summary["final_return"]) and summary["iterations"] >= 1
    for name in ("summary.json", "policy.pt", "checkpoint.pt", "learning_curve.png", "config.yaml"):
        assert (tmp_path / name).stat().st_size > 0, name
    # policy.pt comes back as the policy the run ended with: the final checkpoint's algorithm acts alike
    policy = load_policy(tmp_path)
    assert policy.record["algo"] == case.name
    spec = action_spec_from_bounds(policy.record["action_low"], policy.record["action_high"])
    trained = ALGORITHMS[case.name](policy.record["obs_dim"], spec, cfg.algo)
    checkpoint = torch.load(tmp_path / "checkpoint.pt", weights_only=False)
    assert checkpoint["iteration"] == summary["iterations"]
    trained.load_state_dict(checkpoint["algorithm"])
    observation = TensorDict({"observation": torch.randn(5, policy.record["obs_dim"])}, [5])
    actions = []
    for acting in (policy, trained.policy):
        torch.manual_seed(0)  # a best-of-N policy samples its candidates
        with torch.no_grad():
            actions.append(acting(observation.clone())["action"])
    torch.testing.assert_close(actions[0], actions[1], rtol=0, atol=0)
    # and FQE scores it (python -m torchrl_bail.ope: every algorithm's policy.pt, a sampling one included)
    from torchrl_bail.ope import main as ope_main

    assert ope_main([str(tmp_path), "--updates", "20", "--log-every", "10", "--hidden", "16,16", "--no-progress"]) == 0
    scored = json.loads((tmp_path / "ope.json").read_text())
    assert scored["algo"] == case.name and math.isfinite(scored["estimate"])

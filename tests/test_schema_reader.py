"""The registries read from the code's own files: an algorithm's schema sits in ``algorithms/<name>.py`` beside its
class, a recipe's in its ``behaviour/`` module beside its collection; each is read there without importing the file,
and importing the file gives back the same classes (:mod:`torchrl_bail.configuration.schema_reader`)."""

from __future__ import annotations

import dataclasses
import importlib
import re
import subprocess
import sys
import textwrap
import typing

import pytest

from torchrl_bail.configuration import algo_schemas, schema_reader
from torchrl_bail.configuration.algo_schemas import ALGO_SCHEMAS
from torchrl_bail.configuration.batch_schemas import BATCH_SCHEMAS
from torchrl_bail.configuration.config import ConfigError
from torchrl_bail.configuration.schema_reader import SchemaReadError, read_schemas


def _blocks(schema: type) -> list[type]:
    """``schema`` and every dataclass block it nests, depth first."""
    found = [schema]
    for f in dataclasses.fields(schema):
        block = typing.get_type_hints(schema)[f.name]
        if dataclasses.is_dataclass(block):
            found += _blocks(block)
    return found


def _defined_once(schema: type) -> None:
    for block in _blocks(schema):  # the entry, its own blocks and those it shares with a sibling or a registry
        module = importlib.import_module(block.__module__)
        assert getattr(module, block.__name__) is block, f"{block.__module__}.{block.__name__} defined twice"


def test_each_algorithm_is_one_file_whose_classes_are_the_schemas_read_without_it():
    from torchrl_bail.algorithms import ALGORITHMS

    for name, schema in ALGO_SCHEMAS.items():
        assert ALGORITHMS[name].__module__ == schema.__module__
        assert schema.__module__.startswith("torchrl_bail.algorithms.")
        _defined_once(schema)


def test_each_recipe_is_one_module_holding_its_schema():
    from torchrl_bail.behaviour import RECIPES

    assert list(BATCH_SCHEMAS) == sorted(RECIPES)
    for name, schema in BATCH_SCHEMAS.items():
        assert type(RECIPES[name]).__module__ == schema.__module__, name
        _defined_once(schema)


def _package(tmp_path, **files: str):
    folder = tmp_path / "algorithms"
    folder.mkdir()
    for stem, text in files.items():
        (folder / f"{stem}.py").write_text(textwrap.dedent(text))
    return folder


def _read(folder) -> None:
    read_schemas(folder, "torchrl_bail.algorithms", {"algo_schema"})


@pytest.fixture
def empty_registry(monkeypatch):
    """A registry of its own for the test's made-up algorithms."""
    monkeypatch.setattr(algo_schemas, "ALGO_SCHEMAS", {})
    monkeypatch.setattr(schema_reader, "_DEFINED", {})
    return algo_schemas


HEAD = """\
    from __future__ import annotations

    import torch
    from omegaconf import MISSING

    from torchrl_bail.configuration.algo_schemas import AlgoConfig, NetConfig, algo_schema, schema_block
    from torchrl_bail.configuration.config import discount
"""


def test_a_schema_is_read_with_its_files_imports_and_its_siblings_schema_classes(tmp_path, empty_registry):
    folder = _package(tmp_path, shared=HEAD + """
    @schema_block
    class SharedConfig(AlgoConfig):
        gamma: float = discount()
    """, mine=HEAD + """
    from torchrl_bail.algorithms.shared import SharedConfig, helper_that_needs_torch

    SCALE = torch.tensor(2.0)  # never run: the reader runs the imports it knows and the schema classes only

    @algo_schema("mine")
    class MineConfig(SharedConfig):
        column = 0.5
        policy: NetConfig = MISSING
    """)
    _read(folder)
    schema = empty_registry.ALGO_SCHEMAS["mine"]
    assert list(empty_registry.ALGO_SCHEMAS) == ["mine"]  # the shared block is no entry
    assert schema.__module__ == "torchrl_bail.algorithms.mine" and schema.column == 0.5
    assert schema.__mro__[1].__module__ == "torchrl_bail.algorithms.shared"
    assert [f.name for f in dataclasses.fields(schema)] == ["name", "batch_size", "epochs", "gamma", "policy"]
    assert typing.get_type_hints(schema)["policy"] is algo_schemas.NetConfig  # annotations resolved, not strings
    with pytest.raises(ConfigError, match="gamma"):
        schema(name="mine", batch_size=1, epochs=1, gamma=1.5, policy=algo_schemas.NetConfig([8], 1e-3))


def test_a_schema_using_what_the_reader_does_not_run_is_refused_naming_the_file_line_and_name(tmp_path,
                                                                                            empty_registry):
    folder = _package(tmp_path, bad=HEAD + """
    SCALE = 2.0

    @algo_schema("bad")
    class BadConfig(AlgoConfig):
        lr: float = SCALE
    """)
    expected = (r"bad\.py:12: schema BadConfig uses 'SCALE', which the torch-free reader does not define.*"
                r"without importing torchrl_bail\.algorithms\.bad")
    with pytest.raises(SchemaReadError, match=expected):
        _read(folder)
    assert empty_registry.ALGO_SCHEMAS == {}


@pytest.mark.parametrize("body, where", [
    ("    def check(self) -> None:\n        assert self.lr < LIMIT\n", "BadConfig.check"),
    ("    top: float = rule(lambda v: v < LIMIT, 'below the limit')\n", "BadConfig.<lambda>"),
])
def test_a_method_or_rule_using_what_the_reader_does_not_define_is_refused_when_read(tmp_path, empty_registry, body,
                                                                                       where):
    """A method or a rule's lambda keeps the reader's namespace as its globals: a name missing there would fail
    only when a config is checked, as a NameError; it is refused when the schema is read."""
    folder = _package(tmp_path, bad=HEAD + """
    from torchrl_bail.configuration.config import rule

    LIMIT = 1.0

    @algo_schema("bad")
    class BadConfig(AlgoConfig):
        lr: float = 0.5
""" + textwrap.indent(body, "    "))
    with pytest.raises(SchemaReadError, match=rf"bad\.py:\d+: {re.escape(where)} uses 'LIMIT'"):
        _read(folder)


def test_relative_sibling_imports_attribute_decorators_and_the_package_init(tmp_path, empty_registry):
    folder = _package(tmp_path, __init__="raise RuntimeError('never read: the package imports its modules')\n",
                      shared=HEAD + """
    @schema_block
    class SharedConfig(AlgoConfig):
        gamma: float = discount()
    """, rel="""\
    from __future__ import annotations

    import torchrl_bail.configuration.algo_schemas as registry

    from .shared import SharedConfig

    @registry.algo_schema("rel")
    class RelConfig(SharedConfig):
        pass
    """)
    _read(folder)
    assert [f.name for f in dataclasses.fields(empty_registry.ALGO_SCHEMAS["rel"])][-1] == "gamma"


def test_a_sweeps_configs_travel_to_other_processes_as_the_registered_schemas(tmp_path):
    """joblib's and submitit's launchers cloudpickle each job's config: a schema class read from a module that is
    not imported would travel by value, and the worker's copy is no registered schema (StopIteration at its check);
    the command line imports the modules first (cli.import_schema_modules)."""
    cloudpickle = pytest.importorskip("cloudpickle")
    blob = tmp_path / "config.pkl"
    send = ("import sys, cloudpickle; from torchrl_bail.configuration.config_builders import algo_config; "
            "from torchrl_bail.cli import import_schema_modules; import_schema_modules(); "
            f"open({str(blob)!r}, 'wb').write(cloudpickle.dumps(algo_config('bail')))")
    receive = ("import pickle; from omegaconf import OmegaConf; "
               "from torchrl_bail.configuration.algo_schemas import ALGO_SCHEMAS; "
               f"cfg = pickle.load(open({str(blob)!r}, 'rb')); obj = OmegaConf.to_object(cfg); "
               "print(type(obj) is ALGO_SCHEMAS['bail'], type(obj).__module__)")
    for code in (send, receive):
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
        assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["True", "torchrl_bail.algorithms.bail"]
    assert cloudpickle  # the worker side needs plain pickle only


def test_schemas_importing_each_other_and_two_schemas_of_one_name_are_refused(tmp_path, empty_registry):
    cycle = _package(tmp_path, a=HEAD + "    from torchrl_bail.algorithms.b import BConfig\n",
                     b=HEAD + "    from torchrl_bail.algorithms.a import AConfig\n")
    with pytest.raises(SchemaReadError, match=r"b\.py: imports from a\.py, which imports from it"):
        _read(cycle)
    twice = HEAD + """
    @algo_schema("same")
    class {0}(AlgoConfig):
        pass
    """
    (tmp_path / "twice").mkdir()
    folder = _package(tmp_path / "twice", one=twice.format("OneConfig"), two=twice.format("TwoConfig"))
    with pytest.raises(ValueError, match=r"two schemas named 'same': torchrl_bail\.algorithms\.one\.OneConfig and "
                                         r"torchrl_bail\.algorithms\.two\.TwoConfig"):
        _read(folder)


def test_the_registry_is_in_column_order():
    columns = [schema.column for schema in ALGO_SCHEMAS.values()]
    assert columns == sorted(columns) and len(set(columns)) == len(columns)
    assert list(ALGO_SCHEMAS)[:2] == ["bail", "pbail"]  # the report's first columns: BAIL, then Progressive BAIL


def test_an_unstated_entry_is_pointed_to_in_its_algorithms_own_file(monkeypatch):
    from torchrl_bail.configuration.config_builders import tiny_run_overrides

    monkeypatch.setattr(ALGO_SCHEMAS["iql"], "tiny", None)
    with pytest.raises(ValueError, match=r"IQLConfig\.tiny is not stated: .*state it on the schema in "
                                         r"torchrl_bail\.algorithms\.iql\)"):
        tiny_run_overrides("iql", 5, [16])

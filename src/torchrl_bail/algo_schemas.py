"""The algorithms' registry (:data:`ALGO_SCHEMAS`): each algorithm's schema (``conf/algo``), named
``algo/base_<name>_schema`` in Hydra (:func:`torchrl_bail.hydra_setup.register_schemas`), is its registry entry
(:class:`AlgoConfig`'s class variables): what the study, the drills, the contract suite and the docs know of an
algorithm besides its keys. The rules come from :mod:`torchrl_bail.config`; this module holds the keys every
algorithm has, the blocks several share and the registration (:func:`algo_schema`, :func:`schema_block`).

A schema is written in its algorithm's module (``algorithms/<name>.py``), beside the update step, and read from
there without importing it. The module imports torch, tensordict and torchrl, while a command line is checked
against its schema before any of them loads, so that a bad one fails in about a second
(:func:`torchrl_bail.cli.run_cli`): measured on the project's 2-core CPU (one core, the other busy, load ~4; best
and median of five ``python -c "import ..."`` in a fresh process), the config modules import in 0.14 s / 0.18 s and
``torchrl_bail.algorithms.iql`` in 6.0 s / 6.7 s (torch alone 2.8 s / 3.3 s, torchrl 5.1 s / 6.8 s). So on import
this module parses each module of the package (:mod:`ast`) and runs only its schema classes and the torch-free
imports they need (:func:`_read_package_schemas`); importing the module later gives back the same classes.
"""

from __future__ import annotations

import ast
import dataclasses
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, List, Optional  # noqa: UP035 -- OmegaConf reads these annotations at runtime

from torchrl_bail.config import (
    Checked,
    at_least,
    fraction,
    layers,
    learning_rate,
    non_negative,
    positive,
    registry_name,
    rule,
)

__all__ = ["ALGO_SCHEMAS", "AlgoConfig", "CriticConfig", "EnvelopeConfig", "NetConfig", "SchemaReadError",
           "SelectionConfig", "algo_schema", "blocks_with", "entry_gaps", "envelope_algorithm", "schema_block",
           "study_algorithms"]


# ---------------------------------------------------------------------------------------------------------------
# algorithms (conf/algo)
# ---------------------------------------------------------------------------------------------------------------


@dataclass
class NetConfig(Checked):
    hidden: List[int] = layers()
    lr: float = learning_rate()


@dataclass
class AlgoConfig(Checked):
    """The keys every algorithm has, and its registry entry: class variables (not config keys, torch-free) that the
    study (``results/run_study.py``), the drills (``benchmarks/kill_drill.py``), the contract suite
    (``tests/_contract.py``) and the docs (``docs/gen_algorithm_table.py``) read, so that no list of algorithm names
    is kept anywhere else. A schema sets the ones that differ from these defaults; ``tiny``, ``description`` and
    ``losses`` have none, every schema states them (:func:`entry_gaps`; ``tests/test_contract.py`` fails without)."""

    #: its place among the report's columns and everywhere the algorithms are listed (:data:`ALGO_SCHEMAS`' order):
    #: the paper's imitation methods, its actor-critics, then the later baselines; ties and unset (a module outside
    #: the package) by name, after the package's
    column: ClassVar[float] = float("inf")
    #: which paper-scale schedule it takes (``results/run_study.PAPER_SCHEDULE``): ``"imitation"`` (the paper's own
    #: epochs) or ``"offline_rl"`` (an actor-critic at 10 % of its paper's 10^6 updates: ~10x an imitation run)
    cost: ClassVar[str] = "imitation"
    #: the batch kinds the study runs it on: ``"all"``, ``"ddpg"`` (the two DDPG batches of each env only, for
    #: cost) or ``"none"`` (not in the study); whether an algorithm joins the study is this one line
    study: ClassVar[str] = "none"
    #: whether the paper-scale Hopper study (``--study paper_hopper``) runs it: the paper's six algorithms
    paper_study: ClassVar[bool] = False
    #: what a run of a few updates needs besides small networks and its length (both set by
    #: :func:`tiny_run_overrides`): overrides of ``algo`` keys (``"warm_start_updates=2"``) that make a handful of
    #: updates cross each switch of the update (BEAR's warm start, Progressive BAIL's validations) and keep
    #: ``prepare`` as short (BAIL's envelope fit); ``()`` when nothing else is needed. The contract suite's tiny
    #: runs and the kill drill read it
    tiny: ClassVar[Optional[tuple[str, ...]]] = None
    #: one line for the docs' table (``docs/guides/algorithms.md``): what the algorithm does, its paper by arXiv id
    #: or section; ``{key}`` fields are filled with the paper preset's values (``{selection.percentile:.0%}``)
    description: ClassVar[Optional[str]] = None
    #: the loss modules (and selection transforms) it trains with, by import path (``torchrl.objectives.BCLoss``);
    #: the docs' table lists them, ``tests/test_contract.py`` checks that each imports and that the built algorithm
    #: holds no loss module missing here
    losses: ClassVar[tuple[str, ...]] = ()

    name: str = registry_name("ALGO_SCHEMAS")
    batch_size: int = at_least(1, "a positive mini-batch size")
    epochs: float = positive("a positive number of epochs (10^6 samples each)")

    def check(self) -> None:
        self._registered_as("name", ALGO_SCHEMAS, "choose the algorithm with algo=<name>")


@dataclass
class EnvelopeConfig(Checked):
    hidden: List[int] = layers()
    head_scale: float = positive()
    penalty: float = rule(lambda v: v >= 1, "a penalty K >= 1 (1: ordinary regression)")
    lr: float = learning_rate()
    weight_decay: float = non_negative("a non-negative L2 coefficient")
    val_fraction: float = rule(lambda v: 0 <= v < 1, "a fraction in [0, 1) (0: no validation, no early stopping)")
    patience: int = at_least(1)


@dataclass
class SelectionConfig(Checked):
    percentile: float = fraction()


@dataclass
class CriticConfig(NetConfig):
    vmap: Any = rule(lambda v: v in ("auto", True, False), "auto | true | false")


#: algorithm name -> its schema, in the report's column order (:attr:`AlgoConfig.column`); filled by
#: :func:`algo_schema` as each ``algorithms/<name>.py`` is read (:func:`_read_package_schemas`) and kept equal to the
#: algorithm classes' registry, :data:`torchrl_bail.algorithms.ALGORITHMS`, by a test; each schema's class variables
#: are its registry entry
ALGO_SCHEMAS: dict[str, type[AlgoConfig]] = {}
#: (module, class name) -> every schema class an algorithm module defines (its entry and its blocks), so that a
#: module's classes are the ones its schemas were read as
_DEFINED: dict[tuple[str, str], type] = {}


def schema_block(cls: type) -> type:
    """Declares a block of an algorithm's schema (a nested node such as ``actor``, or a base schema several
    algorithms share) in the algorithm's module: a dataclass that the torch-free reader picks up with the entry
    (:func:`algo_schema`). Defined once: importing the module later gives back the class the reader made."""
    key = (cls.__module__, cls.__qualname__)
    if key not in _DEFINED:
        _DEFINED[key] = dataclass(cls)
    return _DEFINED[key]


def algo_schema(name: str):
    """Registers the decorated class as algorithm ``name``'s schema and registry entry (``algo=<name>``,
    ``conf/algo/<name>.yaml``) in :data:`ALGO_SCHEMAS`; the class is made a dataclass (:func:`schema_block`).

    It is written in the algorithm's own module, beside its update step, and read from there without importing the
    module (:func:`_read_package_schemas`), so a bad command line fails before torch loads. A module outside this
    package registers the same way when it is imported.

    Examples:
        >>> from torchrl_bail.algorithms import bcq
        >>> ALGO_SCHEMAS["bcq"].__module__, ALGO_SCHEMAS["bcq"] is bcq.BCQConfig
        ('torchrl_bail.algorithms.bcq', True)
    """

    def register(cls: type) -> type:
        schema = schema_block(cls)
        known = ALGO_SCHEMAS.setdefault(name, schema)
        if known is not schema:
            raise ValueError(f"two schemas named {name!r}: {known.__module__}.{known.__qualname__} and "
                             f"{schema.__module__}.{schema.__qualname__}")
        return schema

    return register


class SchemaReadError(ImportError):
    """An algorithm module's schema uses something the torch-free reader cannot give it."""


_DECORATORS = {"algo_schema", "schema_block"}


def _is_schema(node: ast.stmt) -> bool:
    """A top-level class decorated with :func:`algo_schema` or :func:`schema_block`."""
    def decorator_name(d: ast.expr) -> str | None:
        target = d.func if isinstance(d, ast.Call) else d
        return target.id if isinstance(target, ast.Name) else None

    return isinstance(node, ast.ClassDef) and any(decorator_name(d) in _DECORATORS for d in node.decorator_list)


#: the modules whose imports the reader runs: what a schema may use besides its siblings' schema classes
TORCH_FREE_MODULES = frozenset({"typing", "dataclasses", "omegaconf", f"{__package__}.config", __name__})


def _is_torch_free_import(node: ast.stmt) -> bool:
    if isinstance(node, ast.ImportFrom):
        return node.module in TORCH_FREE_MODULES and not node.level
    return isinstance(node, ast.Import) and all(alias.name in TORCH_FREE_MODULES for alias in node.names)


def _read_module_schemas(stem: str, folder: Path, namespaces: dict[str, dict], reading: tuple[str, ...] = ()) -> dict:
    """Defines the schema classes of ``folder/<stem>.py`` (and first those of the sibling modules it imports from)
    by running only its imports of :data:`TORCH_FREE_MODULES` and its schema class statements, with the sibling
    schema classes it imports; returns that namespace. Nothing else of the module runs: no torch."""
    if stem in namespaces:
        return namespaces[stem]
    module = f"{__package__}.algorithms.{stem}"
    path = folder / f"{stem}.py"
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    namespace = {"__name__": module}
    for node in tree.body:  # the module's own torch-free imports, and the schema classes it imports from siblings
        if _is_torch_free_import(node):
            exec(compile(ast.Module(body=[node], type_ignores=[]), str(path), "exec", dont_inherit=True), namespace)
        elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith(f"{__package__}.algorithms."):
            sibling = node.module.rsplit(".", 1)[-1]
            if sibling in reading:
                raise SchemaReadError(f"{path}: its schemas import from {sibling}.py, which imports from it")
            theirs = _read_module_schemas(sibling, folder, namespaces, (*reading, stem))
            namespace.update({alias.asname or alias.name: theirs[alias.name] for alias in node.names
                              if isinstance(theirs.get(alias.name), type)})
    for node in filter(_is_schema, tree.body):
        code = compile(ast.Module(body=[node], type_ignores=[]), str(path), "exec", dont_inherit=True)
        try:
            exec(code, namespace)  # noqa: S102 -- one class statement of the package's own source
        except NameError as e:
            raise SchemaReadError(
                f"{path}:{node.lineno}: schema {node.name} uses {e.name!r}, which the torch-free reader does not "
                f"define: a schema may use what its module imports from {', '.join(sorted(TORCH_FREE_MODULES))} and "
                f"the schema classes of its own and sibling modules (it is read without importing {module})"
            ) from None
    namespaces[stem] = namespace
    return namespace


def _read_package_schemas() -> None:
    """Fills :data:`ALGO_SCHEMAS` from every module of :mod:`torchrl_bail.algorithms`, torch-free: each module's
    classes decorated with :func:`algo_schema` / :func:`schema_block` are defined from its source (parsed with
    :mod:`ast`, ~10 ms for the package), the rest of the module is not run; then orders the registry by
    :attr:`AlgoConfig.column`. Importing a module afterwards gives back these same classes."""
    folder = Path(__file__).with_name("algorithms")
    namespaces: dict[str, dict] = {}
    for path in sorted(folder.glob("*.py")):
        _read_module_schemas(path.stem, folder, namespaces)
    ordered = sorted(ALGO_SCHEMAS.items(), key=lambda item: (item[1].column, item[0]))
    ALGO_SCHEMAS.clear()
    ALGO_SCHEMAS.update(ordered)


_read_package_schemas()


def study_algorithms(batches: str) -> list[str]:
    """The registered algorithms the study runs on ``batches`` (``"all"`` or ``"ddpg"``: :attr:`AlgoConfig.study`),
    in registry order.

    Examples:
        >>> study_algorithms("ddpg")
        ['bcq', 'bear']
    """
    return [name for name, schema in ALGO_SCHEMAS.items() if schema.study == batches]


def entry_gaps(name: str) -> list[str]:
    """What algorithm ``name``'s registry entry leaves unstated of what has no default, as ``<Schema>.<variable>``:
    :attr:`AlgoConfig.tiny` (``()`` states that nothing is needed), :attr:`AlgoConfig.description` and
    :attr:`AlgoConfig.losses`. The docs build and ``tests/test_contract.py`` fail on any.

    Examples:
        >>> entry_gaps("bear")
        []
    """
    schema = ALGO_SCHEMAS[name]
    gaps = {"tiny": schema.tiny is None, "description": not schema.description, "losses": not schema.losses}
    return [f"{schema.__name__}.{variable}" for variable, missing in gaps.items() if missing]


def blocks_with(name: str, key: str) -> list[str]:
    """The dotted names of the blocks (nested nodes) of algorithm ``name``'s schema that have the field ``key``, in
    schema order: ``blocks_with(name, "hidden")`` are its networks.

    Examples:
        >>> blocks_with("bail", "hidden"), blocks_with("bail", "batch_size"), blocks_with("bcq", "hidden")
        (['envelope', 'policy'], ['envelope'], ['vae', 'critic', 'actor'])
    """
    return _blocks_with(ALGO_SCHEMAS[name], key)


def envelope_algorithm() -> str:
    """The registered algorithm whose upper envelope is fitted before its training, for a number of epochs (BAIL):
    what the benchmarks time as "the envelope fit".

    Examples:
        >>> envelope_algorithm()
        'bail'
    """
    return next(name for name in ALGO_SCHEMAS if "envelope" in blocks_with(name, "epochs"))


def _blocks_with(schema: type, key: str, prefix: str = "") -> list[str]:
    types = typing.get_type_hints(schema)
    found = []
    for f in dataclasses.fields(schema):
        block = types[f.name]
        if dataclasses.is_dataclass(block):
            found += [prefix + f.name] if key in {g.name for g in dataclasses.fields(block)} else []
            found += _blocks_with(block, key, f"{prefix}{f.name}.")
    return found

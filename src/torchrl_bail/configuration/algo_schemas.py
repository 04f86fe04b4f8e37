"""The algorithms' registry (:data:`ALGO_SCHEMAS`): each algorithm's schema (``conf/algo``), named
``algo/base_<name>_schema`` in Hydra (:func:`torchrl_bail.configuration.hydra_setup.register_schemas`), is its registry
entry
(:class:`AlgoConfig`'s class variables): what the study, the drills, the contract suite and the docs know of an
algorithm besides its keys. The rules come from :mod:`torchrl_bail.configuration.config`; this module holds the keys
every
algorithm has, the blocks several share and the registration (:func:`algo_schema`, :func:`schema_block`).

A schema is written in its algorithm's module (``algorithms/<name>.py``), beside the update step, and read from
there without importing it when this module is imported (:mod:`torchrl_bail.configuration.schema_reader`: why, and what
a schema
may use); importing the module later gives back the same classes.
"""

from __future__ import annotations

import dataclasses
import typing
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, List, Optional  # noqa: UP035 -- OmegaConf reads these annotations at runtime

from torchrl_bail.configuration.config import (
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
from torchrl_bail.configuration.schema_reader import read_schemas, register_as, schema_block

__all__ = ["ALGO_SCHEMAS", "AlgoConfig", "CriticConfig", "EnvelopeConfig", "NetConfig", "SelectionConfig",
           "algo_schema", "blocks_with", "entry_gaps", "envelope_algorithm", "schema_block", "study_algorithms"]


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
    #: the paper's imitation methods, its actor-critics, then the later baselines; ties, and an entry that states
    #: none, by name after the others
    column: ClassVar[float] = float("inf")
    #: which paper-scale schedule it takes (``results/run_study.paper_schedule``): ``"imitation"`` (the paper's own
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
#: :func:`algo_schema` as each ``algorithms/<name>.py`` is read (:func:`_read_algorithm_schemas`) and kept equal to the
#: algorithm classes' registry, :data:`torchrl_bail.algorithms.ALGORITHMS`, by a test; each schema's class variables
#: are its registry entry
ALGO_SCHEMAS: dict[str, type[AlgoConfig]] = {}


def algo_schema(name: str) -> Callable[[type], type]:
    """Registers the decorated class as algorithm ``name``'s schema and registry entry (``algo=<name>``,
    ``conf/algo/<name>.yaml``) in :data:`ALGO_SCHEMAS`, made a dataclass. It is written in the algorithm's own
    module, beside its update step, and read from there without importing the module
    (:mod:`torchrl_bail.configuration.schema_reader`), so a bad command line fails before torch loads.

    Examples:
        >>> from torchrl_bail.algorithms import iql
        >>> iql.IQLConfig is ALGO_SCHEMAS["iql"], iql.IQLActorConfig is iql.IQLConfig.__annotations__["actor"]
        (True, True)
    """
    return register_as(ALGO_SCHEMAS, name)


def _read_algorithm_schemas() -> None:
    """Fills :data:`ALGO_SCHEMAS` from the modules of :mod:`torchrl_bail.algorithms` without importing them, in
    :attr:`AlgoConfig.column` order."""
    read_schemas(Path(__file__).parents[1] / "algorithms", "torchrl_bail.algorithms", {"algo_schema"},
                 ALGO_SCHEMAS, key=lambda name, schema: (schema.column, name))


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


_read_algorithm_schemas()  # last: the modules read may import any name above

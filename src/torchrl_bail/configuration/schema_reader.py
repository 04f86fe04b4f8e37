"""Schemas written beside their code, read from it without importing it.

An algorithm's schema sits in ``algorithms/<name>.py`` beside its update step, a behaviour recipe's in its
``behaviour/`` module beside the collection; both modules import torch, tensordict and torchrl. A command line is
checked against its schema before any of them loads, so that a bad one fails in a fraction of the time an
algorithm's module takes to import (:func:`torchrl_bail.cli.run_cli`; ``benchmarks/bench_fail_fast.py`` measures
both, in fresh processes).

So each registry (:mod:`torchrl_bail.configuration.algo_schemas`, :mod:`torchrl_bail.configuration.batch_schemas`) reads
its package when it is
imported (:func:`read_schemas`): every module is parsed (:mod:`ast`) and only its schema classes run -- the classes
decorated with the registry's decorator or :func:`schema_block` -- with the module's imports from
:data:`TORCH_FREE_MODULES` and the schema classes it imports from its sibling modules. Nothing else of a module
runs. A class is defined once, so importing the module later gives back the very classes read. A schema that uses
anything else (a constant of its module, a torch type), in its body, a method or a rule's lambda, is refused with
its file, line and name.

Reading both registries' schemas this way takes 0.045-0.055 s after ``torchrl_bail.configuration.config`` (5 fresh
processes, one
core, the other training), and ``python -m torchrl_bail.train +exp=hopper_ddpg05 algo=iql algo.batch_size=0``
exits 2 with its one line in 0.46-0.55 s, torch never imported.

Examples:
    >>> from torchrl_bail.configuration.algo_schemas import ALGO_SCHEMAS
    >>> from torchrl_bail.algorithms import bcq
    >>> ALGO_SCHEMAS["bcq"].__module__, ALGO_SCHEMAS["bcq"] is bcq.BCQConfig
    ('torchrl_bail.algorithms.bcq', True)
"""

from __future__ import annotations

import ast
import builtins
import dis
import types
from collections.abc import Callable, Collection
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["TORCH_FREE_MODULES", "SchemaReadError", "read_schemas", "register_as", "schema_block"]

#: the modules whose imports the reader runs: what a schema may use besides the schema classes of its siblings
TORCH_FREE_MODULES = frozenset({"typing", "dataclasses", "omegaconf", "torchrl_bail.configuration.config",
                                "torchrl_bail.core.errors", "torchrl_bail.configuration.schema_reader",
                                "torchrl_bail.configuration.algo_schemas", "torchrl_bail.configuration.batch_schemas"})
#: the same modules under their names before the layer folders (``torchrl_bail.MOVED``): a schema written against
#: ``from torchrl_bail.algo_schemas import ...`` still reads
_OLD_NAMES = frozenset({"torchrl_bail.config", "torchrl_bail.errors", "torchrl_bail.schema_reader",
                        "torchrl_bail.algo_schemas", "torchrl_bail.batch_schemas"})

#: (module, class name) -> every schema class defined, read or imported, so that each is defined once
_DEFINED: dict[tuple[str, str], type] = {}


class SchemaReadError(ImportError):
    """A module's schema uses something the torch-free reader does not give it, or two modules' schemas import
    from each other."""


def schema_block(cls: type) -> type:
    """Declares a schema class that is no registry entry itself (a nested block such as ``actor``, or a base that
    several entries share) in the module of the code it configures; makes it a dataclass. Defined once: importing
    the module after :func:`read_schemas` read it gives back the class read."""
    key = (cls.__module__, cls.__qualname__)
    if key not in _DEFINED:
        _DEFINED[key] = dataclass(cls)
    return _DEFINED[key]


def register_as(registry: dict[str, type], name: str) -> Callable[[type], type]:
    """The decorator that enters its class in ``registry`` under ``name`` (a :func:`schema_block` otherwise); a
    second class under a taken name is refused."""

    def register(cls: type) -> type:
        schema = schema_block(cls)
        known = registry.setdefault(name, schema)
        if known is not schema:
            raise ValueError(f"two schemas named {name!r}: {known.__module__}.{known.__qualname__} and "
                             f"{schema.__module__}.{schema.__qualname__}")
        return schema

    return register


def read_schemas(folder: Path, package: str, decorators: Collection[str], registry: dict[str, type] | None = None,
                 key: Callable[[str, type], Any] | None = None) -> None:
    """Defines the schema classes of every module ``folder/*.py`` of ``package`` (``__init__.py`` aside) without
    importing the modules: the top-level classes decorated with one of ``decorators`` (the registry's, which
    registers them as they are defined; ``@name``, ``@name(...)`` or ``@module.name(...)``) or :func:`schema_block`.
    A module's schemas are read after those of the sibling modules it imports from (absolute or ``from .sibling``
    imports); a cycle of such imports is a :class:`SchemaReadError`. The classes run in source order: a block is
    written before the schema that uses it. Then ``registry`` (the one the decorators fill), given, is put in
    ``key(name, schema)`` order, by name without ``key``."""
    namespaces: dict[str, dict] = {}
    for path in sorted(folder.glob("*.py")):
        if path.stem != "__init__":
            _read_module(path.stem, folder, package, {*decorators, "schema_block"}, namespaces, ())
    if registry is not None:
        ordered = sorted(registry.items(), key=lambda item: key(*item) if key else item[0])
        registry.clear()
        registry.update(ordered)


def _read_module(stem: str, folder: Path, package: str, decorators: set[str], namespaces: dict[str, dict],
                 reading: tuple[str, ...]) -> dict:
    """Runs the torch-free imports and the schema classes of ``folder/<stem>.py`` in a namespace of their own (the
    sibling schema classes it imports added); returns that namespace."""
    if stem in namespaces:
        return namespaces[stem]
    module, path = f"{package}.{stem}", folder / f"{stem}.py"
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    namespace: dict = {"__name__": module}
    for node in tree.body:
        sibling = _sibling(node, package)
        if _is_torch_free_import(node):
            _run(node, path, namespace)
        elif sibling is not None:
            if sibling in reading:
                raise SchemaReadError(f"{path}: imports from {sibling}.py, which imports from it; the reader follows "
                                      "the imports between a package's modules to find the schema classes they share")
            theirs = _read_module(sibling, folder, package, decorators, namespaces, (*reading, stem))
            namespace.update({alias.asname or alias.name: theirs[alias.name] for alias in node.names
                              if isinstance(theirs.get(alias.name), type)})
    for node in tree.body:
        if isinstance(node, ast.ClassDef) and any(_name(d) in decorators for d in node.decorator_list):
            try:
                _run(node, path, namespace)
            except NameError as e:
                raise _unread(path, node.lineno, f"schema {node.name}", e.name, module) from None
            _check_globals(namespace[node.name], namespace, path, module)
    namespaces[stem] = namespace
    return namespace


def _check_globals(cls: type, namespace: dict, path: Path, module: str) -> None:
    """Every global name that a function of the schema class ``cls`` reads (its methods, and the rules' lambdas of
    its fields) must be defined for it by the reader: those functions keep the reader's namespace as their
    globals for good, so a missing name would fail only when the config is checked."""
    functions = [f for v in vars(cls).values() for f in _functions(v)]
    functions += [f for field in getattr(cls, "__dataclass_fields__", {}).values()
                  for f in _functions(field.metadata.get("check"))]
    for function in functions:
        if function.__globals__ is not namespace:  # defined elsewhere (a rule of torchrl_bail.configuration.config)
            continue
        for code in _code_objects(function.__code__):
            for instruction in dis.get_instructions(code):
                name = instruction.argval
                if instruction.opname == "LOAD_GLOBAL" and name not in namespace and not hasattr(builtins, name):
                    where = instruction.positions.lineno if instruction.positions else code.co_firstlineno
                    raise _unread(path, where, f"{cls.__name__}.{function.__name__}", name, module)


def _functions(value: object) -> list:
    """The plain functions behind a class attribute or a rule: a method, a static or class method, a property's
    accessors, a lambda."""
    if isinstance(value, (staticmethod, classmethod)):
        value = value.__func__
    if isinstance(value, property):
        return [f for f in (value.fget, value.fset, value.fdel) if f is not None]
    return [value] if isinstance(value, types.FunctionType) else []


def _code_objects(code: types.CodeType) -> list[types.CodeType]:
    """``code`` and the code of every function and comprehension nested in it."""
    nested = [c for c in code.co_consts if isinstance(c, types.CodeType)]
    return [code, *(inner for c in nested for inner in _code_objects(c))]


def _unread(path: Path, line: int, what: str, name: str, module: str) -> SchemaReadError:
    return SchemaReadError(
        f"{path}:{line}: {what} uses {name!r}, which the torch-free reader does not define: a schema may use what its "
        f"module imports from {', '.join(sorted(TORCH_FREE_MODULES))} and the schema classes of its own module "
        f"(defined above it) and of sibling modules (it is read without importing {module})")


def _run(node: ast.stmt, path: Path, namespace: dict) -> None:
    """One statement of the module, compiled without this file's ``annotations`` future: a schema's annotations
    are types, as OmegaConf reads them, not strings to resolve in a module that is not imported."""
    exec(compile(ast.Module(body=[node], type_ignores=[]), str(path), "exec", dont_inherit=True), namespace)


def _is_torch_free_import(node: ast.stmt) -> bool:
    if isinstance(node, ast.ImportFrom):
        return node.module in TORCH_FREE_MODULES | _OLD_NAMES and not node.level
    return isinstance(node, ast.Import) and all(alias.name in TORCH_FREE_MODULES | _OLD_NAMES for alias in node.names)


def _sibling(node: ast.stmt, package: str) -> str | None:
    """The sibling module a ``from ... import`` statement imports from (``from package.x import`` or
    ``from .x import``), else ``None``."""
    if not isinstance(node, ast.ImportFrom) or node.module is None:
        return None
    if node.level == 1:
        return node.module
    if node.level == 0 and node.module.startswith(f"{package}."):
        return node.module.removeprefix(f"{package}.")
    return None


def _name(decorator: ast.expr) -> str | None:
    """A decorator's name: ``name`` of ``@name``, ``@name(...)``, ``@module.name(...)``."""
    target = decorator.func if isinstance(decorator, ast.Call) else decorator
    if isinstance(target, ast.Attribute):
        return target.attr
    return target.id if isinstance(target, ast.Name) else None

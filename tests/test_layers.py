"""The package's layering, read from its source with ``ast`` (no import is executed).

The layers are folders (docs/guides/layout.md draws them): the top level holds only the entry points and a few
modules that every layer shares (:data:`TOP_LEVEL`); ``core`` is the bottom and imports nothing of the package;
``configuration`` (torch-free) imports only ``core``; ``data`` only ``core``. Data flows one way: entry points
(``train``, ``collect``, ``report``, ``evaluate``, ``ope``) -> ``training.trainer`` -> ``algorithms`` ->
``training.envelope`` / ``objectives`` / ``transforms`` / ``modules`` -> ``data`` (+ ``core``); the online side
``behaviour`` -> ``data``, ``modules``, ``evaluation``; only the entry points reach ``behaviour``. ``study`` (the
paper's studies: their declarations, runner and reports) sits on top: every module of it is an entry point, and no
other module of the package imports it.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import torchrl_bail

PACKAGE = Path(torchrl_bail.__file__).resolve().parent
ENTRY_POINTS = {"torchrl_bail.train", "torchrl_bail.collect", "torchrl_bail.report", "torchrl_bail.evaluate",
                "torchrl_bail.ope"}
#: the package on top of the entry points: each of its modules counts as one (it runs them, follows them and reports)
STUDY = "torchrl_bail.study"
# the bottom layer (atomic writes, the one-line error classes, the interrupt requests, progress bars, seed stacks):
# it imports nothing from the package
BOTTOM = "torchrl_bail.core"
#: the only modules directly in src/torchrl_bail/: the package face, the entry points and the modules every layer
#: shares (the network builders, the command-line front, the "bail:" dataset source)
TOP_LEVEL = {"torchrl_bail", *ENTRY_POINTS, "torchrl_bail.cli", "torchrl_bail.modules", "torchrl_bail.datasets"}
#: the layer packages
LAYERS = {"core", "configuration", "data", "objectives", "transforms", "algorithms", "training",
          "behaviour", "evaluation", "reports", "study"}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _resolve(module: str, node: ast.ImportFrom, is_package: bool) -> str:
    if not node.level:
        return node.module or ""
    base = module.split(".") if is_package else module.split(".")[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


class Import:
    def __init__(self, source: str, target: str, names: list[str], line: int, in_function: bool):
        self.source, self.target, self.names, self.line, self.in_function = source, target, names, line, in_function

    def __repr__(self) -> str:
        where = "inside a function" if self.in_function else "at module level"
        return f"{self.source}:{self.line} imports {self.target} {self.names or ''} {where}"


def _imports() -> tuple[set[str], list[Import]]:
    modules, found = set(), []
    for path in sorted(PACKAGE.rglob("*.py")):
        module = _module_name(path)
        modules.add(module)
        tree = ast.parse(path.read_text(), filename=str(path))
        functions = {id(n) for f in ast.walk(tree) if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))
                     for n in ast.walk(f)}
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name.startswith("torchrl_bail"):
                        found.append(Import(module, alias.name, [], node.lineno, id(node) in functions))
            elif isinstance(node, ast.ImportFrom):
                target = _resolve(module, node, path.name == "__init__.py")
                if target.startswith("torchrl_bail"):
                    found.append(Import(module, target, [a.name for a in node.names], node.lineno,
                                        id(node) in functions))
    return modules, found


MODULES, IMPORTS = _imports()


def _target_module(imp: Import, name: str) -> str:
    """``from pkg import sub`` imports the module ``pkg.sub``; anything else imports from ``imp.target``."""
    candidate = f"{imp.target}.{name}"
    return candidate if candidate in MODULES else imp.target


def _edges() -> dict[str, set[str]]:
    graph: dict[str, set[str]] = {m: set() for m in MODULES}
    for imp in IMPORTS:
        targets = {_target_module(imp, n) for n in imp.names} if imp.names else {imp.target}
        graph[imp.source] |= {t for t in targets if t in MODULES and t != imp.source}
    return graph


def _in(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


def _entry_point(module: str) -> bool:
    return module in ENTRY_POINTS or _in(module, STUDY)


def test_the_scan_sees_the_package():
    assert {"torchrl_bail.data.batch", "torchrl_bail.behaviour.catalogue", "torchrl_bail.training.envelope"} <= MODULES
    assert any(i.source == "torchrl_bail.algorithms.bail" and i.target == "torchrl_bail.training.envelope"
               for i in IMPORTS)


def test_no_import_cycle():
    """Every import edge counts, a module's import of its own package face included: a package face that defines
    something a lower module imports closes a cycle through the face's own imports."""
    graph = _edges()
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                cycle = stack[stack.index(nxt):] + [nxt]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if nxt not in state:
                visit(nxt)
        stack.pop()
        state[node] = 2

    for module in sorted(graph):
        if module not in state:
            visit(module)


def test_the_top_level_shows_the_layers():
    """At most ten modules directly in src/torchrl_bail/ (the face, the entry points, the shared ones); every other
    module sits in the package of its layer."""
    top = {m for m in MODULES if m.count(".") <= 1 and not (PACKAGE / m.rsplit(".", 1)[-1]).is_dir()}
    assert top == TOP_LEVEL and len(top) <= 10, sorted(top ^ TOP_LEVEL)
    packages = {p.name for p in PACKAGE.iterdir() if (p / "__init__.py").is_file()}
    assert packages <= LAYERS, sorted(packages - LAYERS)


def test_the_layout_page_draws_the_folders():
    """docs/guides/layout.md names every layer folder, every top-level module, and every module of the folders the
    move made (core, configuration, training, evaluation, reports)."""
    page = (PACKAGE.parents[1] / "docs" / "guides" / "layout.md").read_text()
    tree = page[page.index("src/torchrl_bail/"):page.index("docs/ ")]
    missing = [f"{p}/" for p in LAYERS if f"  {p}/ " not in tree]
    files = {f"{m.rsplit('.', 1)[1]}.py" for m in TOP_LEVEL - {"torchrl_bail"}}
    missing += [f for f in sorted(files) if f not in tree]
    for layer in ("core", "configuration", "training", "evaluation", "reports"):
        missing += [f"{layer}/{p.name}" for p in (PACKAGE / layer).glob("*.py")
                    if p.name != "__init__.py" and p.name not in tree]
    assert not missing, f"docs/guides/layout.md does not draw {missing}"


def test_core_and_data_are_the_bottom_layer():
    bad = [i for i in IMPORTS if _in(i.source, "torchrl_bail.data")
           and not (_in(i.target, "torchrl_bail.data") or _in(i.target, BOTTOM))]
    assert not bad, f"torchrl_bail.data may import only itself and {BOTTOM}: {bad}"
    bad = [i for i in IMPORTS if _in(i.source, BOTTOM) and not _in(i.target, BOTTOM)]
    assert not bad, f"{BOTTOM} must import nothing else from the package: {bad}"


def test_configuration_imports_only_core():
    """The configuration layer stays torch-free: it imports itself and the bottom layer, no layer of tensors."""
    bad = [i for i in IMPORTS if _in(i.source, "torchrl_bail.configuration")
           and not (_in(i.target, "torchrl_bail.configuration") or _in(i.target, BOTTOM))]
    assert not bad, f"torchrl_bail.configuration may import only itself and {BOTTOM}: {bad}"


def test_only_entry_points_reach_the_behaviour_package():
    bad = [i for i in IMPORTS if _in(i.target, "torchrl_bail.behaviour")
           and not _in(i.source, "torchrl_bail.behaviour") and not _entry_point(i.source)]
    assert not bad, f"only {sorted(ENTRY_POINTS)} and {STUDY} may import torchrl_bail.behaviour: {bad}"


def test_the_study_package_is_the_top():
    bad = [i for i in IMPORTS if _in(i.target, STUDY) and not _in(i.source, STUDY)]
    assert not bad, f"{STUDY} sits on top of the package: nothing else may import it: {bad}"


@pytest.mark.parametrize("lower, upper", [
    ("torchrl_bail.data", "torchrl_bail.algorithms"),
    ("torchrl_bail.modules", "torchrl_bail.algorithms"),
    ("torchrl_bail.objectives", "torchrl_bail.algorithms"),
    ("torchrl_bail.transforms", "torchrl_bail.algorithms"),
    ("torchrl_bail.training.envelope", "torchrl_bail.algorithms"),
    ("torchrl_bail.algorithms", "torchrl_bail.training.trainer"),
    ("torchrl_bail.behaviour", "torchrl_bail.algorithms"),
    ("torchrl_bail.behaviour", "torchrl_bail.objectives"),
    ("torchrl_bail.behaviour", "torchrl_bail.training.trainer"),
    ("torchrl_bail.evaluation", "torchrl_bail.training.trainer"),
    ("torchrl_bail.reports", "torchrl_bail.training"),
    ("torchrl_bail.reports", "torchrl_bail.algorithms"),
    ("torchrl_bail.reports", "torchrl_bail.evaluation"),
    ("torchrl_bail.training.resume", "torchrl_bail.algorithms"),
])
def test_no_upward_import(lower, upper):
    bad = [i for i in IMPORTS if _in(i.source, lower) and _in(i.target, upper)]
    assert not bad, f"{lower} sits below {upper} and must not import it: {bad}"


def test_no_function_level_package_imports_outside_entry_points():
    # the package root may re-export lazily (module ``__getattr__``) so that ``import torchrl_bail`` stays light
    bad = [i for i in IMPORTS if i.in_function and not (_entry_point(i.source) or i.source == "torchrl_bail")]
    assert not bad, f"package imports hidden inside functions (move them to the top of the module): {bad}"


def test_no_private_name_crosses_a_module():
    bad = []
    for imp in IMPORTS:
        for name in imp.names:
            target = _target_module(imp, name)
            if target == imp.source:
                continue
            if name.startswith("_"):
                bad.append(f"{imp} (private name {name})")
            private_module = next((p for p in target.split(".") if p.startswith("_") and p != "__init__"), None)
            owner = target.rsplit(".", 1)[0]
            if private_module and not _in(imp.source, owner):
                bad.append(f"{imp} (private module {target} outside {owner})")
    assert not bad, "\n".join(bad)


def test_the_loss_layer_loads_no_config_no_resume_and_no_behaviour():
    """``import torchrl_bail.objectives`` (what a user of the losses alone imports) loads neither Hydra, OmegaConf,
    the schemas, :mod:`torchrl_bail.training.resume` nor the behaviour agents."""
    import subprocess
    import sys

    code = ("import sys, torchrl_bail.objectives; print(sorted(m for m in sys.modules if m.split('.')[0] in "
            "('hydra', 'omegaconf') or m in ('torchrl_bail.configuration.config', "
            "'torchrl_bail.configuration.algo_schemas', "
            "'torchrl_bail.configuration.batch_schemas', 'torchrl_bail.training.resume') or "
            "m.startswith('torchrl_bail.behaviour')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={**__import__("os").environ, "PYTHONPATH": str(PACKAGE.parent)})
    assert out.stdout.strip() == "[]", out.stdout

"""The modules that moved into the layer packages (issue 52) keep their old names: every old name in
:data:`torchrl_bail.MOVED` imports, is the very module of its new name, has no file of its own, and the kept policy
files and pickles that name an old module still load."""

from __future__ import annotations

import importlib
import os
import pickle
import subprocess
import sys
from pathlib import Path

import pytest

import torchrl_bail

PACKAGE = Path(torchrl_bail.__file__).resolve().parent
REPO = PACKAGE.parents[1]


def _run(code: str) -> str:
    env = {**os.environ, "PYTHONPATH": str(PACKAGE.parent)}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env).stdout


@pytest.mark.parametrize("old", sorted(torchrl_bail.MOVED))
def test_an_old_name_is_the_new_module(old):
    new = torchrl_bail.MOVED[old]
    assert importlib.import_module(old) is importlib.import_module(new)
    assert sys.modules[old] is sys.modules[new]
    assert not (PACKAGE / f"{old.rsplit('.', 1)[1]}.py").exists(), f"{old} still has a file of its own"
    assert (PACKAGE / (new.split(".", 1)[1].replace(".", "/") + ".py")).is_file()


def test_old_import_forms_work():
    from torchrl_bail.policy import load_policy as old_load_policy

    from torchrl_bail.configuration.config import validate_config
    from torchrl_bail.core import interrupts as new_interrupts
    from torchrl_bail.evaluation.policy import load_policy

    assert old_load_policy is load_policy is torchrl_bail.load_policy
    from torchrl_bail import interrupts  # an attribute the face lacks: imported through the old module name
    assert interrupts is new_interrupts
    old_config = importlib.import_module("torchrl_bail.config")
    assert old_config.validate_config is validate_config


def test_an_old_name_imports_lazily_and_stays_torch_free():
    """``import torchrl_bail`` imports none of the moved modules, and the old name of a configuration module imports
    no torch (the config path stays torch-free)."""
    out = _run("import sys, torchrl_bail; print(sorted(m for m in sys.modules if m.startswith('torchrl_bail.')))")
    assert out.strip() == "[]", out
    out = _run("import sys, torchrl_bail.config, torchrl_bail.algo_schemas, torchrl_bail.hydra_setup; "
               "print('torch' in sys.modules, sys.modules['torchrl_bail.config'] is "
               "sys.modules['torchrl_bail.configuration.config'])")
    assert out.split() == ["False", "True"], out


def test_a_pickle_naming_an_old_module_loads():
    """A pickle written before the move names a class by its old module (``torchrl_bail.errors.ConfigError``)."""
    from torchrl_bail.core.errors import ResumeError

    blob = pickle.dumps(ResumeError("x"), protocol=2)  # GLOBAL: the module name as text
    blob = blob.replace(b"torchrl_bail.core.errors", b"torchrl_bail.errors")
    assert b"torchrl_bail.errors" in blob
    out = _run(f"import pickle; e = pickle.loads({blob!r}); print(type(e).__module__, type(e).__name__)")
    assert out.split() == ["torchrl_bail.core.errors", "ResumeError"]


def test_a_schema_written_against_the_old_names_reads(tmp_path, monkeypatch):
    """An algorithm module of a user's, ``from torchrl_bail.algo_schemas import ...``, reads as before the move."""
    from torchrl_bail.configuration import algo_schemas, schema_reader

    monkeypatch.setattr(algo_schemas, "ALGO_SCHEMAS", {})
    monkeypatch.setattr(schema_reader, "_DEFINED", {})
    folder = tmp_path / "algorithms"
    folder.mkdir()
    (folder / "mine.py").write_text(
        "from __future__ import annotations\n\nimport torch\n\n"
        "from torchrl_bail.algo_schemas import AlgoConfig, algo_schema\n"
        "from torchrl_bail.config import discount\n\n\n"
        "@algo_schema('mine')\nclass MineConfig(AlgoConfig):\n    column = 0.5\n    gamma: float = discount()\n")
    schema_reader.read_schemas(folder, "torchrl_bail.algorithms", {"algo_schema"})
    assert algo_schemas.ALGO_SCHEMAS["mine"].__mro__[1] is algo_schemas.AlgoConfig


KEPT_POLICIES = sorted((REPO / "results" / "ope_headline" / "runs").glob("**/policy.pt"))


@pytest.mark.skipif(not KEPT_POLICIES, reason="no kept policy files in this checkout")
def test_the_kept_policies_load_after_the_move():
    from torchrl_bail.policy import load_policy, read_policy_file

    for path in KEPT_POLICIES[:3]:
        assert read_policy_file(path)
        assert load_policy(path) is not None

"""The GPU session's two scripts, read as text (neither can run without a GPU or PyPI): ``benchmarks/gpu_check.sh``
fits in the 8 minutes a GPU session gives it, and ``benchmarks/gpu_wheels.sh`` fetches the versions this package
pins, once each."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

from packaging.requirements import Requirement

ROOT = Path(__file__).resolve().parents[1]
CHECK = (ROOT / "benchmarks" / "gpu_check.sh").read_text()
WHEELS = (ROOT / "benchmarks" / "gpu_wheels.sh").read_text()


def _wheel_pins() -> dict[str, str]:
    lists = re.findall(r"^(?:binary|source_only)=\((.*?)\)", WHEELS, flags=re.M | re.S)
    pins = [pin for block in lists for pin in block.split()]
    names = [pin.split("==")[0].lower().replace("_", "-") for pin in pins]
    assert all("==" in pin for pin in pins) and len(names) == len(set(names)), pins
    return dict(zip(names, (pin.split("==")[1] for pin in pins), strict=True))


def test_the_gpu_checks_time_limits_fit_in_eight_minutes():
    limits = [int(s) for s in re.findall(r"^\s*step \w+ (\d+) ", CHECK, flags=re.M)]
    assert len(limits) >= 5 and sum(limits) <= 480, limits


def test_the_gpu_wheels_are_the_versions_this_package_pins():
    pins = _wheel_pins()
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    required = {Requirement(r).name.lower(): Requirement(r) for r in project["dependencies"]}
    for name in ("torchrl", "tensordict", "hydra-core", "gymnasium", "mujoco"):
        assert name in pins, f"gpu_wheels.sh fetches no {name}"
        assert required[name].specifier.contains(pins[name]), (name, pins[name], str(required[name].specifier))
    # Hydra's OmegaConf pins its parser runtime to 4.9.*, which PyPI has only as source: built, not downloaded
    assert pins["antlr4-python3-runtime"].startswith("4.9.")

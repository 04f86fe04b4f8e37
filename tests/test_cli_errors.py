"""Every bad command line ends with ONE line on stderr naming the key (or option) and what was expected, exit code 2,
no traceback, and nothing written: no run directory, no batch collection started.

Each case is a real ``python -m torchrl_bail.train`` (or ``.collect``) subprocess; the config is checked before
torch is imported, so a case costs about a second of CPU (the training cases run a few at a time).
"""

from __future__ import annotations

import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
EXP = "+exp=hopper_ddpg05"

#: (id, overrides, fragments the one stderr line must contain)
CASES = [
    # values out of range
    ("percentile_above_one", [EXP, "algo.selection.percentile=1.5"], ["algo.selection.percentile", "(0, 1]"]),
    ("percentile_zero", [EXP, "algo.selection.percentile=0"], ["algo.selection.percentile", "(0, 1]"]),
    ("negative_penalty", [EXP, "algo.envelope.penalty=-1"], ["algo.envelope.penalty", "K >= 1"]),
    ("zero_batch_steps", [EXP, "batch.steps=0"], ["batch.steps", "positive number of transitions"]),
    ("discount_above_one", [EXP, "returns.gamma=1.5"], ["returns.gamma", "(0, 1]"]),
    ("zero_eval_episodes", [EXP, "eval.episodes=0"], ["eval.episodes", "positive integer"]),
    ("zero_samples_per_epoch", [EXP, "samples_per_epoch=0"], ["samples_per_epoch", "positive integer"]),
    ("zero_time_limit", [EXP, "env.max_episode_steps=0"], ["env.max_episode_steps", "positive integer"]),
    ("empty_layer", [EXP, "algo.policy.hidden=[0,300]"], ["algo.policy.hidden", "positive layer widths"]),
    ("bear_alpha_bounds", [EXP, "algo=bear", "algo.log_alpha_min=20"], ["algo.log_alpha_min", "log_alpha_max"]),
    ("sac_polyak", ["+exp=hopper_sac", "batch.sac.polyak=1"], ["batch.sac.polyak", "[0, 1)"]),
    ("sac_batch_longer_than_run", ["+exp=hopper_sac", "batch.steps=2000", "batch.sac.train_steps=1000"],
     ["batch.steps", "sac.train_steps = 1000"]),
    ("oracle_horizon", [EXP, "batch.oracle.enabled=true", "batch.oracle.horizon=500"],
     ["batch.oracle.horizon", "larger than keep = 1000"]),
    # values outside a set of choices
    ("unknown_augment", [EXP, "returns.augment=magic"], ["returns.augment", "gain | none | oracle"]),
    ("unknown_device", [EXP, "device=tpu"], ["device", "cpu | cuda | cuda:N | auto"]),
    ("unknown_logger", [EXP, "logger.backend=neptune"], ["logger.backend", "csv | tensorboard | wandb | mlflow"]),
    ("unknown_exec_policy", ["+exp=hopper_med_det", "batch.policy=best"], ["batch.policy", "mediocre | optimal"]),
    ("unknown_vmap", [EXP, "algo=bcq", "algo.critic.vmap=maybe"], ["algo.critic.vmap", "auto | true | false"]),
    ("algo_name_instead_of_group", [EXP, "algo.name=dqn"], ["algo.name", "algo=<name>"]),
    # types
    ("seed_not_an_integer", [EXP, "seed=abc"], ["seed", "Integer"]),
    ("lr_not_a_number", [EXP, "algo.envelope.lr=foo"], ["algo.envelope.lr", "Float"]),
    ("progress_not_a_bool", [EXP, "progress=maybe"], ["progress", "valid bool"]),
    ("steps_not_an_integer", [EXP, "batch.steps=1.5"], ["batch.steps", "Integer"]),
    # unknown keys
    ("unknown_key", [EXP, "algo.foo=1"], ["algo.foo", "no such key", "selection"]),
    ("appended_unknown_key", [EXP, "+algo.envelope.pen=3"], ["algo.envelope.pen", "no such key", "penalty"]),
    ("key_of_another_recipe", [EXP, "batch.sac.polyak=0.9"], ["batch.sac", "no such key", "sigma"]),
    # wrong group options
    ("mistyped_exp", ["+exp=hopper_ddpg5"], ["exp=hopper_ddpg5", "hopper_ddpg05", "walker_sac"]),
    ("mistyped_algo", [EXP, "algo=bal"], ["algo=bal", "expected one of bail, bc, bcq, "]),
    ("mistyped_env", [EXP, "env=hoper"], ["env=hoper", "halfcheetah, hopper"]),
    ("mistyped_batch", [EXP, "batch=ddpg5"], ["batch=ddpg5", "ddpg01, ddpg05, med_det"]),
    ("mistyped_preset", [EXP, "preset=fast"], ["preset=fast", "paper, quick"]),
    ("override_syntax", [EXP, "seed=[1"], ["seed=[1", "override syntax"]),
    # env x batch combinations the catalogue does not have, and oracle returns without an oracle batch
    ("ddpg_on_ant", [EXP, "env=ant"], ["batch", "ddpg05", "hopper, walker, halfcheetah"]),
    ("ddpg_on_humanoid", ["+exp=humanoid_sac", "batch=ddpg01"], ["batch", "ddpg01", "hopper, walker, halfcheetah"]),
    ("oracle_returns_without_oracle_batch", [EXP, "returns.augment=oracle"],
     ["returns.augment", "batch.oracle.enabled=true"]),
    # paths
    ("missing_dataset", [EXP, "dataset=/nonexistent/hopper-medium-v2.hdf5"], ["dataset", "existing D4RL"]),
    ("missing_resume_dir", [EXP, "resume=/nonexistent/run"],
     ["resume", "auto | true | false | an existing run directory"]),
    ("data_dir_is_a_file", [EXP, f"data_dir={REPO / 'pyproject.toml'}"], ["data_dir", "a directory"]),
]


def _run(module: str, args: list[str], tmp_path: Path) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}  # the CLI must not need it
    env.update(RL_WARNINGS="0", PYTHONPATH=os.pathsep.join([str(REPO / "src"), env.get("PYTHONPATH", "")]))
    cmd = [sys.executable, "-m", module, *args]
    if not any(a.startswith("data_dir=") for a in args):
        cmd.append(f"data_dir={tmp_path / 'data'}")
    cmd += [f"hydra.run.dir={tmp_path / 'run'}", f"hydra.sweep.dir={tmp_path / 'multirun'}"]
    return subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=120, cwd=tmp_path)


def _assert_one_clear_line(proc: subprocess.CompletedProcess, fragments: list[str]) -> str:
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-2000:])
    assert "Traceback" not in proc.stdout + proc.stderr and "HYDRA_FULL_ERROR" not in proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    line = lines[0]
    assert line.startswith("torchrl_bail: ")
    for fragment in fragments:
        assert fragment in line, (fragment, line)
    return line


@pytest.fixture(scope="module")
def training_runs(tmp_path_factory) -> dict[str, tuple[subprocess.CompletedProcess, Path]]:
    """Every case's subprocess, run a few at a time (each is mostly interpreter start-up and imports)."""
    dirs = {name: tmp_path_factory.mktemp(name) for name, _, _ in CASES}
    with ThreadPoolExecutor(max_workers=max(2, os.cpu_count() or 1)) as pool:
        procs = {name: pool.submit(_run, "torchrl_bail.train", overrides, dirs[name]) for name, overrides, _ in CASES}
        return {name: (proc.result(), dirs[name]) for name, proc in procs.items()}


@pytest.mark.parametrize("name,fragments", [(c[0], c[2]) for c in CASES], ids=[c[0] for c in CASES])
def test_bad_training_command_line_is_one_line_and_writes_nothing(training_runs, name, fragments):
    proc, tmp_path = training_runs[name]
    _assert_one_clear_line(proc, fragments)
    assert not (tmp_path / "run").exists()  # no run directory, no config/summary/checkpoint
    assert not (tmp_path / "data").exists()  # collection never started


@pytest.mark.parametrize("overrides,fragments", [
    ([EXP, "batch.sigma=-1"], ["batch.sigma", "non-negative noise std"]),
    (["+exp=walker_ddpg05", "env=humanoid"], ["batch", "hopper, walker, halfcheetah"]),
    ([EXP, "algo=bal"], ["algo=bal", "bail, bc"]),
    (["--export-minari", "bail/noversion", EXP], ["Minari dataset id 'bail/noversion'", "name-v<version>"]),
    (["--export-minari", "bail/hopper-v0", "-m", EXP], ["--export-minari accepts only", "'-m'"]),
    (["--export-minari", "bail/hopper-v0", EXP, "batch.sigma=-1"], ["batch.sigma", "non-negative noise std"]),
], ids=["negative_sigma", "ddpg_on_humanoid", "mistyped_algo", "export_id_without_version", "export_multirun",
        "export_bad_recipe"])
def test_bad_collection_command_line_is_one_line_and_collects_nothing(tmp_path, overrides, fragments):
    proc = _run("torchrl_bail.collect", overrides, tmp_path)
    _assert_one_clear_line(proc, fragments)
    assert not (tmp_path / "run").exists() and not (tmp_path / "data").exists()


def test_multirun_with_a_bad_value_is_one_line_and_writes_no_summary(tmp_path):
    """Sweeps are composed job by job inside Hydra: the first bad job stops the sweep with the same one line."""
    proc = _run("torchrl_bail.train", ["-m", EXP, "algo.selection.percentile=1.5,0.3"], tmp_path)
    _assert_one_clear_line(proc, ["algo.selection.percentile", "(0, 1]"])
    assert not list(tmp_path.rglob("summary.json")) and not list(tmp_path.rglob("checkpoint.pt"))
    assert not (tmp_path / "data").exists()


def test_unreadable_dataset_is_one_line(tmp_path):
    """A dataset file that exists but is not a dataset is found out by the importer, still before any training."""
    bad = tmp_path / "broken.hdf5"
    bad.write_bytes(b"not an hdf5 file")
    proc = _run("torchrl_bail.train", [EXP, f"dataset={bad}"], tmp_path)
    line = _assert_one_clear_line(proc, [])
    assert "broken.hdf5" in line
    assert not list(tmp_path.rglob("summary.json")) and not list(tmp_path.rglob("checkpoint.pt"))


def test_entry_points_do_not_import_torch_before_the_config_is_checked():
    """What keeps a bad command line at about a second: the entry modules and the schemas load without torch."""
    code = ("import sys, torchrl_bail.train, torchrl_bail.collect, torchrl_bail.cli, "
            "torchrl_bail.configuration.config, "
            "torchrl_bail.configuration.algo_schemas; "
            "print(sorted(m for m in ('torch', 'torchrl', 'tensordict', 'numpy') if m in sys.modules))")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO / "src"), os.environ.get("PYTHONPATH", "")])}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert out.stdout.strip() == "[]"


def test_a_batch_that_does_not_fit_the_env_is_one_config_error():
    """``dataset=`` of another env: one ConfigError naming the env key, both sizes and the remedy (it was a
    TypeError: the error was built from one string)."""
    from types import SimpleNamespace

    from omegaconf import OmegaConf

    from torchrl_bail.cli import describe_error
    from torchrl_bail.configuration.config import ConfigError
    from torchrl_bail.train import training_data

    cfg = OmegaConf.create({"env": {"name": "walker", "id": "Walker2d-v5"}})
    batch = SimpleNamespace(path="/data/hopper_ddpg05_b1", obs_dim=11, act_dim=3)
    evaluator = SimpleNamespace(obs_dim=17, action_spec=SimpleNamespace(shape=(6,)))
    with pytest.raises(ConfigError) as err:
        training_data(cfg, batch, evaluator)
    assert describe_error(err.value) == (
        "config key env = 'walker': expected the env of batch /data/hopper_ddpg05_b1, whose observation/action "
        "sizes are (11, 3) where Walker2d-v5 has (17, 6); pick the matching env= for this dataset")


def test_help_lists_each_groups_real_options(tmp_path):
    """``--help`` names the options of conf/'s groups, not the schemas or included parts Hydra's ConfigStore holds."""
    from torchrl_bail.configuration.algo_schemas import ALGO_SCHEMAS
    from torchrl_bail.configuration.hydra_setup import group_options

    proc = _run("torchrl_bail.train", ["--help"], tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    groups = {line.split(": ")[0]: line.split(": ")[1].split(", ") for line in proc.stdout.splitlines()
              if line.split(": ")[0] in ("algo", "algo_preset", "batch", "env", "exp", "preset")}
    assert groups == group_options()
    assert groups["algo"] == sorted(ALGO_SCHEMAS)
    assert "ddpg05" in groups["batch"] and "base_" not in proc.stdout and "_collection" not in proc.stdout


@pytest.mark.parametrize("command", ["train", "collect"])
def test_help_opens_with_the_commands_a_user_types(tmp_path, command):
    """``--help`` starts with the commands to type (README command 1 for ``train``), what ``+exp=`` and ``preset=``
    choose, then Hydra's help; not Hydra's bare "train is powered by Hydra."; every option its examples name exists."""
    import re

    from torchrl_bail.configuration.hydra_setup import group_options

    proc = _run(f"torchrl_bail.{command}", ["--help"], tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    head, groups_header, _ = proc.stdout.partition("== Configuration groups ==")
    assert groups_header and "powered by Hydra" not in head
    assert head.startswith(f"python -m torchrl_bail.{command}:")
    assert "+exp=<env>_<batch>" in head and "preset=quick|study|paper" in head
    if command == "train":
        readme = (REPO / "README.md").read_text()
        first = re.search(r"python -m torchrl_bail\.train \+exp=\S+ preset=quick seed=1", readme).group(0)
        assert f"  {first}   #" in head  # README command 1, as the first example
    examples = [line.split("#")[0].split()[3:] for line in head.splitlines()
                if line.startswith(f"  python -m torchrl_bail.{command} ")]
    assert len(examples) >= 3
    options = group_options()
    for args in examples:
        for arg in args:
            key, _, value = arg.lstrip("+").partition("=")
            if key in options and "," not in value:
                assert value in options[key], arg

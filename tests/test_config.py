"""Every config composes, the quick preset shortens every algorithm, and bad values are named clearly."""

from __future__ import annotations

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import open_dict

from torchrl_bail import config_dir
from torchrl_bail.configuration.algo_schemas import ALGO_SCHEMAS
from torchrl_bail.configuration.config import ConfigError, validate_config

ALGOS = list(ALGO_SCHEMAS)


def _compose(*overrides: str):
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        return compose("config", overrides=list(overrides))


def test_exp_selects_env_and_batch_with_bail_by_default():
    cfg = _compose("+exp=hopper_ddpg05")
    assert (cfg.env.id, cfg.batch.kind, cfg.batch.sigma, cfg.algo.name) == ("Hopper-v5", "ddpg05", 0.5, "bail")
    assert cfg.batch.steps == 1_000_000 and cfg.algo.epochs == 50 and cfg.algo.selection.percentile == 0.30
    assert cfg.algo.envelope.penalty == 1000.0 and cfg.algo.envelope.early_stopping == "paper"


@pytest.mark.parametrize("algo", ALGOS)
def test_every_algo_composes_and_quick_preset_shortens_it(algo):
    paper = _compose("+exp=hopper_ddpg05", f"algo={algo}")
    quick = _compose("+exp=hopper_ddpg05", f"algo={algo}", "preset=quick")
    assert paper.algo.name == quick.algo.name == algo
    assert quick.algo.epochs < paper.algo.epochs
    assert quick.batch.steps < paper.batch.steps
    validate_config(paper)
    validate_config(quick)


def test_command_line_beats_exp_and_preset():
    cfg = _compose("+exp=hopper_ddpg05", "preset=quick", "batch.index=2", "seed=7", "algo.epochs=3")
    assert (cfg.batch.index, cfg.seed, cfg.algo.epochs) == (2, 7, 3)


@pytest.mark.parametrize(
    "key,value,match",
    [("returns.augment", "magic", "returns.augment"), ("returns.gamma", 1.5, "returns.gamma"),
     ("eval.episodes", 0, "eval.episodes"), ("algo.batch_size", 0, "algo.batch_size"),
     ("device", "tpu", "device"), ("algo.name", "dqn", "algo.name"),
     ("returns.augment", "oracle", "batch.oracle.enabled=true")],
)
def test_bad_values_name_their_key(key, value, match):
    cfg = _compose("+exp=hopper_ddpg05")
    with open_dict(cfg):
        node, leaf = key.rsplit(".", 1) if "." in key else (None, key)
        (cfg if node is None else cfg[node])[leaf] = value
    with pytest.raises(ConfigError, match=match):
        validate_config(cfg)


def test_slurm_launcher_config_composes():
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("config", overrides=["+exp=hopper_ddpg05", "hydra/launcher=slurm"], return_hydra_config=True)
    assert cfg.hydra.launcher._target_.endswith("SlurmLauncher")
    assert cfg.hydra.launcher.timeout_min == 1440


class _StubLogger:
    def __init__(self):
        self.hparams = None

    def log_hparams(self, cfg):
        self.hparams = cfg


@pytest.mark.parametrize("backend", ["csv", "tensorboard", "wandb", "mlflow"])
def test_logger_gets_project_group_name_and_the_resolved_config(monkeypatch, tmp_path, backend):
    import torchrl.record.loggers

    from torchrl_bail.train import make_logger

    calls = []

    def get_logger(logger_type, logger_name, experiment_name, **kwargs):
        calls.append((logger_type, logger_name, experiment_name, kwargs))
        return _StubLogger()

    monkeypatch.setattr(torchrl.record.loggers, "get_logger", get_logger)
    cfg = _compose("+exp=walker_sac", "algo=bcq", "seed=4", f"logger.backend={backend}", "logger.project=mine")
    logger = make_logger(cfg, tmp_path / "seed4_x")
    (logger_type, logger_dir, experiment, kwargs), = calls
    assert (logger_type, logger_dir) == (backend, str(tmp_path / "seed4_x"))
    if backend == "wandb":
        assert experiment == "bcq_seed4_seed4_x"
        assert kwargs == {"wandb_kwargs": {"project": "mine", "group": "walker_sac_b1"}}
    elif backend == "mlflow":
        assert experiment == "mine"
        assert kwargs == {"mlflow_kwargs": {"tags": {"group": "walker_sac_b1", "mlflow.runName": "bcq_seed4_seed4_x"}}}
    else:  # file backends write into <run_dir>/logs
        assert experiment == "logs" and kwargs == {}
    hp = logger.hparams  # every key, resolved and flat, for every backend
    assert hp["algo.name"] == "bcq" and hp["seed"] == 4 and hp["logger.project"] == "mine"
    assert hp["batch.sac.train_steps"] == 1_000_000 and hp["algo.vae.hidden"] == "[750, 750]"
    assert all(isinstance(v, (bool, int, float, str)) for v in hp.values())


def test_logger_name_from_the_config_wins(monkeypatch, tmp_path):
    import torchrl.record.loggers

    from torchrl_bail.train import make_logger

    seen = {}
    monkeypatch.setattr(torchrl.record.loggers, "get_logger",
                        lambda *a, **kw: seen.update(args=a, kwargs=kw) or _StubLogger())
    make_logger(_compose("+exp=hopper_ddpg05", "logger.backend=wandb", "logger.name=ablation-K1",
                         "logger.group=ablations"), tmp_path)
    assert seen["kwargs"]["experiment_name"] == "ablation-K1"
    assert seen["kwargs"]["wandb_kwargs"]["group"] == "ablations"


def test_library_defaults_are_the_yaml_defaults():
    """The library functions BAIL's config drives keep the defaults of ``conf/algo/bail.yaml`` (the one home of
    the paper's constants): a default changed in one place and not the other fails here."""
    import inspect

    from omegaconf import OmegaConf

    from torchrl_bail.configuration.config_builders import algo_config
    from torchrl_bail.modules import make_deterministic_actor, make_value_network
    from torchrl_bail.training.envelope import EarlyStoppingTracker, envelope_split, fit_upper_envelope
    from torchrl_bail.transforms import BestActionFilter

    def defaults(fn) -> dict:
        return {k: p.default for k, p in inspect.signature(fn).parameters.items() if p.default is not p.empty}

    bail = OmegaConf.to_container(algo_config("bail"))
    envelope, selection = bail["envelope"], bail["selection"]
    fit = defaults(fit_upper_envelope)
    for key in ("penalty", "lr", "weight_decay", "batch_size", "epochs", "val_fraction", "patience", "early_stopping"):
        assert fit[key] == envelope[key], key
    assert defaults(EarlyStoppingTracker)["patience"] == envelope["patience"]
    assert defaults(envelope_split)["val_fraction"] == envelope["val_fraction"]
    value = defaults(make_value_network)
    assert (list(value["hidden"]), value["head_scale"]) == (envelope["hidden"], envelope["head_scale"])
    assert list(defaults(make_deterministic_actor)["hidden"]) == bail["policy"]["hidden"]
    selection_filter = defaults(BestActionFilter)
    assert (selection_filter["percentile"], selection_filter["nonpositive_value"]) == (
        selection["percentile"], selection["nonpositive_value"])


def test_one_run_only_mark_feeds_resume_the_report_and_the_run_directory_names():
    """The schema's ``run_only`` marks are the one list: resume compares configs without them, the report never
    separates runs by them, and ``conf/config.yaml``'s ``exclude_keys`` (which run directory names leave out) is
    exactly the keys under them plus those already in the path."""
    from torchrl_bail import report
    from torchrl_bail.configuration.run_dirs import RUN_DIR_KEYS, RUN_ONLY_KEYS, run_dir_excluded_keys
    from torchrl_bail.training import resume

    assert RUN_ONLY_KEYS == ("device", "data_dir", "progress", "resume", "threads", "logger", "checkpoint")
    assert resume.RUN_ONLY_KEYS is RUN_ONLY_KEYS
    assert set(RUN_ONLY_KEYS) <= set(report.NON_SEPARATING_KEYS)
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("config", overrides=["+exp=hopper_ddpg05"], return_hydra_config=True)
    yaml_keys = list(cfg.hydra.job.config.override_dirname.exclude_keys)
    assert sorted(yaml_keys) == sorted(run_dir_excluded_keys()) and len(set(yaml_keys)) == len(yaml_keys)
    assert {"logger.backend", "checkpoint.every_minutes", *RUN_DIR_KEYS} <= set(yaml_keys)

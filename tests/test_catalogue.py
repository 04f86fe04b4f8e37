"""The batch catalogue: all 62 paper batches resolve, SAC / execution / oracle recipes on tiny budgets, one SAC run
shared by several batches, and interrupted collections that never leave anything loadable."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from torchrl_bail import config_dir
from torchrl_bail.behaviour import ensure_batch
from torchrl_bail.configuration.config import ConfigError
from torchrl_bail.configuration.config_builders import collection_config
from torchrl_bail.data.cache import batch_name, batch_path
from torchrl_bail.data.listing import list_batches
from torchrl_bail.data.locks import SCRATCH, clean_stale, owned_name

ENVS = ["hopper", "walker", "halfcheetah", "ant", "humanoid"]
SAC_KINDS = ["sac", "med_det", "med_stoch", "opt_det", "opt_stoch"]
TINY_SAC = [
    "batch.steps=600", "env.max_episode_steps=100", "batch.sac.start_steps=200", "batch.sac.eval_every=200",
    "batch.sac.eval_episodes=2", "batch.sac.actor_hidden=[32,32]", "batch.sac.critic_hidden=[32,32]",
    "batch.sac.batch_size=32",
]
TINY_DDPG = [
    "batch.steps=300", "batch.start_steps=50", "env.max_episode_steps=50", "batch.agent.actor_hidden=[16,16]",
    "batch.agent.critic_hidden=[16,16]", "batch.agent.batch_size=8",
]
SRC = str(Path(__file__).resolve().parents[1] / "src")


def _compose(*overrides: str):
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        return compose("config", overrides=list(overrides))


def _paper_exps() -> list[tuple[str, str]]:
    return [(e, k) for e in ENVS for k in (["ddpg01", "ddpg05"] if e in ENVS[:3] else []) + SAC_KINDS]


def test_the_31_exps_give_the_papers_62_distinct_batches():
    exps = _paper_exps()
    assert len(exps) == 31
    assert sorted(p.stem for p in (config_dir() / "exp").glob("*.yaml")) >= sorted(f"{e}_{k}" for e, k in exps)
    paths = set()
    for env, kind in exps:
        for index in (1, 2):
            cfg = _compose(f"+exp={env}_{kind}", f"batch.index={index}")
            collection_config(cfg)
            assert (cfg.env.name, cfg.batch.kind) == (env, kind)
            assert batch_name(cfg) == f"{env}_{kind}_b{index}"
            paths.add(batch_path(cfg, "/d"))
    assert len(paths) == 62


def test_quick_preset_scales_every_recipe_and_any_combination_composes():
    for kind in ["ddpg01", "ddpg05", *SAC_KINDS]:
        paper, quick = _compose(f"+exp=hopper_{kind}"), _compose(f"+exp=hopper_{kind}", "preset=quick")
        assert quick.batch.steps < paper.batch.steps
        if "sac" in quick.batch:
            assert quick.batch.sac.train_steps < paper.batch.sac.train_steps
    cfg = _compose("env=ant", "batch=ddpg05")
    collection_config(cfg)
    assert batch_name(cfg) == "ant_ddpg05_b1"
    assert batch_name(_compose("+exp=hopper_ddpg05", "batch.oracle.enabled=true")) == "hopper_ddpg05_oracle_b1"


def test_exec_and_sac_recipes_are_validated():
    with pytest.raises(ConfigError, match=r"batch\.policy"):
        collection_config(_compose("+exp=hopper_med_det", "batch.policy=best"))
    with pytest.raises(ConfigError, match=r"batch\.sac\.polyak"):
        collection_config(_compose("+exp=hopper_sac", "batch.sac.polyak=1.5"))
    with pytest.raises(ConfigError, match=r"batch\.steps"):
        collection_config(_compose("+exp=hopper_sac", "batch.steps=2000", "batch.sac.train_steps=1000"))
    with pytest.raises(ConfigError, match=r"batch\.oracle\.horizon"):
        collection_config(_compose("+exp=hopper_ddpg05", "batch.oracle.enabled=true", "batch.oracle.horizon=500"))


@pytest.fixture(scope="module")
def sac_family(tmp_path_factory):
    """med_det first (trains the SAC run once), then opt_stoch and sac reuse it."""
    from torchrl_bail.behaviour import sac_run

    data_dir = tmp_path_factory.mktemp("sac")
    runs = []
    original = sac_run.train_sac

    def spy(*args, **kwargs):
        runs.append(1)
        return original(*args, **kwargs)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(sac_run, "train_sac", spy)
        med = ensure_batch(_compose("+exp=hopper_med_det", *TINY_SAC), progress=False, data_dir=data_dir)
        opt = ensure_batch(_compose("+exp=hopper_opt_stoch", *TINY_SAC), progress=False, data_dir=data_dir)
        sac_batch = ensure_batch(_compose("+exp=hopper_sac", *TINY_SAC), progress=False, data_dir=data_dir)
    return {"med": med, "opt": opt, "sac": sac_batch, "runs": runs, "data_dir": data_dir}


def test_one_sac_run_serves_mediocre_optimal_and_training_batches(sac_family):
    from torchrl_bail.behaviour.sac_run import load_sac_run

    assert len(sac_family["runs"]) == 1, "the SAC run must be trained once and reused"
    med, opt, sac_batch = sac_family["med"], sac_family["opt"], sac_family["sac"]
    for b in (med, opt, sac_batch):
        assert b.num_transitions == 600 and b.obs_dim == 11 and b.act_dim == 3
    run_dirs = list((sac_family["data_dir"] / "policies").iterdir())
    assert len(run_dirs) == 1
    run = load_sac_run(run_dirs[0])
    assert [e["step"] for e in run.evaluations] == [200, 400, 600]
    pol = med.metadata["behaviour_policy"]
    assert pol["which"] == "mediocre" and Path(pol["file"]).is_file() and pol["run"] == str(run_dirs[0])
    assert med.metadata["behaviour_return"] == pol["eval_return_mean"]
    assert opt.metadata["behaviour_policy"]["eval_step"] == 600
    assert sac_batch.metadata["sac_run"] == str(run_dirs[0])
    # the SAC batch starts with start_steps uniformly random actions, in bounds
    a = sac_batch.data["action"][:200]
    assert a.abs().max() <= 1 and a.min() < -0.8 and a.max() > 0.8


def test_execution_batches_follow_the_saved_policy(sac_family):
    from tensordict import TensorDict
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from torchrl_bail.behaviour.sac_run import SACRun, load_sac_run

    med, opt = sac_family["med"], sac_family["opt"]
    run = load_sac_run(Path(med.metadata["behaviour_policy"]["run"]))
    assert isinstance(run, SACRun)
    ev = next(e for e in run.evaluations if e["step"] == med.metadata["behaviour_policy"]["eval_step"])
    actor = run.load_actor(ev)
    obs = med.data["observation"][:50].clone()
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        mu = actor(TensorDict({"observation": obs}, [50]))["action"]
    torch.testing.assert_close(med.data["action"][:50], mu)  # sigma = 0: max_action * tanh(mu(s))
    final = run.load_actor(run.optimal())
    obs = opt.data["observation"][:200].clone()
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        mu = final(TensorDict({"observation": obs}, [200]))["action"]
    noise = (opt.data["action"][:200] - mu).abs()
    assert noise.mean() > 1e-3, "stochastic execution samples around the mean"
    assert opt.data["action"].abs().max() <= 1


def test_mediocre_is_the_first_evaluation_reaching_the_threshold(tmp_path):
    from torchrl_bail.behaviour.sac_run import SACRun

    evals = [{"step": s, "return_mean": r, "file": f"e{s}"} for s, r in [(5, 10.0), (10, 60.0), (15, 40.0),
                                                                          (20, 90.0)]]
    run = SACRun(tmp_path, {"evaluations": evals})
    assert run.mediocre(50.0) == (evals[1], True)
    assert run.mediocre(1000.0) == (evals[3], False)  # never reached: the best, flagged
    assert run.optimal() == evals[3]


def test_oracle_batches_cut_episodes_and_keep_the_real_continuation(tmp_path):
    cfg = _compose("+exp=hopper_ddpg05", *TINY_DDPG, "batch.oracle.enabled=true", "batch.oracle.horizon=40",
                   "batch.oracle.keep=20", "batch.sigma=0.0", "batch.start_steps=300")
    batch = ensure_batch(cfg, progress=False, data_dir=tmp_path)
    assert batch.path.name.startswith("hopper_ddpg05_oracle_b1-") and batch.num_transitions == 300
    d = batch.data
    g, r = d["oracle_return"], d["next", "reward"].squeeze(-1)
    term, trunc = d["next", "terminated"].squeeze(-1), d["next", "truncated"].squeeze(-1)
    ep = d["episode"]
    n_cut = 0
    for e in ep.unique().tolist():
        idx = (ep == e).nonzero().flatten()
        assert len(idx) <= 20
        torch.testing.assert_close(g[idx[:-1]], r[idx[:-1]] + 0.99 * g[idx[1:]], rtol=1e-4, atol=1e-4)
        last = idx[-1]
        if term[last]:
            torch.testing.assert_close(g[last], r[last])  # a fall ends the sum
        elif trunc[last]:
            assert len(idx) == 20
            n_cut += 1
            assert abs(float(g[last] - r[last])) > 1e-3, "the return after t = keep - 1 includes the real continuation"
    assert n_cut >= 3


def _child_script(cfg_overrides: list[str], data_dir: Path) -> str:
    return textwrap.dedent(f"""
        import signal, time, sys
        # a suite started as a background job hands its children SIGINT ignored: Ctrl-C's handler is put back
        signal.signal(signal.SIGINT, signal.default_int_handler)
        sys.path.insert(0, {SRC!r})
        from hydra import compose, initialize_config_dir
        from torchrl_bail import config_dir
        from torchrl_bail.behaviour import ddpg
        from torchrl_bail.behaviour import ensure_batch
        def wait_for_the_signal(self, replay, n):
            # the first update after the first episode: the collection waits here until the test's signal ends it,
            # so it provably has not finished when the signal arrives, however loaded the machine
            print("TRAINING", flush=True)
            while True:
                time.sleep(60)
        ddpg.DDPGAgent.train = wait_for_the_signal
        with initialize_config_dir(str(config_dir()), version_base="1.3"):
            cfg = compose("config", overrides={cfg_overrides!r})
        ensure_batch(cfg, progress=False, data_dir={str(data_dir)!r})
        print("FINISHED", flush=True)
    """)


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGINT])
def test_interrupted_collection_leaves_nothing_loadable_and_recollects(tmp_path, sig):
    overrides = ["+exp=hopper_ddpg05", *TINY_DDPG]
    data_dir = tmp_path / "data"
    env = {**os.environ, "RL_WARNINGS": "0"}
    proc = subprocess.Popen([sys.executable, "-c", _child_script(overrides, data_dir)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)
    try:
        deadline = time.time() + 120
        line = ""
        while "TRAINING" not in line and time.time() < deadline:
            line = proc.stdout.readline()
            if not line and proc.poll() is not None:
                pytest.fail(f"child exited early: {proc.stderr.read()[-3000:]}")
        assert "TRAINING" in line
        proc.send_signal(sig)
        out, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode != 0 and "FINISHED" not in out
    cfg = _compose(*overrides)
    path = batch_path(cfg, data_dir)
    assert not path.exists(), "an interrupted collection must not leave a batch under its final name"
    scratch = list((data_dir / SCRATCH).glob("*")) if (data_dir / SCRATCH).exists() else []
    if sig == signal.SIGINT:
        assert scratch == [], "Ctrl-C cleans its scratch directory on the way out"
    else:
        assert len(scratch) == 1, "a killed run leaves its scratch directory ..."
    batch = ensure_batch(cfg, progress=False, data_dir=data_dir)  # ... which the next call removes
    assert batch.num_transitions == 300
    assert list((data_dir / SCRATCH).glob("*")) == []
    assert clean_stale(data_dir) == []


def test_stale_scratch_of_a_live_process_is_kept(tmp_path):
    live = tmp_path / SCRATCH / owned_name("x")
    dead = tmp_path / SCRATCH / owned_name("y").replace(f".{os.getpid()}.", ".999999999.", 1)  # this namespace's
    live.mkdir(parents=True)
    dead.mkdir(parents=True)
    assert clean_stale(tmp_path) == [dead]
    assert live.exists() and not dead.exists()


def test_listing_reports_each_cached_batch(sac_family):
    rows = {r["name"].split("-")[0]: r for r in list_batches(sac_family["data_dir"])}
    assert set(rows) == {"hopper_med_det_b1", "hopper_opt_stoch_b1", "hopper_sac_b1"}
    for r in rows.values():
        assert r["transitions"] == 600 and r["episodes"] >= 6 and r["bytes"] > 0
        assert r["max_return"] >= r["mean_return"]
    assert "mediocre/det" in rows["hopper_med_det_b1"]["recipe"]

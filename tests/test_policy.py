"""Trained policies a user can run: policy files, load_policy, evaluate (reproducing the run) and exports."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from test_cli import ALGO_TINY, _summary, _train

from torchrl_bail import load_policy
from torchrl_bail.evaluate import main as evaluate_main
from torchrl_bail.evaluation.policy import export_policy, policy_actions, save_policy

ENV = {**os.environ, "RL_WARNINGS": "0"}


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("batches")


@pytest.fixture(scope="module")
def bc_run(tmp_path_factory, data_dir):
    """A tiny BC run whose one evaluation (at the end) scored the saved policy."""
    run_dir = tmp_path_factory.mktemp("bc") / "run"
    _train(run_dir, data_dir, "algo=bc", "seed=4", *ALGO_TINY["bc"], "eval.every_epochs=0.01")
    return run_dir


def _evaluate_cli(*args) -> str:
    proc = subprocess.run([sys.executable, "-m", "torchrl_bail.evaluate", *map(str, args)], capture_output=True,
                          text=True, env=ENV, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc.stdout


def test_evaluate_reproduces_the_runs_last_evaluation(bc_run):
    summary = _summary(bc_run)
    out = _evaluate_cli(bc_run, "--reproduce")
    replayed = float(out.split("return ")[1].split(" ±")[0])
    assert replayed == pytest.approx(summary["final_return"], abs=0.01), out
    assert "over 2 episodes (seed 4)" in out
    # and the discounted return at FQE's gamma, as the run logged it beside the return
    discounted = float(out.split("discounted return (gamma 0.99, the scale of an FQE estimate): ")[1].split(" ±")[0])
    logged = (bc_run / "logs" / "scalars" / "eval" / "discounted_return.csv").read_text().splitlines()
    assert discounted == pytest.approx(float(logged[-1].split(",")[1]), abs=0.01), out
    # another seed gives other start states
    assert f"{summary['final_return']:.2f}" not in _evaluate_cli(bc_run, "--episodes", 3, "--seed", 11)


def test_policy_file_records_how_to_rebuild_the_actor(bc_run):
    record = torch.load(bc_run / "policy.pt", weights_only=True)
    assert (record["algo"], record["env_id"], record["obs_dim"], record["act_dim"]) == ("bc", "Hopper-v5", 11, 3)
    assert record["action_low"] == [-1.0] * 3 and record["action_high"] == [1.0] * 3
    assert record["hidden"]["policy"] == list(record["config"]["algo"]["policy"]["hidden"])
    assert record["config"]["seed"] == 4 and record["info"]["evaluation"] == 0
    policy = load_policy(bc_run)
    obs = TensorDict({"observation": torch.randn(5, 11)}, [5])
    action = policy(obs)["action"]
    assert action.shape == (5, 3) and bool((action.abs() <= 1).all())


def test_best_policy_is_kept_and_named_in_the_summary(tmp_path, data_dir, monkeypatch):
    run_dir = tmp_path / "run"
    _train(run_dir, data_dir, "algo=bc", "seed=2", *ALGO_TINY["bc"])  # 5 evaluations
    summary = _summary(run_dir)
    logged = [float(line.split(",")[1]) for line in
              (run_dir / "logs" / "scalars" / "eval" / "return.csv").read_text().splitlines()]
    best = summary["best_policy"]
    assert len(logged) == 5 and best["path"] == "policy_best.pt"
    assert best["evaluation"] == logged.index(max(logged)) and best["mean_return"] == summary["best_return"]
    assert best["epoch"] == pytest.approx(0.002 * (best["evaluation"] + 1))
    policy = load_policy(run_dir, best=True)
    assert policy.record["info"]["iteration"] == best["iteration"]
    # the replay of a later evaluation plays that one evaluation alone, on its own start states, to the digit
    from torchrl_bail.evaluate import replay_evaluation
    from torchrl_bail.evaluation import Evaluator

    played = []
    original = Evaluator.evaluate
    monkeypatch.setattr(Evaluator, "evaluate", lambda self, p: played.append(self.evaluations) or original(self, p))
    final = load_policy(run_dir)
    assert final.record["info"]["evaluation"] == 4
    assert replay_evaluation(final).mean_return == final.record["info"]["mean_return"]
    assert replay_evaluation(policy).mean_return == best["mean_return"]
    assert played == [4, best["evaluation"]], "only the replayed evaluation is played"


def _plain_torch_actions(fmt: str, path, obs) -> torch.Tensor:
    """Runs a copy of the exported file, alone in a fresh directory, in an isolated interpreter (``-I``) where
    torchrl_bail, tensordict and torchrl cannot import."""
    alone = path.parent / f"alone_{path.name}"
    alone.mkdir()
    copy = alone / path.name
    shutil.copy(path, copy)
    torch.save(obs, alone / "obs.pt")
    load = {"pt2": f"torch.export.load({str(copy)!r}).module()", "torchscript": f"torch.jit.load({str(copy)!r})"}
    if fmt == "onnx":
        code = (f"import numpy, onnxruntime, torch; s = onnxruntime.InferenceSession({str(copy)!r}); "
                f"a = s.run(None, {{'observation': torch.load('obs.pt').numpy()}})[0]; "
                f"torch.save(torch.from_numpy(a), 'act.pt')")
    else:
        code = f"import torch; torch.manual_seed(0); m = {load[fmt]}; torch.save(m(torch.load('obs.pt')), 'act.pt')"
    block = "import sys; sys.modules.update(torchrl_bail=None, tensordict=None, torchrl=None); "
    proc = subprocess.run([sys.executable, "-I", "-c", block + code], capture_output=True, text=True, timeout=300,
                          cwd=alone)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return torch.load(alone / "act.pt")


@pytest.mark.parametrize("fmt", ["pt2", "torchscript", "onnx"])
def test_export_runs_without_this_package(bc_run, tmp_path, fmt):
    if fmt == "onnx":
        pytest.importorskip("onnxscript")
        pytest.importorskip("onnxruntime")
    path = tmp_path / f"policy.{fmt}"
    assert evaluate_main([str(bc_run), "--export", fmt, "--out", str(path)]) == 0
    obs = torch.randn(7, 11)
    expected = policy_actions(load_policy(bc_run), obs)
    assert torch.allclose(_plain_torch_actions(fmt, path, obs), expected, atol=1e-5)


def _tiny_bc(tmp_path):
    from torchrl_bail.algorithms.bc import BehaviourCloning
    from torchrl_bail.configuration.config_builders import algo_config
    from torchrl_bail.modules import action_spec_from_bounds

    spec = action_spec_from_bounds([-1.0] * 3, [1.0] * 3)
    torch.manual_seed(0)
    algo = BehaviourCloning(11, spec, algo_config("bc", policy={"hidden": [16]}))
    cfg = {"seed": 0, "env": {"id": "Hopper-v5"}, "algo": {"name": "bc", "policy": {"hidden": [16]}}}
    return save_policy(tmp_path / "policy.pt", algo, cfg, obs_dim=11, action_spec=spec)


def test_onnx_export_is_one_file_and_reexports_leave_nothing_behind(tmp_path, capsys):
    pytest.importorskip("onnxscript")
    pytest.importorskip("onnxruntime")
    path = _tiny_bc(tmp_path)
    for _ in range(2):
        assert evaluate_main([str(path), "--export", "onnx"]) == 0
    assert capsys.readouterr().out.splitlines() == [f"wrote {tmp_path / 'policy.onnx'} (standalone)"] * 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["policy.onnx", "policy.pt"]


def test_onnx_weights_too_large_to_embed_go_beside_the_file_under_its_name(tmp_path, capsys, monkeypatch):
    pytest.importorskip("onnxscript")
    onnxruntime = pytest.importorskip("onnxruntime")
    import torchrl_bail.evaluation.policy as policy_module

    path = _tiny_bc(tmp_path)
    monkeypatch.setattr(policy_module, "ONNX_EMBED_LIMIT", 0)  # every model is "too large"
    assert evaluate_main([str(path), "--export", "onnx", "--out", str(tmp_path / "out" / "bc.onnx")]) == 0
    out, data = tmp_path / "out" / "bc.onnx", tmp_path / "out" / "bc.onnx.data"
    assert capsys.readouterr().out.strip() == f"wrote {out} and its weights {data} (keep the two files together)"
    assert sorted(p.name for p in out.parent.iterdir()) == ["bc.onnx", "bc.onnx.data"]
    moved = tmp_path / "moved"
    moved.mkdir()
    for file in (out, data):  # the pair travels together
        shutil.copy(file, moved / file.name)
    obs = torch.randn(5, 11)
    session = onnxruntime.InferenceSession(str(moved / "bc.onnx"))
    actions = torch.from_numpy(session.run(None, {"observation": obs.numpy()})[0])
    assert torch.allclose(actions, policy_actions(load_policy(path), obs), atol=1e-5)
    monkeypatch.undo()  # small again: the weights go back inside and the old weights file goes away
    export_policy(path, out, "onnx")
    assert sorted(p.name for p in out.parent.iterdir()) == ["bc.onnx"]


def test_a_loaded_policy_acts_without_a_graph_and_takes_numpy_observations(tmp_path):
    policy = load_policy(_tiny_bc(tmp_path))
    obs = np.random.default_rng(0).standard_normal((4, 11))  # float64, as gymnasium returns it
    action = policy(TensorDict({"observation": torch.as_tensor(obs, dtype=torch.float32)}, [4]))["action"]
    assert action.grad_fn is None and not action.requires_grad
    from_numpy = policy_actions(policy, obs)  # cast once, at the edge
    assert from_numpy.dtype == torch.float32 and torch.equal(from_numpy, action)


def _tiny_bcq(tmp_path):
    from omegaconf import OmegaConf

    from torchrl_bail.algorithms.bcq import BCQ
    from torchrl_bail.configuration.config_builders import algo_config
    from torchrl_bail.modules import action_spec_from_bounds

    spec = action_spec_from_bounds([-1.0] * 3, [1.0] * 3)
    nets = {"vae": {"hidden": [16, 16]}, "actor": {"hidden": [16, 16]}, "critic": {"hidden": [16, 16]}}
    config = algo_config("bcq", **nets, batch_size=4, epochs=1e-5)
    algo = BCQ(11, spec, config)
    cfg = {"seed": 0, "env": {"id": "Hopper-v5"}, "algo": OmegaConf.to_container(config)}
    return algo, save_policy(tmp_path / "policy.pt", algo, cfg, obs_dim=11, action_spec=spec)


def test_bcq_best_of_n_loads_and_exports_to_pt2_only_where_it_can(tmp_path, capsys):
    algo, path = _tiny_bcq(tmp_path)
    policy = load_policy(path)
    obs = torch.randn(6, 11)
    torch.manual_seed(0)
    expected = policy_actions(algo.policy, obs)
    torch.manual_seed(0)
    assert torch.equal(policy_actions(policy, obs), expected)  # same weights, same candidates
    export_policy(policy, tmp_path / "bcq.pt2", "pt2")
    torch.manual_seed(0)
    assert torch.equal(policy_actions(policy, obs), expected)  # exporting left the policy untouched
    assert torch.allclose(_plain_torch_actions("pt2", tmp_path / "bcq.pt2", obs), expected, atol=1e-5)
    assert evaluate_main([str(path), "--export", "torchscript"]) == 2
    err = capsys.readouterr().err
    assert "bcq" in err and "pt2" in err and len(err.strip().splitlines()) == 1


def test_bcq_onnx_export_samples_in_onnxruntime(tmp_path):
    pytest.importorskip("onnxscript")
    pytest.importorskip("onnxruntime")
    _, path = _tiny_bcq(tmp_path)
    export_policy(path, tmp_path / "bcq.onnx", "onnx")
    obs = torch.randn(6, 11)
    actions = _plain_torch_actions("onnx", tmp_path / "bcq.onnx", obs)
    assert actions.shape == (6, 3) and bool((actions.abs() <= 1).all())  # its own random stream: no equality


def test_clear_errors(tmp_path, bc_run, capsys, monkeypatch):
    assert evaluate_main([str(tmp_path)]) == 2
    assert "policy.pt" in capsys.readouterr().err
    torch.save({"policy": {}}, tmp_path / "old.pt")  # the format before policy files carried their config
    assert evaluate_main([str(tmp_path / "old.pt")]) == 2
    assert "old.pt" in capsys.readouterr().err
    monkeypatch.setitem(sys.modules, "moviepy", None)
    assert evaluate_main([str(bc_run), "--episodes", "1", "--video", str(tmp_path / "video")]) == 2
    assert "moviepy" in capsys.readouterr().err


@pytest.mark.parametrize("damage", ["random_bytes", "truncated"])
def test_evaluate_names_a_damaged_policy_file_as_such(bc_run, tmp_path, damage):
    """A policy.pt of random bytes, or cut short, is called corrupt or truncated by the policy-file reader itself,
    so ``python -m torchrl_bail.evaluate`` says so as ``ope`` does: one line, exit status 2, without torch's advice
    to load it with weights_only=False (right for a trusted file of another format, wrong for a damaged one)."""
    data = (bc_run / "policy.pt").read_bytes()
    damaged = tmp_path / "policy.pt"
    damaged.write_bytes(os.urandom(4096) if damage == "random_bytes" else data[:len(data) // 2])
    proc = subprocess.run([sys.executable, "-m", "torchrl_bail.evaluate", str(damaged)], capture_output=True,
                          text=True, env=ENV, timeout=300)
    err = proc.stderr.strip()
    assert proc.returncode == 2 and len(err.splitlines()) == 1, err
    assert err.startswith(f"torchrl_bail.evaluate: {damaged}: not a readable policy file: corrupt or truncated"), err
    assert "weights_only" not in err, err


def test_video_of_a_trained_policy(bc_run, tmp_path):
    pytest.importorskip("moviepy")
    assert evaluate_main([str(bc_run), "--episodes", "1", "--video", str(tmp_path / "video")]) == 0
    (video,) = (tmp_path / "video").glob("*.mp4")
    assert video.stat().st_size > 1000

"""Load a trained policy, evaluate it, and export it to files that run without this package.

    python docs/tutorials/load_evaluate_export.py --run-dir outputs/hopper_ddpg05_b1/bail/seed1,preset=quick
    python docs/tutorials/load_evaluate_export.py      # no run at hand: trains a quick BAIL run first

Any further argument is a Hydra override of that training run.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnxruntime
import torch
from tensordict import TensorDict

from torchrl_bail import load_policy
from torchrl_bail.evaluation.policy import export_policy, read_policy_file


def sh(*args: str) -> None:
    print("$", " ".join(args).replace(sys.executable, "python"), flush=True)
    subprocess.run(args, check=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run-dir", type=Path, help="a finished run's directory (default: train one)")
    parser.add_argument("--work-dir", type=Path, default=Path("tutorial_policy"))
    parser.add_argument("--episodes", type=int, default=10)
    args, overrides = parser.parse_known_args()
    if args.run_dir is None:
        args.run_dir = args.work_dir / "run"
        sh(sys.executable, "-m", "torchrl_bail.train", "+exp=hopper_ddpg05", "preset=quick", "progress=false",
           f"hydra.run.dir={args.run_dir}", *overrides)

    # 1. Load: the policy file records the algorithm, sizes, action bounds and config, so one call rebuilds it.
    policy = load_policy(args.run_dir)                   # policy.pt; best=True for policy_best.pt
    record = read_policy_file(args.run_dir)
    obs_dim = record["obs_dim"]
    observation = torch.randn(4, obs_dim, generator=torch.Generator().manual_seed(0))  # the same 4 every run
    with torch.no_grad():
        action = policy(TensorDict({"observation": observation}, [4]))["action"]
    print(f"{record['algo']} policy for {record['env_id']}: observation {obs_dim} -> action {action.shape[-1]}")

    # 2. Evaluate: deterministic episodes in a batched env, mean +- sample std of the returns.
    sh(sys.executable, "-m", "torchrl_bail.evaluate", str(args.run_dir), "--episodes", str(args.episodes))

    # 3. Export: observation [B, obs_dim] -> action [B, act_dim], loadable without torchrl_bail, TorchRL or tensordict.
    #    The command line does the same: python -m torchrl_bail.evaluate RUN_DIR --export pt2 --out policy.pt2
    args.work_dir.mkdir(parents=True, exist_ok=True)
    pt2 = export_policy(args.run_dir, args.work_dir / "policy.pt2", "pt2")
    onnx = export_policy(args.run_dir, args.work_dir / "policy.onnx", "onnx")
    exported = torch.export.load(str(pt2)).module()
    session = onnxruntime.InferenceSession(str(onnx))
    with torch.no_grad():
        via_pt2 = exported(observation)
    via_onnx = session.run(None, {session.get_inputs()[0].name: observation.numpy()})[0]
    print(f"pt2 export: largest difference from the loaded policy {float((via_pt2 - action).abs().max()):.2e}")
    onnx_gap = float(np.abs(via_onnx - action.numpy()).max())
    print(f"onnx export: largest difference from the loaded policy {onnx_gap:.2e}")


if __name__ == "__main__":
    main()

"""The d3rlpy side of ``bench_d3rlpy.py``; runs under d3rlpy's own interpreter (``--python``), never imported.

It builds d3rlpy 2.8's BCQ, BEAR and BC at the sizes ``bench_d3rlpy.py`` passes, then answers lines on stdin:
``<algo> <n>`` runs ``n`` training iterations of ``<algo>`` (``sample_transition_batch`` + ``update``, what
d3rlpy's ``fit`` runs per step) and prints ``<updates per wall-clock second> <updates per CPU second>``; ``quit``
ends it. Only numpy, torch and d3rlpy are imported here.
"""

from __future__ import annotations

import json
import os
import sys
import time
import warnings

warnings.filterwarnings("ignore")
# replies go to the original stdout; everything d3rlpy or gym print goes to stderr
REPLY = os.fdopen(os.dup(1), "w")
os.dup2(2, 1)

import d3rlpy  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from d3rlpy.models.encoders import VectorEncoderFactory  # noqa: E402


def dataset(n: int, obs: int, act: int) -> d3rlpy.dataset.MDPDataset:
    rng = np.random.default_rng(0)
    terminals = (rng.random(n) < 0.01).astype(np.float32)
    timeouts = np.zeros(n, dtype=np.float32)
    timeouts[-1] = 1.0 if not terminals[-1] else 0.0
    return d3rlpy.dataset.MDPDataset(
        observations=rng.standard_normal((n, obs)).astype(np.float32),
        actions=(rng.random((n, act)) * 2 - 1).astype(np.float32),
        rewards=rng.standard_normal((n, 1)).astype(np.float32),
        terminals=terminals, timeouts=timeouts,
        action_space=d3rlpy.constants.ActionSpace.CONTINUOUS,
    )


def build(cfg: dict, data: d3rlpy.dataset.MDPDataset) -> dict:
    net, vae = VectorEncoderFactory(cfg["net_hidden"]), VectorEncoderFactory(cfg["vae_hidden"])
    common = dict(actor_encoder_factory=net, critic_encoder_factory=net, imitator_encoder_factory=vae,
                  actor_learning_rate=1e-3, critic_learning_rate=1e-3, imitator_learning_rate=1e-3,
                  batch_size=cfg["batch"], gamma=0.99, tau=0.005, n_critics=2, lam=0.75)
    algos = {
        "bcq": d3rlpy.algos.BCQConfig(**common, n_action_samples=cfg["n_target"], action_flexibility=0.05,
                                      beta=0.5, rl_start_step=0),
        "bear": d3rlpy.algos.BEARConfig(**common, n_action_samples=cfg["n_target"],
                                        n_target_samples=cfg["n_target"], n_mmd_action_samples=cfg["n_match"],
                                        mmd_kernel="laplacian", mmd_sigma=10.0, alpha_threshold=0.05,
                                        vae_kl_weight=0.5, alpha_learning_rate=1e-3, warmup_steps=0,
                                        temp_learning_rate=0.0),
        "bc": d3rlpy.algos.BCConfig(encoder_factory=net, learning_rate=1e-3, batch_size=cfg["bc_batch"],
                                    policy_type="deterministic"),
    }
    out = {}
    for name, config in algos.items():
        algo = config.create(device="cpu:0")
        algo.build_with_dataset(data)
        out[name] = algo
    return out


def main() -> None:
    cfg = json.loads(sys.argv[1])
    torch.set_num_threads(cfg["threads"])
    torch.manual_seed(0)
    np.random.seed(0)
    data = dataset(cfg["transitions"], cfg["obs"], cfg["act"])
    algos = build(cfg, data)
    print(json.dumps({"d3rlpy": d3rlpy.__version__, "torch": torch.__version__}), file=REPLY, flush=True)
    for line in sys.stdin:
        parts = line.split()
        if not parts or parts[0] == "quit":
            break
        name, n = parts[0], int(parts[1])
        algo = algos[name]
        batch_size = algo.config.batch_size
        wall, cpu = time.perf_counter(), time.process_time()
        for _ in range(n):
            algo.update(data.sample_transition_batch(batch_size))
        print(n / (time.perf_counter() - wall), n / (time.process_time() - cpu), file=REPLY, flush=True)


if __name__ == "__main__":
    main()

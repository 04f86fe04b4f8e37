"""The d3rlpy side of ``bench_d3rlpy.py`` and ``bench_d3rlpy_returns.py``; runs under d3rlpy's own interpreter
(``--python``), never imported. Only numpy, torch and d3rlpy are imported here.

Two modes, chosen by the JSON config in ``argv[1]`` (``"mode"``):

* ``throughput`` (default): builds d3rlpy 2.8's BCQ, BEAR and BC at the sizes ``bench_d3rlpy.py`` passes on
  synthetic data, then answers lines on stdin: ``<algo> <n>`` runs ``n`` training iterations of ``<algo>``
  (``sample_transition_batch`` + ``update``, what d3rlpy's ``fit`` runs per step) and prints ``<updates per
  wall-clock second> <updates per CPU second>``.
* ``train``: builds one algorithm (``"algo"``) with the matched constants ``bench_d3rlpy_returns.py`` passes, on
  the arrays of ``"dataset"`` (an ``.npz`` written by that script), seeded with ``d3rlpy.seed(seed)``, and
  answers ``update <n>`` (``n`` more updates; prints the CPU seconds they took) and ``act`` followed by one line
  of JSON observations ``[[...], ...]`` (prints ``algo.predict``'s greedy actions as JSON). For BC in lockstep
  (``bench_d3rlpy_lockstep.py``): ``set_policy <npz>`` loads the policy's parameters (``p0``, ``p1``, ... in
  ``parameters()`` order: the encoder's layers, then the output layer) and ``update_on <npz>`` runs one update per
  row of its ``index`` array on the mini-batch of its ``observations``/``actions`` rows that the row names,
  printing the losses as JSON.

``quit`` ends either mode.

``"decoder_tanh": true`` in the config (``bench_d3rlpy_returns.py --d3rlpy-decoder-tanh``) patches d3rlpy's
``VAEDecoder.forward`` before anything is built, so that the decoder's output is ``tanh`` of its linear head, as in
the authors' BCQ (sfujim/BCQ) and in d3rlpy before its commit 4abdbd3f (2.1.0): since then ``forward`` returns
the linear head when ``with_squash`` is true, which every d3rlpy caller passes (the default), so its BCQ and
BEAR candidate actions are bounded only by the later clamp to the action bounds.
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
from d3rlpy.models.torch.imitators import VAEDecoder  # noqa: E402


def restore_decoder_tanh() -> None:
    """Makes every ``VAEDecoder`` output ``tanh(fc(encoder(x, latent)))``, whatever ``with_squash`` says (see the
    module doc)."""
    def forward(self, x, latent, with_squash):
        return torch.tanh(self._fc(self._encoder(x, latent)))

    VAEDecoder.forward = forward


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


def make_config(name: str, cfg: dict):
    """d3rlpy's config of ``name`` (bcq, bear, bc) from the constants in ``cfg`` (the throughput mode passes only
    sizes; the rest default to the values it has always used)."""
    lr = cfg.get("lr", {})
    if name == "bc":
        return d3rlpy.algos.BCConfig(encoder_factory=VectorEncoderFactory(cfg.get("bc_hidden", cfg.get("net_hidden"))),
                                     learning_rate=lr.get("bc", 1e-3), batch_size=cfg["bc_batch"],
                                     policy_type="deterministic")
    common = dict(actor_encoder_factory=VectorEncoderFactory(cfg.get("actor_hidden", cfg.get("net_hidden"))),
                  critic_encoder_factory=VectorEncoderFactory(cfg.get("critic_hidden", cfg.get("net_hidden"))),
                  imitator_encoder_factory=VectorEncoderFactory(cfg["vae_hidden"]),
                  actor_learning_rate=lr.get("actor", 1e-3), critic_learning_rate=lr.get("critic", 1e-3),
                  imitator_learning_rate=lr.get("vae", 1e-3), batch_size=cfg["batch"], gamma=cfg.get("gamma", 0.99),
                  tau=cfg.get("tau", 0.005), n_critics=2, lam=cfg.get("lmbda", 0.75))
    if name == "bcq":
        return d3rlpy.algos.BCQConfig(**common, n_action_samples=cfg["n_target"],
                                      action_flexibility=cfg.get("phi", 0.05), beta=cfg.get("kl_weight", 0.5),
                                      rl_start_step=0)
    return d3rlpy.algos.BEARConfig(**common, n_action_samples=cfg["n_target"], n_target_samples=cfg["n_target"],
                                   n_mmd_action_samples=cfg["n_match"], mmd_kernel="laplacian",
                                   mmd_sigma=cfg.get("kernel_sigma", 10.0), alpha_threshold=cfg.get("epsilon", 0.05),
                                   vae_kl_weight=cfg.get("kl_weight", 0.5), alpha_learning_rate=lr.get("alpha", 1e-3),
                                   warmup_steps=cfg.get("warmup", 0), temp_learning_rate=0.0,
                                   initial_temperature=cfg.get("temperature", 1.0))


def build(cfg: dict, data: d3rlpy.dataset.MDPDataset, names=("bcq", "bear", "bc")) -> dict:
    out = {}
    for name in names:
        algo = make_config(name, cfg).create(device="cpu:0")
        algo.build_with_dataset(data)
        out[name] = algo
    return out


def throughput_main(cfg: dict) -> None:
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


def train_main(cfg: dict) -> None:
    arrays = np.load(cfg["dataset"])
    data = d3rlpy.dataset.MDPDataset(
        observations=arrays["observations"], actions=arrays["actions"], rewards=arrays["rewards"],
        terminals=arrays["terminals"], timeouts=arrays["timeouts"],
        action_space=d3rlpy.constants.ActionSpace.CONTINUOUS,
    )
    d3rlpy.seed(cfg["seed"])
    algo = build(cfg, data, names=(cfg["algo"],))[cfg["algo"]]
    batch_size = algo.config.batch_size
    print(json.dumps({"d3rlpy": d3rlpy.__version__, "torch": torch.__version__,
                      "transitions": int(data.transition_count)}), file=REPLY, flush=True)
    for line in sys.stdin:
        parts = line.split()
        if not parts or parts[0] == "quit":
            break
        if parts[0] == "update":
            cpu = time.process_time()
            for _ in range(int(parts[1])):
                algo.update(data.sample_transition_batch(batch_size))
            print(time.process_time() - cpu, file=REPLY, flush=True)
        elif parts[0] == "set_policy":
            with np.load(parts[1]) as saved, torch.no_grad():
                for i, param in enumerate(algo.impl.policy.parameters()):
                    value = torch.from_numpy(saved[f"p{i}"])
                    if value.shape != param.shape:
                        raise SystemExit(f"parameter {i}: shape {tuple(value.shape)} for {tuple(param.shape)}")
                    param.copy_(value)
            print("ok", file=REPLY, flush=True)
        elif parts[0] == "update_on":
            with np.load(parts[1]) as given:
                obs, act, index = given["observations"], given["actions"], given["index"]
            losses = []
            for rows in index:
                n = len(rows)
                losses.append(algo.update(d3rlpy.dataset.TransitionMiniBatch(
                    observations=obs[rows], actions=act[rows], rewards=np.zeros((n, 1), np.float32),
                    next_observations=obs[rows], next_actions=act[rows], terminals=np.zeros((n, 1), np.float32),
                    intervals=np.ones((n, 1), np.float32), transitions=[]))["loss"])
            print(json.dumps(losses), file=REPLY, flush=True)
        elif parts[0] == "act":
            obs = np.asarray(json.loads(sys.stdin.readline()), dtype=np.float32)
            print(json.dumps(algo.predict(obs).tolist()), file=REPLY, flush=True)


def main() -> None:
    cfg = json.loads(sys.argv[1])
    torch.set_num_threads(cfg["threads"])
    if cfg.get("decoder_tanh"):
        restore_decoder_tanh()
    (train_main if cfg.get("mode") == "train" else throughput_main)(cfg)


if __name__ == "__main__":
    main()

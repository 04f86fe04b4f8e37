"""Why MARWIL imitates worse than BC on Hopper's execution batches: the measurements behind README "MARWIL".

    python results/marwil_stall.py                                  # Hopper med_stoch and opt_det, seed 1
    python results/marwil_stall.py --batches hopper_med_stoch --updates 4000 --seeds 1 2

For each batch (the results study's 50k-transition B1, ``preset=study``) and seed, four trainees see the same
mini-batches in the same order, for ``--updates`` updates of 1000:

* ``marwil`` -- MARWIL as configured (``conf/algo/marwil.yaml``: RLlib's constants, joint training);
* ``marwil_adam_reset`` -- the same, but the actor's Adam state is cleared after ``--reset-at`` updates: the
  direct test of the guess that Adam's second moment, filled by the first updates' huge weights, stalls the actor
  (if it does, the actor's imitation error falls as soon as the memory is gone);
* ``marwil_value_warmup`` -- ``algo.value_warmup_updates=--reset-at``: V is fitted alone first, the actor starts
  with a fresh Adam (the switch that would fix it);
* ``bc`` -- behaviour cloning (``algo=bc``), the reference fit.

Every ``--every`` updates it records, per trainee: the actor's unweighted imitation error on a fixed held-out
sample of 5000 states (``mean_a (pi(s) - a)^2``, BC's loss), MARWIL's normaliser ``c^2``, the advantage scale
``sqrt(mean A^2)``, the largest weight's share of a mini-batch's total weight, the clamped fraction, the effective
sample size of the weights (``(sum w)^2 / sum w^2``, in points of 1000), and the actor's Adam state: the RMS of
``sqrt(v_hat)`` (the denominator) and the RMS of the step it takes (``lr * m_hat / (sqrt(v_hat) + eps)``).
It writes ``results/marwil_stall/stall.json`` and ``stall.png``. The returns of the switch are measured with
ordinary training runs (``results/run_study.py``; README).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir

from torchrl_bail import config_dir
from torchrl_bail.algorithms import PrepareContext, build_algorithm
from torchrl_bail.behaviour import ensure_batch
from torchrl_bail.data import monte_carlo_returns
from torchrl_bail.modules import action_spec_from_bounds

HERE = Path(__file__).resolve().parent
TRAINEES = ("marwil", "marwil_adam_reset", "marwil_value_warmup", "bc")


EXTRA: list[str] = []  # --extra overrides, applied to every config (e.g. a tiny batch for a dry run)


def compose_config(batch: str, algo: str, seed: int, *extra: str):
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        return compose("config", overrides=[f"+exp={batch}", "preset=study", f"algo={algo}", f"seed={seed}",
                                            "progress=false", *EXTRA, *extra])


def adam_statistics(optimizer: torch.optim.Adam) -> tuple[float, float]:
    """``(rms sqrt(v_hat), rms step)`` over every parameter element Adam has state for (``(nan, nan)`` before)."""
    denominator, step, count = 0.0, 0.0, 0
    for group in optimizer.param_groups:
        beta1, beta2 = group["betas"]
        for param in group["params"]:
            state = optimizer.state.get(param)
            if not state:
                continue
            t = float(state["step"])
            v_hat = state["exp_avg_sq"] / (1 - beta2 ** t)
            m_hat = state["exp_avg"] / (1 - beta1 ** t)
            denominator += float(v_hat.sum())
            step += float((group["lr"] * m_hat / (v_hat.sqrt() + group["eps"])).square().sum())
            count += param.numel()
    if not count:
        return math.nan, math.nan
    return math.sqrt(denominator / count), math.sqrt(step / count)


@torch.no_grad()
def probe(algo, held_out, trainee: str) -> dict[str, float]:
    """The imitation error on ``held_out`` and, for MARWIL, its weights' statistics there."""
    predicted = algo.actor(held_out.select("observation").clone())["action"]
    row = {"imitation_error": float((predicted - held_out["action"]).square().mean())}
    if trainee != "bc":
        weight, advantage, clamped = algo.loss.advantage_weights(held_out.select("observation", "return").clone())
        row.update(c2=float(algo.loss.c2), advantage_rms=float(advantage.square().mean().sqrt()),
                   clamped_fraction=float(clamped.float().mean()),
                   weight_share_max_per_1000=float(weight.max() / weight.sum() * held_out.batch_size[0] / 1000),
                   ess_per_1000=float(weight.sum() ** 2 / weight.square().sum() / held_out.batch_size[0] * 1000))
    row["adam_denominator_rms"], row["adam_step_rms"] = adam_statistics(algo.optimizers["actor"])
    return row


def run_batch(batch_name: str, seed: int, updates: int, every: int, reset_at: int) -> dict:
    base = compose_config(batch_name, "marwil", seed)
    batch = ensure_batch(base, progress=False)
    data = batch.data.select("observation", "action", "next", "episode").clone(False)
    data.set("return", monte_carlo_returns(batch.data, gamma=base.returns.gamma, horizon=base.returns.horizon,
                                           augment=base.returns.augment))
    spec = action_spec_from_bounds(batch.metadata["action_low"], batch.metadata["action_high"])
    n = data.batch_size[0]
    held = min(5000, n // 5)
    order = torch.randperm(n, generator=torch.Generator().manual_seed(seed))
    held_out, train = data[order[:held]].clone(), data[order[held:]].clone()
    overrides = {name: [] for name in TRAINEES}
    overrides["marwil_value_warmup"] = [f"algo.value_warmup_updates={reset_at}"]
    trainees = {}
    for name in TRAINEES:
        cfg = compose_config(batch_name, "bc" if name == "bc" else "marwil", seed, *overrides[name])
        torch.manual_seed(seed)  # every trainee starts from the same actor weights
        algo = build_algorithm(cfg.algo, batch.obs_dim, spec, "cpu")
        trainees[name] = (algo, algo.prepare(train, PrepareContext(generator=torch.Generator().manual_seed(seed))))
    sampler = torch.Generator().manual_seed(1000 + seed)
    curves = {name: [] for name in TRAINEES}
    start = time.perf_counter()
    for step in range(updates + 1):
        if step % every == 0:
            for name, (algo, _) in trainees.items():
                curves[name].append({"update": step, **probe(algo, held_out, name)})
        if step == updates:
            break
        index = torch.randint(0, n - held, (base.algo.batch_size,), generator=sampler)
        for algo, prepared in trainees.values():
            algo.update(prepared[index])
        if step + 1 == reset_at:
            trainees["marwil_adam_reset"][0].optimizers["actor"].state.clear()
    return {"batch": batch_name, "seed": seed, "updates": updates, "reset_at": reset_at,
            "behaviour_return": batch.metadata.get("behaviour_return"), "wall_s": round(time.perf_counter() - start),
            "curves": curves}


def plot(records: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("imitation_error", "held-out imitation error", True), ("adam_step_rms", "actor's Adam step (RMS)", True),
              ("adam_denominator_rms", "actor's Adam sqrt(v_hat) (RMS)", True),
              ("ess_per_1000", "effective sample size per 1000", False)]
    fig, axes = plt.subplots(len(records), len(panels), figsize=(4.2 * len(panels), 3.2 * len(records)),
                             squeeze=False, constrained_layout=True)
    for row, record in zip(axes, records, strict=True):
        for ax, (key, title, log) in zip(row, panels, strict=True):
            for name, curve in record["curves"].items():
                points = [(p["update"], p[key]) for p in curve if key in p and p[key] == p[key]]
                if points:
                    ax.plot(*zip(*points, strict=True), label=name)
            ax.axvline(record["reset_at"], color="grey", lw=0.8, ls=":")
            ax.set_title(f"{record['batch']} seed {record['seed']}: {title}", fontsize=9)
            ax.set_xlabel("updates")
            if log:
                ax.set_yscale("log")
    axes[0][0].legend(fontsize=7)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batches", nargs="+", default=["hopper_med_stoch", "hopper_opt_det"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[1])
    parser.add_argument("--updates", type=int, default=2000, help="the study's MARWIL schedule is 2000")
    parser.add_argument("--every", type=int, default=50)
    parser.add_argument("--reset-at", type=int, default=200)
    parser.add_argument("--out", type=Path, default=HERE / "marwil_stall")
    parser.add_argument("--extra", nargs="*", default=[], help="Hydra overrides for every config")
    args = parser.parse_args()
    EXTRA.extend(args.extra)
    torch.set_num_threads(1)
    records = [run_batch(b, s, args.updates, args.every, args.reset_at) for b in args.batches for s in args.seeds]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "stall.json").write_text(json.dumps(records, indent=1) + "\n")
    plot(records, args.out / "stall.png")
    for record in records:
        last = {name: curve[-1] for name, curve in record["curves"].items()}
        print(record["batch"], "seed", record["seed"], " ".join(
            f"{name}={point['imitation_error']:.4f}" for name, point in last.items()))


if __name__ == "__main__":
    main()

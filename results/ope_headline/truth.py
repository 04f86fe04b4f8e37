"""The true values FQE's estimates are ranked against, for the OPE study's 20 kept final policies (issue 53).

    python results/ope_headline/truth.py            # replays kept in truth.json are kept; --force replays again
    python results/ope_headline/truth.py --check    # exit status 1 unless truth.json is what the kept files give

FQE at ``gamma = 0.99`` estimates a *discounted* value, ``E[sum_t gamma^t r_t]`` from an episode's start; the study
(``ope.md``) ranked it against each policy's *undiscounted* return over up to 1000 steps. This script gives both
truths for every kept policy (``runs/**/policy.pt``, listed in ``ope.json``), from the policy's own last evaluation
in training, replayed exactly as the training run made it (:func:`torchrl_bail.evaluate.replay_evaluation`: the
run's env, seed, 10 episodes, 1000-step budget, and that evaluation's episode seeds,
``episode_seed(seed, evaluation, episode)``; the training itself is not run again):

* ``true_return``: the mean undiscounted return; for a deterministic policy the replay must equal the return the
  training run recorded (``policy.pt``'s ``info.mean_return``, ``ope.json``'s ``true_return``) to the last digit,
  or the script stops. BCQ's and BEAR's best-of-N policies draw their candidates from torch's global stream, which
  training also drew from: their replay (torch seeded with the run's seed, so this file is reproducible) is a fresh
  draw on the same start states, and their ``true_return`` stays the recorded one;
* ``true_discounted_return``: the same episodes' mean ``sum_t gamma^t r_t`` at FQE's ``gamma``
  (:attr:`torchrl_bail.ope.FQESettings.gamma`), what an FQE estimate aims at.

Snapshots: a BAIL run's 5 snapshots are listed with their recorded (undiscounted) evaluation returns; their weights
were not kept (``runs/**/snapshots`` holds the FQE records only), so they have no discounted truth.

Then, from what is kept (each policy's single FQE fit in ``ope.json``, its action gap, these truths), how each
selection rule of :mod:`torchrl_bail.ope` ranks the policies: Spearman's rho with its bootstrap interval
(:func:`torchrl_bail.ope.spearman_interval`) against each truth, and the regret of the policy each rule picks.
Writes ``truth.json`` beside this file.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]


def _sha1(path: Path) -> str:
    import hashlib

    return hashlib.sha1(path.read_bytes()).hexdigest()


def replay(policy_entry: dict) -> dict:
    """One kept policy's last evaluation, replayed: per-episode returns, discounted returns and lengths."""
    import torch

    from torchrl_bail.algorithms import ALGORITHMS
    from torchrl_bail.evaluate import replay_evaluation
    from torchrl_bail.policy import load_policy

    path = ROOT / policy_entry["run"] / "policy.pt"
    policy = load_policy(path)
    info, config = policy.record["info"], policy.record["config"]
    samples = bool(ALGORITHMS[policy.record["algo"]].policy_samples)
    start = time.perf_counter()
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(config["seed"]))  # a sampling policy's draws: fixed, so the file is reproducible
        result = replay_evaluation(policy)
    recorded = float(info["mean_return"])
    same = result.mean_return == recorded
    if not samples and not same:
        sys.exit(f"truth.py: {policy_entry['job']}: the replay returns {result.mean_return!r} where the training "
                 f"run recorded {recorded!r}; a deterministic policy's replay must equal it")
    return {"policy_sha1": _sha1(path), "seed": int(config["seed"]), "evaluation": int(info["evaluation"]),
            "iteration": int(info["iteration"]), "episodes": len(result.returns), "gamma": result.gamma,
            "sampling_policy": samples, "recorded_return": recorded, "replayed_return": result.mean_return,
            "same_to_the_digit": same, "returns": result.returns, "discounted_returns": result.discounted_returns,
            "lengths": result.lengths, "failures": result.failures,
            "replayed_discounted_return": result.mean_discounted_return,
            "replay_wall_time_s": time.perf_counter() - start}


def _rank(estimates: list[float], truths: list[float], names: list[str]) -> dict:
    from torchrl_bail.ope import ranking_quality, spearman_interval

    q = ranking_quality(estimates, truths)
    low, high = spearman_interval(estimates, truths)
    return {"spearman": q["spearman"], "spearman_ci": [low, high], "selected": names[q["selected"]],
            "best": names[q["best"]], "regret": q["regret"]}


def analyse(policies: list[dict]) -> dict:
    """Rank figures of the single-fit estimates against both truths; filled in by the selection rules below."""
    names = [p["job"] for p in policies]
    estimates = [p["fqe_estimate"] for p in policies]
    return {"single_fit": {
        "against_discounted": _rank(estimates, [p["true_discounted_return"] for p in policies], names),
        "against_undiscounted": _rank(estimates, [p["true_return"] for p in policies], names)}}


def build(force: bool) -> dict:
    study = json.loads((HERE / "ope.json").read_text())
    kept = {}
    if not force and (HERE / "truth.json").is_file():
        kept = {p["job"]: p for p in json.loads((HERE / "truth.json").read_text())["policies"]}
    from torchrl_bail.ope import FQESettings

    policies, snapshots = [], []
    for entry in study["policies"]:
        path = ROOT / entry["run"] / "policy.pt"
        old = kept.get(entry["job"])
        if old is not None and old["replay"]["policy_sha1"] == _sha1(path):
            rep = old["replay"]
        else:
            rep = replay(entry)
            print(f"{entry['job']}: replayed {rep['replayed_return']:.1f} (recorded {rep['recorded_return']:.1f}, "
                  f"{'same' if rep['same_to_the_digit'] else 'a fresh draw'}), discounted "
                  f"{rep['replayed_discounted_return']:.2f} [{rep['replay_wall_time_s']:.0f} s]", flush=True)
        truth_discounted = rep["replayed_discounted_return"]
        policies.append({
            "job": entry["job"], "algo": entry["algo"], "seed": entry["seed"], "run": entry["run"],
            "true_return": rep["recorded_return"], "true_discounted_return": truth_discounted,
            "fqe_estimate": entry["estimate"], "action_gap": entry["action_gap"],
            "estimate_over_discounted_truth": entry["estimate"] / truth_discounted - 1.0,
            "replay": rep})
        if entry.get("snapshots"):
            snapshots.append({"job": entry["job"], "candidates": [
                {"iteration": c["iteration"], "true_return": c["eval_return"], "true_discounted_return": None,
                 "fqe_estimate": c["fqe_estimate"]} for c in entry["snapshots"]["candidates"]]})
    return {"gamma": FQESettings.gamma, "source": "results/ope_headline/ope.json (the kept single FQE fits, action "
            "gaps and recorded returns) and each kept policy.pt, its last evaluation replayed",
            "command": "python results/ope_headline/truth.py",
            "snapshot_note": "the BAIL runs' snapshot weights were not kept (runs/**/snapshots holds their FQE "
                             "records only): each snapshot has its recorded undiscounted evaluation return and no "
                             "discounted truth",
            "policies": policies, "snapshots": snapshots, "ranking": analyse(policies)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--force", action="store_true", help="replay every policy again")
    parser.add_argument("--check", action="store_true", help="exit 1 unless truth.json is what the kept files give")
    args = parser.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    record = build(args.force)
    text = json.dumps(record, indent=2) + "\n"
    out = HERE / "truth.json"
    if args.check:
        same = out.is_file() and out.read_text() == text
        print(f"{out}: {'up to date' if same else 'differs from what the kept files give'}")
        return 0 if same else 1
    out.write_text(text)
    single = record["ranking"]["single_fit"]
    for name, q in single.items():
        print(f"single FQE fit {name.replace('_', ' ')}: rho {q['spearman']:.2f} "
              f"[{q['spearman_ci'][0]:.2f}, {q['spearman_ci'][1]:.2f}], regret {q['regret']:.1f}")
    print(f"-> {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

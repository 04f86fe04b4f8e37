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
    from torchrl_bail.evaluation.policy import load_policy

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


#: the stopping rules' knobs measured on the kept curves: windows (curve points) and tolerances
WINDOWS, TOLERANCES = (5, 10, 20, 30), (0.01, 0.02, 0.05)


def _previous_window_settled(estimates: list[float], window: int, tol: float) -> bool:
    """The rule not taken: the mean of the last ``window`` points against the mean of the ``window`` points before
    them (a fixed look-back, where :func:`torchrl_bail.ope.curve_converged` looks back to half the fit)."""
    n = len(estimates)
    if window < 1 or n < 2 * window:
        return False
    last, before = sum(estimates[n - window:]) / window, sum(estimates[n - 2 * window:n - window]) / window
    return abs(last - before) < tol * abs(last)


def curve_measurement() -> dict:
    """The stopping rule and the number of fits, measured on the kept fits' curves (every ``runs/**/ope*.json``:
    20 final policies and 20 BAIL snapshots, one fit each of 10^5 updates, a point every 1000).

    For each rule, window and tolerance: how many curves it stops before their end, where, and how far the estimate
    where it stops lies from the curve's last value. And the mini-batch noise of a curve: the standard deviation of
    its last 20 points around their least-squares line, relative to their mean, from which the default number of
    fits follows (:data:`torchrl_bail.ope.DEFAULT_FITS`)."""
    import math

    import numpy as np

    from torchrl_bail.ope import FQESettings, curve_converged

    curves = {}
    for path in sorted((HERE / "runs").rglob("ope*.json")):
        record = json.loads(path.read_text())
        if record.get("curve"):
            curves[path.relative_to(HERE / "runs").as_posix()] = [p["estimate"] for p in record["curve"]]
    log_every = 1000
    rules = {"half_the_fit": curve_converged, "previous_window": _previous_window_settled}
    measured = []
    for name, rule in rules.items():
        for window in WINDOWS:
            for tol in TOLERANCES:
                stops = {}
                for key, curve in curves.items():
                    n = next((n for n in range(1, len(curve)) if rule(curve[:n], window, tol)), None)
                    if n is not None:
                        stops[key] = {"update": n * log_every,
                                      "from_last": abs(curve[n - 1] - curve[-1]) / abs(curve[-1])}
                measured.append({"rule": name, "window": window, "tol": tol, "curves": len(curves),
                                 "stopped": len(stops), "stops": stops,
                                 "max_from_last": max((s["from_last"] for s in stops.values()), default=None)})
    noise = []
    for curve in curves.values():
        y = np.asarray(curve[-20:])
        x = np.arange(len(y))
        residual = y - np.polyval(np.polyfit(x, y, 1), x)
        noise.append(float(residual.std(ddof=2) / abs(y.mean())))
    rises = [(curve[-1] - curve[len(curve) // 2 - 1]) / abs(curve[-1]) for curve in curves.values()]
    tol = FQESettings.stop_tol
    median_noise = float(np.median(noise))
    return {"curves": len(curves), "updates": 100_000, "log_every": log_every,
            "rise_over_the_second_half": {"min": min(rises), "median": float(np.median(rises)), "max": max(rises)},
            "rules": measured,
            "noise": {"median": median_noise, "min": min(noise), "max": max(noise)},
            "fits_for_half_the_tolerance": math.ceil((median_noise / (tol / 2)) ** 2)}


def _fqe_record(entry: dict, iteration: int | None = None) -> dict:
    """What the selection rules read from a kept FQE record: ``{fqe_estimate, fqe_spread, num_fits, action_gap}``.

    The final policy's is its run's ``ope.json``; a snapshot's its ``snapshots/ope_policy_<iteration>.json``, except
    the last snapshot's, the final policy's weights, which took the final policy's fit. The spread is ``None`` for a
    record of one fit (every kept record so far; a refit with ``--fits`` of 2 or more records it), the gap ``None``
    for a record fitted before ``ope`` recorded gaps (BAIL seed 1's snapshots: their weights are not kept to compute
    it)."""
    path = ROOT / entry["run"] / "snapshots" / f"ope_policy_{iteration}.json"
    if iteration is None or not path.is_file():
        path = ROOT / entry["run"] / "ope.json"
    record = json.loads(path.read_text())
    return {"fqe_estimate": record["estimate"], "fqe_spread": record.get("spread"),
            "num_fits": record.get("num_fits", 1), "action_gap": record.get("action_gap")}


def _rank(estimates: list[float], truths: list[float], names: list[str]) -> dict:
    from torchrl_bail.ope import ranking_quality, spearman_interval

    q = ranking_quality(estimates, truths)
    low, high = spearman_interval(estimates, truths)
    return {"spearman": q["spearman"], "spearman_ci": [low, high], "selected": names[q["selected"]],
            "best": names[q["best"]], "regret": q["regret"]}


#: gap_penalised's lambda swept on the 20 final policies (in-sample: the default, 1, is set before looking)
LAMBDAS = (0.5, 1.0, 2.0, 3.0, 4.0)


def _rules(means, gaps, truths: dict, names: list[str], lam: float, interval: bool = True, spreads=None) -> dict:
    """:func:`torchrl_bail.ope.compare_rules` (``lower_bound`` is unavailable without every spread: single fits),
    with the selected policy named and its true values."""
    from torchrl_bail.ope import compare_rules

    report = compare_rules(means, truths, spreads=spreads, gaps=gaps, lam=lam, interval=interval)
    for entry in report.values():
        if entry["available"]:
            entry["selected_name"] = names[entry["selected"]]
            entry.pop("scores")
            for name, values in truths.items():
                entry[name]["selected_value"] = values[entry["selected"]]
                entry[name]["best_name"] = names[entry[name]["best"]]
    return report


def analyse(policies: list[dict], snapshots: list[dict]) -> dict:
    """Rank figures of the single-fit estimates against both truths, and each selection rule's ranking of the 20
    final policies and of each BAIL run's snapshots (the rules that single fits allow: ``mean`` and
    ``gap_penalised``; ``lower_bound`` needs several fits per policy)."""
    from torchrl_bail.ope import DEFAULT_LAMBDA

    names = [p["job"] for p in policies]
    estimates = [p["fqe_estimate"] for p in policies]
    spreads = [p["fqe_spread"] for p in policies]
    gaps = [p["action_gap"] for p in policies]
    truths = {"discounted": [p["true_discounted_return"] for p in policies],
              "undiscounted": [p["true_return"] for p in policies]}
    sweep = {str(lam): {rule: {truth: {key: entry[truth][key] for key in ("spearman", "regret")} for truth in truths}
                        for rule, entry in _rules(estimates, gaps, truths, names, lam, interval=False).items()
                        if rule == "gap_penalised"}["gap_penalised"] for lam in LAMBDAS}
    per_run = []
    for run in snapshots:
        c = run["candidates"]
        report = _rules([x["fqe_estimate"] for x in c], [x["action_gap"] for x in c],
                        {"undiscounted": [x["true_return"] for x in c]}, [str(x["iteration"]) for x in c],
                        DEFAULT_LAMBDA, interval=False, spreads=[x["fqe_spread"] for x in c])
        per_run.append({"job": run["job"], "best_return": max(x["true_return"] for x in c),
                        "final_return": c[-1]["true_return"],
                        "rules": {rule: {"selected_iteration": int(entry["selected_name"]),
                                         "selected_return": entry["undiscounted"]["selected_value"],
                                         "regret": entry["undiscounted"]["regret"],
                                         "spearman": entry["undiscounted"]["spearman"]}
                                  for rule, entry in report.items() if entry["available"]}})
    def summary(runs: list[dict], rule: str) -> dict:
        return {"runs": [r["job"] for r in runs],
                "mean_selected_return": sum(r["rules"][rule]["selected_return"] for r in runs) / len(runs),
                "mean_regret": sum(r["rules"][rule]["regret"] for r in runs) / len(runs),
                "mean_spearman": sum(r["rules"][rule]["spearman"] for r in runs) / len(runs),
                "mean_final_return": sum(r["final_return"] for r in runs) / len(runs),
                "mean_best_return": sum(r["best_return"] for r in runs) / len(runs)}

    # each rule over the runs where both can score every snapshot; the mean rule also over every run
    common = [r for r in per_run if {"mean", "gap_penalised"} <= set(r["rules"])]
    snapshot_summary = {"mean": summary(common, "mean"), "gap_penalised": summary(common, "gap_penalised"),
                        "mean_every_run": summary(per_run, "mean")}
    return {"single_fit": {
                "against_discounted": _rank(estimates, truths["discounted"], names),
                "against_undiscounted": _rank(estimates, truths["undiscounted"], names)},
            "rules": {"lambda": DEFAULT_LAMBDA,
                      "final_policies": _rules(estimates, gaps, truths, names, DEFAULT_LAMBDA, spreads=spreads),
                      "gap_penalised_lambda_sweep": sweep,
                      "snapshots": {"per_run": per_run, "mean_over_runs": snapshot_summary}},
            "fits_per_policy": sorted({p["num_fits"] for p in policies}),
            **({} if all(s is not None for s in spreads) else {
                "lower_bound": "not computed: it needs several fits per policy (--fits >= 2), and a kept policy has "
                               "one fit; the refits need the headline batch (10^6 transitions), not on this machine"})}


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
        fqe = _fqe_record(entry)
        policies.append({
            "job": entry["job"], "algo": entry["algo"], "seed": entry["seed"], "run": entry["run"],
            "true_return": rep["recorded_return"], "true_discounted_return": truth_discounted, **fqe,
            "estimate_over_discounted_truth": fqe["fqe_estimate"] / truth_discounted - 1.0,
            "replay": rep})
        if entry.get("snapshots"):
            snapshots.append({"job": entry["job"], "candidates": [
                {"iteration": c["iteration"], "true_return": c["eval_return"], "true_discounted_return": None,
                 **_fqe_record(entry, c["iteration"])} for c in entry["snapshots"]["candidates"]]})
    return {"gamma": FQESettings.gamma, "source": "results/ope_headline/ope.json (the policies, their recorded "
            "returns and snapshots), each run's FQE records under runs/ (estimate, spread, action gap) and each kept "
            "policy.pt, its last evaluation replayed",
            "command": "python results/ope_headline/truth.py",
            "snapshot_note": "the BAIL runs' snapshot weights were not kept (runs/**/snapshots holds their FQE "
                             "records only): each snapshot has its recorded undiscounted evaluation return and no "
                             "discounted truth",
            "policies": policies, "snapshots": snapshots, "ranking": analyse(policies, snapshots),
            "curves": curve_measurement()}


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
    for rule, entry in record["ranking"]["rules"]["final_policies"].items():
        if not entry["available"]:
            print(f"rule {rule}: not available ({entry['reason']})")
            continue
        print(f"rule {rule}: deploys {entry['selected_name']}; " + "; ".join(
            f"{truth} rho {entry[truth]['spearman']:.2f} [{entry[truth]['spearman_ci'][0]:.2f}, "
            f"{entry[truth]['spearman_ci'][1]:.2f}] regret {entry[truth]['regret']:.1f}"
            for truth in ("discounted", "undiscounted")))
    print(f"-> {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

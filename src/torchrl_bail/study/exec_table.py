"""The execution-batch report (the ``paper_exec`` study): supp. Table 2 of arXiv:1910.12179 at the paper's scale, and
the SAC rows of its Table 1.

``table2.{md,json}`` (:func:`exec_table_report`): per env the SAC training batch (a Table 1 row) and its four
execution batches (M σ = 0, M σ = σ(s), O σ = 0, O σ = σ(s): the SAC run's mediocre and final policies, without and
with noise), each with its data's mean episode return and its behaviour policy's return from the batch's kept
metadata, each algorithm's mean ± std beside the paper's figure and its IQM [95 % CI]; a verdict per claim of
Table 2 (:func:`exec_claims`); the rows each algorithm wins and how each row orders the algorithms against the
paper's (:func:`exec_rankings`); the SAC behaviour runs' pace and learning curves (:func:`sac_run_summary`,
``sac_runs.png``). ``curves_<batch>.png``: each batch's learning curves.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from torchrl_bail.configuration.hydra_setup import config_dir
from torchrl_bail.core.io import write_json_atomic, write_text_atomic
from torchrl_bail.reports.plots import new_figure, save_figure
from torchrl_bail.study.declaration import Study, StudyJob, load_study
from torchrl_bail.study.tables import (
    CURVE_WINDOW_UPDATES,
    HIERARCHICAL_BOOTSTRAP,
    MIN_SEEDS_FOR_VERDICT,
    batch_rows,
    bootstrap_sentence,
    bootstrap_settings,
    claim_verdict,
    fmt,
    improvement,
    improvement_lines,
    interval_order,
    iqm_table,
    mean_cell,
    plot_batch_curves,
    reference_row,
    shown_path,
)

#: the execution-batch study (``paper_exec``): per env in turn, the 10^6-step SAC run (its ``sac``
#: training batch) and its four execution batches of supp. Table 2 (B1, 10^6 transitions each), then on each of those
#: five batches :data:`PAPER_EXEC_CELLS` at the paper-scale schedules; Hopper's batches complete before Walker2d's start
PAPER_EXEC_ENVS = ("hopper", "walker")
PAPER_EXEC_KINDS = ("sac", "med_det", "med_stoch", "opt_det", "opt_stoch")
PAPER_EXEC_CELLS = [("bail", 3), ("bc", 3), ("marwil", 3), ("bcq", 3)]

#: supp. Table 2, arXiv:1910.12179: the authors' final returns on the 40 SAC execution batches (gym -v2 envs, mean ±
#: std over seeds), as ``(env, kind, batch index, *cells)``, the cells in :data:`PAPER_TABLE2_COLUMNS`' order (the
#: table's own); kinds as this package names the batches: med_det = M σ = 0, med_stoch = M σ = σ(s), opt_det = O
#: σ = 0, opt_stoch = O σ = σ(s) (:data:`EXEC_KINDS`)
PAPER_TABLE2_COLUMNS = ("bail", "bcq", "bear", "bc", "marwil")
_PAPER_TABLE2_ROWS = [
    ("hopper", "med_det", 1, (1026, 0), (901, 132), (4, 1), (1026, 0), (1026, 0)),
    ("hopper", "med_det", 2, (696, 233), (805, 312), (19, 23), (977, 0), (977, 1)),
    ("walker", "med_det", 1, (437, 20), (525, 45), (380, 194), (444, 16), (439, 17)),
    ("walker", "med_det", 2, (500, 12), (554, 29), (546, 28), (489, 15), (504, 4)),
    ("halfcheetah", "med_det", 1, (4057, 69), (4255, 150), (4470, 96), (4032, 72), (4073, 55)),
    ("halfcheetah", "med_det", 2, (4013, 12), (4438, 25), (4395, 31), (3998, 4), (3999, 6)),
    ("ant", "med_det", 1, (753, 9), (996, 52), (734, 43), (730, 7), (732, 11)),
    ("ant", "med_det", 2, (738, 4), (994, 12), (988, 30), (708, 11), (725, 7)),
    ("humanoid", "med_det", 1, (4313, 139), (3108, 510), (0, 0), (4507, 481), (4521, 156)),
    ("humanoid", "med_det", 2, (4053, 252), (2906, 226), (0, 0), (3994, 530), (3940, 165)),
    ("hopper", "med_stoch", 1, (375, 52), (881, 155), (0, 0), (1026, 0), (1026, 0)),
    ("hopper", "med_stoch", 2, (254, 102), (961, 25), (3, 7), (977, 0), (977, 0)),
    ("walker", "med_stoch", 1, (384, 21), (399, 21), (507, 7), (369, 10), (359, 15)),
    ("walker", "med_stoch", 2, (512, 24), (517, 19), (515, 30), (527, 12), (532, 5)),
    ("halfcheetah", "med_stoch", 1, (4744, 19), (5500, 12), (5443, 21), (4415, 25), (4439, 59)),
    ("halfcheetah", "med_stoch", 2, (4123, 19), (4712, 40), (4824, 51), (3928, 18), (3936, 18)),
    ("ant", "med_stoch", 1, (790, 9), (1068, 12), (1161, 32), (775, 7), (774, 15)),
    ("ant", "med_stoch", 2, (781, 6), (1089, 29), (1150, 18), (768, 5), (761, 6)),
    ("humanoid", "med_stoch", 1, (1375, 387), (489, 87), (0, 0), (1947, 901), (1963, 264)),
    ("humanoid", "med_stoch", 2, (1309, 372), (816, 177), (0, 0), (3021, 1042), (2976, 241)),
    ("hopper", "opt_det", 1, (2602, 5), (1976, 383), (1904, 321), (2594, 8), (2603, 4)),
    ("hopper", "opt_det", 2, (3046, 34), (3014, 47), (2202, 410), (3071, 10), (3050, 22)),
    ("walker", "opt_det", 1, (2735, 26), (2409, 235), (877, 1077), (2646, 133), (2691, 121)),
    ("walker", "opt_det", 2, (3019, 6), (3019, 45), (0, 0), (3014, 5), (3013, 5)),
    ("halfcheetah", "opt_det", 1, (11265, 243), (10405, 275), (1755, 1142), (11674, 90), (11661, 49)),
    ("halfcheetah", "opt_det", 2, (11360, 265), (10792, 209), (1139, 960), (11797, 29), (11691, 96)),
    ("ant", "opt_det", 1, (4901, 65), (4646, 179), (1756, 2151), (4881, 74), (4933, 74)),
    ("ant", "opt_det", 2, (4975, 108), (4734, 100), (0, 0), (5041, 29), (4974, 52)),
    ("humanoid", "opt_det", 1, (4872, 895), (4884, 641), (0, 0), (5462, 124), (5503, 1)),
    ("humanoid", "opt_det", 2, (5320, 125), (5362, 54), (0, 0), (5413, 64), (5413, 29)),
    ("hopper", "opt_stoch", 1, (2359, 153), (2650, 99), (1962, 300), (1952, 85), (2012, 101)),
    ("hopper", "opt_stoch", 2, (2035, 217), (1678, 113), (1461, 75), (2063, 95), (2092, 100)),
    ("walker", "opt_stoch", 1, (2834, 120), (3386, 196), (3278, 128), (2024, 131), (1987, 114)),
    ("walker", "opt_stoch", 2, (3200, 16), (3375, 12), (2100, 1715), (3091, 15), (3090, 10)),
    ("halfcheetah", "opt_stoch", 1, (10258, 1255), (10928, 215), (694, 651), (11659, 75), (11663, 44)),
    ("halfcheetah", "opt_stoch", 2, (10882, 634), (11755, 97), (1470, 1211), (11871, 57), (11819, 78)),
    ("ant", "opt_stoch", 1, (4981, 91), (4878, 117), (3462, 1740), (5000, 79), (4992, 86)),
    ("ant", "opt_stoch", 2, (5067, 83), (5054, 157), (0, 0), (5079, 55), (5124, 47)),
    ("humanoid", "opt_stoch", 1, (2129, 381), (1715, 637), (0, 0), (3514, 1195), (3180, 503)),
    ("humanoid", "opt_stoch", 2, (4328, 569), (1970, 512), (0, 0), (4875, 885), (4772, 272)),
]

PAPER_TABLE2 = {(env, kind, index): dict(zip(PAPER_TABLE2_COLUMNS, cells, strict=True))
                for env, kind, index, *cells in _PAPER_TABLE2_ROWS}

#: the BAIL authors' BAIL on the SAC training batches of this study (their repository's README table, the paper's
#: Table 1 BAIL column; gym -v2, mean ± std over seeds); no other algorithm's figure on these batches is published
#: where this project could read it
PAPER_SAC_BAIL = {("hopper", "sac", 1): {"bail": (3296, 105)}, ("walker", "sac", 1): {"bail": (2455, 211)}}

#: each kind of :data:`PAPER_EXEC_KINDS` as the paper's tables name its rows
EXEC_KINDS = {"sac": "SAC training batch (Table 1)", "med_det": "M σ = 0", "med_stoch": "M σ = σ(s)",
              "opt_det": "O σ = 0", "opt_stoch": "O σ = σ(s)"}

#: the report's columns: the study's cells (:data:`PAPER_EXEC_CELLS`) in the paper's order, then BEAR (shown once a
#: run of it is kept)
EXEC_CENTRAL = tuple(a for a in PAPER_TABLE2_COLUMNS if a in dict(PAPER_EXEC_CELLS))
EXEC_ALGOS = (*EXEC_CENTRAL, *(a for a in PAPER_TABLE2_COLUMNS if a not in EXEC_CENTRAL))

#: how the report names each algorithm in a claim
ALGO_NAMES = {"bail": "BAIL", "bcq": "BCQ", "bc": "BC", "marwil": "MARWIL", "bear": "BEAR"}

#: the probabilities of improvement over every execution batch: P(first > second)
EXEC_PAIRS = [("bail", "bcq"), ("bc", "bail"), ("marwil", "bc")]

#: supp. E's reading of Table 2: the algorithms with the most wins
PAPER_MOST_WINS = ("bc", "marwil")

#: the keys of an execution batch's metadata that the report keeps (no machine's paths)
EXEC_METADATA_KEYS = ("episode_return_mean", "episode_return_std", "episode_return_min", "episode_return_max",
                      "num_episodes", "num_transitions", "behaviour_return", "behaviour_final_eval_return",
                      "collection_wall_time_s", "env_id", "recipe_hash")
EXEC_POLICY_KEYS = ("which", "stochastic", "eval_step", "eval_return_mean", "eval_return_std", "mediocre_threshold",
                    "threshold_reached")


def exec_batches() -> list[tuple[str, str]]:
    """The report's rows as ``(env, kind)``: per env of :data:`PAPER_EXEC_ENVS`, its SAC training batch, then its
    execution batches in :data:`PAPER_EXEC_KINDS`' order (all B1)."""
    return [(env, kind) for env in PAPER_EXEC_ENVS for kind in PAPER_EXEC_KINDS]


def _paper_figure(pair: tuple[int, int] | None) -> str:
    return "" if pair is None else f"{pair[0]} ± {pair[1]}"


def _behaviour_return(batch: dict) -> float | None:
    """The return of a batch's behaviour policy from its kept metadata: an execution batch's ``behaviour_return``
    (the SAC policy it runs, as the SAC run evaluated it), the SAC training batch's ``behaviour_final_eval_return``
    (the SAC run's final evaluation: the batch is that whole run); ``None`` while no metadata is kept."""
    meta = batch["metadata"] or {}
    return meta.get("behaviour_final_eval_return" if batch["kind"] == "sac" else "behaviour_return")


def _gap(a: dict | None, b: dict | None) -> float | None:
    """``a``'s IQM against ``b``'s, in % of ``b``'s (``None`` while either has too few seeds)."""
    if a is None or b is None or (not a.get("reference") and a.get("seeds", 0) < MIN_SEEDS_FOR_VERDICT) or (
            not b.get("reference") and b.get("seeds", 0) < MIN_SEEDS_FOR_VERDICT) or not b["final_return_iqm"]:
        return None
    return 100.0 * (a["final_return_iqm"] - b["final_return_iqm"]) / abs(b["final_return_iqm"])


def exec_claims(batches: list[dict]) -> list[dict]:
    """supp. Table 2's claims (and Table 1's on the SAC training batches), each read on the batches it concerns by
    the paper cell's rule (:func:`claim_verdict`, :data:`MIN_SEEDS_FOR_VERDICT` seeds a side): on each O σ = 0 batch,
    BAIL, BC and MARWIL ≈ the behaviour policy (its return a fixed figure, :func:`reference_row`: the claim holds
    where the IQM interval contains it); on Hopper M σ = σ(s), BAIL below BC; on every execution batch MARWIL ≈ BC;
    on each SAC training batch BAIL ≫ BC. Each with the first side's IQM against the second's (``gap``, %)."""
    claims = []

    def claim(batch, text, a, b, kind):
        verdict = ("pending (the batch's metadata, with its behaviour policy's return, is not kept yet)"
                   if b is None and text.endswith("behaviour policy") else claim_verdict(a, b, kind))
        claims.append({"batch": batch["batch"], "claim": text, "verdict": verdict, "gap": _gap(a, b)})

    for batch in batches:
        cells = batch["cells"]
        if batch["kind"] == "opt_det":
            behaviour = _behaviour_return(batch)
            for algo in ("bail", "bc", "marwil"):
                claim(batch, f"{ALGO_NAMES[algo]} ≈ the behaviour policy", cells.get(algo),
                      None if behaviour is None else reference_row(behaviour), "similar")
        if (batch["env"], batch["kind"]) == ("hopper", "med_stoch"):
            claim(batch, "BAIL below BC", cells.get("bail"), cells.get("bc"), "below")
        if batch["kind"] == "sac":
            claim(batch, "BAIL ≫ BC (Table 1)", cells.get("bail"), cells.get("bc"), "above")
        else:
            claim(batch, "MARWIL ≈ BC", cells.get("marwil"), cells.get("bc"), "similar")
    return claims


def _ready_cells(cells: dict[str, dict]) -> dict[str, dict] | None:
    """The cells of an execution batch that a ranking reads, those with :data:`MIN_SEEDS_FOR_VERDICT` seeds (BEAR
    where it has them), or ``None`` while any of :data:`EXEC_CENTRAL` has fewer."""
    ready = {a: cells[a] for a in EXEC_ALGOS if cells.get(a, {}).get("seeds", 0) >= MIN_SEEDS_FOR_VERDICT}
    return ready if all(a in ready for a in EXEC_CENTRAL) else None


def row_winners(cells: dict[str, dict]) -> list[str] | None:
    """The algorithms that win an execution batch: the best IQM and every one whose IQM interval overlaps the best's
    (:func:`interval_order`: a tie, no difference shown); ``None`` while the batch is not ready
    (:func:`_ready_cells`)."""
    ready = _ready_cells(cells)
    if ready is None:
        return None
    best = max(ready, key=lambda a: ready[a]["final_return_iqm"])
    return [a for a in ready if a == best or not interval_order(ready[a], ready[best]).startswith("below")]


def paper_winners(paper: dict[str, tuple[int, int]], algos) -> list[str]:
    """The algorithms of ``algos`` with the best mean of a supp. Table 2 row (ties: equal means)."""
    best = max(paper[a][0] for a in algos)
    return [a for a in algos if paper[a][0] == best]


def _sign(x: float) -> int:
    return (x > 0) - (x < 0)


def row_ordering(cells: dict[str, dict], paper: dict[str, tuple[int, int]]) -> dict:
    """How an execution batch orders its algorithms (IQM) against supp. Table 2's row (means): Kendall's tau-b over
    the algorithms with :data:`MIN_SEEDS_FOR_VERDICT` seeds (``scipy.stats.kendalltau``; ``None`` where one side ties
    them all), and the row's pairs counted concordant, discordant and tied (either side equal); pending while the
    batch is not ready (:func:`_ready_cells`)."""
    from scipy.stats import kendalltau

    ready = _ready_cells(cells)
    if ready is None:
        return {"algorithms": [], "tau": None, "pairs": None, "reading": "pending"}
    algos = list(ready)
    ours = [ready[a]["final_return_iqm"] for a in algos]
    theirs = [paper[a][0] for a in algos]
    tau = float(kendalltau(ours, theirs).statistic)
    tau = None if not np.isfinite(tau) else tau
    signs = [_sign(ours[i] - ours[j]) * _sign(theirs[i] - theirs[j])
             for i in range(len(algos)) for j in range(i + 1, len(algos))]
    pairs = {"concordant": signs.count(1), "discordant": signs.count(-1), "tied": signs.count(0)}
    reading = ("undefined (one side ties every algorithm)" if tau is None else "the same order" if tau == 1.0
               else "agrees in part" if tau > 0 else "does not agree")
    return {"algorithms": algos, "ours": sorted(algos, key=lambda a: -ready[a]["final_return_iqm"]),
            "paper": sorted(algos, key=lambda a: -paper[a][0]), "tau": tau, "pairs": pairs, "reading": reading}


def exec_rankings(batches: list[dict]) -> dict:
    """Over the execution batches: each one's winners (:func:`row_winners`) beside the paper's on its supp. Table 2
    row among the same algorithms (:func:`paper_winners`) and the two orderings (:func:`row_ordering`); the count of
    rows each algorithm wins, ours, the paper's on the same rows and the paper's over its 40 rows (all five
    algorithms); the verdict on supp. E's "BC and MARWIL win the most rows" (holds where the most wins go to them
    alone); the orderings over all rows (Kendall's tau-a over every row's pairs pooled: (concordant - discordant) /
    pairs); and the probabilities of improvement of :data:`EXEC_PAIRS` over the batches (:func:`improvement`, raw
    returns) with the verdict on "BAIL ≈ BCQ on average" (holds where P(BAIL > BCQ)'s interval contains 0.5)."""
    rows = []
    for batch in batches:
        winners = row_winners(batch["cells"])
        ordering = row_ordering(batch["cells"], batch["paper"])
        rows.append({"batch": batch["batch"], "winners": winners,
                     "paper_winners": None if winners is None else paper_winners(batch["paper"],
                                                                                 ordering["algorithms"]),
                     "ordering": ordering})
    ready = [r for r in rows if r["winners"] is not None]
    wins = {a: {"ours": sum(a in r["winners"] for r in ready), "paper_same_rows": sum(a in r["paper_winners"]
                                                                                      for r in ready),
                "paper_all_rows": sum(a in paper_winners(p, PAPER_TABLE2_COLUMNS) for p in PAPER_TABLE2.values())}
            for a in EXEC_ALGOS}
    if len(ready) < len(rows):
        most, verdict = [], f"pending ({len(ready)} of {len(rows)} execution batches ranked)"
    else:
        top = max(w["ours"] for w in wins.values())
        most = [a for a, w in wins.items() if w["ours"] == top]
        holds = set(most) <= set(PAPER_MOST_WINS)
        verdict = (f"{'holds' if holds else 'does not hold'} (the most wins, {top} of {len(rows)}: "
                   f"{', '.join(ALGO_NAMES[a] for a in most)})")
    pooled = {k: sum(r["ordering"]["pairs"][k] for r in rows if r["ordering"]["pairs"] is not None)
              for k in ("concordant", "discordant", "tied")}
    n_pairs = sum(pooled.values())
    pairs = [improvement(batches, a, b, normalised=False) for a, b in EXEC_PAIRS]
    average = pairs[0]
    if average["reading"].startswith("pending"):
        average_verdict = average["reading"]
    else:
        holds = average["reading"].startswith("no difference shown")
        average_verdict = (f"{'holds' if holds else 'does not hold'} (P(BAIL > BCQ) = {fmt(average['p'], 2)} "
                           f"[{fmt(average['ci_low'], 2)}, {fmt(average['ci_high'], 2)}]: {average['reading']})")
    same_rows = [(b["env"], b["kind"], 1) for b in batches]
    paper_means = {a: {"same_rows": float(np.mean([PAPER_TABLE2[k][a][0] for k in same_rows])),
                       "all_rows": float(np.mean([p[a][0] for p in PAPER_TABLE2.values()]))}
                   for a in PAPER_TABLE2_COLUMNS}
    return {"rows": rows, "ranked": len(ready), "wins": wins, "most_wins": most, "most_wins_verdict": verdict,
            "ordering": {"rows": sum(r["ordering"]["tau"] is not None for r in rows),
                         "same_order": sum(r["ordering"]["tau"] == 1.0 for r in rows), **pooled,
                         "tau_pooled": None if not n_pairs else (pooled["concordant"] - pooled["discordant"])
                         / n_pairs},
            "probability_of_improvement": pairs, "average_verdict": average_verdict, "paper_means": paper_means}


def _exec_row_cells(batch: dict, algos: list[str]) -> list[str]:
    """A row's mean ± std cells with the paper's figure beside each (none published: the cell alone)."""
    out = []
    for a in algos:
        figure = _paper_figure(batch["paper"].get(a))
        out.append(mean_cell(batch["cells"].get(a)) + (f"; paper {figure}" if figure else ""))
    return out


def _behaviour_cell(batch: dict) -> str:
    value = _behaviour_return(batch)
    if value is None:
        return "pending"
    policy = (batch["metadata"] or {}).get("behaviour_policy") or {}
    note = ("SAC run's final evaluation" if batch["kind"] == "sac" else
            f"{policy.get('which', '')} policy at step {policy['eval_step']:,}" if policy.get("eval_step") else "")
    if policy.get("threshold_reached") is False:
        note += f"; threshold {fmt(policy.get('mediocre_threshold'), 0)} not reached: the best evaluation"
    return fmt(value) + (f" ({note})" if note else "")


def sac_run_summary(env: str, metadata: dict | None) -> dict | None:
    """What the report says of an env's SAC behaviour run, from its ``sac`` training batch's kept metadata (the batch is
    the run's first 10^6 transitions and its metadata carries the run's evaluations): its pace (env steps and updates
    per second, evaluations included in the first), its learning curve, the first evaluation at or above the env's
    mediocre threshold (``conf/env/<env>.yaml``: the mediocre behaviour policy of the ``med_*`` batches) and its final
    evaluation (the optimal policy of the ``opt_*`` batches); ``None`` until the metadata is kept."""
    if metadata is None or not metadata.get("evaluations"):
        return None
    threshold = float(OmegaConf.load(config_dir() / "env" / f"{env}.yaml").mediocre_threshold)
    curve = [(int(e["step"]), float(e["return_mean"])) for e in metadata["evaluations"]]
    crossed = next(((step, ret) for step, ret in curve if ret >= threshold), None)
    return {"env": env, "env_steps": metadata.get("sac_run_train_steps"),
            "gradient_steps": metadata.get("gradient_steps"),
            "env_steps_per_s": metadata.get("env_steps_per_s"), "updates_per_s": metadata.get("updates_per_s"),
            "resumed_from_step": metadata.get("resumed_from_step"), "mediocre_threshold": threshold,
            "crossed_at_step": None if crossed is None else crossed[0],
            "crossed_with_return": None if crossed is None else crossed[1],
            "final_eval_return": metadata.get("behaviour_final_eval_return"),
            "best_eval_return": max(ret for _, ret in curve), "curve": curve}


def plot_sac_runs(runs: list[dict], path: Path) -> Path | None:
    """One figure of the SAC behaviour runs (:func:`sac_run_summary`): each env's evaluation return against env steps,
    its mediocre threshold as a dashed line and the evaluation that crossed it marked; ``None`` without a run."""
    if not runs:
        return None
    fig = new_figure(figsize=(7.0, 4.2), layout="constrained")
    ax = fig.subplots()
    for run in runs:
        steps, returns = zip(*run["curve"], strict=True)
        label = f"{run['env']} (final {run['final_eval_return']:.0f})"
        (line,) = ax.plot(np.asarray(steps) / 1e6, returns, label=label)
        ax.axhline(run["mediocre_threshold"], color=line.get_color(), linestyle="--", linewidth=0.8)
        if run["crossed_at_step"] is not None:
            ax.plot([run["crossed_at_step"] / 1e6], [run["crossed_with_return"]], "o", color=line.get_color())
    ax.set_xlabel("env steps (millions)")
    ax.set_ylabel("evaluation return (10 deterministic episodes)")
    ax.set_title("SAC behaviour runs: dashed, the mediocre threshold; dot, the mediocre policy")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    return save_figure(fig, path)


def _sac_run_lines(runs: list[dict], figure: Path | None) -> list[str]:
    """The Table 2 report's SAC-runs paragraph and table (:func:`sac_run_summary`)."""
    lines = ["", "The SAC behaviour runs (one per env, B1: the training batch is the run's first 10^6 transitions, the "
             "execution batches run its mediocre and final policies), from each SAC batch's kept metadata:", "",
             "| env | env steps | env steps/s | updates/s | mediocre threshold | first evaluation at or above it "
             "(step: return) | final evaluation | best evaluation |", "|---|---|---|---|---|---|---|---|"]
    for r in runs:
        crossed = ("never" if r["crossed_at_step"] is None
                   else f"{r['crossed_at_step']:,}: {r['crossed_with_return']:.1f}")
        lines.append(f"| {r['env']} | {r['env_steps']:,} | {fmt(r['env_steps_per_s'])} | {fmt(r['updates_per_s'])} | "
                     f"{r['mediocre_threshold']:g} | {crossed} | {fmt(r['final_eval_return'])} | "
                     f"{fmt(r['best_eval_return'])} |")
    if not runs:
        lines.append("| pending | | | | | | | |")
    lines += ["", "Pace: one core, `threads=1`, evaluations (10 deterministic episodes every 5000 steps) included in "
              "env steps/s; a run resumed from a checkpoint counts from its restart. "
              + (f"Figure: `{figure.name}`." if figure is not None else "Figure: none yet.")]
    return lines


def exec_table_report(results: Path, jobs: list[StudyJob] | None = None) -> dict:
    """``results/table2.{md,json}`` and ``results/curves_<batch>.png`` of the execution-batch study (``jobs``: its jobs,
    default the declared ``paper_exec`` study's; kept runs and batch metadata in ``results``), supp. Table 2 style: one
    row per batch (:func:`exec_batches`: each env's SAC training batch as a Table 1 row, then its four execution
    batches) with the batch's mean episode return and its behaviour policy's return (:func:`_behaviour_return`) from its
    kept metadata, each algorithm's mean ± std beside the paper's figure (:data:`PAPER_TABLE2`, :data:`PAPER_SAC_BAIL`)
    and its IQM [95 % CI]; a verdict per claim (:func:`exec_claims`); the rows each algorithm wins and how each row
    orders the algorithms against the paper's (:func:`exec_rankings`). A cell without its seeds, a batch without
    metadata, reads "pending"; reads kept files only, so ``--report-only`` rebuilds it at any stage. Returns the JSON
    written."""
    jobs = load_study("paper_exec").jobs if jobs is None else jobs
    batches, sac_runs = [], []
    for env, kind in exec_batches():
        label = f"{env}_{kind}_b1"
        cells, meta_path, metadata, rows = batch_rows(results, jobs, label, EXEC_ALGOS)
        if kind == "sac" and (run := sac_run_summary(env, metadata)) is not None:
            sac_runs.append(run)
        complete = metadata is not None and all(rows.get(a, {}).get("seeds", 0) >= rows[a]["scheduled"]
                                                for a in EXEC_CENTRAL if a in rows)
        figure = plot_batch_curves(label, cells, metadata, results / f"curves_{label}.png", EXEC_ALGOS)
        kept = None if metadata is None else {k: metadata.get(k) for k in EXEC_METADATA_KEYS}
        if kept is not None and isinstance(metadata.get("behaviour_policy"), dict):
            kept["behaviour_policy"] = {k: metadata["behaviour_policy"].get(k) for k in EXEC_POLICY_KEYS}
        batches.append({"batch": label, "env": env, "kind": kind, "row": EXEC_KINDS[kind],
                        "paper": (PAPER_SAC_BAIL if kind == "sac" else PAPER_TABLE2).get((env, kind, 1), {}),
                        "metadata_file": None if meta_path is None else shown_path(meta_path), "metadata": kept,
                        "complete": complete, "cells": rows, "figure": None if figure is None else figure.name})
    for b in batches:
        b["behaviour_return"] = _behaviour_return(b)
    claims = exec_claims(batches)
    rankings = exec_rankings([b for b in batches if b["kind"] != "sac"])
    done = [b["batch"] for b in batches if b["complete"]]
    status = ("Batches complete (every cell at its seeds: "
              + ", ".join(f"{a} x {dict(PAPER_EXEC_CELLS)[a]}" for a in EXEC_CENTRAL)
              + f"; the batch's metadata kept): {len(done)} of {len(batches)}" + (f" ({', '.join(done)})" if done
                                                                                 else "") + ".")
    algos = [*EXEC_CENTRAL, *(a for a in EXEC_ALGOS if a not in EXEC_CENTRAL
                              and any(b["cells"].get(a, {}).get("seeds") for b in batches))]
    out = {"status": status, "complete_batches": done, "min_seeds_for_verdict": MIN_SEEDS_FOR_VERDICT,
           "bootstrap": {**bootstrap_settings(), "across_batches": HIERARCHICAL_BOOTSTRAP},
           "batches": batches, "claims": claims, "rankings": rankings, "sac_runs": sac_runs}
    sac_figure = plot_sac_runs(sac_runs, results / "sac_runs.png")

    def meta(b, key):
        return "pending" if b["metadata"] is None or b["metadata"].get(key) is None else fmt(b["metadata"][key])

    names = [ALGO_NAMES[a] for a in algos]
    lines = [status, "",
             "| batch | paper's row | data: mean episode return | behaviour policy's return | " + " | ".join(names)
             + " |", "|---|---|---|---|" + "---|" * len(algos)]
    lines += [f"| {b['batch']} | {b['row']} | {meta(b, 'episode_return_mean')} | {_behaviour_cell(b)} | "
              + " | ".join(_exec_row_cells(b, algos)) + " |" for b in batches]
    lines += ["", "Final return (the mean of a run's last evaluations), mean ± sample std over seeds; beside it the "
              "paper's figure on the same kind of batch (B1), mean ± std over seeds on gym's -v2 envs: supp. Table 2 "
              "(arXiv:1910.12179) for the execution batches; for the SAC training batches the BAIL authors' BAIL "
              "(their repository's README, the paper's Table 1 column), the only figure published there. These runs "
              "use Gymnasium's -v5 envs (simulator and rewards changed) and batches made again, so a level is a "
              "ballpark and the ordering of the algorithms is what compares. Data: the batch's mean episode "
              "return; behaviour policy's return: the frozen SAC policy an execution batch runs, as the SAC run "
              "evaluated it (`behaviour_return`), or for a SAC training batch the run's final evaluation (the batch "
              "is the whole run); both from the batch's kept metadata.json.", "", *iqm_table(batches, algos, names),
              "", "| batch | claim | verdict | first side's IQM against the second's |", "|---|---|---|---|"]
    lines += [f"| {c['batch']} | {c['claim']} | {c['verdict']} | "
              + ("" if c["gap"] is None else f"{c['gap']:+.1f} %") + " |" for c in claims]
    lines += ["", f"A verdict needs {MIN_SEEDS_FOR_VERDICT} seeds a side (the paper cell's rule): 'above' and 'below' "
              "claims hold where the first group's IQM interval lies wholly above (below) the second's, ≈ claims "
              "where they overlap (no difference shown, which is not proof of equality). The behaviour policy's "
              "return is one measured figure, so BAIL ≈ the behaviour policy holds where BAIL's IQM interval "
              "contains it; the last column says how far apart the two are."]
    lines += _exec_ranking_lines(rankings, batches)
    figures = ", ".join(f"`{shown_path(results / b['figure'])}`" for b in batches if b["figure"]) or "none yet"
    lines += ["", f"Learning curves, one figure per batch (updates on a linear axis, each seed's evaluations averaged "
              f"per {CURVE_WINDOW_UPDATES} updates; the mean over seeds, a band from the lowest to the highest seed): "
              f"{figures}."]
    lines += _sac_run_lines(sac_runs, sac_figure)
    text = "\n".join(lines) + "\n"
    write_text_atomic(results / "table2.md", text)
    write_json_atomic(results / "table2.json", out)
    return out


def _exec_ranking_lines(rankings: dict, batches: list[dict]) -> list[str]:
    """The Table 2 report's wins, orderings and averages (:func:`exec_rankings`), as Markdown lines."""
    def names(algos):
        return ", ".join(ALGO_NAMES[a] for a in algos)

    lines = ["", "| batch | ours: best IQM (ties: intervals overlapping the best's) | paper: best mean (same "
             "algorithms) | ours, best to worst | paper, best to worst | Kendall's tau | reading |",
             "|---|---|---|---|---|---|---|"]
    for r in rankings["rows"]:
        o = r["ordering"]
        if r["winners"] is None:
            lines.append(f"| {r['batch']} | pending | pending |  |  |  | pending |")
            continue
        lines.append(f"| {r['batch']} | {names(r['winners'])} | {names(r['paper_winners'])} | "
                     f"{' > '.join(ALGO_NAMES[a] for a in o['ours'])} | "
                     f"{' > '.join(ALGO_NAMES[a] for a in o['paper'])} | {fmt(o['tau'], 2) or 'undefined'} | "
                     f"{o['reading']} |")
    n = len(rankings["rows"])
    lines += ["", f"| algorithm | rows won, ours ({rankings['ranked']} of {n} ranked) | paper, the same rows | paper, "
              f"all {len(PAPER_TABLE2)} rows of Table 2 |", "|---|---|---|---|"]
    lines += [f"| {ALGO_NAMES[a]} | {w['ours']} | {w['paper_same_rows']} | {w['paper_all_rows']} |"
              for a, w in rankings["wins"].items()]
    ordering = rankings["ordering"]
    tau = ("pending" if ordering["tau_pooled"] is None else
           f"{ordering['tau_pooled']:+.2f} ({ordering['concordant']} pairs concordant, {ordering['discordant']} "
           f"discordant, {ordering['tied']} tied, over {ordering['rows']} rows; {ordering['same_order']} rows in the "
           "paper's order)")
    means = rankings["paper_means"]
    lines += ["", "| Table 2's reading (supp. E) | verdict |", "|---|---|",
              f"| BC and MARWIL win the most rows | {rankings['most_wins_verdict']} |",
              f"| BAIL ≈ BCQ on average (the paper: BAIL's mean {means['bail']['same_rows']:.0f} against BCQ's "
              f"{means['bcq']['same_rows']:.0f} on these rows, {means['bail']['all_rows']:.0f} against "
              f"{means['bcq']['all_rows']:.0f} on all {len(PAPER_TABLE2)}) | {rankings['average_verdict']} |",
              f"| our orderings against the paper's, over every ranked row | Kendall's tau {tau} |", "",
              "A row is ranked once BAIL, BCQ, BC and MARWIL each have "
              f"{MIN_SEEDS_FOR_VERDICT} seeds there (BEAR joins where it has them). Its winners: the best IQM and "
              "every algorithm whose IQM interval overlaps the best's (a tie); the paper's: the best mean of its "
              "row among the same algorithms (ties: equal means). 'BC and MARWIL win the most rows' holds where the "
              "most wins go to them alone. Kendall's tau per row: tau-b between our IQMs and the paper's means "
              "(scipy.stats.kendalltau); over all rows, every row's pairs pooled: (concordant - discordant) / "
              "pairs, a pair tied on either side counting neither way.", "",
              *improvement_lines(rankings["probability_of_improvement"], len(rankings["rows"])), "",
              f"Over the execution batches, on raw returns (a probability of improvement compares runs within a "
              f"batch, so no normalisation enters). {bootstrap_sentence(len(rankings['rows']))}"]
    return lines


def exec_table_study_report(study: Study, results: Path) -> list[Path]:
    """The ``exec_table`` report of ``study`` (``paper_exec``) from the runs kept in ``results``
    (:func:`exec_table_report`); returns the files written."""
    out = exec_table_report(results, study.jobs)
    return [results / "table2.md", results / "table2.json",
            *(results / b["figure"] for b in out["batches"] if b["figure"]),
            *([results / "sac_runs.png"] if out["sac_runs"] else [])]

"""The cross-batch report (the ``paper_batches`` study, supp. Table 1 of arXiv:1910.12179 at the paper's scale): the
headline batch and three more 10^6-transition batches side by side.

``cross_batch.{md,json}`` (:func:`cross_batch_report`): per batch its data (mean episode return), its behaviour agent's
final return and collection time from its kept metadata, each algorithm's mean ± std and IQM [95 % CI] over seeds
beside the BAIL authors' published figure, a verdict per claim of the paper per batch; a batch made by another one's
recipe with another behaviour seed set beside it (:func:`same_recipe_comparisons`: how much of a verdict is the batch
drawn); and over all batches, each batch's final returns min-max normalised by its own episodes, each algorithm's IQM
and the probabilities of improvement with intervals from a hierarchical bootstrap (:func:`cross_batch_aggregate`,
``cross_batch_aggregate.png``). ``curves_<batch>.png``: each batch's learning curves. The headline batch's runs are
another study's (``paper_hopper``, kept in ``results/paper_hopper``).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from torchrl_bail.configuration.algo_schemas import ALGO_SCHEMAS
from torchrl_bail.core.io import write_json_atomic, write_text_atomic
from torchrl_bail.reports.plots import new_figure, save_figure
from torchrl_bail.study.declaration import Study, StudyJob, batch_overrides, load_study
from torchrl_bail.study.gather import label_recipe, remakes_file
from torchrl_bail.study.tables import (
    CURVE_WINDOW_UPDATES,
    HIERARCHICAL_BOOTSTRAP,
    MIN_SEEDS_FOR_VERDICT,
    NORMALISATION,
    PAPER_ANCHORS,
    PAPER_CLAIMS,
    aggregate_iqm,
    batch_rows,
    bootstrap_sentence,
    bootstrap_settings,
    claim_verdict,
    fmt,
    improvement,
    improvement_lines,
    interval_order,
    iqm_cell,
    iqm_table,
    mean_cell,
    plot_batch_curves,
    shown_path,
)

#: the study whose kept runs (``results/paper_hopper``) hold the headline batch's, Hopper DDPG σ = 0.5 B1
HEADLINE_STUDY = "paper_hopper"

#: the cross-batch study (``paper_batches``): three more 10^6-transition training batches, in the order they
#: run, each as (exp, batch index, the BAIL authors' published figure on it: their repository's README table, gym -v2
#: envs, mean ± std over seeds). Hopper DDPG sigma=0.5 B2 is the headline batch's recipe with another seed: how much of
#: a verdict is the batch itself
PAPER_BATCHES = [("walker_ddpg05", 1, "2522 ± 51"), ("hopper_ddpg01", 1, "2173 ± 291"),
                 ("hopper_ddpg05", 2, "2623 ± 282")]

#: the central algorithms of the cross-batch study, with their seeds, in the order they run on each batch
PAPER_BATCH_CELLS = [("bail", 5), ("bc", 5), ("bcq", 3), ("pbail", 3)]

#: when every batch has its central cells: the paper's other actor-critic and two modern reference points (no claim
#: rests on these)
PAPER_BATCH_EXTRA_CELLS = [("bear", 3), ("td3bc", 3), ("iql", 3)]

#: the cross-batch report's columns, in the registry's order: the central cells of every batch, then the reference
#: points (shown once any batch has a run of them)
CROSS_BATCH_CENTRAL = tuple(a for a in ALGO_SCHEMAS if a in dict(PAPER_BATCH_CELLS))
CROSS_BATCH_EXTRA = tuple(a for a in ALGO_SCHEMAS if a in dict(PAPER_BATCH_EXTRA_CELLS))

#: the claims read on every batch: the paper cell's own (:data:`PAPER_CLAIMS`) whose groups every batch runs
CROSS_BATCH_CLAIMS = [c for c in PAPER_CLAIMS if (c[1], c[2]) in {("bail", "bc"), ("bail", "bcq"), ("pbail", "bail")}]

#: the probabilities of improvement over all batches: P(first > second)
CROSS_BATCH_PAIRS = [("bail", "bcq"), ("bail", "bc")]

#: the markers that tell the batches apart in the aggregate figure, in :func:`cross_batches` order
BATCH_MARKERS = ("o", "s", "^", "D")


def cross_batches() -> list[tuple[str, int, str, str]]:
    """The cross-batch report's rows, as ``(exp, batch index, the BAIL authors' published figure, the study whose
    results hold its runs)``: the headline batch (Hopper DDPG sigma=0.5 B1, ``results/paper_hopper``), then
    :data:`PAPER_BATCHES` (``results/paper_batches``)."""
    return [("hopper_ddpg05", 1, PAPER_ANCHORS["bail"][0], HEADLINE_STUDY),
            *((exp, index, published, "paper_batches") for exp, index, published in PAPER_BATCHES)]


def same_recipe_comparisons(batches: list[dict], algos: list[str]) -> list[dict]:
    """Batches made by one recipe with another behaviour seed (``<exp>_b1``, ``<exp>_b2``, ...: the same env, agent
    and noise, ``batch.index`` apart), each set beside the recipe's first batch: how much of a score, and of a
    verdict, is the batch drawn rather than the algorithm. Per algorithm, where the later batch's IQM interval lies
    against the first's (:func:`interval_order`); per claim, the verdict on each batch and whether they agree."""
    by_recipe: dict[str, list[dict]] = {}
    for b in batches:
        by_recipe.setdefault(label_recipe(b["batch"]), []).append(b)
    out = []
    for recipe, group in by_recipe.items():
        first = group[0]
        for other in group[1:]:
            claims = []
            for i, claim in enumerate(first["claims"]):
                verdicts = [claim["verdict"], other["claims"][i]["verdict"]]
                heads = [v.split(" (")[0] for v in verdicts]
                reading = ("pending" if "pending" in heads else "the same verdict" if heads[0] == heads[1]
                           else "the verdicts differ")
                claims.append({"claim": claim["claim"], "verdicts": verdicts, "reading": reading})
            out.append({"recipe": recipe, "batches": [first["batch"], other["batch"]],
                        "algorithms": {a: interval_order(other["cells"].get(a), first["cells"].get(a))
                                       for a in algos},
                        "claims": claims})
    return out


def _same_recipe_lines(comparisons: list[dict], batches: list[dict]) -> list[str]:
    """The cross-batch report's "Same recipe, another behaviour seed" section, as Markdown lines."""
    meta = {b["batch"]: b["metadata"] or {} for b in batches}
    cells = {b["batch"]: b["cells"] for b in batches}
    lines = []
    for c in comparisons:
        first, other = c["batches"]
        data = "; ".join(f"{label}: data {fmt(meta[label].get('episode_return_mean')) or 'pending'}, behaviour "
                         f"agent {fmt(meta[label].get('behaviour_final_return_mean10')) or 'pending'}"
                         for label in c["batches"])
        lines += ["", f"**Same recipe, another behaviour seed: {first} and {other}.** One recipe ({c['recipe']}: env, "
                  f"behaviour agent, its noise and the batch's size), a behaviour seed apart (`batch.index`), so what "
                  f"differs between the two rows is the batch drawn, not the algorithm ({data}). Each algorithm's "
                  f"IQM [95 % CI] on both, and where {other}'s interval lies against {first}'s:", "",
                  f"| algorithm | {first} | {other} | {other} against {first} |", "|---|---|---|---|"]
        lines += [f"| {a} | {iqm_cell(cells[first].get(a))} | {iqm_cell(cells[other].get(a))} | "
                  f"{'pending' if order.startswith('pending') else order} |" for a, order in c["algorithms"].items()]
        lines += ["", f"| claim | {first} | {other} | reading |", "|---|---|---|---|"]
        lines += [f"| {k['claim']} | {k['verdicts'][0]} | {k['verdicts'][1]} | {k['reading']} |"
                  for k in c["claims"]]
    return lines


def cross_batch_aggregate(batches: list[dict]) -> dict:
    """Over all batches, on the normalised scale (:data:`NORMALISATION`): each algorithm's IQM with its 95 % interval
    over the batches where it has :data:`MIN_SEEDS_FOR_VERDICT` seeds (:func:`aggregate_iqm`), and each of
    :data:`CROSS_BATCH_PAIRS`'s probability of improvement over the batches where both have them
    (:func:`improvement`), with each batch's own value beside it. Every interval is :data:`HIERARCHICAL_BOOTSTRAP`'s
    (:func:`hierarchical_interval`): with four batches drawn, most of its width is which batches they were. A batch
    without kept metadata enters nothing. Unequal seeds: each batch gives its first ``n`` seeds, ``n`` the fewest of
    the batches entered (so 5-seed BAIL stays 5 where every batch has 5)."""
    iqm = {algo: row for algo in CROSS_BATCH_CENTRAL + CROSS_BATCH_EXTRA
           if (row := aggregate_iqm(batches, algo)) is not None}
    pairs = [improvement(batches, a, b) for a, b in CROSS_BATCH_PAIRS]
    return {"normalisation": NORMALISATION, "bootstrap": HIERARCHICAL_BOOTSTRAP, "iqm": iqm,
            "probability_of_improvement": pairs}


def plot_cross_batch_aggregate(batches: list[dict], aggregate: dict, path: Path) -> Path | None:
    """Saves :func:`cross_batch_aggregate_figure` to ``path``; ``None`` (nothing written) while it has nothing to
    show."""
    fig = cross_batch_aggregate_figure(batches, aggregate)
    return None if fig is None else save_figure(fig, path)


def cross_batch_aggregate_figure(batches: list[dict], aggregate: dict):
    """The figure ``cross_batch_aggregate.png``: the aggregate of :func:`cross_batch_aggregate` with each batch
    beside it. Left, per algorithm, its IQM of the normalised final return over the batches entered with its 95 %
    interval (black), and on each batch where it has :data:`MIN_SEEDS_FOR_VERDICT` seeds the IQM of that batch's
    normalised final returns alone (a marker per batch); right, the same for each probability of improvement. Where
    the batches' markers fall on both sides of an aggregate, the batches disagree, and the interval (over batches and
    seeds: :func:`hierarchical_interval`) widens with it. ``None`` while no algorithm has entered a batch."""
    from rliable import metrics  # an optional extra (torchrl_bail[report])

    algos = [a for a in CROSS_BATCH_CENTRAL + CROSS_BATCH_EXTRA if a in aggregate["iqm"]]
    pairs = [p for p in aggregate["probability_of_improvement"] if p["p"] is not None]
    if not algos:
        return None
    markers = {b["batch"]: BATCH_MARKERS[i % len(BATCH_MARKERS)] for i, b in enumerate(batches)}
    fig = new_figure(figsize=(10.0, 0.45 * max(len(algos), 4) + 1.6), layout="constrained")
    left, right = fig.subplots(1, 2, gridspec_kw={"width_ratios": [3, 2]})
    seen = set()

    def batch_point(ax, x: float, y: float, batch: str) -> None:
        ax.plot(x, y, linestyle="none", marker=markers[batch], markersize=6, markerfacecolor="none",
                color=f"C{list(markers).index(batch)}", label=None if batch in seen else batch)
        seen.add(batch)

    for y, algo in enumerate(algos):
        row = aggregate["iqm"][algo]
        left.errorbar(row["iqm"], y, xerr=[[row["iqm"] - row["ci_low"]], [row["ci_high"] - row["iqm"]]],
                      fmt="|", color="black", markersize=14, capsize=4, linewidth=2)
        for b in batches:
            if b["batch"] in row["batches"]:
                batch_point(left, float(metrics.aggregate_iqm(np.array(b["cells"][algo]["per_seed_normalised"]))),
                            y, b["batch"])
    left.set_yticks(range(len(algos)), algos)
    left.invert_yaxis()
    left.set_xlabel("normalised final return (0: the batch's worst episode, 1: its best)")
    left.set_title("IQM over the batches entered [95 % CI], and per batch", fontsize="medium")
    left.grid(axis="x", alpha=0.3)
    for y, p in enumerate(pairs):
        right.errorbar(p["p"], y, xerr=[[p["p"] - p["ci_low"]], [p["ci_high"] - p["p"]]], fmt="|", color="black",
                       markersize=14, capsize=4, linewidth=2)
        for batch, value in p["per_batch"].items():
            batch_point(right, value, y, batch)
    right.set_yticks(range(len(pairs)), [f"P({p['a']} > {p['b']})" for p in pairs])
    right.set_ylim(-0.5, max(len(pairs), 1) - 0.5)
    right.invert_yaxis()
    right.axvline(0.5, color="gray", linestyle="--", linewidth=1)
    right.set_xlim(-0.05, 1.05)
    right.set_xlabel("probability that a run of the first ends above a run of the second")
    right.set_title("Probability of improvement [95 % CI], and per batch", fontsize="medium")
    right.grid(axis="x", alpha=0.3)
    fig.legend(loc="outside lower center", ncol=len(seen), fontsize="small", title="batch (hollow markers)")
    fig.suptitle("Across batches: interval over batches and seeds (black), each batch on its own (markers)")
    return fig


def _aggregate_lines(aggregate: dict, algos: list[str], n_batches: int, figure: Path | None) -> list[str]:
    """The cross-batch report's "Over all batches" section (:func:`cross_batch_aggregate`'s tables, and the figure
    of :func:`plot_cross_batch_aggregate` where there is one), as Markdown lines."""
    lines = [f"**Over all batches.** Normalisation: {NORMALISATION}. Min-max by the batch itself because every "
             "batch's metadata carries both bounds (the v5 reference scores have no expert end yet) and the four "
             "batches differ in env and behaviour quality; it changes no ordering within a batch. A batch enters "
             f"an algorithm's IQM when the algorithm has {MIN_SEEDS_FOR_VERDICT} seeds there, and a comparison "
             f"when both sides have; each batch gives its first n seeds (seed order), n the fewest of the batches "
             f"entered. {bootstrap_sentence(n_batches)}", "",
             "| algorithm | batches entered | seeds per batch | IQM of normalised final return [95 % CI] "
             "| [over seeds alone] |", "|---|---|---|---|---|"]
    for algo in algos:
        row = aggregate["iqm"].get(algo)
        lines.append(f"| {algo} | pending (no batch with {MIN_SEEDS_FOR_VERDICT} seeds) |  |  |  |" if row is None else
                     f"| {algo} | {', '.join(row['batches'])} ({len(row['batches'])} of {n_batches}) | "
                     f"{row['seeds_per_batch']} | {fmt(row['iqm'], 3)} [{fmt(row['ci_low'], 3)}, "
                     f"{fmt(row['ci_high'], 3)}] | [{fmt(row['seeds_only'][0], 3)}, "
                     f"{fmt(row['seeds_only'][1], 3)}] |")
    lines += ["", *improvement_lines(aggregate["probability_of_improvement"], n_batches)]
    if figure is not None:
        lines += ["", "Both tables at a glance, with each batch on its own beside the aggregate: "
                  f"`{shown_path(figure)}`."]
    return lines


def cross_batch_report(results: Path, headline: Path | None = None, jobs: list[StudyJob] | None = None,
                       headline_jobs: list[StudyJob] | None = None) -> dict:
    """``results/cross_batch.{md,json}`` and ``results/curves_<batch>.png``: the headline batch (its kept runs and
    metadata in ``headline``, default ``paper_hopper`` beside ``results``; ``headline_jobs``: the jobs of that study,
    default :func:`kept_run_jobs`) and :data:`PAPER_BATCHES` (in ``results``; ``jobs``: the study's, default the
    declared ``paper_batches`` study's) side by side, Table-1 style — per batch its own mean episode return, its
    behaviour agent's final evaluation return (``behaviour_final_return_mean10``) and collection time
    (``collection_wall_time_s``) from its kept metadata, each algorithm's mean ± std and IQM [95 % CI] over seeds, the
    BAIL authors' published figure; a verdict per claim of :data:`CROSS_BATCH_CLAIMS` per batch (:func:`claim_verdict`);
    over all batches :func:`cross_batch_aggregate`. Reads kept runs only (no workdir, no batch); a cell without runs, a
    batch without metadata, reads "pending". Returns the JSON written."""
    headline = headline if headline is not None else results.parent / HEADLINE_STUDY
    jobs = load_study("paper_batches").jobs if jobs is None else jobs
    sources = {HEADLINE_STUDY: (headline, headline_jobs), "paper_batches": (results, jobs)}
    batches = []
    for exp, index, published, study in cross_batches():
        label = f"{exp}_b{index}"
        root, its_jobs = sources[study]
        its_jobs = kept_run_jobs(root, label, jobs) if its_jobs is None else its_jobs
        cells, meta_path, metadata, rows = batch_rows(root, its_jobs, label, CROSS_BATCH_CENTRAL + CROSS_BATCH_EXTRA)
        claims = [{"claim": claim, "a": a, "b": b, "verdict": claim_verdict(rows.get(a), rows.get(b), kind)}
                  for claim, a, b, kind in CROSS_BATCH_CLAIMS]
        complete = all(rows.get(a, {}).get("seeds", 0) >= rows[a]["scheduled"] for a in CROSS_BATCH_CENTRAL
                       if a in rows) and metadata is not None
        figure = plot_batch_curves(label, cells, metadata, results / f"curves_{label}.png",
                                   CROSS_BATCH_CENTRAL + CROSS_BATCH_EXTRA)
        keys = ("episode_return_mean", "episode_return_min", "episode_return_max", "behaviour_final_return_mean10",
                "collection_wall_time_s", "collection_timed_from_step", "num_transitions", "num_episodes", "env_id",
                "recipe_hash")
        remakes = [] if meta_path is None or not remakes_file(meta_path).is_file() else [
            {k: r.get(k) for k in ("created_at", "collection_wall_time_s", "collection_timed_from_step")}
            for r in json.loads(remakes_file(meta_path).read_text())["remakes"]]
        batches.append({
            "batch": label, "results": shown_path(root), "published_bail": published, "complete": complete,
            "metadata_file": None if meta_path is None else shown_path(meta_path),
            "metadata": None if metadata is None else {k: metadata.get(k) for k in keys}, "remakes": remakes,
            "cells": rows, "claims": claims, "figure": None if figure is None else figure.name})
    aggregate = cross_batch_aggregate(batches)
    aggregate_figure = plot_cross_batch_aggregate(batches, aggregate, results / "cross_batch_aggregate.png")
    across = []
    for claim, *_ in CROSS_BATCH_CLAIMS:
        verdicts = [next(c["verdict"] for c in b["claims"] if c["claim"] == claim) for b in batches]
        across.append({"claim": claim, **{k: sum(v.startswith(k + " ") or v == k for v in verdicts)
                                          for k in ("holds", "does not hold", "pending")}})
    done = [b["batch"] for b in batches if b["complete"]]
    status = ("Batches complete (every central cell at its seeds: "
              + ", ".join(f"{a} x {dict(PAPER_BATCH_CELLS)[a]}" for a in CROSS_BATCH_CENTRAL)
              + f"; the batch's metadata kept): {len(done)} of {len(batches)}"
              + (f" ({', '.join(done)})" if done else "") + ". "
              + ("The cross-batch reading is pending until every batch is complete."
                 if len(done) < len(batches) else "Every batch is complete."))
    shown_extra = [a for a in CROSS_BATCH_EXTRA if any(b["cells"].get(a, {}).get("seeds") for b in batches)]
    algos = [*CROSS_BATCH_CENTRAL, *shown_extra]
    same_recipe = same_recipe_comparisons(batches, algos)
    out = {"status": status, "complete_batches": done, "min_seeds_for_verdict": MIN_SEEDS_FOR_VERDICT,
           "batches": batches, "claims_across_batches": across, "same_recipe": same_recipe, "aggregate": aggregate,
           "aggregate_figure": None if aggregate_figure is None else aggregate_figure.name,
           "bootstrap": bootstrap_settings()}

    def meta(b, key, show):
        return "pending" if b["metadata"] is None or b["metadata"].get(key) is None else show(b["metadata"][key])

    def collection_time(b) -> str:  # a part of a resumed collection may not have been timed
        timed_from = (b["metadata"] or {}).get("collection_timed_from_step")
        again = [f"{r['collection_wall_time_s'] / 3600:.1f} h" for r in b["remakes"]
                 if r["collection_wall_time_s"] is not None and not r["collection_timed_from_step"]]
        return (meta(b, "collection_wall_time_s", lambda s: f"{s / 3600:.1f} h")
                + (f" (env steps {timed_from:,} on)" if timed_from else "")
                + (f"; made again: {', '.join(again)}" if again else ""))

    lines = [status, "",
             "| batch | data: mean episode return | behaviour agent's final return | collection time | "
             + " | ".join(algos) + " | published BAIL (gym -v2) |", "|---|---|---|---|" + "---|" * len(algos) + "---|"]
    for b in batches:
        lines.append(f"| {b['batch']} | {meta(b, 'episode_return_mean', fmt)} | "
                     f"{meta(b, 'behaviour_final_return_mean10', fmt)} | "
                     f"{collection_time(b)} | "
                     + " | ".join(mean_cell(b["cells"].get(a)) for a in algos) + f" | {b['published_bail']} |")
    lines += ["", "Final return (the mean of a run's last evaluations), mean ± sample std over seeds. Data: the "
              "batch's mean episode return; behaviour agent's final return: the mean of its last 10 evaluations as "
              "collection ended; collection time: wall time of the 10^6-step collection, summed over its parts "
              "when it was resumed from its checkpoint (\"env steps N on\": an older version's checkpoint, "
              "which kept no time, held the steps before N) (all from the batch's kept metadata.json); made again: the "
              "time of each later collection of the same batch from scratch, its cache lost, that made the same data "
              "to every digit (its remakes.json). "
              "Published BAIL: the authors' figures, mean ± std over seeds, on gym's -v2 "
              "envs — for the three added batches from their repository's README table, for hopper_ddpg05_b1 the "
              "paper's Table 1. These runs use Gymnasium's -v5 (simulator and rewards changed), so the levels "
              "differ and the ordering of the algorithms is what compares.", "", *iqm_table(batches, algos), "",
              "| batch | " + " | ".join(c[0] for c in CROSS_BATCH_CLAIMS) + " |",
              "|---|" + "---|" * len(CROSS_BATCH_CLAIMS)]
    lines += [f"| {b['batch']} | " + " | ".join(c["verdict"] for c in b["claims"]) + " |" for b in batches]
    lines.append("| across batches | " + " | ".join(
        f"holds on {c['holds']}, does not hold on {c['does not hold']}, pending on {c['pending']} of {len(batches)}"
        for c in across) + " |")
    lines += ["", f"A verdict needs {MIN_SEEDS_FOR_VERDICT} seeds on both sides (the paper cell's rule: 'holds' for "
              "an 'above' claim means the first group's IQM interval lies wholly above the second's; for ≈ that the "
              "intervals overlap, no difference shown, which is not proof of equality).",
              *_same_recipe_lines(same_recipe, batches), "",
              *_aggregate_lines(aggregate, algos, len(batches), aggregate_figure)]
    figures = ", ".join(f"`{shown_path(results / b['figure'])}`" for b in batches if b["figure"]) or "none yet"
    lines += ["", f"Learning curves, one figure per batch (updates on a linear axis, each seed's "
              f"evaluations averaged per {CURVE_WINDOW_UPDATES} updates; the mean over seeds, a band from the lowest "
              f"to the highest seed): {figures}."]
    text = "\n".join(lines) + "\n"
    write_text_atomic(results / "cross_batch.md", text)
    write_json_atomic(results / "cross_batch.json", out)
    return out


def kept_run_jobs(root: Path, label: str, like: list[StudyJob]) -> list[StudyJob]:
    """The training jobs of batch ``label`` whose runs are kept in ``root/runs``, read from the runs themselves: for
    the headline batch, whose study (``paper_hopper``) is not declared in this package. A kept run counts when its
    algorithm is one that ``like`` (the reading study's jobs) trains and its overrides are those ``like`` gives that
    algorithm (its schedule: the same on every batch), as a job of its one seed, in ``like``'s order of the
    algorithms; a variant (other overrides) is left out. Each cell so read has as many seeds scheduled as kept."""
    schedules: dict[str, list[str]] = {}
    for job in like:
        if job.module == "torchrl_bail.train" and len(job.name.split("/")) == 3:
            schedules.setdefault(job.overrides["algo"], sorted(
                a for a in job.args if not a.startswith(("+exp=", "algo=", "seed=", "batch.index="))))
    jobs = []
    for algo, schedule in schedules.items():
        for run in sorted((root / "runs" / label / algo).glob("seed*"), key=lambda r: r.name):
            seed, *extra = run.name.split(",")
            if seed[4:].isdigit() and sorted(extra) == schedule and (run / "summary.json").is_file():
                jobs.append(StudyJob(f"{label}/{algo}/{seed}",
                                     (*batch_overrides(label), f"algo={algo}", f"seed={seed[4:]}", *extra)))
    return jobs


def cross_batch_study_report(study: Study, results: Path, headline: Path | None = None,
                             headline_jobs: list[StudyJob] | None = None) -> list[Path]:
    """The ``cross_batch`` report of ``study`` (``paper_batches``) from the runs kept in ``results``
    (:func:`cross_batch_report`, the headline batch's kept runs in ``headline``); returns the files written."""
    out = cross_batch_report(results, headline, study.jobs, headline_jobs)
    return [results / "cross_batch.md", results / "cross_batch.json",
            *(results / b["figure"] for b in out["batches"] if b["figure"]),
            *([results / out["aggregate_figure"]] if out["aggregate_figure"] else [])]

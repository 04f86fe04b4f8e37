"""A study's report from its kept runs: the tables every study gets and the study's own (:data:`REPORTS`).

Every study's results directory gets ``study.{md,csv,json}`` and its figures through ``torchrl_bail.report`` (every
kept run, grouped by batch, algorithm and overrides: :func:`report_runs`) and ``curves.{md,json}`` (whether each
learning curve has flattened: :func:`curve_check`); a study's ``report`` key (``declared/<study>.yaml``) names its own
report: ``cross_batch`` (:mod:`torchrl_bail.study.cross_batch`) or ``exec_table``
(:mod:`torchrl_bail.study.exec_table`). :func:`write_report` writes them all from the kept files alone (the runs and
batch metadata :mod:`torchrl_bail.study.gather` keeps), so it rebuilds the same report at any stage of a study, with
zero, some or all of its runs; :func:`build_report` (``python -m torchrl_bail.study report``) gathers first.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from torchrl_bail.core.io import write_json_atomic, write_text_atomic
from torchrl_bail.reports.plots import read_eval_curve
from torchrl_bail.study.cross_batch import cross_batch_study_report
from torchrl_bail.study.declaration import Study, StudyError
from torchrl_bail.study.exec_table import exec_table_study_report
from torchrl_bail.study.gather import gather_study
from torchrl_bail.study.tables import REPOSITORY, shown_path

#: a study's own report, by the name its declaration's ``report`` key gives: ``(study, results) -> files written``
REPORTS: dict[str, Callable[..., list[Path]]] = {"cross_batch": cross_batch_study_report,
                                                 "exec_table": exec_table_study_report}
#: the kept runs that are supp. D's ablations (on Hopper DDPG σ = 0.5), not a study's cells
ABLATION = re.compile(r"selection\.by=|envelope\.penalty=|oracle|augment")


def report_runs(results: Path, ablations: bool = True) -> list[Path]:
    """``study.*`` (every kept run of ``results/runs`` but the ablations) and, with ``ablations``, ``ablations.*``
    (supp. D on Hopper DDPG σ = 0.5) through ``torchrl_bail.report`` (its tables and figures), run from the
    repository so that they name the runs relative to it; returns the files written."""
    runs = results / "runs"
    main_runs = [p for p in sorted(runs.glob("*/*/*")) if not ABLATION.search(p.name)]
    bail_ddpg05 = sorted(runs.glob("hopper_ddpg05_b1/bail/*")) + sorted(runs.glob("hopper_ddpg05_oracle*/bail/*"))
    written = []
    for prefix, paths in (("study", main_runs), ("ablations", bail_ddpg05 if ablations else [])):
        if paths:
            done = subprocess.run([sys.executable, "-m", "torchrl_bail.report", *map(shown_path, paths),
                                   "--out", shown_path(results / prefix), "--plot"], cwd=REPOSITORY,
                                  stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
            sys.stderr.write(done.stderr)
            done.check_returncode()
            written += [results / f"{prefix}{suffix}" for suffix in (".md", ".csv", ".json")]
            written += [REPOSITORY / line[len("wrote "):] for line in done.stderr.splitlines()
                        if line.startswith("wrote ")]
    return written


def curve_check(results: Path) -> list[dict]:
    """Has each learning curve flattened? Per group (batch x algorithm x overrides): the mean curve over seeds,
    and over its second half (evaluations ``n // 2`` to ``n``, the ones ``final_return`` averages) its mean, the
    change a least-squares line fits across it and the spread of the points around that line. ``still_moving``
    marks a change larger than twice the spread and than 5 % of the mean. Groups whose second half holds fewer than
    3 evaluations are left out.

    For the algorithms that fit an upper envelope (their ``summary.json`` has ``envelope_best_epoch``) each group
    also lists every seed's best validation epoch against the fit's cap ``algo.envelope.epochs``, and whether early
    stopping ended every fit: ``envelope_settled`` when each best epoch is at least ``algo.envelope.patience``
    epochs before the cap (the validation loss then stopped improving for that long), not when a fit was still
    improving as the cap stopped it. Written to ``results/curves.{md,json}``."""
    groups: dict[tuple[str, str, str], list] = {}
    envelopes: dict[tuple[str, str, str], list] = {}
    for run in sorted((results / "runs").glob("*/*/*")):
        curve = read_eval_curve(run)
        if curve is not None:
            key = (run.parent.parent.name, run.parent.name,
                   ",".join(o for o in run.name.split(",")[1:] if o != "preset=study"))
            groups.setdefault(key, []).append(np.asarray(curve[1]))
            summary = json.loads((run / "summary.json").read_text()) if (run / "summary.json").is_file() else {}
            if summary.get("envelope_best_epoch") is not None:
                fit = OmegaConf.load(run / "config.yaml").algo.envelope
                envelopes.setdefault(key, []).append((int(summary["envelope_best_epoch"]), int(fit.epochs),
                                                      int(fit.patience)))
    rows = []
    for key, curves in groups.items():
        n = min(len(c) for c in curves)
        if n - n // 2 < 3:  # a line through a second half of fewer than 3 evaluations says nothing
            continue
        y = np.mean([c[:n] for c in curves], axis=0)[n // 2:]
        dx = np.arange(n // 2, n) - (n // 2 + n - 1) / 2  # evaluation index about the half's centre
        # least squares in closed form, not np.polyfit: LAPACK's kernels differ by CPU, these sums do not
        slope = float((dx * (y - y.mean())).sum() / (dx * dx).sum())
        spread = float(np.std(y - (y.mean() + slope * dx), ddof=2))
        change, level = slope * float(dx[-1] - dx[0]), float(y.mean())
        row = {"batch": key[0], "algo": key[1], "overrides": key[2], "seeds": len(curves), "evaluations": n,
               "second_half_mean": level, "second_half_change": change, "residual_spread": spread,
               "still_moving": bool(abs(change) > max(2 * spread, 0.05 * abs(level)))}
        if key in envelopes:
            at_cap = sum(best > cap - patience for best, cap, patience in envelopes[key])
            row.update(envelope_best_epochs=[best for best, _, _ in envelopes[key]],
                       envelope_epochs=max(cap for _, cap, _ in envelopes[key]),
                       envelope_fits_at_cap=at_cap, envelope_settled=at_cap == 0)
        rows.append(row)

    def envelope_cell(row: dict) -> str:
        if "envelope_best_epochs" not in row:
            return ""
        verdict = "stopped early" if row["envelope_settled"] else "**at the cap**"
        return f"{', '.join(map(str, row['envelope_best_epochs']))} of {row['envelope_epochs']}: {verdict}"

    lines = ["| batch | algo | overrides | 2nd-half mean | change over it | spread | still moving "
             "| envelope best epoch |", "|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['batch']} | {r['algo']} | {r['overrides']} | {r['second_half_mean']:.1f} | "
              f"{r['second_half_change']:+.1f} | {r['residual_spread']:.1f} | "
              f"{('**rising**' if r['second_half_change'] > 0 else '**falling**') if r['still_moving'] else 'no'} | "
              f"{envelope_cell(r)} |" for r in rows]
    fits = [r for r in rows if "envelope_best_epochs" in r]
    at_cap = sum(r["envelope_fits_at_cap"] for r in fits)
    lines += ["", "2nd-half mean: the seed-mean curve over the evaluations final_return averages; change: what a "
              "least-squares line through them rises or falls across that half; spread: the points' standard "
              "deviation around the line; still moving: |change| > 2 x spread and > 5 % of the mean. Envelope "
              "best epoch: each seed's best validation epoch of the upper-envelope fit, of the fit's epoch cap; "
              "stopped early: every best epoch is at least the patience (algo.envelope.patience) epochs before the "
              "cap; at the cap: a "
              "fit was still improving when the cap stopped it"
              + (f" ({at_cap} of {sum(len(r['envelope_best_epochs']) for r in fits)} fits here)." if fits else ".")]
    write_text_atomic(results / "curves.md", "\n".join(lines) + "\n")
    write_json_atomic(results / "curves.json", rows)
    return rows


def write_report(study: Study, results: Path, **options) -> list[Path]:
    """Every report of ``study`` from the runs and batch metadata kept in ``results``: :func:`report_runs` (no
    ablations), :func:`curve_check` and the study's own, if it names one (:data:`REPORTS`, by its ``report`` key;
    ``options`` go to it: the cross-batch report's ``headline`` and ``headline_jobs``); returns the files written."""
    if study.report is not None and study.report not in REPORTS:
        raise StudyError(f"study {study.name}: report {study.report!r} is not one of {', '.join(REPORTS)}")
    written = report_runs(results, ablations=False)
    curve_check(results)
    own = REPORTS[study.report](study, results, **options) if study.report is not None else []
    return [*written, results / "curves.md", results / "curves.json", *own]


def build_report(study: Study, workdir: Path, results: Path, data_dir: Path, **options) -> list[Path]:
    """``python -m torchrl_bail.study report``: gathers what ``run`` made of ``study`` in ``workdir`` (batches in
    ``data_dir``) into ``results`` (:func:`~torchrl_bail.study.gather.gather_study`), then :func:`write_report`;
    returns the files written. With nothing to gather it rebuilds the report from what ``results`` keeps."""
    gather_study(study, workdir, results, data_dir)
    return write_report(study, results, **options)

"""The report groups runs by batch recipe x algorithm x separating override and computes rliable's IQM."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from torchrl_bail.core.io import write_json_atomic
from torchrl_bail.report import find_runs, group_runs, main

rliable = pytest.importorskip("rliable", reason="the report needs the 'report' extra")
from rliable import library, metrics  # noqa: E402

BATCHES = {"hopper_ddpg05_b1": "aaaa1111", "hopper_sac_b1": "bbbb2222", "walker_ddpg05_b1": "cccc3333"}
ALGOS = {"bail": 1000.0, "bc": 800.0, "bcq": 900.0}
SEEDS = [1, 2, 3, 4, 5]


def _score(batch_i: int, algo: str, seed: int, ablation: bool) -> float:
    return ALGOS[algo] + 100.0 * batch_i + 37.0 * seed ** 1.5 - (400.0 if ablation else 0.0)


def _write_run(root, batch, algo, seed, score, by="envelope"):
    run = root / f"{batch}_{algo}_{by}_s{seed}"
    config = {"seed": seed, "progress": False, "device": "cpu", "data_dir": f"/tmp/data{seed}",
              "logger": {"backend": "csv"}, "env": {"id": "Hopper-v5"}, "batch": {"kind": batch.split("_")[1]},
              "eval": {"episodes": 5}, "algo": {"name": algo, "epochs": 0.01,
                                                **({"selection": {"by": by}} if algo == "bail" else {})}}
    (run / "logs" / "scalars" / "eval").mkdir(parents=True)
    (run / "config.yaml").write_text(yaml.safe_dump(config))
    steps = [10, 20, 30]
    (run / "logs" / "scalars" / "eval" / "return.csv").write_text(
        "".join(f"{s},{score * s / 30}\n" for s in steps))
    (run / "logs" / "scalars" / "eval" / "epoch.csv").write_text("".join(f"{s},{s / 1000}\n" for s in steps))
    write_json_atomic(run / "summary.json", {
        "algo": algo, "batch": batch, "seed": seed, "final_return": score, "best_return": score + 50.0,
        "dataset_mean_episode_return": 500.0, "batch_path": f"/data/{batch}-{BATCHES[batch]}"})


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    root = tmp_path_factory.mktemp("runs")
    for i, batch in enumerate(BATCHES):
        for algo in ALGOS:
            for seed in SEEDS:
                _write_run(root, batch, algo, seed, _score(i, algo, seed, False))
    for seed in SEEDS:  # the ablation: BAIL selecting by return, on the first batch only
        _write_run(root, "hopper_ddpg05_b1", "bail", seed, _score(0, "bail", seed, True), by="return")
    return root


def test_report_writes_three_files_with_rliable_iqm(tree, tmp_path, capsys):
    prefix = tmp_path / "results"
    assert main([str(tree), "--out", str(prefix), "--reps", "500", "--bootstrap-seed", "7"]) == 0
    groups = json.loads((tmp_path / "results.json").read_text())["groups"]
    assert len(groups) == 3 * 3 + 1
    with open(tmp_path / "results.csv") as f:
        assert len(list(csv.DictReader(f))) == 10
    for g in groups:
        batch_i = list(BATCHES).index(g["batch"])
        ablation = g["variant"] == "algo.selection.by=return"
        scores = [_score(batch_i, g["algo"], s, ablation) for s in SEEDS]
        assert g["recipe_hash"] == BATCHES[g["batch"]] and g["seeds"] == 5
        assert g["final_return_mean"] == pytest.approx(np.mean(scores))
        assert g["final_return_std"] == pytest.approx(np.std(scores, ddof=1))
        assert g["best_return_mean"] == pytest.approx(np.mean(scores) + 50.0)
        np.random.seed(7)  # rliable 1.2.0 resamples from numpy's global stream
        point, interval = library.get_interval_estimates(
            {"x": np.array(scores)[:, None]}, lambda x: np.array([metrics.aggregate_iqm(x)]), reps=500)
        assert g["final_return_iqm"] == pytest.approx(point["x"][0])
        assert [g["final_return_iqm_ci_low"], g["final_return_iqm_ci_high"]] == pytest.approx(interval["x"][:, 0])
        assert g["final_return_iqm_ci_low"] < g["final_return_iqm"] < g["final_return_iqm_ci_high"]
    md = (tmp_path / "results.md").read_text()
    # batches as rows, algorithms as columns, the ablation in its own row, best per row in bold
    assert md.splitlines()[0] == "| batch | data | bail | bc | bcq |"
    first, iqm_table = md.split("\n\n")[0], md.split("\n\n")[2]
    rows = {line.split(" | ")[0].lstrip("| "): line for line in first.splitlines()[2:]}
    assert iqm_table.splitlines()[0] == "| batch | data | bail | bc | bcq |" and len(iqm_table.splitlines()) == 2 + 4
    assert set(rows) == {*BATCHES, "hopper_ddpg05_b1 [algo.selection.by=return]"}
    assert rows["hopper_sac_b1"].split(" | ")[2].startswith("**")  # BAIL best on the default rows
    assert "algo.selection.by" in md and "seed" not in json.loads((tmp_path / "results.json").read_text())[
        "separating_keys"]["bail"]
    assert json.loads((tmp_path / "results.json").read_text())["separating_keys"] == {
        "bail": ["algo.selection.by"], "bc": [], "bcq": []}


def test_report_figures(tree, tmp_path):
    prefix = tmp_path / "fig"
    assert main([str(tree), "--out", str(prefix), "--plot", "--reps", "200"]) == 0
    for name in ("fig_curves.png", "fig_aggregate.png", "fig_profiles.png"):
        assert (tmp_path / name).stat().st_size > 1000, name


@pytest.mark.parametrize("bcq_epochs, scale", [(0.03, "linear"), (0.006, "log")])
def test_curves_use_a_log_epoch_axis_when_schedules_differ_fourfold(tmp_path, monkeypatch, bcq_epochs, scale):
    """BCQ at 10 epochs beside BC at 100 (the paper cell) must not be squeezed against the left edge."""
    import torchrl_bail.report as report

    for seed in (1, 2):
        _write_run(tmp_path, "hopper_ddpg05_b1", "bc", seed, 800.0)
        run = tmp_path / f"hopper_ddpg05_b1_bcq_envelope_s{seed}"
        _write_run(tmp_path, "hopper_ddpg05_b1", "bcq", seed, 900.0)
        (run / "logs" / "scalars" / "eval" / "epoch.csv").write_text(
            "".join(f"{s},{bcq_epochs * s / 30}\n" for s in (10, 20, 30)))
    saved = []
    monkeypatch.setattr(report, "save_figure", lambda fig, path: saved.append(fig) or path)
    report._plot_curves(group_runs(find_runs([tmp_path])), tmp_path / "c.png")
    (ax,) = saved[0].axes
    assert ax.get_xscale() == scale and ("log scale" in ax.get_xlabel()) == (scale == "log")
    saved[0].canvas.draw()  # the legend sits below the axes, over no curve
    assert ax.get_legend().get_window_extent().y1 < ax.get_window_extent().y0


@pytest.mark.parametrize("content, expected", [("{not json", "unreadable"), ('{"algo": "bc", "seed": 1}',
                                                                             "missing final_return, best_return")])
def test_bad_summary_is_one_line_naming_the_file(tmp_path, capsys, content, expected):
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "summary.json").write_text(content)
    assert main([str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(tmp_path / "run" / "summary.json") in err and expected in err


def test_runs_of_one_batch_on_different_data_are_refused(tmp_path, capsys):
    """Two copies of one recipe (same name and hash) with other transitions, say one made again on another CPU
    kind: their runs are refused as one cell, naming both; another batch may hold other data."""
    for seed in (1, 2):
        _write_run(tmp_path, "hopper_ddpg05_b1", "bc", seed, 100.0 * seed)
    _write_run(tmp_path, "hopper_sac_b1", "bc", 1, 100.0)
    other = tmp_path / "hopper_sac_b1_bc_envelope_s1" / "summary.json"
    other.write_text(json.dumps({**json.loads(other.read_text()), "dataset_mean_episode_return": 612.5}))
    assert len(group_runs(find_runs([tmp_path]))) == 2
    remade = tmp_path / "hopper_ddpg05_b1_bc_envelope_s2" / "summary.json"
    remade.write_text(json.dumps({**json.loads(remade.read_text()), "dataset_mean_episode_return": 500.25}))
    assert main([str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "hopper_ddpg05_b1_bc_envelope_s1 and " in err and "hopper_ddpg05_b1_bc_envelope_s2 name one batch" in err
    assert "dataset_mean_episode_return 500.0 vs 500.25" in err


def test_missing_directory_and_empty_tree(tmp_path, capsys):
    assert main([str(tmp_path / "missing")]) == 2
    assert main([str(tmp_path)]) == 1
    assert "no summary.json" in capsys.readouterr().err


def test_runs_from_before_a_key_existed_group_with_its_default(tmp_path):
    """A run whose config.yaml predates ``compile`` and one with ``compile: false`` are one group; ``true`` is not."""
    for seed, extra in ((1, {}), (2, {"compile": False}), (3, {"compile": True})):
        _write_run(tmp_path, "hopper_ddpg05_b1", "bc", seed, 100.0 * seed)
        if extra:
            path = tmp_path / f"hopper_ddpg05_b1_bc_envelope_s{seed}" / "config.yaml"
            path.write_text(yaml.safe_dump({**yaml.safe_load(path.read_text()), **extra}))
    groups = group_runs(find_runs([tmp_path]))
    assert sorted((g.variant_label, g.seeds) for g in groups) == [("", 2), ("compile=true", 1)]


def test_the_fqe_selected_return_is_a_column_only_when_a_run_has_one(tmp_path):
    """``fqe_selected`` (written by ``python -m torchrl_bail.ope`` for a run with snapshots) gives each group the mean
    and std of the selected snapshots' evaluation returns over the runs that have one; without it, no column."""
    from torchrl_bail.report import format_csv, format_markdown, summarise

    for seed in (1, 2, 3):
        _write_run(tmp_path, "hopper_ddpg05_b1", "bc", seed, 100.0 * seed)
    (row,) = summarise(group_runs(find_runs([tmp_path])), reps=50)
    assert not any(k.startswith("fqe") for k in row)
    assert "fqe" not in format_csv([row]) and "fqe" not in format_markdown([row])
    for seed, online in ((1, 90.0), (2, 110.0)):
        path = tmp_path / f"hopper_ddpg05_b1_bc_envelope_s{seed}" / "summary.json"
        summary = json.loads(path.read_text())
        summary["fqe_selected"] = {"path": "snapshots/policy_4.pt", "iteration": 4, "fqe_estimate": 1.5,
                                   "online_return": online}
        write_json_atomic(path, summary)
    (row,) = summarise(group_runs(find_runs([tmp_path])), reps=50)
    assert row["fqe_selected_return_mean"] == 100.0 and row["fqe_selected_runs"] == 2
    assert row["fqe_selected_return_std"] == pytest.approx(np.std([90.0, 110.0], ddof=1))
    assert row["final_return_mean"] == 200.0  # beside final_return, over all three runs
    header = format_csv([row]).splitlines()[0].split(",")
    assert header[-3:] == ["fqe_selected_return_mean", "fqe_selected_return_std", "fqe_selected_runs"]
    assert "| hopper_ddpg05_b1 | 500.0 | 100.0 ± 14.1 (2) |" in format_markdown([row])


def test_the_aggregates_take_each_batchs_first_seeds_not_its_lowest_scores():
    """With unequal seeds across a label's batches, each batch enters rliable's matrix with its first ``n`` seeds in
    seed order: a batch with 5 seeds does not give its 3 lowest scores beside a batch with 3."""
    from torchrl_bail.report import Group, Run, _normalized_scores

    def run(batch, seed, final):
        return Run(Path(f"/runs/{batch}/bail/seed{seed}"), {"seed": seed, "final_return": final,
                                                            "dataset_mean_episode_return": 100.0}, {}, (batch, None))

    five = Group(("a", None), "bail", (), "bail", "", [run("a", s, f) for s, f in
                                                        zip((4, 2, 5, 1, 3), (50.0, 300.0, 10.0, 500.0, 400.0),
                                                            strict=True)])
    three = Group(("b", None), "bail", (), "bail", "", [run("b", s, 100.0 * s) for s in (1, 2, 3)])
    matrices, name, level = _normalized_scores([five, three])
    assert name == "final return / batch mean episode return" and level == 1.0
    assert matrices["bail"].tolist() == [[5.0, 1.0], [3.0, 2.0], [4.0, 3.0]]  # seeds 1, 2, 3 of each batch


def test_the_optimality_gap_is_measured_below_the_scores_own_reference_level():
    """On the D4RL 0-100 scale the gap is the shortfall below 100 (expert), on the batch-mean ratio below 1.0 (the
    data's mean): runs at 40-60 normalised are about 50 short of the expert, not 0 (the figure's panel read 0 for every
    algorithm when its threshold was 1.0 on the 0-100 scale)."""
    from torchrl_bail.report import Group, Run, _normalized_scores, aggregate_estimates

    def run(batch, seed, normalised, final):
        summary = {"seed": seed, "final_return": final, "dataset_mean_episode_return": 100.0,
                   "final_return_normalized": normalised}
        return Run(Path(f"/runs/{batch}/bail/seed{seed}"), summary, {}, (batch, None))

    runs = [run(b, s, 40.0 + 10 * (s - 1), 80.0 + 20 * (s - 1)) for b in ("a", "b") for s in (1, 2, 3)]
    groups = [Group((b, None), "bail", (), "bail", "", [r for r in runs if r.batch[0] == b]) for b in ("a", "b")]
    matrices, name, level = _normalized_scores(groups)
    assert (name, level) == ("normalised score", 100.0)
    point, _, panels = aggregate_estimates(matrices, level, reps=50)
    assert panels[-1] == "Optimality gap (below 100)" and point["bail"][-1] == pytest.approx(50.0)
    for r in runs:  # without D4RL scores: the ratio to the batch's mean, 0.8, 1.0 and 1.2 -> 0.2 short of 1.0 / 3
        del r.summary["final_return_normalized"]
    matrices, name, level = _normalized_scores(groups)
    point, _, panels = aggregate_estimates(matrices, level, reps=50)
    assert level == 1.0 and point["bail"][-1] == pytest.approx(0.2 / 3)

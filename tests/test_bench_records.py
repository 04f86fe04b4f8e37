"""The benchmark records and the tables of docs/benchmarks.md: every figure of those tables comes from a record.

``benchmarks/render_records.py`` renders each table from the JSON records (``results/benchmarks/*.json``, written
by the benchmark scripts, and ``results/d3rlpy/*.json``); the page includes the rendered files. These tests render
them again and compare, check that each record's ratio rows follow from its rounds, and that the page's prose quotes
only means that a rendered table holds.
"""

from __future__ import annotations

import json
import re
import statistics
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import render_records  # noqa: E402
from _bench import PACKAGES, Record, derive_table, summarise  # noqa: E402

PAGE = ROOT / "docs" / "benchmarks.md"
RECORDS_DIR = ROOT / "results" / "benchmarks"
D3RLPY = ROOT / "results" / "d3rlpy"
RECORDS = sorted(RECORDS_DIR.glob("*.json"))


def test_every_rendered_table_matches_its_records():
    rendered = render_records.render_all()
    assert {p.name for p in rendered} >= {"ratios.md", "records.md", "collection_rates.md",
                                          "d3rlpy_returns_hopper_sac_b1.md", "d3rlpy_returns_hopper_ddpg05_b1.md"}
    for path, text in rendered.items():
        assert path.is_file(), f"{path.relative_to(ROOT)} missing: python benchmarks/render_records.py"
        assert path.read_text() == text, (f"{path.relative_to(ROOT)} differs from its records "
                                          "(python benchmarks/render_records.py rewrites it)")


def test_a_planted_wrong_number_is_found(tmp_path):
    """A table with one figure changed (a ratio off by 0.01) is reported stale; so is a missing one."""
    records, d3rlpy = tmp_path / "benchmarks", ROOT / "results" / "d3rlpy"
    records.mkdir()
    rows = [summarise("case", "updates/s", {"torchrl_bail": [10.0, 12.0, 11.0], "bare": [10.0, 10.0, 10.0]})]
    record = Record("bench_x.py", records / "bench_x.json", reference="bare PyTorch").write(rows)
    assert record["table"][0]["ratio"] == pytest.approx(1.1)
    rendered = render_records.render_all(records, d3rlpy)
    table = records / "ratios.md"
    assert "| `bench_x.py` | case | 11.0 | bare PyTorch: 10.0 | updates/s | **1.10** | 3 |" in rendered[table]
    assert render_records.stale(records, d3rlpy) == list(rendered)  # nothing written yet
    for path, text in rendered.items():
        path.write_text(text)
    assert render_records.stale(records, d3rlpy) == []
    table.write_text(rendered[table].replace("**1.10**", "**1.11**"))
    assert render_records.stale(records, d3rlpy) == [table]


def test_the_ratio_table_names_scripts_that_exist():
    """A record saved under another name (``--json ..._bear_envelope.json``) is still shown as its script's row."""
    scripts = re.findall(r"^\| `([^`]+)` \|", (RECORDS_DIR / "ratios.md").read_text(), re.MULTILINE)
    assert "bench_paper_cost.py" in scripts
    assert [s for s in scripts if not (ROOT / "benchmarks" / s).is_file()] == []


@pytest.mark.parametrize("path", RECORDS, ids=[p.stem for p in RECORDS])
def test_a_record_states_its_run_and_every_round(path):
    record = json.loads(path.read_text())
    script = record["script"]  # a record is named after its script, a second run's with a suffix (--json)
    assert path.stem == script[:-3] or path.stem.startswith(script[:-3] + "_"), (path.name, script)
    assert (ROOT / "benchmarks" / script).is_file() and record["command"].startswith(f"python benchmarks/{script}")
    assert set(record["versions"]) >= {"python", *PACKAGES} and all(record["versions"][k] for k in PACKAGES)
    machine = record["machine"]
    assert machine["cpu_model"] and machine["cpus"] >= 1 and machine["torch_threads"] >= 1
    assert "OMP_NUM_THREADS" in machine and machine["affinity"]
    assert len(record["load_average"]["start"]) == 3 and len(record["load_average"]["end"]) == 3
    assert re.fullmatch(r"[0-9a-f]{40}", record["git"]["commit"]) and isinstance(record["git"]["uncommitted"], list)
    assert record["started"] <= record["finished"] and record["wall_s"] > 0 and record["process_cpu_s"] > 0
    for row in record["rows"]:
        assert "rounds" in row, row["name"]
        if "ratio_of" in row:  # every median and ratio follows from the rounds
            numerator, denominator = row["ratio_of"]
            for side, values in row["rounds"].items():
                assert row[side] == pytest.approx(statistics.median(values)), (row["name"], side)
            assert row["ratio"] == pytest.approx(row[numerator] / row[denominator]), row["name"]
    assert record["table"] == derive_table(record["rows"])


def test_derived_rows_are_medians_of_the_rounds():
    row = summarise("x", "updates/s", {"ours": [1.0, 5.0, 3.0], "theirs": [2.0, 2.0, 4.0, 100.0]},
                    ratio_of=("ours", "theirs"))
    assert (row["ours"], row["theirs"], row["ratio"]) == (3.0, 3.0, 1.0)
    assert derive_table([row, {"name": "no ratio", "rounds": {"a": [1.0]}}]) == [
        {"case": "x", "unit": "updates/s", "torchrl_bail": 3.0, "reference": 3.0, "ratio": 1.0, "rounds": 3}]


def test_a_d3rlpy_row_the_script_did_not_write_or_a_cell_given_twice_is_refused(tmp_path):
    (row, *_) = render_records.d3rlpy_rows(D3RLPY / "hopper_ddpg05_b1_bc_bcq.json")
    typed = tmp_path / "typed.json"  # a row copied from printed output has no curve
    typed.write_text(json.dumps([{k: v for k, v in row.items() if k != "d3rlpy_evaluations"}]))
    with pytest.raises(ValueError, match="typed.json: hopper_ddpg05_b1 bc seed 1 has no curve"):
        render_records.table_rows([typed])
    again = tmp_path / "again.json"
    again.write_text(json.dumps([row]))
    with pytest.raises(ValueError, match="bc seed 1 is in both hopper_ddpg05_b1_bc_bcq.json and again.json"):
        render_records.table_rows([D3RLPY / "hopper_ddpg05_b1_bc_bcq.json", again])


def test_the_ddpg05_rerun_records_both_curves_and_reproduces_the_study_seed_for_seed():
    """BC's and BCQ's seeds 1-3 on hopper_ddpg05_b1, as bench_d3rlpy_returns.py wrote them: each final return is
    the mean of its curve's last eval.final_window evaluations (both sides), and our side's return and curve are
    the study's runs of the same cells to every digit."""
    record = json.loads((D3RLPY / "hopper_ddpg05_b1_bc_bcq.json").read_text())
    assert record["script"] == "bench_d3rlpy_returns.py"
    assert record["command"].startswith("python benchmarks/bench_d3rlpy_returns.py --python .d3venv/bin/python ")
    assert sorted((r["algo"], r["seed"]) for r in record["rows"]) == [(a, s) for a in ("bc", "bcq") for s in (1, 2, 3)]
    window = OmegaConf.load(ROOT / "conf" / "preset" / "study.yaml").eval.final_window
    study = ROOT / "results" / "study" / "runs" / "hopper_ddpg05_b1"
    for row in record["rows"]:
        points = row["evaluated_at_updates"]
        assert points == sorted(points) and points[-1] == row["updates"]
        for side in ("torchrl_bail", "d3rlpy"):
            curve = row[f"{side}_evaluations"]
            assert len(curve) == len(points) and row[side] == pytest.approx(statistics.mean(curve[-window:]))
        run = study / row["algo"] / f"seed{row['seed']},preset=study"
        assert row["torchrl_bail"] == json.loads((run / "summary.json").read_text())["final_return"]
        logged = (run / "logs" / "scalars" / "eval" / "return.csv").read_text().splitlines()
        assert row["torchrl_bail_evaluations"] == [float(line.split(",")[1]) for line in logged]


def test_the_page_includes_every_table_and_names_no_machine_path():
    page = PAGE.read_text()
    for path in render_records.render_all():
        assert f'--8<-- "{path.relative_to(ROOT)}"' in page, path.name
    assert not re.search(r"/work/|/tmp/|d3venv/bin", page.replace(".d3venv/bin", "")), "a machine's own path"
    assert "passed in" not in page


def test_every_mean_quoted_on_the_page_is_a_rendered_one():
    """Prose quotes ``mean ± std`` figures only as a rendered d3rlpy table (of a record) states them."""
    page = PAGE.read_text()
    tables = "".join(render_records.render_all().values())
    quoted = re.findall(r"\d+\.\d ± \d+\.\d", page)
    assert quoted, "the page quotes no mean"
    for figure in quoted:
        assert figure in tables, figure


def test_the_paper_scale_section_quotes_its_records():
    """The costs the Paper scale section states are those of the paper cell's timings, its batch's metadata, the
    cost probe's record and the study's SAC collections."""
    page = PAGE.read_text()
    section = page[page.index("## Paper scale"):]
    results = ROOT / "results"
    wall = {job: round(t if isinstance(t, (int, float)) else t["wall_s"])
            for job, t in json.loads((results / "paper_hopper" / "timings.json").read_text()).items()}
    bail = [wall[f"hopper_ddpg05/bail/seed{s}"] for s in range(2, 6)]
    bc = [wall[job] for job in wall if job.startswith("hopper_ddpg05/bc/")]
    assert f"BAIL's jobs of seeds 2-5 took {min(bail)}-{max(bail)} s and BC's jobs {min(bc)}-{max(bc)} s" in section
    assert f"**{wall['hopper_ddpg05/bail/seed5']} s**" in section
    assert f"BAIL seed 1's {wall['hopper_ddpg05/bail/seed1']} s" in section
    flat_section = " ".join(section.split())
    for algo, name in (("BCQ", "bcq"), ("BEAR", "bear"), ("TD3+BC", "td3bc")):  # 10^5 updates each, 20 evaluations
        seconds = sorted(wall[job] for job in wall if job.startswith(f"hopper_ddpg05/{name}/"))
        rates = sorted(f"{10**5 / s:.1f}" for s in seconds)
        span = f"{seconds[0]}-{seconds[-1]} s" if len(seconds) > 1 else f"{seconds[0]} s"
        pace = f"{rates[0]}-{rates[-1]}" if len(rates) > 1 else rates[0]
        jobs = f"{len(seconds)} jobs" if len(seconds) > 1 else "job"
        assert f"{algo}'s {jobs} took {span} ({pace} updates/s" in flat_section, algo
    meta = json.loads((results / "paper_hopper" / "batches" / "hopper_ddpg05_b1-dcc2994b.metadata.json").read_text())
    assert (f"{meta['collection_wall_time_s']:.0f} s (2 h {meta['collection_wall_time_s'] / 60 - 120:.0f} min) at "
            f"{meta['env_steps_per_s']:.0f} env steps/s: {meta['num_transitions']}") in section
    flat = " ".join(section.split())
    assert f"{meta['num_episodes']} episodes, mean return {meta['episode_return_mean']:.1f}" in flat
    rows = [row for record in ("bench_paper_cost.json", "bench_paper_cost_bear_envelope.json",
                               "bench_paper_cost_td3bc.json")
            for row in json.loads((RECORDS_DIR / record).read_text())["rows"]]
    probe = {row["name"].split()[0]: row for row in rows}
    assert len(probe) == len(rows), "a probe measured in two records: say which one the page quotes"
    quoted = {"bc": "BC {:.1f} updates/s on one thread and {:.1f} on two (×{:.2f})",
              "bcq": "BCQ {:.1f} and {:.1f} (×{:.2f})", "bear": "BEAR {:.1f} and {:.1f} (×{:.2f})",
              "envelope": "envelope fit {:.2f} and {:.2f} epochs/s (×{:.2f})",
              "td3bc": "TD3+BC {:.1f} and {:.1f} (×{:.2f})"}
    for algo, text in quoted.items():
        row = probe[algo]
        assert text.format(row["threads=1"], row["threads=2"], row["ratio"]) in flat, algo
    minutes = {algo: 10**5 / probe[algo]["threads=1"] / 60 for algo in ("bcq", "bear")}
    assert (f"BCQ's 10^5 updates take about {minutes['bcq']:.0f} min and BEAR's about {minutes['bear']:.0f} min "
            "before their evaluations") in flat
    assert f"50 epochs take about {50 / probe['envelope']['threads=1'] / 60:.1f} min" in flat
    assert f"its 10^5 updates of 256 take about {10**5 / probe['td3bc']['threads=1'] / 60:.0f} min" in flat
    ratios = sorted(row["ratio"] for row in rows)
    assert f"A second thread pays (×{ratios[0]:.2f}-{ratios[-1]:.2f})" in flat
    sac = sorted(round(t) for job, t in json.loads((results / "study" / "timings.json").read_text()).items()
                 if job.startswith("collect/") and job.endswith("_sac"))
    assert f"SAC runs took {sac[0]}-{sac[-1]} s" in flat


def test_the_throughput_section_quotes_its_record():
    """The d3rlpy throughput prose states the ratios, the load and the rounds' spread of bench_d3rlpy.json."""
    record = json.loads((RECORDS_DIR / "bench_d3rlpy.json").read_text())
    flat = " ".join(PAGE.read_text().split())
    ratio = {row["name"].split()[0]: row["ratio"] for row in record["rows"]}
    assert f"level with d3rlpy** (ratios {ratio['BCQ']:.2f} and {ratio['BEAR']:.2f})" in flat
    assert f"**BC: {ratio['BC']:.2f}× d3rlpy's rate**" in flat
    spread = {kind: max(max(v) / min(v) for row in record["rows"] for side, v in row["rounds"].items()
                        if side.endswith(kind)) for kind in ("_wall", "_cpu")}
    assert (f"swung up to {spread['_wall']:.0f}-fold with the neighbours' load, its CPU-time rounds by at most "
            f"{spread['_cpu']:.1f}-fold") in flat
    assert f"load average {record['load_average']['start'][0]:.1f} at its start" in flat
    assert f"medians of {len(record['rows'][0]['rounds']['d3rlpy_cpu'])} alternating rounds" in flat


def test_a_case_name_shows_its_floats_at_their_shortest():
    assert render_records.case_name("bcq (algo.epochs 0.2 vs 0.6000000000000001)") == "bcq (algo.epochs 0.2 vs 0.6)"
    assert render_records.case_name("x 1.2345678901234 y 0.3") == "x 1.23456789012 y 0.3"
    assert "0.6000000000000001" not in render_records.render_ratios(render_records.load_records())


@pytest.mark.parametrize("name", ["kill_drill", "kill_drill_bcq"])
def test_the_interrupted_runs_guide_quotes_each_kill_drill_record(name):
    drill = json.loads((RECORDS_DIR / f"{name}.json").read_text())["drill"]
    landed = drill["landed"]
    assert sum(landed.values()) == drill["signals_sent"] == sum(len(t["stages"]) for t in drill["per_trial"])
    assert drill["matched"] == sum(not t["diffs"] for t in drill["per_trial"]) == drill["trials"]
    quoted = (f"{drill['matched']}/{drill['trials']} trials matched ({drill['signals_sent']} SIG{drill['signal']}s: "
              f"{landed['before the first checkpoint']} before the\nfirst checkpoint, {landed['mid-run']} mid-run, "
              f"{landed['after the end']} after the end; {drill['resumed']} trials resumed from a checkpoint)")
    page = " ".join((ROOT / "docs" / "guides" / "interrupted-runs.md").read_text().split())
    assert " ".join(quoted.split()) in page and f"{name}.json`" in page


def test_the_fail_fast_figures_are_the_records():
    """Adding an algorithm's "fails in X s, where importing one algorithm's module takes Y s (×R)" is
    ``bench_fail_fast.json``'s medians, and the bad command line is the faster by far."""
    record = json.loads((RECORDS_DIR / "bench_fail_fast.json").read_text())
    (row,) = [r for r in record["rows"] if r["name"].startswith("bad command line")]
    guide = " ".join((ROOT / "docs" / "guides" / "adding-an-algorithm.md").read_text().split())
    rounds = len(row["rounds"]["bad command line"])
    assert (f"it fails in {row['bad command line']:.2f} s, where importing one algorithm's module takes "
            f"{row['algorithm module']:.2f} s (×{row['ratio']:.2f}; medians of {rounds} fresh processes") in guide
    assert row["ratio"] < 0.5


def test_the_ope_guide_quotes_the_fqe_record():
    """The FQE throughput the guide states (rates, ratio, rounds, whole fits, load) is ``bench_fqe.json``'s."""
    record = json.loads((RECORDS_DIR / "bench_fqe.json").read_text())
    assert record["script"] == "bench_fqe.py" and record["reference"] == "bare PyTorch"
    assert record["machine"]["affinity"] == [1] and record["machine"]["torch_threads"] == 1
    update, fit = record["rows"]
    assert update["name"].startswith("FQE update") and fit["name"].startswith("FQE whole fit")
    rounds = len(update["rounds"]["torchrl_bail"])
    guide = " ".join((ROOT / "docs" / "guides" / "ope.md").read_text().split())
    assert (f"FQE's update ran at {update['torchrl_bail']:.1f} updates/s, the bare twin's at {update['bare']:.1f} "
            f"(ratio {update['ratio']:.2f}, medians of {rounds} rounds of {update['updates_per_round']} updates a "
            f"side)") in guide
    assert (f"whole fits of {fit['updates_per_round']} updates, with the policy's actions and the estimate, ran at "
            f"{fit['torchrl_bail']:.1f} and {fit['bare']:.1f} updates/s (ratio {fit['ratio']:.2f}, "
            f"{len(fit['rounds']['bare'])} fits a side)") in guide
    assert f"(load average {record['load_average']['start'][0]:.1f} at its start)" in guide
    assert "`results/benchmarks/bench_fqe.json`" in guide


def test_the_many_seeds_guide_quotes_the_seed_stack_record():
    """The stacked updates' range (lowest and highest ratio, with their algorithms) and the envelope fit's ratio the
    guide states are ``bench_seed_stack.json``'s."""
    record = json.loads((RECORDS_DIR / "bench_seed_stack.json").read_text())
    names = {"bail": "BAIL", "pbail": "Progressive BAIL", "bc": "BC", "marwil": "MARWIL", "bcq": "BCQ", "bear": "BEAR"}
    updates = sorted((row["ratio"], names[row["name"].split()[0]]) for row in record["rows"]
                     if " update " in row["name"])
    (envelope,) = [row for row in record["rows"] if row["name"].startswith("bail envelope fit")]
    guide = " ".join((ROOT / "docs" / "guides" / "many-seeds.md").read_text().split())
    (low, low_algo), (high, high_algo) = updates[0], updates[-1]
    rounds = len(record["rows"][0]["rounds"]["stacked_per_s"])
    assert (f"({low:.2f} for {low_algo} to {high:.2f} for {high_algo}, one run each, {rounds} rounds a side)"
            in guide)
    envelope_rounds = len(envelope["rounds"]["stacked_per_s"])
    assert f"The stacked envelope fit is faster ({envelope['ratio']:.2f}, {envelope_rounds} rounds)" in guide


def test_the_compile_guide_quotes_the_compile_record():
    record = json.loads((RECORDS_DIR / "bench_compile.json").read_text())
    rows = {row["algo"]: row for row in record["rows"]}
    guide = " ".join((ROOT / "docs" / "guides" / "compiled-updates.md").read_text().split())
    assert (f"×{rows['bc']['ratio']:.2f} for BC and ×{rows['marwil']['ratio']:.2f} for MARWIL (batch 1000) from "
            f"{len(rows['bc']['rounds']['eager_updates_per_s'])} rounds a side") in guide
    assert f"after {max(row['compile_s'] for row in rows.values()):.0f} s of compiling each" in guide
    assert max(row["compile_s"] for row in rows.values()) - min(row["compile_s"] for row in rows.values()) < 1


def test_the_page_names_every_ratio_below_the_issues_floor():
    """"One ratio lies below the issues' 0.8 now, ...": of the rows that set the package against a reference (its
    rate over the reference's), those under 0.8 are the ones the page names."""
    below = [(row["name"], row["ratio"]) for record in render_records.load_records().values()
             for row in record["rows"] if str((row.get("ratio_of") or [""])[0]).startswith("torchrl_bail")
             and row["ratio"] < 0.8]
    flat = " ".join(PAGE.read_text().split())
    assert len(below) == 1 and below[0][0].startswith("FQE update")
    assert f"One ratio lies below the issues' 0.8 now, FQE's update ({below[0][1]:.2f};" in flat


def test_the_threads_section_quotes_its_record():
    """The Threads section's ratios and rates are those of ``bench_threads.json``, and they support the default it
    states: beside busy processes one thread is faster than two in every workload."""
    record = json.loads((RECORDS_DIR / "bench_threads.json").read_text())
    rows = {(row["workload"], row["busy"]): row for row in record["rows"]}
    flat = " ".join(PAGE.read_text().split())
    section = flat[flat.index("## Threads on a busy CPU"):flat.index("## Paper scale")]
    assert f"the campaign's job was paused for its {record['wall_s']:.0f} s" in section
    ratios = {key: f"{row['ratio']:.2f}×" for key, row in rows.items()}
    assert (f"a second thread runs the collection at {ratios['collection', 0]} and the envelope fit at "
            f"{ratios['envelope', 0]} of one thread; beside one busy process at {ratios['collection', 1]} and "
            f"{ratios['envelope', 1]}, beside two at {ratios['collection', 2]} and {ratios['envelope', 2]}") in section
    one = {key: row["threads=1"] for key, row in rows.items()}
    assert (f"({one['collection', 1]:.1f} env steps/s and {one['envelope', 1]:.1f} updates/s against "
            f"{one['collection', 0]:.1f} and {one['envelope', 0]:.1f} idle)") in section
    assert all(row["ratio"] < 1 for (_, busy), row in rows.items() if busy), "the default's reason no longer holds"

"""The documentation cannot rot: the configuration reference is generated from the schemas and fails on an
undocumented field, and every tutorial script runs here at tiny scale (the site itself is built by ``.ci/run``)."""

from __future__ import annotations

import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from _contract import _SMALL_POLICY, TINY_RUN
from test_importers import minari_episode, write_minari

ROOT = Path(__file__).resolve().parents[1]
TUTORIALS = ROOT / "docs" / "tutorials"


def _generator():
    spec = importlib.util.spec_from_file_location("gen_config_reference", ROOT / "docs" / "gen_config_reference.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


gen = _generator()


# ---------------------------------------------------------------------------------------------------------------
# the configuration reference
# ---------------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def sections():
    return gen.collect()


def _row(sections, group, key):
    return next(r for s in sections if s.group == group for r in s.rows if r.key == key)


def test_every_schema_field_has_a_one_line_doc(sections):
    assert gen.missing_docs(sections) == []
    documented = {(s.group, r.key) for s in sections for r in s.rows}
    # every schema of both registries appears, with all of its fields
    from torchrl_bail.configuration.algo_schemas import ALGO_SCHEMAS
    from torchrl_bail.configuration.batch_schemas import BATCH_SCHEMAS
    from torchrl_bail.configuration.config import Config
    schemas = {s.schema for s in sections}
    assert set(ALGO_SCHEMAS.values()) | set(BATCH_SCHEMAS.values()) | {Config} <= schemas
    assert ("algo", "envelope.early_stopping") in documented and ("batch", "sac.log_prob_on") in documented


def test_a_row_joins_the_schema_and_the_yaml(sections):
    row = _row(sections, "algo", "selection.percentile")  # BAIL's section comes first among the algo rows
    assert (row.type, row.allowed, row.defaults) == ("float", "a fraction in (0, 1]", {"bail": 0.3})
    assert row.doc.startswith("p (the paper's 30%")
    steps = _row(sections, "batch", "steps")
    assert steps.defaults == {"ddpg01": 1000000, "ddpg05": 1000000}
    assert steps.presets == {"ddpg01": {"quick": 50000, "study": 50000}, "ddpg05": {"quick": 50000, "study": 50000}}
    assert _row(sections, None, "checkpoint.every_minutes").type == "float or null"
    # a top-level key that only some algorithms' preset files set says which
    every = _row(sections, None, "eval.every_epochs").presets["default"]
    assert every["quick with bcq, bear"] == 0.1 and "quick" not in every
    # a comment continued on the next line is one meaning
    assert _row(sections, None, "seeds").doc.endswith("(docs: Many seeds in one process)")
    # bear.yaml borrows bcq.yaml's comments of the block both inherit (vae), never those of a block of its own
    bcq, bear = ({r.key: r.doc for r in s.rows} for name in ("bcq", "bear") for s in sections if s.options == [name])
    assert "vae.hidden" not in gen.yaml_comments(ROOT / "conf" / "algo" / "bear.yaml")
    assert bear["vae.hidden"] == bcq["vae.hidden"] == "VAE encoder and decoder MLPs"
    assert bear["actor.hidden"] != bcq["actor.hidden"]


def test_an_undocumented_field_fails_with_its_name(tmp_path):
    conf = shutil.copytree(ROOT / "conf", tmp_path / "conf")
    bail = conf / "algo" / "bail.yaml"
    bail.write_text(re.sub(r"(?m)^(  penalty: 1000.0) +#.*$", r"\1  #", bail.read_text()))  # an empty comment
    with pytest.raises(gen.MissingDocs, match=r"yaml: algo\.envelope\.penalty \(BAILConfig\); add '# <meaning>'"):
        gen.generate(conf)


def test_yaml_comments_continue_below_and_block_comments_belong_to_no_key(tmp_path):
    path = tmp_path / "x.yaml"
    path.write_text("# a block comment\na: 1   # first line\n        # second line\n# about b\nb:\n"
                    "  c: 'x # not a comment'   # the c\n  d: [1, 2]\n")
    assert gen.yaml_comments(path) == {"a": "first line second line", "b.c": "the c"}


def test_the_page_renders_pipes_and_tags_inside_tables(sections):
    text = gen.render(sections)
    line = next(row for row in text.splitlines() if row.startswith("| `device` |"))
    assert "cpu \\| cuda \\| cuda:N \\| auto" in line
    line = next(row for row in text.splitlines() if row.startswith("| `logger.name` |"))
    assert "&lt;algo&gt;\\_seed&lt;seed&gt;" in line


def _html(table_row: str) -> str:
    """One row of the page's tables as the site renders it."""
    import markdown

    return markdown.markdown("| a | b | c | d | e |\n|---|---|---|---|---|\n" + table_row, extensions=["tables"])


def test_the_page_shows_underscores_and_asterisks_as_written(sections):
    text = gen.render(sections)
    cell = _html(next(row for row in text.splitlines() if row.startswith("| `logger.name` |")))
    assert "<em>" not in cell and "&lt;algo&gt;_seed&lt;seed&gt;_&lt;run dir name&gt;" in cell
    assert gen._cell("a*b*c and x_y_z") == "a\\*b\\*c and x\\_y\\_z"
    assert "<em>" not in _html(f"| k | str | 1 | x | {gen._cell('a*b*c and _y_ z')} |")


def test_enumerated_strings_show_their_values(sections):
    from torchrl_bail.configuration.algo_schemas import ALGO_SCHEMAS
    from torchrl_bail.configuration.config import RESUME_MODES

    resume = _row(sections, None, "resume")
    assert resume.type == "enum or path"
    assert resume.allowed == " · ".join(f"`{m}`" for m in RESUME_MODES) + " · an existing run directory"
    backend = _row(sections, None, "logger.backend")
    assert backend.type == "enum" and "`tensorboard`" in backend.allowed
    envs = sorted(p.stem for p in (ROOT / "conf" / "env").glob("*.yaml"))
    assert _row(sections, "env", "name").allowed.startswith(" · ".join(f"`{e}`" for e in envs) + " (or ")
    kinds = {k for s in sections if s.group == "batch" for r in s.rows if r.key == "kind"
             for k in re.findall(r"`(\w+)`", r.allowed)}
    assert kinds == {p.stem for p in (ROOT / "conf" / "batch").glob("[!_]*.yaml")}
    names = {r.allowed.split("`")[1] for s in sections if s.group == "algo" for r in s.rows if r.key == "name"}
    assert names == set(ALGO_SCHEMAS)
    assert "| `env.name` | str | the option's name (`ant` in `env=ant`) |" in gen.render(sections)
    free = {f"{s.group or ''}.{r.key}" for s in sections for r in s.rows if r.type == "str" and not r.allowed}
    assert free == {".logger.project", "env.id"}  # free text; any other string key names what it allows


# ---------------------------------------------------------------------------------------------------------------
# the tutorials, at tiny scale
# ---------------------------------------------------------------------------------------------------------------

#: the tiny run's overrides (a 600-transition batch of a tiny DDPG, 100-step episodes), for every tutorial's runs
TINY = [o for o in TINY_RUN if not o.startswith(("+exp=", "preset="))] + ["algo.epochs=0.004", _SMALL_POLICY]


def _script(path: Path, *args: str, cwd: Path, data_dir: Path) -> str:
    env = {**os.environ, "TORCHRL_BAIL_DATA_DIR": str(data_dir), "OMP_NUM_THREADS": "1",
           "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, str(path), *args], check=False, cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return proc.stdout


def _tutorial(name: str, *args: str, cwd: Path, data_dir: Path) -> str:
    """Runs a tutorial script and checks its output against its page's expected output (:func:`_shows`)."""
    out = _script(TUTORIALS / name, *args, cwd=cwd, data_dir=data_dir)
    page = next(p for p in TUTORIALS.glob("*.md") if f'--8<-- "docs/tutorials/{name}"' in p.read_text())
    _shows(page, out)
    return out


#: a number (or a comma-separated list of them, ``seed=1,2,3``, ``[1, 2, 3]``) in an expected-output line: any number
#: (or list) matches it (the pages show the default scale, the tests run tiny)
_NUMBER = r"[-+]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?(?:, ?[-+]?\d+(?:\.\d*)?)*"


def expected_output(page: Path) -> list[str]:
    """The lines of a page's expected output: the ```text block right after a paragraph that starts with
    "Expected output" (a line holding only ``…`` stands for lines left out)."""
    block = re.search(r"^Expected output[^\n]*(?:\n[^\n]+)*\n\n```text\n(.*?)^```", page.read_text(), re.M | re.S)
    assert block, f"{page.name}: no 'Expected output' paragraph followed by a ```text block"
    return [line for line in block.group(1).splitlines() if line.strip() not in ("", "…")]


def _line_pattern(line: str) -> re.Pattern:
    """An expected line as a pattern: any number for a number, anything for ``…``, any run of spaces for spaces,
    bold marks ignored."""
    parts = re.split(f"(…|{_NUMBER}|\\s+)", " ".join(line.replace("**", "").split()))
    return re.compile("".join(".*" if p == "…" else _NUMBER if re.fullmatch(_NUMBER, p or "x") else
                              r"\s+" if p.isspace() else re.escape(p) for p in parts))


def _matches(expected: str, line: str) -> bool:
    """Whether an output line has the expected line's shape. A command line (``python -m torchrl_bail...``) matches
    one holding its words in order, whatever else is between them: the tests add Hydra overrides."""
    if " -m torchrl_bail." not in expected:
        return bool(_line_pattern(expected).fullmatch(line))
    words = iter(line.split())
    return all(any(_line_pattern(want).fullmatch(word) for word in words) for want in expected.split())


def _shows(page: Path, out: str) -> None:
    """Every line of the page's expected output has a line of the same shape in ``out`` (the words as shown, any
    numbers): a renamed or dropped output line fails, while the page keeps the default scale's numbers."""
    lines = [" ".join(line.replace("**", "").split()) for line in out.splitlines()]
    missing = [e for e in expected_output(page) if not any(_matches(e, x) for x in lines)]
    assert not missing, f"{page.name} shows lines the script no longer prints: {missing}\n--- it printed:\n{out}"


def test_every_tutorial_script_has_a_page_and_a_test():
    pages = "".join(p.read_text() for p in TUTORIALS.glob("*.md"))
    tested = Path(__file__).read_text()
    for script in TUTORIALS.glob("*.py"):
        assert f'--8<-- "docs/tutorials/{script.name}"' in pages, script.name
        assert f'_tutorial("{script.name}"' in tested, script.name


def test_every_tutorial_script_takes_the_work_dir_the_index_promises():
    assert "Every script takes `--work-dir`" in (TUTORIALS / "index.md").read_text()
    for script in TUTORIALS.glob("*.py"):
        assert re.search(r'add_argument\("--work-dir", type=Path', script.read_text()), script.name


def test_tutorial_pages_use_the_options_their_scripts_define():
    for page in [*TUTORIALS.glob("*.md"), *TUTORIALS.glob("*.py")]:  # the pages and the scripts' usage lines
        for script, args in re.findall(r"python docs/tutorials/(\w+\.py)([^\n#]*)", page.read_text()):
            source = (TUTORIALS / script).read_text()
            for flag in re.findall(r"(?<!\S)--[a-z][\w-]*", args):
                assert f'"{flag}"' in source, f"{page.name}: {script} has no option {flag}"


def test_every_tutorial_page_shows_its_expected_output():
    for page in TUTORIALS.glob("*.md"):
        if page.name != "index.md":
            assert len(expected_output(page)) >= 2, page.name


def test_expected_lines_match_by_shape(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("Expected output (numbers vary):\n\n```text\nseed 1: final_return 742.1 at …\n…\n"
                    "| hopper_ddpg05_b1 | 290.1 | **835.1 ± 81.4** |\n```\n")
    assert expected_output(page) == ["seed 1: final_return 742.1 at …",
                                     "| hopper_ddpg05_b1 | 290.1 | **835.1 ± 81.4** |"]
    _shows(page, "x\nseed 2: final_return  -3.5e-02 at /tmp/a\n| hopper_ddpg05_b1 | 12.0 | 1.5 ± 0.2 |\n")
    with pytest.raises(AssertionError, match="final_return"):
        _shows(page, "seed 2: final return 3.5 at /tmp/a\n| hopper_ddpg05_b1 | 12.0 | 1.5 ± 0.2 |\n")
    command = "$ python -m torchrl_bail.train +exp=hopper_ddpg05 'seeds=[1,2,3]' hydra.run.dir=x"
    assert _matches(command, "$ python -m torchrl_bail.train +exp=hopper_ddpg05 eval.episodes=1 'seeds=[1,2]' "
                             "hydra.run.dir=x progress=false")
    assert not _matches(command, "$ python -m torchrl_bail.train +exp=hopper_ddpg05 'seeds=[1,2]'")
    assert not _matches(command, "$ python -m torchrl_bail.train 'seeds=[1,2]' +exp=hopper_ddpg05 hydra.run.dir=x")


def test_tutorial_reproduce_a_row(tmp_path, tiny_run_data_dir):
    out = _tutorial("reproduce_a_row.py", "--seeds", "1,2", *TINY, cwd=tmp_path, data_dir=tiny_run_data_dir)
    table = (tmp_path / "tutorial_row" / "row.md").read_text()
    assert table.splitlines()[0].startswith("| batch | data | bail | bc |")
    scores = [line for line in out.splitlines() if re.match(r" *(bail|bc) seed [12]: final_return ", line)]
    assert "hopper_ddpg05_b1" in table and len(scores) == 4


def test_tutorial_bring_your_own_data(tmp_path, tiny_run_data_dir):
    minari = write_minari(tmp_path / "minari", [minari_episode(40, "terminal", 10 * i) for i in range(8)])
    out = _tutorial("bring_your_own_data.py", "--steps", "600", "--minari", str(minari), *TINY, cwd=tmp_path,
                    data_dir=tmp_path / "data")
    assert "d4rl: 600 transitions" in out and "minari: 320 transitions, 8 episodes" in out
    assert out.count("normalised") == 2  # Hopper has D4RL reference scores
    assert (tmp_path / "tutorial_data" / "run_minari" / "summary.json").is_file()


def test_tutorial_losses_in_a_torchrl_loop(tmp_path):
    out = _tutorial("losses_in_a_torchrl_loop.py", "--steps", "600", "--envelope-epochs", "2", "--updates", "10",
                    "--eval-steps", "50", cwd=tmp_path, data_dir=tmp_path / "data")
    assert "selected 180 of 600 pairs" in out and "evaluation: return" in out
    assert {p.name for p in (tmp_path / "tutorial_losses").iterdir()} == {"actor.pt", "envelope.pt"}


def test_tutorial_sweep_seeds(tmp_path, tiny_run_data_dir):
    out = _tutorial("sweep_seeds.py", "--seeds", "1,2", *TINY, cwd=tmp_path, data_dir=tiny_run_data_dir)
    assert "hydra/launcher=slurm" in out and "hydra/launcher=joblib" in out
    for seed in (1, 2):  # the stacked run gives each seed its single-seed score
        line = next(row for row in out.splitlines() if row.startswith(f"seed {seed}: final_return"))
        alone, stacked = (float(w) for w in line.replace(",", "").split() if w.replace(".", "").lstrip("-").isdigit())
        assert stacked == pytest.approx(alone, rel=1e-4, abs=1e-3)


def test_tutorial_resume_a_killed_run(tmp_path, tiny_run_data_dir):
    out = _tutorial("resume_a_killed_run.py", *TINY, "algo.epochs=0.03", cwd=tmp_path, data_dir=tiny_run_data_dir)
    assert "killed" in out.splitlines() and "the summaries agree in every score" in out


def test_tutorial_load_evaluate_export(tmp_path, tiny_run_data_dir):
    out = _tutorial("load_evaluate_export.py", "--episodes", "2", *TINY, cwd=tmp_path, data_dir=tiny_run_data_dir)
    assert "bail policy for Hopper-v5: observation 11 -> action 3" in out
    for fmt in ("pt2", "onnx"):
        line = next(row for row in out.splitlines() if row.startswith(f"{fmt} export"))
        assert float(line.split()[-1]) < 1e-5


# ---------------------------------------------------------------------------------------------------------------
# the known issues: each reproduction still shows its bug (when one stops, it is fixed upstream: update the page)
# ---------------------------------------------------------------------------------------------------------------

KNOWN_ISSUES = ROOT / "docs" / "known_issues"


def test_every_known_issue_script_has_a_section_and_a_test():
    page = (ROOT / "docs" / "known-issues.md").read_text()
    tested = Path(__file__).read_text()
    for script in KNOWN_ISSUES.glob("*.py"):
        assert f'--8<-- "docs/known_issues/{script.name}"' in page, script.name
        assert f'KNOWN_ISSUES / "{script.name}"' in tested, script.name


def test_known_issue_torchrl_minari_zeros(tmp_path):
    """TorchRL 0.14.1's MinariExperienceReplay returns zeros for a Minari dataset; this package's importer does not.
    If this fails on the zeros, TorchRL has fixed its reader: update docs/known-issues.md (and the strict xfail in
    tests/test_minari_export.py)."""
    pytest.importorskip("minari")
    out = _script(KNOWN_ISSUES / "torchrl_minari_zeros.py", cwd=tmp_path, data_dir=tmp_path / "data")
    assert "rewards equal Minari's: True" in out, out
    assert re.search(r"^minari: .*reward sum -\d", out, re.M), out  # the file holds real, negative rewards
    assert "every value is zero: True" in out, ("TorchRL's MinariExperienceReplay returns the dataset's values now: "
                                                "the bug is fixed; update docs/known-issues.md\n" + out)
    _shows(ROOT / "docs" / "known-issues.md", out)


# ---------------------------------------------------------------------------------------------------------------
# the README: short, its two commands those of Getting started, its links alive (mkdocs checks the site's own)
# ---------------------------------------------------------------------------------------------------------------


def _first_bash_block(text: str) -> str:
    return re.search(r"```bash\n(.*?)```", text[text.index("## Two commands"):], re.DOTALL).group(1)


def test_readme_is_short_and_shares_its_two_commands_with_getting_started():
    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) <= 200, "the README is the front door; long sections belong on a docs page"
    commands = _first_bash_block(readme)
    assert "python -m torchrl_bail.train +exp=hopper_ddpg05 preset=quick seed=1" in commands
    assert commands == _first_bash_block((ROOT / "docs" / "getting-started.md").read_text())
    assert commands == _first_bash_block((ROOT / "docs" / "index.md").read_text()), "the home page leads with them"


def test_readme_links_point_to_files_that_exist():
    readme = (ROOT / "README.md").read_text()
    targets = [t for t in re.findall(r"\]\(([^)\s]+)\)", readme) if not t.startswith(("http://", "https://"))]
    assert len(targets) > 10
    missing = [t for t in targets if not (ROOT / t.split("#")[0]).exists()]
    assert missing == []


def test_readme_names_every_registered_algorithm_in_the_registrys_order():
    """The README's Algorithms paragraph is written by hand; the registry decides what it must name."""
    from torchrl_bail.configuration.algo_schemas import ALGO_SCHEMAS

    readme = (ROOT / "README.md").read_text()
    section = readme[readme.index("## Algorithms"):readme.index("\n## ", readme.index("## Algorithms") + 1)]
    assert re.findall(r"`algo=(\w+)`", section) == list(ALGO_SCHEMAS)


def _table(text: str, key: str) -> dict[str, dict[str, str]]:
    """The first Markdown table of ``text`` whose header starts with ``| key |``: ``{first cell: {column: cell}}``,
    bold marks dropped."""
    lines = text[text.index(f"| {key} |"):].splitlines()
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    rows = {}
    for line in lines[2:]:
        if not line.startswith("|"):
            break
        cells = [c.strip().replace("**", "") for c in line.strip("|").split("|")]
        rows[cells[0]] = dict(zip(header, cells, strict=True))
    return rows


def _cross_batch_entry(batch: str) -> dict:
    """``batch``'s entry of the cross-batch report (``results/paper_batches/cross_batch.json``)."""
    report = json.loads((ROOT / "results" / "paper_batches" / "cross_batch.json").read_text())
    return next(b for b in report["batches"] if b["batch"] == batch)


def test_the_home_pages_headline_result_is_the_results_own():
    """Every figure of the home page's headline table is the one its results file holds: the study's Hopper DDPG
    sigma = 0.5 row, the paper-scale cell (results/paper_hopper: its report and its batch's metadata), and the
    Walker2d, Hopper sigma = 0.1 and Hopper sigma = 0.5 B2 batches of the cross-batch study
    (results/paper_batches/cross_batch.json: every seed of the row's three cells); BAIL, BC and BCQ, the best of
    each row in bold, and the sentences on BCQ's order against BAIL (and against BC where it ends level with it) are
    the data's."""
    page = (ROOT / "docs" / "index.md").read_text()
    headline = page[page.index("## The headline result"):page.index("## Where to start")]
    home = _table(headline, "batch")
    small = home["Hopper-v5, 50k transitions (`preset=study`)"]
    paper = home["Hopper-v5, 10^6 transitions, the paper's size (`preset=paper`)"]
    walker = home["Walker2d-v5, 10^6 transitions (`preset=paper`)"]
    sigma01 = home["Hopper-v5 σ = 0.1, 10^6 transitions (`preset=paper`)"]
    b2 = home["Hopper-v5 σ = 0.5 B2 (the same recipe, another behaviour seed), 10^6 transitions (`preset=paper`)"]
    text = " ".join(headline.split())
    for row, batch_label, published in ((walker, "walker_ddpg05_b1", "2522 ± 51 on the Walker2d one"),
                                        (sigma01, "hopper_ddpg01_b1", "2173 ± 291 on the σ = 0.1 one"),
                                        (b2, "hopper_ddpg05_b2", "2623 ± 282 on the B2 one")):
        across = _cross_batch_entry(batch_label)
        assert [row["the batch's own mean episode return"], row["BAIL"], row["BC"], row["BCQ"]] == [
            f"{across['metadata']['episode_return_mean']:.1f}",
            *(f"{across['cells'][a]['final_return_mean']:.1f} ± {across['cells'][a]['final_return_std']:.1f}"
              for a in ("bail", "bc", "bcq"))]
        assert [across["cells"][a]["seeds"] for a in ("bail", "bc", "bcq")] == [5, 5, 3]
        assert published in text and across["published_bail"] == published.split(" on ")[0]
        claim = next(c for c in across["claims"] if c["claim"].startswith("BAIL above BCQ"))
        assert claim["verdict"].startswith("holds"), (batch_label, claim)
    bc, bcq = (_cross_batch_entry("hopper_ddpg01_b1")["cells"][a] for a in ("bc", "bcq"))
    assert "(there BCQ ends level with BC)" in text
    assert bcq["final_return_iqm_ci_low"] <= bc["final_return_iqm_ci_high"], "level: the IQM intervals overlap"
    assert bc["final_return_iqm_ci_low"] <= bcq["final_return_iqm_ci_high"], "level: the IQM intervals overlap"
    study = _table((ROOT / "results" / "study" / "study.md").read_text(), "batch")["hopper_ddpg05_b1"]
    assert [small["the batch's own mean episode return"], small["BAIL"], small["BC"], small["BCQ"]] == [
        study["data"], study["bail"], study["bc"], study["bcq"]]
    cell = _table((ROOT / "results" / "paper_hopper" / "cell.md").read_text(), "algorithm")
    batch = json.loads((ROOT / "results" / "paper_hopper" / "batches" /
                        "hopper_ddpg05_b1-dcc2994b.metadata.json").read_text())
    assert [paper["the batch's own mean episode return"], paper["BAIL"], paper["BC"], paper["BCQ"]] == [
        f"{batch['episode_return_mean']:.1f}", cell["bail"]["mean ± std"], cell["bc"]["mean ± std"],
        cell["bcq"]["mean ± std"]]
    runs = ROOT / "results" / "study" / "runs" / "hopper_ddpg05_b1"
    seeds = [sum(bool(re.fullmatch(r"seed\d+,preset=study", d.name)) for d in (runs / algo).iterdir())
             for algo in ("bail", "bc", "bcq")]
    assert seeds == [5, 5, 3], "the study's runs of the cell without overrides"
    assert cell["bail"]["seeds"] == cell["bc"]["seeds"] == "5" and cell["bcq"]["seeds"] == "3"
    assert "over 5 seeds (BCQ: 3 seeds)" in page
    assert "2054 ± 158" in page and cell["bail"]["published (gym v2)"] == "2054 ± 158"
    rows = (small, paper, walker, sigma01, b2)
    for row in rows:  # the bold cell is the row's best mean
        means = {algo: float(row[algo].split(" ± ")[0]) for algo in ("BAIL", "BC", "BCQ")}
        best = max(means, key=means.get)
        assert f"**{row[best]}**" in headline and headline.count("**") == 2 * len(rows), (best, row)
    mean = {k: float(v.split(" ± ")[0]) for k, v in (("study bail", study["bail"]), ("study bcq", study["bcq"]),
                                                       ("cell bail", cell["bail"]["mean ± std"]),
                                                       ("cell bcq", cell["bcq"]["mean ± std"]))}
    assert "0.5 % on the 50k batch, where it ends below BAIL" in text and mean["study bcq"] < mean["study bail"]
    assert "(10^5 updates) at the paper's size. There it ends above BAIL on the σ = 0.5 Hopper batch" in text
    assert mean["cell bcq"] > mean["cell bail"]
    assert "far below BAIL on Walker2d and on Hopper's σ = 0.1 batch, where the claim holds" in text
    verdict = next(c["verdict"] for c in json.loads((ROOT / "results" / "paper_hopper" / "cell.json").read_text())[
        "claims"] if (c["a"], c["b"]) == ("bail", "bcq"))
    assert verdict.startswith("does not hold") and "BAIL beats BCQ does not hold on this batch" in text
    assert ("B2), BCQ ends below BAIL and the claim holds: BCQ's lead on the first "
            "σ = 0.5 batch belongs to that batch, not to its recipe") in text, "B2's reading"


def test_getting_started_quotes_the_kept_run_of_the_first_command():
    """Getting started's numbers are those of ``results/getting_started`` (the run behind its figures)."""
    page = (ROOT / "docs" / "getting-started.md").read_text()
    kept = ROOT / "results" / "getting_started"
    summary = json.loads((kept / "summary.json").read_text())
    batch = json.loads((kept / "batch_metadata.json").read_text())
    collect = json.loads((ROOT / "results" / "study" / "timings.json").read_text())["collect/hopper_ddpg05"]
    assert summary["batch_path"].endswith(f"{batch['name']}-{batch['recipe_hash']}")
    assert (kept / "config.yaml").is_file() and (kept / "logs" / "scalars" / "eval" / "return.csv").is_file()
    quoted = (f"`final_return` {summary['final_return']:.1f}, best evaluation\n{summary['best_return']:.1f}, "
              f"batch mean episode return {summary['dataset_mean_episode_return']:.1f})")
    assert quoted in page
    assert f"Its training took {summary['wall_time_s']:.0f} s there" in page
    assert f"{collect:.0f} s and {batch['collection_wall_time_s']:.0f} s in two collections" in page
    for figure in ("learning_curve.png", "envelope.png"):
        assert (kept / figure).is_file() and f"](assets/getting_started/{figure})" in page


def test_the_readme_quotes_the_first_command_run_on_a_busy_machine():
    """README command 1 keeps its promise (under an hour) beside other work with one thread, and ends on the kept
    run's numbers: the README's figure is the record's (``results/getting_started/busy_machine.json``)."""
    record = json.loads((ROOT / "results" / "getting_started" / "busy_machine.json").read_text())
    kept = json.loads((ROOT / "results" / "getting_started" / "summary.json").read_text())
    assert record["torch_threads"] == record["collection_threads"] == 1 and record["wall_s"] < 3600
    assert record["same_as_kept_run"] and record["final_return"] == kept["final_return"]
    flat = " ".join((ROOT / "README.md").read_text().split())
    assert f"the whole command took {record['wall_s']:.0f} s from an empty data directory" in flat


KEPT_TUTORIALS = ROOT / "results" / "tutorials"
TUTORIAL_PAGES = sorted(p for p in TUTORIALS.glob("*.md") if p.name != "index.md")


def _tutorial_script(page: Path) -> str:
    return re.search(r'--8<-- "docs/tutorials/(\w+)\.py"', page.read_text()).group(1)


def _exact_line(line: str) -> re.Pattern:
    """An expected line as a pattern that keeps every word and number: only ``…`` stands for anything."""
    parts = re.split(r"(…|\s+)", " ".join(line.replace("**", "").split()))
    return re.compile("".join(".*" if p == "…" else r"\s+" if p.isspace() else re.escape(p) for p in parts))


@pytest.mark.parametrize("page", TUTORIAL_PAGES, ids=[p.stem for p in TUTORIAL_PAGES])
def test_a_tutorial_page_quotes_its_kept_run(page):
    """The numbers a page shows are those its script printed at the default scale (``results/run_tutorials.py``)."""
    script = _tutorial_script(page)
    assert json.loads((KEPT_TUTORIALS / "record.json").read_text())[script]["exit_status"] == 0
    kept = [" ".join(line.replace("**", "").split())
            for line in (KEPT_TUTORIALS / f"{script}.txt").read_text().splitlines()]
    missing = [e for e in expected_output(page) if not any(_exact_line(e).fullmatch(line) for line in kept)]
    assert not missing, f"{page.name} shows lines its kept run (results/tutorials/{script}.txt) lacks: {missing}"


def _duration(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 90 else f"{seconds / 60:.0f} min"


def test_the_tutorial_index_quotes_the_kept_runs_times():
    record = json.loads((KEPT_TUTORIALS / "record.json").read_text())
    rows = (TUTORIALS / "index.md").read_text().splitlines()
    for page in TUTORIAL_PAGES:
        entry = record[_tutorial_script(page)]
        (row,) = [r for r in rows if r.startswith("| [") and f"]({page.name})" in r]
        assert row.endswith(f"| {_duration(entry['wall_s'])} |"), (row, entry["wall_s"])


def test_readme_quotes_the_paper_scale_cell():
    """The README's paper-scale sentence is the cell's report (``results/paper_hopper/cell.json``) as it stands."""
    cell = json.loads((ROOT / "results" / "paper_hopper" / "cell.json").read_text())
    readme = " ".join((ROOT / "README.md").read_text().split())
    for label, g in cell["groups"].items():
        spread = f" ± {g['final_return_std']:.0f}" if g["seeds"] > 1 else ""
        seeds = f"{g['seeds']} seeds" if g["seeds"] > 1 else "1 seed"
        assert f"{label} {g['final_return_mean']:.0f}{spread} ({seeds})" in readme, label
    for claim in cell["claims"]:
        assert f"{claim['claim']}: {claim['verdict'].split(' (')[0]}" in readme, claim["claim"]
    results = " ".join((ROOT / "docs" / "results.md").read_text().split())
    bcq, bail = cell["groups"]["bcq"], cell["groups"]["bail"]
    assert (f"BCQ {bcq['final_return_mean']:.0f} ± {bcq['final_return_std']:.0f} ({bcq['seeds']} seeds) vs BAIL "
            f"{bail['final_return_mean']:.0f} ± {bail['final_return_std']:.0f} ({bail['seeds']} seeds)") in results


@pytest.mark.parametrize("batch, start, end, env", [
    ("walker_ddpg05_b1", "Walker2d's batch is complete:", "differs between the two complete batches", "Walker2d"),
    ("hopper_ddpg01_b1", "On Hopper DDPG σ = 0.1", "On Hopper DDPG σ = 0.5 B2", "Hopper"),
    ("hopper_ddpg05_b2", "On Hopper DDPG σ = 0.5 B2", "Across all four:", "Hopper"),
])
def test_readme_quotes_each_batchs_finished_cells_as_the_cross_batch_report_has_them(batch, start, end, env):
    """The README's sentence on a batch is ``cross_batch.json``'s entry: each central cell that has all its seeds,
    with its mean ± std and seeds, the authors' figure, and the verdict of each claim that is no longer pending (a
    cell or claim that the next job completes makes this fail until the sentence has it too)."""
    entry = _cross_batch_entry(batch)
    readme = " ".join((ROOT / "README.md").read_text().split())
    sentence = readme[readme.index(start):]
    sentence = sentence[:sentence.index(end)]
    central = [entry["cells"][a] for a in ("bail", "pbail", "bc", "bcq")]
    cells = "; ".join(f"{c['algo']} {_pm(c)} ({c['seeds']} seeds)" for c in central if c["seeds"] >= c["scheduled"])
    assert cells in sentence, cells
    assert f"the authors' BAIL {entry['published_bail']} on gym's -v2 {env}" in sentence
    assert ("is complete" in sentence) == entry["complete"], "the sentence says whether the batch is complete"
    for claim in entry["claims"]:
        if not claim["verdict"].startswith("pending"):
            assert f"{claim['claim']}: {claim['verdict'].split(' (')[0]}" in sentence, claim["claim"]


def test_readme_reads_bail_over_bc_across_batches_as_the_cross_batch_report_does():
    """The README's sentence on BAIL ≫ BC across the four batches is ``cross_batch.json``'s: the count of batches
    where it holds and the aggregate probability of improvement of BAIL over BC with its interval and reading."""
    report = json.loads((ROOT / "results" / "paper_batches" / "cross_batch.json").read_text())
    claim = next(c for c in report["claims_across_batches"] if c["claim"] == "BAIL ≫ BC")
    improvement = next(p for p in report["aggregate"]["probability_of_improvement"]
                       if (p["a"], p["b"]) == ("bail", "bc"))
    assert improvement["reading"].startswith("bail above bc across batches"), improvement["reading"]
    readme = " ".join((ROOT / "README.md").read_text().split())
    assert (f"BAIL ≫ BC holds on {claim['holds']} of {len(report['batches'])} batches (disjoint IQM intervals on each)"
            in readme) and claim["holds"] == len(report["batches"])
    assert (f"the probability that a BAIL run ends above a BC run on the same batch is {improvement['p']:.2f} "
            f"[{improvement['ci_low']:.2f}, {improvement['ci_high']:.2f}] over the four") in readme
    bcq = next(p for p in report["aggregate"]["probability_of_improvement"] if (p["a"], p["b"]) == ("bail", "bcq"))
    counts = {c["claim"].split(" (")[0]: c["holds"] for c in report["claims_across_batches"]}
    per_batch = ", ".join(f"{v:.2f}" for v in bcq["per_batch"].values())
    assert (f"BAIL above BCQ holds on {counts['BAIL above BCQ']} of 4 (P(BAIL > BCQ) = {bcq['p']:.2f} "
            f"[{bcq['ci_low']:.2f}, {bcq['ci_high']:.2f}]; per batch {per_batch}, the headline batch first); "
            f"Progressive BAIL ≈ BAIL holds on {counts['Progressive BAIL ≈ BAIL']} of 4") in readme
    assert "bootstrap over batches, then seeds within each" in readme and "batches with replacement" in (
        report["aggregate"]["bootstrap"]), "the README says which bootstrap the report's intervals come from"
    assert ("four batches show no difference between BAIL and BCQ" in readme) == bcq["reading"].startswith(
        "no difference shown"), bcq["reading"]


def test_the_results_pages_cross_batch_state_is_the_reports():
    """"Across batches" includes the cross-batch report, whose first line (``cross_batch.json``'s ``status``) says
    where the study stands, so that the page never restates a state that the next job changes. Once all four batches
    are complete this fails until the page gives the verdict across them in words of its own, quoting each claim's
    count of batches where it holds and each probability of improvement with its interval."""
    report = json.loads((ROOT / "results" / "paper_batches" / "cross_batch.json").read_text())
    page = (ROOT / "docs" / "results.md").read_text()
    section = " ".join(page[page.index("## Across batches"):].split())
    assert '--8<-- "results/paper_batches/cross_batch.md"' in section
    assert "Where it stands is the report's first line" in section
    if len(report["complete_batches"]) == len(report["batches"]):
        assert "**Across the four batches:**" in section, "write the cross-batch verdict on the Results page"
        verdict = section[section.index("**Across the four batches:**"):]
        for claim in report["claims_across_batches"]:  # the counts and probabilities the verdict rests on
            assert f"{claim['claim'].split(' (')[0]} holds on {claim['holds']} of 4" in verdict, claim
        for p in report["aggregate"]["probability_of_improvement"]:
            assert (f"P({p['a'].upper()} > {p['b'].upper()}) = {p['p']:.2f} [{p['ci_low']:.2f}, {p['ci_high']:.2f}]"
                    in verdict), p
        names = {"pbail": "Progressive BAIL", "bail": "BAIL", "bcq": "BCQ", "bc": "BC"}
        for algo, name in names.items():  # the IQMs over all four batches, with the intervals over batches and seeds
            row = report["aggregate"]["iqm"][algo]
            assert f"{row['iqm']:.2f} [{row['ci_low']:.2f}, {row['ci_high']:.2f}] for {name}" in verdict, algo
        assert "hierarchical bootstrap" in verdict and "hierarchical bootstrap" in report["aggregate"]["bootstrap"]
        bcq = next(p for p in report["aggregate"]["probability_of_improvement"] if (p["a"], p["b"]) == ("bail", "bcq"))
        assert (f"P(BAIL > BCQ) = {bcq['p']:.2f} [{bcq['seeds_only'][0]:.2f}, {bcq['seeds_only'][1]:.2f}]"
                in verdict), "the page quotes the interval over seeds alone beside the one over batches"
    assert [b["batch"] for b in report["batches"]][0] == "hopper_ddpg05_b1" and len(report["batches"]) == 4
    assert report["status"] in (ROOT / "results" / "paper_batches" / "cross_batch.md").read_text()
    figures = [report["aggregate_figure"], *(b["figure"] for b in report["batches"] if b["figure"])]
    shown = re.findall(r"!\[[^\]]*\]\(assets/paper_batches/([^)]+)\)", page[page.index("## Across batches"):])
    assert shown == figures, "the Results page shows the report's figures: the aggregate, then each batch's curves"


def test_the_ope_guide_shows_the_ope_report_as_its_kept_runs_rebuild_it(tmp_path):
    """The OPE guide includes ``results/ope_headline/ope.md`` and its figure, and that report is what
    ``run_study.ope_headline_report`` makes from the kept runs alone (here, from a copy of them): nothing in it is
    typed by hand or left behind by a later run."""
    spec = importlib.util.spec_from_file_location("run_study", ROOT / "results" / "run_study.py")
    run_study = importlib.util.module_from_spec(spec)
    sys.modules["run_study"] = run_study
    try:
        spec.loader.exec_module(run_study)
        kept = ROOT / "results" / "ope_headline"
        copy = tmp_path / "ope_headline"
        if (kept / "runs").is_dir():
            shutil.copytree(kept / "runs", copy / "runs")
        run_study.ope_headline_report(copy, ROOT / "results" / "paper_hopper")
    finally:
        sys.modules.pop("run_study", None)
    assert (copy / "ope.md").read_text() == (kept / "ope.md").read_text()
    page = (ROOT / "docs" / "guides" / "ope.md").read_text()
    section = page[page.index("## How well FQE ranks the paper cell's policies"):]
    assert '--8<-- "results/ope_headline/ope.md"' in section
    assert "](../assets/ope_headline/ope.png)" in section and (kept / "ope.png").is_file()


def test_the_ope_guide_reads_the_study_in_its_own_words_once_every_policy_is_scored():
    """Until every planned policy is scored, the report's first line says the readings are preliminary and the guide
    adds none; once all are, this fails until the guide gives the reading (how well FQE ranks, its regret, the
    snapshot choice) in words of its own, beside the report."""
    report = json.loads((ROOT / "results" / "ope_headline" / "ope.json").read_text())
    scored = [p for p in report["policies"] if p.get("estimate") is not None]
    page = (ROOT / "docs" / "guides" / "ope.md").read_text()
    section = " ".join(page[page.index("## How well FQE ranks the paper cell's policies"):].split())
    if len(scored) == len(report["policies"]):
        assert report["status"].endswith("Every policy is scored.")
        assert f"**Over the {len(scored)} policies:**" in section, "write the OPE study's reading in the guide"
        rank, algos, snaps = report["ranking"], report["algorithm_ranking"], report["snapshot_selection"]
        low, high = rank["spearman_ci"]
        same = sum(p["reproduces"] is True for p in report["policies"])
        for quoted in (f"{rank['spearman']:.2f} [{low:.2f}, {high:.2f}]", f"gets {rank['selected_return']:.1f}",
                       f"returns {rank['best_return']:.1f}",
                       f"regret is {rank['regret']:.1f}, {100 * rank['regret_fraction']:.0f} % of the best",
                       f"rho is {algos['spearman']:.2f} and the regret {algos['regret']:.1f}",
                       f"(rho {report['gap_overrating']['spearman']:.2f} between the action gap",
                       f"returns {snaps['fqe_selected_return']:.1f} on average",
                       f"final policy would give {snaps['final_policy_return']:.1f}",
                       f"among the 5 snapshots {snaps['best_candidate_return']:.1f}",
                       f"`final_return` is {snaps['final_return']:.1f}", f"evaluations, {snaps['best_return']:.1f}",
                       f"{same} of the {len(scored)} retrained runs equal"):
            assert quoted in section, quoted
        readme = " ".join((ROOT / "README.md").read_text().split())
        for quoted in (f"{len(scored)} of the headline batch's policies", f"{rank['spearman']:.2f} [{low:.2f}, "
                       f"{high:.2f}]", f"gives up {rank['regret']:.1f} of the best policy's {rank['best_return']:.1f}",
                       f"returns {snaps['fqe_selected_return']:.1f} on average over 5 runs, against "
                       f"{snaps['final_policy_return']:.1f} for the final policy"):
            assert quoted in readme, quoted
        home = " ".join((ROOT / "docs" / "index.md").read_text().split())
        assert (f"{rank['spearman']:.2f} [{low:.2f}, {high:.2f}], and its top pick returns "
                f"{rank['selected_return']:.1f} where the best policy returns {rank['best_return']:.1f}") in home
    else:
        assert report["status"].endswith("are scored.") and "**Over the" not in section


def test_the_readme_quotes_the_ope_rules_against_the_discounted_truth():
    """The README's reading of FQE against the discounted truth is ``results/ope_headline/truth.json``'s."""
    rules = json.loads((ROOT / "results" / "ope_headline" / "truth.json").read_text())["ranking"]["rules"]
    readme = " ".join((ROOT / "README.md").read_text().split())

    def rho(rule):
        quality = rules["final_policies"][rule]["discounted"]
        low, high = quality["spearman_ci"]
        return f"{quality['spearman']:.2f} [{low:.2f}, {high:.2f}]"

    assert f"rho is {rho('mean')} and penalising a policy's action gap gives {rho('gap_penalised')}" in readme
    assert not rules["final_policies"]["lower_bound"]["available"], "the README says the pessimistic rule waits"


def _pm(group: dict) -> str:
    return f"{group['final_return_mean']:.0f} ± {group['final_return_std']:.0f}"


def test_the_paper_cells_reading_is_its_report():
    """The Results page's "What the cell says" and the README's BEAR clause quote ``results/paper_hopper/cell.json``:
    every mean ± std, BEAR's seed range, the batch's mean return and BAIL's mean best evaluation."""
    cell = json.loads((ROOT / "results" / "paper_hopper" / "cell.json").read_text())
    g = cell["groups"]
    page = (ROOT / "docs" / "results.md").read_text()
    reading = " ".join(page[page.index("**What the cell says.**"):].split("\n\n")[0].split())
    bear = [f"{r:.0f}" for r in sorted(g["bear"]["per_seed"])]
    for quoted in (f"BAIL ≫ BC ({_pm(g['bail'])} vs {_pm(g['bc'])})", f"BAIL ≈ BAIL ({_pm(g['pbail'])})",
                   f"BCQ ends above BAIL ({_pm(g['bcq'])})", f"({bear[0]} to {bear[-1]})",
                   f"above or below BAIL ({_pm(g['bear'])})", f"ends below BC ({_pm(g['marwil'])})",
                   f"mean episode return ({g['bail']['dataset_mean_episode_return']:.1f})",
                   f"does not lift it ({_pm(g['marwil (value_warmup_updates=1000)'])})",
                   f"10^5 updates, ends at {_pm(g['td3bc'])}: between BEAR and BCQ",
                   f"BAIL: {g['bail']['final_return_mean']:.0f} against a mean best of "
                   f"{g['bail']['best_return_mean']:.0f}"):
        assert quoted in reading, quoted
    verdicts = {c["b"] if c["a"] == "bail" else c["a"]: c["verdict"] for c in cell["claims"]}
    assert verdicts["bcq"].startswith("does not hold (below") and verdicts["bear"].startswith("does not hold (no")
    readme = " ".join((ROOT / "README.md").read_text().split())
    assert f"BEAR's three seeds ({bear[0]} to {bear[-1]}) straddle BAIL's" in readme
    assert min(g["bear"]["per_seed"]) < min(g["bail"]["per_seed"]) < max(g["bear"]["per_seed"])
    assert g["bear"]["final_return_mean"] < g["td3bc"]["final_return_mean"] < g["bcq"]["final_return_mean"]


def test_the_sweep_tutorials_spread_over_seeds_is_its_kept_runs():
    """The sweep page's "654.3 ± 79.5 alone, 675.7 ± 68.1 stacked" are the mean ± sample std of the three seeds' final
    returns its kept run printed, each way."""
    import statistics

    kept = (KEPT_TUTORIALS / "sweep_seeds.txt").read_text()
    runs = re.findall(r"seed \d: final_return ([\d.]+) alone, ([\d.]+) stacked", kept)
    assert len(runs) == 3
    alone, stacked = ([float(r[i]) for r in runs] for i in (0, 1))
    page = " ".join((TUTORIALS / "sweep-seeds.md").read_text().split())
    assert (f"here {statistics.mean(alone):.1f} ± {statistics.stdev(alone):.1f} alone, "
            f"{statistics.mean(stacked):.1f} ± {statistics.stdev(stacked):.1f} stacked") in page


def test_the_interrupted_runs_guide_quotes_the_slurm_drills_record():
    """The Slurm paragraph's restart delays and time-limit signal times are those of ``results/slurm/drills.txt``
    (Slurm's accounting of the drill jobs: 26 requeued, 27 preempted, 29 stopped by its 1-minute limit)."""
    from datetime import datetime

    rows = [line.split("|") for line in (ROOT / "results" / "slurm" / "drills.txt").read_text().splitlines()
            if "|" in line and not line.startswith("JobID")]
    runs = {}
    for job, _, state, start, end, _ in rows:
        runs.setdefault(job, []).append((state, datetime.fromisoformat(start), datetime.fromisoformat(end)))

    def restart_s(job):
        return round((runs[job][1][1] - runs[job][0][2]).total_seconds())

    stopped = [(end - start).total_seconds() for state, start, end in runs["29"] if state == "REQUEUED"]
    page = " ".join((ROOT / "docs" / "guides" / "interrupted-runs.md").read_text().split())
    assert (f"its requeued and preempted drill jobs started again {restart_s('26')} s and {restart_s('27')} s after "
            "the stop") in page
    assert (f"Slurm sent it {min(stopped):.0f} to {max(stopped):.0f} s into each start, {60 - max(stopped):.0f} to "
            f"{60 - min(stopped):.0f} s before the limit") in page

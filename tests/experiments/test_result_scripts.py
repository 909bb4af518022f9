"""The result scripts on a tiny real sweep: `make results` (scripts/update-results.sh) evaluates a
finished run deterministically and shielded, zero-shot at 90 and 120 veh/km and on the on-ramp, writes every
table; a second pass evaluates only what a stopped evaluation left unfinished."""

from __future__ import annotations

import csv
import importlib
import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from types import ModuleType

import pandas as pd
import pytest

from lanefree_sumo.errors import ReportError
from lanefree_sumo.experiments.analysis import comparison
from lanefree_sumo.experiments.analysis.report import report
from lanefree_sumo.experiments.sweep.summary import complete_seeds

from conftest import ROOT, lanefree

SCRIPTS = ("update-results.sh", "evaluation-helper.sh", "varobs-transfer.sh", "readme_results.py",
           "collisions_vs_overtakes.py")
CELL = "ddpg_fields_zones_overtake_collision_d70_s0"  # a paper sweep cell and the vector baseline's seed 0
EPISODES = 4  # per evaluation (50 in make results)


def rows(path: Path) -> int:
    with open(path, newline="") as fh:
        return sum(1 for _ in csv.DictReader(fh))


def script(name: str) -> ModuleType:
    """The module ``scripts/<name>.py`` of this checkout, imported."""
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        return importlib.import_module(name)
    finally:
        sys.path.remove(str(ROOT / "scripts"))


def make_results(root: Path) -> subprocess.CompletedProcess:
    """``scripts/update-results.sh EPISODES`` of the checkout ``root``, to completion."""
    return subprocess.run(["bash", str(root / "scripts" / "update-results.sh"), str(EPISODES)],
                          capture_output=True, text=True, timeout=900)


@pytest.mark.slow
@pytest.mark.sumo
def test_update_results_evaluates_a_finished_run_once_and_writes_every_table(tmp_path):
    root = tmp_path / "checkout"  # the scripts work relative to their checkout: a copy with this venv
    (root / "scripts").mkdir(parents=True)
    for name in SCRIPTS:
        shutil.copy2(ROOT / "scripts" / name, root / "scripts" / name)
    (root / ".venv").symlink_to(sys.prefix)  # the venv running this suite (its lanefree command)
    (root / "README.md").write_text("# results\n<!-- results-table -->\nstale\n<!-- /results-table -->\nafter\n")
    grid = tmp_path / "one.yaml"
    grid.write_text("reward_presets: [fields_zones_overtake_collision]\nn_seeds: 1\nepisodes: 2\n"
                    "overrides: {sim: {episode_steps: 40}, train: {checkpoint_every_episodes: 1}}\n")
    paper = root / "results" / "paper"
    done = lanefree("sweep", str(grid), "--out", str(paper), "--no-ray", "--no-progress", timeout=600)
    assert done.returncode == 0, done.stderr
    run = paper / "runs" / CELL
    # a set sweep stand-in (a copy of this sweep: its summary written before any evaluation existed)
    set_sweep = root / "results" / "varobs" / "set"
    shutil.copytree(paper, set_sweep)
    assert next(csv.DictReader(open(set_sweep / "runs.csv")))["eval_episodes"] in ("", "0")
    for bad in ("abc", "0", "-3"):  # refused in one line before anything is evaluated
        refused = subprocess.run(["bash", str(root / "scripts" / "update-results.sh"), bad], capture_output=True,
                                 text=True, timeout=60)
        assert refused.returncode == 2 and refused.stderr.count("\n") == 1 and bad in refused.stderr
    assert not list(run.glob("eval*"))

    first = make_results(root)
    assert first.returncode == 0, first.stdout + first.stderr
    for folder in ("eval", "eval_shield", "eval_d90", "eval_d120", "eval_onramp"):
        assert rows(run / folder / "episodes.csv") == EPISODES, folder
    assert {r["density"] for r in csv.DictReader(open(run / "eval_d90" / "episodes.csv"))} == {"90.0"}
    assert (paper / "summary.md").is_file() and not (paper / "claims.md").exists()  # one setting: no claim
    assert rows(paper / "runs.csv") == 1 and (paper / "collisions_vs_overtakes.png").stat().st_size > 0
    for folder in ("eval_report", "eval_shield_report"):
        text = (paper / folder / "summary.md").read_text()
        assert "| ddpg | fields_zones_overtake_collision | 70 |" in text and "Skipped runs" not in text
    transfer = (root / "results" / "varobs" / "report_transfer" / "summary.md").read_text()
    assert all(f"| `{name}` |" in transfer for name in ("eval", "eval_d90", "eval_d120", "eval_onramp"))
    assert (root / "results" / "varobs" / "report" / "summary.md").is_file()
    # the set sweep's summary rewritten with the evaluations made since
    assert next(csv.DictReader(open(set_sweep / "runs.csv")))["eval_episodes"] == str(EPISODES)
    assert not (root / "results" / "varobs" / "verdict").exists()  # vector runs only (the stand-in's): no verdict
    readme = (root / "README.md").read_text()  # its table rewritten from the summary, the rest kept
    assert "stale" not in readme and readme.startswith("# results\n") and readme.endswith("-->\nafter\n")
    assert "| fields_zones_overtake_collision | 1 of 1 |" not in readme  # every planned run: the count alone
    assert "| fields_zones_overtake_collision | 1 | " in readme and " [n/a] (0.449) |" in readme

    # a later seed's evaluated run (a sweep being extended to more seeds): left out of the evaluation tables,
    # which keep the seeds complete in every setting (here seed 0)
    shutil.copytree(run, run.with_name(CELL[:-1] + "1"))
    # a second pass evaluates nothing again, but an evaluation stopped part-way (it keeps the episodes it
    # finished) is run again whole
    cut = run / "eval_d120" / "episodes.csv"
    cut.write_text("".join(cut.read_text().splitlines(keepends=True)[:3]))
    assert rows(cut) == 2
    evaluations = {p: p.stat().st_mtime_ns for p in run.glob("eval*/episodes.csv") if p != cut}
    again = make_results(root)
    assert again.returncode == 0, again.stdout + again.stderr
    for folder in ("eval_report", "eval_shield_report"):
        assert [r["n_seeds"] for r in csv.DictReader(open(paper / folder / "summary.csv"))] == ["1"], folder
    assert {p: p.stat().st_mtime_ns for p in evaluations} == evaluations and len(evaluations) == 4
    assert rows(cut) == EPISODES


def test_the_readme_results_table_is_the_committed_summary():
    """README.md's table is what scripts/readme_results.py makes of the committed results/paper/summary.csv:
    committing a new summary without its README table fails here."""
    readme_results = script("readme_results")
    expected = readme_results.table(ROOT / "results" / "paper" / "summary.csv")
    readme = (ROOT / "README.md").read_text()
    assert f"{readme_results.BEGIN}\n{expected}\n{readme_results.END}" in readme
    assert expected.count("\n") == 1 + rows(ROOT / "results" / "paper" / "summary.csv") >= 16  # 15 settings


def test_readme_results_refuses_a_readme_without_its_markers_in_one_line_and_leaves_it(tmp_path):
    readme = tmp_path / "README.md"
    readme.write_text("# no table here\n")
    refused = subprocess.run([sys.executable, str(ROOT / "scripts" / "readme_results.py"), "--readme", str(readme)],
                             capture_output=True, text=True, timeout=120)
    assert refused.returncode == 2 and refused.stderr.count("\n") == 1 and "results-table" in refused.stderr
    assert readme.read_text() == "# no table here\n"
    (tmp_path / "empty.csv").write_text("")  # not a summary: refused the same way, naming it
    refused = subprocess.run([sys.executable, str(ROOT / "scripts" / "readme_results.py"), "--readme", str(readme),
                              "--summary", str(tmp_path / "empty.csv")], capture_output=True, text=True, timeout=120)
    assert refused.returncode == 2 and refused.stderr.count("\n") == 1 and "empty.csv" in refused.stderr


def varobs_finished(root: Path) -> list[Path]:
    """The runs scripts/varobs-transfer.sh hands to the verdict: both algorithms' vector runs (the paper sweep's seeds
    0-2 of the cell) and set runs, those evaluated."""
    runs = [root / "results" / "paper" / "runs" / f"{algorithm}_fields_zones_overtake_collision_d70_s{seed}"
            for algorithm in ("ddpg", "dqn") for seed in range(3)]
    runs += sorted((root / "results" / "varobs").glob("set*/runs/*"))
    return [run for run in runs if (run / "eval" / "episodes.csv").is_file()]


def test_the_varobs_verdict_page_is_what_the_run_folders_make(tmp_path):
    """results/varobs/verdict/verdict.md is what `lanefree report RUN … --compare` makes of the committed run folders,
    so committing new runs without their verdict fails here."""
    made = report(varobs_finished(ROOT), tmp_path / "verdict", compare=True)
    assert (ROOT / "results" / "varobs" / "verdict" / "verdict.md").read_text() == \
        (tmp_path / "verdict" / "verdict.md").read_text()
    assert made.files[-1] == tmp_path / "verdict" / "verdict.md"
    text = (tmp_path / "verdict" / "verdict.md").read_text()
    for algorithm in ("ddpg", "dqn"):  # 7 sources x 3 metrics each
        assert text.count(f"| {algorithm} / fields_zones_overtake_collision / d70 |") == 21
    assert text.startswith("# observation.kind=set, observation.encoder=paper against the defaults")


def test_the_interpretation_studys_phase1_page_is_what_the_committed_runs_make():
    """results/interpretations/phase1.md (the distance, the pick, the readings, the claims per variant) is what the
    committed run tables and run folders give today."""
    from lanefree_sumo.experiments.analysis.interpretations import phase1_page

    results = ROOT / "results"
    assert phase1_page(results) == (results / "interpretations" / "phase1.md").read_text()


def test_the_remedy_report_is_what_the_run_folders_make(tmp_path):
    """results/varobs_remedies/report150/ is `lanefree report … --first 150 --compare` of the vector DDPG runs (seeds
    0-2), the set runs and the pre-tanh penalty's 150-episode runs: both variants against the vector runs over the
    same 150 episodes; report_td3_150/ the TD3 runs with those set runs `--against` the vector runs, and
    report_td3_vs_set150/ the TD3 runs `--against` the plain set DDPG runs, report_penalty150/ the vector, set and
    penalty runs `--against` the vector runs with the penalty."""
    committed = ROOT / "results"
    runs = [committed / "paper" / "runs" / f"ddpg_fields_zones_overtake_collision_d70_s{seed}" for seed in range(3)]
    runs += sorted((committed / "varobs" / "set" / "runs").glob("*"))
    runs += sorted((committed / "varobs_remedies" / "pretanh150" / "runs").glob("*"))
    made = report(runs, tmp_path / "report150", compare=True, first=150)
    assert not made.skipped and len(made.table) == 3
    td3 = sorted((committed / "varobs_remedies" / "td3_150" / "runs").glob("*"))
    made = report([*td3, *runs[3:]], tmp_path / "report_td3_150", first=150, against=runs[:3])
    assert not made.skipped and len(made.table) == 4
    made = report(td3, tmp_path / "report_td3_vs_set150", first=150, against=runs[3:6])
    assert not made.skipped and len(made.table) == 2
    control = sorted((committed / "varobs_remedies" / "vector_pretanh150" / "runs").glob("*"))
    made = report([*runs[:3], *control, *runs[3:]], tmp_path / "report_penalty150", first=150, against=control)
    assert not made.skipped and len(made.table) == 4
    assert not any("more than once" in note for note in made.notes)  # given as RUN and --against: no note
    for folder in ("report150", "report_td3_150", "report_td3_vs_set150", "report_penalty150"):
        for name in ("verdict.md", "summary.md"):
            assert (committed / "varobs_remedies" / folder / name).read_text() == \
                (tmp_path / folder / name).read_text(), (folder, name)


def test_the_paper_claims_are_what_the_run_folders_make(tmp_path):
    """results/paper/claims.md and claims.csv are `lanefree report` of the paper sweep's runs of the seeds complete
    in every setting (the tables' seeds, scripts/update-results.sh), so committing runs without the tables they
    make fails here; every claim compares all of those seeds a side."""
    paper = ROOT / "results" / "paper"
    seeds = complete_seeds(paper)
    runs = sorted(run for run in (paper / "runs").iterdir() if int(run.name.rsplit("_s", 1)[1]) < seeds)
    made = report(runs, tmp_path / "claims")
    assert seeds >= 3 and len(runs) == 15 * seeds and not made.skipped and not made.notes
    claims = pd.read_csv(tmp_path / "claims" / "claims.csv")
    assert len(claims) == 20 and set(claims.n_a) == set(claims.n_b) == {seeds}
    for name in ("claims.md", "claims.csv"):
        assert (paper / name).read_text() == (tmp_path / "claims" / name).read_text(), name


def copy_run(run: Path, to: Path) -> None:
    """A run folder's committed files: config, training episodes and every evaluation's episodes."""
    to.mkdir(parents=True)
    for name in ("config.yaml", "episodes.csv"):
        shutil.copy2(run / name, to / name)
    for evaluation in run.glob("eval*/episodes.csv"):
        (to / evaluation.parent.name).mkdir()
        shutil.copy2(evaluation, to / evaluation.parent.name / "episodes.csv")


def test_report_compare_decides_set_against_vector_from_the_run_folders(tmp_path):
    """With 3 vector runs and 4 set runs the DDPG set encoder (standing still or racing) is decided worse in return and
    speed deviation, each side's column the mean of its runs' last 50 episodes (its first 12 for Liu et al.'s
    window), with the two-sided rank test; a vector run without one evaluation is missing from that one only; a run
    of another setting with no variant of its own (a DQN run) is in no comparison; runs without any variant are
    refused in one line."""
    committed = ROOT / "results"
    vector = []
    for seed in range(3):
        name = f"ddpg_fields_zones_overtake_collision_d70_s{seed}"
        vector.append(tmp_path / "vector" / name)
        copy_run(committed / "paper" / "runs" / name, vector[-1])
    shutil.rmtree(vector[2] / "eval_d90")
    finished = [run for run in sorted((committed / "varobs" / "set" / "runs").glob("*")) if (run / "eval").is_dir()]
    assert len(finished) >= 2
    sets = [tmp_path / "set" / f"set_{k}" for k in range(len(finished) + 1)]
    for run, to in zip([*finished, finished[0]], sets):  # at least 3 set runs: a copy of the first one more
        copy_run(run, to)
    other = tmp_path / "other_cell"
    copy_run(committed / "paper" / "runs" / "dqn_fields_zones_overtake_collision_d70_s1", other)
    report([*vector, *sets, other], tmp_path / "out", compare=True)
    label = "ddpg / fields_zones_overtake_collision / d70"
    table = {tuple(cells[1:4]): cells[4:] for line in (tmp_path / "out" / "verdict.md").read_text().splitlines()
             if line.startswith("| ") for cells in [[c.strip() for c in line.strip("|").split("|")]]
             if cells[0] == label}
    assert "| dqn / " not in (tmp_path / "out" / "verdict.md").read_text()
    n_set = len(sets)
    ret = table[("training, last 50 episodes", "return", f"{n_set}, 3")]
    # every set run below every vector run: two-sided, twice the share of the splits as extreme; decided only when
    # that reaches 0.05 (the claims' one rule: 4 runs against 3 give 2/35 = 0.057, undecided)
    p = 2 / math.comb(n_set + 3, 3)
    assert ret[3] == f"0/{n_set * 3}, p = {p:.2f}"
    assert ret[-1] == ("variant worse" if p <= 0.05 else "undecided")
    expected = sum(pd.read_csv(run / "episodes.csv")["return"].iloc[-50:].mean() for run in sets) / n_set
    assert ret[0] == f"{expected:.2f}"
    early = table[("training, episodes 1–12 (Liu et al.'s 10 000 steps)", "return", f"{n_set}, 3")]
    expected = sum(pd.read_csv(run / "episodes.csv")["return"].iloc[:12].mean() for run in sets) / n_set
    assert early[0] == f"{expected:.2f}"
    speed = table[("deterministic, 70 veh/km", "speed deviation (m/s)", f"{n_set}, 3")]
    assert speed[-1] == ("variant worse" if float(speed[3].rsplit("p = ", 1)[1]) <= 0.05 else "undecided")
    assert ("zero-shot, 90 veh/km", "collisions / episode", f"{n_set}, 2") in table  # the one without it left out
    assert ("zero-shot, 120 veh/km", "collisions / episode", f"{n_set}, 3") in table
    assert comparison.reading(1, -3.0, -1.0, 0.01) == comparison.reading(-1, 1.0, 3.0, 0.05) == "set worse"
    assert comparison.reading(-1, -3.0, -1.0, 0.01) == comparison.reading(1, 1.0, 3.0, 0.01) == "set better"
    assert comparison.reading(1, -1.0, 2.0, 0.01) == "no difference detected"
    assert comparison.reading(1, -3.0, -1.0, 0.10) == "undecided"  # the CI alone decides nothing
    assert comparison.reading(1, -3.0, -1.0, 0.01, "cap25") == "cap25 worse"
    refused = lanefree("report", *map(str, vector), "--out", str(tmp_path / "none"), "--compare")
    assert refused.returncode != 0 and refused.stderr.count("\n") == 1 and "--compare needs runs" in refused.stderr
    assert not (tmp_path / "none").exists()
    refused = lanefree("report", *map(str, sets), "--out", str(tmp_path / "none"), "--eval", "eval", "--compare")
    assert refused.returncode != 0 and refused.stderr.count("\n") == 1 and "drop --eval" in refused.stderr
    assert not (tmp_path / "none").exists()


def shortened(run: Path, to: Path, episodes: int) -> None:
    """A copy of ``run``'s config and training episodes as if it had been planned for ``episodes`` and stopped
    there (its first ``episodes`` rows, ``train.episodes`` set to that)."""
    to.mkdir(parents=True)
    config = (run / "config.yaml").read_text()
    assert config.count("  episodes: 625\n") == 1
    (to / "config.yaml").write_text(config.replace("  episodes: 625\n", f"  episodes: {episodes}\n"))
    lines = (run / "episodes.csv").read_text().splitlines(keepends=True)
    (to / "episodes.csv").write_text("".join(lines[:episodes + 1]))


def test_report_first_compares_runs_of_different_lengths_over_their_first_episodes(tmp_path):
    """``first`` reads every run over its first N training episodes: 150-episode set runs and the first 150 of a
    625-episode set run form one variant against the vector runs cut at 150 (each side's last 50 are episodes
    101-150, its "all" window 1-150), no evaluation is compared, a shorter run is skipped with the reason; without
    it, the planned length separates the 150-episode runs into their own variant. Bad values are refused in one
    line."""
    committed = ROOT / "results"
    vector = [committed / "paper" / "runs" / f"ddpg_fields_zones_overtake_collision_d70_s{seed}" for seed in range(3)]
    whole = sorted((committed / "varobs" / "set" / "runs").glob("*"))
    short = [tmp_path / f"short_{k}" for k in range(3)]
    for run, to in zip(whole, short):
        shortened(run, to, 150)
    too_short = tmp_path / "too_short"
    shortened(whole[0], too_short, 100)
    made = report([*vector, *short, whole[1], too_short], tmp_path / "out", compare=True, first=150)
    assert made.skipped == [(too_short, "has 100 episode(s), fewer than the first 150 asked for")]
    assert any("first 150 training episodes" in note for note in made.notes)
    assert sorted(made.table["variant"]) == ["", "observation.kind=set, observation.encoder=paper"]
    label = "ddpg / fields_zones_overtake_collision / d70"
    text = (tmp_path / "out" / "verdict.md").read_text()
    table = {tuple(cells[1:4]): cells[4:] for line in text.splitlines()
             if line.startswith("| ") for cells in [[c.strip() for c in line.strip("|").split("|")]]
             if cells[0] == label}
    assert {source for source, *_ in table} == {"training, episodes 1–12 (Liu et al.'s 10 000 steps)",
                                                "training, all 150 episodes", "training, last 50 episodes"}
    sets = [*short, whole[1]]
    last = table[("training, last 50 episodes", "return", "4, 3")]
    mean = [sum(pd.read_csv(run / "episodes.csv")["return"].iloc[100:150].mean() for run in side) / len(side)
            for side in (sets, vector)]
    assert last[:2] == [f"{mean[0]:.2f}", f"{mean[1]:.2f}"]
    every = table[("training, all 150 episodes", "return", "4, 3")]
    assert every[1] == f"{sum(pd.read_csv(r / 'episodes.csv')['return'].iloc[:150].mean() for r in vector) / 3:.2f}"
    plain = report([*vector, *short, whole[1]], tmp_path / "plain")
    assert "observation.kind=set, observation.encoder=paper, train.episodes=150" in set(plain.table["variant"])
    for bad, words in ((["--first", "0"], "expected a positive number of episodes"),
                       (["--first", "150", "--eval", "eval"], "drop --eval")):
        refused = lanefree("report", *map(str, vector), "--out", str(tmp_path / "none"), *bad)
        assert refused.returncode != 0 and refused.stderr.count("\n") == 1 and words in refused.stderr
        assert not (tmp_path / "none").exists()


def test_report_against_sets_every_group_against_one_groups_runs(tmp_path):
    """``against``: every group of the runs given — another algorithm's included, which the defaults' comparison
    never pairs — against the baseline runs (vector DDPG), each side's column the mean of its runs' last 50
    episodes; the baseline joins the table as a group and is not set against itself. Baselines of several groups,
    an unusable baseline run, no other group (naming a RUN folder left out), runs of different lengths without
    ``first``, a sweep folder and evaluations are refused in one line."""
    committed = ROOT / "results"
    vector = [committed / "paper" / "runs" / f"ddpg_fields_zones_overtake_collision_d70_s{seed}" for seed in range(3)]
    dqn = [committed / "paper" / "runs" / f"dqn_fields_zones_overtake_collision_d70_s{seed}" for seed in range(3)]
    sets = sorted((committed / "varobs" / "set" / "runs").glob("*"))
    made = report([*dqn, *sets, vector[0]], tmp_path / "out", against=vector, first=150)
    assert not made.skipped and len(made.table) == 3  # dqn, set ddpg and the vector ddpg baseline
    text = (tmp_path / "out" / "verdict.md").read_text()
    assert text.startswith("# Each group against ddpg / fields_zones_overtake_collision / d70: every source")
    table = {tuple(cells[:4]): cells[4:] for line in text.splitlines() if line.startswith("| ")
             for cells in [[c.strip() for c in line.strip("|").split("|")]] if " / " in cells[0]}
    mean = {name: sum(pd.read_csv(run / "episodes.csv")["return"].iloc[100:150].mean() for run in side) / len(side)
            for name, side in (("dqn", dqn), ("vector", vector))}
    row = table[("dqn / fields_zones_overtake_collision / d70", "training, last 50 episodes", "return", "3, 3")]
    assert row[:2] == [f"{mean['dqn']:.2f}", f"{mean['vector']:.2f}"]
    assert row[-1] in ("undecided", "no difference detected")  # 3 runs against 3: p ≥ 0.10, never decided
    with pytest.raises(ReportError, match="against needs at least one run folder"):
        report(dqn, tmp_path / "empty", against=[])
    assert {key[0] for key in table} == {"dqn / fields_zones_overtake_collision / d70",
                                         "ddpg / fields_zones_overtake_collision / d70 / observation.kind=set, "
                                         "observation.encoder=paper"}
    too_short = tmp_path / "too_short"
    shortened(vector[1], too_short, 100)
    short_dqn = tmp_path / "short_dqn"
    shortened(dqn[0], short_dqn, 150)
    for runs, against, first, words in (
            (dqn, [*vector, dqn[0]], ["--first", "150"], "the runs of one group"),
            (dqn, [vector[0], too_short], ["--first", "150"], f"--against {too_short} is unusable: has 100"),
            (vector, vector, ["--first", "150"], "no run of another group"),
            ([too_short], vector, ["--first", "150"], f"({too_short} was left out: has 100"),
            ([short_dqn], vector, [], "have 150 to 625 episodes, so their last 50 are different episodes; compare "
                                      "them over the same ones with --first 150"),
            ([committed / "paper"], vector, [], "a sweep writes its own verdict.md"),
            (dqn, vector, ["--eval", "eval"], "drop --eval")):
        refused = lanefree("report", *map(str, runs), "--out", str(tmp_path / "none"), *first,
                           "--against", *map(str, against))
        assert refused.returncode != 0 and refused.stderr.count("\n") == 1 and words in refused.stderr, refused.stderr
        assert not (tmp_path / "none").exists()


def test_collisions_vs_overtakes_refuses_a_sweep_without_runs_csv_in_one_line(tmp_path):
    refused = subprocess.run([sys.executable, str(ROOT / "scripts" / "collisions_vs_overtakes.py"), str(tmp_path)],
                             capture_output=True, text=True, timeout=120)
    assert refused.returncode == 2 and refused.stderr.count("\n") == 1 and "lanefree report" in refused.stderr
    (tmp_path / "runs.csv").write_text("run,seed\nx,0\n")
    refused = subprocess.run([sys.executable, str(ROOT / "scripts" / "collisions_vs_overtakes.py"), str(tmp_path)],
                             capture_output=True, text=True, timeout=120)
    assert refused.returncode == 2 and refused.stderr.count("\n") == 1 and "lacks column(s)" in refused.stderr
    assert not (tmp_path / "collisions_vs_overtakes.png").exists()
    (tmp_path / "collisions_vs_overtakes.png").write_bytes(b"a figure of runs since removed")
    (tmp_path / "runs.csv").write_text("run,algorithm,reward_preset,density,seed,overtakes,collisions\n")
    empty = subprocess.run([sys.executable, str(ROOT / "scripts" / "collisions_vs_overtakes.py"), str(tmp_path)],
                           capture_output=True, text=True, timeout=120)
    assert empty.returncode == 0 and "no complete run" in empty.stdout  # no run yet is no error: no figure
    assert not (tmp_path / "collisions_vs_overtakes.png").exists()


def test_collisions_vs_overtakes_draws_the_deterministic_panel_from_evaluated_runs_only():
    figure = script("collisions_vs_overtakes")
    import pandas as pd
    runs = pd.DataFrame({"algorithm": ["ddpg", "dqn"], "reward_preset": ["collision"] * 2, "density": [70.0, 90.0],
                         "overtakes": [5.0, 140.0], "collisions": [0.4, 20.0], "eval_episodes": [50, 0],
                         "eval_overtakes": [4.0, float("nan")], "eval_collisions": [0.3, float("nan")]})
    (training, all_runs), (deterministic, evaluated) = figure.panels(runs)
    assert training.startswith("training") and list(all_runs["setting"]) == ["collision 70 veh/km",
                                                                            "collision 90 veh/km"]
    assert deterministic.startswith("deterministic") and evaluated[["overtakes", "collisions"]].values.tolist() == \
        [[4.0, 0.3]]
    assert [title for title, _ in figure.panels(runs.drop(columns=["eval_overtakes"]))] == [training]


def test_reproduce_refuses_a_bad_worker_count_in_one_line_before_starting_anything(tmp_path):
    (tmp_path / "scripts").mkdir()
    shutil.copy2(ROOT / "scripts" / "reproduce.sh", tmp_path / "scripts" / "reproduce.sh")
    script = str(tmp_path / "scripts" / "reproduce.sh")
    cores = len(os.sched_getaffinity(0))  # what nproc counts without OMP_NUM_THREADS, which must not count
    env = {**os.environ, "OMP_NUM_THREADS": str(cores + 8)}
    # more paper workers than cores: more runs than cores; a leading 0 would be octal in bash arithmetic
    for bad in ("abc", "-1", "1.5", str(cores + 1), "9" * 20, "00", "01", "08"):
        refused = subprocess.run(["bash", script, "start", bad], capture_output=True, text=True, timeout=60,
                                 cwd=tmp_path, env=env)
        assert refused.returncode == 2 and refused.stderr.count("\n") == 1 and f"'{bad}'" in refused.stderr
    for verb in (["begin"], []):  # an unknown command, none: one line on stderr, nothing written
        usage = subprocess.run(["bash", script, *verb], capture_output=True, text=True, timeout=60, cwd=tmp_path)
        assert usage.returncode == 2 and usage.stdout == "" and usage.stderr.count("\n") == 1, usage
        assert ("unknown command 'begin'" if verb else "no command given") in usage.stderr
        assert "usage: scripts/reproduce.sh start" in usage.stderr
    assert not (tmp_path / ".worktrees" / "logs" / "paper.pid").exists()
    stop = subprocess.run(["bash", script, "stop"], capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert stop.returncode == 0 and stop.stdout.startswith("nothing to stop"), stop
    assert sorted(p.name for p in (tmp_path / ".worktrees" / "logs").iterdir()) == []


def test_reproduce_gives_the_set_sweeps_the_cores_the_paper_sweep_leaves_and_stops_everything(tmp_path):
    """``start N``: the paper sweep on N workers (none for 0); on the cores - N left, the DDPG set-encoder sweep
    and then the DQN one, each on as many cores as it has runs to train, counted by the real ``lanefree sweep
    --status`` (or, before a sweep begins, from its grid); the watcher; ``stop`` ends every one of them. The
    venv's python is a stand-in that records its arguments and runs until SIGTERM (it passes the counting on to
    the real python), so no sweep trains."""
    root = tmp_path / "checkout"
    (root / "scripts").mkdir(parents=True)
    shutil.copy2(ROOT / "scripts" / "reproduce.sh", root / "scripts" / "reproduce.sh")
    (root / "results" / "varobs").mkdir(parents=True)
    for grid in ("set_paper.yaml", "set_dqn_paper.yaml"):
        shutil.copy2(ROOT / "results" / "varobs" / grid, root / "results" / "varobs" / grid)
    watched = root / "watcher-ran"
    (root / "scripts" / "update-results.sh").write_text(f"#!/usr/bin/env bash\ntouch {watched}\n")
    calls = root / "calls"
    (root / ".venv" / "bin").mkdir(parents=True)
    python = root / ".venv" / "bin" / "python"
    python.write_text("#!/usr/bin/env bash\n"
                      f"case \"$*\" in *--status*|*load_grid*) exec {sys.executable} \"$@\";; esac\n"
                      f"echo \"$*\" >> {calls}\ntrap 'exit 0' TERM\nwhile true; do sleep 0.05; done\n")
    python.chmod(0o755)
    (root / "scripts" / "update-results.sh").chmod(0o755)
    git = ["git", "-c", "user.name=t", "-c", "user.email=t@t", "-C", str(root)]
    subprocess.run(["git", "init", "-q", str(root)], check=True)
    (root / ".gitignore").write_text(".worktrees/\n.venv/\ncalls\nwatcher-ran\nresults/*/*/\n")
    subprocess.run([*git, "add", "."], check=True)
    subprocess.run([*git, "commit", "-qm", "scripts"], check=True)
    script, logs = str(root / "scripts" / "reproduce.sh"), root / ".worktrees" / "logs"
    cores = len(os.sched_getaffinity(0))

    def start_and_stop(workers: int) -> tuple[dict[str, str], str]:
        """Each sweep driver's workers by the folder it sweeps, and what ``start`` said (stdout and stderr)."""
        calls.unlink(missing_ok=True)
        watched.unlink(missing_ok=True)
        started = subprocess.run(["bash", script, "start", str(workers)], capture_output=True, text=True, timeout=120)
        assert started.returncode == 0, started.stderr
        drivers = [name for name in ("paper", "varobs", "varobs_dqn") if (logs / f"{name}.pid").exists()]
        pids = [int((logs / f"{name}.pid").read_text()) for name in (*drivers, "watcher")]
        deadline = time.monotonic() + 120
        while not (calls.exists() and len(calls.read_text().splitlines()) == len(drivers) and watched.exists()):
            assert time.monotonic() < deadline, "the sweeps and the watcher did not all start"
            time.sleep(0.05)
        again = subprocess.run(["bash", script, "start", str(workers)], capture_output=True, text=True, timeout=120)
        assert again.returncode == 2 and again.stdout == "" and again.stderr.count("\n") == 1, again
        assert "already running" in again.stderr
        stopped = subprocess.run(["bash", script, "stop"], capture_output=True, text=True, timeout=120)
        assert stopped.returncode == 0 and "stopped" in stopped.stdout, stopped.stderr
        assert not [pid for pid in pids if running(pid)]  # stop waits until they are gone
        swept = {}
        for call in calls.read_text().splitlines():
            folder = next(f for f in ("results/varobs/set_dqn", "results/varobs/set", "results/paper") if f in call)
            swept[folder] = call.split("--workers ")[1].split()[0]
        return swept, started.stdout + started.stderr

    try:
        alone, said = start_and_stop(cores)  # every core to the paper sweep: no set-encoder sweep
        assert alone == {"results/paper": str(cores)}
        assert "no set-encoder sweep (no core left), no DQN set-encoder sweep (no core left)" in said
        # neither set sweep begun: the DDPG one takes as many cores as its grid has runs (3), the DQN one the rest
        fresh, said = start_and_stop(0)
        assert fresh == {"results/varobs/set": str(min(cores, 3)), **({"results/varobs/set_dqn": str(min(cores - 3, 3))}
                                                                    if cores > 3 else {})}
        assert "no paper sweep" in said and "results/varobs/set_paper.yaml" in calls.read_text()  # begun from its grid
        # the DDPG sweep begun (its manifest and seed 0 complete, seeds 1-2 to train): 2 cores to it
        sweep = root / "results" / "varobs" / "set"
        sweep.mkdir()
        shutil.copy2(ROOT / "results" / "varobs" / "set" / "sweep.yaml", sweep / "sweep.yaml")
        run = "ddpg_fields_zones_overtake_collision_d70_s0"
        (sweep / "runs" / run).mkdir(parents=True)
        for name in ("config.yaml", "episodes.csv", "last_session.json"):
            shutil.copy2(ROOT / "results" / "varobs" / "set" / "runs" / run / name, sweep / "runs" / run / name)
        begun, said = start_and_stop(0)
        assert begun == {"results/varobs/set": str(min(cores, 2)), **({"results/varobs/set_dqn": str(min(cores - 2, 3))}
                                                                    if cores > 2 else {})}
        assert "--resume" in calls.read_text()
        if cores > 1:  # one paper worker: the DDPG set sweep on the cores left
            beside, said = start_and_stop(1)
            assert beside["results/paper"] == "1" and beside["results/varobs/set"] == str(min(cores - 1, 2))
        # a manifest the status cannot read: said in one line, and every core left to that sweep
        (sweep / "sweep.yaml").write_text("not a manifest\n")
        unreadable, said = start_and_stop(0)
        assert unreadable == {"results/varobs/set": str(cores)}
        assert "cannot count the runs left in results/varobs/set" in said
    finally:  # a failed assertion leaves no stand-in running
        subprocess.run(["bash", script, "stop"], capture_output=True, timeout=120)


def running(pid: int) -> bool:
    """Process ``pid`` exists and is not a zombie."""
    try:
        with open(f"/proc/{pid}/status") as status:
            return "zombie" not in status.read().lower()
    except FileNotFoundError:
        return False

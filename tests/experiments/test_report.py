"""The training report on synthetic run folders: grouping, last-50 means over seeds to the number,
paper values beside the right cells, damaged runs skipped by name, the written files."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest

from lanefree_sumo.config import LaneFreeConfig, merge_config
from lanefree_sumo.errors import ReportError
from lanefree_sumo.experiments.analysis.curves import evaluation_series, smoothed_curve
from lanefree_sumo.experiments.analysis.paper import PAPER_REFERENCE
from lanefree_sumo.experiments.analysis.report import RunData, report
from lanefree_sumo.experiments.storage.episodes import EPISODE_COLUMNS
from lanefree_sumo.experiments.storage.rundir import write_config

from conftest import fenced_rows, lanefree

FZOC = "fields_zones_overtake_collision"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def make_run(root: Path, name: str, algo: str = "ddpg", preset: str = FZOC, density: float = 70.0,
             seed: int = 0, *, collisions: list[float] | None = None, speed_dev: list[float] | None = None,
             returns: list[float] | None = None, overtakes: list[float] | None = None,
             episodes: int = 80, extra: dict | None = None) -> Path:
    """A run folder like ``lanefree train`` writes (config.yaml + episodes.csv, all columns);
    ``extra``: more config overrides."""
    run = root / name
    run.mkdir(parents=True)
    config = {"train": {"algo": algo}, "reward": {"preset": preset},  # planned: 625 episodes, CSV: ``episodes``
              "scenario": {"density_veh_per_km": density}, "seed": seed, "road": {"length_m": 500.0}}
    write_config(run, merge_config(merge_config(LaneFreeConfig(), config), extra or {}))
    collisions = collisions if collisions is not None else [1.0] * episodes
    speed_dev = speed_dev if speed_dev is not None else [0.5] * episodes
    returns = returns if returns is not None else [10.0] * episodes
    overtakes = overtakes if overtakes is not None else [1.0] * episodes
    with open(run / "episodes.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=EPISODE_COLUMNS)
        writer.writeheader()
        for i in range(episodes):
            writer.writerow({
                "episode": i + 1, "steps": 800, "return": returns[i], "collisions": collisions[i],
                "collision_steps": 3 * collisions[i], "background_collisions": 0, "speed_dev_mps": speed_dev[i],
                "mean_speed_mps": 20.0 - speed_dev[i], "overtakes": overtakes[i], "boundary_contacts": 0,
                "mean_c_x": 0.1, "mean_c_y": 0.2, "mean_c_f": 0.3, "mean_reward": returns[i] / 800,
                "density": density, "seed": 1000 + i, "algorithm": algo, "reward_preset": preset,
                "timesteps": 800 * (i + 1), "wall_s": 1.0,
            })
    return run


def early_then_last(early: float, last_values: list[float], episodes: int = 80) -> list[float]:
    """``episodes`` values: ``early`` for the first ones, then ``last_values`` (the last 50)."""
    return [early] * (episodes - len(last_values)) + last_values


@pytest.fixture
def two_seed_runs(tmp_path: Path) -> list[Path]:
    """ddpg/FZOC/70 seeds 0 and 1 with known last-50 means, dqn/FZOC/70 seed 0.

    Seed 0, last 50: collisions 25×0 + 25×1 → 0.5, speed dev 0.4, return 100, overtakes 2.
    Seed 1, last 50: collisions 15×0 + 35×1 → 0.7, speed dev 0.8, return 120, overtakes 4.
    The first 30 episodes carry very different values (10, 9, −500, 50) and must not count.
    """
    runs = tmp_path / "runs"
    a = make_run(runs, "ddpg_s0", seed=0,
                 collisions=early_then_last(10.0, [0.0] * 25 + [1.0] * 25),
                 speed_dev=early_then_last(9.0, [0.4] * 50), returns=early_then_last(-500.0, [100.0] * 50),
                 overtakes=early_then_last(50.0, [2.0] * 50))
    b = make_run(runs, "ddpg_s1", seed=1,
                 collisions=early_then_last(10.0, [1.0, 0.0] * 15 + [1.0] * 20),
                 speed_dev=early_then_last(9.0, [0.8] * 50), returns=early_then_last(-500.0, [120.0] * 50),
                 overtakes=early_then_last(50.0, [4.0] * 50))
    c = make_run(runs, "dqn_s0", algo="dqn", seed=0, collisions=[2.0] * 80, speed_dev=[0.3] * 80)
    return [a, b, c]


def row(table, algo: str, preset: str = FZOC, density: float = 70.0):
    sel = table[(table.algorithm == algo) & (table.reward_preset == preset) & (table.density_veh_per_km == density)]
    assert len(sel) == 1, table
    return sel.iloc[0]


def test_grouping_by_algorithm_preset_density(two_seed_runs: list[Path], tmp_path: Path) -> None:
    result = report(two_seed_runs, tmp_path / "out")
    assert result.skipped == []
    assert len(result.table) == 2
    assert row(result.table, "ddpg").n_seeds == 2
    assert row(result.table, "ddpg").seeds == "0;1"
    assert row(result.table, "dqn").n_seeds == 1


def test_a_changed_setting_is_its_own_group_and_the_learner_path_is_not(tmp_path: Path) -> None:
    runs = [make_run(tmp_path, "plain_s0", seed=0, collisions=[1.0] * 80),
            make_run(tmp_path, "sb3_s1", seed=1, collisions=[3.0] * 80, extra={"train": {"backend": "libsumo"}}),
            make_run(tmp_path, "shield_s0", seed=0, collisions=[0.0] * 80, extra={"shield": {"enabled": True}}),
            make_run(tmp_path, "top40_s0", seed=0, collisions=[5.0] * 80,
                     extra={"scenario": {"agent_max_speed_mps": 40.0}, "shield": {"enabled": True}}),
            make_run(tmp_path, "short_s0", seed=0, collisions=[7.0] * 80, extra={"train": {"episodes": 150}}),
            # DDPG never reads the DQN section nor PPO's rollout length: a run saved with other values there
            # is the same DDPG run
            make_run(tmp_path, "dqn_section_s2", seed=2, collisions=[2.0] * 80,
                     extra={"train": {"dqn": {"target_update_steps": 1000}, "actor_critic": {"ppo_n_steps": 64}}}),
            # a DQN run's discrete actions follow from its algorithm: not a variant
            make_run(tmp_path, "dqn_s0", "dqn", seed=0, collisions=[4.0] * 80, extra={"action": {"kind": "discrete"}}),
            make_run(tmp_path, "dqn_target_s0", "dqn", seed=0, collisions=[6.0] * 80,
                     extra={"action": {"kind": "discrete"},
                            "train": {"dqn": {"target_update_steps": 1000}, "actor_critic": {"tau": 0.01}}})]
    result = report(runs, tmp_path / "out")
    table = result.table
    assert list(table.algorithm) == ["ddpg"] * 4 + ["dqn"] * 2
    assert list(table.variant) == ["", "scenario.agent_max_speed_mps=40.0, shield.enabled=True",
                                   "shield.enabled=True", "train.episodes=150",
                                   "", "train.dqn.target_update_steps=1000"]
    assert list(table.n_seeds) == [3, 1, 1, 1, 1, 1] and list(table.collisions_mean) == [2.0, 5.0, 0.0, 7.0, 4.0, 6.0]
    assert list(table.collisions_paper) == [0.449] * 4 + [0.952] * 2
    md = (tmp_path / "out" / "summary.md").read_text()
    # the columns every group shares are named once above the table, not repeated in each row
    assert "Every row: reward preset fields_zones_overtake_collision; density (veh/km) 70." in md
    assert "| ddpg | default | 3 |" in md
    assert "| shield.enabled=True | 1 |" in md
    assert len(fenced_rows(md)) == 1 + 2 + 6  # the shared columns, header, rule, one row per group


def test_eval_source_tabulates_each_runs_evaluation_at_its_density(tmp_path: Path) -> None:
    runs = [make_run(tmp_path / "runs", f"s{seed}", seed=seed, collisions=[3.0] * 80) for seed in (0, 1)]
    for run, value in zip(runs, (0.2, 0.4)):  # evaluated at 120 veh/km: 50 episodes each
        made = make_run(tmp_path / "made", run.name, density=120.0, collisions=[value] * 50, episodes=50)
        (run / "eval_d120").mkdir()
        (made / "episodes.csv").rename(run / "eval_d120" / "episodes.csv")
    result = report(runs, tmp_path / "out", source="eval_d120")
    assert result.skipped == []
    only = result.table.iloc[0]
    assert (only.density_veh_per_km, only.n_seeds) == (120.0, 2)
    assert only.collisions_mean == pytest.approx(0.3) and only.collisions_paper == 0.591  # Table 7 at 120
    assert "**Evaluation** (`RUN/eval_d120/episodes.csv`" in (tmp_path / "out" / "summary.md").read_text()
    with pytest.raises(ReportError, match="no eval/episodes.csv"):
        report(runs, tmp_path / "out2", source="eval")


def test_several_evaluations_side_by_side_one_row_each_a_missing_one_named(tmp_path: Path) -> None:
    runs = [make_run(tmp_path / "runs", f"s{seed}", seed=seed, collisions=[3.0] * 80) for seed in (0, 1)]
    for run, at70, at120 in zip(runs, (1.0, 2.0), (10.0, 30.0)):
        for folder, density, value in (("eval", 70.0, at70), ("eval_d120", 120.0, at120)):
            if folder == "eval_d120" and run.name == "s1":
                continue  # s1 was never evaluated at 120 veh/km
            made = make_run(tmp_path / "made" / folder, run.name, density=density, collisions=[value] * 50,
                            episodes=50)
            (run / folder).mkdir()
            (made / "episodes.csv").rename(run / folder / "episodes.csv")
    result = report(runs, tmp_path / "out", source=["eval", "eval_d120"])
    table = result.table
    assert list(table.evaluation) == ["eval", "eval_d120"] and list(table.density_veh_per_km) == [70.0, 120.0]
    assert list(table.n_seeds) == [2, 1] and list(table.collisions_mean) == [1.5, 10.0]
    assert table.collisions_std.iloc[0] == pytest.approx(math.sqrt(0.5)) and math.isnan(table.collisions_std.iloc[1])
    assert result.skipped == [(runs[1], "no eval_d120/episodes.csv (run 'lanefree evaluate' first)")]
    assert [p.name for p in result.files] == ["evaluations_collisions.png", "evaluations_speed_dev.png",
                                              "summary.csv", "summary.md"]
    assert all(p.stat().st_size > 0 for p in result.files)
    rows = fenced_rows((tmp_path / "out" / "summary.md").read_text())
    assert rows[0] == f"Every row: algorithm ddpg; reward preset {FZOC}; variant default."
    assert rows[3].startswith("| `eval` | 70 | 2 | 1.500 ± 0.707 |")
    assert rows[4].startswith("| `eval_d120` | 120 | 1 | 10.000 ± n/a |")
    with pytest.raises(ReportError, match="name each evaluation folder once"):
        report(runs, tmp_path / "out2", source=["eval", "eval"])
    with pytest.raises(ReportError, match="no run has any of the evaluations eval_d90, eval_shield"):
        report(runs, tmp_path / "out3", source=["eval_d90", "eval_shield"])


def test_evaluations_of_runs_at_several_densities_keep_each_density_its_own_bar(tmp_path: Path) -> None:
    runs = []
    for density, value in ((70.0, 1.0), (120.0, 4.0)):
        run = make_run(tmp_path / "runs", f"d{density:g}", density=density, collisions=[3.0] * 80)
        for folder, episodes in (("eval", 50), ("eval_shield", 20)):  # the shielded one stopped after 20
            made = make_run(tmp_path / "made" / folder, run.name, density=density, collisions=[value] * episodes,
                            episodes=episodes)
            (run / folder).mkdir()
            (made / "episodes.csv").rename(run / folder / "episodes.csv")
        runs.append(run)
    broken = tmp_path / "runs" / "broken"
    broken.mkdir()
    result = report([*runs, broken], tmp_path / "out", source=["eval", "eval_shield"])
    assert evaluation_series(result.table) == [("ddpg", FZOC, "", 70.0), ("ddpg", FZOC, "", 120.0)] * 2
    one = result.table[result.table.density_veh_per_km == 70.0]
    assert evaluation_series(one) == [("ddpg", FZOC, "")] * 2  # one density per evaluation: no split
    assert [p for p, _ in result.skipped] == [broken]  # named once, not once per evaluation
    assert sum("(eval_shield) has 20 episodes (< 50)" in note for note in result.notes) == 2
    assert "(eval) has" not in " ".join(result.notes)
    assert "## Notes" in (tmp_path / "out" / "summary.md").read_text()


def test_run_folders_after_eval_are_refused_in_one_line(two_seed_runs: list[Path], tmp_path: Path) -> None:
    res = lanefree("report", "--eval", *map(str, two_seed_runs), "--out", str(tmp_path / "out"))
    assert res.returncode == 2 and "put the RUN folders before --eval" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and not (tmp_path / "out").exists()
    res = lanefree("report", "--eval", "eval_d90")
    assert res.returncode == 2 and "needs at least one RUN folder" in res.stderr
    res = lanefree("report", *map(str, two_seed_runs), "--eval", "eval/", "--out", str(tmp_path / "out"))
    assert "put the RUN folders" not in res.stderr and "no eval/episodes.csv" in res.stderr  # a name with its slash


def test_last_50_means_averaged_over_seeds_exactly(two_seed_runs: list[Path], tmp_path: Path) -> None:
    table = report(two_seed_runs, tmp_path / "out").table
    ddpg = row(table, "ddpg")
    # mean over seeds of (0.5, 0.7); sample std (ddof=1) = sqrt(((−0.1)² + 0.1²) / 1)
    assert ddpg.collisions_mean == pytest.approx(0.6, abs=1e-12)
    assert ddpg.collisions_std == pytest.approx(math.sqrt(0.02), abs=1e-12)
    assert ddpg.speed_dev_mps_mean == pytest.approx(0.6, abs=1e-12)
    assert ddpg.speed_dev_mps_std == pytest.approx(math.sqrt(0.08), abs=1e-12)
    assert ddpg.return_mean == pytest.approx(110.0, abs=1e-9)
    assert ddpg.return_std == pytest.approx(math.sqrt(200.0), abs=1e-9)
    assert ddpg.overtakes_mean == pytest.approx(3.0, abs=1e-12)
    assert ddpg.overtakes_std == pytest.approx(math.sqrt(2.0), abs=1e-12)
    assert ddpg.episodes_min == 80
    dqn = row(table, "dqn")
    assert dqn.collisions_mean == pytest.approx(2.0) and dqn.speed_dev_mps_mean == pytest.approx(0.3)
    assert math.isnan(dqn.collisions_std)  # one seed: no std


def test_other_window_lengths_change_the_means(two_seed_runs: list[Path], tmp_path: Path) -> None:
    # last=80 takes every episode: seed 0 = (30·10 + 25)/80, seed 1 = (30·10 + 35)/80
    table = report(two_seed_runs, tmp_path / "out", last=80).table
    expected = ((300 + 25) / 80 + (300 + 35) / 80) / 2
    assert row(table, "ddpg").collisions_mean == pytest.approx(expected, abs=1e-12)


def test_paper_numbers_beside_matching_cells_only(two_seed_runs: list[Path], tmp_path: Path) -> None:
    extra = make_run(tmp_path / "runs", "ddpg_d100", density=100.0, seed=3)  # paper has no 100 veh/km
    extra2 = make_run(tmp_path / "runs", "td3_d70", algo="td3", seed=0)  # paper has no TD3
    out = tmp_path / "out"
    table = report(two_seed_runs + [extra, extra2], out).table
    ddpg = row(table, "ddpg")
    assert ddpg.collisions_paper == 0.449 and ddpg.speed_dev_mps_paper == 0.723
    assert row(table, "dqn").collisions_paper == 0.952 and row(table, "dqn").speed_dev_mps_paper == 0.471
    for missing in (row(table, "ddpg", density=100.0), row(table, "td3")):
        assert math.isnan(missing.collisions_paper) and math.isnan(missing.speed_dev_mps_paper)
        assert missing.paper_source == ""

    md = (out / "summary.md").read_text()
    assert f"Every row: reward preset {FZOC}; variant default." in md  # columns: algorithm, density, ...
    lines = {ln.split("|")[1].strip() + "/" + ln.split("|")[2].strip(): ln for ln in fenced_rows(md)
             if ln.startswith("| ") and not ln.startswith("| algorithm")}
    assert "0.600 ± 0.141 (paper 0.449)" in lines["ddpg/70"]
    assert "0.600 ± 0.283 (paper 0.723)" in lines["ddpg/70"]
    assert "(paper 0.952)" in lines["dqn/70"] and "(paper 0.471)" in lines["dqn/70"]
    assert "paper" not in lines["ddpg/100"]
    assert "paper" not in lines["td3/70"]

    with open(out / "summary.csv", newline="") as fh:
        csv_rows = list(csv.DictReader(fh))
    by_key = {(r["algorithm"], r["density_veh_per_km"]): r for r in csv_rows}
    assert float(by_key[("ddpg", "70.0")]["collisions_paper"]) == 0.449
    assert float(by_key[("ddpg", "70.0")]["collisions_mean"]) == pytest.approx(0.6, abs=1e-12)
    assert by_key[("ddpg", "100.0")]["collisions_paper"] == ""


def test_paper_reference_table_matches_spec() -> None:
    assert len(PAPER_REFERENCE) == 15  # distinct settings of specification §10 Tables 5–8
    assert PAPER_REFERENCE[("ddpg", "collision", 70.0)][:2] == (2.256, 0.135)
    assert PAPER_REFERENCE[("ddpg", "fields_overtake_collision", 120.0)][:2] == (1.066, 1.715)
    assert PAPER_REFERENCE[("per", FZOC, 70.0)][:2] == (0.792, 0.617)
    assert PAPER_REFERENCE[("ddpg", "fields_overtake_collision", 70.0)].source == "Tables 5, 6, 7"
    assert PAPER_REFERENCE[("ddpg", FZOC, 70.0)].source == "Tables 6, 7, 8"
    assert PAPER_REFERENCE[("dueling", FZOC, 70.0)].source == "Table 8"


def test_damaged_runs_are_skipped_by_name(two_seed_runs: list[Path], tmp_path: Path) -> None:
    bad = tmp_path / "bad"
    truncated = make_run(bad, "truncated", seed=7)
    text = (truncated / "episodes.csv").read_text()
    (truncated / "episodes.csv").write_text(text[: len(text) - 40])  # last line cut mid-row
    abc = make_run(bad, "abc", seed=8)
    lines = (abc / "episodes.csv").read_text().splitlines(keepends=True)
    fields = lines[10].split(",")
    fields[EPISODE_COLUMNS.index("collisions")] = "abc"
    lines[10] = ",".join(fields)
    (abc / "episodes.csv").write_text("".join(lines))
    nocol = make_run(bad, "no_overtakes", seed=9)
    with open(nocol / "episodes.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    with open(nocol / "episodes.csv", "w", newline="") as fh:
        cols = [c for c in EPISODE_COLUMNS if c != "overtakes"]
        writer = csv.DictWriter(fh, fieldnames=cols, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    noconf = make_run(bad, "no_config", seed=10)
    (noconf / "config.yaml").unlink()
    badyaml = make_run(bad, "bad_yaml", seed=11)
    (badyaml / "config.yaml").write_text("train: [unclosed\n  algo: ddpg\n")

    damaged = [truncated, abc, nocol, noconf, badyaml, bad / "missing_folder"]
    result = report(two_seed_runs + damaged, tmp_path / "out")
    reasons = {p.name: r for p, r in result.skipped}
    assert set(reasons) == {p.name for p in damaged}
    assert "line 81" in reasons["truncated"] and "fields" in reasons["truncated"]
    assert "collisions" in reasons["abc"] and "'abc'" in reasons["abc"]
    assert "overtakes" in reasons["no_overtakes"]
    assert "config.yaml" in reasons["no_config"]
    assert "config.yaml" in reasons["bad_yaml"]
    assert all("\n" not in r for r in reasons.values())
    # the report is made from the good runs only, with the same numbers as without the bad ones
    assert len(result.table) == 2
    assert row(result.table, "ddpg").n_seeds == 2
    assert row(result.table, "ddpg").collisions_mean == pytest.approx(0.6, abs=1e-12)
    md = (tmp_path / "out" / "summary.md").read_text()
    assert "truncated" in md and "Skipped runs" in md


def test_all_bad_input_raises_report_error(tmp_path: Path) -> None:
    run = make_run(tmp_path, "only", seed=0)
    (run / "episodes.csv").write_text(",".join(EPISODE_COLUMNS) + "\n")  # header only
    other = make_run(tmp_path, "other", seed=1)
    (other / "episodes.csv").unlink()
    with pytest.raises(ReportError) as info:
        report([run, other, tmp_path / "nope"], tmp_path / "out")
    message = str(info.value)
    assert "\n" not in message and "no usable run" in message and "only" in message
    assert isinstance(info.value, ValueError)
    with pytest.raises(ReportError):
        report([], tmp_path / "out")


def test_unwritable_output_raises_report_error(two_seed_runs: list[Path], tmp_path: Path) -> None:
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    with pytest.raises(ReportError) as info:
        report(two_seed_runs, blocker / "out")
    assert "\n" not in str(info.value) and "cannot write" in str(info.value)


def test_report_replaces_only_its_own_earlier_output(two_seed_runs: list[Path], tmp_path: Path) -> None:
    """--out into a folder the report did not make (a user's notes) is refused and the folder untouched; an
    earlier report is replaced whole."""
    users = tmp_path / "notes"
    users.mkdir()
    (users / "summary.md").write_text("my notes")
    with pytest.raises(ReportError, match="not the output of an earlier 'lanefree report'"):
        report(two_seed_runs, users)
    assert (users / "summary.md").read_text() == "my notes" and len(list(users.iterdir())) == 1
    out = tmp_path / "rep"
    first = report(two_seed_runs, out)
    assert all(p.is_file() for p in first.files)
    (out / "stale.png").write_text("from an older report")
    again = report(two_seed_runs, out)
    assert [p.name for p in again.files] == [p.name for p in first.files] and not (out / "stale.png").exists()


def test_written_files_are_valid(two_seed_runs: list[Path], tmp_path: Path) -> None:
    import matplotlib.image

    out = tmp_path / "out"
    result = report(two_seed_runs, out, smooth=5)
    names = [p.name for p in result.files]
    assert names == ["curves_return.png", "curves_collisions.png", "curves_speed_dev.png",
                     "summary.csv", "summary.md", "claims.csv", "claims.md"]  # dqn − ddpg at FZOC/70: a claim
    for name in names[:3]:
        data = (out / name).read_bytes()
        assert data[:8] == PNG_MAGIC
        assert len(data) > 10_000
        pixels = matplotlib.image.imread(out / name)
        assert pixels.ndim == 3 and pixels.shape[0] > 300 and pixels.shape[1] > 500
        assert float(np.std(pixels)) > 0.01  # not a blank canvas
    md = (out / "summary.md").read_text()
    assert ("| algorithm | seeds | collisions / episode | speed deviation (m/s) | return | overtakes / episode |"
            in md) and f"Every row: reward preset {FZOC}; density (veh/km) 70; variant default." in md


def _run_data(values: list[float], seed: int) -> RunData:
    import pandas as pd

    frame = pd.DataFrame({"return": values, "collisions": values, "speed_dev_mps": values, "overtakes": values},
                         index=pd.Index(range(1, len(values) + 1), name="episode"))
    return RunData(Path(f"r{seed}"), "ddpg", FZOC, 70.0, seed, frame)


def test_the_paper_claims_two_groups_of_default_runs_decide_are_checked(tmp_path: Path) -> None:
    """DDPG (last-50 collisions 0.5, 0.6, 0.7) against DQN (2.0, 2.1, 2.2) at FZOC/70, 625 episodes each: Table 8's
    claim, every DQN run above every DDPG run; a shielded DDPG run (a variant), an on-ramp DQN run and a DDPG run
    stopped at episode 80 of 625 (its last 50 are early training) are not counted."""
    runs = tmp_path / "runs"
    folders = [make_run(runs, f"ddpg_s{k}", seed=k, collisions=early_then_last(9.0, [c] * 50, 625), episodes=625)
               for k, c in enumerate((0.5, 0.6, 0.7))]
    folders += [make_run(runs, f"dqn_s{k}", algo="dqn", seed=k, collisions=early_then_last(9.0, [c] * 50, 625),
                         episodes=625) for k, c in enumerate((2.0, 2.1, 2.2))]
    folders += [make_run(runs, "ddpg_shield", seed=5, collisions=[0.0] * 80, extra={"shield": {"enabled": True}}),
                make_run(runs, "dqn_onramp", algo="dqn", seed=7, collisions=[9.0] * 80,
                         extra={"road": {"kind": "onramp"}}),
                make_run(runs, "ddpg_s9", seed=9, collisions=[9.0] * 80)]
    result = report(folders, tmp_path / "rep")
    assert [p.name for p in result.files][-2:] == ["claims.csv", "claims.md"]
    claims = list(csv.DictReader(open(tmp_path / "rep" / "claims.csv")))
    assert [c["claim"] for c in claims] == ["DDPG has fewer collisions than DQN (Table 8): dqn − ddpg > 0",
                                            "DQN has a smaller speed deviation than DDPG (Table 8): ddpg − dqn > 0"]
    claim, speed = claims
    assert float(speed["difference"]) == 0.0 and speed["verdict"] == "undecided"  # every run 0.5 m/s
    assert (claim["n_a"], claim["n_b"]) == ("3", "3")
    assert float(claim["difference"]) == pytest.approx(1.5) and float(claim["pairs_a_above_b"]) == 9
    assert float(claim["rank_p"]) == pytest.approx(0.05) and claim["verdict"] == "consistent with the paper"
    assert "| 3, 3 | +0.503 | +1.500 [" in (tmp_path / "rep" / "claims.md").read_text()
    assert result.notes == ["the paper's claims count complete runs only (every one of the 625 planned episodes); "
                            "left out of claims.md: ddpg_s9 (80/625 episodes)"]
    alone = report(folders[:3], tmp_path / "alone")  # one setting: no claim, no claims files
    assert "claims.md" not in [p.name for p in alone.files] and not (tmp_path / "alone" / "claims.md").exists()
    cut = report(folders[:6], tmp_path / "cut", first=60)  # the paper's claims are over whole runs
    assert "claims.md" not in [p.name for p in cut.files]
    res = lanefree("report", *map(str, folders[:6]), "--out", str(tmp_path / "cli"))
    assert res.returncode == 0 and "-> " + str(tmp_path / "cli") + " (and claims.md)" in res.stdout, res.stderr


def test_curves_use_trailing_moving_average_and_std_over_seeds() -> None:
    curve = smoothed_curve([_run_data([1, 2, 3, 4, 5, 6], 0), _run_data([3, 4, 5, 6, 7, 8], 1)], "collisions", 3)
    # trailing window of 3: run 0 → 1, 1.5, 2, 3, 4, 5; run 1 → 3, 3.5, 4, 5, 6, 7
    assert curve["mean"].tolist() == pytest.approx([2, 2.5, 3, 4, 5, 6])
    assert curve["std"].tolist() == pytest.approx([math.sqrt(2)] * 6)
    shorter = smoothed_curve([_run_data([1, 2, 3, 4], 0), _run_data([3, 4, 5, 6, 7, 8], 1)], "collisions", 2)
    assert shorter["n"].tolist() == [2, 2, 2, 2, 1, 1]  # episodes 5–6 only from the longer run
    assert shorter["mean"].iloc[-1] == pytest.approx(7.5) and math.isnan(shorter["std"].iloc[-1])


def test_a_short_runs_note_counts_its_episodes_in_words(tmp_path):
    runs = [make_run(tmp_path / "runs", "one", collisions=[1.0], episodes=1),
            make_run(tmp_path / "runs", "two", seed=1, collisions=[1.0] * 2, episodes=2)]
    notes = report(runs, tmp_path / "out").notes
    assert f"{runs[0]} has 1 episode (< 50); its mean uses all of them" in notes
    assert f"{runs[1]} has 2 episodes (< 50); its mean uses all of them" in notes

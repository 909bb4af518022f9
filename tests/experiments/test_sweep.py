"""``lanefree sweep``: grids, manifest, run states, bootstrap CIs and summaries (fast, no Ray), and
real sweeps on Ray (slow): a tiny grid on the embedded Ray and its no-op rerun, the same grid on a
two-node Ray cluster on 127.0.0.1, and a worker killed mid-run plus Ctrl-C and --resume.

Every Ray process binds to 127.0.0.1 only; the cluster test starts its own head and worker node
(own ports, own temp dirs), checks that none of their processes listens elsewhere, and stops them
by process id.
"""

from __future__ import annotations

import contextlib
import csv
import ipaddress
import json
import math
import os
import re
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from lanefree_sumo.cli import main
from lanefree_sumo.config import merge_config
from lanefree_sumo.errors import ConfigError, ReportError, RunError, UsageError
from lanefree_sumo.experiments.storage.episodes import EPISODE_COLUMNS
from lanefree_sumo.experiments.storage.rundir import RunDir, record_session, write_config
from lanefree_sumo.experiments.sweep.command import _pace_sample, plan, status_text
from lanefree_sumo.experiments.sweep.grid import (
    BUILTIN_GRIDS,
    GRIDS_DIR,
    Cell,
    Grid,
    builtin_descriptions,
    builtin_grid,
    load_grid,
    parse_grid,
)
from lanefree_sumo.experiments.sweep.manifest import Manifest, SweepDir, check_same_grid, read_manifest, write_manifest
from lanefree_sumo.experiments.sweep.state import BUSY, COMPLETE, DAMAGED, PARTIAL, PENDING, STALE, inspect_run
from lanefree_sumo.experiments.sweep.summary import COLUMNS, RUN_COLUMNS, bootstrap_ci, complete_seeds, summarize

from conftest import CLI_ENV, ROOT, fenced_rows, lanefree, lanefree_popen

TINY = {"reward_presets": ["collision", "fields_collision"], "n_seeds": 2, "episodes": 2,
        "overrides": {"sim": {"episode_steps": 40}, "train": {"checkpoint_every_episodes": 1}}}
"""2 presets × 2 seeds × 2 episodes of 40 steps: the smallest grid that still has CIs."""
TINY_SEEDS = {key: value for key, value in TINY.items() if key != "n_seeds"}


def write_grid(path: Path, data: dict) -> Path:
    path.write_text(yaml.safe_dump(data))
    return path


def episodes_of(csv_path: Path) -> list[int]:
    if not csv_path.exists():
        return []
    with open(csv_path, newline="") as fh:
        return [int(r["episode"]) for r in csv.DictReader(fh) if (r.get("episode") or "").isdigit()]


def fake_run(folder: Path, grid, cell: Cell, episodes: int, collisions: float = 1.0, model: bool = True,
             checkpoint: int | None = None, extra_rows: list[int] | None = None, wall_s: float = 0.0,
             ended: str | None = None) -> None:
    """A run folder as train() leaves it, without training: config, episodes.csv (each episode taking
    ``wall_s`` seconds), checkpoint, model, and a training session that ended at ``ended`` (ISO 8601)."""
    folder.mkdir(parents=True)
    write_config(folder, grid.config(cell))
    with open(folder / "episodes.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=EPISODE_COLUMNS, extrasaction="ignore", restval="0")
        writer.writeheader()
        for e in list(range(1, episodes + 1)) + (extra_rows or []):
            writer.writerow({"episode": e, "return": 1.0, "collisions": collisions, "speed_dev_mps": collisions / 2,
                             "overtakes": 0, "wall_s": wall_s})
    if checkpoint is not None:
        ckpt = folder / "checkpoints" / f"ep_{checkpoint:05d}"
        ckpt.mkdir(parents=True)
        (ckpt / "model.zip").write_bytes(b"model")
        (ckpt / "state.json").write_text(json.dumps({"episodes": checkpoint, "timesteps": 40 * checkpoint}))
    if model:
        (folder / "model.zip").write_bytes(b"model")
    if ended is not None:
        record_session(folder, {"episodes_done": episodes, "ended": ended})


def walls_from(folder: Path, episode: int, wall: float) -> None:
    """Rewrite a run's episodes.csv so that its episodes from ``episode`` on took ``wall`` s each."""
    path = folder / "episodes.csv"
    rows = list(csv.DictReader(open(path)))
    for row in rows:
        if int(row["episode"]) >= episode:
            row["wall_s"] = str(wall)
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


# -- grids ----------------------------------------------------------------------------------------

def test_builtin_grids_are_the_papers_tables():
    assert [len(builtin_grid(f"table{t}").settings) for t in (5, 6, 7, 8)] == [5, 3, 6, 5]
    paper = builtin_grid("paper")
    assert len(paper.settings) == 15 and len(set(paper.settings)) == 15  # the union, each setting once
    assert len(paper.cells()) == 150 and paper.episodes == 625 and paper.seeds == tuple(range(10))
    assert not paper.budget()["reduced"] and all(s.tables for s in paper.settings)
    t7 = builtin_grid("table7")
    assert sorted({s.density for s in t7.settings}) == [70.0, 90.0, 120.0]
    assert t7.cells()[0].name == "ddpg_fields_zones_overtake_collision_d70_s0"
    assert {s.algorithm for s in builtin_grid("table8").settings} == {"ddpg", "dqn", "ddqn", "dueling", "per"}


def test_builtin_grids_are_the_package_grid_files_and_the_paper_grid_is_its_manifest():
    """The names are the files of the package's grids folder, each with what it is; the paper grid is the grid of
    the committed sweep, being extended from 3 seeds to the paper's 10 (so it resumes under today's built-in)."""
    assert BUILTIN_GRIDS == ("paper", "table5", "table6", "table7", "table8", "varobs")
    assert sorted(p.stem for p in GRIDS_DIR.glob("*.yaml")) == list(BUILTIN_GRIDS)
    descriptions = builtin_descriptions()
    assert "Tables 5-8" in descriptions["paper"] and "set encoder" in descriptions["varobs"]
    committed = read_manifest(ROOT / "results" / "paper").grid
    assert builtin_grid("paper").to_dict() == committed.to_dict()


def test_the_varobs_grid_sets_the_set_encoder_against_the_vector_at_the_papers_seeds():
    grid = builtin_grid("varobs")
    assert [s.label for s in grid.settings] == [
        f"{algo} / fields_zones_overtake_collision / d70 / {variant}" for variant in ("default", "set")
        for algo in ("ddpg", "dqn")]
    assert grid.seeds == tuple(range(10)) and grid.episodes == 625 and grid.compare == ("set",)
    assert not grid.budget()["reduced"] and len(grid.cells()) == 40
    names = [c.name for c in grid.cells()]
    assert names[:4] == ["ddpg_fields_zones_overtake_collision_d70_default_s0",
                         "dqn_fields_zones_overtake_collision_d70_default_s0",
                         "ddpg_fields_zones_overtake_collision_d70_set_s0",
                         "dqn_fields_zones_overtake_collision_d70_set_s0"]
    vector, sets = grid.config(grid.cells()[0]), grid.config(grid.cells()[2])
    assert (vector.observation.kind, sets.observation.kind, sets.observation.encoder) == ("vector", "set", "paper")
    assert Grid.from_dict(grid.to_dict(), "manifest") == grid  # the manifest keeps what to compare
    three = grid.with_budget(seeds=3)
    assert three.compare == ("set",) and three.budget()["notes"] == ["3 seed(s) per setting instead of the paper's 10"]


def test_a_grid_of_tables_is_those_tables_settings_with_variants():
    grid = parse_grid({"tables": [6, 8], "n_seeds": 1, "variants": {"default": {}, "cap25": {
        "scenario.agent_max_speed_mps": 25}}}, "t", "t.yaml")
    paper = {s for s in builtin_grid("table6").settings} | {s for s in builtin_grid("table8").settings}
    assert {s._replace(variant="") for s in grid.settings} == paper and len(grid.settings) == 2 * len(paper)
    for bad, named in (({"tables": [6], "densities": [70]}, "'densities' is given too"), ({"tables": [4]}, "tables"),
                       ({"tables": [6, 6]}, "tables"), ({"tables": []}, "tables"),
                       ({"tables": [6], "compare": ["x"]}, "name one in variants"),
                       ({"tables": [6], "variants": {"default": {}, "b": {}}, "compare": ["default"]}, "compare")):
        with pytest.raises(ConfigError, match=re.escape(named)):
            parse_grid(bad, "bad", "bad.yaml")


def test_yaml_grid_and_budget_overrides(tmp_path):
    grid = load_grid(write_grid(tmp_path / "g.yaml", {**TINY, "densities": [70, 90]}))
    assert grid.name == "g" and len(grid.settings) == 4 and grid.seeds == (0, 1)
    assert [c.name for c in grid.cells()][:2] == ["ddpg_collision_d70_s0", "ddpg_collision_d90_s0"]
    cfg = grid.config(grid.cells()[-1])
    assert (cfg.seed, cfg.reward.preset, cfg.scenario.density_veh_per_km, cfg.train.episodes,
            cfg.sim.episode_steps) == (1, "fields_collision", 90.0, 2, 40)
    smaller = builtin_grid("table7").with_budget(seeds=3, episodes=100, episode_steps=200)
    budget = smaller.budget()
    assert budget["reduced"] and smaller.seeds == (0, 1, 2) and smaller.episode_steps == 200
    assert any("100 episodes" in n for n in budget["notes"]) and any("3 seed" in n for n in budget["notes"])


@pytest.mark.parametrize(("data", "named"), [
    ({**TINY, "seed": [1]}, "'seed'"),
    ({**TINY, "algorithms": ["dqnn"]}, "algorithms: 'dqnn'"),
    ({**TINY, "reward_presets": ["collisions"]}, "reward_presets: 'collisions'"),
    ({**TINY, "densities": [0]}, "densities"),
    ({**TINY, "densities": [1000]}, "d1000"),
    ({**TINY_SEEDS, "seeds": [0, 0]}, "seeds must be distinct whole numbers"),
    ({**TINY_SEEDS, "seeds": [1, 1.0]}, "seeds must be distinct whole numbers"),
    ({**TINY, "densities": [70, 70.0]}, "densities"),
    ({**TINY, "densities": [70, 70.0000001]}, "the same run folder ddpg_collision_d70_s0"),
    ({**TINY, "densities": [70.00001, 70.00002]}, "the same run folder"),
    ({**TINY, "seeds": [0, 1]}, "either 'seeds' or 'n_seeds'"),
    ({**TINY, "episodes": 0}, "episodes"),
    ({**TINY, "overrides": {"seed": 3}}, "overrides.seed"),
    ({**TINY, "overrides": {"scenario": {"agents": 3}}}, "overrides.scenario.agents"),
    ({**TINY, "overrides": {"train": {"episodes": 3}}}, "overrides.train.episodes"),
    ({**TINY, "overrides": {"sim": {"episode_stepz": 3}}}, "sim.episode_stepz"),
    ({"algorithms": ["ddpg"]}, "'reward_presets' is missing"),
    ([1, 2], "expected a mapping"),
])
def test_bad_grids_are_one_line_errors_naming_the_key(data, named):
    with pytest.raises(ConfigError) as err:
        parse_grid(data, "bad", "bad.yaml")
    assert named in str(err.value) and "\n" not in str(err.value) and "bad.yaml" in str(err.value)


def test_cli_bad_input_is_one_line_exit_2_and_writes_nothing(tmp_path, capsys):
    out = tmp_path / "sweep"
    bad = write_grid(tmp_path / "bad.yaml", {**TINY, "densities": [1000]})
    for argv in (["sweep", "nosuch", "--out", str(out)], ["sweep", str(bad), "--out", str(out)],
                 ["sweep"], ["sweep", "table5", "--resume", str(out)], ["sweep", "table5", "--seeds", "0"],
                 ["sweep", "table5", "--out", str(out), "--address", "nonsense"],
                 ["sweep", "table5", "--out", str(out), "--workers", "2", "--address", "127.0.0.1:6379"],
                 ["sweep", "table5", "--out", str(out), "--address", f"127.0.0.1:{free_port()}"],
                 ["sweep", "--status", str(out)], ["sweep", "--resume", str(out), "--episodes", "3"],
                 ["sweep", "table5", "--out", str(out), "--workers", "0"],
                 ["sweep", "table5", "--out", str(out), "--retries", "-1"], ["sweep", "--list", "varobs"],
                 ["sweep", "--list", "--seeds", "3"]):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith("lanefree: error: ") and err.count("\n") == 1, (argv, err)
    assert not out.exists()
    assert main(["sweep", "--list"]) == 0  # every built-in grid, one line each with what it is
    listed = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in listed] == list(BUILTIN_GRIDS) and "Liu et al." in listed[-1]


# -- manifest and run states ----------------------------------------------------------------------

def test_manifest_roundtrip_and_another_grid_is_refused(tmp_path):
    grid = parse_grid(TINY, "tiny", "tiny.yaml")
    manifest = Manifest(grid, sessions=[{"command": "lanefree sweep tiny.yaml"}])
    write_manifest(tmp_path, manifest)
    back = read_manifest(tmp_path)
    assert back.grid == grid and back.sessions == manifest.sessions
    saved = yaml.safe_load((tmp_path / "sweep.yaml").read_text())
    assert saved["budget"]["reduced"] and saved["budget"]["paper_episodes"] == 625 and saved["runs"] == 4
    check_same_grid(tmp_path, back.grid, grid)
    with pytest.raises(UsageError, match=r"seeds: \[0, 1\] vs \[0, 1, 2\]"):
        check_same_grid(tmp_path, back.grid, grid.with_budget(seeds=3))
    with pytest.raises(UsageError, match="episodes"):
        plan(tmp_path, grid.with_budget(episodes=5))
    (tmp_path / "sweep.yaml").write_text("grid: [1\n")
    with pytest.raises(RunError, match="sweep.yaml is unusable"):
        read_manifest(tmp_path)
    # the folder's own path becomes <sweep folder>; a file beside it whose name starts the same stays itself
    here = tmp_path.resolve()
    moved = Manifest(grid, sessions=[{"command": f"lanefree sweep {here}_paper.yaml --out {here} --resume {here}/"}])
    write_manifest(tmp_path, moved)
    assert read_manifest(tmp_path).sessions[0]["command"] == \
        f"lanefree sweep {here}_paper.yaml --out <sweep folder> --resume <sweep folder>/"


def test_run_states_and_adoption_of_existing_run_folders(tmp_path):
    grid = parse_grid({**TINY, "episodes": 3}, "tiny", "tiny.yaml")
    sweep = SweepDir(tmp_path)
    a, b, c, d = grid.cells()
    fake_run(sweep.run(a), grid, a, 3)                                    # complete
    fake_run(sweep.run(b), grid, b, 2, model=False, checkpoint=1)         # interrupted: resumable
    fake_run(sweep.run(c), grid, c, 1, model=False)                       # died before its first checkpoint
    states = plan(tmp_path, grid)
    assert [states[x.name].state for x in (a, b, c, d)] == [COMPLETE, PARTIAL, STALE, PENDING]
    assert states[b.name].episodes == 2 and "episode 1" in states[b.name].detail
    shutil.rmtree(sweep.run(a))
    fake_run(sweep.run(a), grid, a, 3, extra_rows=[3])                    # a duplicated episode
    assert inspect_run(sweep.run(a), 3).state == DAMAGED
    # a run folder of another config, or with more episodes than the grid's, is refused, naming why
    other = parse_grid({**TINY, "episodes": 3, "overrides": {**TINY["overrides"], "reward": {"epsilon_r": 0.2}}},
                       "tiny", "tiny.yaml")
    with pytest.raises(RunError, match=r"reward\.epsilon_r = 0\.1 in the folder vs 0\.2 in the grid"):
        plan(tmp_path, other)
    with pytest.raises(RunError, match="run of 3 episodes but the grid asks for 2"):
        plan(tmp_path, parse_grid(TINY, "tiny", "tiny.yaml"))
    # a shorter finished run is extended
    assert plan(tmp_path, parse_grid({**TINY, "episodes": 5}, "tiny", "tiny.yaml"))[b.name].state == PARTIAL
    (sweep.run(d)).mkdir(parents=True)
    (sweep.run(d) / "notes.txt").write_text("mine")
    with pytest.raises(RunError, match="not a run folder"):
        plan(tmp_path, grid)


def test_committed_runs_without_models_are_complete_and_any_backend_is_adopted(tmp_path):
    """git keeps no models: a finished run's small files (all episodes, last_session.json) are a complete run,
    never retrained or deleted; a run trained on libsumo (or with SB3's loop) is a run of the same setting."""
    grid = parse_grid({**TINY, "episodes": 3}, "tiny", "tiny.yaml")
    sweep = SweepDir(tmp_path)
    a, b, c, _ = grid.cells()
    fake_run(sweep.run(a), grid, a, 3, model=False)
    (sweep.run(a) / "last_session.json").write_text('{"episodes_done": 3}')
    fake_run(sweep.run(b), grid, b, 2, model=False)                      # cut short: no checkpoint, not complete
    (sweep.run(b) / "last_session.json").write_text('{"episodes_done": 2}')
    libsumo = merge_config(grid.config(c), {"backend": "libsumo", "train": {"backend": "libsumo"}})
    fake_run(sweep.run(c), grid, c, 3)
    write_config(sweep.run(c), libsumo)
    states = plan(tmp_path, grid)
    assert [states[x.name].state for x in (a, b, c)] == [COMPLETE, STALE, COMPLETE]
    assert "without models" in states[a.name].detail
    # so is one saved with hyperparameters the algorithm never reads (DDPG: train.dqn, PPO's rollout length)
    write_config(sweep.run(c), merge_config(libsumo, {"train": {"dqn": {"target_update_steps": 1000},
                                                                "actor_critic": {"ppo_n_steps": 64}}}))
    assert plan(tmp_path, grid)[c.name].state == COMPLETE
    # but a setting that changes what is learned is still another config
    capped = merge_config(grid.config(c), {"scenario": {"agent_max_speed_mps": 25.0}})
    write_config(sweep.run(c), capped)
    with pytest.raises(RunError, match=r"scenario\.agent_max_speed_mps = 25\.0 in the folder vs 30\.0 in the grid"):
        plan(tmp_path, grid)


def test_resume_with_more_seeds_adds_runs_and_keeps_the_rest(tmp_path):
    grid = parse_grid({**{k: v for k, v in TINY.items() if k != "n_seeds"}, "seeds": [0, 2]}, "tiny", "tiny.yaml")
    write_manifest(tmp_path, Manifest(grid))
    for cell in grid.cells():
        fake_run(SweepDir(tmp_path).run(cell), grid, cell, 2)
    more = grid.with_more_seeds(4, "DIR")
    assert more.seeds == (0, 2, 1, 3) and more.settings == grid.settings and more.overrides == grid.overrides
    states = plan(tmp_path, more, extend=True)
    assert sorted(i.state for i in states.values()) == [COMPLETE] * 4 + [PENDING] * 4
    with pytest.raises(UsageError, match="only adds seeds"):
        grid.with_more_seeds(1, "DIR")
    with pytest.raises(UsageError, match="another grid"):
        plan(tmp_path, more)  # without --resume, another seed list is another grid
    for extra, named in ((["--seeds", "1"], "only adds seeds"), (["--episodes", "3"], "--episodes goes with GRID")):
        refused = lanefree("sweep", "--resume", str(tmp_path), *extra)
        assert refused.returncode == 2 and named in refused.stderr and len(refused.stderr.strip().splitlines()) == 1


def test_a_run_trained_by_another_process_is_left_alone(tmp_path):
    grid = parse_grid(TINY, "tiny", "tiny.yaml")
    cell = grid.cells()[0]
    fake_run(SweepDir(tmp_path).run(cell), grid, cell, 1, model=False, checkpoint=1)
    csv_path = SweepDir(tmp_path).run(cell) / "episodes.csv"
    holder = subprocess.Popen([sys.executable, "-c", f"f = open({str(csv_path)!r}, 'a'); print('open', flush=True); "
                               "import time; time.sleep(60)"], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "open"
        info = plan(tmp_path, grid)[cell.name]
        assert info.state == BUSY and str(holder.pid) in info.detail
    finally:
        holder.kill()
        holder.wait()


# -- statistics and summary -----------------------------------------------------------------------

def test_bootstrap_ci():
    assert all(np.isnan(bootstrap_ci([1.0]))) and all(np.isnan(bootstrap_ci([])))
    assert bootstrap_ci([0.5, 0.5, 0.5]) == (0.5, 0.5)
    values = [0.2, 0.4, 0.5, 0.7, 1.1]
    low, high = bootstrap_ci(values)
    assert low < np.mean(values) < high and bootstrap_ci(values) == (low, high)  # reproducible
    assert min(values) <= low and high <= max(values)
    wide = bootstrap_ci([0.0, 2.0, 0.1, 1.9, 1.0])
    assert wide[1] - wide[0] > high - low
    rng = np.random.default_rng(1)
    covered = sum(lo <= 1.0 <= hi for lo, hi in (bootstrap_ci(rng.normal(1.0, 0.5, 10), resamples=2000, seed=k)
                                                  for k in range(200)))
    assert covered >= 170  # ~95 % nominal; percentile bootstrap with n = 10 runs a little under


def _pair_sweep(folder: Path):
    """A sweep of two settings × 3 seeds of 60 episodes, without training: every run complete but the last (30
    episodes), one deterministic evaluation (2 episodes), one unreadable shielded one."""
    grid = parse_grid({"reward_presets": ["fields_collision", "collision"], "n_seeds": 3, "episodes": 60},
                      "pair", "pair.yaml")
    write_manifest(folder, Manifest(grid))
    sweep = SweepDir(folder)
    cells = grid.cells()
    for cell, collisions in zip(cells, [0.4, 1.2, 0.5, 1.3, 0.6, 1.4]):
        fake_run(sweep.run(cell), grid, cell, 60, collisions=collisions)
    shutil.rmtree(sweep.run(cells[-1]))
    fake_run(sweep.run(cells[-1]), grid, cells[-1], 30, model=False, checkpoint=25)  # not complete: left out
    evaluated = RunDir(sweep.run(cells[0])).eval_dir()  # fields_collision seed 0: 2 deterministic episodes
    evaluated.mkdir()
    with open(evaluated / "episodes.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=EPISODE_COLUMNS, extrasaction="ignore", restval="0")
        writer.writeheader()
        writer.writerows({"episode": e, "collisions": c, "speed_dev_mps": 0.75} for e, c in ((1, 0.0), (2, 0.5)))
    shielded = RunDir(sweep.run(cells[1])).eval_dir(shield=True)  # collision seed 0: a broken shielded one
    shielded.mkdir()
    (shielded / "episodes.csv").write_text("episode,return\n1,2\n")
    return grid, sweep, cells


def test_summary_and_status_from_run_folders(tmp_path):
    grid, sweep, cells = _pair_sweep(tmp_path)
    result = summarize(tmp_path)
    table = result.table
    assert tuple(table.columns) == COLUMNS
    fc = table.iloc[0]
    assert (fc["algorithm"], fc["reward_preset"], fc["density"], fc["episodes"], fc["n_runs"]) == \
        ("ddpg", "fields_collision", 70.0, 60, 3)
    assert fc["collisions_mean"] == pytest.approx(0.5) and fc["speed_dev_mps_mean"] == pytest.approx(0.25)
    assert fc["collisions_ci95_low"] == pytest.approx(0.4) and fc["collisions_ci95_high"] == pytest.approx(0.6)
    assert (fc["paper_collisions"], fc["paper_speed_dev_mps"]) == (0.726, 0.698)
    assert table.iloc[1]["n_runs"] == 2 and table.iloc[1]["paper_collisions"] == 2.256
    on_disk = list(csv.DictReader(open(tmp_path / "summary.csv")))
    assert len(on_disk) == 2 and on_disk[0]["collisions_ci95_low"]
    md = (tmp_path / "summary.md").read_text()
    assert "**Reduced budget**" in md and "0.500 [0.400, 0.600] (paper 0.726, 0.7×)" in md
    claims = list(csv.DictReader(open(tmp_path / "claims.csv")))  # the one claim comparing these two settings
    assert [(c["a"], c["b"], c["n_a"], c["n_b"], c["verdict"]) for c in claims] == \
        [("ddpg/collision/70", "ddpg/fields_collision/70", "2", "3", "no data")]
    assert f"runs/{cells[-1].name}" in md and "2/3" in md
    per_run = list(csv.DictReader(open(tmp_path / "runs.csv")))  # every complete run, grouped as the table
    assert tuple(per_run[0]) == RUN_COLUMNS and len(per_run) == 5
    assert [(r["reward_preset"], r["seed"]) for r in per_run] == [
        ("fields_collision", "0"), ("fields_collision", "1"), ("fields_collision", "2"),
        ("collision", "0"), ("collision", "1")]
    first = per_run[0]
    assert (float(first["collisions"]), first["eval_episodes"], float(first["eval_collisions"]),
            float(first["eval_speed_dev_mps"]), first["eval_shield_episodes"]) == \
        (pytest.approx(0.4), "2", 0.25, 0.75, "0")
    assert per_run[3]["eval_shield_episodes"] == "0" and per_run[3]["eval_shield_collisions"] == ""  # unreadable,
    assert f"`runs/{cells[1].name}/eval_shield/` left out of the every-run table: episodes.csv lacks" in md  # said
    runs_table = md[md.index("<!-- runs -->"):md.index("<!-- /runs -->")]
    assert "| ddpg | fields_collision | 70 | 0 | 0.40 | 0.20 | 0 | 0.25 / 0.75 (2) | – |" in runs_table
    assert "| ddpg | collision | 70 | 1 | 1.30 | 0.65 | 0 | – | – |" in runs_table
    assert {p.name for p in (tmp_path / "curves").iterdir()} == {"table5_collisions.png", "table5_return.png",
                                                                 "table5_speed_dev.png"}
    status = status_text(tmp_path)
    assert "5 complete" in status and "1 partial" in status and "REDUCED BUDGET" in status
    assert "episodes: 330/360" in status and "driver: not running" in status


def test_status_says_the_time_left_at_the_pace_of_each_algorithms_latest_runs(tmp_path):
    grid = parse_grid({"algorithms": ["ddpg", "dqn"], "reward_presets": ["collision"], "n_seeds": 5,
                       "episodes": 60}, "pace", "pace.yaml")
    write_manifest(tmp_path, Manifest(grid))
    sweep = SweepDir(tmp_path)
    ddpg = [c for c in grid.cells() if c.setting.algorithm == "ddpg"]
    dqn = [c for c in grid.cells() if c.setting.algorithm == "dqn"]

    def time_line() -> str:
        return next(line for line in status_text(tmp_path).splitlines() if line.startswith("time left"))

    def training(cell: Cell, batch: str | None = None) -> None:  # a live heartbeat (this process's): training now
        sweep.heartbeat(cell.name).parent.mkdir(parents=True, exist_ok=True)
        beat = {"pid": os.getpid(), "host": socket.gethostname(), **({"batch": batch} if batch else {})}
        sweep.heartbeat(cell.name).write_text(json.dumps(beat))

    assert time_line().startswith("time left: unknown until a run completes or has 25 episodes")
    fake_run(sweep.run(ddpg[0]), grid, ddpg[0], 24, model=False, checkpoint=20, wall_s=50.0)
    assert time_line().startswith("time left: unknown until a run completes")  # 24 episodes: too few to tell
    shutil.rmtree(sweep.run(ddpg[0]))
    fake_run(sweep.run(ddpg[0]), grid, ddpg[0], 30, model=False, checkpoint=25, wall_s=48.0)
    # a stopped run's 30 episodes set DDPG's pace; left: 30 + 4 × 60 DDPG and 5 × 60 DQN episodes, 48 s each
    assert time_line().startswith("time left: ≈ 7.6 core-hours for 570 episodes")
    assert "ddpg 48.0; dqn: no run far enough yet, 48.0 assumed" in time_line()
    shutil.rmtree(sweep.run(ddpg[0]))
    fake_run(sweep.run(ddpg[0]), grid, ddpg[0], 60, wall_s=400.0)  # no sessions.jsonl: the oldest
    fake_run(sweep.run(ddpg[1]), grid, ddpg[1], 60, wall_s=100.0, ended="2026-11-24T10:00:00+00:00")
    fake_run(sweep.run(ddpg[2]), grid, ddpg[2], 60, wall_s=140.0, ended="2026-11-25T09:00:00+00:00")
    fake_run(sweep.run(ddpg[3]), grid, ddpg[3], 30, model=False, checkpoint=25, wall_s=120.0)  # stopped long ago
    # the 3 latest: 140 and 100 by their sessions' ends, then the stopped run without one (sorted by name after
    # the complete one without one); the oldest complete run's 400 left out. Left: 30 + 60 DDPG and 300 DQN
    # episodes (DQN has no run: DDPG's pace assumed), 120 s each
    assert time_line().startswith("time left: ≈ 13.0 core-hours for 390 episodes")
    assert "median of its 3 latest runs' latest sessions: ddpg 120.0; dqn: no run far enough yet, 120.0 " \
        "assumed" in time_line()
    training(ddpg[3])  # training now: the latest of all
    assert "ddpg 120.0 (with runs training now)" in time_line()
    fake_run(sweep.run(ddpg[4]), grid, ddpg[4], 60, wall_s=10.0, ended="2026-11-25T10:00:00+00:00")
    assert "ddpg 120.0 (with runs training now)" in time_line()  # 120 training, then 10 and 140 by their ends
    shutil.rmtree(sweep.run(ddpg[4]))
    (sweep.run(ddpg[1]) / "sessions.jsonl").write_text("not json\n")  # unreadable: counts as the oldest too
    assert "ddpg 120.0" in time_line()  # 120 training, 140, then 100 (ddpg[1] sorts after ddpg[0]: 400 left out)
    # a run resumed on another machine: its last session (episodes 31-60) sets its pace, not its 60 episodes
    shutil.rmtree(sweep.run(ddpg[2]))
    fake_run(sweep.run(ddpg[2]), grid, ddpg[2], 60, wall_s=140.0)
    walls_from(sweep.run(ddpg[2]), 31, 110.0)
    record_session(sweep.run(ddpg[2]), {"episodes_done": 60, "first_episode": 31, "ended": "2026-11-25T09:00:00"})
    assert "ddpg 110.0 (with runs training now)" in time_line()  # 120 training, 110, 100 (all its episodes: 125)
    fake_run(sweep.run(dqn[0]), grid, dqn[0], 60, wall_s=40.0)
    # left: 30 + 60 DDPG episodes at 110 s, 240 DQN ones at 40 s
    assert time_line().startswith("time left: ≈ 5.4 core-hours for 330 episodes")
    assert "ddpg 110.0 (with runs training now), dqn 40.0)" in time_line()
    fake_run(sweep.run(ddpg[4]), grid, ddpg[4], 30, model=False, checkpoint=25, wall_s=120.0)
    training(ddpg[4])  # two runs training at once, each in a process of its own: 120 s each
    assert "ddpg 120.0 (with runs training now)" in time_line()
    # ddpg[3] and ddpg[4] train as one batch (its batch.json, named by their heartbeats): each has half of 120 s
    sweep.batch("batch_ddpg_k2_0").mkdir(parents=True)
    (sweep.batch("batch_ddpg_k2_0") / "batch.json").write_text(json.dumps(
        {"runs": [f"../../runs/{cell.name}" for cell in (ddpg[3], ddpg[4])]}))
    for cell in (ddpg[3], ddpg[4]):
        training(cell, "batch_ddpg_k2_0")
    # the 3 latest: 60 and 60 training, then 110; left: 30 + 30 DDPG episodes at 60 s, 240 DQN ones at 40 s
    assert time_line().startswith("time left: ≈ 3.7 core-hours for 300 episodes")
    assert "ddpg 60.0 (with runs training now), dqn 40.0)" in time_line()
    training(ddpg[4], "batch_gone")  # a batch without batch.json: alone
    assert "ddpg 110.0 (with runs training now)" in time_line()  # 60 (ddpg[3], its batch of 2), 120, 110
    for cell in [*dqn[1:], ddpg[3], ddpg[4]]:
        shutil.rmtree(sweep.run(cell), ignore_errors=True)
        fake_run(sweep.run(cell), grid, cell, 60, wall_s=1.0)
    assert "time left: none, every run is complete" in status_text(tmp_path)


def test_a_runs_pace_is_its_latest_sessions(tmp_path):
    grid = parse_grid({"reward_presets": ["collision"], "n_seeds": 1, "episodes": 100}, "pace", "pace.yaml")
    cell, run = grid.cells()[0], tmp_path / "run"
    fake_run(run, grid, cell, 80, wall_s=50.0)
    assert _pace_sample(run) == (None, [50.0] * 80)  # no sessions.jsonl: every episode
    with open(run / "episodes.csv", "a") as fh:  # a damaged row's wall time is left out
        fh.write("81," + ",".join(["x"] * (len(EPISODE_COLUMNS) - 1)) + "\n")
    assert _pace_sample(run) == (None, [])  # an unreadable column: no sample
    shutil.rmtree(run)
    fake_run(run, grid, cell, 80, wall_s=50.0)
    walls_from(run, 51, 20.0)
    record_session(run, {"episodes_done": 40, "first_episode": 1, "ended": "2026-11-24T10:00:00+00:00"})
    record_session(run, {"episodes_done": 80, "first_episode": 41, "ended": "2026-11-25T10:00:00+00:00"})
    assert _pace_sample(run) == ("2026-11-25T10:00:00+00:00", [50.0] * 10 + [20.0] * 30)
    with open(run / "sessions.jsonl", "a") as fh:
        fh.write('{"episodes_done": 90, "first_')  # a half-written last line: the one before stands
    assert _pace_sample(run)[0] == "2026-11-25T10:00:00+00:00"
    record_session(run, {"episodes_done": 50, "first_episode": 41, "ended": "2026-11-25T11:00:00+00:00"})
    # training now: the episodes after the last recorded session (51-80), all at 20 s
    assert _pace_sample(run, together=1) == ("2026-11-25T11:00:00+00:00", [20.0] * 30)
    assert _pace_sample(run, together=4)[1] == [5.0] * 30  # batched with 3 other runs on one core: a quarter each
    record_session(run, {"episodes_done": 80, "first_episode": 51, "ended": "2026-11-25T12:00:00+00:00",
                         "batch": {"folder": "../../batches/b", "run": 2, "runs": 5}})
    assert _pace_sample(run)[1] == [4.0] * 30  # a session of a batch of 5: its episodes' wall time shared by 5
    for runs in (0, -2, "5", None, [5], 2.5, True, float("inf")):  # not a whole number >= 1: as if alone
        record_session(run, {"episodes_done": 80, "first_episode": 51, "batch": {"runs": runs}})
        assert _pace_sample(run)[1] == [20.0] * 30, runs
    record_session(run, {"episodes_done": 60, "first_episode": 51, "ended": "2026-11-25T12:00:00+00:00"})
    assert _pace_sample(run, together=1)[1] == [50.0] * 50 + [20.0] * 30  # 20 episodes since: too few, all
    (run / "sessions.jsonl").write_text('["not", "a", "session"]\n{"episodes_done": "many"}\n')
    assert _pace_sample(run, together=1) == (None, [50.0] * 50 + [20.0] * 30)


def test_a_setting_in_several_tables_is_drawn_once(tmp_path):
    grid = parse_grid({"reward_presets": ["fields_zones_overtake_collision"], "n_seeds": 1, "episodes": 60},
                      "row", "row.yaml")  # DDPG / fzoc / 70 is a row of Tables 6, 7 and 8
    write_manifest(tmp_path, Manifest(grid))
    fake_run(SweepDir(tmp_path).run(grid.cells()[0]), grid, grid.cells()[0], 60)
    for stale in ("claims.csv", "claims.md"):  # as an earlier version wrote them for every grid
        (tmp_path / stale).write_text("claim\n")
    result = summarize(tmp_path)
    assert sorted(p.name for p in (tmp_path / "curves").iterdir()) == \
        ["table6_collisions.png", "table6_return.png", "table6_speed_dev.png"]
    assert [p.name for p in result.files[3:]] == ["summary.csv", "runs.csv", "summary.md"]  # no claim: one setting
    assert not (tmp_path / "claims.csv").exists() and not (tmp_path / "claims.md").exists()
    md = (tmp_path / "summary.md").read_text()
    assert "- Table 6, Table 7, Table 8: [return](curves/table6_return.png)" in md
    assert fenced_rows(md)[2].startswith("| ddpg | fields_zones_overtake_collision | 70 | 60 | 1/1 |")


def test_lanefree_report_of_a_sweep_folder_writes_its_summary(tmp_path):
    grid = parse_grid({"reward_presets": ["collision"], "n_seeds": 2, "episodes": 60}, "one", "one.yaml")
    write_manifest(tmp_path, Manifest(grid))
    for cell, collisions, model in zip(grid.cells(), [0.8, 1.6], [True, False]):  # a copy without its model counts
        fake_run(SweepDir(tmp_path).run(cell), grid, cell, 60, collisions=collisions, model=model)
    done = lanefree("report", str(tmp_path))
    assert done.returncode == 0, done.stderr
    table = list(csv.DictReader(open(tmp_path / "summary.csv")))
    assert [(r["reward_preset"], r["n_runs"]) for r in table] == [("collision", "2")]
    assert float(table[0]["collisions_mean"]) == pytest.approx(1.2)
    assert "1.200 [0.800, 1.600]" in done.stdout and not (tmp_path / "runs" / "report").exists()
    for extra in (["--out", str(tmp_path / "elsewhere")], [str(SweepDir(tmp_path).run(grid.cells()[0]))]):
        refused = lanefree("report", str(tmp_path), *extra)
        assert refused.returncode == 2 and len(refused.stderr.strip().splitlines()) == 1, refused.stderr
        assert "sweep folder" in refused.stderr


def _study_sweep(folder: Path, preset: str, variants: dict, collisions: dict[str, float]) -> None:
    """A sweep folder of one cell (ddpg / ``preset`` / 70 veh/km), 4 seeds per variant, its runs faked with
    each variant's collisions per episode."""
    grid = parse_grid({"reward_presets": [preset], "n_seeds": 4, "episodes": 3, "variants": variants},
                      folder.name, f"{folder.name}.yaml")
    write_manifest(folder, Manifest(grid))
    for cell in grid.cells():
        fake_run(SweepDir(folder).run(cell), grid, cell, 3, collisions=collisions[cell.setting.variant])


def test_lanefree_report_of_several_sweeps_puts_each_choice_in_every_cell_on_one_page(tmp_path):
    """``lanefree report A B --out DIR``: each sweep's summary written into it, and DIR/effects.md with one row per
    choice — its verdict in each cell (– where it was not run) and its strongest over the cells — then each
    cell's figures; mixing a run folder in, two sweeps of one cell and sweeps without variants are refused."""
    a, b = tmp_path / "a", tmp_path / "b"
    _study_sweep(a, "collision", {"default": {}, "cap25": {"scenario.agent_max_speed_mps": 25}},
                 {"default": 5.0, "cap25": 1.0})
    _study_sweep(b, "fields_collision", {"default": {}, "cap25": {"scenario.agent_max_speed_mps": 25},
                                         "keras": {"train.profile": "kerasrl"}},
                 {"default": 2.0, "cap25": 2.0, "keras": 2.0})
    done = lanefree("report", str(a), str(b), "--out", str(tmp_path / "study"))
    assert done.returncode == 0, done.stderr
    assert (a / "summary.md").is_file() and (b / "effects.md").is_file()
    page = (tmp_path / "study" / "effects.md").read_text()
    lines = page.splitlines()
    inside = lines[lines.index("<!-- effects-overview -->") + 1:lines.index("<!-- /effects-overview -->")]
    assert [[c.strip() for c in line.strip("|").split("|")] for line in inside if line and "---" not in line] == [
        ["choice", "verdict (strongest over the cells)", "ddpg / collision / 70 veh/km",
         "ddpg / fields_collision / 70 veh/km"],
        ["cap25", "moves the numbers", "moves the numbers (racing 0% → 0%; runs 4, 4)",
         "no effect detected (racing 0% → 0%; runs 4, 4)"],
        ["keras", "no effect detected", "–", "no effect detected (racing 0% → 0%; runs 4, 4)"]]
    assert "## ddpg / collision / 70 veh/km" in page and "## ddpg / fields_collision / 70 veh/km" in page
    assert "-4.00 [-4.00, -4.00] (p 0.029)" in page  # cap25's collisions in the first cell: 1 − 5, 4 runs a side
    rows = list(csv.DictReader(open(tmp_path / "study" / "effects.csv")))
    assert {(r["reward_preset"], r["variant"]) for r in rows} == \
        {("collision", "cap25"), ("fields_collision", "cap25"), ("fields_collision", "keras")}
    assert page in done.stdout
    run = next((a / "runs").iterdir())
    again = tmp_path / "again"
    _study_sweep(again, "collision", {"default": {}, "lateral": {"scenario.agent_lateral_speed_ratio": 0.5}},
                 {"default": 5.0, "lateral": 5.0})
    plain = tmp_path / "plain"
    plain_grid = parse_grid({"reward_presets": ["collision"], "n_seeds": 1, "episodes": 3}, "plain", "plain.yaml")
    write_manifest(plain, Manifest(plain_grid))
    for args, words in (([str(a), str(run)], "report sweep folders alone or together"),
                        ([str(a), str(again)], "both have the cell ddpg / collision / 70 veh/km"),
                        ([str(plain), str(plain)], "none of these sweeps has variants"),
                        ([str(a), str(b), "--eval"], "drop --eval"),
                        ([str(a), "--compare"], "a sweep writes its own verdict.md")):
        refused = lanefree("report", *args, "--out", str(tmp_path / "refused"))
        assert refused.returncode != 0 and len(refused.stderr.strip().splitlines()) == 1, refused.stderr
        assert words in refused.stderr, refused.stderr


# -- real sweeps on Ray (slow) --------------------------------------------------------------------

def run_logs_nodes(out: Path) -> set[str]:
    return {m for log in (out / "logs").glob("*.log") for m in re.findall(r" node (\w+)", log.read_text())}


def assert_complete(out: Path, grid_episodes: int, runs: int) -> None:
    folders = sorted((out / "runs").iterdir())
    assert len(folders) == runs
    for folder in folders:
        assert episodes_of(folder / "episodes.csv") == list(range(1, grid_episodes + 1)), folder
        assert (folder / "model.zip").is_file() and (folder / "config.yaml").is_file()


@pytest.mark.slow
@pytest.mark.sumo
def test_tiny_grid_on_the_embedded_ray_then_a_rerun_trains_nothing(tmp_path):
    grid, out = write_grid(tmp_path / "tiny.yaml", TINY), tmp_path / "sweep"
    done = lanefree("sweep", str(grid), "--out", str(out), "--workers", "2", timeout=600)
    assert done.returncode == 0, done.stderr
    assert "4/4 runs complete" in done.stdout and "REDUCED BUDGET" in done.stdout
    assert_complete(out, 2, 4)
    table = list(csv.DictReader(open(out / "summary.csv")))
    assert [(r["reward_preset"], r["n_runs"], r["episodes"]) for r in table] == \
        [("collision", "2", "2"), ("fields_collision", "2", "2")]
    assert (out / "curves" / "table5_collisions.png").is_file()
    assert "Reduced budget" in (out / "summary.md").read_text()
    before = {p: p.stat().st_mtime_ns for p in (out / "runs").rglob("*") if p.is_file()}
    again = lanefree("sweep", str(grid), "--out", str(out), timeout=120)
    assert again.returncode == 0, again.stderr
    assert "4 complete" in again.stdout and "nothing to train" in again.stdout
    assert {p: p.stat().st_mtime_ns for p in (out / "runs").rglob("*") if p.is_file()} == before
    assert len(read_manifest(out).sessions) == 2
    # more seeds for the same sweep: only the new seed's runs train, the summary has 3 runs per setting
    more = lanefree("sweep", "--resume", str(out), "--seeds", "3", "--workers", "2", timeout=600)
    assert more.returncode == 0, more.stderr
    assert "4 complete, 0 to resume, 2 to start" in more.stdout and "6/6 runs complete" in more.stdout
    assert {p: p.stat().st_mtime_ns for p in before} == before
    assert_complete(out, 2, 6)
    assert read_manifest(out).grid.seeds == (0, 1, 2)
    assert [r["n_runs"] for r in csv.DictReader(open(out / "summary.csv"))] == ["3", "3"]


@pytest.mark.slow
@pytest.mark.sumo
def test_a_killed_worker_is_retried_and_ctrl_c_then_resume_finish_every_run_exactly(tmp_path):
    """A worker SIGKILLed after its first checkpoint: Ray retries the task, which resumes from the
    checkpoint. Then Ctrl-C on the driver stops the run with a checkpoint (exit 130), and --resume
    finishes it. The CSV holds episodes 1 … N exactly once."""
    # a budget far longer than the few episodes the test waits for, so the Ctrl-C always lands mid-run,
    # however fast the machine (the run can never finish before the driver is interrupted); no gradient
    # steps (learning starts after the budget): what is checked is the run folder's bookkeeping, and
    # resuming a learner's state is test_train's (this keeps the 300 episodes cheap)
    episodes, every = 300, 5
    grid = write_grid(tmp_path / "kill.yaml", {
        "reward_presets": ["fields_zones_overtake_collision"], "seeds": [0], "episodes": episodes,
        "overrides": {"sim": {"episode_steps": 25},
                      "train": {"checkpoint_every_episodes": every, "actor_critic": {"learning_starts_steps": 10**6}}}})
    out = tmp_path / "sweep"
    sweep = SweepDir(out)
    name = "ddpg_fields_zones_overtake_collision_d70_s0"
    ckpts = sweep.run(name) / "checkpoints"
    proc = lanefree_popen("sweep", str(grid), "--out", str(out), "--workers", "1", "--no-progress")
    try:
        deadline = time.time() + 300
        while not (ckpts / f"ep_{every:05d}" / "state.json").exists():
            assert time.time() < deadline and proc.poll() is None, "no first checkpoint"
            time.sleep(0.05)
        victim = json.loads(sweep.heartbeat(name).read_text())["pid"]
        os.kill(victim, signal.SIGKILL)
        # resumed: the retry's command line is on file (it loaded the checkpoint, truncated the victim's later
        # rows and handles SIGINT from then on) and it wrote 2 episodes of its own
        command = sweep.run(name) / "command.txt"
        while not (len(command.read_text().splitlines()) == 2
                   and len(episodes_of(sweep.run(name) / "episodes.csv")) >= every + 2):
            assert time.time() < deadline and proc.poll() is None, "the killed run was not resumed"
            time.sleep(0.05)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=240)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    assert "--resume" in err and "Traceback" not in err
    stopped = episodes_of(sweep.run(name) / "episodes.csv")
    assert every + 2 <= len(stopped) < episodes and stopped == list(range(1, len(stopped) + 1))
    assert json.loads((sweep.run(name) / "last_session.json").read_text())["stopped_by"] == "SIGINT"
    log = sweep.log(name).read_text()
    assert log.count(f"run {name} on host") == 2 and "resumable from episode" in log

    resumed = lanefree("sweep", "--resume", str(out), "--no-ray", "--no-progress", timeout=600)  # in the driver
    assert resumed.returncode == 0, resumed.stderr
    assert_complete(out, episodes, 1)
    assert len((sweep.run(name) / "command.txt").read_text().splitlines()) == 3


# -- a two-node Ray cluster on 127.0.0.1 ----------------------------------------------------------

RAY_START = ("import sys; import ray._private.services as s; s.resolve_ip_for_localhost = lambda host: host; "
             "from ray.scripts.scripts import main; sys.exit(main())")
"""``ray start ARGS`` exactly, except that Ray keeps 127.0.0.1 in --address and --node-ip-address as
it is: by default it swaps the loopback address for the host's outward one (and refuses a worker
node when told to stay on loopback), which would take the cluster off 127.0.0.1."""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def descendants(pids: set[int]) -> set[int]:
    found, parents = set(pids), {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
            parents[int(stat.parent.name)] = int(fields[1])
        except (OSError, IndexError, ValueError):
            continue
    changed = True
    while changed:
        new = {pid for pid, ppid in parents.items() if ppid in found} - found
        found |= new
        changed = bool(new)
    return found


def listening_addresses(pids: set[int]) -> set[str]:
    """Local addresses of the TCP sockets that processes ``pids`` listen on (from /proc/net)."""
    inodes = set()
    for pid in pids:
        for fd in Path(f"/proc/{pid}/fd").glob("*"):
            try:
                target = os.readlink(fd)
            except OSError:
                continue
            if target.startswith("socket:["):
                inodes.add(target[8:-1])
    found = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            parts = line.split()
            if parts[3] == "0A" and parts[9] in inodes:  # LISTEN
                hexaddr = parts[1].split(":")[0]
                raw = bytes.fromhex(hexaddr)
                words = b"".join(raw[i:i + 4][::-1] for i in range(0, len(raw), 4))  # /proc stores host order
                found.add(str(ipaddress.ip_address(words)))
    return found


def is_loopback(address: str) -> bool:
    ip = ipaddress.ip_address(address)
    mapped = getattr(ip, "ipv4_mapped", None)
    return (mapped or ip).is_loopback


@pytest.fixture
def ray_cluster() -> Iterator[tuple[str, dict[str, str]]]:
    """A head and a worker node (1 CPU each) on 127.0.0.1, own ports and temp dirs; yields the
    address and the environment to reach it; stops both by process id."""
    temp = Path(tempfile.mkdtemp(prefix="lfr-", dir="/tmp"))  # short: Ray's socket paths must fit 107 chars
    env = {**CLI_ENV, "RAY_USAGE_STATS_ENABLED": "0", "RAY_AUTH_MODE": "token",
           "RAY_AUTH_TOKEN": secrets.token_hex(16)}
    env.pop("RAY_ADDRESS", None)
    port = free_port()
    address = f"127.0.0.1:{port}"
    common = ["--block", "--node-ip-address", "127.0.0.1", "--num-cpus", "1", "--disable-usage-stats"]
    nodes: list[subprocess.Popen] = []
    try:
        nodes.append(subprocess.Popen(
            [sys.executable, "-c", RAY_START, "start", "--head", "--port", str(port), "--temp-dir", str(temp / "h"),
             "--include-dashboard", "false", *common], env=env, stdout=open(temp / "head.log", "w"),
            stderr=subprocess.STDOUT))
        wait_for_nodes(address, env, 1, nodes)
        nodes.append(subprocess.Popen(
            [sys.executable, "-c", RAY_START, "start", "--address", address, "--temp-dir", str(temp / "w"), *common],
            env=env, stdout=open(temp / "worker.log", "w"), stderr=subprocess.STDOUT))
        wait_for_nodes(address, env, 2, nodes)
        outside = {a for a in listening_addresses(descendants({p.pid for p in nodes})) if not is_loopback(a)}
        assert not outside, f"Ray listens on {outside}"
        yield address, env
    finally:
        for node in reversed(nodes):
            node.terminate()  # `ray start --block` stops its node's processes on SIGTERM
        for node in reversed(nodes):
            try:
                node.wait(timeout=60)
            except subprocess.TimeoutExpired:
                node.kill()
        for pid in [int(p.name) for p in Path("/proc").glob("[0-9]*")]:  # anything of ours still alive
            if str(temp) in _cmdline(pid):
                with contextlib.suppress(OSError):
                    os.kill(pid, signal.SIGKILL)
        shutil.rmtree(temp, ignore_errors=True)


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def wait_for_nodes(address: str, env: dict[str, str], count: int, nodes: list[subprocess.Popen]) -> None:
    probe = ("import ray, sys, time; ray.init(address=sys.argv[1], log_to_driver=False, logging_level='ERROR')\n"
             "while sum(n['Alive'] for n in ray.nodes()) < int(sys.argv[2]): time.sleep(0.5)")
    wait = subprocess.run([sys.executable, "-c", probe, address, str(count)], timeout=180, capture_output=True,
                          text=True, env={**env, "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0"})
    assert wait.returncode == 0 and all(n.poll() is None for n in nodes), wait.stderr[-2000:]


@pytest.mark.slow
@pytest.mark.sumo
def test_tiny_grid_on_a_two_node_ray_cluster(tmp_path, ray_cluster):
    address, env = ray_cluster
    grid, out = write_grid(tmp_path / "tiny.yaml", {**TINY, "episodes": 1}), tmp_path / "sweep"
    done = subprocess.run([sys.executable, "-m", "lanefree_sumo.cli", "sweep", str(grid), "--out", str(out),
                           "--address", address, "--no-progress"], capture_output=True, text=True, env=env,
                          timeout=600)
    assert done.returncode == 0, done.stderr
    assert f"Ray cluster at {address}" in done.stdout and "4/4 runs complete" in done.stdout
    assert_complete(out, 1, 4)
    assert len(run_logs_nodes(out)) == 2  # both nodes trained runs
    assert read_manifest(out).sessions[0]["ray"] == f"Ray cluster at {address}"


def test_set_adds_to_the_grids_overrides_and_cannot_set_what_the_grid_sets(tmp_path):
    grid = parse_grid(TINY, "tiny", "tiny.yaml").with_budget(settings={"reward": {"broad_stretch": "absolute"},
                                                                      "train": {"checkpoint_every_episodes": 2}})
    cfg = grid.config(grid.cells()[0])
    assert cfg.reward.broad_stretch == "absolute" and cfg.train.checkpoint_every_episodes == 2
    assert cfg.sim.episode_steps == 40  # the grid's own overrides stay
    with pytest.raises(ConfigError, match="train.episodes"):
        parse_grid(TINY, "tiny", "tiny.yaml").with_budget(settings={"train": {"episodes": 3}})
    res = lanefree("sweep", str(write_grid(tmp_path / "g.yaml", TINY)), "--out", str(tmp_path / "s"),
                   "--set", "reward.nope=1")
    assert res.returncode == 2 and "reward.nope" in res.stderr and not (tmp_path / "s").exists()


@pytest.mark.slow
def test_a_sweep_on_the_on_ramp(tmp_path):
    """Grids take the road too: a run of the on-ramp's merge task through the sweep, complete, with the
    merge metrics in its episodes.csv."""
    grid = write_grid(tmp_path / "onramp.yaml", {
        "reward_presets": ["fields_zones_overtake_collision"], "densities": [20], "seeds": [0], "episodes": 2,
        "overrides": {"road": {"kind": "onramp"}, "sim": {"episode_steps": 60},
                      "train": {"actor_critic": {"learning_starts_steps": 30}}}})
    out = tmp_path / "sweep"
    res = lanefree("sweep", str(grid), "--out", str(out), "--no-ray", "--no-progress")
    assert res.returncode == 0, res.stderr
    run = out / "runs" / "ddpg_fields_zones_overtake_collision_d20_s0"
    assert (run / "model.zip").is_file() and "merged" in (run / "episodes.csv").read_text().splitlines()[0]


def test_variants_are_settings_of_their_own_with_their_own_runs_and_rows(tmp_path):
    """A grid's variants: each setting once per variant (dotted keys applied after the overrides), run folders
    named after the variant, the summary grouped by variant with both speed readings, claims on ``default``."""
    data = {"reward_presets": ["fields_collision", "collision"], "n_seeds": 2, "episodes": 3,
            "overrides": {"reward": {"overtake_reward": 3.0}},
            "variants": {"default": {}, "cap25": {"scenario.agent_max_speed_mps": 25,
                                                  "reward.overtake_bonus": "once_per_vehicle"},
                         "keras": {"train.profile": "kerasrl"}}}
    grid = parse_grid(data, "study", "study.yaml")
    assert [s.label for s in grid.settings][:3] == ["ddpg / fields_collision / d70 / default",
                                                    "ddpg / collision / d70 / default",
                                                    "ddpg / fields_collision / d70 / cap25"]
    assert len(grid.cells()) == 3 * 2 * 2
    cap = next(c for c in grid.cells() if c.setting.variant == "cap25")
    assert cap.name == "ddpg_fields_collision_d70_cap25_s0"
    cfg = grid.config(cap)
    assert (cfg.scenario.agent_max_speed_mps, cfg.reward.overtake_bonus, cfg.reward.overtake_reward) == \
        (25.0, "once_per_vehicle", 3.0)
    keras = grid.config(next(c for c in grid.cells() if c.setting.variant == "keras"))
    assert keras.train.actor_critic.warmup_actions == "policy" and keras.train.dqn.loss == "squared"
    assert grid.config(grid.cells()[0]).scenario.agent_max_speed_mps == 30.0
    assert Grid.from_dict(grid.to_dict(), "manifest") == grid  # the manifest keeps the variants
    write_manifest(tmp_path, Manifest(grid))
    sweep = SweepDir(tmp_path)
    for k, cell in enumerate(grid.cells()):
        fake_run(sweep.run(cell), grid, cell, 3, collisions=float(k))
    table = summarize(tmp_path).table
    assert list(table["variant"]) == ["default", "default", "cap25", "cap25", "keras", "keras"]
    # cells are seed-major: seed 0 of the 6 settings (k = 0..5), then seed 1 (k = 6..11)
    assert list(table["collisions_mean"]) == [3.0, 4.0, 5.0, 6.0, 7.0, 8.0]
    assert list(table["speed_error_mps_mean"]) == [0.0] * 6  # as the fake runs recorded them
    # a run recorded before the per-episode readings existed: derived from its mean speed (v_d = 20 m/s)
    old = sweep.run(grid.cells()[0]) / "episodes.csv"
    old.write_text("episode,return,collisions,speed_dev_mps,overtakes,mean_speed_mps\n"
                   "1,1,0,3,0,23.5\n2,1,0,3,0,17.0\n3,1,0,3,0,20.0\n")
    table = summarize(tmp_path).table
    derived = (3.5 - 3.0 + 0.0) / 3  # episode means: +3.5, −3.0, 0.0 m/s
    assert table["speed_error_mps_mean"][0] == pytest.approx(derived / 2)  # with seed 1's 0.0
    assert table["speed_dev_episode_mps_mean"][0] == pytest.approx((3.5 + 3.0 + 0.0) / 3 / 2)
    per_run = list(csv.DictReader(open(tmp_path / "runs.csv")))
    assert [r["variant"] for r in per_run[:2]] == ["default", "default"] and per_run[4]["variant"] == "cap25"
    md = (tmp_path / "summary.md").read_text()
    assert "| variant |" in md and "| cap25 |" in md and "per episode" in md
    claims = list(csv.DictReader(open(tmp_path / "claims.csv")))  # on the default variant's runs only
    assert [(c["n_a"], c["n_b"]) for c in claims] == [("2", "2")]
    effects = (tmp_path / "effects.md").read_text()  # each variant against default, per cell: 2 runs a side
    assert "| cap25 | 2, 2 | too few runs |" in effects and "| keras | 2, 2 | too few runs |" in effects
    assert {r["variant"] for r in csv.DictReader(open(tmp_path / "effects.csv"))} == {"cap25", "keras"}


def test_summary_of_the_first_seeds_of_an_extended_sweep(tmp_path, capsys):
    """``--summary DIR --seeds N``: a sweep extended to more seeds keeps the tables of its seeds 0 … N−1 (the
    later seeds' runs are left out, the budget reads N seeds); N above the sweep's seeds is a one-line error;
    ``complete_seeds`` counts the first seeds complete in every setting."""
    grid = parse_grid({"reward_presets": ["collision", "fields_collision"], "n_seeds": 4, "episodes": 3},
                      "grid", "grid.yaml")
    write_manifest(tmp_path, Manifest(grid))
    sweep = SweepDir(tmp_path)
    for cell in grid.cells():
        fake_run(sweep.run(cell), grid, cell, 3, collisions=float(cell.seed))
    assert list(summarize(tmp_path).table["collisions_mean"]) == [1.5, 1.5]  # seeds 0–3
    assert main(["sweep", "--summary", str(tmp_path), "--seeds", "2"]) == 0
    table = list(csv.DictReader(open(tmp_path / "summary.csv")))
    assert [(r["n_runs"], float(r["collisions_mean"])) for r in table] == [("2", 0.5), ("2", 0.5)]
    assert "2 seed(s) per setting instead of the paper's 10" in (tmp_path / "summary.md").read_text()
    assert len(list(csv.DictReader(open(tmp_path / "runs.csv")))) == 4
    assert read_manifest(tmp_path).grid.seeds == (0, 1, 2, 3)  # the sweep itself is unchanged
    assert complete_seeds(tmp_path) == 4
    shutil.rmtree(sweep.run(grid.cells()[5]))  # seed 2 of the second setting not trained yet
    assert complete_seeds(tmp_path) == 2
    second = grid.cells()[1]  # seed 0 of the second setting, as a copy of the results holds it: no model.zip
    shutil.rmtree(sweep.run(second))
    fake_run(sweep.run(second), grid, second, 3, model=False)
    assert complete_seeds(tmp_path) == 2  # every episode on file counts
    shutil.rmtree(sweep.run(grid.cells()[2]))  # seed 1 of the first setting
    assert complete_seeds(tmp_path) == 1
    shutil.rmtree(sweep.run(grid.cells()[0]))
    fake_run(sweep.run(grid.cells()[0]), grid, grid.cells()[0], 2, model=False)  # seed 0 stopped at episode 2
    assert complete_seeds(tmp_path) == 0
    capsys.readouterr()
    assert main(["sweep", "--summary", str(tmp_path), "--seeds", "5"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "--seeds 5 asks for seeds 0 … 4 (give N ≤ 4)" in err


def test_a_grid_that_compares_a_variant_writes_its_verdict_over_every_source(tmp_path):
    """``compare``: verdict.md sets the variant against ``default`` per setting, over the training windows and each
    evaluation some run has; a summary of a grid without ``compare`` writes none (and removes an old one)."""
    data = {"reward_presets": ["collision"], "n_seeds": 3, "episodes": 3,
            "variants": {"default": {}, "cap": {"scenario.agent_max_speed_mps": 25}}, "compare": ["cap"]}
    grid = parse_grid(data, "study", "study.yaml")
    write_manifest(tmp_path, Manifest(grid))
    sweep = SweepDir(tmp_path)
    for cell in grid.cells():
        fake_run(sweep.run(cell), grid, cell, 3, collisions=10.0 * (cell.setting.variant == "cap") + cell.seed)
    evaluation = sweep.run(grid.cells()[0]) / "eval"
    evaluation.mkdir()
    shutil.copy2(sweep.run(grid.cells()[0]) / "episodes.csv", evaluation / "episodes.csv")
    summarize(tmp_path)
    table = {tuple(cells[:3]): cells[3:] for line in fenced_rows((tmp_path / "verdict.md").read_text())[2:]
             for cells in [[c.strip() for c in line.strip("|").split("|")]]}
    label = "ddpg / collision / d70"
    collisions = table[(label, "training, last 50 episodes", "collisions / episode")]
    # every cap run above every default run: the CI excludes 0, but 3 against 3 cannot reach p = 0.05 (two-sided
    # 0.10), so by the claims' one rule the verdict is undecided
    assert collisions[:3] == ["3, 3", "11.00", "1.00"] and collisions[-1] == "undecided"
    assert collisions[-2] == f"9/9, p = {2 / 20:.2f}"
    assert table[(label, "training, all 3 episodes", "return")][-1] == "no difference detected"
    assert table[(label, "deterministic, 70 veh/km", "return")][0] == "0, 1"  # one default run has eval/
    assert table[(label, "deterministic, 70 veh/km", "return")][-1] == "too few runs (< 3 a side)"
    assert not any("90 veh/km" in key[1] for key in table)  # no run has that evaluation
    write_manifest(tmp_path, Manifest(parse_grid({**data, "compare": None}, "study", "study.yaml")))
    summarize(tmp_path)
    assert not (tmp_path / "verdict.md").exists()


@pytest.mark.parametrize(("variants", "named"), [
    ({"Cap": {}}, "variant name 'Cap'"),
    ({"cap": {"scenario.agent_max_speed_mps": -1}}, "variants.cap"),
    ({"cap": {"seed": 3}}, "variants.cap.seed is set by the grid itself"),
    ({"cap": {"reward.nonsense": 1}}, "unknown config key 'reward.nonsense'"),
    ({"cap": ["scenario.agent_max_speed_mps"]}, "variants.cap must be a mapping"),
    ([], "variants must be a mapping"),
])
def test_bad_variants_are_one_line_errors_naming_the_variant(variants, named):
    with pytest.raises(ConfigError, match=re.escape(named)):
        parse_grid({"reward_presets": ["collision"], "variants": variants}, "bad", "bad.yaml")


def test_an_on_ramp_sweep_and_report_are_not_compared_with_the_papers_ring():
    """The paper's values and claims are the ring's: an on-ramp grid's summary has neither, a ring grid's both;
    the report's table of on-ramp runs has no paper column values either."""
    import pandas as pd

    from lanefree_sumo.experiments.analysis.report import RunData, summary_table
    from lanefree_sumo.experiments.sweep.summary import _rows, paper_comparisons

    settings = {"reward_presets": ["fields_overtake_collision", "fields_zones_overtake_collision"],
                "densities": [90], "n_seeds": 1, "episodes": 2}
    ring = parse_grid(settings, "ring", "ring.yaml")
    onramp = parse_grid({**settings, "overrides": {"road": {"kind": "onramp"}}}, "onramp", "onramp.yaml")
    assert (ring.road(ring.settings[0]), onramp.road(onramp.settings[0])) == ("ring", "onramp")
    assert paper_comparisons(ring) and paper_comparisons(onramp) == ()
    assert _rows(ring, {}, 50)["paper_collisions"].notna().all()
    assert _rows(onramp, {}, 50)["paper_collisions"].isna().all()
    frame = pd.DataFrame({"return": [1.0], "collisions": [1.0], "speed_dev_mps": [1.0], "overtakes": [1.0]},
                         index=pd.Index([1], name="episode"))
    runs = {road: RunData(Path(road), "ddpg", "fields_overtake_collision", 90.0, 0, frame, road=road)
            for road in ("ring", "onramp")}
    table = summary_table({("ddpg", "fields_overtake_collision", 90.0, road): [run] for road, run in runs.items()})
    assert table["collisions_paper"].notna().tolist() == [True, False]


SUMMARY_GOLDEN = Path(__file__).resolve().parents[1] / "golden" / "summary"
"""Whole pages of ``lanefree sweep --summary`` for the two hand-made sweeps below, their numbers checked by hand
(the means of values written into the runs, the paper's Table 5 values, the ratios; the percentile CI of 3 values
ends at their extremes: each extreme mean has probability 1/27 > 2.5 %)."""


def _capped_sweep(folder: Path, preset: str = "collision") -> None:
    """A sweep of one DQN setting under two variants (default, cap25; compared), 10 seeds of 700 episodes (the
    budget differs from the paper's but is not reduced) with a config override; run i of the cells writes
    i mod 10 × 0.125 collisions per episode, 0.5 more under cap25 (numbers exact in binary: ties are exact)."""
    grid = parse_grid({"algorithms": ["dqn"], "reward_presets": [preset], "n_seeds": 10, "episodes": 700,
                       "overrides": {"scenario": {"agent_lateral_speed_ratio": 0.5}},
                       "variants": {"default": {}, "cap25": {"scenario.agent_max_speed_mps": 25}},
                       "compare": ["cap25"]}, "capped", "capped.yaml")
    write_manifest(folder, Manifest(grid))
    sweep = SweepDir(folder)
    for i, cell in enumerate(grid.cells()):
        fake_run(sweep.run(cell), grid, cell, 700,
                 collisions=0.125 * (i % 10) + (0.5 if cell.setting.variant == "cap25" else 0.0))


@pytest.mark.parametrize("case", ["pair", "capped"])
def test_the_summary_pages_word_for_word(tmp_path, case):
    """summary.md (and the variants' verdict.md) as a reader gets them, whole: the budget line, the overrides, the
    readings' note, the table with its constant columns folded into one line, the paper's values and ratios, the
    curves, every run with its evaluations, the runs left out and the notes."""
    if case == "pair":
        _pair_sweep(tmp_path)
    else:
        _capped_sweep(tmp_path)
    result = summarize(tmp_path)
    own = ["claims.csv", "claims.md"] if case == "pair" else ["effects.csv", "effects.md", "verdict.md"]
    pages = ["summary.md", "summary.csv", "runs.csv", *own]
    curves = [f"{'table5' if case == 'pair' else 'other'}_{name}.png" for name in ("return", "collisions", "speed_dev")]
    assert sorted(path.name for path in result.files) == sorted(["summary.md", "summary.csv", "runs.csv", *own,
                                                                 *curves])
    assert all(path.is_file() for path in result.files)
    assert result.incomplete == ([("ddpg_collision_d70_s2", "partial, 30/60 episodes")] if case == "pair" else [])
    assert len(result.notes) == (1 if case == "pair" else 0)
    assert (result.effects is None) == (case == "pair") and len(result.table) == (2 if case == "pair" else 2)
    for page in pages:
        golden = SUMMARY_GOLDEN / f"{case}_{page}"
        if os.environ.get("LANEFREE_WRITE_GOLDEN") == "1":
            golden.parent.mkdir(parents=True, exist_ok=True)
            golden.write_text((tmp_path / page).read_text())
        if page.endswith(".csv"):  # every column and string exactly, the numbers to float rounding
            ours, theirs = (list(csv.reader(open(path))) for path in (tmp_path / page, golden))
            assert ours[0] == theirs[0] and len(ours) == len(theirs), page
            for mine, frozen in zip(ours[1:], theirs[1:]):
                assert [_number_or_text(v) for v in mine] == [_number_or_text(v) for v in frozen], (page, mine)
        else:
            assert (tmp_path / page).read_text() == golden.read_text(), page


def _number_or_text(value: str) -> Any:
    """A CSV field as a number compared to float rounding (NaN equal to NaN: an empty field), or its text."""
    try:
        number = float(value) if value else math.nan
    except ValueError:
        return value
    return "nan" if math.isnan(number) else pytest.approx(number, rel=1e-12, abs=1e-15)


def test_the_summary_takes_its_window_and_smoothing_from_the_call(tmp_path):
    """``last`` and ``smooth`` given: the means over that window (a run whose episodes differ), the page and the
    tables say so; left out: the report config's defaults (50 episodes)."""
    grid = parse_grid({"reward_presets": ["collision"], "n_seeds": 2, "episodes": 60}, "window", "window.yaml")
    write_manifest(tmp_path, Manifest(grid))
    sweep = SweepDir(tmp_path)
    for cell in grid.cells():
        fake_run(sweep.run(cell), grid, cell, 60, collisions=1.0)
        path = sweep.run(cell) / "episodes.csv"
        rows = list(csv.DictReader(open(path)))
        for row in rows[-10:]:  # the last 10 episodes: 3 collisions each
            row["collisions"] = "3.0"
        with open(path, "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
    table = summarize(tmp_path, last=10, smooth=5).table
    assert list(table["collisions_mean"]) == [3.0] and list(table["last_episodes"]) == [10]
    assert "the mean over its last 10 episodes" in (tmp_path / "summary.md").read_text()
    assert [float(r["collisions"]) for r in csv.DictReader(open(tmp_path / "runs.csv"))] == [3.0, 3.0]
    default = summarize(tmp_path).table
    assert list(default["collisions_mean"]) == [pytest.approx(1.4)] and list(default["last_episodes"]) == [50]


def test_a_study_puts_several_sweeps_effects_on_one_page(tmp_path):
    """``summarize_study``: each sweep summarised in its folder, their effect rows in one effects.csv and one
    page; refused in one line without variants, for a cell two sweeps share, and where the page cannot be written."""
    from lanefree_sumo.experiments.sweep.summary import summarize_study

    first, second, plain = tmp_path / "a", tmp_path / "b", tmp_path / "plain"
    _capped_sweep(first)
    _capped_sweep(second, "fields_collision")
    summaries, page = summarize_study([first, second], tmp_path / "study")
    assert page == tmp_path / "study" / "effects.md" and len(summaries) == 2
    assert all((folder / "summary.md").is_file() for folder in (first, second))
    rows = list(csv.DictReader(open(tmp_path / "study" / "effects.csv")))
    assert sorted({(r["reward_preset"], r["variant"]) for r in rows}) == [("collision", "cap25"),
                                                                        ("fields_collision", "cap25")]
    text = page.read_text()
    assert str(first) in text and str(second) in text and "fields_collision" in text
    _pair_sweep(plain)
    with pytest.raises(ReportError) as err:
        summarize_study([plain], tmp_path / "none")
    assert str(err.value) == ("none of these sweeps has variants (a grid's `variants` with a `default`): there is no "
                              "effect to put side by side; report each sweep alone")
    assert not (tmp_path / "none").exists()
    with pytest.raises(ReportError) as err:
        summarize_study([first, plain, first], tmp_path / "twice")
    assert str(err.value) == (f"the sweeps {first} and {first} both have the cell dqn / collision / 70 veh/km: each "
                              "cell's variants are compared within one sweep")
    blocked = tmp_path / "blocked"
    blocked.write_text("a file where the study's folder would go")
    with pytest.raises(ReportError, match=f"cannot write the study's effects into {blocked}: "):
        summarize_study([first], blocked)


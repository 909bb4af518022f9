"""Replay in sumo-gui under Xvfb: fidelity to the recording, screenshots, frames, GIF, FCD export."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from PIL import Image

from lanefree_sumo.config import LaneFreeConfig, merge_config
from lanefree_sumo.errors import RunError, SumoError
from lanefree_sumo.experiments.runners.evaluate import evaluate
from lanefree_sumo.experiments.runners.replay import ReplayError, load_recording, replay
from lanefree_sumo.experiments.runners.train import train
from lanefree_sumo.experiments.storage.rundir import write_config
from lanefree_sumo.sim.road import road_of

from conftest import CLI_ENV, ROOT, lanefree, wait_for

pytestmark = [pytest.mark.sumo, pytest.mark.gui, pytest.mark.slow]


def _trained_and_recorded(folder: Path, overrides: dict, learning_starts: int, episodes: int = 1,
                          shield: bool | None = None) -> Path:
    """A one-episode run of ``overrides`` in ``folder``/run, its ``episodes`` evaluation episodes recorded."""
    cfg = merge_config(LaneFreeConfig(), {
        **overrides, "train": {"episodes": 1, "actor_critic": {"learning_starts_steps": learning_starts}}})
    run, _ = train(cfg, run=folder / "run", progress=False)
    evaluate(run, episodes=episodes, record=True, progress=False, shield=shield)
    return run


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Path:
    return _trained_and_recorded(tmp_path_factory.mktemp("replay"), {
        "sim": {"episode_steps": 60}, "scenario": {"density_veh_per_km": 90}}, learning_starts=30, episodes=2)


def test_gui_replay_matches_the_recording_to_a_centimetre(display, recorded):
    result = replay(recorded, episode=2, gui=True)
    assert result.steps == 60
    assert result.max_dx_m <= 0.01 and result.max_dy_m <= 0.01


def test_headless_replay_is_exact_too(recorded):
    result = replay(recorded, episode=1, gui=False)
    assert result.max_dx_m <= 0.01 and result.max_dy_m <= 0.01
    rec = load_recording(recorded, 1)
    assert rec.x.shape == (61, 46) and "agent" in rec.ids


def test_screenshot_has_the_size_and_shows_the_green_agent(display, recorded, tmp_path):
    shot = tmp_path / "view.png"
    replay(recorded, episode=1, screenshot=shot, screenshot_step=30, size=(640, 480))
    image = np.asarray(Image.open(shot).convert("RGB")).astype(int)
    assert image.shape == (480, 640, 3)
    r, g, b = image[..., 0], image[..., 1], image[..., 2]
    green = (g > 150) & (r < 120) & (b < 120)
    assert green.sum() > 50  # the agent, drawn in green and tracked by the view
    assert image.std() > 10  # not blank


def test_frames_and_gif(display, recorded, tmp_path):
    result = replay(recorded, episode=1, frames=tmp_path / "frames", every=20, gif=tmp_path / "a.gif", size=(320, 240))
    assert [p.name for p in result.frames] == ["frame_0020.png", "frame_0040.png", "frame_0060.png"]
    assert all(p.is_file() for p in result.frames)
    gif = Image.open(tmp_path / "a.gif")
    assert gif.n_frames == 3 and gif.size == (320, 240)


def test_missing_recording_says_how_to_make_one(tmp_path):
    with pytest.raises(RunError, match="is not a run folder .*'lanefree train' made"):  # not "evaluate it"
        load_recording(tmp_path, 1)
    write_config(tmp_path, LaneFreeConfig())
    with pytest.raises(ReplayError, match="lanefree evaluate .* --record"):
        load_recording(tmp_path, 1)


def test_export_of_an_episode_not_recorded_makes_no_folder(recorded, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(recorded, run, ignore=shutil.ignore_patterns("export"))
    res = lanefree("export", str(run), "--episode", "99")
    assert res.returncode == 2 and "no recording of episode 99" in res.stderr and res.stderr.count("\n") == 1
    assert not (run / "eval" / "export").exists()  # it was made, with its marker, before the error


def test_export_writes_csv_and_fcd_with_lateral_positions(recorded, tmp_path):
    out = tmp_path / "export"
    res = lanefree("export", str(recorded), "--episode", "1", "--out", str(out))
    assert res.returncode == 0, res.stderr
    assert (out / "episode_0001.csv").read_bytes() == \
        (recorded / "eval" / "trajectories" / "episode_0001.csv").read_bytes()
    root = ET.parse(out / "episode_0001.fcd.xml").getroot()
    steps = root.findall("timestep")
    assert len(steps) >= 60
    vehicles = steps[-1].findall("vehicle")
    assert len(vehicles) == 46 and all("posLat" in v.attrib and "x" in v.attrib for v in vehicles)
    # SUMO's own lateral positions equal the recording's (y = posLat + W/2)
    rec = load_recording(recorded, 1)
    last = {v.attrib["id"]: float(v.attrib["posLat"]) + 5.1 for v in vehicles}
    assert max(abs(last[vid] - y) for vid, y in zip(rec.ids, rec.y[-1])) < 0.01


def test_replay_and_export_never_write_over_a_runs_files_or_a_users(recorded, tmp_path):
    """One safe-file mechanism (rundir.check_new_file/new_file): a run's own files are refused whatever
    --overwrite says, an existing file without it, and export --overwrite only replaces its own output."""
    owned = [recorded / "episodes.csv", recorded / "model.zip", recorded / "eval" / "trajectories" / "episode_0001.csv",
             recorded / "config.yaml"]
    before = {p: p.read_bytes() for p in owned}
    for target in owned:
        res = lanefree("replay", str(recorded), "--no-gui", "--fcd", str(target))
        assert res.returncode != 0 and "belongs to the run folder" in res.stderr and res.stderr.count("\n") == 1
    assert {p: p.read_bytes() for p in owned} == before
    mine = tmp_path / "notes.xml"
    mine.write_text("mine")
    res = lanefree("replay", str(recorded), "--no-gui", "--fcd", str(mine))
    assert res.returncode != 0 and "exists" in res.stderr and mine.read_text() == "mine"
    fcd = tmp_path / "new" / "replay.fcd.xml"
    assert lanefree("replay", str(recorded), "--no-gui", "--fcd", str(fcd)).returncode == 0
    assert fcd.stat().st_size > 1000 and not list(fcd.parent.glob(".*new-*"))  # complete, no temporary left
    users = tmp_path / "users"
    users.mkdir()
    (users / "episode_0001.csv").write_text("mine")
    res = lanefree("export", str(recorded), "--out", str(users), "--overwrite")
    assert res.returncode != 0 and "not the output of an earlier 'lanefree export'" in res.stderr
    assert (users / "episode_0001.csv").read_text() == "mine"
    out = tmp_path / "export"
    assert lanefree("export", str(recorded), "--out", str(out)).returncode == 0
    assert lanefree("export", str(recorded), "--out", str(out)).returncode != 0  # exists, no --overwrite
    assert lanefree("export", str(recorded), "--out", str(out), "--overwrite").returncode == 0


def _damaged_copy(recorded: Path, tmp_path: Path, damage) -> Path:
    """A copy of the recorded run whose episode-1 recording is changed by ``damage(text) -> text``."""
    copy = tmp_path / "copy"
    shutil.copytree(recorded, copy)
    traj = copy / "eval" / "trajectories" / "episode_0001.csv"
    traj.write_text(damage(traj.read_text()))
    return copy


@pytest.mark.parametrize("damage,reason", [
    (lambda text: text.splitlines(keepends=True)[0], "no steps"),
    (lambda text: text.replace(text.splitlines()[5].split(",")[2], "nan", 1), "NaN or infinite"),
    (lambda text: text.replace(text.splitlines()[7].split(",")[3], "inf", 1), "NaN or infinite"),
])
def test_damaged_recordings_get_one_clear_error(recorded, tmp_path, damage, reason):
    copy = _damaged_copy(recorded, tmp_path, damage)
    with pytest.raises(ReplayError, match=reason):
        replay(copy, episode=1, gui=False)


def test_gui_without_a_display_says_so_at_once(recorded, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    t0 = time.perf_counter()
    with pytest.raises(SumoError, match="xvfb-run"):
        replay(recorded, episode=1, gui=True)
    assert time.perf_counter() - t0 < 10


def test_gui_on_a_display_that_does_not_answer_is_one_line_quoting_sumo_gui(recorded):
    unused = next(n for n in range(4000, 5000) if not Path(f"/tmp/.X11-unix/X{n}").exists())
    res = subprocess.run([sys.executable, "-m", "lanefree_sumo.cli", "replay", str(recorded)], capture_output=True,
                         text=True, cwd=ROOT, timeout=120, env={**CLI_ENV, "DISPLAY": f":{unused}"})
    assert res.returncode != 0
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr  # sumo-gui's own complaint is quoted, not printed beside ours
    assert f"did not open its window on display ':{unused}'" in lines[0]
    assert f"unable to open display :{unused}" in lines[0] and "xvfb-run" in lines[0]


def test_unwritable_screenshot_path_is_refused_before_the_replay(recorded, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    res = lanefree("replay", str(recorded), "--screenshot", str(blocker / "view.png"))
    assert res.returncode == 2 and "cannot write" in res.stderr and res.stderr.count("\n") == 1


def test_sigterm_stops_a_replay_like_ctrl_c_and_leaves_no_file(display, recorded, tmp_path):
    """Every verb runs with SIGTERM turned into Ctrl-C: a replay in sumo-gui stopped mid-episode exits 130 with
    one line, and its FCD output is neither left half-written nor as a temporary file."""
    fcd = tmp_path / "out.fcd.xml"
    proc = subprocess.Popen([sys.executable, "-m", "lanefree_sumo.cli", "replay", str(recorded), "--delay", "0.2",
                             "--fcd", str(fcd)], cwd=ROOT, env={**CLI_ENV, "DISPLAY": display},
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    wait_for(lambda: any(p.stat().st_size > 0 for p in tmp_path.glob(".out.fcd.xml.new-*")), proc,
             "FCD output being written")
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130 and "interrupted" in err and "Traceback" not in err, err
    assert list(tmp_path.iterdir()) == []


def _children(pid: int) -> list[tuple[int, str]]:
    """(pid, name) of the processes whose parent is ``pid``."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            text = stat.read_text()
        except OSError:  # ended meanwhile
            continue
        name, rest = text[text.index("(") + 1:text.rindex(")")], text[text.rindex(")") + 2:].split()
        if int(rest[1]) == pid:
            found.append((int(stat.parent.name), name))
    return found


def test_sumo_gui_closed_mid_replay_is_one_line_not_a_bug(display, recorded, tmp_path):
    """The user closes sumo-gui's window while the replay runs (here: its process ends): one line saying so, exit 1
    — not an internal error with a traceback."""
    fcd = tmp_path / "out.fcd.xml"
    proc = subprocess.Popen([sys.executable, "-m", "lanefree_sumo.cli", "replay", str(recorded), "--delay", "0.2",
                             "--fcd", str(fcd)], cwd=ROOT, env={**CLI_ENV, "DISPLAY": display},
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    wait_for(lambda: any("<timestep" in p.read_text() for p in tmp_path.glob(".out.fcd.xml.new-*")), proc,
             "steps in the FCD output (sumo-gui connected and stepping)")
    gui = [pid for pid, name in _children(proc.pid) if name == "sumo-gui"]
    assert len(gui) == 1
    os.kill(gui[0], signal.SIGKILL)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 1 and err.strip().count("\n") == 0, err
    assert err.startswith("lanefree: error: sumo-gui closed before the end (its window was closed, or it stopped")


@pytest.fixture(scope="module")
def onramp_recorded(tmp_path_factory) -> Path:
    """An on-ramp run whose recorded episodes have vehicles entering and leaving."""
    return _trained_and_recorded(tmp_path_factory.mktemp("onramp_replay"), {
        "road": {"kind": "onramp"}, "sim": {"episode_steps": 240}, "scenario": {"density_veh_per_km": 20}},
        learning_starts=60)


def test_onramp_recording_holds_every_vehicle_seen_while_it_was_on_the_road(onramp_recorded):
    rec = load_recording(onramp_recorded, 1)
    changes = np.diff(rec.present.astype(int), axis=0)
    assert (changes == 1).any() and (changes == -1).any()  # vehicles entered and left during the episode
    assert np.isnan(rec.x[~rec.present]).all() and np.isfinite(rec.x[rec.present]).all()
    assert rec.present[:, rec.ids.index("agent")].all()
    # an entering vehicle's first row is where it was placed, before it moved: the main road's upstream
    # end (its rear at x = 0) or the ramp (y < 0)
    first = rec.present.argmax(axis=0)
    entered = np.flatnonzero(first > 0)
    placed_x, placed_y = rec.x[first[entered], entered], rec.y[first[entered], entered]
    assert np.all(np.isclose(placed_x, 0.5 * rec.length[entered]) | (placed_y < 0))
    # ramp vehicles merged on the way: on the ramp (y < 0) at first, wholly on the main road later
    was_on_ramp = ((rec.y < 0) & rec.present).any(axis=0)
    merged = was_on_ramp & (np.nan_to_num(rec.y - 0.5 * rec.width, nan=-1.0) >= 0).any(axis=0)
    assert merged.any()


def test_onramp_replay_is_exact_while_vehicles_come_and_go(onramp_recorded, tmp_path):
    fcd = tmp_path / "onramp.fcd.xml"
    result = replay(onramp_recorded, episode=1, gui=False, fcd=fcd)
    assert result.steps == load_recording(onramp_recorded, 1).steps
    assert result.max_dx_m <= 0.01 and result.max_dy_m <= 0.01
    # SUMO's own output has, after every step, exactly the vehicles the recording has on the road then
    # (a vehicle's placement row, before its first step, is not a SUMO time step)
    rec = load_recording(onramp_recorded, 1)
    first = rec.present.argmax(axis=0)
    steps = ET.parse(fcd).getroot().findall("timestep")
    assert len(steps) == rec.steps + 1
    for k in range(1, rec.steps + 1):
        expected = {vid for j, vid in enumerate(rec.ids) if rec.present[k, j] and first[j] < k}
        assert {v.attrib["id"] for v in steps[k].findall("vehicle")} == expected, k


def test_onramp_gui_replay_shows_the_green_agent(display, onramp_recorded, tmp_path):
    shot = tmp_path / "onramp.png"
    result = replay(onramp_recorded, episode=1, screenshot=shot, screenshot_step=40, size=(640, 480))
    assert result.max_dx_m <= 0.01 and result.max_dy_m <= 0.01
    image = np.asarray(Image.open(shot).convert("RGB")).astype(int)
    r, g, b = image[..., 0], image[..., 1], image[..., 2]
    assert ((g > 150) & (r < 120) & (b < 120)).sum() > 50


def test_onramp_recording_of_several_agents_keeps_each_agents_rows_and_last_step(tmp_path):
    """Agents taken off the road one by one (shielded): each keeps its row of the step it left in, every
    row's realised acceleration is its own ((vx_k − vx_k−1)/T, to the recording's rounding), its shielded
    rows are its interventions, and the replay is exact."""
    overrides = {"road": {"kind": "onramp", "onramp": {"agent_start": "main", "agent_main_start_m": 1800.0}},
                 "sim": {"episode_steps": 240}, "scenario": {"density_veh_per_km": 20, "agents": 2}}
    cfg = merge_config(LaneFreeConfig(), overrides)
    run = _trained_and_recorded(tmp_path, overrides, learning_starts=60, shield=True)
    recorded = run / "eval_shield"
    rec = load_recording(recorded, 1)
    road_end = road_of(cfg).length_m
    for name in ("agent", "agent1"):
        rows = np.flatnonzero(rec.present[:, rec.ids.index(name)])
        assert rows[0] == 0 and rec.x[rows[-1], rec.ids.index(name)] >= road_end  # its last row: past the end
    assert rec.present[-1, rec.ids.index("agent")] or rec.present[-1, rec.ids.index("agent1")]
    table = pd.read_csv(recorded / "trajectories" / "episode_0001.csv").sort_values(["id", "t"], kind="stable")
    realised = table.groupby("id")["vx"].diff() / cfg.sim.step_s
    assert (table["ax"] - realised).abs().max() < 1e-4
    # each agent's shielded rows, its last step's included, are the interventions its episodes.csv row counts
    episodes = pd.read_csv(recorded / "episodes.csv").set_index("agent")["shield_interventions"]
    assert table.groupby("id")["shielded"].sum()[["agent", "agent1"]].tolist() == episodes[["agent", "agent1"]].tolist()
    assert episodes.sum() > 0
    result = replay(recorded, episode=1, gui=False)
    assert result.max_dx_m <= 0.01 and result.max_dy_m <= 0.01


def test_video_of_a_recording_without_sumo_or_a_display(recorded, tmp_path):
    res = lanefree("replay", str(recorded), "--episode", "2", "--video", str(tmp_path / "ep2.mp4"))
    assert res.returncode == 0, res.stderr
    assert "wrote 61 frames of episode 2" in res.stdout
    video = tmp_path / "ep2.mp4"
    assert video.stat().st_size > 1000 and video.read_bytes()[4:8] == b"ftyp"  # an MP4 container
    again = lanefree("replay", str(recorded), "--video", str(video))
    assert again.returncode != 0 and again.stderr.count("\n") == 1 and "exists" in again.stderr
    gif = tmp_path / "ep1.gif"
    assert lanefree("replay", str(recorded), "--video", str(gif), "--every", "4").returncode == 0
    with Image.open(gif) as image:
        assert image.n_frames == 16  # steps 0, 4, …, 60


def test_video_frames_follow_the_recording(recorded):
    from lanefree_sumo.experiments.runners.replay import recording_frames
    from lanefree_sumo.rl.render import AGENT

    frames = recording_frames(load_recording(recorded, 1), every=30)
    assert len(frames) == 3 and not np.array_equal(frames[0], frames[2])
    assert all(np.all(f == np.array(AGENT, dtype=np.uint8), axis=-1).sum() > 100 for f in frames)


@pytest.mark.parametrize("args,named", [(["--video", "x.avi"], ".mp4 or .gif"),
                                        (["--video", "x.mp4", "--screenshot", "s.png"], "drop --screenshot")])
def test_video_mistakes_are_one_line(recorded, tmp_path, args, named):
    res = lanefree("replay", str(recorded), *args, cwd=tmp_path)
    assert res.returncode != 0 and named in res.stderr and res.stderr.count("\n") == 1

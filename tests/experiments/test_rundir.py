"""The run-folder guard (:mod:`lanefree_sumo.experiments.storage.rundir`): which earlier output ``--overwrite``
may replace, which files a run folder owns, and the atomic replacement (files made by hand, no SUMO)."""

from __future__ import annotations

import fcntl
import json
import os
import re
import shutil
import stat
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
import yaml

from lanefree_sumo.config import LaneFreeConfig, config_to_dict, merge_config
from lanefree_sumo.errors import RunError
from lanefree_sumo.experiments.storage.rundir import (
    OUTPUT_MARKER,
    RunDir,
    append_command,
    check_new_file,
    check_replaceable,
    check_writable,
    claim,
    claim_path,
    find_eval_dir,
    fresh_output,
    new_file,
    read_config,
    read_sessions,
    record_session,
    trajectory_path,
    vehicles_path,
    write_atomic,
    write_config,
)


def _child_env() -> dict[str, str]:
    """This process's environment with this checkout first on the child's import path."""
    root = str(Path(__file__).resolve().parents[2])
    return {**os.environ, "PYTHONPATH": os.pathsep.join([root, *filter(None, [os.environ.get("PYTHONPATH")])])}


def output_of(folder: Path, verb: str, *files: str) -> Path:
    """A folder as ``lanefree VERB --out folder`` leaves it: its marker and ``files``."""
    folder.mkdir(parents=True)
    (folder / OUTPUT_MARKER).write_text(verb + "\n")
    for name in files:
        (folder / name).write_text("data\n")
    return folder


def run_folder(folder: Path) -> Path:
    folder.mkdir(parents=True)
    (folder / "config.yaml").write_text("{}\n")
    (folder / "episodes.csv").write_text("episode\n1\n")
    return folder


def test_overwrite_replaces_only_the_same_verbs_earlier_output(tmp_path):
    sim = output_of(tmp_path / "sim", "simulate", "trajectory.csv")
    check_replaceable(sim, True, "simulate")  # same verb: may be replaced
    with pytest.raises(RunError, match="not the output of an earlier 'lanefree evaluate'"):
        check_replaceable(sim, True, "evaluate")  # another verb's output
    with pytest.raises(RunError, match=r"exists; choose another --out or pass --overwrite"):
        check_replaceable(sim, False, "simulate")  # not without --overwrite
    # the marker's whole text names the verb: a prefix or another verb in it is not that verb
    (sim / OUTPUT_MARKER).write_text("simulated\n")
    with pytest.raises(RunError, match="no marker file"):
        check_replaceable(sim, True, "simulate")
    (sim / OUTPUT_MARKER).write_text("  simulate \n")  # surrounding blanks do not matter
    check_replaceable(sim, True, "simulate")
    # a marker that is a folder is no marker
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / OUTPUT_MARKER).mkdir()
    with pytest.raises(RunError, match="no marker file"):
        check_replaceable(foreign, True, "simulate")


def test_overwrite_accepts_a_missing_or_empty_folder_and_refuses_everything_else(tmp_path):
    check_replaceable(tmp_path / "new", False, "simulate")  # does not exist: nothing to replace
    empty = tmp_path / "empty"
    empty.mkdir()
    check_replaceable(empty, True, "evaluate")
    with pytest.raises(RunError, match="exists"):
        check_replaceable(empty, False, "evaluate")
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("precious")
    with pytest.raises(RunError, match="not the output of an earlier 'lanefree simulate'"):
        check_replaceable(mine, True, "simulate")
    a_file = tmp_path / "file.csv"
    a_file.write_text("x")
    with pytest.raises(RunError, match="it is a file"):
        check_replaceable(a_file, True, "simulate")
    # a training run folder, even with the verb's marker in it (each of the three files alone tells)
    for name in ("model.zip", "versions.json", "checkpoints"):
        folder = output_of(tmp_path / f"run_{name}", "simulate")
        (folder / name).mkdir() if name == "checkpoints" else (folder / name).write_text("x")
        with pytest.raises(RunError, match="training run folder"):
            check_replaceable(folder, True, "simulate")


def test_overwrite_never_replaces_the_current_folder_or_a_parent(tmp_path, monkeypatch):
    here = output_of(tmp_path / "a" / "b", "simulate")
    monkeypatch.chdir(here)
    for target in (here, here.parent, tmp_path, Path(".")):
        with pytest.raises(RunError, match="current folder or one of its parents"):
            check_replaceable(target, True, "simulate")
    sibling = output_of(tmp_path / "a" / "c", "simulate")
    check_replaceable(sibling, True, "simulate")  # beside the current folder: fine


def test_fresh_output_marks_replaces_and_keeps_the_old_output_on_failure(tmp_path):
    out = tmp_path / "out"
    with fresh_output(out, False, "simulate") as tmp:
        assert tmp != out and tmp.parent == tmp_path and (tmp / OUTPUT_MARKER).read_text() == "simulate\n"
        (tmp / "a.csv").write_text("first")
        assert not out.exists()  # nothing at out until the block ends
    assert sorted(p.name for p in out.iterdir()) == [OUTPUT_MARKER, "a.csv"]
    with pytest.raises(ValueError), fresh_output(out, True, "simulate") as tmp:
        (tmp / "a.csv").write_text("second")
        raise ValueError("the verb failed")
    assert (out / "a.csv").read_text() == "first"  # the earlier output is kept
    with fresh_output(out, True, "simulate") as tmp:
        (tmp / "b.csv").write_text("second")
    assert sorted(p.name for p in out.iterdir()) == [OUTPUT_MARKER, "b.csv"]  # replaced whole
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no temporary folder left
    with pytest.raises(RunError, match="not the output of an earlier 'lanefree evaluate'"), \
            fresh_output(out, True, "evaluate"):
        pass
    assert (out / "b.csv").read_text() == "second"


def test_a_run_folder_owns_its_files_whatever_overwrite_says(tmp_path):
    run = run_folder(tmp_path / "run")
    for name in ("config.yaml", "episodes.csv", "model.zip", "command.txt", "checkpoints/ep_00001/model.zip",
                 "tb/events", "eval/episodes.csv", "eval_d90_shield/recording.json", "eval/trajectories/e.csv"):
        with pytest.raises(RunError, match="belongs to the run folder or output"):
            check_new_file(run / name, True, "export")
    # but not its evaluations' export/ folders, nor a file of its own the run does not write
    check_new_file(run / "eval" / "export" / "table.csv", False, "export")
    check_new_file(run / "notes.md", False, "export")
    # a folder with a config but neither episodes nor checkpoints is not a run folder
    bare = tmp_path / "bare"
    bare.mkdir()
    (bare / "config.yaml").write_text("{}\n")
    check_new_file(bare / "episodes.csv", False, "export")
    with_ckpt = tmp_path / "ckpt"
    (with_ckpt / "checkpoints").mkdir(parents=True)
    (with_ckpt / "config.yaml").write_text("{}\n")
    with pytest.raises(RunError, match="belongs to"):
        check_new_file(with_ckpt / "episodes.csv", False, "export")


def test_another_verbs_output_owns_its_files_but_not_its_export_folder(tmp_path):
    sim = output_of(tmp_path / "sim", "simulate", "trajectory.csv")
    with pytest.raises(RunError, match="belongs to the run folder or output"):
        check_new_file(sim / "plot.png", True, "plot")
    check_new_file(sim / "export" / "plot.png", False, "plot")  # export/ is anyone's
    check_new_file(sim / "plot.png", False, "simulate")  # the same verb's own folder


def test_an_existing_file_needs_overwrite_and_with_a_marker_folder_the_same_verb(tmp_path):
    target = tmp_path / "plain" / "table.csv"
    target.parent.mkdir()
    target.write_text("old")
    with pytest.raises(RunError, match=r"exists; choose another path or pass --overwrite$"):
        check_new_file(target, False, "export")
    with pytest.raises(RunError, match=r"exists; choose another path$"):
        check_new_file(target, False, "plot")  # only export offers --overwrite
    check_new_file(target, True, "export")
    with pytest.raises(RunError, match="its folder is not the output of an earlier 'lanefree plot'"):
        check_new_file(target, True, "plot", marker_folder=True)  # no marker
    (target.parent / OUTPUT_MARKER).write_text("export\n")
    with pytest.raises(RunError, match="belongs to"):  # another verb's output folder
        check_new_file(target, True, "plot", marker_folder=True)
    (target.parent / OUTPUT_MARKER).write_text("plot\n")
    check_new_file(target, True, "plot", marker_folder=True)
    check_new_file(tmp_path / "plain" / "new.csv", False, "plot", marker_folder=True)  # a new file: no question
    folder = tmp_path / "plain" / "sub"
    folder.mkdir()
    with pytest.raises(RunError, match="exists and is not a file"):
        check_new_file(folder, True, "plot")


def test_new_file_replaces_only_on_success(tmp_path):
    path = tmp_path / "table.csv"
    path.write_text("old")
    with pytest.raises(ValueError), new_file(path, "export") as tmp:
        tmp.write_text("half")
        raise ValueError("cut")
    assert path.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["table.csv"]
    with new_file(path, "export") as tmp:
        assert tmp.parent == tmp_path and tmp != path
        tmp.write_text("new")
    assert path.read_text() == "new" and sorted(p.name for p in tmp_path.iterdir()) == ["table.csv"]


# -- the run folder's own files ---------------------------------------------------------------------

def test_config_round_trip_and_a_damaged_config_is_named(tmp_path):
    cfg = merge_config(LaneFreeConfig(), {"reward": {"epsilon_r": 0.25}, "scenario": {"density_veh_per_km": 90}})
    write_config(tmp_path, cfg)
    assert read_config(tmp_path) == cfg and RunDir(tmp_path).load_config() == cfg
    data = yaml.safe_load((tmp_path / "config.yaml").read_text())
    assert list(data) == list(config_to_dict(cfg))  # in the config's own order, not sorted
    with pytest.raises(RunError, match=r"is not a run folder \(no config.yaml\)"):
        read_config(tmp_path / "nothing")
    (tmp_path / "config.yaml").write_text("- a list\n")
    with pytest.raises(RunError, match=r"\(it is not a mapping of config keys\); restore it or start a new run$"):
        read_config(tmp_path)
    del data["reward"]["epsilon_r"], data["seed"]
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(RunError, match=r"key 'reward.epsilon_r' and 1 more missing \(file cut short\?\)"):
        read_config(tmp_path)
    (tmp_path / "config.yaml").write_text(yaml.safe_dump({**config_to_dict(cfg), "seed": 0}).replace(
        "seed: 0", "seed: [1"))
    with pytest.raises(RunError, match=r"config.yaml is unusable \(.+\); restore it or start a new run$") as err:
        read_config(tmp_path)
    assert "\n" not in str(err.value)


def test_one_missing_key_is_named_alone(tmp_path):
    data = config_to_dict(LaneFreeConfig())
    del data["seed"]
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(RunError, match=r"key 'seed' missing \(file cut short\?\)"):
        read_config(tmp_path)


def test_sessions_are_appended_one_per_line_and_a_cut_line_is_skipped(tmp_path):
    assert read_sessions(tmp_path) == []
    record_session(tmp_path, {"episodes_done": 3, "ended": "finished"})
    assert json.loads((tmp_path / "last_session.json").read_text()) == {"episodes_done": 3, "ended": "finished"}
    with open(tmp_path / "sessions.jsonl", "a") as fh:
        fh.write('{"episodes_done": 4, "ended"')  # a process killed mid-write
    record_session(tmp_path, {"episodes_done": 5})
    assert json.loads((tmp_path / "last_session.json").read_text()) == {"episodes_done": 5}
    lines = (tmp_path / "sessions.jsonl").read_text().split("\n")
    assert lines == ['{"episodes_done": 3, "ended": "finished"}', '{"episodes_done": 4, "ended"',
                     '{"episodes_done": 5}', ""]
    assert read_sessions(tmp_path) == [{"episodes_done": 3, "ended": "finished"}, {"episodes_done": 5}]
    with open(tmp_path / "sessions.jsonl", "a") as fh:
        fh.write("[1, 2]\n")  # JSON, but not a session
    assert len(read_sessions(tmp_path)) == 2
    (tmp_path / "sessions.jsonl").write_bytes(b"\xff\xfe\n")
    assert read_sessions(tmp_path) == []


def test_commands_are_appended_one_per_line(tmp_path):
    append_command(tmp_path, "lanefree train --density 90")
    append_command(tmp_path, "lanefree evaluate run")
    assert (tmp_path / "command.txt").read_text() == "lanefree train --density 90\nlanefree evaluate run\n"


def test_evaluation_folder_names(tmp_path):
    run = RunDir(tmp_path)
    assert run.eval_dir() == tmp_path / "eval"
    assert run.eval_dir(90.0) == tmp_path / "eval_d90"
    assert run.eval_dir(87.5, shield=True) == tmp_path / "eval_d87.5_shield"
    assert run.eval_dir(shield=False) == tmp_path / "eval_noshield"
    assert run.eval_dir(90, scenario="onramp") == tmp_path / "eval_onramp_d90"
    assert run.eval_dir(scenario="onramp", shield=True) == tmp_path / "eval_onramp_shield"
    assert run.checkpoint(7) == tmp_path / "checkpoints" / "ep_00007"
    assert (run.config, run.episodes, run.model, run.versions, run.last_session, run.tensorboard, run.lock_file) == \
        tuple(tmp_path / n for n in ("config.yaml", "episodes.csv", "model.zip", "versions.json", "last_session.json",
                                     "tb", ".lock"))
    assert trajectory_path(tmp_path, 3) == tmp_path / "trajectories" / "episode_0003.csv"
    assert vehicles_path(tmp_path, 12) == tmp_path / "trajectories" / "episode_0012.vehicles.csv"
    assert find_eval_dir(tmp_path) == tmp_path / "eval"
    (tmp_path / "trajectories").mkdir()
    assert find_eval_dir(tmp_path) == tmp_path  # a recording itself


def _checkpoint(run: RunDir, episodes: int, model: bool = True, buffer: bool = True) -> Path:
    folder = run.checkpoint(episodes)
    folder.mkdir(parents=True)
    if model:
        (folder / "model.zip").write_bytes(b"m")
    if buffer:
        (folder / "replay_buffer.pkl").write_bytes(b"b")
    run.write_checkpoint_state(folder, {"episodes": episodes, "timesteps": 100 * episodes})
    return folder


def test_the_newest_complete_checkpoint_and_the_model_to_load(tmp_path):
    run = RunDir(tmp_path)
    with pytest.raises(RunError, match="has no model.zip and no checkpoint"):
        run.find_model()
    with pytest.raises(RunError, match="no usable checkpoint under checkpoints/"):
        run.newest_checkpoint()
    _checkpoint(run, 2)
    _checkpoint(run, 4)
    _checkpoint(run, 6, model=False)  # not complete: its model is missing
    (run.checkpoint(8)).mkdir()  # nor is one without state.json
    assert json.loads((run.checkpoint(4) / "state.json").read_text()) == {"episodes": 4, "timesteps": 400}
    newest = run.newest_checkpoint()
    assert (newest.path, newest.episodes, newest.timesteps) == (run.checkpoint(4), 4, 400)
    assert newest.model == run.checkpoint(4) / "model.zip"
    assert newest.replay_buffer == run.checkpoint(4) / "replay_buffer.pkl"
    assert run.find_model() == run.checkpoint(4) / "model.zip"
    (tmp_path / "model.zip").write_bytes(b"final")
    assert run.find_model() == tmp_path / "model.zip"


def test_replay_buffers_are_pruned_to_the_newest(tmp_path):
    run = RunDir(tmp_path)
    run.prune_replay_buffers(1)  # no checkpoints yet: nothing to do
    for episodes in (1, 2, 3):
        _checkpoint(run, episodes)

    def buffers() -> list[int]:
        return [e for e in (1, 2, 3) if (run.checkpoint(e) / "replay_buffer.pkl").exists()]

    run.prune_replay_buffers(2)
    assert buffers() == [2, 3]
    run.prune_replay_buffers(1)
    assert buffers() == [3]
    run.prune_replay_buffers(0)
    assert buffers() == [] and all((run.checkpoint(e) / "model.zip").exists() for e in (1, 2, 3))


def test_one_writer_at_a_time(tmp_path):
    run = RunDir(tmp_path)
    with run.writer_lock():
        assert run.lock_file.read_text() == f"{os.getpid()}\n"
        with pytest.raises(RunError, match=f"is being written by process {os.getpid()} "), run.writer_lock():
            pass
    with run.writer_lock():  # released
        pass


# -- what dead writers leave, what a live one holds, how outputs are made --------------------------------------

def test_a_claim_clears_what_dead_writers_left_and_puts_an_output_they_moved_aside_back(tmp_path):
    out = tmp_path / "out"
    (tmp_path / ".out.new-abcd_123").mkdir()  # a half-written output
    (tmp_path / ".out.new-abcd_123" / "a.csv").write_text("half")
    (tmp_path / ".out.new-0000aaaa").write_text("half a file")
    aside = tmp_path / ".out.old-zz99zz99"  # the earlier output, moved aside by a writer that died before the swap
    output_of(aside / "out", "simulate", "a.csv")
    (tmp_path / ".out.new-abc").mkdir()  # not a temporary name (8 characters): someone else's
    (tmp_path / ".other.new-abcd1234").mkdir()
    with claim(out, "simulate"):
        assert (tmp_path / claim_path(out).name).read_text() == f"{os.getpid()} simulate\n"
        assert sorted(p.name for p in tmp_path.iterdir()) == [".other.new-abcd1234", ".out.lock", ".out.new-abc", "out"]
        assert (out / "a.csv").read_text() == "data\n"  # put back, nothing lost
    assert sorted(p.name for p in tmp_path.iterdir()) == [".other.new-abcd1234", ".out.new-abc", "out"]
    # an earlier output moved aside while a newer one is in place: the newer one stays, the old is removed
    output_of(tmp_path / ".out.old-12345678" / "out", "simulate", "old.csv")
    with claim(out, "simulate"):
        pass
    assert sorted(p.name for p in out.iterdir()) == [OUTPUT_MARKER, "a.csv"]
    assert not (tmp_path / ".out.old-12345678").exists()


def test_a_claim_held_by_another_process_names_it(tmp_path):
    out = tmp_path / "out"
    holder = subprocess.Popen([sys.executable, "-c", "import sys\n"
                               "from pathlib import Path\n"
                               "from lanefree_sumo.experiments.storage.rundir import claim\n"
                               f"with claim(Path({str(out)!r}), 'evaluate'):\n"
                               "    print('held', flush=True); sys.stdin.read()"],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=_child_env())
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(RunError, match=rf"^{re.escape(str(out))} is being written by process {holder.pid} "
                                           r"\(another 'lanefree evaluate'\); wait for it or choose another output$"):
            with claim(out, "simulate"):
                pass
    finally:
        holder.stdin.close()
        holder.wait()
    assert holder.returncode == 0 and not claim_path(out).exists()  # released and removed on the way out
    with claim(out, "simulate"):
        pass


def test_outputs_are_ordinary_files_and_folders_under_the_umask(tmp_path):
    old = os.umask(0o027)
    try:
        with new_file(tmp_path / "table.csv", "export") as tmp:
            tmp.write_text("x")
        with fresh_output(tmp_path / "out", False, "simulate") as folder:
            (folder / "a.csv").write_text("x")
        write_atomic(tmp_path / "sub" / "state.json", "{}\n")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "table.csv").stat().st_mode) == 0o640
    assert stat.S_IMODE((tmp_path / "out").stat().st_mode) == 0o750
    assert stat.S_IMODE((tmp_path / "sub" / "state.json").stat().st_mode) == 0o640
    assert (tmp_path / "sub" / "state.json").read_text() == "{}\n"
    assert sorted(p.name for p in (tmp_path / "sub").iterdir()) == ["state.json"]  # no temporary left


def test_an_output_made_by_another_program_meanwhile_is_left_alone(tmp_path):
    out = tmp_path / "out"

    def refused(k: int) -> str:
        return (rf"^{re.escape(str(out))} was made or replaced by another program while 'lanefree simulate' wrote; "
                rf"it is left as it is, and this output is in {re.escape(str(out))}.simulate-{k}$")

    with pytest.raises(RunError, match=refused(1)), fresh_output(out, False, "simulate") as folder:
        (folder / "mine.csv").write_text("1")
        output_of(out, "simulate", "theirs.csv")  # made meanwhile where nothing was
    with pytest.raises(RunError, match=refused(2)), fresh_output(out, True, "simulate") as folder:
        (folder / "mine.csv").write_text("2")
        out.rename(tmp_path / "moved")  # the earlier output replaced by another one meanwhile
        output_of(out, "simulate", "newer.csv")
    assert [(tmp_path / f"out.simulate-{k}" / "mine.csv").read_text() for k in (1, 2)] == ["1", "2"]
    assert sorted(p.name for p in out.iterdir()) == [OUTPUT_MARKER, "newer.csv"]


def test_a_run_that_never_reached_a_checkpoint_is_told_from_a_users_folder_and_cleared(tmp_path):
    run = RunDir(tmp_path / "run")
    assert not run.never_checkpointed()  # no folder
    run.path.mkdir()
    for name in ("config.yaml", "episodes.csv", ".lock"):
        (run.path / name).write_text("x")
    (run.path / "tb").mkdir()
    assert run.never_checkpointed() and not run.has_checkpoint()
    (run.path / ".lock").unlink()
    assert not run.never_checkpointed()  # no lock: not made by a training
    (run.path / ".lock").write_text("1\n")
    (run.path / "notes.md").write_text("mine")
    assert not run.never_checkpointed()  # a file training never writes
    (run.path / "notes.md").unlink()
    (run.path / "model.zip").write_text("m")
    assert not run.never_checkpointed()  # it finished
    (run.path / "model.zip").unlink()
    _checkpoint(run, 1)
    assert run.has_checkpoint() and not run.never_checkpointed()  # resumable
    target = tmp_path / "elsewhere"
    target.mkdir()
    (target / "keep.txt").write_text("keep")
    (run.path / "link").symlink_to(target)
    run.clear()
    assert sorted(p.name for p in run.path.iterdir()) == [".lock"]
    assert (target / "keep.txt").read_text() == "keep"  # a link is removed, not what it points to


def test_a_session_line_starts_a_line_of_its_own_only_after_a_cut_one(tmp_path):
    (tmp_path / "sessions.jsonl").write_text("")  # created, nothing written yet
    record_session(tmp_path, {"episodes_done": 1})
    record_session(tmp_path, {"episodes_done": 2})
    assert (tmp_path / "sessions.jsonl").read_text() == '{"episodes_done": 1}\n{"episodes_done": 2}\n'
    one = tmp_path / "one"
    one.mkdir()
    (one / "sessions.jsonl").write_text("{")  # killed after one byte
    record_session(one, {"episodes_done": 3})
    assert (one / "sessions.jsonl").read_text() == '{\n{"episodes_done": 3}\n'
    assert read_sessions(one) == [{"episodes_done": 3}]


def test_a_marker_that_is_not_text_names_no_verb(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / OUTPUT_MARKER).write_bytes(b"\xff\xfesimulate\n")
    with pytest.raises(RunError, match="belongs to the run folder or output"):
        check_new_file(out / "plot.png", False, "simulate")


def test_writability_is_checked_where_the_output_goes(tmp_path):
    folder = tmp_path / "new" / "deeper"
    check_writable(folder, folder=True)
    assert folder.is_dir()  # the folder itself, made now
    check_writable(tmp_path / "other" / "table.csv")
    assert (tmp_path / "other").is_dir() and not (tmp_path / "other" / "table.csv").exists()
    assert list((tmp_path / "other").iterdir()) == []  # the probe leaves nothing behind
    if not Path("/sys/kernel").is_dir():
        pytest.skip("no sysfs: no folder that even root cannot write into")
    with pytest.raises(RunError, match=r"^cannot write /sys/kernel/table.csv: [A-Z][a-z -]+$"):  # the OS reason
        check_writable(Path("/sys/kernel/table.csv"))  # sysfs makes no files, whoever asks


def test_atomic_writes_into_an_existing_folder_and_nothing_is_left_when_one_fails(tmp_path, monkeypatch):
    # the temporaries go beside the file, never to the system's temporary folder (here one that does not exist)
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "no-such-folder"))
    old = os.umask(0o022)
    try:
        write_atomic(tmp_path / "state.json", "1\n")  # the folder exists already
        write_atomic(tmp_path / "state.json", "2\n")  # and so does the file
    finally:
        os.umask(old)
    assert (tmp_path / "state.json").read_text() == "2\n"
    assert stat.S_IMODE((tmp_path / "state.json").stat().st_mode) == 0o644
    with pytest.raises(UnicodeEncodeError):
        write_atomic(tmp_path / "state.json", "\ud800")  # text UTF-8 cannot hold: fails while writing
    assert (tmp_path / "state.json").read_text() == "2\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["state.json"]  # its temporary removed
    # an output replacing an earlier one: the earlier one goes aside under the name a claim can restore it from
    removed = []
    real_rmtree = shutil.rmtree
    monkeypatch.setattr(shutil, "rmtree", lambda p, **kw: (removed.append(Path(p).name), real_rmtree(p, **kw)))
    with fresh_output(tmp_path / "out", False, "simulate"):
        pass
    with fresh_output(tmp_path / "out", True, "simulate"):
        pass
    assert len(removed) == 1 and re.fullmatch(r"\.out\.old-[a-z0-9_]{8}", removed[0])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "state.json"]


def test_a_marker_that_is_not_text_is_no_marker_to_replace(tmp_path):
    out = output_of(tmp_path / "out", "simulate", "a.csv")
    (out / OUTPUT_MARKER).write_bytes(b"\xff\xfesimulate\n")
    with pytest.raises(RunError, match=r"\(no marker file\); remove it yourself or choose another --out$"):
        check_replaceable(out, True, "simulate")


def test_a_claim_makes_its_folders_and_never_moves_a_half_written_output_into_place(tmp_path):
    out = tmp_path / "a" / "b" / "out"  # two folders that do not exist yet
    half = out.parent / ".out.new-abcdefgh" / "out"  # an output being written that holds a folder named like it
    old = os.umask(0o022)
    try:
        with claim(tmp_path / "x" / "y" / "z", "simulate"):
            assert stat.S_IMODE(claim_path(tmp_path / "x" / "y" / "z").stat().st_mode) == 0o644  # an ordinary file
        half.mkdir(parents=True)
        (half / "partial.csv").write_text("half")
        with claim(out, "simulate"):
            pass
    finally:
        os.umask(old)
    assert not out.exists() and sorted(p.name for p in out.parent.iterdir()) == []


def test_the_reason_a_config_is_unusable_is_cut_at_300_characters(tmp_path):
    data = config_to_dict(LaneFreeConfig())
    data["reward"]["no_such_key_" + "x" * 300] = 1
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(RunError) as err:
        read_config(tmp_path)
    reason = re.fullmatch(r".* is unusable \((.*)\); restore it or start a new run", str(err.value)).group(1)
    assert len(reason) == 300 and reason.startswith("unknown config key 'reward.no_such_key_xxx")


@pytest.mark.parametrize("content,named", [
    (b"", "process ? (another 'lanefree simulate')"),  # the holder has not written yet: our own verb
    (b"1234", "process 1234 (another 'lanefree simulate')"),
    (b"1234 evaluate\n", "process 1234 (another 'lanefree evaluate')"),
    (b"\xff\xfe evaluate", "process \ufffd\ufffd (another 'lanefree evaluate')"),
    (b"1234 " + b"v" * 200, f"process 1234 (another 'lanefree {'v' * 95}')"),  # the first 100 bytes only
])
def test_a_claim_names_what_the_holders_lock_file_says(tmp_path, content, named):
    out = tmp_path / "out"
    lock = claim_path(out)
    lock.write_bytes(content)
    with open(lock, "rb") as held:
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)  # another open file: as another process would hold it
        with pytest.raises(RunError, match=f"^{re.escape(str(out))} is being written by {re.escape(named)}; "):
            with claim(out, "simulate"):
                pass
    assert lock.read_bytes() == content  # the holder's lock file untouched

"""The run-folder guard (:mod:`lanefree_sumo.experiments.rundir`): which earlier output ``--overwrite``
may replace, which files a run folder owns, and the atomic replacement (files made by hand, no SUMO)."""

from __future__ import annotations

from pathlib import Path

import pytest

from lanefree_sumo.errors import RunError
from lanefree_sumo.experiments.rundir import (
    OUTPUT_MARKER,
    check_new_file,
    check_replaceable,
    fresh_output,
    new_file,
)


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
    with pytest.raises(ValueError), new_file(path) as tmp:
        tmp.write_text("half")
        raise ValueError("cut")
    assert path.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["table.csv"]
    with new_file(path) as tmp:
        assert tmp.parent == tmp_path and tmp != path
        tmp.write_text("new")
    assert path.read_text() == "new" and sorted(p.name for p in tmp_path.iterdir()) == ["table.csv"]

"""No command destroys a result, and every mistake gets one clear line (issue: data safety).

One test per data-loss case found by probing the verbs; each failed on the code before the fix.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

import pytest
import yaml

from lanefree_sumo.config import LaneFreeConfig, merge_config
from lanefree_sumo.errors import LaneFreeError, RunError
from lanefree_sumo.experiments.runners.evaluate import evaluate
from lanefree_sumo.experiments.runners.session import new_run_folder
from lanefree_sumo.experiments.runners.train import train
from lanefree_sumo.experiments.storage.rundir import OUTPUT_MARKER, RunDir, fresh_output, read_config, write_config

from conftest import CLI_ENV, TINY_TRAINING, lanefree, lanefree_popen, wait_for

pytestmark = pytest.mark.sumo


def tiny(episodes: int = 2, algo: str = "dqn", **extra) -> LaneFreeConfig:
    """A run of ``episodes`` episodes of 100 steps (DQN: a batch of one; SAC: SB3's loop)."""
    train_cfg = {**TINY_TRAINING["train"], "algo": algo, "episodes": episodes}
    return merge_config(LaneFreeConfig(), {**TINY_TRAINING, **extra, "train": train_cfg})


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` with its bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> Path:
    run, done = train(tiny(), run=tmp_path_factory.mktemp("finished") / "run", progress=False)
    assert done == 2
    return run


# -- 1. resuming a finished run --------------------------------------------------------------------

@pytest.mark.slow
def test_resume_of_a_finished_run_changes_nothing_and_extending_is_explicit(tmp_path, finished_run):
    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    before = snapshot(run)
    with pytest.raises(RunError, match="is finished .* pass --episodes N"):
        train(LaneFreeConfig(), run=run, resume=True, progress=False)
    assert snapshot(run) == before
    res = lanefree("train", "--resume", str(run), "--density", "90")
    assert res.returncode == 2 and "--density cannot be changed" in res.stderr and res.stderr.count("\n") == 1
    assert snapshot(run) == before
    _, done = train(LaneFreeConfig(), run=run, resume=True, progress=False, episodes=3)
    assert done == 3 and read_config(run).train.episodes == 3
    episodes = [line.split(",")[0] for line in (run / "episodes.csv").read_text().splitlines()[1:]]
    assert episodes == ["1", "2", "3"]


def test_a_run_has_one_writer_at_a_time(tmp_path, finished_run):
    """While a process trains a run (holds its writer lock), a second training of it is one line naming that
    process, and changes nothing; the lock is free again when the holder ends."""
    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    before = snapshot(run)
    with RunDir(run).writer_lock():
        res = lanefree("train", "--resume", str(run), "--episodes", "3")
        assert res.returncode != 0 and res.stderr.count("\n") == 1, res.stderr
        assert f"being written by process {os.getpid()}" in res.stderr and "Traceback" not in res.stderr
    assert {k: v for k, v in snapshot(run).items() if k != ".lock"} == {
        k: v for k, v in before.items() if k != ".lock"}
    _, done = train(LaneFreeConfig(), run=run, resume=True, progress=False, episodes=3)
    assert done == 3


# -- 2. --overwrite never removes what is not its own output ---------------------------------------

def test_evaluate_overwrite_refuses_a_run_folder_and_the_current_folder(tmp_path, finished_run, monkeypatch):
    before = snapshot(finished_run)
    with pytest.raises(RunError, match="training run folder"):
        evaluate(finished_run, episodes=1, out=finished_run, overwrite=True, progress=False)
    assert snapshot(finished_run) == before
    data = tmp_path / "data.csv"
    data.write_text("precious\n")
    sub = tmp_path / "sub"
    sub.mkdir()
    monkeypatch.chdir(sub)
    res = lanefree("simulate", "--seconds", "1", "--out", "..", "--overwrite", cwd=sub)
    assert res.returncode == 2 and "current folder or one of its parents" in res.stderr
    assert data.read_text() == "precious\n"
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    res = lanefree("simulate", "--seconds", "1", "--out", str(foreign), "--overwrite")
    assert res.returncode == 2 and "not the output of an earlier 'lanefree simulate'" in res.stderr
    assert (foreign / "notes.txt").read_text() == "mine"


# -- 3. a failing new output leaves the old one ----------------------------------------------------

def test_overwrite_that_fails_keeps_the_previous_output(tmp_path):
    out = tmp_path / "sim"
    assert lanefree("simulate", "--seconds", "2", "--out", str(out)).returncode == 0
    before = snapshot(out)
    assert (out / OUTPUT_MARKER).read_text().strip() == "simulate"
    bad = tmp_path / "bad.net.xml"
    bad.write_text("<net>")
    res = lanefree("simulate", "--seconds", "2", "--out", str(out), "--overwrite", "--net", str(bad))
    assert res.returncode != 0 and res.stderr.count("\n") == 1
    assert snapshot(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.net.xml", "sim"]  # no temporary left


# -- 4. a corrupt checkpoint is found before episodes.csv is cut ------------------------------------

@pytest.mark.slow
@pytest.mark.parametrize(("algo", "said"), [("dqn", "batch checkpoint .* is unusable"), ("sac", "is corrupt")])
def test_resume_with_a_corrupt_checkpoint_cuts_nothing(tmp_path, algo, said):
    """A batch of one (dqn) resumes from its batch checkpoint, SB3's loop (sac) from the checkpoint's model.zip:
    either damaged, the error names it and episodes.csv is as it was."""
    run, _ = train(tiny(episodes=3, algo=algo), run=tmp_path / "run", progress=False)
    (run / "model.zip").unlink()  # as if interrupted after episode 3 ...
    if algo == "dqn":
        newest = sorted((run / "batch_checkpoints").glob("step_*.pt"))[-1]
        newest.write_bytes(b"garbage")  # ... with a damaged newest checkpoint
    else:
        newest = sorted((run / "checkpoints").glob("ep_*"))[-1]
        (newest / "model.zip").write_bytes(b"garbage")
    rows = (run / "episodes.csv").read_bytes()
    with pytest.raises(RunError, match=said):
        train(LaneFreeConfig(), run=run, resume=True, progress=False, episodes=5)
    assert (run / "episodes.csv").read_bytes() == rows


# -- 5. run folders are unique even within one second ----------------------------------------------

def test_two_runs_started_in_the_same_second_get_different_folders(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    cfg = tiny()
    folders = {new_run_folder(cfg, None) for _ in range(3)}
    assert len(folders) == 3 and all(f.is_dir() for f in folders)


# -- 6. a cut or wrong config.yaml is refused, naming the key --------------------------------------

def test_truncated_or_wrong_config_is_refused_by_key(tmp_path):
    write_config(tmp_path, LaneFreeConfig())
    text = (tmp_path / "config.yaml").read_text()
    (tmp_path / "config.yaml").write_text(text[: text.rindex("\n", 0, len(text) // 3) + 1])  # cut at a line end
    with pytest.raises(RunError, match="key '.*' .*missing"):
        read_config(tmp_path)
    data = yaml.safe_load(text)
    data["seed"] = "zero"
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(RunError, match="'seed' must be a whole number"):
        read_config(tmp_path)
    (tmp_path / "config.yaml").write_bytes(bytes(range(256)) * 4)
    with pytest.raises(RunError, match="unusable"):
        read_config(tmp_path)


# -- 7. a failed start leaves nothing that blocks a retry ------------------------------------------

def test_a_start_that_fails_leaves_no_run_folder(tmp_path):
    bad = tmp_path / "bad.net.xml"
    bad.write_text("<net>")
    run = tmp_path / "run"
    in_sumo = merge_config(tiny(net_file=str(bad)), {"train": {"backend": "libsumo"}})
    with pytest.raises(LaneFreeError):  # SUMO cannot read the network: fails before the first episode
        train(in_sumo, run=run, progress=False)
    assert not run.exists()
    res = lanefree("train", "--density", "5000", "--episodes", "1", "--out", str(run))
    assert res.returncode == 2 and "veh/km" in res.stderr and not run.exists()


# -- clear one-line errors -------------------------------------------------------------------------

@pytest.mark.parametrize("args,needle", [
    (("--seed", "-1"), "'seed' = -1 is out of range"),
    (("--seed", str(2**31)), "'seed' = 2147483648 is out of range"),
    (("--length", "1e300"), "'road.length_m' = 1e+300 is out of range"),
    (("--width", "0.001"), "'road.width_m' = 0.001 is out of range"),
    (("--seconds", "0.1"), "shorter than one step"),
])
def test_out_of_range_values_get_one_line(tmp_path, args, needle):
    res = lanefree("simulate", "--out", str(tmp_path / "o"), *args)
    assert res.returncode == 2 and needle in res.stderr and res.stderr.count("\n") == 1
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_evaluation_stopped_mid_episode_keeps_only_complete_episodes(finished_run, tmp_path):
    out = tmp_path / "eval"
    proc = lanefree_popen("evaluate", str(finished_run), "--episodes", "500", "--record", "--out", str(out))
    wait_for_new_episode(tmp_path, ".eval.new-*", proc)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and "kept" in err, err
    episodes = (out / "episodes.csv").read_text().splitlines()[1:]
    recordings = sorted((out / "trajectories").glob("episode_*[0-9].csv"))
    assert 0 < len(episodes) == len(recordings) < 500
    vehicles = len((out / "trajectories" / "episode_0001.vehicles.csv").read_text().splitlines()) - 1
    for path in recordings:  # every kept recording is whole: 100 steps + the initial state
        assert len(path.read_text().splitlines()) - 1 == 101 * vehicles


def wait_for_new_episode(folder: Path, pattern: str, proc, episodes: int = 1) -> None:
    """Wait (for a state, not a time) until the output being written in ``folder/pattern`` holds ``episodes``
    complete episodes; fail if the process ends first."""
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline:
        for csv_path in folder.glob(f"{pattern}/episodes.csv"):
            if len(csv_path.read_text().splitlines()) > episodes:
                return
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.1)
    raise AssertionError("no episode was written within 300 s")


def test_an_interrupted_overwrite_keeps_the_earlier_evaluation(finished_run, tmp_path):
    out = tmp_path / "eval"
    evaluate(finished_run, episodes=2, out=out, progress=False)
    before = snapshot(out)
    proc = lanefree_popen("evaluate", str(finished_run), "--episodes", "500", "--out", str(out), "--overwrite")
    wait_for_new_episode(tmp_path, ".eval.new-*", proc)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and "the earlier evaluation" in err and "is kept" in err, err
    assert snapshot(out) == before
    assert not list(tmp_path.glob(".eval.*"))  # the incomplete replacement is gone


def test_operating_system_limits_and_impossible_requests_are_one_line(tmp_path):
    """An OSError (here a name longer than the file system allows) is the environment's limit, not a bug:
    one line naming it and what to do, exit 1; a process count no machine has is refused before spawning."""
    long_name = tmp_path / ("x" * 300)
    res = lanefree("simulate", "--seconds", "1", "--backend", "numpy", "--out", str(long_name))
    assert res.returncode == 1 and res.stderr.count("\n") == 1, res.stderr
    assert "File name too long" in res.stderr and "shorter name" in res.stderr and "internal error" not in res.stderr
    res = lanefree("train", "--algo", "ppo", "--envs", "1000", "--episodes", "1", "--out", str(tmp_path / "many"))
    assert res.returncode == 2 and "use at most" in res.stderr and res.stderr.count("\n") == 1
    assert not (tmp_path / "many").exists()
    res = lanefree("train", "--algo", "dqn", "--envs", "2", "--backend", "traci", "--episodes", "1",
                   "--out", str(tmp_path / "inside"))  # libsumo holds one simulation per process
    assert res.returncode == 2 and res.stderr.count("\n") == 1, res.stderr
    assert "dqn does not train several environments (--envs) inside SUMO (--backend traci)" in res.stderr
    assert "--backend numpy (the same episodes)" in res.stderr and not (tmp_path / "inside").exists()


def test_every_committed_run_config_still_loads():
    """Config keys added since (e.g. scenario.agents) take their defaults in older saved configs: every
    config.yaml committed under results/ loads, so reports and resumes of earlier runs keep working."""
    root = Path(__file__).resolve().parents[2] / "results"
    configs = sorted(root.rglob("config.yaml"))
    assert len(configs) >= 10
    for path in configs:
        cfg = read_config(path.parent)
        assert cfg.scenario.agents >= 1 and cfg.train.episodes >= 1, path


# -- 8. an output is claimed when its verb starts ---------------------------------------------------

def test_a_second_writer_of_the_same_output_is_refused_while_the_first_runs(tmp_path):
    """Two simulations into one --out: the second is refused at once (with --overwrite too), naming the first's
    process; the first one's output is what ends up there."""
    out = tmp_path / "s"
    first = lanefree_popen("simulate", "--seconds", "4000", "--seed", "1", "--backend", "numpy", "--out", str(out))
    wait_for(lambda: any(tmp_path.glob(".s.new-*/trajectory.csv")), first, "the first simulation writing")
    for extra in ((), ("--overwrite",)):
        res = lanefree("simulate", "--seconds", "5", "--seed", "2", "--backend", "numpy", "--out", str(out), *extra)
        assert res.returncode == 2 and res.stderr.count("\n") == 1, res.stderr
        assert f"being written by process {first.pid}" in res.stderr
    first.send_signal(signal.SIGTERM)
    _, err = first.communicate(timeout=120)
    assert first.returncode == 130, err
    assert read_config(out).seed == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s"]  # neither a lock file nor a temporary left


def test_evaluate_and_mixed_autonomy_refuse_an_output_another_process_writes(tmp_path, finished_run):
    """The claim is one mechanism for every verb with an --out: held by another process, evaluate and
    mixed-autonomy are refused before writing anything."""
    out = tmp_path / "eval"
    holder = subprocess.Popen([sys.executable, "-c", textwrap.dedent(f"""
        import sys, time
        from pathlib import Path
        from lanefree_sumo.experiments.storage.rundir import claim
        with claim(Path({str(out)!r}), "evaluate"):
            print("held", flush=True)
            sys.stdin.read()
        """)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=CLI_ENV)
    try:
        assert holder.stdout is not None and holder.stdout.readline() == "held\n"
        with pytest.raises(RunError, match=f"being written by process {holder.pid}"):
            evaluate(finished_run, episodes=1, out=out, progress=False)
        res = lanefree("mixed-autonomy", str(finished_run), "--agents", "0", "--episodes", "1", "--out", str(out))
        assert res.returncode == 2 and f"being written by process {holder.pid}" in res.stderr, res.stderr
        assert not out.exists()
    finally:
        holder.communicate("", timeout=60)
    evaluate(finished_run, episodes=1, out=out, progress=False)  # released with its process
    assert (out / "episodes.csv").is_file()


def test_the_final_swap_never_replaces_what_the_verb_did_not_claim(tmp_path):
    """An output that another program put in place while the verb wrote is left alone; the verb's own output is
    kept beside it under the name its one-line error gives."""
    out = tmp_path / "out"
    with pytest.raises(RunError, match=r"made or replaced by another program.*out\.simulate-1"):
        with fresh_output(out, overwrite=False, verb="simulate") as tmp:
            (tmp / "summary.json").write_text("new\n")
            out.mkdir()
            (out / "notes.txt").write_text("mine\n")
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    assert (tmp_path / "out.simulate-1" / "summary.json").read_text() == "new\n"


# -- 9. the leftovers of a killed writer are cleaned by the next one --------------------------------

def test_a_killed_writers_temporaries_are_removed_by_the_next_writer(tmp_path):
    out = tmp_path / "s"
    first = lanefree_popen("simulate", "--seconds", "4000", "--backend", "numpy", "--out", str(out))
    wait_for(lambda: any(tmp_path.glob(".s.new-*/trajectory.csv")), first, "the simulation writing")
    first.kill()
    first.communicate(timeout=60)
    assert list(tmp_path.glob(".s.new-*"))  # SIGKILL cleans nothing up
    res = lanefree("simulate", "--seconds", "2", "--backend", "numpy", "--out", str(out))
    assert res.returncode == 0, res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s"]


def test_an_earlier_output_a_dead_writer_left_aside_is_put_back(tmp_path):
    """A writer killed between moving the earlier output aside and moving the new one in leaves only the
    ``.old-`` folder: the next writer puts it back before anything else (its --overwrite then replaces it)."""
    out = tmp_path / "eval"
    aside = tmp_path / ".eval.old-abcd1234" / "eval"
    aside.mkdir(parents=True)
    (aside / OUTPUT_MARKER).write_text("evaluate\n")
    (aside / "episodes.csv").write_text("episode\n1\n")
    (tmp_path / ".eval.new-zyxw9876").mkdir()
    (tmp_path / ".eval.lock").write_text("999999 evaluate\n")  # its lock file, no longer locked by anyone
    with pytest.raises(RunError, match="exists; choose another --out"):
        with fresh_output(out, overwrite=False, verb="evaluate"):
            pass
    assert (out / "episodes.csv").read_text() == "episode\n1\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["eval"]


# -- 10. a resumed run's paths follow its folder ----------------------------------------------------

def tb_files(folder: Path) -> set[str]:
    return {str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file()}


@pytest.mark.slow
def test_a_resumed_copy_writes_its_tensorboard_logs_into_itself(tmp_path, finished_run, monkeypatch):
    """A run copied (or renamed, or resumed from another directory by a relative path) writes its TensorBoard
    events into its own ``tb/``: not into the original's, whose path the checkpoint holds, nor into a folder of
    the old name under the current directory (the sweep's workers resume runs the same way)."""
    original = tb_files(finished_run / "tb")
    assert original
    monkeypatch.chdir(tmp_path)
    shutil.copytree(finished_run, tmp_path / "copy")
    _, done = train(LaneFreeConfig(), run=Path("copy"), resume=True, progress=False, episodes=3)
    assert done == 3
    assert tb_files(finished_run / "tb") == original
    assert len(tb_files(tmp_path / "copy" / "tb")) > len(original)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["copy"]


# -- 11. a new run ended before its first checkpoint is no dead end ---------------------------------

@pytest.mark.slow
def test_a_new_run_killed_before_its_first_checkpoint_is_started_afresh(tmp_path):
    """SIGKILL leaves the folder of a run that never checkpointed (nothing to resume): a new start into it
    begins afresh, and --resume says so. A user's folder of like-named files is still refused."""
    run = tmp_path / "run"
    proc = lanefree_popen("train", "--backend", "numpy", "--episodes", "1", "--set", "sim.episode_steps=100000",
                          "--out", str(run))
    wait_for(lambda: (run / "versions.json").is_file(), proc, "the run folder set up")
    proc.kill()
    proc.communicate(timeout=60)
    assert (run / ".lock").exists() and not (run / "checkpoints").exists()
    res = lanefree("train", "--resume", str(run))
    assert res.returncode == 2 and "never reached its first" in res.stderr and "no --resume" in res.stderr
    _, done = train(tiny(episodes=1), run=run, progress=False)
    assert done == 1 and (run / "model.zip").is_file() and read_config(run).sim.episode_steps == 100
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "config.yaml").write_text("my notes\n")
    with pytest.raises(RunError, match="exists; resume it"):
        train(tiny(episodes=1), run=mine, progress=False)
    assert (mine / "config.yaml").read_text() == "my notes\n"


@pytest.mark.slow
def test_a_new_run_whose_first_checkpoint_fails_leaves_nothing(tmp_path, monkeypatch):
    """A full disk at the first checkpoint: the error, and no folder that blocks the same command once space is
    freed (nothing in it could be resumed)."""
    import lanefree_sumo.experiments.runners.train as train_module

    def full_disk(_model, folder: RunDir, episodes: int, _algo: str):
        folder.checkpoint(episodes).mkdir(parents=True)
        (folder.checkpoint(episodes) / "model.zip").write_bytes(b"PK")  # cut short: the disk filled up
        raise OSError(28, "No space left on device")

    real = train_module.save_checkpoint
    monkeypatch.setattr(train_module, "save_checkpoint", full_disk)
    run = tmp_path / "run"
    with pytest.raises(OSError, match="No space left"):
        train(tiny(episodes=1, algo="sac"), run=run, progress=False)
    assert not run.exists()
    monkeypatch.setattr(train_module, "save_checkpoint", real)
    _, done = train(tiny(episodes=1, algo="sac"), run=run, progress=False)
    assert done == 1


@pytest.mark.slow
def test_a_batch_of_one_whose_first_checkpoint_fails_leaves_nothing(tmp_path, monkeypatch):
    """The same for a single run trained as a batch of one: the disk fills while its first batch checkpoint is
    written (after episode 1 of 2); one line says so, and no folder is left to block the same command."""
    import torch

    from lanefree_sumo.errors import OperatingSystemError

    save = torch.save

    def full_disk(obj: Any, path: Any, *args: Any, **kwargs: Any) -> None:
        if not str(path).endswith(".pt.tmp"):  # a model.zip's parts, written by SB3
            return save(obj, path, *args, **kwargs)
        Path(path).write_bytes(b"half")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(torch, "save", full_disk)
    run = tmp_path / "run"
    with pytest.raises(OperatingSystemError, match=r"could not write the batch checkpoint .*No space left") as err:
        train(tiny(episodes=2), run=run, progress=False)
    assert "\n" not in str(err.value) and not run.exists()
    monkeypatch.undo()
    _, done = train(tiny(episodes=2), run=run, progress=False)
    assert done == 2

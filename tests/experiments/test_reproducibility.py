"""What repeats, and where: numpy kept on its portable kernels (AVX2 on x86-64) unless the user chose, the kernels
recorded in versions.json, a new run's first episode (no network yet) equal to that of the committed paper run that
another machine trained, and on one machine a whole run with its learning. The learner's floating point (torch and
its BLAS) is the CPU's: a committed run's later episodes need not repeat on another CPU (docs/training.md)."""

from __future__ import annotations

import csv
import json
import os
import platform
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from lanefree_sumo.numerics import MKL_REPRODUCIBLE, MKL_VARIABLE, PORTABLE_NUMPY_DISPATCH, PROBE_CACHE, VARIABLE

from conftest import ROOT, lanefree_popen, wait_for

pytestmark = pytest.mark.slow
# what the cross-machine tests hold to (numpy's x86-64 kernel tiers, episodes trained on an x86-64 machine) has no
# counterpart on another architecture, whose numpy rounds exp/log its own way: not a missing dependency
x86_64_only = pytest.mark.skipif(platform.machine().lower() not in ("x86_64", "amd64"),
                                 reason="the committed runs and numpy's kernel tiers are x86-64's")


def _rows(path: Path, n: int) -> list[dict[str, str]]:
    """The first ``n`` rows of an episodes.csv, every column but wall time."""
    with open(path, newline="") as fh:
        return [{k: v for k, v in row.items() if k != "wall_s"} for row in csv.DictReader(fh)][:n]


def _python(code: str, **env: str) -> list[str]:
    """The lines a fresh interpreter prints, run without the suite's own numpy setting plus ``env``."""
    base = {k: v for k, v in os.environ.items() if k != VARIABLE}
    out = subprocess.run([sys.executable, "-c", code], env={**base, **env}, capture_output=True, text=True,
                         check=True, cwd=ROOT)
    return out.stdout.splitlines()


def _kernels(**env: str) -> tuple[set[str], str]:
    """(numpy's kernel tiers, the variable a child process sees) in a fresh interpreter that imports the package
    first, as ``lanefree`` does."""
    lines = _python("import os, subprocess, sys, lanefree_sumo, numpy\n"
                    "from lanefree_sumo.experiments.runners.session import numpy_simd\nprint(numpy_simd())\n"
                    f"print(subprocess.run([sys.executable, '-c', 'import os; print(os.environ.get(\"{VARIABLE}\"))'],"
                    " capture_output=True, text=True).stdout.strip())", **env)
    return set(lines[0].split()), lines[1]


def _cpu_has_avx512() -> bool:
    """The CPU offers x86-64-v4 (AVX-512 F, CD, VL, BW, DQ), read from /proc/cpuinfo."""
    flags = set(Path("/proc/cpuinfo").read_text().split("flags", 1)[1].split("\n", 1)[0].split())
    return {"avx512f", "avx512cd", "avx512vl", "avx512bw", "avx512dq"} <= flags


@x86_64_only
def test_numpy_keeps_portable_kernels_unless_the_user_chose() -> None:
    (pinned, child), (own, own_child) = _kernels(), _kernels(**{VARIABLE: ""})
    assert "X86_V3" in pinned and not set(PORTABLE_NUMPY_DISPATCH.split()) & pinned
    assert child == PORTABLE_NUMPY_DISPATCH  # sweep workers and env processes inherit it
    assert ("X86_V4" in own) is _cpu_has_avx512() and own_child == ""  # the user's empty setting: the whole CPU


def test_mkl_is_kept_reproducible_unless_the_user_chose_or_torch_came_first() -> None:
    """Importing the package sets MKL's conditional numerical reproducibility for itself and its child processes
    (sweep workers); a user's own setting stays, and so does torch's state when torch was imported first (its MKL
    may have read the variable already)."""
    child = (f"import os, subprocess, sys\nprint(os.environ.get('{MKL_VARIABLE}'))\n"
             f"print(subprocess.run([sys.executable, '-c', 'import os; print(os.environ.get(\"{MKL_VARIABLE}\"))'],"
             " capture_output=True, text=True).stdout.strip())")
    env = {k: v for k, v in os.environ.items() if k != MKL_VARIABLE}
    runs = {name: subprocess.run([sys.executable, "-c", first + child], capture_output=True, text=True, check=True,
                                 cwd=ROOT, env={**env, **extra}).stdout.splitlines()
            for name, first, extra in (("package", "import lanefree_sumo\n", {}),
                                       ("user", "import lanefree_sumo\n", {MKL_VARIABLE: "AVX2"}),
                                       ("torch first", "import torch, lanefree_sumo\n", {}))}
    assert runs == {"package": [MKL_REPRODUCIBLE, MKL_REPRODUCIBLE], "user": ["AVX2", "AVX2"],
                    "torch first": ["None", "None"]}


@x86_64_only
def test_a_numpy_that_cannot_switch_a_tier_off_keeps_its_kernels() -> None:
    """numpy refuses to switch off a tier of its baseline (a build for a newer CPU): the setting is withdrawn
    and numpy imports with its own kernels instead of failing."""
    lines = _python("import os, runpy\n"
                    "keep = runpy.run_path('lanefree_sumo/numerics.py')['keep_numpy_portable']\n"
                    f"print(keep('X86_V2'), os.environ.get('{VARIABLE}'))\n"
                    "import numpy\nprint(int(numpy.ones(3).sum()))")
    assert lines == ["False ", "3"]  # set empty: numpy's own kernels, and child processes do not ask again


@x86_64_only
def test_the_probe_is_asked_once_per_numpy_installation_and_a_damaged_cache_asks_again(tmp_path: Path) -> None:
    """The child interpreter's answer is kept per numpy installation: the next start reads it (a kept "no" gives
    numpy's own kernels without asking), and an unreadable cache is asked again and rewritten."""
    setting = f"import os, lanefree_sumo\nprint(repr(os.environ['{VARIABLE}']))"
    cache = tmp_path / "lanefree_sumo" / PROBE_CACHE
    assert _python(setting, XDG_CACHE_HOME=str(tmp_path)) == [repr(PORTABLE_NUMPY_DISPATCH)]
    kept = json.loads(cache.read_text())
    assert list(kept.values()) == [True] and f"|{PORTABLE_NUMPY_DISPATCH}|" in next(iter(kept))
    cache.write_text(json.dumps(dict.fromkeys(kept, False)))  # as a numpy whose baseline has the tiers
    assert _python(setting, XDG_CACHE_HOME=str(tmp_path)) == ["''"]
    cache.write_text("{not json")
    assert _python(setting, XDG_CACHE_HOME=str(tmp_path)) == [repr(PORTABLE_NUMPY_DISPATCH)]
    assert json.loads(cache.read_text()) == kept


def _stopped_run(out: Path, algo: str, episodes: int, *options: str) -> list[dict[str, str]]:
    """Seed 0 of the paper's 625-episode ``algo`` fields_zones_overtake_collision run at 70 veh/km (plus
    ``options``), stopped with Ctrl-C once ``episodes`` episodes are logged: those rows, every column but wall
    time. The budget stays 625 episodes, since the DQN family's epsilon schedule is a fraction of it."""
    proc = lanefree_popen("train", "--algo", algo, "--reward", "fields_zones_overtake_collision", "--density", "70",
                          "--seed", "0", "--episodes", "625", "--out", str(out), *options)
    log = out / "episodes.csv"
    wait_for(lambda: log.is_file() and len(log.read_text().splitlines()) > episodes, proc, f"{episodes} episodes")
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    return _rows(log, episodes)


@x86_64_only
@pytest.mark.parametrize("algo", ["ddpg", "dqn"])
def test_a_new_runs_first_episode_repeats_the_committed_run_of_another_machine(algo: str, tmp_path: Path) -> None:
    """The first episode (the random warm-up: traffic, rewards and forces, no network) equals, in every column but
    wall time, that of the committed paper run another machine trained (DDPG's on an AVX2 machine, DQN's on an earlier
    one): numpy's portable kernels make the environment repeat across machines (with numpy's AVX-512 kernels
    DDPG's episode 1 has 4 collisions against 5). versions.json names the kernels."""
    out = tmp_path / "run"
    committed = _rows(ROOT / f"results/paper/runs/{algo}_fields_zones_overtake_collision_d70_s0/episodes.csv", 1)
    new = _stopped_run(out, algo, 1)
    assert len(committed[0]) == 20 < len(new[0])  # the committed run predates the speed readings and return parts
    assert [{k: row[k] for k in committed[0]} for row in new] == committed
    versions = json.loads((out / "versions.json").read_text())
    assert "X86_V3" in versions["numpy_simd"].split() and "X86_V4" not in versions["numpy_simd"].split()
    assert versions["torch_cpu"] and versions["cpu"]


def test_a_run_repeats_itself_on_one_machine_learning_included(tmp_path: Path) -> None:
    """Two DDPG runs of one config on one machine give the same episodes, every column but wall time: the first
    (random actions) and the second (800 updates, then the actor's actions with OU noise)."""
    first, second = (_stopped_run(tmp_path / name, "ddpg", 2) for name in ("a", "b"))
    assert first == second and first[1]["timesteps"] == "1600"


def test_a_batch_of_one_repeats_the_dqn_run_of_sb3s_loop(tmp_path: Path, monkeypatch) -> None:
    """The DQN run of ``lanefree train`` (a batch of one: the batched learner) and the same run in SB3's loop with
    stock SB3's ``DQN`` (what SAC and PPO train in; here in this process) give the same first two episodes, every
    column but wall time: episode 2 acts on 800 updates (the first episode fills the buffer). The variants SB3 lacks
    are held by their golden files (``tests/experiments/test_golden_runs.py``)."""
    algo = "dqn"
    from lanefree_sumo.config import LaneFreeConfig, merge_config
    from lanefree_sumo.experiments.runners import train as runner
    from lanefree_sumo.experiments.storage.rundir import RunDir
    from lanefree_sumo.rl.models import training_config

    batched = _stopped_run(tmp_path / "batched", algo, 2)
    assert json.loads((tmp_path / "batched" / "batch.json").read_text()) == {"runs": ["."]}
    make_callback = runner._make_callback

    def stopping_after_two(run, cfg, log, done, stop, progress):  # Ctrl-C once two episodes are logged
        callback = make_callback(run, cfg, log, done, stop, progress)
        on_step = callback._on_step

        def _on_step() -> bool:
            stop.requested = stop.requested or callback.episodes >= 2
            return on_step()

        callback._on_step = _on_step
        return callback

    monkeypatch.setattr(runner, "_make_callback", stopping_after_two)
    cfg = training_config(merge_config(LaneFreeConfig(), {
        "seed": 0, "scenario": {"density_veh_per_km": 70}, "reward": {"preset": "fields_zones_overtake_collision"},
        "train": {"algo": algo, "episodes": 625}}))
    folder = tmp_path / "sb3_loop"
    folder.mkdir()
    assert runner._train_session(cfg, RunDir(folder), None, 0, 625, False, "test") == (folder, 2)
    assert not (folder / "batch.json").exists()
    assert batched == _rows(folder / "episodes.csv", 2)

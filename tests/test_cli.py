"""``lanefree`` end to end in a subprocess: outputs, JSON summary, and one-line errors."""

from __future__ import annotations

import csv
import json
import signal
from pathlib import Path

import pytest

from conftest import lanefree, lanefree_popen, wait_for

pytestmark = pytest.mark.sumo


def test_simulate_writes_trajectory_and_json_summary(tmp_path):
    out = tmp_path / "sim"
    res = lanefree("simulate", "--density", "90", "--seconds", "5", "--seed", "0", "--out", str(out), "--json")
    assert res.returncode == 0, res.stderr
    summary = json.loads(res.stdout.strip().splitlines()[-1])
    for key in ("steps", "vehicles", "background_collisions", "mean_speed_mps", "mean_desired_speed_mps",
                "min_lateral_margin_m", "wall_s"):
        assert key in summary
    assert summary["steps"] == 20 and summary["vehicles"] == 45
    assert summary["min_lateral_margin_m"] > 0
    with open(out / "trajectory.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == ["t", "id", "x", "y", "vx", "vy", "ax", "ay"]
    assert len(rows) == 20 * 45
    assert {r["id"] for r in rows} == {f"bg{i}" for i in range(45)}
    assert json.loads((out / "summary.json").read_text()) == summary
    assert "density_veh_per_km: 90.0" in (out / "config.yaml").read_text()
    assert (out / "command.txt").read_text().startswith("lanefree simulate")


def test_same_seed_gives_identical_trajectories(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    for out in (a, b):
        assert lanefree("simulate", "--seconds", "3", "--seed", "4", "--out", str(out)).returncode == 0
    assert (a / "trajectory.csv").read_bytes() == (b / "trajectory.csv").read_bytes()


def test_numpy_backend_matches_sumo_output(tmp_path):
    a, b = tmp_path / "sumo", tmp_path / "numpy"
    assert lanefree("simulate", "--seconds", "10", "--out", str(a)).returncode == 0
    assert lanefree("simulate", "--seconds", "10", "--out", str(b), "--backend", "numpy").returncode == 0
    assert (a / "trajectory.csv").read_bytes() == (b / "trajectory.csv").read_bytes()


@pytest.mark.parametrize(
    "args,needle",
    [
        (["--density", "abc"], "density must be a number"),
        (["--density", "0"], "positive finite"),
        (["--density", "-3"], "positive finite"),
        (["--density", "nan"], "positive finite"),
        (["--density", "5000"], "the maximum is"),
        (["--frobnicate"], "lanefree simulate: unrecognized arguments: --frobnicate (see 'lanefree simulate --help')"),
        (["--seconds", "x"], "expected a number in s"),
        (["--net", "/no/such/file.net.xml"], "does not exist"),
    ],
)
def test_bad_input_is_one_line_and_nonzero(tmp_path, args, needle):
    res = lanefree("simulate", "--seconds", "1", "--out", str(tmp_path / "o"), *args)
    assert res.returncode != 0
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    assert needle in lines[0]
    assert "Traceback" not in res.stderr


def test_an_unknown_option_is_named_by_the_parser_it_was_given_to():
    before = lanefree("--frobnicate", "simulate")
    assert before.returncode == 2
    assert before.stderr.strip() == ("lanefree: error: lanefree: unrecognized arguments: --frobnicate "
                                     "(see 'lanefree --help')")
    after = lanefree("report", "a", "--frobnicate", "b")  # between a verb's positional arguments
    assert after.returncode == 2 and "lanefree report: unrecognized arguments: --frobnicate b" in after.stderr


def test_corrupt_network_is_one_line(tmp_path):
    bad = tmp_path / "bad.net.xml"
    bad.write_text("not xml at all <<<")
    res = lanefree("simulate", "--seconds", "1", "--out", str(tmp_path / "o"), "--net", str(bad))
    assert res.returncode == 1
    assert res.stderr.strip().count("\n") == 0 and "not a readable SUMO network" in res.stderr


def test_existing_output_is_refused_unless_overwrite(tmp_path):
    out = tmp_path / "o"
    out.mkdir()
    (out / "keep.txt").write_text("precious")
    res = lanefree("simulate", "--seconds", "1", "--out", str(out))
    assert res.returncode == 2 and "--overwrite" in res.stderr
    assert (out / "keep.txt").read_text() == "precious"
    res = lanefree("simulate", "--seconds", "1", "--out", str(out), "--overwrite")  # not a simulate output
    assert res.returncode == 2 and (out / "keep.txt").read_text() == "precious"
    sim = tmp_path / "sim"
    assert lanefree("simulate", "--seconds", "1", "--out", str(sim)).returncode == 0
    res = lanefree("simulate", "--seconds", "2", "--out", str(sim), "--overwrite")
    assert res.returncode == 0 and '"steps": 8' in (sim / "summary.json").read_text()


def test_net_command_builds_a_ring(tmp_path):
    res = lanefree("net", "--length", "300", "--width", "7", "--out-dir", str(tmp_path))
    assert res.returncode == 0, res.stderr
    net = Path(res.stdout.strip().splitlines()[-1])
    assert net.exists() and net.name == "ring_L300_W7.net.xml"
    res = lanefree("simulate", "--seconds", "2", "--density", "70", "--length", "300", "--width", "7",
                   "--net", str(net), "--out", str(tmp_path / "o"), "--json")
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout.strip().splitlines()[-1])["vehicles"] == 21


def test_help_explains_units():
    res = lanefree("simulate", "--help")
    assert res.returncode == 0
    assert "veh/km" in res.stdout and "in s" in res.stdout


def test_output_under_a_file_is_refused_before_simulating(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    res = lanefree("simulate", "--seconds", "1", "--out", str(blocker / "sim"))
    assert res.returncode == 2 and "cannot write" in res.stderr and res.stderr.count("\n") == 1
    assert blocker.read_text() == "x"


@pytest.mark.slow
def test_sigterm_stops_simulate_like_ctrl_c(tmp_path):
    out = tmp_path / "sim"
    proc = lanefree_popen("simulate", "--seconds", "5000", "--out", str(out))
    wait_for(lambda: any(p.stat().st_size > 0 for p in tmp_path.glob(".sim.new-*/trajectory.csv")), proc,
             "a trajectory being written")
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    summary = json.loads((out / "summary.json").read_text())
    assert proc.returncode == 130 and summary["interrupted"] and 0 < summary["steps"] < 20000
    assert not list(tmp_path.glob(".sim.*"))  # no temporary folder left


def test_any_config_value_from_the_command_line(tmp_path):
    """--set KEY=VALUE and --config FILE reach the run's config.yaml (file < options given < --set); a bad
    key or value is one line naming it; 'lanefree config' prints the resolved config with meanings."""
    import yaml

    run = tmp_path / "run"
    res = lanefree("train", "--episodes", "1", "--episode-steps", "40", "--out", str(run),
                   "--set", "reward.broad_stretch=absolute", "--set", "train.actor_critic.learning_starts_steps=20")
    assert res.returncode == 0, res.stderr
    saved = yaml.safe_load((run / "config.yaml").read_text())
    assert saved["reward"]["broad_stretch"] == "absolute"
    assert saved["train"]["actor_critic"]["learning_starts_steps"] == 20
    assert "--set reward.broad_stretch=absolute" in (run / "command.txt").read_text()

    for setting, needle in (("reward.nope=1", "unknown config key 'reward.nope'"),
                            ("reward.broad_stretch=sideways", "reward.broad_stretch"),
                            ("seed=-3", "seed"), ("reward", "not KEY=VALUE")):
        res = lanefree("train", "--episodes", "1", "--out", str(tmp_path / "bad"), "--set", setting)
        assert res.returncode == 2 and needle in res.stderr and res.stderr.count("\n") == 1, (setting, res.stderr)
        assert not (tmp_path / "bad").exists()

    file = tmp_path / "mine.yaml"
    file.write_text(yaml.safe_dump({"seed": 7, "scenario": {"density_veh_per_km": 90}, "reward": {"epsilon_r": 0.2}}))
    res = lanefree("config", "--config", str(file), "--set", "seed=8")
    assert res.returncode == 0, res.stderr
    printed = yaml.safe_load(res.stdout)  # the comments are YAML comments: it loads back
    assert printed["seed"] == 8 and printed["scenario"]["density_veh_per_km"] == 90
    assert printed["reward"]["epsilon_r"] == 0.2
    assert "length_m: 500.0  # Centre-line length" in res.stdout and "road.onramp``; 50 … 10000" in res.stdout
    res = lanefree("simulate", "--config", str(file), "--density", "70", "--seconds", "1", "--backend", "numpy",
                   "--out", str(tmp_path / "sim"))
    assert res.returncode == 0, res.stderr
    sim = yaml.safe_load((tmp_path / "sim" / "config.yaml").read_text())
    assert sim["seed"] == 7 and sim["scenario"]["density_veh_per_km"] == 70  # the option given beats the file
    file.write_text("- a list")
    res = lanefree("config", "--config", str(file))
    assert res.returncode == 2 and "must hold a mapping" in res.stderr


def test_rollout_takes_set_too():
    res = lanefree("rollout", "--episodes", "1", "--backend", "numpy", "--set", "sim.episode_steps=30",
                   "--set", "scenario.density_veh_per_km=90", "--json")
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout.splitlines()[-1])["density"] == 90
    res = lanefree("rollout", "--set", "shield.nope=1")
    assert res.returncode == 2 and "shield.nope" in res.stderr


def test_rollouts_summary_line_counts_one_episode_in_the_singular():
    res = lanefree("rollout", "--episodes", "1", "--backend", "numpy", "--set", "sim.episode_steps=20")
    assert res.returncode == 0, res.stderr
    assert res.stdout.splitlines()[-1].startswith("1 episode at 70 veh/km, policy random"), res.stdout


def test_sigterm_stops_rollout_with_the_summary_of_complete_episodes():
    proc = lanefree_popen("rollout", "--episodes", "100000", "--backend", "numpy", "--json")
    assert proc.stdout is not None
    header = proc.stdout.readline()  # the column header, then one row per finished episode: wait for a row
    assert "episode" in header
    first = proc.stdout.readline()
    assert first.split()[0] == "1", first
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    summary = json.loads(out.splitlines()[-1])
    assert summary["interrupted"] is True and summary["episodes"] >= 1
    assert "complete episode" in err and "Traceback" not in err


def test_simulate_names_its_default_folder_after_the_scenario(tmp_path):
    """A ring run and an on-ramp run of the same density and seed get two folders: neither refuses the other."""
    for scenario in ("ring", "onramp"):
        res = lanefree("simulate", "--scenario", scenario, "--seconds", "1", "--backend", "numpy", cwd=tmp_path)
        assert res.returncode == 0, res.stderr
    assert sorted(p.name for p in (tmp_path / "runs").iterdir()) == ["sim-d70-s0", "sim-onramp-d70-s0"]


def test_train_resume_and_evaluate_say_what_they_did(tmp_path):
    run = tmp_path / "run"
    res = lanefree("train", "--episodes", "1", "--episode-steps", "20", "--backend", "numpy", "--out", str(run))
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip().splitlines()[-1] == f"trained 1 episode -> {run}"
    res = lanefree("train", "--resume", str(run), "--episodes", "3")
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip().splitlines()[-1] == f"trained 2 episodes (3 of 3 in all) -> {run}"
    res = lanefree("evaluate", str(run), "--episodes", "2")
    assert res.returncode == 0, res.stderr
    line = res.stdout.strip().splitlines()[-1]
    assert line.startswith("evaluated 2 episodes: ") and " agent collisions per episode, speed deviation " in line
    assert line.endswith(f"-> {run / 'eval' / 'episodes.csv'}")


@pytest.mark.parametrize(
    "args,needle",
    [
        (["--seeds", "3-1"], "expected seeds as A-B"),
        (["--seeds", "a-b"], "expected seeds as A-B"),
        (["--seeds", "1,1"], "seeds repeat"),
        (["--seeds", "0-1", "--seed", "4"], "--seed and --seeds exclude each other"),
        (["--seeds", "0-1", "--backend", "libsumo"], "does not support the libsumo backend"),
        (["--seeds", "0-1", "--envs", "2", "--backend", "libsumo"],
         "does not train several environments (--envs) inside SUMO (--backend libsumo); train them on --backend "
         "numpy"),
        (["--seeds", "0-1", "--shield", "--device", "cuda"],
         "the safety shield (--shield) train on the CPU (train.device = cpu), not on train.device = cuda; "
         "leave --device out"),
        (["--shield", "--device", "cuda"],  # one run: a batch of one, refused alike
         "the safety shield (--shield) train on the CPU (train.device = cpu), not on train.device = cuda; "
         "leave --device out"),
        (["--seeds", "0-1", "--agents", "2", "--device", "cuda"],
         "runs with several agents (--agents) train on the CPU (train.device = cpu), not on train.device = cuda"),
        (["--seeds", "0-1", "--algo", "td3", "--set", "train.profile=kerasrl"], "td3 takes SB3's uniform warm-up"),
        (["--seeds", "0-1", "--algo", "td3", "--set", "train.actor_critic.pre_tanh_penalty=0.01"],
         "set it to 0 for td3"),
        (["--seeds", "0-1", "--algo", "ppo"], "batched training covers ddpg, td3, dqn, ddqn, dueling, per, not ppo"),
    ],
)
def test_bad_batch_options_are_one_line_and_write_nothing(tmp_path, args, needle):
    out = tmp_path / "batch"
    res = lanefree("train", "--out", str(out), *args)
    assert res.returncode != 0
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], res.stderr
    assert not out.exists()


def test_a_run_of_a_batch_is_resumed_with_its_batch(tmp_path):
    """--resume of one run folder of a batch names the batch to resume instead (its checkpoints are the batch's)."""
    batch = tmp_path / "batch"
    run = batch / "ddpg_fields_zones_overtake_collision_d70_s0"
    run.mkdir(parents=True)
    (batch / "batch.json").write_text('{"runs": ["ddpg_fields_zones_overtake_collision_d70_s0"]}')
    res = lanefree("train", "--resume", str(run))
    assert res.returncode != 0
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and f"lanefree train --resume {batch}" in lines[0], res.stderr

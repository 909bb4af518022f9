"""One line, the last on stderr, for every mistake; options and keys that mean something (issue: data safety)."""

from __future__ import annotations

from pathlib import Path

import pytest

from lanefree_sumo.config import read_config_file
from lanefree_sumo.errors import ConfigError
from lanefree_sumo.experiments.sweep.grid import load_grid

from conftest import lanefree


def last_line_is_the_error(stderr: str) -> str:
    """The error line: stderr's last, on a line of its own (a progress bar's ``\\r`` updates end before it)."""
    assert stderr.endswith("\n"), repr(stderr[-300:])
    last = stderr.split("\n")[-2]
    assert last.startswith("lanefree: error: "), repr(stderr[-300:])
    assert "lanefree: error" not in stderr[: -len(last) - 1], repr(stderr[-300:])
    return last


def test_an_error_inside_a_progress_bar_ends_up_last_on_its_own_line(tmp_path):
    res = lanefree("train", "--scenario", "onramp", "--agents", "64", "--episodes", "1", "--out", str(tmp_path / "r"))
    assert res.returncode == 2
    assert "do not fit" in last_line_is_the_error(res.stderr)
    assert not (tmp_path / "r").exists()


def test_a_key_given_twice_in_a_yaml_file_is_refused(tmp_path):
    config = tmp_path / "c.yaml"
    config.write_text("train:\n  episodes: 3\nsim:\n  step_s: 0.25\ntrain:\n  algo: dqn\n")
    with pytest.raises(ConfigError, match=r"key 'train' is given twice \(lines 1 and 5\)"):
        read_config_file(config)
    config.write_text("train:\n  episodes: 3\n  episodes: 4\n")
    res = lanefree("config", "--config", str(config))
    assert res.returncode == 2 and "key 'episodes' is given twice (lines 2 and 3)" in last_line_is_the_error(
        res.stderr)
    grid = tmp_path / "g.yaml"
    grid.write_text("reward_presets: [collision]\nepisodes: 2\nepisodes: 3\n")
    with pytest.raises(ConfigError, match=rf"^{grid}: key 'episodes' is given twice"):
        load_grid(Path(grid))


@pytest.mark.parametrize("args,needle", [
    (("--scenario", "ring", "--main-flow", "100"), "--main-flow applies to --scenario onramp only"),
    (("--scenario", "ring", "--ramp-flow", "100"), "--ramp-flow applies to --scenario onramp only"),
    (("--scenario", "onramp", "--length", "100"), "--length applies to --scenario ring only"),
    (("--backend", "numpy", "--set", "net_file=sumo_nets/ring_L500_W10.2.net.xml"),
     "the numpy backend uses no SUMO network"),
])
def test_options_that_do_not_apply_are_refused(tmp_path, args, needle):
    res = lanefree("simulate", "--seconds", "1", *args, "--out", str(tmp_path / "o"))
    assert res.returncode == 2 and needle in last_line_is_the_error(res.stderr)
    assert list(tmp_path.iterdir()) == []


def test_the_python_api_takes_numpy_scalars_and_names_a_section_of_another_kind():
    import gymnasium
    import numpy as np

    import lanefree_sumo  # noqa: F401 - registers LaneFree-v0
    from lanefree_sumo.config import LaneFreeConfig, ShieldConfig, merge_config

    cfg = merge_config(LaneFreeConfig(), {"seed": np.int64(3), "scenario": {"density_veh_per_km": np.float32(70.5),
                                                                             "agents": np.int32(2)}})
    assert (cfg.seed, cfg.scenario.density_veh_per_km, cfg.scenario.agents) == (3, 70.5, 2)
    assert type(cfg.seed) is int and type(cfg.scenario.density_veh_per_km) is float
    env = gymnasium.make("LaneFree-v0", config={"backend": "numpy", "seed": np.int64(3)})
    try:
        first, info = env.reset(seed=np.int64(7))
        assert info["episode_seed"] == 7
        np.testing.assert_array_equal(first, env.reset(seed=7)[0])
        with pytest.raises(ValueError, match="seed must be a whole number"):
            env.reset(seed=1.5)
    finally:
        env.close()
    with pytest.raises(ConfigError, match="config 'road' is a RoadConfig section, not a ShieldConfig"):
        merge_config(LaneFreeConfig(), {"road": ShieldConfig()})
    with pytest.raises(ConfigError, match=r"config 'shield.horizon_s' = 0.0 is out of range"):
        merge_config(LaneFreeConfig(), {"shield": ShieldConfig(horizon_s=0.0)})


@pytest.mark.parametrize("actions", [[[0.0, 0.0], [0.0, 0.0]], None])
def test_a_pettingzoo_step_with_a_list_or_none_is_a_clear_error(actions):
    import numpy as np

    from lanefree_sumo.rl.multi_agent import parallel_env

    env = parallel_env({"backend": "numpy", "scenario": {"agents": 2}})
    try:
        env.reset(seed=np.int64(1))
        with pytest.raises(TypeError, match=r"step\(\) takes a dict of one action per live agent"):
            env.step(actions)
    finally:
        env.close()

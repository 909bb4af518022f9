"""The actor probe: feature state-dependence (cosine similarity, varying share of the energy) as pure logic, and
the probe of a real tiny set-encoder DDPG run's untrained actor, checkpoints and final model."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from lanefree_sumo.errors import RunError
from lanefree_sumo.experiments.analysis.actor_probe import feature_dependence, main, probe_markdown, probe_run

from conftest import lanefree


def test_feature_dependence_of_known_matrices():
    same = np.tile([[3.0, 4.0, 0.0]], (5, 1))  # one vector for every state
    assert feature_dependence(same) == pytest.approx((1.0, 0.0))
    basis = np.eye(4)  # orthogonal: cosine 0; the mean (¼ each) is the part common to all
    assert feature_dependence(basis) == pytest.approx((0.0, 3 / 4))
    opposite = np.array([[1.0, 2.0], [-1.0, -2.0]])
    assert feature_dependence(opposite) == pytest.approx((-1.0, 1.0))
    common = np.array([[10.0, 0.0], [10.0, 1.0], [10.0, -1.0]])  # a large common part: cosine near 1
    cosine, varying = feature_dependence(common)
    assert 0.99 < cosine < 1.0 and varying == pytest.approx(2 / 302)
    with pytest.raises(ValueError):
        feature_dependence(np.ones((1, 3)))


@pytest.mark.slow
def test_the_probe_reads_a_set_encoder_runs_actor_at_every_checkpoint(tmp_path):
    run = tmp_path / "run"
    done = lanefree("train", "--obs", "set", "--episodes", "2", "--episode-steps", "30", "--checkpoint-every", "1",
                    "--set", "train.actor_critic.learning_starts_steps=30", "--out", str(run), timeout=600)
    assert done.returncode == 0, done.stderr
    probes = probe_run(run, states=8)
    assert [p.label for p in probes] == ["initial", "ep_00001", "ep_00002", "final"]
    assert [p.timesteps for p in probes] == [0, 30, 60, None]
    for p in probes:
        assert -1.0 <= p.cosine <= 1.0 and 0.0 <= p.varying <= 1.0 and p.median_pre_tanh >= 0.0
        assert 0.0 <= p.at_bound <= 1.0
    assert probes[-1] == replace(probes[-2], label="final", timesteps=None)  # the last checkpoint is the model
    assert probes[2] != probes[0]  # the updates of episode 2 moved the actor
    text = probe_markdown([(run, probes)], 8)
    assert "| ep_00002 | 60 |" in text and "| initial | 0 |" in text
    dqn = tmp_path / "dqn"
    dqn.mkdir()
    (dqn / "config.yaml").write_text((run / "config.yaml").read_text().replace("algo: ddpg", "algo: dqn"))
    with pytest.raises(RunError, match="dqn run"):
        probe_run(dqn, states=8)
    assert main([str(dqn)]) == 2  # one line on stderr, nothing written

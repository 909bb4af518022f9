"""A run's config is resolved once, at the top of the run: the environments (in worker processes too), the
simulation and the learners take the :class:`ResolvedConfig` as it is."""

from __future__ import annotations

import dataclasses
import pickle
from typing import Any

import pytest

from lanefree_sumo.config import LaneFreeConfig, ResolvedConfig, merge_config
from lanefree_sumo.rl.env import LaneFreeEnv, resolve_config
from lanefree_sumo.rl.models import make_vec_env, training_config

from conftest import TINY_TRAINING


def test_a_resolved_config_is_taken_as_it_is_and_a_changed_one_is_resolved_anew():
    resolved = training_config(merge_config(LaneFreeConfig(), {"train": {"algo": "dqn"}}))
    assert type(resolved) is ResolvedConfig
    assert resolved.scenario.with_agent and resolved.action.kind == "discrete"
    assert resolve_config(resolved) is resolved and training_config(resolved) is resolved
    assert LaneFreeEnv(resolved).cfg is resolved  # no backend starts before reset
    copy = pickle.loads(pickle.dumps(resolved))  # as a worker process receives it
    assert type(copy) is ResolvedConfig and copy == resolved and resolve_config(copy) is copy
    changed = merge_config(resolved, {"seed": 3})
    assert type(changed) is LaneFreeConfig and changed.seed == 3
    assert training_config(changed) == dataclasses.replace(resolved, seed=3)
    with pytest.raises(dataclasses.FrozenInstanceError):
        resolved.scenario.density_veh_per_km = 90.0  # type: ignore[misc]
    # a config that training resolves differently (another action kind) is resolved again, not taken as it is
    continuous = training_config(merge_config(resolved, {"train": {"algo": "ddpg"}}))
    assert continuous.action.kind == "continuous" and resolve_config({"seed": 1}).scenario.with_agent


def _counting(monkeypatch: pytest.MonkeyPatch) -> list[Any]:
    """Every resolution (:meth:`ResolvedConfig.of`) from now on, and every whole-config validation in the
    simulation (below the environment), recorded."""
    calls: list[Any] = []
    resolve = ResolvedConfig.of

    def counted(cls: type, cfg: LaneFreeConfig) -> ResolvedConfig:
        calls.append("resolve")
        return resolve(cfg)

    monkeypatch.setattr(ResolvedConfig, "of", classmethod(counted))
    monkeypatch.setattr("lanefree_sumo.sim.simulation.validate_config",
                        lambda cfg, path="": calls.append("validate in the simulation") or cfg)
    return calls


@pytest.mark.slow
@pytest.mark.parametrize(("algo", "on_resume"), [("sac", ["resolve"]), ("ddpg", [])])
def test_a_training_run_resolves_its_config_once(tmp_path, monkeypatch, algo, on_resume):
    """SB3's path (sac) resolves the saved config once when it resumes; a batch of one (ddpg) resolves it once
    when it starts and continues its checkpointed environment, resolving nothing."""
    from lanefree_sumo.experiments.runners.train import train

    cfg = merge_config(LaneFreeConfig(), {**TINY_TRAINING, "backend": "numpy", "sim": {"episode_steps": 30},
                                          "train": {**TINY_TRAINING["train"], "episodes": 1, "backend": "numpy",
                                                    "algo": algo}})
    calls = _counting(monkeypatch)
    _, done = train(cfg, run=tmp_path / "run", progress=False, command="test")
    assert done == 1 and calls == ["resolve"]
    calls.clear()
    train(cfg, run=tmp_path / "run", resume=True, episodes=2, progress=False, command="test")
    assert calls == on_resume


@pytest.mark.slow
def test_environments_in_worker_processes_receive_the_resolved_config(monkeypatch):
    cfg = training_config(merge_config(LaneFreeConfig(), {"train": {"envs": 2, "backend": "numpy"}}))
    calls = _counting(monkeypatch)
    vec = make_vec_env(cfg)
    try:
        received = vec.get_attr("cfg")
    finally:
        vec.close()
    assert calls == [] and [type(c) for c in received] == [ResolvedConfig] * 2 and received == [cfg, cfg]

"""Several learning vehicles on the ring: a PettingZoo ``ParallelEnv`` and an SB3 adapter for one shared policy.

:func:`parallel_env` builds :class:`LaneFreeParallelEnv`: ``scenario.agents`` = k learning vehicles
(``agent``, ``agent1``, …) among the background traffic of ``scenario.density_veh_per_km`` (they come on top
of it, as LaneFree-v0's agent does). Each agent has LaneFree-v0's observation, action and reward, computed by
the same code (:class:`~lanefree_sumo.rl.env.LearningVehicle`), its own reward terms in its own ``info``, and
its own safety shield with ``shield.enabled``. With k = 1 the episodes are LaneFree-v0's: the same seed and
actions give the same observations, rewards and infos (test).

Collisions: each agent's ``episode_metrics`` count the collisions it took part in (``collisions``), those
of them with another agent (``agent_collisions``) and the collisions among background vehicles only
(``background_collisions``, the same for every agent).

On the ring episodes end for every agent at once: by truncation after ``sim.episode_steps`` steps, or —
with ``episode.terminate_on_collision`` — when any agent collides (the ring has no exit, so an agent that
is done cannot leave the road; the project's choice, see the interpretation table). On the on-ramp
(``road.kind: onramp``) an agent whose centre passes the road's end is done (terminated) and taken off
the road, and leaves ``agents`` as PettingZoo's rules for done agents say; the others go on.

:class:`SharedPolicyVecEnv` shows the k agents to Stable-Baselines3 as a ``VecEnv`` of k environments, so
one learner trains one policy on every agent's transitions (parameter sharing; ``lanefree train --agents K``).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from functools import partial
from typing import Any

import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding
from pettingzoo import ParallelEnv
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices, VecEnvObs, VecEnvStepReturn

from lanefree_sumo.config import LaneFreeConfig
from lanefree_sumo.rl.env import (
    RENDER_FPS,
    RENDER_MODES,
    LearningVehicle,
    action_space,
    action_to_acceleration,
    as_seed,
    face_config,
    numpy_info,
    observation_space,
    resolve_config,
    scene_of,
)
from lanefree_sumo.sim.simulation import Simulation
from lanefree_sumo.sim.spawn import agent_id


class LaneFreeParallelEnv(ParallelEnv):
    """k learning vehicles on the lane-free ring (module docstring); ``config`` as for LaneFree-v0."""

    metadata = {"name": "lanefree_ring_v0", "render_modes": list(RENDER_MODES), "render_fps": RENDER_FPS,
                "is_parallelizable": True}

    def __init__(self, config: LaneFreeConfig | Mapping[str, Any] | None = None,
                 render_mode: str | None = None) -> None:
        self.cfg = resolve_config(face_config(config, render_mode))
        self.render_mode = render_mode
        self.sim = Simulation(self.cfg)
        self._overlap: np.ndarray | None = None
        self.possible_agents: list[str] = [agent_id(i) for i in range(self.cfg.scenario.agents)]
        self.agents: list[str] = []
        self.vehicles = {name: LearningVehicle(self.cfg, self.sim) for name in self.possible_agents}
        self._observation_spaces = {name: observation_space(self.cfg) for name in self.possible_agents}
        self._action_spaces = {name: action_space(self.cfg) for name in self.possible_agents}
        self._rows = np.zeros(0, dtype=int)
        self._np_random: np.random.Generator | None = None
        self.episode = 0
        self.episode_seed = 0
        self.env_seconds = 0.0
        """Wall time of the env's own work in ``step`` (actions, shields, observations, rewards) (s)."""

    def observation_space(self, agent: str) -> spaces.Space:
        return self._observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Space:
        return self._action_spaces[agent]

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict[str, Any], dict[str, dict]]:
        """A new episode; its traffic seed is ``seed``, else drawn from the env's generator (seeded by the
        first ``seed`` given, as gymnasium's ``reset`` does)."""
        seed = as_seed(seed)
        if seed is not None:
            self._np_random, _ = seeding.np_random(seed)
        elif self._np_random is None:
            self._np_random, _ = seeding.np_random()
        self.episode_seed = int(seed) if seed is not None else int(self._np_random.integers(2**31 - 1))
        state = self.sim.reset(self.episode_seed)
        self.episode += 1
        self._rows = np.flatnonzero(~state.controlled)
        self.agents = list(self.possible_agents)
        observations = {name: self.vehicles[name].start(int(row)) for name, row in zip(self.agents, self._rows)}
        self._overlap = None
        return observations, {name: {"episode_seed": np.int64(self.episode_seed)} for name in self.agents}

    def render(self) -> np.ndarray | None:
        """The current frame (``render_mode="rgb_array"``: ``H × W × 3`` uint8, every agent in green,
        :mod:`~lanefree_sumo.rl.render`); None without a render mode or under ``"human"`` (sumo-gui)."""
        if self.render_mode != "rgb_array":
            return None
        from lanefree_sumo.rl.render import draw_frame

        state = self.sim.current()[0]
        return draw_frame(scene_of(state, self._overlap, self.sim.road, self.sim.steps * self.cfg.sim.step_s))

    @property
    def agent_rows(self) -> np.ndarray:
        """The live agents' rows in the simulation state, in the order of ``agents``."""
        if self.sim.road.periodic:
            return self._rows
        ids = self.sim.current()[0].ids
        return np.array([ids.index(self.vehicles[name].vid) for name in self.agents], dtype=int)

    def step(self, actions: Mapping[str, Any]) -> tuple[dict[str, Any], dict[str, float], dict[str, bool],
                                                          dict[str, bool], dict[str, dict]]:
        """One step of every agent; ``actions`` holds one action per live agent."""
        if not self.agents:
            raise RuntimeError("no live agents: call reset() first")
        if not isinstance(actions, Mapping):
            raise TypeError(f"step() takes a dict of one action per live agent {self.agents}, not "
                            f"{type(actions).__name__}")
        missing = [name for name in self.agents if name not in actions]
        unknown = [name for name in actions if name not in self.agents]
        if missing or unknown:
            raise ValueError(f"step() takes one action per live agent {self.agents}; "
                             + (f"missing {missing}" if missing else f"not live: {unknown}"))
        t0 = time.perf_counter()
        commands = np.empty((len(self.agents), 2))
        decisions = []
        for k, name in enumerate(self.agents):
            where = f"step {self.sim.steps + 1} of episode {self.episode} ({name})"
            ax, ay = action_to_acceleration(self.cfg, actions[name], where)
            decision = self.vehicles[name].shield(ax, ay)
            if decision is not None:
                ax, ay = decision.ax, decision.ay
            commands[k] = ax, ay
            decisions.append(decision)
        self.env_seconds += time.perf_counter() - t0
        result = self.sim.step(commands)
        self._overlap = result.overlap
        t0 = time.perf_counter()
        observations, rewards, infos = {}, {}, {}
        any_collided = False
        rows = self.agent_rows  # after the step (on an open road rows come and go)
        for k, name in enumerate(self.agents):
            obs, reward, collided, info = self.vehicles[name].score(
                result, float(commands[k, 0]), float(commands[k, 1]), decisions[k], rows)
            observations[name], rewards[name], infos[name] = obs, reward, numpy_info(info)
            any_collided |= collided
        crashed = bool(self.cfg.episode.terminate_on_collision and any_collided)
        truncated = self.sim.steps >= self.cfg.sim.episode_steps
        terminations = {name: crashed or self.vehicles[name].left_road() for name in self.agents}
        truncations = {name: truncated and not terminations[name] for name in self.agents}
        ended = [name for name in self.agents if terminations[name] or truncations[name]]
        for name in ended:
            infos[name]["episode_metrics"] = self.episode_metrics(name)
        self.agents = [name for name in self.agents if name not in ended]
        if ended and not self.sim.road.periodic:  # on an open road agents that are done are taken off it
            self.sim.remove([self.vehicles[name].vid for name in ended])
        self.env_seconds += time.perf_counter() - t0
        return observations, rewards, terminations, truncations, infos

    def episode_metrics(self, agent: str) -> dict[str, Any]:
        """The metrics (specification §8) of ``agent``'s episode so far, its name and its collisions with other
        agents."""
        vehicle = self.vehicles[agent]
        return {**vehicle.metrics(self.episode, self.episode_seed), "agent": agent,
                "agent_collisions": vehicle.books["agent_collisions"]}

    def close(self) -> None:
        self.sim.close()


def parallel_env(config: LaneFreeConfig | Mapping[str, Any] | None = None,
                 render_mode: str | None = None) -> LaneFreeParallelEnv:
    """The multi-agent ring (:class:`LaneFreeParallelEnv`) for ``config`` (a config or nested overrides)."""
    return LaneFreeParallelEnv(config, render_mode)


def _offset_seed(base: int, episode: int) -> int:
    """Episode ``episode``'s traffic seed when ``SharedPolicyVecEnv`` is given one int ``base``."""
    return base + episode - 1


def _stack(observations: Sequence[Any], space: spaces.Space) -> VecEnvObs:
    """SB3's batched observation of one observation per agent (a dict of arrays for a Dict space)."""
    if isinstance(space, spaces.Dict):
        return {key: np.stack([obs[key] for obs in observations]) for key in space.spaces}
    return np.stack(observations)


class SharedPolicyVecEnv(VecEnv):
    """The agents of a :class:`LaneFreeParallelEnv` as the k environments of an SB3 ``VecEnv`` (parameter
    sharing: one model acts for, and learns from, every agent).

    All agents' episodes end together: on the ring they do (:class:`LaneFreeParallelEnv`); on the on-ramp the
    first agent to leave the road ends the episode of the others too (truncated: their values are
    bootstrapped). Then each agent's ``info`` carries ``terminal_observation`` and ``episode`` (SB3's
    Monitor record) and the next episode starts, with the traffic seed ``seeds(episode)`` (episodes
    numbered from ``first_episode``; ``seeds`` an int s: episode e gets s + e − 1)."""

    def __init__(self, env: LaneFreeParallelEnv, seeds: int | Callable[[int], int], first_episode: int = 1) -> None:
        if isinstance(seeds, bool) or not (callable(seeds) or isinstance(seeds, int | np.integer)):
            raise TypeError(f"seeds is an int (episode e gets seed + e - 1) or a function of the episode number "
                            f"giving its traffic seed, not {type(seeds).__name__}")
        if not callable(seeds):
            base = int(as_seed(seeds) or 0)
            seeds = partial(_offset_seed, base)
        self.par_env = env
        self.names = list(env.possible_agents)
        first = self.names[0]
        super().__init__(len(self.names), env.observation_space(first), env.action_space(first))
        self.seeds = seeds
        self.next_episode = first_episode
        self._actions: np.ndarray | None = None
        self._returns = np.zeros(self.num_envs)
        self._length = 0
        self._t0 = time.time()

    def reset(self) -> VecEnvObs:
        observations, _ = self.par_env.reset(seed=int(self.seeds(self.next_episode)))
        self.next_episode += 1
        self._returns[:] = 0.0
        self._length = 0
        return _stack([observations[name] for name in self.names], self.observation_space)

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(self) -> VecEnvStepReturn:
        assert self._actions is not None, "step_async first"
        observations, rewards, terminations, truncations, infos = self.par_env.step(
            {name: self._actions[k] for k, name in enumerate(self.names)})
        reward = np.array([rewards[name] for name in self.names], dtype=np.float32)
        self._returns += reward
        self._length += 1
        dones = np.array([terminations[name] or truncations[name] for name in self.names])
        info_list = [dict(infos[name]) for name in self.names]
        obs = _stack([observations[name] for name in self.names], self.observation_space)
        if dones.any() and not dones.all():
            # an agent left the on-ramp: one simulation cannot go on for some slots of a VecEnv and restart
            # for others, so the episode ends for every agent; the others' ends are truncations
            for k, name in enumerate(self.names):
                if not dones[k]:
                    truncations[name] = True
                    info_list[k]["episode_metrics"] = self.par_env.episode_metrics(name)
            dones[:] = True
        if dones.all():
            for k, name in enumerate(self.names):
                info_list[k]["TimeLimit.truncated"] = truncations[name] and not terminations[name]
                info_list[k]["terminal_observation"] = observations[name]
                info_list[k]["episode"] = {"r": float(self._returns[k]), "l": self._length,
                                           "t": round(time.time() - self._t0, 6)}
            obs = self.reset()
        return obs, reward, dones, info_list

    def close(self) -> None:
        self.par_env.close()

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        return [getattr(self.par_env, attr_name)] * len(list(self._get_indices(indices)))

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        setattr(self.par_env, attr_name, value)

    def env_method(self, method_name: str, *method_args: Any, indices: VecEnvIndices = None,
                   **method_kwargs: Any) -> list[Any]:
        result = getattr(self.par_env, method_name)(*method_args, **method_kwargs)
        return [result] * len(list(self._get_indices(indices)))

    def env_is_wrapped(self, wrapper_class: type, indices: VecEnvIndices = None) -> list[bool]:
        return [False] * len(list(self._get_indices(indices)))


class PolicyDriver:
    """Episodes of one policy driving every learning vehicle: LaneFree-v0 for one agent, else the multi-agent
    ring (the verbs' common loop: evaluate, rollout, the mixed-autonomy measurement).

    Observations go to the policy as the env gives them (one agent) or stacked, one row per agent (a shared
    policy's ``predict`` takes the batch); actions come back the same way."""

    def __init__(self, cfg: LaneFreeConfig) -> None:
        from lanefree_sumo.rl.env import LaneFreeEnv

        self.cfg = resolve_config(cfg)
        self.agents = self.cfg.scenario.agents
        self.single = LaneFreeEnv(self.cfg) if self.agents == 1 else None
        self.multi = None if self.single is not None else LaneFreeParallelEnv(self.cfg)
        self.sim: Simulation = self.single.sim if self.single is not None else self.multi.sim  # type: ignore[union-attr]
        self._last_obs: dict[str, Any] = {}
        """Each agent's latest observation (an agent that left the road keeps its last)."""
        self._ended: list[dict[str, Any]] = []
        """The ``episode_metrics`` of the agents whose episode ended."""
        if self.multi is not None:
            self.names = list(self.multi.possible_agents)
            self.spaces = [self.multi.action_space(name) for name in self.names]
        else:
            self.names = [agent_id(0)]
            self.spaces = [self.single.action_space]  # type: ignore[union-attr]

    def seed_actions(self, seed: int) -> None:
        """Seed the action spaces' samplers (agent i with ``seed + i``)."""
        for i, space in enumerate(self.spaces):
            space.seed(seed + i)

    def sample(self) -> Any:
        """A uniformly random action for every agent."""
        if self.single is not None:
            return self.spaces[0].sample()
        return np.stack([np.asarray(space.sample()) for space in self.spaces])

    def idle(self) -> Any:
        """The zero action (ax = ay = 0; discrete action 0) for every agent."""
        shape = self.spaces[0].shape or ()
        one = np.zeros(shape, dtype=np.float32) if shape else 0
        return one if self.single is not None else np.stack([np.asarray(one)] * self.agents)

    def reset(self, seed: int) -> Any:
        """Start an episode with traffic seed ``seed``; the first observation(s)."""
        if self.single is not None:
            return self.single.reset(seed=seed)[0]
        assert self.multi is not None
        observations, _ = self.multi.reset(seed=seed)
        self._last_obs = dict(observations)
        self._ended = []
        return _stack([observations[name] for name in self.names], self.multi.observation_space(self.names[0]))

    def step(self, actions: Any) -> tuple[Any, bool, set[str], list[dict[str, Any]]]:
        """(observation(s), episode over, vehicle ids of the agents whose action the shield changed in this
        step — those taken off the road after it included —, the agents' ``episode_metrics`` at the
        episode's end, else [])."""
        if self.single is not None:
            obs, _, terminated, truncated, info = self.single.step(actions)
            shielded = {self.single.vehicle.vid} if info["shield_intervened"] else set()
            done = terminated or truncated
            return obs, done, shielded, [info["episode_metrics"]] if done else []
        assert self.multi is not None
        batch = np.asarray(actions)
        live = list(self.multi.agents)
        observations, _, _, _, infos = self.multi.step({name: batch[self.names.index(name)] for name in live})
        shielded = {self.multi.vehicles[name].vid for name in live if infos[name]["shield_intervened"]}
        self._last_obs.update(observations)
        self._ended += [infos[name]["episode_metrics"] for name in live if "episode_metrics" in infos[name]]
        done = not self.multi.agents
        obs = _stack([self._last_obs[name] for name in self.names], self.multi.observation_space(self.names[0]))
        return obs, done, shielded, sorted(self._ended, key=lambda m: self.names.index(m["agent"])) if done else []

    def close(self) -> None:
        (self.single or self.multi).close()  # type: ignore[union-attr]

"""``LaneFree-v0``: one learning agent among the force-driven background traffic (specification §5–§8).

The environment orchestrates: the simulation core moves every vehicle, :mod:`.rewards` scores
the step, and this module only selects neighbours, scales observations and keeps the episode's
books.  Every step's ``info`` carries each reward term (c_x, c_y, c_f, y_d, v_d_eff, blocked,
collided, overtook, reward); the last step of an episode also carries ``episode_metrics``
(specification §8).

With ``shield.enabled`` every action passes through :mod:`.shield` before the simulation
(the env orchestrates, the shield computes): ``info`` then reports ``shield_intervened`` (bool)
and ``shield_correction`` (m/s², the norm of the change; both also present, False/0, without the
shield), ``ax``/``ay`` are the accelerations commanded after the shield, the reward loses
``shield.intervention_penalty`` on every step the shield changed the action, and the episode
metrics count ``shield_interventions`` (and ``shield_fallbacks``: steps with no certified action).

Observation scaling (``observation.scale``, default on): positions and lengths along x are
divided by the observation range d, lateral positions by the road width W, longitudinal speeds
by ``speed_scale_mps`` (25 m/s) and lateral speeds by ``lateral_speed_scale_mps`` (2 m/s); so
every feature is O(1).  With ``scale=False`` the raw SI values are returned.
"""

from __future__ import annotations

import numbers
import time
from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from lanefree_sumo.config import (
    ConfigError,
    LaneFreeConfig,
    ResolvedConfig,
    merge_config,
    validate_config,
)
from lanefree_sumo.rl.problem import (
    EGO_FEATURES,
    NEIGHBOUR_FEATURES,
    AgentView,
    Problem,
    ProblemState,
    episode_row,
)
from lanefree_sumo.rl.shield import ShieldDecision, ShieldParams, shield_action
from lanefree_sumo.sim.collisions import count_events
from lanefree_sumo.sim.road import road_kind
from lanefree_sumo.sim.simulation import Simulation, StepResult
from lanefree_sumo.sim.xp import NUMPY

# Discrete actions (specification §6) as (sign of ax, sign of ay): none, +ax, −ax, left, right, and the
# four combinations.
DISCRETE_ACTIONS = np.array(
    [(0, 0), (1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (-1, 1), (1, -1), (-1, -1)], dtype=float
)


def resolve_config(config: LaneFreeConfig | Mapping[str, Any] | None) -> ResolvedConfig:
    """The config an environment runs, always a :class:`~lanefree_sumo.config.ResolvedConfig`: one given as it is
    (resolved once, at the top of its run; an environment in a worker process receives it so); else ``config``
    (a dict merged into the defaults) with the agent on the road, validated whole, marked resolved."""
    if isinstance(config, ResolvedConfig):
        return config
    if config is None:
        cfg = LaneFreeConfig()
    elif isinstance(config, LaneFreeConfig):
        cfg = config
    else:
        cfg = merge_config(LaneFreeConfig(), config)
    return ResolvedConfig.of(validate_config(merge_config(cfg, {"scenario": {"with_agent": True}})))


class LearningVehicle:
    """One learning vehicle of a simulation: the learning problem (:mod:`.problem`) with K = 1 on this vehicle's
    row, its shield and the on-ramp's extras (specification §5–§8). :class:`LaneFreeEnv` drives one, the
    multi-agent environment (:mod:`lanefree_sumo.rl.multi_agent`) one per agent."""

    def __init__(self, cfg: LaneFreeConfig, sim: Simulation) -> None:
        self.cfg = cfg
        self.sim = sim
        self.problem = Problem([cfg], NUMPY)
        self.index = -1
        """This vehicle's row in the simulation state (−1 before the first episode)."""
        self.vid = ""
        """Its vehicle id (on an open road rows come and go: the row is looked up by id every step)."""
        self.open_road = not sim.road.periodic
        self.state = ProblemState.empty(NUMPY, 1, 0)
        self._prev_ids: list[str] = []
        self.extra: dict[str, Any] = {}
        """What the books of :mod:`.problem` do not hold: collisions with other agents, the on-ramp's merge step,
        the episode's start (``time.perf_counter``)."""
        self.shield_params: ShieldParams | None = None

    @property
    def books(self) -> dict[str, Any]:
        """The episode's books so far (host numbers; :data:`~lanefree_sumo.rl.problem.BOOKS` and :attr:`extra`)."""
        return {**{name: value[0].item() for name, value in self.state.books.items()}, **self.extra}

    def start(self, index: int) -> Any:
        """Begin an episode as row ``index`` of the freshly reset simulation; returns the first observation."""
        self.index = index
        state = self.sim.current()[0]
        self.vid = state.ids[index]
        self.extra = {"agent_collisions": 0, "merged_at_step": -1, "t0": time.perf_counter()}
        self.state = ProblemState.empty(NUMPY, 1, state.n)
        self._prev_ids = state.ids
        obs = self.problem.begin(self.state, self.view(), 0, self._extra_ego())
        return obs[0] if not isinstance(obs, dict) else {name: value[0] for name, value in obs.items()}

    def view(self) -> AgentView:
        """The scene around this vehicle (K = 1) in the simulation's current state."""
        (state, (dx_all, dy_all)), a = self.sim.current(), self.index
        lo, hi = self.lateral_bounds()
        row = np.array([a])
        present = np.ones((1, state.n), dtype=bool)
        return AgentView.of(NUMPY, dx_all[row], dy_all[row], state.vx[None], state.vy[None], state.length[None],
                            state.width[None], state.v_desired[None], state.y[None], present, row, np.array([lo]),
                            np.array([hi - lo]), np.array([float(self.cfg.road.length_m)]))

    def _extra_ego(self) -> np.ndarray | None:
        """The on-ramp's ego features ``[1, 4]`` (None on the ring, or with ``observation.road_features`` off)."""
        return self._road_features()[None] if self.open_road and self.cfg.observation.road_features else None

    def follow(self) -> None:
        """On an open road: find this vehicle's row again (rows before it leave the road) and line the previous
        step's offsets and pass book up with the current rows (a vehicle that just entered has none: no
        overtake)."""
        state = self.sim.current()[0]
        if state.ids is self._prev_ids:
            return
        self.index = state.ids.index(self.vid)
        old = {vid: i for i, vid in enumerate(self._prev_ids)}
        keep = {j: old[vid] for j, vid in enumerate(state.ids) if vid in old}
        now = self.sim.current()[1][0][self.index]
        prev = self.state.prev_dx[0]
        self.state.prev_dx = np.array([[prev[keep[j]] if j in keep else d for j, d in enumerate(now)]])
        self.state.remap(keep, state.n)
        self._prev_ids = state.ids

    def shield(self, ax: float, ay: float) -> ShieldDecision | None:
        """The shield's decision on the policy's (ax, ay) (m/s²), None when the shield is off."""
        if not self.cfg.shield.enabled:
            return None
        if self.shield_params is None:
            self.shield_params = ShieldParams.from_config(self.cfg)
        state = self.sim.current()[0]
        if not self.open_road:
            return shield_action(self.index, state, ax, ay, self.shield_params)
        self.follow()  # the shield acts before the step: this vehicle's row in the state it sees
        bounds = self.sim.road.bounds(state.x + 0.5 * state.length, self.sim.on_ramp)
        return shield_action(self.index, state, ax, ay, self.shield_params, bounds)

    def score(self, result: StepResult, ax: float, ay: float, decision: ShieldDecision | None,
              agents: np.ndarray | None = None) -> tuple[Any, float, bool, dict[str, Any]]:
        """After a simulation step: (observation, reward, collided, info) of this vehicle, its books updated.
        ``agents``: the rows of every agent vehicle (collisions with them are also counted apart); None:
        this vehicle alone (its row as of after the step)."""
        if self.open_road:
            self.follow()
        a = self.index
        if agents is None:
            agents = np.array([a])
        agent_events, with_agents, background_only = count_events(result.new_collisions, a, agents)
        collided = bool(result.overlap[a].any())
        contact = bool(result.boundary_contact[a])
        intervened = decision is not None and decision.intervened
        shield: dict[str, Any] = {} if decision is None else {
            "intervened": np.array([intervened]), "fallback": np.array([not decision.certified])}
        obs, reward, terms, overtakes = self.problem.step(
            self.state, self.view(), np.array([collided]), np.array([agent_events]), np.array([background_only]),
            np.array([contact]), extra_ego=self._extra_ego(), **shield)
        self.extra["agent_collisions"] += with_agents
        if self.open_road and self.extra["merged_at_step"] < 0 and not self.sim.on_ramp[a]:
            self.extra["merged_at_step"] = self.sim.steps
        info: dict[str, Any] = {
            **{name: value[0].item() for name, value in terms.as_dict().items()},
            "overtakes": int(overtakes[0]),
            "collision_events": agent_events,
            "boundary_contact": contact,
            "ax": ax,
            "ay": ay,
            "reward": float(reward[0]),
            "shield_intervened": intervened,
            "shield_correction": decision.correction if decision is not None else 0.0,
        }
        obs = obs[0] if not isinstance(obs, dict) else {name: value[0] for name, value in obs.items()}
        return obs, float(reward[0]), collided, info

    def lateral_bounds(self) -> tuple[float, float]:
        """(lowest, highest) lateral position this vehicle's body may reach at its front now (m): 0 and W on
        the ring."""
        if not self.open_road:
            return 0.0, self.cfg.road.width_m
        state, a = self.sim.current()[0], self.index
        lo, hi = self.sim.road.bounds(state.x[a:a + 1] + 0.5 * state.length[a:a + 1], self.sim.on_ramp[a:a + 1])
        return float(np.asarray(lo).ravel()[0]), float(np.asarray(hi).ravel()[0])

    def left_road(self) -> bool:
        """On an open road: this vehicle's centre passed the road's end."""
        return self.open_road and float(self.sim.current()[0].x[self.index]) >= self.sim.road.length_m

    def _road_features(self) -> np.ndarray:
        """The on-ramp's ego features (module constants): the boundaries at the front (/W), on the ramp (0/1),
        and the room to the ramp's end ahead of the front (/d, 1 when merged or beyond d)."""
        state, a, road = self.sim.current()[0], self.index, self.sim.road
        lo, hi = self.lateral_bounds()
        on_ramp = bool(self.sim.on_ramp[a])
        room = road.ramp_end_m - (float(state.x[a]) + 0.5 * float(state.length[a]))
        ahead = min(max(room / self.cfg.observation.range_m, 0.0), 1.0) if on_ramp else 1.0
        return np.array([lo / road.width_m, hi / road.width_m, float(on_ramp), ahead])

    def metrics(self, episode: int, seed: int) -> dict[str, Any]:
        """specification §8 metrics of the episode so far (one CSV row)."""
        return {**episode_row(episode, self.sim.steps, self.books, self.cfg, seed,
                              time.perf_counter() - self.extra["t0"]),
                **(self._onramp_metrics() if self.open_road else {})}

    def _onramp_metrics(self) -> dict[str, Any]:
        """The on-ramp's episode metrics: merged (a ramp start whose body reached the main road), the time it
        took (s; NaN when it did not, or started on the main road) and whether it left the road at its end."""
        merged_at = self.extra["merged_at_step"]
        from_ramp = self.cfg.road.onramp.agent_start == "ramp"
        return {"merged": bool(from_ramp and merged_at >= 0),
                "time_to_merge_s": merged_at * self.cfg.sim.step_s if from_ramp and merged_at >= 0 else float("nan"),
                "left_road": self.left_road()}


def ego_features(cfg: LaneFreeConfig) -> int:
    """How many ego features an observation has: 4, and 4 more on the on-ramp (unless
    ``observation.road_features`` is off)."""
    return EGO_FEATURES + (len(road_kind(cfg).ego_features) if cfg.observation.road_features else 0)


def observation_space(cfg: LaneFreeConfig) -> spaces.Space:
    """A learning vehicle's observation space: a vector, or a dict of ego features and a padded table."""
    obs_cfg = cfg.observation
    n_feat = ego_features(cfg) + NEIGHBOUR_FEATURES * obs_cfg.n_neighbours
    if obs_cfg.kind == "vector":
        return spaces.Box(-np.inf, np.inf, (n_feat,), np.float32)
    return spaces.Dict(
        {
            "ego": spaces.Box(-np.inf, np.inf, (ego_features(cfg),), np.float32),
            "others": spaces.Box(-np.inf, np.inf, (obs_cfg.max_rows, NEIGHBOUR_FEATURES + 1), np.float32),
        }
    )


def action_space(cfg: LaneFreeConfig) -> spaces.Space:
    """A learning vehicle's action space: (ax, ay) in [−1, 1]², or one of the 9 discrete actions."""
    if cfg.action.kind == "continuous":
        return spaces.Box(-1.0, 1.0, (2,), np.float32)
    return spaces.Discrete(len(DISCRETE_ACTIONS))


def action_to_acceleration(cfg: LaneFreeConfig, action: Any, where: str) -> tuple[float, float]:
    """(ax, ay) in m/s² for an action (specification §6); continuous actions are clipped to [−1, 1].

    A NaN or infinite action raises ``ValueError`` naming ``where`` (the step): a diverged policy must
    not silently drive the car."""
    values = np.asarray(action, dtype=float).ravel()
    if not np.isfinite(values).all():
        raise ValueError(f"action {action!r} at {where} is not finite; a diverged policy must not drive the car")
    if cfg.action.kind == "discrete":
        if values.size != 1 or values[0] != int(values[0]) or not 0 <= values[0] < len(DISCRETE_ACTIONS):
            raise ValueError(f"a discrete action is one whole number 0 … {len(DISCRETE_ACTIONS) - 1}, "
                             f"got {action!r}")
        sign_x, sign_y = DISCRETE_ACTIONS[int(values[0])]
        return sign_x * cfg.action.discrete_ax_mps2, sign_y * cfg.action.discrete_ay_mps2
    if values.size != 2:
        raise ValueError(f"a continuous action has 2 components (ax, ay in [-1, 1]), got {action!r}")
    bounds = cfg.scenario.agent_bounds
    a0 = min(1.0, max(-1.0, float(values[0])))
    a1 = min(1.0, max(-1.0, float(values[1])))
    return (a0 * bounds.ax_max if a0 >= 0.0 else -a0 * bounds.ax_min), a1 * bounds.ay_max


def as_seed(seed: Any) -> int | None:
    """A ``reset`` seed as a Python int (numpy's integers too: gymnasium takes only Python ints), None kept;
    ValueError saying what a seed is for anything else."""
    if seed is None:
        return None
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or seed < 0:
        raise ValueError(f"seed must be a whole number ≥ 0 (or None), got {seed!r}")
    return int(seed)


RENDER_MODES = ("rgb_array", "human")
"""The render modes of every face: ``rgb_array`` frames drawn from the simulation's arrays (:mod:`.render`),
``human`` the run in sumo-gui (the TraCI backend under a display)."""
RENDER_FPS = 4
"""Frames per second of real time: one frame per 0.25 s step."""


def face_config(config: LaneFreeConfig | Mapping[str, Any] | None,
                render_mode: str | None = None) -> LaneFreeConfig | Mapping[str, Any]:
    """The config a face (LaneFree-v0, the vector env, the PettingZoo env) runs: a dict of overrides (or
    none) runs on the ``numpy`` backend unless it names ``backend`` or ``gui`` — the same episodes as libsumo
    bit for bit, many environments per process —, a :class:`~lanefree_sumo.config.LaneFreeConfig` as it is;
    ``render_mode="human"`` turns on sumo-gui. ValueError for a render mode other than :data:`RENDER_MODES`."""
    if render_mode is not None and render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode {render_mode!r} is not one of {', '.join(RENDER_MODES)} (or None)")
    if config is None or (isinstance(config, Mapping) and not isinstance(config, LaneFreeConfig)):
        given = dict(config or {})
        if "backend" not in given and not given.get("gui"):
            given["backend"] = "numpy"
        config = given
    if render_mode == "human":
        config = merge_config(config, {"gui": True}) if isinstance(config, LaneFreeConfig) else {**config,
                                                                                                  "gui": True}
    return config


_SCALAR_TYPES: dict[type, type] = {bool: np.bool_, np.bool_: np.bool_, int: np.int64, np.int64: np.int64,
                                   float: np.float64, np.float64: np.float64}
"""The scalar types a step's ``info`` holds and their numpy types (looked up before the slower abstract checks)."""


def numpy_info(info: dict[str, Any]) -> dict[str, Any]:
    """A step's ``info`` with numpy-typed scalars (``np.float64``, ``np.int64``, ``np.bool_``), as array libraries
    read them; other values (``episode_metrics``: the episode's CSV row) as they are."""
    out: dict[str, Any] = {}
    for key, value in info.items():
        to = _SCALAR_TYPES.get(type(value))
        if to is None:
            if isinstance(value, bool | np.bool_):
                to = np.bool_
            elif isinstance(value, numbers.Integral):
                to = np.int64
            elif isinstance(value, numbers.Real):
                to = np.float64
        out[key] = value if to is None else to(value)
    return out


def scene_of(state: Any, overlap: np.ndarray | None, road: Any, time_s: float) -> Any:
    """The :class:`~lanefree_sumo.rl.render.Scene` of a simulation state (:class:`~lanefree_sumo.sim.state.
    VehicleState`), its ``[N, N]`` overlap matrix (None: none) and the road."""
    from lanefree_sumo.rl.render import Scene

    n = state.n
    fits = overlap is not None and overlap.shape == (n, n)
    touching = np.asarray(overlap.any(axis=1)) if fits and overlap is not None else np.zeros(n, dtype=bool)
    return Scene(state.x, state.y, state.vx, state.vy, state.length, state.width, ~state.controlled, touching,
                 road, time_s)


class LaneFreeEnv(gym.Env):
    """Gymnasium environment of the paper's MDP on the ring road (or the on-ramp).

    ``config``: a :class:`~lanefree_sumo.config.LaneFreeConfig` or a nested dict of overrides; a dict runs on
    the ``numpy`` backend unless it names ``backend`` (``libsumo``, ``traci``) or ``gui`` (:func:`face_config`).
    Episodes last ``sim.episode_steps`` steps and end by truncation; collisions end them only
    with ``episode.terminate_on_collision``; on the on-ramp (``road.kind``) leaving the road ends them
    (terminated).  ``reset(seed=...)`` is reproducible. ``render_mode``: ``"rgb_array"`` (``render()`` returns
    an ``H × W × 3`` uint8 frame, :mod:`.render`) or ``"human"`` (sumo-gui).
    """

    metadata = {"render_modes": list(RENDER_MODES), "render_fps": RENDER_FPS}

    def __init__(
        self, config: LaneFreeConfig | Mapping[str, Any] | None = None, render_mode: str | None = None
    ) -> None:
        super().__init__()
        self.render_mode = render_mode
        self.cfg = resolve_config(face_config(config, render_mode))
        if self.cfg.scenario.agents != 1:
            raise ConfigError(f"LaneFree-v0 drives one agent (scenario.agents = {self.cfg.scenario.agents}); "
                              "use lanefree_sumo.rl.multi_agent.parallel_env for several")
        self.sim = Simulation(self.cfg)
        self.observation_space: spaces.Space = observation_space(self.cfg)
        self.action_space: spaces.Space = action_space(self.cfg)
        self.episode = 0
        self.env_seconds = 0.0
        """Wall time of the env's own work in ``step`` (observation, reward, books) (s)."""
        self.vehicle = LearningVehicle(self.cfg, self.sim)
        self._episode_seed = 0
        self._overlap: np.ndarray | None = None

    @property
    def _agent(self) -> int:
        """The agent's row in the simulation state (−1 before the first ``reset``)."""
        return self.vehicle.index

    def action_to_acceleration(self, action: Any) -> tuple[float, float]:
        """(ax, ay) in m/s² for an action (:func:`action_to_acceleration`)."""
        return action_to_acceleration(self.cfg, action, f"step {self.sim.steps + 1} of episode {self.episode}")

    # -- gymnasium API ---------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[Any, dict]:
        seed = as_seed(seed)
        super().reset(seed=seed)
        self._episode_seed = int(seed) if seed is not None else int(self.np_random.integers(2**31 - 1))
        state = self.sim.reset(self._episode_seed)
        self.episode += 1
        obs = self.vehicle.start(state.n - 1)
        self._overlap = None
        return obs, {"episode_seed": np.int64(self._episode_seed)}

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict]:
        if self._agent < 0:
            raise RuntimeError("call reset() before step()")
        t0 = time.perf_counter()
        ax, ay = self.action_to_acceleration(action)
        decision = self.vehicle.shield(ax, ay)
        if decision is not None:
            ax, ay = decision.ax, decision.ay
        self.env_seconds += time.perf_counter() - t0
        result = self.sim.step((ax, ay))
        t0 = time.perf_counter()
        obs, reward, collided, info = self.vehicle.score(result, ax, ay, decision)
        self._overlap = result.overlap
        terminated = bool(self.cfg.episode.terminate_on_collision and collided) or self.vehicle.left_road()
        truncated = self.sim.steps >= self.cfg.sim.episode_steps
        info = numpy_info(info)
        if terminated or truncated:
            info["episode_metrics"] = self.episode_metrics()
        self.env_seconds += time.perf_counter() - t0
        return obs, reward, terminated, truncated, info

    def render(self) -> np.ndarray | None:
        """The current frame (``render_mode="rgb_array"``: ``H × W × 3`` uint8, :mod:`.render`); None without a
        render mode or under ``"human"`` (sumo-gui shows every step itself)."""
        if self.render_mode != "rgb_array":
            return None
        if self._agent < 0:
            raise RuntimeError("call reset() before render()")
        from lanefree_sumo.rl.render import draw_frame

        state = self.sim.current()[0]
        return draw_frame(scene_of(state, self._overlap, self.sim.road, self.sim.steps * self.cfg.sim.step_s))

    def close(self) -> None:
        self.sim.close()

    def episode_metrics(self) -> dict[str, Any]:
        """specification §8 metrics of the episode so far (one CSV row)."""
        return self.vehicle.metrics(self.episode, self._episode_seed)

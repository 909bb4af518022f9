"""The learning problem, once, over K worlds (specification §5–§8): what a learning vehicle observes, the reward
terms it earns, which of its passes earn the overtake bonus, and its episode books and metrics.

Array code over a leading run axis ``[K]`` (numpy, or torch on a device through :mod:`~lanefree_sumo.sim.xp`), one
learning vehicle per run and call. Every face is a view of it:

- :class:`~lanefree_sumo.rl.batched_env.BatchedRingEnv` (and through it the vector env, ``--seeds``, sweeps, the
  GPU's lockstep loop): K rings, each run's agent row of the batched world;
- :class:`~lanefree_sumo.rl.env.LearningVehicle` (``LaneFree-v0`` on every backend and road, and each agent of the
  PettingZoo env): K = 1, one vehicle of a :class:`~lanefree_sumo.sim.simulation.Simulation`.

A step's scene around the vehicle is an :class:`AgentView`; what a run keeps from step to step (the previous
offsets, who is in range, the pass book, the episode books) is its :class:`ProblemState`; the per-run constants
(reward weights, feature scales, the overtake-bonus mode) are a :class:`Problem`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from lanefree_sumo.config import LaneFreeConfig
from lanefree_sumo.rl.rewards import (
    COST_NAMES,
    COST_TERMS,
    OVERTAKE_BONUS_MODES,
    Rewards,
    RewardScene,
    get_preset,
    pass_events,
    reward_terms,
    term_weight,
)
from lanefree_sumo.sim.xp import array_namespace, device_name

EGO_FEATURES = 4  # y, vx, vy, v_d
NEIGHBOUR_FEATURES = 4  # dx, dy, vx, vy
METRIC_TERMS = (*COST_NAMES, "reward")
"""The reward terms whose per-step means are episode metrics (``mean_<term>``)."""

BOOKS = ("return", "return_bonus", "return_collision", "collisions", "collision_steps", "background_collisions",
         "speed_dev_sum", "speed_error_sum", "speed_sum", "overtakes", "boundary_contacts", "shield_interventions",
         "shield_fallbacks", *(f"sum_{t}" for t in METRIC_TERMS))
"""A run's episode books: sums over the episode's steps, ``[K]`` each."""



def feature_scales(cfg: LaneFreeConfig) -> tuple[np.ndarray, np.ndarray]:
    """(ego, neighbour) divisors of the observation's features (``observation.scale``): the ego's y by the road
    width W, vx and v_d by ``speed_scale_mps``, vy by ``lateral_speed_scale_mps``; a neighbour's dx by the range
    d, dy by W, its speeds likewise; ones without scaling."""
    o = cfg.observation
    if not o.scale:
        return np.ones(EGO_FEATURES), np.ones(NEIGHBOUR_FEATURES)
    w, v, vy = cfg.road.width_m, o.speed_scale_mps, o.lateral_speed_scale_mps
    return np.array([w, v, vy, v]), np.array([o.range_m, w, v, vy])


@dataclass
class AgentView:
    """One step's scene around each run's learning vehicle: every vehicle row ``[K, N]`` as seen from it and its
    own values ``[K]`` (m, m/s)."""

    dx: Any
    """Longitudinal offset of each row from the vehicle (wrapped on a ring)."""
    dy: Any
    """Lateral offset of each row from the vehicle."""
    vx: Any
    vy: Any
    length: Any
    width: Any
    others: Any
    """True for the rows of other vehicles on the road (False: the vehicle itself, padding)."""
    y: Any
    vx_a: Any
    vy_a: Any
    len_a: Any
    wid_a: Any
    v_desired: Any
    lo: Any
    """The lowest lateral position the vehicle may reach at its front (0 on the ring)."""
    road_width: Any
    """The width between its lateral bounds (W on the ring)."""
    road_length: Any
    """The road's length (the ring's circumference: a pass is never counted across its seam)."""

    @classmethod
    def of(cls, xp: Any, dx: Any, dy: Any, vx: Any, vy: Any, length: Any, width: Any, v_desired: Any, y: Any,
           present: Any, agent: Any, lo: Any, road_width: Any, road_length: Any) -> AgentView:
        """The view of the vehicles in rows ``agent`` (``[K]`` ints) from their offset rows ``dx``, ``dy``
        ``[K, N]``, every row's values ``[K, N]`` and which rows are on the road (``present``)."""
        runs = xp.arange(dx.shape[0])
        others = xp.copy(present)
        xp.put_along_axis(others, agent[:, None], False, 1)
        return cls(dx, dy, vx, vy, length, width, others, y[runs, agent], vx[runs, agent], vy[runs, agent],
                   length[runs, agent], width[runs, agent], v_desired[runs, agent], lo, road_width, road_length)


@dataclass
class ProblemState:
    """What each run keeps from one step to the next (``[K, N]`` per vehicle row, the books ``[K]``)."""

    prev_dx: Any
    """The vehicle's offset of every row at the previous step (passes are sign changes)."""
    in_range: Any
    """The rows within the observation range (other vehicles only)."""
    order: Any
    """Every row by distance from the vehicle, nearest first (the rows out of range last)."""
    net: Any
    """Per row: the vehicle's passes of it minus its passes of the vehicle this episode."""
    best: Any
    """Per row: the highest ``net`` a pass gave it this episode (0 before any)."""
    ever: Any
    """Per row: passed at least once this episode."""
    books: dict[str, Any]
    """The episode's books (:data:`BOOKS`)."""

    ARRAYS: ClassVar[tuple[str, ...]] = ("prev_dx", "in_range", "order", "net", "best", "ever")
    """The fields besides the books."""

    @classmethod
    def empty(cls, xp: Any, runs: int, rows: int) -> ProblemState:
        """Every run before its first episode."""
        return cls(xp.zeros((runs, rows)), xp.zeros((runs, rows), dtype=bool), xp.zeros((runs, rows), dtype=int),
                   xp.zeros((runs, rows), dtype=int), xp.zeros((runs, rows), dtype=int),
                   xp.zeros((runs, rows), dtype=bool), {name: xp.zeros(runs) for name in BOOKS})

    def remap(self, keep: Mapping[int, int], rows: int) -> None:
        """K = 1 on an open road, whose rows come and go: row ``j`` of the new rows is old row ``keep[j]``; a row
        not in ``keep`` (a vehicle that just entered) starts with no passes and its current offset as its last."""
        for name in ("net", "best", "ever"):
            old = getattr(self, name)
            new = np.zeros((1, rows), dtype=old.dtype)
            for j, i in keep.items():
                new[0, j] = old[0, i]
            setattr(self, name, new)

    def tensors(self) -> dict[str, Any]:
        """Every array by name (the books as ``books.<name>``): what a lockstep iteration holds."""
        return {**{name: getattr(self, name) for name in self.ARRAYS},
                **{f"books.{name}": value for name, value in self.books.items()}}

    def point_at(self, arrays: Mapping[str, Any]) -> None:
        """Take ``arrays`` (as :meth:`tensors` names them) as the state's own."""
        for name in self.ARRAYS:
            setattr(self, name, arrays[name])
        self.books = {name: arrays[f"books.{name}"] for name in self.books}


class Problem:
    """The per-run constants of the learning problem for the runs of ``cfgs`` (they share the observation
    settings; the reward preset, the overtake bonus and the feature scales may differ), as arrays of ``xp``."""

    def __init__(self, cfgs: Sequence[LaneFreeConfig], xp: Any) -> None:
        self.cfg = cfgs[0]
        self.xp = xp
        self.runs = len(cfgs)
        presets = [get_preset(c.reward.preset) for c in cfgs]
        self.weights = {**{t.weight: xp.asarray(np.array([term_weight(t, p, c.reward) for p, c in zip(presets, cfgs)]))
                           for t in COST_TERMS},
                        **{name: xp.asarray(np.array([getattr(p, name) for p in presets]))
                           for name in ("use_collision", "use_overtake")}}
        """Each cost's weight (by :attr:`~lanefree_sumo.rl.rewards.CostTerm.weight`) and the r_c / r_o switches,
        ``[K]`` each."""
        self.ego_scale, self.neighbour_scale = (xp.asarray(np.array(s)) for s in zip(*(feature_scales(c)
                                                                                        for c in cfgs)))
        modes = [c.reward.overtake_bonus for c in cfgs]
        unknown = sorted(set(modes) - set(OVERTAKE_BONUS_MODES))
        if unknown:
            raise ValueError(f"unknown overtake bonus mode {unknown[0]!r}; one of {', '.join(OVERTAKE_BONUS_MODES)}")
        bonus = np.array(modes)
        self.once = xp.asarray(bonus == "once_per_vehicle")
        self.net_passes = xp.asarray(bonus == "net_passes")
        zones = [p.w_y > 0.0 for p in presets]
        self._zones = all(zones) or (False if not any(zones) else None)
        """The zones are part of every run's reward (True), of none (False), of some (None)."""
        o = self.cfg.observation
        self._rows = max(o.n_neighbours, o.max_rows if o.kind == "set" else 0)
        """How many of the nearest vehicles an observation and the fields read."""

    def __getstate__(self) -> dict[str, Any]:
        """Pickled (a batch checkpoint holds its env) with the namespace's device name in place of the namespace."""
        return {**self.__dict__, "xp": self.xp.name}

    def __setstate__(self, saved: dict[str, Any]) -> None:
        self.__dict__.update(saved, xp=array_namespace(device_name(saved["xp"])))

    # -- episodes ---------------------------------------------------------------------------------------------
    def begin(self, state: ProblemState, view: AgentView, index: Any, extra_ego: Any = None) -> Any:
        """Start the episodes of the runs ``index`` (their books and pass books cleared) on ``view``; returns every
        run's observation."""
        for book in state.books.values():
            book[index] = 0.0
        state.net[index], state.best[index], state.ever[index] = 0, 0, False
        obs = self.observe(state, view, extra_ego)
        state.prev_dx[index] = view.dx[index]
        return obs

    # -- one step ---------------------------------------------------------------------------------------------
    def observe(self, state: ProblemState, view: AgentView, extra_ego: Any = None) -> Any:
        """Every run's observation (specification §5; ``extra_ego`` ``[K, E']``: features appended to the ego's,
        the on-ramp's); keeps who is in range and their order by distance in ``state``."""
        return self._observe(state, view, extra_ego)[0]

    def _observe(self, state: ProblemState, view: AgentView, extra_ego: Any) -> tuple[Any, Any, Any]:
        """(:meth:`observe`, the nearest vehicles' (dx, dy, vx, vy, length, width) ``[K, rows, 6]``, how many are
        in range ``[K]``)."""
        o, xp, runs = self.cfg.observation, self.xp, self.runs
        dx, dy = view.dx, view.dy
        in_range = (xp.abs(dx) <= o.range_m) & view.others
        order = xp.argsort_stable(xp.where(in_range, xp.hypot(dx, dy), xp.inf), axis=1)
        state.in_range, state.order = in_range, order
        seen = xp.sum(in_range, axis=1)
        shown = order[:, :self._rows]
        if shown.shape[1] < self._rows:  # fewer vehicles on the road than rows: the rest repeats the last one
            shown = xp.concatenate([shown, xp.broadcast_to(shown[:, -1:], (runs, self._rows - shown.shape[1]))],
                                   axis=1)
        # the nearest vehicles' (dx, dy, vx, vy, length, width), gathered once for the observation and the fields
        near = xp.take_along_axis(xp.stack([dx, dy, view.vx, view.vy, view.length, view.width], axis=-1),
                                  shown[..., None], 1)
        ego = xp.column_stack([view.y, view.vx_a, view.vy_a, view.v_desired]) / self.ego_scale
        if extra_ego is not None:
            ego = xp.concatenate([ego, extra_ego], axis=1)
        if o.kind == "vector":
            n = o.n_neighbours
            fill = xp.stack([xp.full(runs, o.range_m), xp.zeros(runs), view.vx_a, view.vy_a], axis=-1)[:, None, :]
            rows = xp.where((xp.arange(n) < seen[:, None])[..., None], near[:, :n, :NEIGHBOUR_FEATURES], fill)
            rows = rows / self.neighbour_scale[:, None, :]
            return xp.astype(xp.concatenate([ego, rows.reshape(runs, -1)], axis=1), np.float32), near, seen
        table = xp.zeros((runs, o.max_rows, NEIGHBOUR_FEATURES + 1), dtype=np.float32)
        shown_rows = xp.arange(o.max_rows) < seen[:, None]
        scaled = near[:, :o.max_rows, :NEIGHBOUR_FEATURES] / self.neighbour_scale[:, None, :]
        table[..., :NEIGHBOUR_FEATURES] = xp.astype(xp.where(shown_rows[..., None], scaled, 0.0), np.float32)
        table[..., NEIGHBOUR_FEATURES] = xp.astype(shown_rows, np.float32)
        return {"ego": xp.astype(ego, np.float32), "others": table}, near, seen

    def step(self, state: ProblemState, view: AgentView, collided: Any, agent_events: Any, background: Any,
             contact: Any, active: Any = None, intervened: Any = None, fallback: Any = None,
             extra_ego: Any = None) -> tuple[Any, Any, Rewards, Any]:
        """After the world's step: (every run's observation, its reward, the reward terms, its overtakes this step)
        from the scene ``view`` and the step's events ``[K]`` (whether the vehicle overlaps another, its
        collision events, the other vehicles' own, whether it touched a road boundary); the books of the
        ``active`` runs (None: every run) take the step. ``intervened``/``fallback`` ``[K]`` (None: no shield):
        the shield changed the action (the reward loses ``shield.intervention_penalty``) / found no certified
        one."""
        xp, r = self.xp, self.cfg.reward
        obs, near, seen = self._observe(state, view, extra_ego)
        passed, passed_by = pass_events(state.prev_dx, view.dx, self.cfg.observation.range_m,
                                        view.road_length[:, None])
        passed, passed_by = passed & state.in_range, passed_by & state.in_range
        overtakes = xp.count_nonzero(passed, axis=1)
        state.prev_dx = view.dx
        terms = self._rewards(state, view, near, seen, collided, self.earned(state, passed, passed_by) > 0)
        reward = terms.reward
        if intervened is not None:
            reward = xp.where(intervened, reward - self.cfg.shield.intervention_penalty, reward)

        error = view.vx_a - view.v_desired
        w = self.weights
        bonus = xp.where(w["use_overtake"] & terms.overtook & ~collided, r.overtake_reward, 0.0)
        values = {"return": reward, "return_bonus": bonus,
                  "return_collision": xp.where(w["use_collision"] & collided, r.collision_reward, 0.0),
                  "collisions": agent_events, "collision_steps": collided, "background_collisions": background,
                  "speed_dev_sum": xp.abs(error), "speed_error_sum": error, "speed_sum": view.vx_a,
                  "overtakes": overtakes, "boundary_contacts": contact,
                  **{f"sum_{name}": terms.costs[name] for name in COST_NAMES}, "sum_reward": reward}
        if intervened is not None:
            values.update(shield_interventions=intervened, shield_fallbacks=fallback)
        b = state.books
        for name, value in values.items():
            b[name] = b[name] + value if active is None else xp.where(active, b[name] + value, b[name])
        return obs, reward, terms, overtakes

    def earned(self, state: ProblemState, passed: Any, passed_by: Any) -> Any:
        """How many of this step's passes ``[K, N]`` earn the bonus ``[K]``, each run by its
        ``reward.overtake_bonus``: ``every_pass`` every pass; ``once_per_vehicle`` a vehicle's first pass in the
        episode only; ``net_passes`` a pass that raises the vehicle's passes minus its passes of the agent above
        the highest value it had in the episode (passing back a vehicle that just passed the agent earns
        nothing). A row is a vehicle (its identity through the episode); a row is never passed and passing at
        once. Books the passes in ``state``."""
        xp = self.xp
        state.net = state.net + xp.astype(passed, int) - xp.astype(passed_by, int)  # never both at once
        first = passed & ~state.ever
        gained = passed & (state.net > state.best)
        paid = xp.where(self.once[:, None], first, xp.where(self.net_passes[:, None], gained, passed))
        state.ever = state.ever | passed
        state.best = xp.where(gained, state.net, state.best)
        return xp.count_nonzero(paid, axis=1)

    def _rewards(self, state: ProblemState, view: AgentView, near: Any, seen: Any, collided: Any,
                 overtook: Any) -> Rewards:
        """Every run's reward terms (specification §7, paper Eq. 16; the scalar reference is
        :func:`~lanefree_sumo.rl.rewards.compute_reward`): the zones on every vehicle in range, the fields on the
        ``observation.n_neighbours`` nearest (``near``, ``seen``: :meth:`_observe`'s), the lateral terms within
        the vehicle's bounds."""
        n = self.cfg.observation.n_neighbours
        scene = RewardScene(view.dx, view.dy, view.vx, view.length, view.width, state.in_range, view.y - view.lo,
                            view.vx_a, view.vy_a, view.len_a, view.wid_a, view.v_desired, view.road_width,
                            near[:, :n], self.xp.minimum(seen, n), self.cfg.reward,
                            self.weights["w_y"] > 0.0 if self._zones is None else self._zones)
        return reward_terms(scene, self.weights, collided, overtook)


def episode_row(episode: int, steps: int, books: Mapping[str, Any], cfg: LaneFreeConfig, seed: int,
                wall_s: float) -> dict[str, Any]:
    """One episode's metrics (specification §8; one row of ``episodes.csv``) from a run's books (host numbers)
    after ``steps`` steps: sums as they are, per-step means over ``steps``; the traffic ``seed`` and the wall time
    ``wall_s`` (s)."""
    b, per = books, max(steps, 1)
    return {
        "episode": episode,
        "steps": steps,
        "return": float(b["return"]),
        "return_bonus": float(b["return_bonus"]),
        "return_collision": float(b["return_collision"]),
        "return_reciprocal": float(b["return"] - b["return_bonus"] - b["return_collision"]),
        "collisions": int(b["collisions"]),
        "collision_steps": int(b["collision_steps"]),
        "background_collisions": int(b["background_collisions"]),
        "speed_dev_mps": float(b["speed_dev_sum"] / per),
        "speed_dev_episode_mps": float(abs(b["speed_error_sum"]) / per),
        "speed_error_mps": float(b["speed_error_sum"] / per),
        "mean_speed_mps": float(b["speed_sum"] / per),
        "overtakes": int(b["overtakes"]),
        "boundary_contacts": int(b["boundary_contacts"]),
        "shield_interventions": int(b["shield_interventions"]),
        "shield_fallbacks": int(b["shield_fallbacks"]),
        **{f"mean_{t}": float(b[f"sum_{t}"] / per) for t in METRIC_TERMS},
        "density": cfg.scenario.density_veh_per_km,
        "seed": seed,
        "reward_preset": cfg.reward.preset,
        "wall_s": wall_s,
    }

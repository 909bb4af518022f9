"""Reward components of the lane-free agent (specification §7; Karalakou et al., Systems 2023, Eq. 16).

Pure numpy: no SUMO, no gym.  Units are SI throughout (m, s, m/s).  Coordinates follow specification §1:
``dx_j = wrap(x_j − x_agent)`` in [−L/2, L/2) on the ring, ``dy_j = y_j − y_agent`` with ``y``
measured from the right road edge (0 ≤ y ≤ W).

Every default comes from :class:`lanefree_sumo.config.RewardConfig` (``_DEFAULTS`` below); the
preset names from :data:`lanefree_sumo.config.RewardPreset`, the one list of them, and each preset's
weights from the components its name lists, as in the paper's Table 4 (specification §7 table).

Conventions shared by the functions taking neighbour arrays (``field_cost``, ``zone_target``,
``agent_overlaps``): arrays are aligned by vehicle and broadcast against each other (so ``lens``
may be a scalar); a row with a non-finite (NaN) position or speed is treated as *absent*, so
padded arrays can be passed directly.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from typing import Any, cast, get_args

import numpy as np
from numpy.typing import ArrayLike

from lanefree_sumo.config import RewardConfig, RewardPreset
from lanefree_sumo.config.schema import OvertakeBonus
from lanefree_sumo.rl.fields_zones import _rows, ellipsoid, field_cost, field_terms, zone_target, zone_targets
from lanefree_sumo.sim.state import row_sum
from lanefree_sumo.sim.xp import namespace

__all__ = [
    "ellipsoid",
    "field_cost",
    "zone_target",
    "reciprocal_reward",
    "longitudinal_cost",
    "lateral_cost",
    "detect_overtakes",
    "pass_events",
    "agent_overlaps",
    "RewardWeights",
    "PRESETS",
    "get_preset",
    "Rewards",
    "RewardScene",
    "CostTerm",
    "COST_TERMS",
    "reward_terms",
    "compute_reward",
]

_DEFAULTS = RewardConfig()

# --------------------------------------------------------------------------------------------
# Costs, events, combination
# --------------------------------------------------------------------------------------------


def _ndim(value: Any) -> int:
    """The number of axes of an array, a tensor or a number (0)."""
    return value.ndim if hasattr(value, "ndim") else int(np.ndim(value))


def longitudinal_cost(
    vx: Any,
    v_d_eff: Any,
    *,
    min_desired_speed: float = _DEFAULTS.min_desired_speed_mps,
) -> Any:
    """``c_x = min(1, |vx − v_d,eff| / max(v_d,eff, min_desired_speed))`` (–); speeds in m/s. Element-wise;
    scalar inputs give a ``float``."""
    xp = namespace(vx, v_d_eff)
    c_x = xp.minimum(1.0, xp.abs(xp.subtract(vx, v_d_eff)) / xp.maximum(v_d_eff, min_desired_speed))
    return float(c_x) if xp.ndim(c_x) == 0 else c_x


def lateral_cost(y: Any, y_d: Any, road_width: Any) -> Any:
    """``c_y = |y − y_d| / W`` (–); y, y_d and road_width W in m. Element-wise; scalar inputs give a ``float``."""
    xp = namespace(y, y_d)
    c_y = xp.abs(xp.subtract(y, y_d)) / road_width
    return float(c_y) if xp.ndim(c_y) == 0 else c_y


def reciprocal_reward(
    c_x: ArrayLike,
    c_y: ArrayLike,
    c_f: ArrayLike,
    collided: ArrayLike,
    overtook: ArrayLike,
    w_x: ArrayLike,
    w_y: ArrayLike,
    w_f: ArrayLike,
    *,
    epsilon_r: float = _DEFAULTS.epsilon_r,
    collision_reward: float = _DEFAULTS.collision_reward,
    overtake_reward: float = _DEFAULTS.overtake_reward,
    use_collision: ArrayLike = True,
    use_overtake: ArrayLike = True,
) -> float | np.ndarray:
    """Paper Eq. 16: ``ε_r/(ε_r + w_x c_x + w_y c_y + w_f c_f) + r_c·[collided]
    + r_o·[overtook and not collided]`` (–).

    ``overtook`` is an indicator (a count > 0 counts once: the bonus is per step, not per
    vehicle).  ``use_collision`` / ``use_overtake`` switch the r_c / r_o terms off (presets; one per
    row when runs differ). Arrays broadcast; scalar inputs give a ``float``.
    """
    if max(_ndim(v) for v in [c_x, c_y, c_f, collided, overtook, w_x, use_collision]) == 0:  # plain floats
        r0 = epsilon_r / (epsilon_r + float(w_x) * float(c_x) + float(w_y) * float(c_y)  # type: ignore[arg-type]
                          + float(w_f) * float(c_f))  # type: ignore[arg-type]
        hit, passed = bool(collided), bool(overtook)
        return (r0 + (collision_reward if use_collision and hit else 0.0)
                + (overtake_reward if use_overtake and passed and not hit else 0.0))
    xp = namespace(c_x, c_y, c_f, collided, overtook, w_x)
    col = xp.astype(xp.asarray(collided), bool)
    ovt = xp.astype(xp.asarray(overtook), bool)
    denom = epsilon_r + xp.multiply(w_x, c_x) + xp.multiply(w_y, c_y) + xp.multiply(w_f, c_f)
    r = xp.divide(epsilon_r, denom)  # not ``epsilon_r / denom``: torch's number / tensor is a reciprocal times
    # a switched-off term adds 0.0: the same number as not adding it
    r = r + xp.where(xp.logical_and(use_collision, col), collision_reward, 0.0)
    r = r + xp.where(xp.logical_and(use_overtake, ovt & ~col), overtake_reward, 0.0)
    return float(r) if xp.ndim(r) == 0 else r


def pass_events(
    prev_dx: ArrayLike,
    dx: ArrayLike,
    range_m: ArrayLike,
    ring_length: ArrayLike,
) -> tuple[np.ndarray, np.ndarray]:
    """(passed, passed_by): boolean masks of the vehicles the agent passed, and of those that passed it,
    between two steps.

    prev_dx, dx: wrapped offsets (m) of the same vehicles (aligned by index) at the previous and
    the current step; NaN = not present / not in range.  A pass is ``prev_dx > 0`` and
    ``dx ≤ 0`` (being passed: ``prev_dx ≤ 0`` and ``dx > 0``) for a vehicle with ``|dx| ≤ range_m``
    at both steps and ``|dx| < ring_length/4`` at both steps, so a jump across the ring seam
    (dx ≈ ±L/2) is never a pass, nor is a vehicle entering or leaving range. Element-wise over arrays of
    any shape (several agents' rows); ``range_m`` and ``ring_length`` broadcast against them.
    """
    xp = namespace(prev_dx, dx)
    aligned = isinstance(prev_dx, np.ndarray) and isinstance(dx, np.ndarray) and prev_dx.shape == dx.shape
    p, c = _rows(prev_dx, dx) if xp.is_numpy and not aligned else (cast(np.ndarray, prev_dx), cast(np.ndarray, dx))
    quarter = 0.25 * xp.asarray(ring_length)
    with xp.errstate(invalid="ignore"):
        valid = (
            xp.isfinite(p) & xp.isfinite(c)
            & (xp.abs(p) <= range_m) & (xp.abs(c) <= range_m)
            & (xp.abs(p) < quarter) & (xp.abs(c) < quarter)
        )
        return valid & (p > 0.0) & (c <= 0.0), valid & (p <= 0.0) & (c > 0.0)


def detect_overtakes(
    prev_dx: ArrayLike,
    dx: ArrayLike,
    range_m: float,
    ring_length: float,
) -> int:
    """Number of vehicles the agent passed between two steps (:func:`pass_events`)."""
    return int(np.count_nonzero(pass_events(prev_dx, dx, range_m, ring_length)[0]))


OVERTAKE_BONUS_MODES: tuple[str, ...] = get_args(OvertakeBonus)
"""``reward.overtake_bonus``'s values (the config's :data:`~lanefree_sumo.config.schema.OvertakeBonus`), as
:meth:`~lanefree_sumo.rl.problem.Problem.earned` books them."""


def agent_overlaps(
    dx: ArrayLike,
    dy: ArrayLike,
    agent_len: float,
    agent_wid: float,
    lens: ArrayLike,
    wids: ArrayLike,
) -> bool:
    """Whether the agent's rectangle overlaps any vehicle's (specification §4).

    Overlap: ``|dx| < (agent_len + len_j)/2`` and ``|dy| < (agent_wid + wid_j)/2`` (m); touching
    edges do not overlap.
    """
    dx_, dy_, lens_, wids_ = _rows(dx, dy, lens, wids)
    with np.errstate(invalid="ignore"):
        hit = (np.abs(dx_) < 0.5 * (agent_len + lens_)) & (np.abs(dy_) < 0.5 * (agent_wid + wids_))
    return bool(hit.any())


# --------------------------------------------------------------------------------------------
# Presets
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RewardWeights:
    """Weights of one reward preset (paper Table 4): w_x, w_y, w_f (–) and the r_c / r_o switches."""

    w_x: float
    w_y: float
    w_f: float
    use_collision: bool
    use_overtake: bool


PRESET_COMPONENTS: tuple[str, ...] = ("fields", "zones", "overtake", "collision")
"""What a reward preset's name may list, joined by ``_`` (paper Table 4's components)."""


def _weights(name: str) -> RewardWeights:
    """A preset's weights from the components its name lists (paper Table 4, specification §7): ``fields``
    w_f = 1; ``zones`` w_y = 0.65 and w_x = 0.35 (w_x = 0.65 without zones); ``collision`` r_c on;
    ``overtake`` r_o on. A name with another part is a mistake in the config's list: ValueError."""
    parts = set(name.split("_"))
    if not parts <= set(PRESET_COMPONENTS):
        unknown = ", ".join(sorted(parts - set(PRESET_COMPONENTS)))
        raise ValueError(f"reward preset {name!r}: unknown component(s) {unknown}; a preset's name joins some of "
                         f"{', '.join(PRESET_COMPONENTS)} with '_'")
    zones = "zones" in parts
    return RewardWeights(w_x=0.35 if zones else 0.65, w_y=0.65 if zones else 0.0,
                         w_f=1.0 if "fields" in parts else 0.0,
                         use_collision="collision" in parts, use_overtake="overtake" in parts)


PRESETS: dict[str, RewardWeights] = {name: _weights(name) for name in get_args(RewardPreset)}
"""Every reward preset's weights, by name: the names are the config's (:data:`lanefree_sumo.config.RewardPreset`)."""


def get_preset(name: str) -> RewardWeights:
    """The weights of preset ``name``; ``ValueError`` listing the valid names if unknown."""
    try:
        return PRESETS[name]
    except (KeyError, TypeError):
        raise ValueError(
            f"unknown reward preset {name!r}; valid presets: {', '.join(PRESETS)}"
        ) from None


# --------------------------------------------------------------------------------------------
# One step
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RewardScene:
    """What the reward sees of one step, per run ``[K]`` (m, m/s; numpy arrays, or tensors of one device): the
    learning vehicle's own values, its lateral position ``y`` within its bounds ``[0, road_width]``, every vehicle
    row ``[K, N]`` (``present``: in range) for the zones, and the nearest ``[K, n, 6]`` (dx, dy, vx, vy, length,
    width; the first ``seen`` real) for the fields. The zones' targets (``y_d``, ``v_d_eff``, ``blocked``) are
    filled in by :func:`reward_terms` before the costs are taken."""

    dx: Any
    dy: Any
    vx: Any
    length: Any
    width: Any
    present: Any
    y: Any
    vx_a: Any
    vy_a: Any
    len_a: Any
    wid_a: Any
    v_desired: Any
    road_width: Any
    near: Any
    seen: Any
    config: RewardConfig
    zones: Any
    """Whether the zones are part of the reward: True (every run), False (none) or a ``[K]`` mask."""
    y_d: Any = None
    v_d_eff: Any = None
    blocked: Any = None


def _longitudinal(s: RewardScene) -> Any:
    """c_x: the speed's distance from the effective desired speed (:func:`longitudinal_cost`)."""
    return longitudinal_cost(s.vx_a, s.v_d_eff, min_desired_speed=s.config.min_desired_speed_mps)


def _lateral(s: RewardScene) -> Any:
    """c_y: the lateral distance from the zones' target (:func:`lateral_cost`); 0 without zones."""
    xp = namespace(s.vx_a)
    if s.zones is False:
        return xp.zeros(s.vx_a.shape)
    cost = lateral_cost(s.y, s.y_d, s.road_width)
    return cost if s.zones is True else xp.where(s.zones, cost, 0.0)


def _fields(s: RewardScene) -> Any:
    """c_f: the potential fields of the nearest vehicles, capped at 1 (:func:`field_cost`)."""
    xp, r, near = namespace(s.vx_a), s.config, s.near
    e_c, e_b = field_terms(near[..., 0], near[..., 1], s.vx_a[:, None] - near[..., 2],
                           s.vy_a[:, None] - near[..., 3], s.len_a[:, None], s.wid_a[:, None], near[..., 4],
                           near[..., 5], magnitude=r.field_magnitude, critical_exponents=r.critical_exponents,
                           broad_exponents=r.broad_exponents, k_r=r.k_r_s_per_m, e_v=r.e_v_s_per_m,
                           stretch=r.broad_stretch)
    valid = xp.arange(near.shape[1]) < s.seen[:, None]
    return xp.minimum(1.0, row_sum(xp.where(valid, e_c, 0.0), s.seen) + row_sum(xp.where(valid, e_b, 0.0), s.seen))


@dataclass(frozen=True)
class CostTerm:
    """One cost of the reciprocal reward (paper Eq. 16): ``cost(scene)`` ``[K]`` in [0, 1], weighted by
    ``weight``: a field of the preset's :class:`RewardWeights` (the paper's terms), or of
    :class:`~lanefree_sumo.config.RewardConfig` (a term beyond the paper's, its weight a config value)."""

    name: str
    weight: str
    cost: Callable[[RewardScene], Any]


COST_TERMS: tuple[CostTerm, ...] = (CostTerm("c_x", "w_x", _longitudinal), CostTerm("c_y", "w_y", _lateral),
                                    CostTerm("c_f", "w_f", _fields))
"""The reward's costs, in the order the reciprocal adds them: the one list a new term joins."""

COST_NAMES: tuple[str, ...] = tuple(t.name for t in COST_TERMS)


def term_weight(term: CostTerm, preset: RewardWeights, config: RewardConfig) -> float:
    """The weight of ``term`` in a run with ``preset`` and ``config`` (:class:`CostTerm`)."""
    return float(getattr(preset, term.weight) if hasattr(preset, term.weight) else getattr(config, term.weight))


@dataclass
class Rewards:
    """Every term of one step's reward (``info``): each cost of :data:`COST_TERMS` (–, also as an attribute:
    ``terms.c_x``), the zones' target ``y_d`` (m) and effective desired speed ``v_d_eff`` (m/s), ``blocked``,
    ``collided``, ``overtook`` and the ``reward``; ``[K]`` arrays over runs, or numbers for one vehicle
    (:func:`compute_reward`)."""

    costs: dict[str, Any]
    y_d: Any
    v_d_eff: Any
    blocked: Any
    collided: Any
    overtook: Any
    reward: Any

    def __getattr__(self, name: str) -> Any:
        costs = self.__dict__.get("costs", {})
        if name in costs:
            return costs[name]
        raise AttributeError(name)

    def as_dict(self) -> dict[str, Any]:
        """The terms by name: the costs, then y_d, v_d_eff, blocked, collided, overtook, reward."""
        return {**self.costs, "y_d": self.y_d, "v_d_eff": self.v_d_eff, "blocked": self.blocked,
                "collided": self.collided, "overtook": self.overtook, "reward": self.reward}


REWARD_TERMS: tuple[str, ...] = (*COST_NAMES, "y_d", "v_d_eff", "blocked", "collided", "overtook", "reward")
"""The keys of :meth:`Rewards.as_dict`, every step's ``info`` has them."""


def reward_terms(scene: RewardScene, weights: Mapping[str, Any], collided: Any, overtook: Any) -> Rewards:
    """Every run's reward terms (paper Eq. 16, specification §7): the zones' targets, then each cost of
    :data:`COST_TERMS` and the reciprocal of their weighted sum, plus r_c and r_o. ``weights``: each term's
    weight by its :attr:`CostTerm.weight` name and ``use_collision``/``use_overtake``, ``[K]`` each."""
    xp, r = namespace(scene.vx_a), scene.config
    width = scene.road_width
    if scene.zones is False:
        y_d, v_d_eff, blocked = 0.5 * width, scene.v_desired, xp.zeros(scene.vx_a.shape, dtype=bool)
    else:
        y_d, v_d_eff, blocked = zone_targets(scene.dx, scene.dy, scene.vx, scene.length, scene.width, scene.y,
                                             scene.vx_a, scene.len_a, scene.wid_a, scene.v_desired, width,
                                             time_gap=r.zone_time_gap_s, margin=r.zone_margin_m,
                                             present=scene.present)
        if scene.zones is not True:
            y_d = xp.where(scene.zones, y_d, 0.5 * width)
            v_d_eff = xp.where(scene.zones, v_d_eff, scene.v_desired)
            blocked = scene.zones & blocked
    scene = replace(scene, y_d=y_d, v_d_eff=v_d_eff, blocked=blocked)
    costs = {t.name: t.cost(scene) for t in COST_TERMS}
    denom = r.epsilon_r
    for t in COST_TERMS:
        denom = denom + xp.multiply(weights[t.weight], costs[t.name])
    reward = xp.divide(r.epsilon_r, denom)  # not ``epsilon_r / denom``: torch's number / tensor is a reciprocal times
    col, ovt = xp.astype(xp.asarray(collided), bool), xp.astype(xp.asarray(overtook), bool)
    reward = reward + xp.where(xp.logical_and(weights["use_collision"], col), r.collision_reward, 0.0)
    reward = reward + xp.where(xp.logical_and(weights["use_overtake"], ovt & ~col), r.overtake_reward, 0.0)
    return Rewards(costs, y_d, v_d_eff, blocked, collided, overtook, reward)


def compute_reward(
    dx: ArrayLike,
    dy: ArrayLike,
    vx: ArrayLike,
    vy: ArrayLike,
    lens: ArrayLike,
    wids: ArrayLike,
    agent_y: float,
    agent_vx: float,
    agent_vy: float,
    agent_len: float,
    agent_wid: float,
    v_desired: float,
    road_width: float,
    weights: RewardWeights | str,
    *,
    observed: ArrayLike | None = None,
    collided: bool | None = None,
    overtook: bool | int = False,
    config: RewardConfig | None = None,
) -> Rewards:
    """All terms of one vehicle's step (paper Eq. 16): :func:`reward_terms` of a scene of one (the learning
    problem, :mod:`lanefree_sumo.rl.problem`, evaluates the same for every run at once), as numbers.

    dx, dy, vx, vy, lens, wids: the vehicles in observation range (m, m, m/s, m/s, m, m) — the
    zones use all of them; the fields use the rows selected by ``observed`` (boolean mask or
    index array of the n observed neighbours; ``None`` = all rows), a row with a non-finite value absent.
    Agent state: agent_y (m), agent_vx, agent_vy (m/s), dimensions (m), nominal ``v_desired`` (m/s); road_width
    W (m). ``weights``: a :class:`RewardWeights` or a preset name.

    ``collided``: ``None`` computes the overlap from the given rows (pass every vehicle within a
    few metres, or the env's own result).  ``overtook``: a bool or the count from
    :func:`detect_overtakes` (the env keeps the vehicle identities across steps).
    ``config``: the :class:`RewardConfig` whose constants are used (default: the defaults).

    When ``weights.w_y == 0`` zones are not evaluated: ``y_d = W/2``, ``v_d_eff = v_desired``,
    ``blocked = False``, ``c_y = 0``.  ``c_f`` is always computed (reported even when w_f = 0).
    """
    cfg = _DEFAULTS if config is None else config
    w = get_preset(weights) if isinstance(weights, str) else weights
    dx_, dy_, vx_, vy_, lens_, wids_ = _rows(dx, dy, vx, vy, lens, wids)
    if observed is None:
        sel: Any = slice(None)
    else:
        sel = np.asarray(observed)
        if sel.dtype != bool:
            sel = sel.astype(int)  # an empty list would otherwise be a float index
    near = np.column_stack([dx_[sel], dy_[sel], vx_[sel], vy_[sel], lens_[sel], wids_[sel]])
    near = near[np.isfinite(near[:, :4]).all(axis=1)][None]  # NaN/inf rows are absent
    if collided is None:
        collided = agent_overlaps(dx_, dy_, agent_len, agent_wid, lens_, wids_)

    def one(value: float) -> np.ndarray:
        return np.array([value], dtype=float)

    scene = RewardScene(dx_[None], dy_[None], vx_[None], lens_[None], wids_[None], None, one(agent_y),
                        one(agent_vx), one(agent_vy), one(agent_len), one(agent_wid), one(v_desired),
                        one(road_width), near, np.array([near.shape[1]]), cfg, w.w_y > 0.0)
    weight = {**{t.weight: one(term_weight(t, w, cfg)) for t in COST_TERMS},
              "use_collision": np.array([w.use_collision]), "use_overtake": np.array([w.use_overtake])}
    terms = reward_terms(scene, weight, np.array([bool(collided)]), np.array([bool(overtook)]))
    return Rewards({name: float(value[0]) for name, value in terms.costs.items()}, float(terms.y_d[0]),
                   float(terms.v_d_eff[0]), bool(terms.blocked[0]), bool(collided), bool(overtook),
                   float(terms.reward[0]))

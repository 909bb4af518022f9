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

from dataclasses import dataclass
from typing import Any, cast, get_args

import numpy as np
from numpy.typing import ArrayLike

from lanefree_sumo.config import RewardConfig, RewardPreset
from lanefree_sumo.config.schema import OvertakeBonus
from lanefree_sumo.rl.fields_zones import _rows, ellipsoid, field_cost, zone_target
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
    "RewardTerms",
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


@dataclass
class RewardTerms:
    """Every term of one step's reward, for ``info`` (costs –, y_d m, v_d_eff m/s)."""

    c_x: float
    c_y: float
    c_f: float
    y_d: float
    v_d_eff: float
    blocked: bool
    collided: bool
    overtook: bool
    reward: float

    def as_dict(self) -> dict[str, Any]:
        """Plain dict of the terms."""
        return dict(self.__dict__)


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
) -> RewardTerms:
    """Combine all terms for one step (paper Eq. 16) and return them.

    dx, dy, vx, vy, lens, wids: the vehicles in observation range (m, m, m/s, m/s, m, m) — the
    zones use all of them; the fields use the rows selected by ``observed`` (boolean mask or
    index array of the n observed neighbours; ``None`` = all rows).  Agent state: agent_y (m),
    agent_vx, agent_vy (m/s), dimensions (m), nominal ``v_desired`` (m/s); road_width W (m).
    ``weights``: a :class:`RewardWeights` or a preset name.

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

    if w.w_y > 0.0:
        y_d, v_d_eff, blocked = zone_target(
            dx_, dy_, vx_, lens_, wids_, agent_y, agent_vx, agent_len, agent_wid, v_desired,
            road_width, time_gap=cfg.zone_time_gap_s, margin=cfg.zone_margin_m,
        )
        c_y = lateral_cost(agent_y, y_d, road_width)
    else:
        y_d, v_d_eff, blocked, c_y = 0.5 * road_width, float(v_desired), False, 0.0

    c_x = longitudinal_cost(agent_vx, v_d_eff, min_desired_speed=cfg.min_desired_speed_mps)

    if observed is None:
        sel: Any = slice(None)
    else:
        sel = np.asarray(observed)
        if sel.dtype != bool:
            sel = sel.astype(int)  # an empty list would otherwise be a float index
    c_f = field_cost(
        dx_[sel], dy_[sel], agent_vx - vx_[sel], agent_vy - vy_[sel], agent_len, agent_wid,
        lens_[sel], wids_[sel],
        magnitude=cfg.field_magnitude, critical_exponents=cfg.critical_exponents,
        broad_exponents=cfg.broad_exponents, k_r=cfg.k_r_s_per_m, e_v=cfg.e_v_s_per_m,
        stretch=cfg.broad_stretch,
    )

    if collided is None:
        collided = agent_overlaps(dx_, dy_, agent_len, agent_wid, lens_, wids_)
    collided = bool(collided)
    overtook = bool(overtook)

    reward = reciprocal_reward(
        c_x, c_y, c_f, collided, overtook, w.w_x, w.w_y, w.w_f,
        epsilon_r=cfg.epsilon_r, collision_reward=cfg.collision_reward,
        overtake_reward=cfg.overtake_reward,
        use_collision=w.use_collision, use_overtake=w.use_overtake,
    )
    return RewardTerms(c_x, c_y, c_f, float(y_d), float(v_d_eff), bool(blocked), collided,
                       overtook, float(reward))

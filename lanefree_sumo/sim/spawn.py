"""Initial placement of vehicles at a density (specification §1).

The road is cut into a grid of cells, one vehicle per cell: ``rows`` across the width and
``cols`` along the ring.  A cell is long enough for the longest vehicle plus ``gap_x`` and wide
enough for the widest plus ``gap_y``; each vehicle sits at a uniform random offset inside its
cell.  So vehicles never overlap, every pair in a row keeps a bumper gap ≥ ``gap_x``, and the
largest number of vehicles that fits is exactly ``rows × cols``.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from lanefree_sumo.config import ConfigError, LaneFreeConfig
from lanefree_sumo.sim.road import road_kind
from lanefree_sumo.sim.state import VehicleState

AGENT_ID = "agent"
"""SUMO id of the (first) agent vehicle; further agents are ``agent1``, ``agent2``, …"""


def agent_id(index: int) -> str:
    """SUMO id of agent vehicle ``index`` (0, 1, …): ``agent``, ``agent1``, ``agent2``, …"""
    return AGENT_ID if index == 0 else f"{AGENT_ID}{index}"


def is_agent_id(vid: str) -> bool:
    """Whether ``vid`` names an agent vehicle (:func:`agent_id`)."""
    return vid == AGENT_ID or (vid.startswith(AGENT_ID) and vid[len(AGENT_ID):].isdigit())


def agent_count(cfg: LaneFreeConfig) -> int:
    """Agent vehicles on the road: ``scenario.agents`` with an agent, else 0."""
    return cfg.scenario.agents if cfg.scenario.with_agent else 0


def background_id(index: int) -> str:
    """SUMO id of background vehicle ``index``."""
    return f"bg{index}"


def without_agents(cfg: LaneFreeConfig) -> LaneFreeConfig:
    """``cfg`` with no agent on the road (``scenario.with_agent`` off), every other value as it is: the
    background of the open road, drawn before its agents start."""
    return replace(cfg, scenario=replace(cfg.scenario, with_agent=False))


def grid_shape(cfg: LaneFreeConfig) -> tuple[int, int]:
    """(rows, cols) of the spawn grid for the vehicle classes on the road."""
    sc = cfg.scenario
    classes = [sc.background] + ([sc.agent] if sc.with_agent else [])
    max_len = max(c.length_m for c in classes)
    max_wid = max(c.width_m for c in classes)
    rows = int(np.floor(cfg.road.width_m / (max_wid + sc.spawn.gap_y_m)))
    cols = int(np.floor(cfg.road.main_length_m / (max_len + sc.spawn.gap_x_m)))
    return rows, cols


def max_density(cfg: LaneFreeConfig) -> float:
    """Largest background density that can be placed (veh/km)."""
    rows, cols = grid_shape(cfg)
    capacity = rows * cols - agent_count(cfg)
    return capacity * 1000.0 / cfg.road.main_length_m


def check_fits(cfg: LaneFreeConfig) -> None:
    """Refuse (:class:`ConfigError`) a density whose vehicles (background and agents) do not fit on the road
    in :func:`spawn`'s grid, or that puts no vehicle on the ring: the check :func:`spawn` makes, without
    drawing a state (a verb makes it before it writes anything)."""
    sc = cfg.scenario
    n_bg = cfg.background_vehicles
    k = agent_count(cfg)
    rows, cols = grid_shape(cfg)
    if n_bg < 1 and road_kind(cfg).periodic:
        raise ConfigError(
            f"density {sc.density_veh_per_km:g} veh/km puts no vehicle on a "
            f"{cfg.road.length_m:g} m ring; use at least {1000.0 / cfg.road.length_m:g} veh/km"
        )
    if n_bg + k > rows * cols:
        raise ConfigError(
            f"density {sc.density_veh_per_km:g} veh/km ({n_bg} vehicles{f' and {k} agents' if k > 1 else ''}) "
            "does not fit on a "
            f"{cfg.road.main_length_m:g} m × {cfg.road.width_m:g} m {cfg.road.kind}; the maximum is "
            f"{max_density(cfg):.0f} veh/km"
        )


def spawn(cfg: LaneFreeConfig, rng: np.random.Generator) -> VehicleState:
    """Random non-overlapping initial state: background vehicles, then the agents if any (the last
    :func:`agent_count` rows; with one agent the draws are those of the one-agent scenario).

    On the on-ramp (``road.kind``) they start on the main road, which may also start empty.
    Raises :class:`ConfigError` when the density does not fit on the road.
    """
    check_fits(cfg)
    sc = cfg.scenario
    n_bg = cfg.background_vehicles
    k = agent_count(cfg)
    n = n_bg + k
    rows, cols = grid_shape(cfg)
    cells = rng.choice(rows * cols, size=n, replace=False)
    row, col = np.divmod(cells, cols)
    length = np.full(n, sc.background.length_m)
    width = np.full(n, sc.background.width_m)
    v_desired = rng.uniform(sc.background.desired_speed_min_mps, sc.background.desired_speed_max_mps, n)
    if k:
        length[n_bg:] = sc.agent.length_m
        width[n_bg:] = sc.agent.width_m
        v_desired[n_bg:] = sc.agent.desired_speed_min_mps
    cell_len = cfg.road.main_length_m / cols
    cell_wid = cfg.road.width_m / rows
    # centre ranges inside a cell keep gap/2 to the cell borders
    slack_x = cell_len - length - sc.spawn.gap_x_m
    slack_y = cell_wid - width - sc.spawn.gap_y_m
    x = col * cell_len + 0.5 * sc.spawn.gap_x_m + 0.5 * length + rng.uniform(0.0, 1.0, n) * slack_x
    y = row * cell_wid + 0.5 * sc.spawn.gap_y_m + 0.5 * width + rng.uniform(0.0, 1.0, n) * slack_y
    ids = [background_id(i) for i in range(n_bg)] + [agent_id(i) for i in range(k)]
    controlled = np.ones(n, dtype=bool)
    controlled[n_bg:] = False
    return VehicleState(
        ids=ids,
        x=np.mod(x, cfg.road.main_length_m),
        y=y,
        vx=np.full(n, sc.spawn.initial_speed_mps),
        vy=np.zeros(n),
        length=length,
        width=width,
        v_desired=v_desired,
        controlled=controlled,
    )

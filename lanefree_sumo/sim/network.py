"""The ring road as SUMO input files (pure file writing; SUMO itself runs in ``sumo_backend``).

A closed ring of ``EDGES`` equal edges, each ONE lane as wide as the road, laid on a circle of
circumference L with ``spreadType="center"`` so the lane centre line is the ring.  Each edge's
``length`` attribute is set to exactly L / EDGES so that SUMO lane positions add up to the
centre-line coordinate x: ``x = edge_index · L / EDGES + lane position``.  Internal junction
lanes are disabled (``--no-internal-links``), so a vehicle is always on one of the edges.

Files for a ring ``ring_L<L>_W<W>`` under ``sumo_nets/`` (committed; other sizes in a cache folder,
:func:`nets_cache`):
``.nod.xml``/``.edg.xml`` (plain input), ``.net.xml`` (netconvert output), ``.add.xml``
(vehicle types and the looping route; rewritten from the config at every start).
"""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from lanefree_sumo.config import LaneFreeConfig, VehicleClassConfig
from lanefree_sumo.sim.road import road_kind
from lanefree_sumo.sim.xp import namespace

EDGES = 4
SHAPE_POINTS_PER_EDGE = 24
NETS_DIR = Path(__file__).resolve().parents[2] / "sumo_nets"
ROUTE_ID = "ring_loop"
VTYPE_AGENT = "agent"
VTYPE_BG_SLOW = "bg_slow"
VTYPE_BG_FAST = "bg_fast"


def edge_length(length_m: Any) -> Any:
    """Length of each of the ring's ``EDGES`` equal edges (m; a scalar, or an array of rings' lengths)."""
    return length_m / EDGES


def ring_to_edge(x: np.ndarray, length_m: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
    """x along the centre line (m, in [0, L)) → (edge index, position on that edge in m).

    THE mapping between the ring coordinate and SUMO's (edge, lane position); its inverse is
    ``edge_index · L / EDGES + lane position``."""
    xp = namespace(x)
    segment = edge_length(length_m)
    edge = xp.minimum(xp.astype(xp.asarray(x) // segment, int), EDGES - 1)
    return edge, x - edge * segment


def edge_to_ring(edge: np.ndarray | int, position_m: np.ndarray | float, length_m: np.ndarray | float) -> np.ndarray:
    """(edge index, position on that edge in m) → x along the centre line (m)."""
    return namespace(edge).asarray(edge) * edge_length(length_m) + position_m


def edge_id(index: int) -> str:
    return f"e{index}"


def ring_name(length_m: float, width_m: float) -> str:
    return f"ring_L{length_m:g}_W{width_m:g}"


def nets_cache() -> Path:
    """Where the networks of road sizes without a committed one are generated: ``lanefree_sumo/nets`` in the
    user's cache folder (``$XDG_CACHE_HOME``, else ``~/.cache``), never the package's ``sumo_nets/``."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "lanefree_sumo" / "nets"


def default_net_path(cfg: LaneFreeConfig) -> Path:
    """The network of ``cfg``'s road: the committed one under ``sumo_nets/``, else its place in
    :func:`nets_cache` (built there on first use)."""
    name = ring_name(cfg.road.length_m, cfg.road.width_m) if road_kind(cfg).periodic else onramp_name(cfg)
    committed = NETS_DIR / f"{name}.net.xml"
    return committed if committed.is_file() else nets_cache() / committed.name


def netconvert_args(nod: Path, edg: Path, net: Path, con: Path | None = None) -> list[str]:
    """netconvert options (after the binary) that build the ring (or, with connections, the on-ramp) from
    plain files."""
    return [
        "--node-files", str(nod),
        "--edge-files", str(edg),
        *(["--connection-files", str(con)] if con is not None else []),
        "--output-file", str(net),
        "--no-internal-links", "true",
        "--no-turnarounds", "true",
        "--junctions.corner-detail", "0",
        "--default.junctions.radius", "0",
        "--offset.disable-normalization", "true",
    ]


def write_plain_ring(length_m: float, width_m: float, speed_mps: float, directory: Path) -> tuple[Path, Path]:
    """Write the node and edge files of the ring; return their paths."""
    directory.mkdir(parents=True, exist_ok=True)
    name = ring_name(length_m, width_m)
    radius = length_m / (2.0 * math.pi)
    nod = directory / f"{name}.nod.xml"
    edg = directory / f"{name}.edg.xml"

    def point(angle: float) -> str:
        return f"{radius * math.cos(angle):.6f},{radius * math.sin(angle):.6f}"

    nodes = ["<nodes>"]
    for k in range(EDGES):
        a = 2.0 * math.pi * k / EDGES
        nodes.append(
            f'    <node id="n{k}" x="{radius * math.cos(a):.6f}" y="{radius * math.sin(a):.6f}" type="priority"/>'
        )
    nodes.append("</nodes>\n")
    nod.write_text("\n".join(nodes))

    edges = ["<edges>"]
    for k in range(EDGES):
        a0 = 2.0 * math.pi * k / EDGES
        a1 = 2.0 * math.pi * (k + 1) / EDGES
        shape = " ".join(
            point(a0 + (a1 - a0) * i / SHAPE_POINTS_PER_EDGE) for i in range(SHAPE_POINTS_PER_EDGE + 1)
        )
        edges.append(
            f'    <edge id="{edge_id(k)}" from="n{k}" to="n{(k + 1) % EDGES}" numLanes="1" '
            f'width="{width_m:g}" speed="{speed_mps:g}" length="{length_m / EDGES:.6f}" '
            f'spreadType="center" shape="{shape}"/>'
        )
    edges.append("</edges>\n")
    edg.write_text("\n".join(edges))
    return nod, edg


def _vtype(vid: str, cls: VehicleClassConfig, max_speed: float) -> str:
    r, g, b = cls.color_rgb
    # Huge accelerations and lateral speed so SUMO executes every commanded step exactly;
    # zero gaps so SUMO's own models never interfere (speed and lane-change modes are 0 too).
    return (
        f'    <vType id="{vid}" length="{cls.length_m:g}" width="{cls.width_m:g}" minGap="0" '
        f'maxSpeed="{max_speed:g}" speedFactor="1" speedDev="0" accel="1000" decel="1000" '
        f'emergencyDecel="1000" maxSpeedLat="1000" lcAccelLat="1000" minGapLat="0" '
        f'latAlignment="arbitrary" color="{r},{g},{b}"/>'
    )


def write_additional(cfg: LaneFreeConfig, path: Path) -> Path:
    """Vehicle types (two background classes split at the middle desired speed, the agent) and
    the looping route (the on-ramp: the main road's and the ramp's routes), as a SUMO additional file."""
    sc = cfg.scenario
    speed = cfg.road.speed_limit_mps
    slow = sc.background
    fast = dataclasses.replace(sc.background, color_rgb=sc.background_fast_color_rgb)
    route = " ".join(edge_id(k) for k in range(EDGES))
    if not road_kind(cfg).periodic:  # the on-ramp's two routes
        routes = [f'    <route id="{ROUTE_MAIN}" edges="{" ".join(ONRAMP_EDGES)}"/>',
                  f'    <route id="{ROUTE_RAMP}" edges="{" ".join(ONRAMP_EDGES[1:])}"/>']
    else:
        routes = [f'    <route id="{ROUTE_ID}" edges="{" ".join([route] * cfg.sim.route_loops)}"/>']
    lines = [
        "<additional>",
        _vtype(VTYPE_BG_SLOW, slow, speed),
        _vtype(VTYPE_BG_FAST, fast, speed),
        _vtype(VTYPE_AGENT, sc.agent, speed),
        *routes,
        "</additional>\n",
    ]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines))
    return path


def background_vtype(v_desired: float, cfg: LaneFreeConfig) -> str:
    """Background class of a vehicle by its desired speed (for colours in sumo-gui)."""
    bg = cfg.scenario.background
    middle = 0.5 * (bg.desired_speed_min_mps + bg.desired_speed_max_mps)
    return VTYPE_BG_FAST if v_desired >= middle else VTYPE_BG_SLOW


# -- the on-ramp -------------------------------------------------------------------------------------------

ONRAMP_EDGES = ("up", "merge", "down")
"""The on-ramp's edges along the main road: before the ramp, beside it (lane 0 the ramp, lane 1 the main
road), after it."""
ROUTE_MAIN = "main"
ROUTE_RAMP = "ramp"
ONRAMP_TAIL_M = 200.0
"""The last edge is this much longer than the road (m): the simulation removes a vehicle once its centre
passes the road's end, before SUMO would let it arrive."""


def onramp_name(cfg: LaneFreeConfig) -> str:
    o = cfg.road.onramp
    return f"onramp_U{o.upstream_m:g}_R{o.ramp_m:g}_D{o.downstream_m:g}_W{cfg.road.width_m:g}_w{o.ramp_width_m:g}"


def onramp_edge_offsets(cfg: LaneFreeConfig) -> tuple[float, float, float]:
    """x (m) where each of :data:`ONRAMP_EDGES` begins: x = offset + lane position."""
    o = cfg.road.onramp
    return 0.0, o.upstream_m, o.upstream_m + o.ramp_m


def onramp_edge_lengths(cfg: LaneFreeConfig) -> tuple[float, float, float]:
    """Lengths of :data:`ONRAMP_EDGES` in SUMO (m; the last one with :data:`ONRAMP_TAIL_M`)."""
    o = cfg.road.onramp
    return o.upstream_m, o.ramp_m, o.downstream_m + ONRAMP_TAIL_M


def onramp_lane_centre(cfg: LaneFreeConfig, edge: int, lane: int) -> float:
    """y (m, from the main road's right edge) of the centre of ``lane`` of edge number ``edge``: the main
    road's lane at W/2, the ramp (lane 0 of ``merge``) at −w_r/2."""
    if edge == 1 and lane == 0:
        return -0.5 * cfg.road.onramp.ramp_width_m
    return 0.5 * cfg.road.width_m


def write_plain_onramp(cfg: LaneFreeConfig, directory: Path) -> tuple[Path, Path, Path]:
    """Write the node, edge and connection files of the on-ramp (straight, along SUMO's x axis; lanes are
    laid right of each edge's line, so the main road's centre is at SUMO y = −W/2 on every edge); return
    their paths."""
    directory.mkdir(parents=True, exist_ok=True)
    name = onramp_name(cfg)
    w, wr, speed = cfg.road.width_m, cfg.road.onramp.ramp_width_m, cfg.road.speed_limit_mps
    offsets, lengths = onramp_edge_offsets(cfg), onramp_edge_lengths(cfg)
    ends = [*offsets, offsets[-1] + lengths[-1]]
    nod, edg, con = (directory / f"{name}.{kind}.xml" for kind in ("nod", "edg", "con"))
    nod.write_text("<nodes>\n" + "".join(f'    <node id="n{k}" x="{x:.6f}" y="0" type="priority"/>\n'
                                         for k, x in enumerate(ends)) + "</nodes>\n")
    up, merge, down = ONRAMP_EDGES
    edg.write_text(
        "<edges>\n"
        f'    <edge id="{up}" from="n0" to="n1" numLanes="1" width="{w:g}" speed="{speed:g}"/>\n'
        f'    <edge id="{merge}" from="n1" to="n2" numLanes="2" speed="{speed:g}">\n'
        f'        <lane index="0" width="{wr:g}"/>\n'
        f'        <lane index="1" width="{w:g}"/>\n'
        "    </edge>\n"
        f'    <edge id="{down}" from="n2" to="n3" numLanes="1" width="{w:g}" speed="{speed:g}"/>\n'
        "</edges>\n")
    con.write_text(
        "<connections>\n"
        f'    <connection from="{up}" to="{merge}" fromLane="0" toLane="1"/>\n'
        f'    <connection from="{merge}" to="{down}" fromLane="1" toLane="0"/>\n'
        "</connections>\n")
    return nod, edg, con

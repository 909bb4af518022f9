"""Frames of the road seen from above, drawn from the simulation's arrays (no SUMO, no display).

A frame (:func:`draw_frame`) is an ``H × W × 3`` uint8 image in two parts: on top the whole road squeezed into
the frame's width (the ring unrolled from x = 0, lateral scale stretched so that the road is visible), below it
a window of ``view_m`` metres centred on the agent at true scale — the road's edges (and the on-ramp's
acceleration lane with its merge zone), every vehicle's box at its position and heading (atan2(vy, vx)), the
agents in green, vehicles that overlap another in red — with a scale bar and the time. Drawing uses Pillow
(``ImageDraw``: polygons, lines, text): no window system and no SDL, so frames come from a process without a display;
``make bench`` prints what a frame costs beside a step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np

from lanefree_sumo.sim.road import Road

BACKGROUND = (236, 236, 232)
ROAD = (92, 94, 98)
ROAD_EDGE = (245, 245, 245)
RAMP = (110, 112, 118)
MERGE_MARK = (238, 200, 60)
VEHICLE = (70, 130, 200)
AGENT = (40, 190, 80)
OVERLAP = (220, 50, 40)
TEXT = (30, 30, 30)
VIEW_BOX = (250, 210, 70)

FRAME_WIDTH_PX = 720
"""Default frame width (px)."""
VIEW_M = 120.0
"""Default length of the road the lower part shows around the agent (m)."""


@dataclass(frozen=True)
class Scene:
    """What one frame shows: the vehicles (``[N]`` arrays, SI units: x, y the body's centre, y from the main
    road's right edge), which are agents, which overlap another vehicle, the road and the time (s)."""

    x: np.ndarray
    y: np.ndarray
    vx: np.ndarray
    vy: np.ndarray
    length: np.ndarray
    width: np.ndarray
    agent: np.ndarray
    """True for the learning vehicles."""
    overlap: np.ndarray
    """True for vehicles overlapping another now."""
    road: Road
    time_s: float


@cache
def _font() -> Any:
    """Pillow's built-in bitmap font, loaded once (loading it is most of a frame's cost otherwise)."""
    from PIL import ImageFont

    return ImageFont.load_default_imagefont()


def _box(cx: float, cy: float, length: float, width: float, heading: float) -> list[tuple[float, float]]:
    """The four corners of a vehicle's box (road coordinates, m), rotated by ``heading`` (rad)."""
    c, s = math.cos(heading), math.sin(heading)
    hl, hw = 0.5 * length, 0.5 * width
    return [(cx + c * dx - s * dy, cy + s * dx + c * dy) for dx, dy in ((hl, hw), (hl, -hw), (-hl, -hw), (-hl, hw))]


@dataclass(frozen=True)
class _Layout:
    """Where a frame puts the road: the overview's and the window's transforms (road m → px)."""

    road: Road
    width_px: int
    ramp_w: float
    margin: int
    overview_h: int
    scale: float
    """px per m in the window around the agent."""
    lo: float
    """The window's first x (m)."""
    hi: float
    """The window's last x (m)."""

    def overview(self, x: float, y: float) -> tuple[float, float]:
        ox = (self.width_px - 2 * self.margin) / self.road.length_m
        oy = self.overview_h / (self.road.width_m + self.ramp_w)
        return self.margin + x * ox, self.margin + (self.road.width_m - y) * oy

    @property
    def view_top(self) -> int:
        return 2 * self.margin + self.overview_h

    def view(self, x: float, y: float) -> tuple[float, float]:
        return (x - self.lo) * self.scale, self.view_top + (self.road.width_m - y) * self.scale

    def clipped(self) -> tuple[float, float]:
        """The window's x range on the road (m): all of it on the ring, cut at the ends of an open road."""
        return (self.lo, self.hi) if self.road.periodic else (max(self.lo, 0.0), min(self.hi, self.road.length_m))


def _draw_overview(draw: Any, scene: Scene, at: _Layout) -> None:
    """The whole road squeezed into the frame's width, every vehicle a dot, the window's extent outlined."""
    road = scene.road
    draw.rectangle([at.overview(0.0, road.width_m), at.overview(road.length_m, 0.0)], fill=ROAD)
    if at.ramp_w:
        draw.rectangle([at.overview(road.ramp_start_m, 0.0), at.overview(road.ramp_end_m, -at.ramp_w)], fill=RAMP)
    for i in range(len(scene.x)):
        x = float(scene.x[i]) % road.length_m if road.periodic else float(scene.x[i])
        px, py = at.overview(x, float(scene.y[i]))
        colour = AGENT if scene.agent[i] else OVERLAP if scene.overlap[i] else VEHICLE
        r = 2.5 if scene.agent[i] else 1.5
        draw.ellipse([px - r, py - r, px + r, py + r], fill=colour)
    for shift in (-road.length_m, 0.0, road.length_m) if road.periodic else (0.0,):  # the window, wrapped
        if at.hi + shift > 0.0 and at.lo + shift < road.length_m:
            draw.rectangle([at.overview(max(at.lo + shift, 0.0), road.width_m),
                            at.overview(min(at.hi + shift, road.length_m), -at.ramp_w)], outline=VIEW_BOX)


def _draw_road(draw: Any, road: Road, at: _Layout) -> None:
    """The window's road surface and edges (and the on-ramp's acceleration lane, its merge zone marked)."""
    a, b = at.clipped()
    draw.rectangle([at.view(a, road.width_m), at.view(b, 0.0)], fill=ROAD)
    draw.line([at.view(a, road.width_m), at.view(b, road.width_m)], fill=ROAD_EDGE, width=2)
    if not at.ramp_w:
        draw.line([at.view(a, 0.0), at.view(b, 0.0)], fill=ROAD_EDGE, width=2)
        return
    if road.ramp_end_m > at.lo and road.ramp_start_m < at.hi:
        draw.polygon([at.view(road.ramp_start_m, 0.0), at.view(road.ramp_start_m, -at.ramp_w),
                      at.view(road.merge_start_m, -at.ramp_w), at.view(road.ramp_end_m, 0.0)], fill=RAMP)
        draw.line([at.view(road.ramp_start_m, 0.0), at.view(road.merge_start_m, 0.0)], fill=ROAD_EDGE, width=2)
        draw.line([at.view(road.merge_start_m, 0.0), at.view(road.ramp_end_m, 0.0)], fill=MERGE_MARK, width=1)
    for seg_a, seg_b in ((a, min(b, road.ramp_start_m)), (max(a, road.ramp_end_m), b)):
        if seg_b > seg_a:
            draw.line([at.view(seg_a, 0.0), at.view(seg_b, 0.0)], fill=ROAD_EDGE, width=2)


def _draw_vehicles(draw: Any, scene: Scene, at: _Layout, focus: float) -> None:
    """Every vehicle in the window as its box at its heading; on the ring the copy nearest the agent."""
    road = scene.road
    for i in range(len(scene.x)):
        x = float(scene.x[i])
        if road.periodic:
            x = focus + (x - focus + 0.5 * road.length_m) % road.length_m - 0.5 * road.length_m
        half = 0.5 * float(scene.length[i])
        if x + half < at.lo or x - half > at.hi:
            continue
        heading = math.atan2(float(scene.vy[i]), max(float(scene.vx[i]), 1e-6))
        corners = [at.view(cx, cy) for cx, cy in _box(x, float(scene.y[i]), float(scene.length[i]),
                                                       float(scene.width[i]), heading)]
        draw.polygon(corners, fill=AGENT if scene.agent[i] else VEHICLE,
                     outline=OVERLAP if scene.overlap[i] else (20, 20, 20))


def draw_frame(scene: Scene, width_px: int = FRAME_WIDTH_PX, view_m: float = VIEW_M) -> np.ndarray:
    """The frame of ``scene`` (module docstring): ``H × width_px × 3`` uint8, H fixed by the road's width."""
    from PIL import Image, ImageDraw

    road = scene.road
    ramp_w = 0.0 if road.periodic else road.ramp_width_m
    agents = np.flatnonzero(scene.agent)
    focus = float(scene.x[agents[0]]) if len(agents) else 0.5 * road.length_m
    at = _Layout(road, width_px, ramp_w, margin=8, overview_h=30, scale=width_px / view_m,
                 lo=focus - 0.5 * view_m, hi=focus + 0.5 * view_m)
    view_h = int(math.ceil((road.width_m + ramp_w) * at.scale))
    height = at.view_top + view_h + 28
    image = Image.new("RGB", (width_px, height + height % 2), BACKGROUND)  # even sides: what video codecs take
    draw = ImageDraw.Draw(image)
    _draw_overview(draw, scene, at)
    _draw_road(draw, road, at)
    _draw_vehicles(draw, scene, at, focus)
    base = at.view_top + view_h + 8
    bar_m = 10.0
    draw.line([(at.margin, base + 6), (at.margin + bar_m * at.scale, base + 6)], fill=TEXT, width=3)
    draw.text((at.margin + bar_m * at.scale + 6, base), f"{bar_m:g} m", fill=TEXT, font=_font())
    label = f"t = {scene.time_s:6.2f} s"
    if len(agents):
        label += f"   agent {float(scene.vx[agents[0]]):5.2f} m/s"
    draw.text((width_px - 7 * len(label) - at.margin, base), label, fill=TEXT, font=_font())
    return np.asarray(image, dtype=np.uint8)

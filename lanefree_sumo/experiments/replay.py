"""``lanefree replay RUN``: replay a recorded evaluation episode in SUMO, step by step.

The recording (``lanefree evaluate RUN --record``) holds every vehicle's x, y, vx at every step.
The replay places the recorded initial state, then drives every vehicle with the same commands
as the simulation does — speed at the end of the step and lateral displacement — chosen so that
each step lands exactly on the recorded positions (the ballistic update inverted:
``v' = 2·Δx/T − v``).  So the replay is exact (the fidelity is measured and returned) and
vehicles move naturally in sumo-gui: the agent green and tracked by the view (magenta on the
steps the safety shield changed its action, in a shielded recording), background vehicles
coloured by desired speed (blue = slow … orange = fast), overlapping vehicles red.

Without a GUI the same replay can write SUMO's own FCD XML (``--fcd``), with lateral positions.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from lanefree_sumo.config import LaneFreeConfig, ReplayConfig, merge_config
from lanefree_sumo.errors import RunError
from lanefree_sumo.experiments.rundir import (
    CONFIG,
    TRAJECTORIES,
    check_new_file,
    check_writable,
    find_eval_dir,
    new_file,
    read_config,
    trajectory_path,
    vehicles_path,
)
from lanefree_sumo.sim.dynamics import StepCommand
from lanefree_sumo.sim.spawn import AGENT_ID, is_agent_id
from lanefree_sumo.sim.state import VehicleState, wrap

REPLAY = ReplayConfig()
FCD_ATTRIBUTES = "x,y,angle,type,speed,pos,lane,posLat"


class ReplayError(RunError):
    """A recording that cannot be replayed; the message says how to make one."""


@dataclass
class Recording:
    """One recorded episode: arrays of shape (steps + 1, vehicles), row 0 the initial state."""

    ids: list[str]
    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    vx: np.ndarray
    vy: np.ndarray
    overlap: np.ndarray
    shielded: np.ndarray
    """True in the agent's column on the steps the shield changed its action (all False when the
    recording has no ``shielded`` column)."""
    length: np.ndarray
    width: np.ndarray
    v_desired: np.ndarray
    cfg: LaneFreeConfig

    @property
    def steps(self) -> int:
        return len(self.t) - 1

    def state(self, k: int) -> VehicleState:
        return VehicleState(
            list(self.ids), self.x[k].copy(), self.y[k].copy(), self.vx[k].copy(), self.vy[k].copy(),
            self.length.copy(), self.width.copy(), self.v_desired.copy(),
            np.array([not is_agent_id(vid) for vid in self.ids]),
        )


def load_recording(run: Path, episode: int = 1) -> Recording:
    """Read episode ``episode`` of the recording in RUN/eval (or in RUN if it is an eval folder)."""
    eval_dir = find_eval_dir(run)
    traj = trajectory_path(eval_dir, episode)
    vehicles = vehicles_path(eval_dir, episode)
    if not traj.is_file() or not vehicles.is_file():
        folder = eval_dir / TRAJECTORIES
        have = sorted(folder.glob("episode_*[0-9].csv")) if folder.is_dir() else []
        hint = f" (recorded: {', '.join(p.stem for p in have[:5])})" if have else ""
        raise ReplayError(
            f"no recording of episode {episode} in {eval_dir / TRAJECTORIES}{hint}; "
            f"make one with: lanefree evaluate {run} --record"
        )
    cfg = read_config(eval_dir) if (eval_dir / CONFIG).is_file() else read_config(run)
    try:
        table = pd.read_csv(traj)
        attrs = pd.read_csv(vehicles)
        ids = list(attrs["id"])
        n = len(ids)
        table["id"] = pd.Categorical(table["id"], categories=ids, ordered=True)
        table = table.sort_values(["t", "id"], kind="stable")
        steps = len(table) // n if n else 0
        if steps < 2:
            raise ValueError("it holds no steps to replay")
        if steps * n != len(table) or table["id"].isna().any():
            raise ValueError("rows are not one per vehicle and step")
        numbers = table[["t", "x", "y", "vx", "vy", "overlap"]].to_numpy(dtype=float)
        sizes = attrs[["length", "width", "v_desired"]].to_numpy(dtype=float)
        if not (np.isfinite(numbers).all() and np.isfinite(sizes).all()):
            raise ValueError("it has NaN or infinite values")

        def grid(col: str) -> np.ndarray:
            return table[col].to_numpy(dtype=float).reshape(steps, n)

        shielded = grid("shielded").astype(bool) if "shielded" in table else np.zeros((steps, n), dtype=bool)
        return Recording(
            ids, grid("t")[:, 0], grid("x"), grid("y"), grid("vx"), grid("vy"), grid("overlap").astype(bool), shielded,
            attrs["length"].to_numpy(float), attrs["width"].to_numpy(float), attrs["v_desired"].to_numpy(float), cfg,
        )
    except (KeyError, ValueError, TypeError, UnicodeDecodeError, pd.errors.ParserError) as exc:
        raise ReplayError(f"{traj} is not a usable recording ({' '.join(str(exc).split())[:200]}); "
                          "record it again with 'lanefree evaluate RUN --record'") from None


def desired_speed_colour(v_desired: float, cfg: LaneFreeConfig) -> tuple[int, int, int, int]:
    """Blue (slowest desired speed) … orange (fastest) (RGBA 0–255)."""
    bg = cfg.scenario.background
    span = max(bg.desired_speed_max_mps - bg.desired_speed_min_mps, 1e-9)
    f = float(np.clip((v_desired - bg.desired_speed_min_mps) / span, 0.0, 1.0))
    slow, fast = np.array(bg.color_rgb), np.array(cfg.scenario.background_fast_color_rgb)
    r, g, b = (slow + f * (fast - slow)).round().astype(int)
    return int(r), int(g), int(b), 255


def _rgba(rgb: tuple[int, int, int]) -> tuple[int, int, int, int]:
    return (*rgb, 255)


def _gui_settings(path: Path, delay_ms: float) -> Path:
    path.write_text(
        "<viewsettings>\n"
        '    <scheme name="lanefree">\n'
        '        <background backgroundColor="white" showGrid="0"/>\n'
        '        <vehicles vehicleMode="0" vehicleQuality="2" vehicle_minSize="1"/>\n'
        "    </scheme>\n"
        f'    <delay value="{delay_ms:g}"/>\n'
        "</viewsettings>\n"
    )
    return path


def _sumo_args(tmp: Path, gui: bool, size: tuple[int, int], delay_s: float, fcd: Path | None) -> list[str]:
    """Extra SUMO options: window size and GUI settings, FCD output."""
    extra: list[str] = []
    if gui:
        extra += ["--window-size", f"{size[0]},{size[1]}",
                  "--gui-settings-file", str(_gui_settings(tmp / "gui.xml", 1000.0 * delay_s))]
    if fcd is not None:
        fcd.parent.mkdir(parents=True, exist_ok=True)
        extra += ["--fcd-output", str(fcd), "--fcd-output.attributes", FCD_ATTRIBUTES]
    return extra


def _paint(backend: Any, rec: Recording, cfg: LaneFreeConfig, zoom: float) -> list[tuple[int, int, int, int]]:
    """Colour every vehicle (agents, background by desired speed), track the (first) agent; return the colours."""
    colours = [_rgba(cfg.scenario.agent.color_rgb) if is_agent_id(vid) else desired_speed_colour(v, cfg)
               for vid, v in zip(rec.ids, rec.v_desired)]
    for vid, colour in zip(rec.ids, colours):
        backend.set_color(vid, colour)
    if AGENT_ID in rec.ids:
        backend.track(AGENT_ID, zoom)
    return colours


@dataclass
class ReplayResult:
    steps: int
    max_dx_m: float
    """Largest |x_SUMO − x_recorded| over all vehicles and steps (m)."""
    max_dy_m: float
    """Largest |y_SUMO − y_recorded| over all vehicles and steps (m)."""
    frames: list[Path]


def replay(
    run: Path,
    episode: int = 1,
    gui: bool = True,
    delay_s: float = 0.0,
    screenshot: Path | None = None,
    screenshot_step: int | None = None,
    frames: Path | None = None,
    every: int = 1,
    gif: Path | None = None,
    fcd: Path | None = None,
    size: tuple[int, int] = REPLAY.size_px,
    zoom: float = REPLAY.zoom_percent,
    overwrite: bool = False,
    verb: str = "replay",
) -> ReplayResult:
    """Replay a recorded episode; see the module docstring.  ``screenshot_step`` defaults to the
    last step; ``frames`` gets ``frame_NNNN.png`` every ``every`` steps; ``gif`` assembles them. Output
    files are checked before any work (:func:`check_new_file`: never a run's own file, an existing one
    only with ``overwrite``; ``verb`` the command whose output folders are its own); the FCD file is
    written beside and moved into place when complete."""
    for target in (screenshot, gif, fcd):
        if target is not None:
            check_new_file(target, overwrite, verb)
    if frames is not None:
        check_writable(frames, folder=True)
    if fcd is None:
        return _replay(run, episode, gui, delay_s, screenshot, screenshot_step, frames, every, gif, None, size, zoom)
    with new_file(fcd) as fcd_tmp:
        return _replay(run, episode, gui, delay_s, screenshot, screenshot_step, frames, every, gif, fcd_tmp, size,
                       zoom)


def _replay(run: Path, episode: int, gui: bool, delay_s: float, screenshot: Path | None, screenshot_step: int | None,
            frames: Path | None, every: int, gif: Path | None, fcd: Path | None, size: tuple[int, int],
            zoom: float) -> ReplayResult:
    from lanefree_sumo.sim.backends.sumo import SumoBackend

    rec = load_recording(run, episode)
    cfg = merge_config(rec.cfg, {"gui": gui, "backend": "traci" if gui else "libsumo"})
    if (screenshot or frames or gif) and not gui:
        raise ReplayError("screenshots need the GUI; drop --no-gui")
    shot_at = rec.steps if screenshot_step is None else screenshot_step
    if screenshot is not None and not 0 < shot_at <= rec.steps:
        raise ReplayError(f"--screenshot-step must be within 1..{rec.steps}")
    frame_dir = frames
    tmp = tempfile.TemporaryDirectory(prefix="lanefree-replay-")
    if gif is not None and frame_dir is None:
        frame_dir = Path(tmp.name) / "frames"
    if frame_dir is not None:
        frame_dir.mkdir(parents=True, exist_ok=True)
    extra = _sumo_args(Path(tmp.name), gui, size, delay_s, fcd)
    backend = SumoBackend(cfg, kind=cfg.backend, gui=gui, extra_args=extra)
    written: list[Path] = []
    try:
        backend.reset(rec.state(0))
        collision_colour = _rgba(REPLAY.collision_color_rgb)
        shield_colour = _rgba(REPLAY.shield_color_rgb)
        base_colour = _paint(backend, rec, cfg, zoom) if gui else []
        shown = np.zeros(len(rec.ids), dtype=int)  # 0 own colour, 1 shielded, 2 overlapping
        x, y, vx = rec.x[0].copy(), rec.y[0].copy(), rec.vx[0].copy()
        max_dx = max_dy = 0.0
        step_s, length = cfg.sim.step_s, cfg.road.length_m
        for k in range(1, rec.steps + 1):
            if gui:
                if screenshot is not None and k == shot_at:
                    screenshot.parent.mkdir(parents=True, exist_ok=True)
                    backend.screenshot(screenshot, *size)
                if frame_dir is not None and k % every == 0:
                    path = frame_dir / f"frame_{k:04d}.png"
                    backend.screenshot(path, *size)
                    written.append(path)
                mode = np.where(rec.overlap[k], 2, rec.shielded[k].astype(int))
                for i in np.flatnonzero(mode != shown):
                    backend.set_color(rec.ids[i], (base_colour[i], shield_colour, collision_colour)[mode[i]])
                shown = mode
            vx_next = np.maximum(2.0 * wrap(rec.x[k] - x, length) / step_s - vx, 0.0)
            dy = rec.y[k] - y
            zeros = np.zeros_like(dy)
            x, y, vx = backend.step(StepCommand(vx_next, dy, zeros, zeros, zeros, zeros.astype(bool)))
            max_dx = max(max_dx, float(np.abs(wrap(x - rec.x[k], length)).max()))
            max_dy = max(max_dy, float(np.abs(y - rec.y[k]).max()))
        if gui and (screenshot is not None or written):
            backend.idle_step()  # a screenshot requested for the last step is written here
    finally:
        backend.close()
    if gif is not None:
        _write_gif([p for p in written if p.exists()], gif, step_s * every)
    tmp.cleanup()
    return ReplayResult(rec.steps, max_dx, max_dy, written if frames is not None else [])


def _write_gif(frames: list[Path], path: Path, seconds_per_frame: float) -> None:
    from PIL import Image

    if not frames:
        raise ReplayError("no frames were captured for the GIF")
    images = [Image.open(p).convert("P", palette=Image.Palette.ADAPTIVE) for p in frames]
    path.parent.mkdir(parents=True, exist_ok=True)
    images[0].save(path, save_all=True, append_images=images[1:], duration=int(1000 * seconds_per_frame), loop=0)

"""``lanefree replay RUN``: replay a recorded evaluation episode in SUMO, step by step.

The recording (``lanefree evaluate RUN --record``) holds every vehicle's x, y, vx at every step.
The replay places the recorded initial state, then drives every vehicle with the same commands
as the simulation does — speed at the end of the step and lateral displacement — chosen so that
each step lands exactly on the recorded positions (the ballistic update inverted:
``v' = 2·Δx/T − v``).  So the replay is exact (the fidelity is measured and returned) and
vehicles move naturally in sumo-gui: the agent green and tracked by the view (magenta on the
steps the safety shield changed its action, in a shielded recording), background vehicles
coloured by desired speed (blue = slow … orange = fast), overlapping vehicles red.  On the on-ramp
vehicles come and go: a vehicle that left is taken off before the step, and one that entered at its
start is placed as recorded (SUMO's ``moveTo``), then commanded like the others.

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
from lanefree_sumo.experiments.storage.rundir import (
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
from lanefree_sumo.sim.road import road_kind, road_of
from lanefree_sumo.sim.spawn import AGENT_ID, is_agent_id
from lanefree_sumo.sim.state import VehicleState, wrap

REPLAY = ReplayConfig()
FCD_ATTRIBUTES = "x,y,angle,type,speed,pos,lane,posLat"


class ReplayError(RunError):
    """A recording that cannot be replayed; the message says how to make one."""


@dataclass
class Recording:
    """One recorded episode: arrays of shape (steps + 1, vehicles), row 0 the initial state, one column
    per vehicle seen; on an open road vehicles come and go, and a vehicle's values are NaN on the steps
    it was not on the road (``present`` False)."""

    ids: list[str]
    t: np.ndarray
    present: np.ndarray
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

    def state(self, k: int, which: np.ndarray | None = None) -> VehicleState:
        """The vehicles on the road after step ``k`` (only those where ``which`` is True, if given)."""
        cols = np.flatnonzero(self.present[k] if which is None else which)
        return VehicleState(
            [self.ids[i] for i in cols], self.x[k, cols], self.y[k, cols], self.vx[k, cols], self.vy[k, cols],
            self.length[cols], self.width[cols], self.v_desired[cols],
            np.array([not is_agent_id(self.ids[i]) for i in cols], dtype=bool),
        )


def load_recording(run: Path, episode: int = 1) -> Recording:
    """Read episode ``episode`` of the recording in RUN/eval (or in RUN if it is an eval folder)."""
    eval_dir = find_eval_dir(run)
    cfg = read_config(eval_dir) if (eval_dir / CONFIG).is_file() else read_config(run)  # not a run: said first
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
    try:
        table = pd.read_csv(traj)
        attrs = pd.read_csv(vehicles)
        ids = list(attrs["id"])
        numbers = table[["t", "x", "y", "vx", "vy", "overlap"]].to_numpy(dtype=float)
        sizes = attrs[["length", "width", "v_desired"]].to_numpy(dtype=float)
        if not (np.isfinite(numbers).all() and np.isfinite(sizes).all()):
            raise ValueError("it has NaN or infinite values")
        t = np.unique(numbers[:, 0])
        if len(t) < 2:
            raise ValueError("it holds no steps to replay")
        column = {vid: i for i, vid in enumerate(ids)}
        if len(column) != len(ids) or not table["id"].isin(column).all():
            raise ValueError(f"its vehicles are not those of {vehicles.name}")
        rows, cols = np.searchsorted(t, numbers[:, 0]), table["id"].map(column).to_numpy(dtype=int)
        present = np.zeros((len(t), len(ids)), dtype=bool)
        present[rows, cols] = True
        entries = present[0].astype(int) + (np.diff(present.astype(int), axis=0) == 1).sum(axis=0)
        if present.sum() != len(table) or (entries != 1).any() or (road_kind(cfg).periodic and not present.all()):
            raise ValueError("rows are not one per vehicle and step on the road")

        def grid(values: np.ndarray) -> np.ndarray:
            out = np.full(present.shape, np.nan)
            out[rows, cols] = values
            return out

        shielded = grid(table["shielded"].to_numpy(dtype=float)) == 1 if "shielded" in table else \
            np.zeros(present.shape, dtype=bool)
        return Recording(
            ids, t, present, grid(numbers[:, 1]), grid(numbers[:, 2]), grid(numbers[:, 3]), grid(numbers[:, 4]),
            grid(numbers[:, 5]) == 1, shielded,
            sizes[:, 0], sizes[:, 1], sizes[:, 2], cfg,
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


def _colours(rec: Recording, cfg: LaneFreeConfig) -> list[tuple[int, int, int, int]]:
    """Each vehicle's own colour: agents', background vehicles' by desired speed."""
    return [_rgba(cfg.scenario.agent.color_rgb) if is_agent_id(vid) else desired_speed_colour(v, cfg)
            for vid, v in zip(rec.ids, rec.v_desired)]


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
    zoom: float | None = None,
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
    with new_file(fcd, verb) as fcd_tmp:
        return _replay(run, episode, gui, delay_s, screenshot, screenshot_step, frames, every, gif, fcd_tmp, size,
                       zoom)


def _replay(run: Path, episode: int, gui: bool, delay_s: float, screenshot: Path | None, screenshot_step: int | None,
            frames: Path | None, every: int, gif: Path | None, fcd: Path | None, size: tuple[int, int],
            zoom: float | None) -> ReplayResult:
    from lanefree_sumo.sim.backends.sumo import sumo_backend

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
    backend_class = sumo_backend(cfg)
    if zoom is None:
        zoom = REPLAY.zoom_percent if road_kind(cfg).periodic else REPLAY.onramp_zoom_percent
    backend = backend_class(cfg, kind=cfg.backend, gui=gui, extra_args=extra)
    written: list[Path] = []
    try:
        max_dx, max_dy = _drive(backend, rec, cfg, gui, screenshot, shot_at, frame_dir, every, size, zoom, written)
    finally:
        backend.close()
    if gif is not None:
        _write_gif([p for p in written if p.exists()], gif, cfg.sim.step_s * every)
    tmp.cleanup()
    return ReplayResult(rec.steps, max_dx, max_dy, written if frames is not None else [])


def _drive(backend: Any, rec: Recording, cfg: LaneFreeConfig, gui: bool, screenshot: Path | None, shot_at: int,
           frame_dir: Path | None, every: int, size: tuple[int, int], zoom: float,
           written: list[Path]) -> tuple[float, float]:
    """Place the initial state, then each step: take off the vehicles that left before it, place those
    that entered at its start as the recording has them placed, command every vehicle onto its recorded
    position and step (on the ring every vehicle stays). Returns the largest |dx|, |dy| (m) against the
    recording; screenshots and frames go to ``written``."""
    backend.reset(rec.state(0))
    collision_colour = _rgba(REPLAY.collision_color_rgb)
    shield_colour = _rgba(REPLAY.shield_color_rgb)
    base_colour = _colours(rec, cfg)
    on_road = rec.present[0].copy()
    if gui:
        for i in np.flatnonzero(on_road):
            backend.set_color(rec.ids[i], base_colour[i])
        if AGENT_ID in rec.ids:
            backend.track(AGENT_ID, zoom)
    shown = np.zeros(len(rec.ids), dtype=int)  # 0 own colour, 1 shielded, 2 overlapping
    x, y, vx = rec.x[0].copy(), rec.y[0].copy(), rec.vx[0].copy()
    max_dx = max_dy = 0.0
    step_s, wrap_length = cfg.sim.step_s, road_of(cfg).wrap_length
    for k in range(1, rec.steps + 1):
        leaving = on_road & ~rec.present[k]
        if leaving.any():
            backend.remove(~leaving[on_road])
            on_road &= ~leaving
        entering = rec.present[k - 1] & rec.present[k] & ~on_road  # row k - 1: as placed at the start
        if entering.any():
            backend.add(rec.state(k - 1, entering))
            x[entering], y[entering], vx[entering] = rec.x[k - 1, entering], rec.y[k - 1, entering], \
                rec.vx[k - 1, entering]
            on_road |= entering
            for i in np.flatnonzero(entering) if gui else ():
                backend.set_color(rec.ids[i], base_colour[i])
        moving = np.flatnonzero(on_road)
        if gui:
            if screenshot is not None and k == shot_at:
                screenshot.parent.mkdir(parents=True, exist_ok=True)
                backend.screenshot(screenshot, *size)
            if frame_dir is not None and k % every == 0:
                path = frame_dir / f"frame_{k:04d}.png"
                backend.screenshot(path, *size)
                written.append(path)
            mode = np.where(rec.overlap[k], 2, rec.shielded[k].astype(int))
            for i in moving[mode[moving] != shown[moving]]:
                backend.set_color(rec.ids[i], (base_colour[i], shield_colour, collision_colour)[mode[i]])
                shown[i] = mode[i]
        vx_next = np.maximum(2.0 * wrap(rec.x[k, moving] - x[moving], wrap_length) / step_s - vx[moving], 0.0)
        dy = rec.y[k, moving] - y[moving]
        zeros = np.zeros_like(dy)
        x[moving], y[moving], vx[moving] = backend.step(StepCommand(vx_next, dy, zeros, zeros, zeros,
                                                                    zeros.astype(bool)))
        max_dx = float(np.maximum(max_dx, np.abs(wrap(x[moving] - rec.x[k, moving], wrap_length)).max(initial=0.0)))
        max_dy = float(np.maximum(max_dy, np.abs(y[moving] - rec.y[k, moving]).max(initial=0.0)))
    if gui and (screenshot is not None or written):
        backend.idle_step()  # a screenshot requested for the last step is written here
    return max_dx, max_dy


def _write_gif(frames: list[Path], path: Path, seconds_per_frame: float) -> None:
    from PIL import Image

    if not frames:
        raise ReplayError("no frames were captured for the GIF")
    images = [Image.open(p).convert("P", palette=Image.Palette.ADAPTIVE) for p in frames]
    path.parent.mkdir(parents=True, exist_ok=True)
    images[0].save(path, save_all=True, append_images=images[1:], duration=int(1000 * seconds_per_frame), loop=0)


VIDEO_SUFFIXES = (".mp4", ".gif")
"""What ``lanefree replay --video`` writes, by the file's suffix: H.264 MP4 (moviepy/ffmpeg) or an animated GIF."""


def recording_frames(rec: Recording, every: int = 1) -> list[np.ndarray]:
    """The recording drawn from above (:func:`~lanefree_sumo.rl.render.draw_frame`), one frame every ``every``
    steps from the initial state; no SUMO."""
    from lanefree_sumo.rl.render import Scene, draw_frame

    road = road_of(rec.cfg)
    agent = np.array([is_agent_id(vid) for vid in rec.ids])
    frames = []
    for k in range(0, rec.steps + 1, every):
        cols = np.flatnonzero(rec.present[k])
        scene = Scene(rec.x[k, cols], rec.y[k, cols], rec.vx[k, cols], rec.vy[k, cols], rec.length[cols],
                      rec.width[cols], agent[cols], rec.overlap[k, cols], road, float(rec.t[k]))
        frames.append(draw_frame(scene))
    return frames


def write_video(run: Path, path: Path, episode: int = 1, every: int = 1, overwrite: bool = False,
                verb: str = "replay") -> int:
    """Write recorded episode ``episode`` of RUN as a video at ``path`` (:data:`VIDEO_SUFFIXES`), in real time
    (one frame per ``every`` steps of 0.25 s), without SUMO; returns the number of frames. The file is checked
    before any work and appears whole or not at all."""
    if path.suffix.lower() not in VIDEO_SUFFIXES:
        raise ReplayError(f"--video {path}: the file's suffix says what to write; use {' or '.join(VIDEO_SUFFIXES)}")
    check_new_file(path, overwrite, verb)
    rec = load_recording(run, episode)
    frames = recording_frames(rec, every)
    fps = 1.0 / (rec.cfg.sim.step_s * every)
    with new_file(path, verb) as tmp:
        if path.suffix.lower() == ".gif":
            from PIL import Image

            images = [Image.fromarray(f).convert("P", palette=Image.Palette.ADAPTIVE) for f in frames]
            images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:],
                           duration=int(1000 / fps), loop=0)
        else:
            from moviepy import ImageSequenceClip

            clip = ImageSequenceClip(frames, fps=fps)
            clip.write_videofile(str(tmp), codec="libx264", audio=False, logger=None,
                                 ffmpeg_params=["-f", "mp4", "-pix_fmt", "yuv420p"])
            clip.close()
    return len(frames)

"""``lanefree replay``: a recorded evaluation episode, step by step, in sumo-gui."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from lanefree_sumo import argtypes
from lanefree_sumo.config import ReplayConfig
from lanefree_sumo.errors import UsageError
from lanefree_sumo.options import Option, add_options

REPLAY = ReplayConfig()

OPTIONS: tuple[Option, ...] = (
    Option("run", type=Path, extra={"metavar": "RUN"}, note="run folder (or its eval folder) with a recording"),
    Option("--episode", type=argtypes.positive(int, "episodes"), default=1,
           note="recorded episode number (default 1)"),
    Option("--delay", "delay_s", schema=ReplayConfig, unit="s", type=argtypes.nonnegative(float, "s")),
    Option("--screenshot", type=Path, note="save a PNG of the view at --screenshot-step"),
    Option("--screenshot-step", type=argtypes.positive(int, "steps"),
           note="step of the screenshot (default: the last)"),
    Option("--frames", type=Path, note="folder for one PNG per --every steps"),
    Option("--every", type=argtypes.positive(int, "steps"), default=1, note="frame interval in steps (default 1)"),
    Option("--gif", type=Path, note="write an animated GIF of the frames"),
    Option("--size", "size_px", schema=ReplayConfig, unit="pixels", type=argtypes.size,
           note="as WIDTHxHEIGHT"),
    Option("--zoom", "zoom_percent", schema=ReplayConfig, unit="%", type=argtypes.positive(float, "%"), default=None,
           note=f"default {REPLAY.zoom_percent:g} % on the ring, {REPLAY.onramp_zoom_percent:g} % on the on-ramp"),
    Option("--no-gui", note="replay without a window (with --fcd: export only)", extra={"action": "store_true"}),
    Option("--fcd", type=Path, note="also write SUMO FCD XML (with posLat) of the replay"),
    Option("--video", type=Path, note="write the episode as a video drawn from the recording, without SUMO or a "
           "display: PATH.mp4 or PATH.gif, real time (4 frames/s, fewer with --every)"),
    Option("--overwrite", note="replace an existing --video file", extra={"action": "store_true"}),
)
GUI_ONLY = ("screenshot", "screenshot_step", "frames", "gif", "fcd", "no_gui")
"""Options of the sumo-gui replay that --video does not take."""


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """The ``replay`` sub-command's parser."""
    p = subparsers.add_parser(
        "replay",
        help="replay a recorded evaluation episode in sumo-gui",
        description="Replay episode K recorded by 'lanefree evaluate RUN --record' in sumo-gui, exactly, step by "
        "step: the agent green and tracked, background vehicles coloured by desired speed (blue slow, orange "
        "fast), overlapping vehicles red. Prints the largest deviation between SUMO and the recording.",
    )
    add_options(p, OPTIONS)
    return p


def run(args: argparse.Namespace) -> int:
    """``lanefree replay``: print the largest deviation from the recording."""
    from lanefree_sumo.experiments.runners.replay import replay, write_video

    if args.video is not None:
        given = [name for name in GUI_ONLY if getattr(args, name) not in (None, False)]
        if given:
            raise UsageError(f"--video draws the recording without SUMO; drop --{given[0].replace('_', '-')} "
                             "(sumo-gui's options) or --video")
        n = write_video(args.run, args.video, episode=args.episode, every=args.every, overwrite=args.overwrite)
        print(f"wrote {n} frames of episode {args.episode} to {args.video}")
        return 0
    result = replay(args.run, episode=args.episode, gui=not args.no_gui, delay_s=args.delay,
                    screenshot=args.screenshot, screenshot_step=args.screenshot_step, frames=args.frames,
                    every=args.every, gif=args.gif, fcd=args.fcd, size=args.size, zoom=args.zoom)
    print(f"replayed {result.steps} steps; largest deviation from the recording: "
          f"x {result.max_dx_m:.2e} m, y {result.max_dy_m:.2e} m")
    return 0

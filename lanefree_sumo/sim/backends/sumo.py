"""The only module that talks to SUMO: netconvert, libsumo/TraCI backends, bare stepping.

SUMO hosts the ring (specification §1).  Every step the orchestrator sends, for every vehicle, the speed
at the end of the step (``setSpeed`` under speed mode 0, ballistic step method) and the lateral
displacement (``changeSublane`` under lane-change mode 0, vTypes with huge ``maxSpeedLat`` and
``lcAccelLat``); SUMO executes exactly that, and the new state is read back through
subscriptions (lane position, lateral lane position, speed, edge).
"""

from __future__ import annotations

import contextlib
import functools
import io
import math
import os
import subprocess
import tempfile
import time
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TypeVar, cast

import numpy as np
import sumo
import traci
import traci.constants as tc
from sumolib.miscutils import getFreeSocketPort
from traci.exceptions import FatalTraCIError

from lanefree_sumo.config import LaneFreeConfig, ReplayConfig
from lanefree_sumo.errors import SumoError
from lanefree_sumo.sim.dynamics import StepCommand
from lanefree_sumo.sim.network import (
    EDGES,
    ONRAMP_EDGES,
    ROUTE_ID,
    ROUTE_MAIN,
    ROUTE_RAMP,
    VTYPE_AGENT,
    background_vtype,
    default_net_path,
    edge_id,
    edge_to_ring,
    netconvert_args,
    onramp_edge_lengths,
    onramp_edge_offsets,
    ring_to_edge,
    write_additional,
    write_plain_onramp,
    write_plain_ring,
)
from lanefree_sumo.sim.spawn import AGENT_ID, is_agent_id
from lanefree_sumo.sim.state import VehicleState

GUI_VIEW = "View #0"
_SUBSCRIBED = (tc.VAR_ROAD_ID, tc.VAR_LANEPOSITION, tc.VAR_LANEPOSITION_LAT, tc.VAR_SPEED)
_SUBSCRIBED_ONRAMP = (*_SUBSCRIBED, tc.VAR_LANE_INDEX)


def sumo_binary(name: str) -> str:
    """Path of a SUMO executable from the eclipse-sumo wheel (``sumo``, ``sumo-gui``, ...)."""
    path = Path(sumo.SUMO_HOME) / "bin" / name
    if not path.exists():
        raise SumoError(f"SUMO binary {path} is missing; reinstall with 'pip install eclipse-sumo'")
    return str(path)


def sumo_version() -> str:
    """Version of the installed SUMO wheel."""
    out = subprocess.run([sumo_binary("sumo"), "--version"], capture_output=True, text=True, check=False)
    first = (out.stdout or "").splitlines()[0] if out.stdout else ""
    return first.replace("Eclipse SUMO sumo ", "").strip() or "unknown"


def build_ring_net(cfg: LaneFreeConfig, directory: Path) -> Path:
    """Write the plain files, run netconvert and write the default vTypes/route file next to
    them (for opening the net by hand in sumo-gui); return the ``.net.xml`` path."""
    nod, edg = write_plain_ring(cfg.road.length_m, cfg.road.width_m, cfg.road.speed_limit_mps, directory)
    return _netconvert(cfg, nod, edg)


def build_onramp_net(cfg: LaneFreeConfig, directory: Path) -> Path:
    """The on-ramp's plain files, netconvert, and its vTypes/routes file beside them; the ``.net.xml`` path."""
    nod, edg, con = write_plain_onramp(cfg, directory)
    return _netconvert(cfg, nod, edg, con)


def _netconvert(cfg: LaneFreeConfig, nod: Path, edg: Path, con: Path | None = None) -> Path:
    """netconvert of plain files into ``<name>.net.xml`` beside them, and the vTypes/routes file
    ``<name>.add.xml``; the ``.net.xml`` path."""
    net = nod.with_name(nod.name.replace(".nod.xml", ".net.xml"))
    cmd = [sumo_binary("netconvert"), *netconvert_args(nod, edg, net, con), "--no-warnings", "true"]
    result = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if result.returncode != 0:
        msg = (result.stderr or result.stdout).strip().splitlines()
        raise SumoError(f"netconvert failed: {msg[-1] if msg else 'no output'}")
    write_additional(cfg, net.with_name(net.name.replace(".net.xml", ".add.xml")))
    return net


def resolve_net(cfg: LaneFreeConfig) -> Path:
    """The network file to load: ``cfg.net_file`` if set, else the committed one of the road's sizes (built on
    first use into the cache folder for other sizes, :func:`~lanefree_sumo.sim.network.default_net_path`)."""
    if cfg.net_file:
        path = Path(cfg.net_file)
        if not path.is_file():
            raise SumoError(f"network file {path} does not exist; build one with 'lanefree net'")
        return path
    path = default_net_path(cfg)
    if not path.is_file():  # built aside and moved in, the network last: a process beside never reads half a file
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(prefix=".build-", dir=path.parent) as tmp:
            built = NETWORKS[cfg.road.kind][0](cfg, Path(tmp))
            for file in sorted(Path(tmp).iterdir(), key=lambda f: f == built):
                os.replace(file, path.parent / file.name)
    return path


def check_onramp_net(path: Path, cfg: LaneFreeConfig) -> None:
    """Fail with a clear message unless ``path`` is a readable on-ramp of the configured sizes."""
    import sumolib

    try:
        net = sumolib.net.readNet(str(path))
    except Exception as exc:  # sumolib raises bare SAX/XML errors
        raise SumoError(f"network file {path} is not a readable SUMO network ({type(exc).__name__})") from None
    found = {e.getID(): e for e in net.getEdges()}
    if set(found) != set(ONRAMP_EDGES):
        raise SumoError(f"network file {path} is not a lanefree on-ramp (edges {sorted(found)[:6]})")
    lengths = [found[e].getLength() for e in ONRAMP_EDGES]
    widths = [found["merge"].getLane(0).getWidth(), found["merge"].getLane(1).getWidth()]
    expected = [*onramp_edge_lengths(cfg)], [cfg.road.onramp.ramp_width_m, cfg.road.width_m]
    if any(abs(a - b) > 1e-3 for a, b in zip(lengths + widths, expected[0] + expected[1])):
        raise SumoError(f"network file {path} does not match road.onramp (lengths {lengths}, widths {widths})")


def check_ring_net(path: Path, cfg: LaneFreeConfig) -> None:
    """Fail with a clear message unless ``path`` is a readable SUMO ring of the configured size."""
    import sumolib

    try:
        net = sumolib.net.readNet(str(path))
    except Exception as exc:  # sumolib raises bare SAX/XML errors
        raise SumoError(
            f"network file {path} is not a readable SUMO network ({type(exc).__name__}); "
            "rebuild it with 'lanefree net' or 'make nets'"
        ) from None
    expected = {edge_id(k) for k in range(EDGES)}
    found = {e.getID() for e in net.getEdges()}
    if found != expected:
        raise SumoError(
            f"network file {path} is not a lanefree ring (edges {sorted(found)[:6]}); "
            "rebuild it with 'lanefree net'"
        )
    total = sum(e.getLength() for e in net.getEdges())
    width = net.getEdge(edge_id(0)).getLane(0).getWidth()
    if abs(total - cfg.road.length_m) > 1e-3 or abs(width - cfg.road.width_m) > 1e-3:
        raise SumoError(
            f"network file {path} is a {total:g} m × {width:g} m ring but the config asks for "
            f"{cfg.road.length_m:g} m × {cfg.road.width_m:g} m; pass matching --length/--width"
        )


NETWORKS: dict[str, tuple[Callable[[LaneFreeConfig, Path], Path], Callable[[Path, LaneFreeConfig], None]]] = {
    "ring": (build_ring_net, check_ring_net), "onramp": (build_onramp_net, check_onramp_net)}
"""Each road kind's (builder, checker) of its SUMO network."""


def sumo_options(cfg: LaneFreeConfig, net: Path, additional: Path) -> list[str]:
    """Command-line options of the SUMO process (after the binary)."""
    return [
        "--net-file", str(net),
        "--additional-files", str(additional),
        "--step-length", f"{cfg.sim.step_s:g}",
        "--lateral-resolution", f"{cfg.sim.lateral_resolution_m:g}",
        "--step-method.ballistic", "true",
        "--collision.action", "none",
        "--collision.check-junctions", "false",
        "--time-to-teleport", "-1",
        "--no-step-log", "true",
        "--no-warnings", "true",
        "--seed", str(cfg.seed),
    ]


def lane_of(x: float, length_m: float) -> tuple[str, float]:
    """SUMO lane id and lane position (m) of ring coordinate ``x`` (m)."""
    edge, pos = ring_to_edge(np.asarray(x), length_m)
    return f"{edge_id(int(edge))}_0", float(pos)


_Method = TypeVar("_Method", bound=Callable[..., Any])


def _connected(method: _Method) -> _Method:
    """``method`` of a backend with a lost TraCI connection (sumo-gui's window closed by its user, SUMO stopped)
    said as one :class:`SumoError`, not a traceback."""

    @functools.wraps(method)
    def wrapper(self: SumoBackend, *args: Any, **kwargs: Any) -> Any:
        try:
            return method(self, *args, **kwargs)
        except FatalTraCIError:
            raise SumoError(self.lost_message()) from None

    return cast(_Method, wrapper)


class SumoBackend:
    """Executes steps in SUMO through libsumo (in-process) or TraCI (a socket; needed for GUI).

    ``reset`` places a new set of vehicles exactly (no process restart); ``step`` executes a
    :class:`StepCommand` and returns the positions and speeds SUMO reports afterwards.
    """

    def __init__(
        self,
        cfg: LaneFreeConfig,
        kind: str = "libsumo",
        gui: bool = False,
        label: str | None = None,
        extra_args: Sequence[str] = (),
        gui_timeout_s: float = ReplayConfig.display_timeout_s,
    ) -> None:
        """``extra_args``: further SUMO options (e.g. ``--fcd-output``, GUI settings); ``gui_timeout_s``: how long
        sumo-gui may take to open its window before the start gives up (s; TraCI retries once a second)."""
        if kind not in ("libsumo", "traci"):
            raise SumoError(f"unknown SUMO backend '{kind}'; use libsumo or traci")
        if gui and kind != "traci":
            kind = "traci"
        self.cfg = cfg
        self.kind = kind
        self.gui = gui
        self.net = resolve_net(cfg)
        NETWORKS[cfg.road.kind][1](self.net, cfg)
        self._label = label or f"lanefree-{os.getpid()}-{id(self)}"
        self._extra_args = list(extra_args)
        self._ids: list[str] = []
        self._edge_offset = {edge_id(k): float(edge_to_ring(k, 0.0, cfg.road.length_m)) for k in range(EDGES)}
        self._half_width = 0.5 * cfg.road.width_m
        self._min_lateral_move = cfg.sim.sumo_min_lateral_speed_mps * cfg.sim.step_s
        self._y = np.zeros(0)
        self._centre = np.zeros(0)
        """y (m) of the centre of each vehicle's lane (as of the last reset or read)."""
        self._conn: Any = None
        self.gui_start_retries = max(0, math.ceil(gui_timeout_s))
        """Attempts (about 1 s each) to connect to sumo-gui before giving up."""
        self.sumo_step_seconds = 0.0
        """Wall time spent inside SUMO's simulationStep during ``step`` (s), for profiling."""
        self._start()

    # -- process ------------------------------------------------------------------------
    def _start(self) -> None:
        self._tmp = tempfile.TemporaryDirectory(prefix="lanefree-")
        self._gui_log = Path(self._tmp.name) / "sumo-gui.log"
        """sumo-gui's output (its error lines are quoted when it fails or closes)."""
        additional = write_additional(self.cfg, Path(self._tmp.name) / "vtypes.add.xml")
        args = [sumo_binary("sumo-gui" if self.gui else "sumo"), *sumo_options(self.cfg, self.net, additional)]
        if self.gui:
            args += ["--start", "true", "--quit-on-end", "true"]
        args += self._extra_args
        try:
            if self.kind == "libsumo":
                import libsumo

                if libsumo.simulation.isLoaded():
                    raise SumoError(
                        "libsumo already runs a simulation in this process; pass config={'backend': 'numpy'} "
                        "(the same episodes, many per process), the traci backend, or one environment per process"
                    )
                libsumo.start(args)
                self._conn = libsumo
            elif self.gui:
                self._conn = self._start_gui(args)
            else:
                with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # traci's "Retrying" noise; we say one line instead
                    traci.start(args, label=self._label, stdout=subprocess.DEVNULL)
                self._conn = traci.getConnection(self._label)
        except SumoError:
            self._tmp.cleanup()
            raise
        except Exception as exc:
            self._tmp.cleanup()
            raise SumoError(f"SUMO did not start: {str(exc).strip() or type(exc).__name__}; "
                            f"check the network file {self.net}") from None

    def _start_gui(self, args: list[str]) -> Any:
        """Start sumo-gui and connect to it within ``gui_start_retries`` seconds, its output in a log beside the
        simulation's files (so that a failure is one line: ours, quoting sumo-gui's). A port taken between its
        choice and sumo-gui's start is retried on another, as :func:`traci.start` does."""
        display = os.environ.get("DISPLAY")
        if not display:
            raise SumoError("sumo-gui needs a display and none is set (DISPLAY); "
                            "on a headless machine run the command under 'xvfb-run -a'")
        for attempt in range(3):
            port = int(getFreeSocketPort())
            with self._gui_log.open("wb") as log:
                proc = subprocess.Popen([*args, "--remote-port", str(port)], stdout=subprocess.DEVNULL, stderr=log)
            try:
                with contextlib.redirect_stdout(io.StringIO()):  # traci's "Retrying" noise; we say one line
                    traci.init(port, numRetries=self.gui_start_retries, label=self._label, proc=proc)
                return traci.getConnection(self._label)
            except BaseException as exc:  # Ctrl-C too: sumo-gui does not outlive the start
                proc.kill()
                proc.wait()
                if not isinstance(exc, Exception):
                    raise
                said = self._gui_said()
                if "in use" in said and attempt < 2:  # the port taken meanwhile: another one
                    continue
                raise SumoError(f"sumo-gui did not open its window on display {display!r}"
                                + (f" ({said})" if said else "")
                                + "; check the display, or on a headless machine run under 'xvfb-run -a'") from None
        raise AssertionError("unreachable")

    def _gui_said(self) -> str:
        """sumo-gui's first error line (an ``Error:``, or the toolkit's ``FXApp::…`` complaint), or "" (its other
        output — font warnings and the like — explains nothing)."""
        try:
            lines = self._gui_log.read_text(errors="replace").splitlines()
        except OSError:
            return ""
        return next((line.strip() for line in lines if "Error" in line or "FXApp" in line), "")

    def lost_message(self) -> str:
        """One line for a lost connection to SUMO: the window closed, or SUMO stopped (quoting sumo-gui)."""
        if self.gui:
            said = self._gui_said()
            return ("sumo-gui closed before the end (its window was closed, or it stopped"
                    + (f": {said}" if said else "") + ")")
        return "SUMO stopped before the end (its connection closed); run again, or use the libsumo backend"

    def close(self) -> None:
        """Stop SUMO (idempotent)."""
        if self._conn is None:
            return
        try:
            self._conn.close()
        except Exception:  # already closed by SUMO (e.g. GUI window closed)
            pass
        self._conn = None
        self._tmp.cleanup()

    def __del__(self) -> None:  # pragma: no cover - best effort
        try:
            self.close()
        except Exception:
            pass

    # -- episodes -----------------------------------------------------------------------
    _subscribed: tuple[int, ...] = _SUBSCRIBED
    """The variables read back after every step."""

    def _placement(self, x: float, y: float) -> tuple[str, str, float, float]:
        """(route, lane id, lane position, centre y of that lane) of a vehicle at (x, y) (m)."""
        lane, pos = lane_of(x, self.cfg.road.length_m)
        return ROUTE_ID, lane, pos, self._half_width

    def _vtype(self, vid: str, v_desired: float) -> str:
        return VTYPE_AGENT if is_agent_id(vid) else background_vtype(v_desired, self.cfg)

    def _insert(self, vid: str, route: str, lane: str, pos: float, speed: float, v_desired: float) -> None:
        """Add ``vid`` under our control (speed and lane-change modes 0) and move it onto ``lane`` at ``pos``."""
        v = self._conn.vehicle
        v.add(vid, route, self._vtype(vid, v_desired), depart="now", departSpeed=repr(speed))
        v.setSpeedMode(vid, 0)
        v.setLaneChangeMode(vid, 0)
        v.moveTo(vid, lane, pos)

    @_connected
    def reset(self, state: VehicleState) -> None:
        """Remove all vehicles and place ``state``'s vehicles at their exact positions/speeds."""
        v = self._conn.vehicle
        places = [self._placement(float(x), float(y)) for x, y in zip(state.x, state.y)]
        try:
            for vid in v.getIDList():
                v.unsubscribe(vid)  # libsumo keeps a removed vehicle's subscription: the next step would fail on it
                v.remove(vid)
            for i, (vid, (route, lane, pos, _)) in enumerate(zip(state.ids, places)):
                self._insert(vid, route, lane, pos, float(state.vx[i]), float(state.v_desired[i]))
            self._conn.simulationStep()  # inserts them
            for i, (vid, (_, lane, pos, centre)) in enumerate(zip(state.ids, places)):
                v.moveTo(vid, lane, pos)
                v.setLateralLanePosition(vid, float(state.y[i]) - centre)
                v.setPreviousSpeed(vid, float(state.vx[i]))
                v.subscribe(vid, self._subscribed)
            if self.gui and AGENT_ID in state.ids:
                self._conn.gui.trackVehicle(GUI_VIEW, AGENT_ID)
        except (SumoError, FatalTraCIError):
            raise
        except Exception as exc:
            raise SumoError(f"SUMO refused to place the vehicles: {exc}") from None
        self._ids = list(state.ids)
        self._y = state.y.copy()
        self._centre = np.array([centre for *_, centre in places])

    @_connected
    def read(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x, y, vx) of every vehicle in the order of the last ``reset`` (m, m, m/s)."""
        res = self._conn.vehicle.getAllSubscriptionResults()
        off = self._edge_offset
        try:
            rows = [res[vid] for vid in self._ids]
        except KeyError as exc:
            raise SumoError(f"vehicle {exc} left the SUMO simulation unexpectedly") from None
        x = np.fromiter((off[r[tc.VAR_ROAD_ID]] + r[tc.VAR_LANEPOSITION] for r in rows), float, len(rows))
        y = np.fromiter((r[tc.VAR_LANEPOSITION_LAT] for r in rows), float, len(rows)) + self._half_width
        vx = np.fromiter((r[tc.VAR_SPEED] for r in rows), float, len(rows))
        self._y = y
        return x, y, vx

    @_connected
    def step(self, cmd: StepCommand) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Command every vehicle, advance SUMO one step, and read the new state back.

        SUMO ignores a ``changeSublane`` whose lateral speed |dy|/T is below its numerical
        epsilon (0.001 m/s, i.e. 0.25 mm per 0.25 s step); such tiny moves are applied with
        ``setLateralLanePosition`` before the step instead, so every move is executed exactly.
        """
        v = self._conn.vehicle
        set_speed = v.setSpeed
        change = v.changeSublane
        set_lat = v.setLateralLanePosition
        tiny = np.abs(cmd.dy) < self._min_lateral_move
        lat_target = (self._y + cmd.dy - self._half_width).tolist()
        for vid, speed, dy, small, target in zip(
            self._ids, cmd.vx_next.tolist(), cmd.dy.tolist(), tiny.tolist(), lat_target
        ):
            set_speed(vid, speed)
            if small:
                if dy != 0.0:
                    set_lat(vid, target)
            else:
                change(vid, dy)
        t0 = time.perf_counter()
        self._conn.simulationStep()
        self.sumo_step_seconds += time.perf_counter() - t0
        return self.read()

    @_connected
    def set_color(self, vid: str, rgba: tuple[int, int, int, int]) -> None:
        """Colour of a vehicle in sumo-gui (0–255 each)."""
        self._conn.vehicle.setColor(vid, rgba)

    @_connected
    def screenshot(self, path: Path, width: int, height: int) -> None:
        """Ask sumo-gui for a PNG of the view; SUMO writes it during the next simulation step."""
        self._conn.gui.screenshot(GUI_VIEW, str(path), width, height)

    @_connected
    def track(self, vid: str, zoom: float) -> None:
        """Centre the sumo-gui view on ``vid`` and follow it, at ``zoom`` (%)."""
        self._conn.gui.setZoom(GUI_VIEW, zoom)
        self._conn.gui.trackVehicle(GUI_VIEW, vid)

    @_connected
    def idle_step(self) -> None:
        """One simulation step without commands (lets SUMO finish pending screenshots)."""
        self._conn.simulationStep()


class OnRampSumoBackend(SumoBackend):
    """:class:`SumoBackend` on the on-ramp: vehicles enter (:meth:`add`) and leave (:meth:`remove`); a
    vehicle's y is its lane centre's (the main road's at W/2 on every edge, the ramp's at −w_r/2) plus
    SUMO's lateral offset in that lane. Main-road vehicles follow the route ``up merge down``, ramp
    vehicles ``merge down`` from lane 0 of ``merge``."""

    _subscribed = _SUBSCRIBED_ONRAMP

    def __init__(self, cfg: LaneFreeConfig, kind: str = "libsumo", gui: bool = False, label: str | None = None,
                 extra_args: Sequence[str] = (), gui_timeout_s: float = ReplayConfig.display_timeout_s) -> None:
        super().__init__(cfg, kind, gui, label, extra_args, gui_timeout_s)
        self._offsets = np.array(onramp_edge_offsets(cfg))
        self._edge_offset = dict(zip(ONRAMP_EDGES, self._offsets.tolist()))
        self._ramp_half = 0.5 * cfg.road.onramp.ramp_width_m

    def _placement(self, x: float, y: float) -> tuple[str, str, float, float]:
        """(route, lane id, lane position, centre y of that lane) of a vehicle at (x, y) (m): the ramp's
        lane is lane 0 of ``merge`` where y < 0; ramp vehicles take the route from ``merge`` on."""
        k = int(np.searchsorted(self._offsets, x, side="right")) - 1
        lane = (0 if y < 0.0 else 1) if k == 1 else 0
        on_ramp = (k, lane) == (1, 0)
        return (ROUTE_RAMP if on_ramp else ROUTE_MAIN, f"{ONRAMP_EDGES[k]}_{lane}", x - float(self._offsets[k]),
                -self._ramp_half if on_ramp else self._half_width)

    @_connected
    def add(self, rows: VehicleState) -> None:
        """Vehicles entering the road where ``rows`` place them (appended, in order): inserted at once
        (``moveTo`` of a vehicle not yet on the road inserts it there, whatever SUMO's own insertion checks
        would say), so they move in the next :meth:`step`."""
        v = self._conn.vehicle
        centres = []
        try:
            for i, vid in enumerate(rows.ids):
                route, lane, pos, centre = self._placement(float(rows.x[i]), float(rows.y[i]))
                speed = float(rows.vx[i])
                self._insert(vid, route, lane, pos, speed, float(rows.v_desired[i]))
                v.setLateralLanePosition(vid, float(rows.y[i]) - centre)
                v.setPreviousSpeed(vid, speed)
                v.subscribe(vid, self._subscribed)
                centres.append(centre)
        except (SumoError, FatalTraCIError):
            raise
        except Exception as exc:
            raise SumoError(f"SUMO refused an entering vehicle: {exc}") from None
        self._ids += list(rows.ids)
        self._y = np.concatenate([self._y, rows.y])
        self._centre = np.concatenate([self._centre, centres])

    @_connected
    def remove(self, keep: np.ndarray) -> None:
        """Take the vehicles where ``keep`` is False off the road."""
        v = self._conn.vehicle
        for vid, kept in zip(self._ids, keep.tolist()):
            if not kept:
                v.unsubscribe(vid)
                v.remove(vid)
        self._ids = [vid for vid, kept in zip(self._ids, keep.tolist()) if kept]
        self._y, self._centre = self._y[keep], self._centre[keep]

    @_connected
    def read(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x, y, vx) of every vehicle, in the order they entered (m, m, m/s)."""
        res = self._conn.vehicle.getAllSubscriptionResults()
        try:
            rows = [res[vid] for vid in self._ids]
        except KeyError as exc:
            raise SumoError(f"vehicle {exc} left the SUMO simulation unexpectedly") from None
        off = self._edge_offset
        x = np.fromiter((off[r[tc.VAR_ROAD_ID]] + r[tc.VAR_LANEPOSITION] for r in rows), float, len(rows))
        self._centre = np.fromiter((-self._ramp_half if (r[tc.VAR_ROAD_ID], r[tc.VAR_LANE_INDEX]) == ("merge", 0)
                                    else self._half_width for r in rows), float, len(rows))
        y = self._centre + np.fromiter((r[tc.VAR_LANEPOSITION_LAT] for r in rows), float, len(rows))
        vx = np.fromiter((r[tc.VAR_SPEED] for r in rows), float, len(rows))
        self._y = y
        return x, y, vx

    @_connected
    def step(self, cmd: StepCommand) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Command every vehicle on the road, advance SUMO one step, read the new state back."""
        v = self._conn.vehicle
        tiny = np.abs(cmd.dy) < self._min_lateral_move
        lat_target = (self._y + cmd.dy - self._centre).tolist()
        for vid, speed, dy, small, target in zip(self._ids, cmd.vx_next.tolist(), cmd.dy.tolist(), tiny.tolist(),
                                                 lat_target):
            v.setSpeed(vid, speed)
            if small:
                if dy != 0.0:
                    v.setLateralLanePosition(vid, target)
            else:
                v.changeSublane(vid, dy)
        t0 = time.perf_counter()
        self._conn.simulationStep()
        self.sumo_step_seconds += time.perf_counter() - t0
        return self.read()


def bare_step_rate(cfg: LaneFreeConfig, state: VehicleState, steps: int) -> float:
    """Steps per second of SUMO alone: the same vehicles on the same ring, driven by SUMO's own
    car-following and sublane models, with no Python control at all (the benchmark baseline)."""
    import libsumo

    net = resolve_net(cfg)
    tmp = tempfile.TemporaryDirectory(prefix="lanefree-")
    additional = write_additional(cfg, Path(tmp.name) / "vtypes.add.xml")
    libsumo.start([sumo_binary("sumo"), *sumo_options(cfg, net, additional)])
    try:
        for i, vid in enumerate(state.ids):
            libsumo.vehicle.add(vid, ROUTE_ID, background_vtype(float(state.v_desired[i]), cfg), depart="now",
                                departSpeed=f"{state.vx[i]:.6f}")
            libsumo.vehicle.moveTo(vid, *lane_of(float(state.x[i]), cfg.road.length_m))
            libsumo.vehicle.setMaxSpeed(vid, float(state.v_desired[i]))
        libsumo.simulationStep()
        for i, vid in enumerate(state.ids):
            libsumo.vehicle.setLateralLanePosition(vid, float(state.y[i]) - 0.5 * cfg.road.width_m)
        t0 = time.perf_counter()
        for _ in range(steps):
            libsumo.simulationStep()
        return steps / (time.perf_counter() - t0)
    finally:
        libsumo.close()
        tmp.cleanup()


BACKENDS: dict[str, type[SumoBackend]] = {"ring": SumoBackend, "onramp": OnRampSumoBackend}
"""Each road kind's SUMO backend."""


def sumo_backend(cfg: LaneFreeConfig) -> type[SumoBackend]:
    """The SUMO backend class of ``cfg``'s road kind."""
    return BACKENDS[cfg.road.kind]

"""``make onramp-flows``: the on-ramp's inflow–outflow curve.

For each main-road demand of ``--main-flows`` at the fixed ramp demand ``--ramp-flow`` and each seed, the
background traffic runs ``--seconds`` on the on-ramp; the first ``--warmup`` seconds are not measured.
Per run: the inflow (vehicles that entered per hour: the demand the road accepted), the outflow (vehicles
that left at the downstream end per hour), the mean speed on the road, collisions, merge success
(ramp vehicles merged, of those that entered, and whether any reached the ramp's end unmerged) and the
arrivals still queued at the end (the demand the entry could not place: the road is saturated).

Writes ``onramp_flows.csv`` (one row per run), ``onramp_flows.md`` (means over seeds per demand) and
``onramp_flows.png`` (outflow and inflow against demand) into ``--out``.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path
from typing import Any

import numpy as np

from lanefree_sumo.config import LaneFreeConfig, merge_config
from lanefree_sumo.sim.simulation import Simulation, StepResult
from lanefree_sumo.sim.state import VehicleState

COLUMNS = ("main_demand_veh_per_h", "ramp_demand_veh_per_h", "seed", "inflow_veh_per_h", "outflow_veh_per_h",
           "mean_speed_mps", "collisions", "ramp_entered", "ramp_merged", "ramp_end_reached_unmerged",
           "waiting_at_end")


def measure(cfg: LaneFreeConfig, seconds: float, warmup: float) -> dict[str, Any]:
    """One run's row (flows in veh/h over the measured part, speeds in m/s)."""
    sim = Simulation(cfg)
    sim.reset(cfg.seed)
    assert sim.traffic is not None
    steps, first = int(round(seconds / cfg.sim.step_s)), int(round(warmup / cfg.sim.step_s))
    books = {"collisions": 0, "speed": 0.0, "measured": 0}
    start: dict[str, int] = {}

    def observe(step: int, state: VehicleState, result: StepResult) -> None:
        if step == first:
            c = sim.traffic.counts  # type: ignore[union-attr]
            start.update(entered=c.entered_main + c.entered_ramp, left=c.left)
        if step > first:
            books["collisions"] += len(result.new_collisions)
            books["speed"] += float(state.vx.mean()) if state.n else 0.0
            books["measured"] += 1

    try:
        for k in range(1, steps + 1):
            result = sim.step()
            observe(k, sim.current()[0], result)
    finally:
        sim.close()
    c = sim.traffic.counts
    hours = books["measured"] * cfg.sim.step_s / 3600.0
    o = cfg.road.onramp
    return {
        "main_demand_veh_per_h": o.main_flow_veh_per_h, "ramp_demand_veh_per_h": o.ramp_flow_veh_per_h,
        "seed": cfg.seed,
        "inflow_veh_per_h": (c.entered_main + c.entered_ramp - start["entered"]) / hours,
        "outflow_veh_per_h": (c.left - start["left"]) / hours,
        "mean_speed_mps": books["speed"] / max(books["measured"], 1), "collisions": books["collisions"],
        "ramp_entered": c.entered_ramp, "ramp_merged": c.merged, "ramp_end_reached_unmerged": c.ramp_end_reached,
        "waiting_at_end": sum(c.waiting),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="The on-ramp's inflow–outflow curve (module docstring).")
    p.add_argument("--main-flows", default="1000,2000,3000,4000,5000,6000,7000,8000",
                   help="main-road demands in veh/h, comma-separated")
    p.add_argument("--ramp-flow", type=float, default=LaneFreeConfig().road.onramp.ramp_flow_veh_per_h,
                   help="ramp demand in veh/h")
    p.add_argument("--seeds", type=int, default=3, help="seeds per demand")
    p.add_argument("--seconds", type=float, default=900.0, help="simulated time per run in s")
    p.add_argument("--warmup", type=float, default=300.0, help="unmeasured first seconds")
    p.add_argument("--density", type=float, default=20.0, help="main-road density at the start in veh/km")
    p.add_argument("--out", type=Path, default=Path("results/onramp"), help="output folder")
    args = p.parse_args(argv)
    demands = [float(q) for q in args.main_flows.split(",")]
    rows = []
    for q in demands:
        for seed in range(args.seeds):
            cfg = merge_config(LaneFreeConfig(), {
                "backend": "numpy", "seed": seed, "scenario": {"density_veh_per_km": args.density},
                "road": {"kind": "onramp", "onramp": {"main_flow_veh_per_h": q, "ramp_flow_veh_per_h": args.ramp_flow}},
            })
            rows.append(measure(cfg, args.seconds, args.warmup))
            r = rows[-1]
            print(f"demand {q:6.0f} seed {seed}: in {r['inflow_veh_per_h']:6.0f} out {r['outflow_veh_per_h']:6.0f} "
                  f"veh/h, {r['mean_speed_mps']:5.2f} m/s, {r['collisions']} collisions, "
                  f"{r['ramp_merged']}/{r['ramp_entered']} merged, {r['waiting_at_end']} waiting", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    with open(args.out / "onramp_flows.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    _table(args, demands, rows)
    _plot(args.out / "onramp_flows.png", demands, rows, args.ramp_flow)
    print(f"-> {args.out}")
    return 0


def _mean(rows: list[dict[str, Any]], q: float, key: str) -> tuple[float, float]:
    values = np.array([r[key] for r in rows if r["main_demand_veh_per_h"] == q], dtype=float)
    return float(values.mean()), float(values.std(ddof=1)) if len(values) > 1 else float("nan")


def _table(args: argparse.Namespace, demands: list[float], rows: list[dict[str, Any]]) -> None:
    lines = [
        "# On-ramp: inflow and outflow against demand", "",
        f"Ramp demand {args.ramp_flow:g} veh/h; {args.seconds:g} s per run, the first {args.warmup:g} s not measured; "
        f"{args.seeds} seeds per demand (mean ± sample std); numpy backend; defaults of `road.onramp`.", "",
        "| main demand (veh/h) | inflow (veh/h) | outflow (veh/h) | mean speed (m/s) | collisions / run "
        "| ramp merged / entered | reached ramp end unmerged | waiting at the end |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for q in demands:
        mine = [r for r in rows if r["main_demand_veh_per_h"] == q]
        cells = [f"{_mean(rows, q, k)[0]:.0f} ± {_mean(rows, q, k)[1]:.0f}" for k in ("inflow_veh_per_h",
                                                                                       "outflow_veh_per_h")]
        speed = _mean(rows, q, "mean_speed_mps")
        lines.append(
            f"| {q:.0f} | {cells[0]} | {cells[1]} | {speed[0]:.2f} ± {speed[1]:.2f} "
            f"| {np.mean([r['collisions'] for r in mine]):.1f} | {sum(r['ramp_merged'] for r in mine)} / "
            f"{sum(r['ramp_entered'] for r in mine)} | {sum(r['ramp_end_reached_unmerged'] for r in mine)} "
            f"| {np.mean([r['waiting_at_end'] for r in mine]):.0f} |")
    (args.out / "onramp_flows.md").write_text("\n".join(lines) + "\n")


def _plot(path: Path, demands: list[float], rows: list[dict[str, Any]], ramp: float) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7.0, 4.6), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    for key, label in (("inflow_veh_per_h", "inflow (entered)"), ("outflow_veh_per_h", "outflow (left)")):
        means = [_mean(rows, q, key) for q in demands]
        ax.errorbar(demands, [m for m, _ in means], yerr=[0.0 if np.isnan(s) else s for _, s in means],
                    marker="o", capsize=3, label=label)
    ax.plot(demands, [q + ramp for q in demands], "k:", label="demand (main + ramp)")
    ax.set_xlabel("main-road demand (veh/h)")
    ax.set_ylabel("flow (veh/h)")
    ax.set_title(f"On-ramp, ramp demand {ramp:g} veh/h", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)


if __name__ == "__main__":
    raise SystemExit(main())

"""``make traffic``: is the background traffic sane, and what holds it below its desired speed?

Runs every density × seed for 200 s on libsumo and prints a Markdown table: collisions, boundary
contacts, smallest margin to a road edge, mean speed against mean desired speed, and from the
driver model's diagnostics the share of vehicle-steps that follow a summed repulsion (Σf_x < 0),
whose x-wall lowers F_x, and whose x-wall leader is alongside with a negative bumper gap; last,
the speed ratio v/v_d of the third of vehicles with the highest desired speeds against the
lowest third.
"""

from __future__ import annotations

import argparse

import numpy as np

from lanefree_sumo.config import BACKENDS, LaneFreeConfig, merge_config
from lanefree_sumo.sim.simulation import Simulation, StepResult, run_simulation
from lanefree_sumo.sim.state import VehicleState

HEADER = ("| density (veh/km) | seed | vehicles | collisions | boundary contacts | min margin (m) | mean speed (m/s) "
          "| mean desired (m/s) | ratio | following % | wall binds % | negative-gap leader % "
          "| v/v_d fast third | v/v_d slow third |")


def check(cfg: LaneFreeConfig, seconds: float) -> str:
    """One table row for ``cfg`` simulated for ``seconds`` (s)."""
    sim = Simulation(cfg, diagnostics=True)
    counts = {"following": 0, "wall": 0, "negative_gap": 0, "vehicle_steps": 0}
    ratio_sum: list[np.ndarray] = []

    def observe(_step: int, state: VehicleState, _result: StepResult) -> None:
        details = sim.force_details or {}
        counts["following"] += int(np.count_nonzero(details["sum_fx"] < 0.0))
        counts["wall"] += int(np.count_nonzero(details["wall_binds"]))
        counts["negative_gap"] += int(np.count_nonzero(details["leader_gap_m"] < 0.0))
        counts["vehicle_steps"] += state.n
        ratio_sum.append(state.vx / state.v_desired)

    s = run_simulation(cfg, int(round(seconds / cfg.sim.step_s)), on_step=observe, sim=sim)
    vs = max(counts["vehicle_steps"], 1)
    ratios = np.mean(ratio_sum, axis=0)
    desired = sim.state.v_desired if sim.state is not None else np.ones_like(ratios)
    order = np.argsort(desired)
    third = max(len(order) // 3, 1)
    return (f"| {cfg.scenario.density_veh_per_km:g} | {cfg.seed} | {s['vehicles']} | {s['background_collisions']} "
            f"| {s['boundary_contacts']} | {s['min_lateral_margin_m']:.3f} | {s['mean_speed_mps']:.2f} "
            f"| {s['mean_desired_speed_mps']:.2f} | {s['mean_speed_mps'] / s['mean_desired_speed_mps']:.3f} "
            f"| {100 * counts['following'] / vs:.1f} | {100 * counts['wall'] / vs:.1f} "
            f"| {100 * counts['negative_gap'] / vs:.2f} | {ratios[order[-third:]].mean():.3f} "
            f"| {ratios[order[:third]].mean():.3f} |")


def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m lanefree_sumo.tools.traffic_check",
                                     description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--densities", type=float, nargs="+", default=[70, 90, 120], help="veh/km (default 70 90 120)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="seeds (default 0 1 2)")
    parser.add_argument("--seconds", type=float, default=200.0, help="simulated time per run in s (default 200)")
    parser.add_argument("--backend", default=LaneFreeConfig().backend, choices=BACKENDS)
    args = parser.parse_args()
    print(HEADER)
    print("|" + "---|" * HEADER.count(" |"))
    for density in args.densities:
        for seed in args.seeds:
            cfg = merge_config(
                LaneFreeConfig(),
                {"seed": seed, "backend": args.backend, "scenario": {"density_veh_per_km": density}},
            )
            print(check(cfg, args.seconds), flush=True)


if __name__ == "__main__":
    main()

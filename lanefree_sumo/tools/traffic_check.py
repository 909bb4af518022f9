"""``make traffic``: is the background traffic sane?  Runs every density × seed for 200 s on
libsumo and prints a Markdown table of collisions, boundary contacts, smallest margin to a road
edge and mean speed against mean desired speed."""

from __future__ import annotations

import argparse

from lanefree_sumo.config import LaneFreeConfig, merge_config
from lanefree_sumo.sim.simulation import run_simulation


def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m lanefree_sumo.tools.traffic_check",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--densities", type=float, nargs="+", default=[70, 90, 120], help="veh/km (default 70 90 120)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="seeds (default 0 1 2)")
    parser.add_argument("--seconds", type=float, default=200.0, help="simulated time per run in s (default 200)")
    parser.add_argument("--backend", default="libsumo", choices=("libsumo", "traci", "numpy"))
    args = parser.parse_args()
    print("| density (veh/km) | seed | vehicles | collisions | boundary contacts | min margin (m) "
          "| mean speed (m/s) | mean desired (m/s) | ratio |")
    print("|---|---|---|---|---|---|---|---|---|")
    for density in args.densities:
        for seed in args.seeds:
            cfg = merge_config(
                LaneFreeConfig(),
                {"seed": seed, "backend": args.backend, "scenario": {"density_veh_per_km": density}},
            )
            s = run_simulation(cfg, int(round(args.seconds / cfg.sim.step_s)))
            print(f"| {density:g} | {seed} | {s['vehicles']} | {s['background_collisions']} | {s['boundary_contacts']} "
                  f"| {s['min_lateral_margin_m']:.3f} | {s['mean_speed_mps']:.2f} | {s['mean_desired_speed_mps']:.2f} "
                  f"| {s['mean_speed_mps'] / s['mean_desired_speed_mps']:.3f} |", flush=True)


if __name__ == "__main__":
    main()

"""Sweep throughput against one standalone run: env steps/s summed over a sweep's concurrent runs
divided by the steps/s of one ``lanefree train`` alone on the same machine (the goal: ≥ 1.7
with 2 workers on 2 cores).

    python -m lanefree_sumo.experiments.sweep.throughput [--workers 2] [--episodes 10] [--out DIR]

Runs, one after the other and on an otherwise idle machine: (1) ``lanefree train`` of DDPG,
fields_zones_overtake_collision, 70 veh/km, seed 0, ``--episodes`` episodes of 800 steps; (2)
``lanefree sweep`` of the same setting with seeds 0 … workers−1 and ``--workers`` workers.
Steps/s of a run is ``last_session.json``'s (timesteps of its training loop / its wall time, so
process and Ray start-up are not counted); the sweep's is the sum over its runs, which ran at the
same time. Also reported: the sweep's end-to-end rate (all steps / wall time of the whole
command, start-up included). Prints a table and writes ``DIR/throughput.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import yaml

ALGORITHM, PRESET, DENSITY = "ddpg", "fields_zones_overtake_collision", 70


def _lanefree(*args: str) -> float:
    """Run ``lanefree ARGS``; its wall time (s)."""
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "lanefree_sumo.cli", *args], check=True)
    return time.perf_counter() - t0


def _rate(run: Path) -> tuple[float, int]:
    session = json.loads((run / "last_session.json").read_text())
    return float(session["steps_per_s"]), int(session["timesteps"])


def measure(out: Path, workers: int, episodes: int) -> dict[str, Any]:
    if out.exists():
        raise SystemExit(f"{out} exists; choose another --out")
    out.mkdir(parents=True)
    alone_run = out / "standalone"
    alone_wall = _lanefree("train", "--algo", ALGORITHM, "--reward", PRESET, "--density", str(DENSITY),
                           "--episodes", str(episodes), "--seed", "0", "--out", str(alone_run))
    alone, _ = _rate(alone_run)
    grid = out / "grid.yaml"
    grid.write_text(yaml.safe_dump({"algorithms": [ALGORITHM], "reward_presets": [PRESET], "densities": [DENSITY],
                                    "n_seeds": workers, "episodes": episodes}))
    sweep_wall = _lanefree("sweep", str(grid), "--out", str(out / "sweep"), "--workers", str(workers), "--no-progress")
    rates = [_rate(run) for run in sorted((out / "sweep" / "runs").iterdir())]
    summed = sum(r for r, _ in rates)
    result = {"workers": workers, "episodes": episodes, "standalone_steps_per_s": alone,
              "standalone_wall_s": alone_wall, "sweep_steps_per_s_summed": summed,
              "sweep_steps_per_s_end_to_end": sum(n for _, n in rates) / sweep_wall, "sweep_wall_s": sweep_wall,
              "ratio": summed / alone, "ratio_end_to_end": sum(n for _, n in rates) / sweep_wall / alone,
              "host": platform.node(), "cpus": len(os.sched_getaffinity(0))}
    (out / "throughput.json").write_text(json.dumps(result, indent=2) + "\n")
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--workers", type=int, default=2, help="sweep workers = concurrent runs (default 2)")
    parser.add_argument("--episodes", type=int, default=10, help="episodes of 800 steps per run (default 10)")
    parser.add_argument("--out", type=Path, default=Path("runs") / f"throughput-{time.strftime('%Y%m%d-%H%M%S')}")
    args = parser.parse_args()
    if args.workers < 1 or args.episodes < 1:
        parser.error("--workers and --episodes must be at least 1")
    r = measure(args.out, args.workers, args.episodes)
    print(f"standalone run:              {r['standalone_steps_per_s']:8.1f} env steps/s")
    print(f"sweep, {r['workers']} workers, summed:    {r['sweep_steps_per_s_summed']:8.1f} env steps/s "
          f"= {r['ratio']:.2f} × standalone")
    print(f"sweep, end to end:           {r['sweep_steps_per_s_end_to_end']:8.1f} env steps/s "
          f"= {r['ratio_end_to_end']:.2f} × standalone (start-up included)")
    print(f"-> {args.out / 'throughput.json'}")


if __name__ == "__main__":
    main()

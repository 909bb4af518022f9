"""The shield's table in docs/shield.md: `lanefree rollout` of the random and the idle policy at 70, 90 and 120
veh/km, with and without the shield, 10 episodes of 800 steps each from traffic seed 9 (libsumo), one Markdown
row per (policy, density, shield). Extra arguments go to every rollout (e.g. ``--set
shield.fallback_steers_clear=true``).

    python scripts/analysis/shield_table.py [--episodes 10] [-- ROLLOUT_ARGS...]
"""

from __future__ import annotations

import argparse
import json
import subprocess
from pathlib import Path

BIN = Path(__file__).resolve().parents[2] / ".venv" / "bin" / "lanefree"
HEADER = ("| policy | density (veh/km) | shield | agent collisions ({n} episodes) | per episode "
          "| background collisions | interventions / episode | steps without a certified action / episode "
          "| speed deviation (m/s) | mean speed (m/s) |\n|---|---|---|---|---|---|---|---|---|---|")


def rollout(policy: str, density: int, shield: bool, episodes: int, extra: list[str]) -> dict:
    """One `lanefree rollout --json` summary (its stdout's last line)."""
    command = [str(BIN), "rollout", "--policy", policy, "--density", str(density), "--episodes", str(episodes),
               "--seed", "9", "--shield" if shield else "--no-shield", "--json", *extra]
    done = subprocess.run(command, capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def row(policy: str, density: int, shield: bool, s: dict) -> str:
    """A table row; the shield's columns are – without it."""
    collisions = f"**{s['collisions']}**" if shield else str(s["collisions"])
    on = (f"{s['shield_interventions_per_episode']:.1f} | {s['shield_fallbacks_per_episode']:.1f}" if shield
          else "– | –")
    return (f"| {policy} | {density} | {'on' if shield else 'off'} | {collisions} | {s['collisions_per_episode']:g} "
            f"| {s['background_collisions']} | {on} | {s['speed_dev_mps']:.2f} | {s['mean_speed_mps']:.2f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=10, help="episodes per row (default 10)")
    parser.add_argument("extra", nargs="*", help="arguments for every rollout, after --")
    args = parser.parse_args()
    print(HEADER.format(n=args.episodes))
    for policy in ("random", "idle"):
        for density in (70, 90, 120):
            for shield in (False, True):
                print(row(policy, density, shield, rollout(policy, density, shield, args.episodes, args.extra)),
                      flush=True)


if __name__ == "__main__":
    main()

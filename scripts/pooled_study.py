"""The diagnosis pooled over a vehicle's flights on seeded simulated vehicles: how often a small temperature
offset present in every flight is recommended for the vehicle, against how often single flights find it, and
how often anything is recommended when nothing is hidden.

    python scripts/pooled_study.py [--coefficient 0.6] [--flights 4] [--vehicles 80] [--minutes 3] [--rate 10]

Each vehicle is ``--flights`` simulated flights (30 nT of noise) with ``temperature_bias`` of ``--coefficient`` nT
per degree C on each axis (0: nothing hidden). Prints the flights where the effect is significant alone, the
vehicles where the pooled diagnosis recommends it (and any effect), those among the vehicles where no flight
reached significance alone, and the vehicles where its coefficient was found to differ between flights.
"""

from __future__ import annotations

import argparse

from magkf.diagnostics.diagnose import diagnose
from magkf.diagnostics.pooled import pool
from magkf.effects import BUILTIN
from magkf.io.drivelog import DriveLog
from magkf.sim import DriveConfig, simulate_drive


def flight(seed: int, coefficient: float, minutes: float, rate: float):
    """One flight's diagnosis."""
    effects = [(BUILTIN["temperature_bias"](), [coefficient] * 3)] if coefficient else []
    config = DriveConfig(duration_s=60.0 * minutes, rate_hz=rate, noise_nt=30.0, seed=seed)
    return diagnose(DriveLog(simulate_drive(config, effects=effects).table))[0]


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--coefficient", type=float, default=0.6, help="nT per degree C on each axis (0: none)")
    p.add_argument("--flights", type=int, default=4)
    p.add_argument("--vehicles", type=int, default=80)
    p.add_argument("--minutes", type=float, default=3.0)
    p.add_argument("--rate", type=float, default=10.0)
    p.add_argument("--seed", type=int, default=20000)
    args = p.parse_args(argv)
    label = BUILTIN["temperature_bias"]().label
    alone = hit = anything = quiet = quiet_hit = differs = 0
    for v in range(args.vehicles):
        seeds = range(args.seed + v * args.flights, args.seed + (v + 1) * args.flights)
        pooled = pool({f"flight{s}": flight(s, args.coefficient, args.minutes, args.rate) for s in seeds})
        c = next(c for c in pooled.candidates if c.effect == label)
        found = bool(pooled.recommended) and pooled.recommended[0].effect == label
        alone += len(c.alone)
        hit += found
        anything += bool(pooled.recommended)
        quiet += not c.alone
        quiet_hit += found and not c.alone
        differs += c.verdict == "differs between flights"
    n = args.vehicles
    print(
        f"temperature_bias {args.coefficient:g} nT/C, {args.flights} flights of {args.minutes:g} min at "
        f"{args.rate:g} Hz: significant alone in {alone} of {n * args.flights} flights; recommended for the "
        f"vehicle in {hit} of {n} (any effect in {anything}); in {quiet_hit} of the {quiet} vehicles where no "
        f"flight reached significance alone; its coefficient found to differ between flights in {differs}"
    )


if __name__ == "__main__":
    main()

"""The diagnosis on seeded simulated logs: false alarms with no effect hidden, and each built-in effect
hidden, with white and with coloured noise (Gauss-Markov 2 s, logged yaw wandering by 0.2 deg).

    python scripts/diagnosis_study.py [--seeds 20] [--minutes 20] [--rate 50]

Prints, per noise: the share of null logs with any candidate significant (against the binomial bound of
alpha) and, per hidden effect, how often it is ranked first and how often taken, and the held-out residual
after it against that of the true model.
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy import stats

from magkf.conventions import MAG
from magkf.diagnostics.diagnose import diagnose
from magkf.effects import BUILTIN
from magkf.io.drivelog import DriveLog
from magkf.sim import DriveConfig, simulate_drive

#: Hidden effects of realistic size (each tens to hundreds of nT on these logs).
TRUTH = {
    "temperature_bias": [8.0, -5.0, 6.0],
    "temperature_scale": [3e-4, -2e-4, 2e-4],
    "current_field": [12.0, -8.0, 5.0],
    "time_lag": [0.12],
    "field_anomaly": [150.0, -80.0, 120.0],
    "bias_drift": [2.0],
    "eddy_current": list(np.diag([1e-2, -8e-3, 8e-3]).ravel()),
}
NOISES = {"white": {}, "coloured": {"noise_correlation_s": 2.0, "attitude_wander_deg": (0.0, 0.0, 0.2)}}


def log_of(seed, minutes, rate, noise, hidden=None):
    effects = [(BUILTIN[hidden](), TRUTH[hidden])] if hidden else []
    config = DriveConfig(duration_s=60.0 * minutes, rate_hz=rate, noise_nt=30.0, seed=seed, **NOISES[noise])
    return simulate_drive(config, effects=effects)


def true_model_residual(sim) -> float:
    """Held-out residual (nT) of the model on the log with the hidden effect's contribution taken out: what
    the true model leaves, diagnosed the same way (a random walk has no constant truth to fit instead)."""
    table = sim.table.copy()
    table[list(MAG)] -= sim.contributions[0]
    d, _ = diagnose(DriveLog(table), candidates=[])
    return d.residual_rms_held_out_nt


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=20)
    p.add_argument("--hidden-seeds", type=int, default=10)
    p.add_argument("--minutes", type=float, default=20.0)
    p.add_argument("--rate", type=float, default=50.0)
    p.add_argument("--alpha", type=float, default=0.01)
    p.add_argument("--noise", choices=sorted(NOISES), action="append", help="default: each")
    p.add_argument("--hidden", choices=sorted(TRUTH), action="append", help="default: each")
    p.add_argument("--no-null", action="store_true", help="leave out the null logs")
    args = p.parse_args(argv)
    bound = int(stats.binom.ppf(0.99, args.seeds, args.alpha))
    for noise in args.noise or NOISES:
        alarms = 0
        for seed in range(0 if args.no_null else args.seeds):
            d, _ = diagnose(DriveLog(log_of(900 + seed, args.minutes, args.rate, noise).table), alpha=args.alpha)
            alarms += bool(d.recommended)
        print(
            f"{noise}: null logs with any candidate significant: {alarms} of {args.seeds} (99 % binomial bound {bound})"
        )
        for hidden in args.hidden or TRUTH:
            first, ranked, ratios = 0, 0, []
            for seed in range(args.hidden_seeds):
                sim = log_of(1000 + seed, args.minutes, args.rate, noise, hidden)
                d, _ = diagnose(DriveLog(sim.table), alpha=args.alpha)
                label = BUILTIN[hidden]().label
                top = d.recommended[0] if d.recommended else None
                first += top is not None and top.effect == label
                ranked += d.candidates[0].effect == label
                row = next(c for c in d.candidates if c.effect == label)
                ratios.append(row.residual_rms_after_nt / true_model_residual(sim))
            within = sum(r <= 1.1 for r in ratios)
            ratio = (
                f"{np.median(ratios):.3f} (max {np.max(ratios):.3f}; within 1.1 on {within}/{len(ratios)})"
                if ratios
                else "n/a"
            )
            print(
                f"  {hidden:18s} ranked first {ranked}/{args.hidden_seeds}, and taken {first}; after/true model {ratio}"
            )


if __name__ == "__main__":
    main()

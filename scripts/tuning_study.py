"""Filter-tuning study: sweep process noise and gate thresholds over simulated logs.

The simulated logs (3-D motion, 10 minutes at 20 Hz, 30 nT noise, disturbances, bad DOP) carry an
offset that drifts as a random walk of ``DRIFT_NT`` nT per sqrt(s), so the process noise matters. For
every setting and seed the study records the final errors, the NEES of the final 12 parameters (its
expectation is 12 when the filter is consistent), the RMS error of ``b`` over the log, and the share of
epochs gated. It writes ``tuning_study.csv`` (one row per setting, means over seeds) and
``tuning_study.png``.

    python scripts/tuning_study.py [--seeds 4] [--out out/]
"""

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from magkf.config import FilterConfig
from magkf.effects import BiasDrift
from magkf.io.drivelog import DriveLog
from magkf.online.run import calibrate_log
from magkf.sim import DriveConfig, simulate_drive

DRIFT_NT = 0.5  # nT per sqrt(s)


SETTINGS = (
    [{"b_walk": w} for w in (0.0, 0.05, 0.2, 0.5, 2.0)]
    + [{"b_walk": 0.5, "innovation_prob": p} for p in (0.99, 0.9999)]
    + [{"b_walk": 0.5, "gate_nt": g} for g in (300.0, 3000.0)]
)


def run(seeds: int) -> pd.DataFrame:
    rows = []
    base = FilterConfig(sensor_noise_nt=30.0, attitude_deg=0.0, reference_nt=0.0, r_walk=0.0)
    for seed in range(seeds):
        sim = simulate_drive(
            DriveConfig(duration_s=600, rate_hz=20, motion="3d", noise_nt=30.0, seed=500 + seed),
            effects=[(BiasDrift(), [DRIFT_NT])],
        )
        truth_b = sim.b + sim.contributions[0]  # (N, 3)
        truth_final = np.concatenate([sim.R.ravel(), truth_b[-1]])
        log = DriveLog(sim.table)
        for setting in SETTINGS:
            result = calibrate_log(log, base.replace(**setting))
            err = result.x[:12] - truth_final
            nees = float(err @ np.linalg.solve(result.P[:12, :12], err))
            b_path = result.states[["b_x", "b_y", "b_z"]].to_numpy()
            status = result.states["status"]
            rows.append(
                {
                    **{"b_walk": 0.01, "innovation_prob": 0.999, "gate_nt": 1000.0},
                    **setting,
                    "seed": seed,
                    "final_b_error_nt": float(np.linalg.norm(err[9:])),
                    "final_R_error": float(np.abs(err[:9]).max()),
                    "nees": nees,
                    "b_rms_error_nt": float(np.sqrt(np.mean(np.sum((b_path - truth_b) ** 2, axis=1)))),
                    "gated_share": float(status.str.startswith("gated").mean()),
                }
            )
    df = pd.DataFrame(rows)
    keys = ["b_walk", "innovation_prob", "gate_nt"]
    return df.groupby(keys, sort=False).mean(numeric_only=True).drop(columns="seed").reset_index()


def plot(df: pd.DataFrame, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    walk = df[(df.innovation_prob == 0.999) & (df.gate_nt == 1000.0)].sort_values("b_walk")
    x = np.maximum(walk.b_walk, 0.01)
    fig, axes = plt.subplots(1, 3, figsize=(13, 4), constrained_layout=True)
    axes[0].plot(x, walk.b_rms_error_nt, "o-")
    axes[0].set(
        xscale="log",
        xlabel="b random walk setting, nT/sqrt(s) (0 drawn at 0.01)",
        ylabel="RMS error of b over the log, nT",
        title="tracking the drifting offset",
    )
    axes[0].axvline(DRIFT_NT, color="k", ls=":", label=f"true drift {DRIFT_NT}")
    axes[0].legend()
    axes[1].plot(x, walk.nees, "o-")
    axes[1].axhline(12, color="k", ls=":", label="expected 12")
    axes[1].set(
        xscale="log",
        yscale="log",
        xlabel="b random walk setting, nT/sqrt(s)",
        ylabel="mean NEES (12 states)",
        title="consistency",
    )
    axes[1].legend()
    gates = df.copy()
    labels = [f"p={r.innovation_prob:g}, {r.gate_nt:g} nT" for r in gates.itertuples()]
    sel = gates.b_walk == 0.5
    axes[2].bar(np.arange(sel.sum()), 100 * gates.gated_share[sel])
    axes[2].set_xticks(
        np.arange(sel.sum()), [lab for lab, s in zip(labels, sel) if s], fontsize=7, rotation=25, ha="right"
    )
    axes[2].set(ylabel="epochs gated, %", title="gates (b walk 0.5)")
    fig.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--out", default="out")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    df = run(args.seeds)
    df.to_csv(out / "tuning_study.csv", index=False)
    plot(df, out / "tuning_study.png")
    pd.set_option("display.width", 160)
    print(df.to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    print(f"\nwrote {out / 'tuning_study.csv'} and {out / 'tuning_study.png'}")


if __name__ == "__main__":
    main()

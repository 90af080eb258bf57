"""Regenerate the simulated example data in data/ (seeded, so the files come out the same)."""

from pathlib import Path

import numpy as np

from magkf.sim import PAPER_EXAMPLE, DriveConfig, simulate_drive, simulate_turntable

DATA = Path(__file__).resolve().parent.parent / "data"


def main() -> None:
    table = simulate_turntable(
        PAPER_EXAMPLE,
        50_000.0,
        43.0,
        step_deg=5.0,
        noise_nt=5.0,
        rng=np.random.default_rng(7),
        heading_offsets_deg=(12.0, -30.0),
    )
    table.to_csv(DATA / "turntable_example.csv", index=False, float_format="%.10g")
    drive = simulate_drive(DriveConfig(duration_s=600.0, rate_hz=20.0, motion="3d", noise_nt=30.0, seed=11))
    drive.write(DATA / "example_drive.csv", DATA / "example_drive_truth.json")
    print(f"wrote {DATA}")


if __name__ == "__main__":
    main()

"""Regenerate the simulated example data in data/ (seeded, so the files come out the same).

python scripts/make_example_data.py [--data DIR]
"""

import argparse
from pathlib import Path

import numpy as np

from magkf.sim import PAPER_EXAMPLE, DriveConfig, simulate_drive, simulate_turntable

DATA = Path(__file__).resolve().parent.parent / "data"


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, default=DATA, help=f"folder to write (default {DATA})")
    folder = p.parse_args(argv).data
    table = simulate_turntable(
        PAPER_EXAMPLE,
        50_000.0,
        43.0,
        step_deg=5.0,
        noise_nt=5.0,
        rng=np.random.default_rng(7),
        heading_offsets_deg=(12.0, -30.0),
    )
    table.to_csv(folder / "turntable_example.csv", index=False, float_format="%.10g")
    drive = simulate_drive(DriveConfig(duration_s=600.0, rate_hz=20.0, motion="3d", noise_nt=30.0, seed=11))
    drive.write(folder / "example_drive.csv", folder / "example_drive_truth.json")
    print(f"wrote {folder}")


if __name__ == "__main__":
    main()

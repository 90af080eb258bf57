"""The fleet views without the filter: the disagreement test on tables of estimates drawn with known standard
deviations (its false alarms, its power against a jumped offset, the scatter it reports), the vehicle rules
and the search for logs."""

import numpy as np
import pandas as pd
import pytest
from scipy.stats import binom

from magkf.errors import InputError
from magkf.fleet import COMPARED, disagreements, find_logs, vehicle_of

ALPHA = 0.05
VEHICLES = 400


def table(flights: int, scatter: float = 0.0, jump: float = 0.0, seed: int = 0) -> pd.DataFrame:
    """``VEHICLES`` vehicles of ``flights`` logs: estimates of 12 parameters (truth 0) with standard deviations
    from 0.5 to 2, plus a flight-to-flight scatter of standard deviation ``scatter``; the first flight's b_x
    moved by ``jump`` of its standard deviations."""
    rng = np.random.default_rng(seed)
    std = rng.uniform(0.5, 2.0, (VEHICLES * flights, 12))
    x = rng.normal(0.0, std) + rng.normal(0.0, scatter, std.shape)
    first = np.arange(VEHICLES * flights) % flights == 0
    x[first, COMPARED.index("b_x")] += jump * std[first, COMPARED.index("b_x")]
    frame = pd.DataFrame(x, columns=list(COMPARED))
    frame[[f"std_{n}" for n in COMPARED]] = std
    frame["vehicle"] = [f"v{i // flights:03d}" for i in range(len(frame))]
    frame["log"] = [f"v{i // flights:03d}/flight{i % flights}" for i in range(len(frame))]
    frame["error"] = ""
    frame["first"] = first
    return frame


def upper(p: float, n: int) -> float:
    """The share of ``n`` trials of probability ``p`` exceeded with probability 0.001."""
    return binom.isf(0.001, n, p) / n


@pytest.mark.slow
@pytest.mark.parametrize("flights", [3, 5, 10])
def test_false_alarms_when_the_standard_deviations_are_right(flights):
    out = disagreements(table(flights, seed=flights), ALPHA)
    share = out.groupby("vehicle")["disagrees"].any().mean()
    assert share <= upper(ALPHA, VEHICLES)  # Bonferroni: at most alpha per vehicle
    # the scatter of consistent logs is about 1: sqrt(Q / (m - 1)), the largest of 12 chi-square variates
    assert 0.8 < out.groupby("vehicle")["vehicle_scatter"].first().median() < 2.0


@pytest.mark.slow
def test_a_jumped_offset_is_found_and_its_vehicle_s_other_logs_are_not_flagged():
    out = disagreements(table(5, jump=10.0, seed=1), 0.01)
    first = out[out["first"]]
    assert first["disagrees"].mean() > 0.95
    assert first.loc[first["disagrees"], "disagreement"].str.startswith("b_x +").all()
    assert out.loc[~out["first"], "disagrees"].mean() <= upper(0.01 / 5, len(out) - VEHICLES)


@pytest.mark.slow
def test_a_vehicle_whose_calibration_changes_between_flights_shows_it_in_its_scatter():
    out = disagreements(table(10, scatter=3.0, seed=2), ALPHA)
    assert out.groupby("vehicle")["vehicle_scatter"].first().median() > 2.0
    # a vehicle with two calibrated logs is not compared
    short = table(3, seed=3)
    short.loc[short["first"], "error"] = "x: cannot be read"
    out = disagreements(short, ALPHA)
    assert not out["disagrees"].any() and out["vehicle_scatter"].isna().all()
    assert out.loc[~out["first"], "disagreement"].str.startswith("not compared: 2 calibrated log(s)").all()
    assert (out.loc[out["first"], "disagreement"] == "").all()


def test_vehicle_rules_and_finding_logs(tmp_path):
    (tmp_path / "V7" / "deep").mkdir(parents=True)
    for name in ("V7/a.csv", "V7/deep/b.ulg", "V7/notes.md", "V7/LICENSE.txt", "V7_2026-05-01.bin"):
        (tmp_path / name).write_text("x")
    found = find_logs([tmp_path / "V7", str(tmp_path / "*.bin"), tmp_path / "V7" / "a.csv"])
    assert [p.name for p in found] == ["a.csv", "b.ulg", "V7_2026-05-01.bin"]  # each once, sorted by path
    assert [p.name for p in find_logs([tmp_path / "V7" / "LICENSE.txt"])] == ["LICENSE.txt"]  # named: taken
    assert [p.name for p in find_logs([tmp_path], exclude=tmp_path / "V7")] == ["V7_2026-05-01.bin"]
    assert vehicle_of(found[0]) == "V7" and vehicle_of(found[1]) == "deep"
    assert vehicle_of(found[2], "name") == "V7" and vehicle_of(found[0], "name") == "a"
    assert vehicle_of(found[2], "none") == "fleet"
    with pytest.raises(InputError, match="no log file here"):
        find_logs([tmp_path / "nothing*.ulg"])

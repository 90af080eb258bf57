"""Property tests of the real-time step, ``OnlineCalibrator.step``.

Samples are dicts (or pandas rows) with any subset of the canonical keys, values plausible, NaN, infinite,
huge, None, text, booleans or numpy scalars, times increasing or not. Each step returns an ``EpochResult``
whose status is one of ``magkf.status`` with a finite estimate, or raises InputError; never another
exception; and after an InputError the calibrator still processes the next valid sample.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from hypothesis import event, given, settings
from hypothesis import strategies as st

from magkf import EpochResult, OnlineCalibrator
from magkf.calibration import Calibration
from magkf.conventions import ATTITUDE, MAG, REF, euler_to_dcm, ned_to_body
from magkf.effects import make_effect
from magkf.errors import InputError
from magkf.io.drivelog import RANGES, TIME_RANGE_S
from magkf.reference import VALID_RANGE_S, igrf_ned
from magkf.status import STATUS_NAMES

#: Eighty generated runs of up to eight samples through the calibrator: seconds.
pytestmark = pytest.mark.slow

PROPERTY = settings(max_examples=60, deadline=None, derandomize=True, database=None)

CALIBRATION = Calibration(
    R=[[1.02, 0.01, -0.004], [0.006, 0.985, 0.012], [-0.003, 0.008, 1.01]],
    b=[120.0, -85.0, 240.0],
    method="test",
    covariance=np.diag([1e-4] * 9 + [1e4] * 3),
)
#: Columns always given to the calibrators that estimate an effect of them (none: a sample without its
#: effect's channel is "missing_column", as in post-processing).
EFFECT_COLUMNS = ()
KEYS = ("time", *MAG, *ATTITUDE, "lat", "lon", "alt", *REF, "dop", "pdop", "hdop", "temp_c", "speed")
T0 = 1_780_308_000.0


#: The IGRF field near Munich at T0 (NED, nT); the step's reference differs from it by a few nT over a day.
FIELD = igrf_ned(np.array([T0]), np.array([48.1]), np.array([11.6]), 520.0)[0]


def plausible(t: float, k: int = 0) -> dict:
    """A complete sample of a car heading ``10 k`` degrees near Munich, its magnetometer reading the IGRF field
    through the calibration (so that the step uses it)."""
    yaw = (10.0 * k) % 360.0
    mag = CALIBRATION.distort(ned_to_body(euler_to_dcm(yaw, -1.0, 0.5), FIELD))
    return {
        "time": t,
        **dict(zip(MAG, map(float, mag))),
        "roll": 0.5,
        "pitch": -1.0,
        "yaw": yaw,
        "lat": 48.1,
        "lon": 11.6,
        "alt": 520.0,
        "dop": 1.2,
        "temp_c": 21.0,
    }


VALUES = st.one_of(
    st.floats(-1e5, 1e5),
    st.floats(),
    st.sampled_from([math.nan, math.inf, -math.inf, 1e308, -1e308, 5e-324, 0.0, None, "", "1.5", "nan", "x", True]),
    st.text(max_size=4),
    st.integers(-(10**30), 10**30),
    st.sampled_from([10**400, -(10**400)]),
    st.builds(np.float32, st.floats(width=32)),
    st.sampled_from([np.int64(7), np.array([20_000.0]), np.array([1.0, 2.0]), 1 + 2j, [1.0], {"a": 1}]),
)


@st.composite
def samples(draw, last: float, keep: tuple = ()):
    """A sample after ``last`` (the time of the last sample taken): a plausible one with keys dropped and
    values replaced, its time later, equal, earlier, missing or strange; sometimes as a pandas row, sometimes
    not a mapping at all. The ``keep`` keys keep their plausible values."""
    step = draw(st.sampled_from(["later", "later", "later", "same", "earlier", "missing", "strange"]))
    t = {
        "later": last + draw(st.floats(1e-3, 10.0)),
        "same": last,
        "earlier": last - draw(st.floats(1e-3, 1e6)),
        "missing": None,
        "strange": draw(VALUES | st.sampled_from([0.0, -1.0, 1e300, T0 * 10, "1780308000", np.float64(T0)])),
    }[step]
    sample = plausible(t, draw(st.integers(0, 35)))
    others = [k for k in KEYS[1:] if k not in keep]
    for key in draw(st.lists(st.sampled_from(others), max_size=4)):
        sample.pop(key, None)
    for key in draw(st.lists(st.sampled_from(others), max_size=3)):
        sample[key] = draw(VALUES)
    if step == "missing":
        del sample["time"]
    shape = draw(st.sampled_from(["dict", "dict", "dict", "row", "other"]))
    if shape == "row":  # a pandas row named by its time, as DataFrame.iterrows gives
        name = sample.pop("time", None) if draw(st.booleans()) else None
        return pd.Series(sample, name=name, dtype=object)
    if shape == "other":
        return draw(st.sampled_from([list(sample.values()), np.array([1.0, 2.0]), None, 3.0, "sample"]))
    return sample


def number(value) -> float:
    """A value as a float, NaN where it is none."""
    try:
        return float(value)
    except (TypeError, ValueError, OverflowError):
        return math.nan


def time_of(sample) -> float:
    """The sample's time as the step's documentation gives it: its ``time`` entry, else a pandas row's name."""
    t = number(sample.get("time")) if hasattr(sample, "get") else math.nan
    if not math.isfinite(t) and isinstance(sample, pd.Series):
        t = number(sample.name)
    return t


def faults(sample, last: float | None) -> tuple[bool, set]:
    """Whether the step must refuse ``sample`` (not a mapping, no time, time not after ``last``), and the
    columns for which it may: a number beyond the range a log may hold, or a time IGRF does not cover where
    the reference field is to come from IGRF."""
    if not hasattr(sample, "keys"):
        return True, set()
    t = time_of(sample)
    if not math.isfinite(t) or (last is not None and not t > last):
        return True, set()
    value = {c: number(sample.get(c)) for c in (*RANGES, *REF)}
    beyond = {c for c, (lo, hi, _) in RANGES.items() if math.isfinite(value[c]) and not lo <= value[c] <= hi}
    if not TIME_RANGE_S[0] <= t <= TIME_RANGE_S[1]:
        beyond.add("time")
    igrf = not all(math.isfinite(value[c]) for c in REF) and all(math.isfinite(value[c]) for c in ("lat", "lon"))
    if igrf and not VALID_RANGE_S[0] <= t <= VALID_RANGE_S[1]:
        beyond.add(None)  # IGRF's own error names no column
    return False, beyond


def check_result(result, t: float, sample) -> None:
    assert isinstance(result, EpochResult)
    assert result.status in STATUS_NAMES and result.time == t
    assert result.R.shape == (3, 3) and result.b.shape == (3,)
    assert np.all(np.isfinite(result.R)) and np.all(np.isfinite(result.b)) and np.all(np.isfinite(result.x))
    assert np.all(np.isfinite(result.std)) and np.all(result.std >= 0)
    mag = [number(sample.get(c)) for c in MAG]
    if not all(map(math.isfinite, mag)):
        assert result.status == "missing_mag" and not result.updated
    ref = [number(sample.get(c)) for c in REF]
    position = [number(sample.get(c)) for c in ("lat", "lon")]
    if all(map(math.isfinite, mag)) and not all(map(math.isfinite, ref)) and not all(map(math.isfinite, position)):
        assert result.status == "missing_position" and not result.updated
    if result.updated:
        assert result.status in ("used", "missing_attitude")


@settings(PROPERTY, max_examples=80)
@given(st.data(), st.booleans())
def test_each_step_gives_a_result_or_an_input_error_and_the_calibrator_goes_on(data, with_effect):
    effects = (make_effect("temperature_bias:temp_c"),) if with_effect else ()
    calibrator = OnlineCalibrator(CALIBRATION, effects=effects)
    last = None
    for k in range(data.draw(st.integers(1, 8))):
        sample = data.draw(samples(T0 if last is None else last, keep=EFFECT_COLUMNS if with_effect else ()))
        must_fail, may_fail = faults(sample, last)
        try:
            result = calibrator.step(sample)
        except InputError as exc:
            assert "\n" not in str(exc)
            event("refused")
            assert must_fail or exc.column in may_fail, f"a valid sample refused: {exc} ({may_fail})"
            # the next valid sample is processed (with its reference field: IGRF ends in 2030, the contract in 2100)
            recovery = {**plausible(max(last or T0, T0) + 1e-3, k), **dict(zip(REF, map(float, FIELD)))}
            check_result(calibrator.step(recovery), recovery["time"], recovery)
            last = recovery["time"]
            continue
        assert not must_fail, f"a sample taken that has no time after {last!r}"
        check_result(result, time_of(sample), sample)
        event(result.status)
        last = time_of(sample)
    final = calibrator.calibration
    assert np.all(np.isfinite(final.R)) and np.all(np.isfinite(final.b))

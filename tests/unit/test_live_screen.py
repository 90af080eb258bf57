"""What the operator of a live calibration sees (magkf.live.screen): the screen's lines, the screen redrawn in place
on a terminal or written as blocks elsewhere, at most once per interval, and the JSON lines."""

import io
import json
import math
import re

import numpy as np
import pytest

from magkf.live.screen import CLEAR_ALL, CLEAR_BELOW, CLEAR_LINE, HOME, JsonLines, Screen, json_line, render
from magkf.live.status import LiveStatus

NAN = float("nan")


def _words(lines) -> str:
    """The screen's lines as one string, runs of spaces (alignment, a line wrapped) as one."""
    return " ".join(" ".join(lines).split())


def _full() -> LiveStatus:
    """A status with every field filled, as a session some minutes in shows it."""
    return LiveStatus(
        elapsed_s=754.2,
        utc=1795000000.0,
        counts={"used": 12345, "gated_dop": 120, "gated_magnitude": 100, "gated_innovation": 14, "late": 2},
        link={
            "packets": 45678,
            "lost": 550,
            "lost_share": 0.0119,
            "reordered": 3,
            "reboots": 1,
            "link_drops": 1,
            "rates_hz": {"RAW_IMU": 49.8, "ATTITUDE": 50.0, "GPS_RAW_INT": 5.0, "SYSTEM_TIME": 1.0, "STATUSTEXT": 0.1},
            "asked_hz": {"RAW_IMU": 50.0, "ATTITUDE": 50.0, "GPS_RAW_INT": 5.0, "SYSTEM_TIME": 1.0, "VFR_HUD": 4.0},
        },
        residual_rms_nt=45.3,
        noise={"sensor_nt": 12.1, "attitude_deg": 0.12, "heading_deg": 0.5},
        b_nt=[123.4, -2345.6, 456.7],
        b_std_nt=[5.6, 6.1, 12.3],
        r_diag=[1.0123, 0.9987, 1.0456],
        r_diag_std=[0.0012, 0.0011, 0.0034],
        undetermined=["turn through 90 more degrees of heading", "the scale of z"],
        verdict="the model fits: the mean NIS per degree of freedom 1.02 lies in its 95 % band",
        diagnosis={
            "window_s": 120.0,
            "epochs": 12000,
            "candidates": [
                {"effect": "time_lag", "p_value": 0.0012, "significant": True},
                {"effect": "current_field", "p_value": 0.31, "significant": False},
                {"effect": "bias_drift", "p_value": NAN, "significant": False},
            ],
            "text": "time_lag is missing.\nAdd --effect time_lag.",
        },
        converged=False,
        events=["link dropped", "link back after 2.1 s", "vehicle rebooted (boot time went back)", "resumed"],
        step_ms={"median": 0.16, "p99": 0.45, "samples": 10.0},
    )


def _empty() -> LiveStatus:
    """A status before anything is known: NaN everywhere a number is, including inside the dicts."""
    return LiveStatus(
        link={"packets": 0, "lost": 0, "lost_share": NAN, "rates_hz": {"RAW_IMU": NAN}, "asked_hz": {"RAW_IMU": NAN}},
        noise={"sensor_nt": NAN, "attitude_deg": NAN, "heading_deg": NAN},
        diagnosis={"window_s": NAN, "candidates": [{"effect": "time_lag", "p_value": NAN}], "text": ""},
        step_ms={"median": NAN, "p99": NAN},
    )


@pytest.mark.parametrize("width", [100, 72, 40, 20])
def test_full_status_lines_within_width(width):
    lines = render(_full(), width)
    assert 12 <= len(lines) <= 24
    assert all(len(line) <= width for line in lines)


def test_full_status_shows_each_figure_with_its_unit():
    text = _words(render(_full(), 100))
    for shown in (
        "754.2 s (0:12:34)",  # elapsed
        "2026-11-18 11:06:40 UTC",  # the last sample's time
        "step 0.16 ms, p99 0.45 ms, 10 samples",  # the filter step
        "12 345 used of 12 579 (98.1 %)",  # 12345 + 120 + 100 + 14 epochs; the 2 late samples are not epochs
        "120 DOP above the limit",
        "100 field magnitude gate",
        "14 innovation gate",
        "2 not after the previous sample",
        "45 678 packets, 1.2 % lost (550)",
        "reboots 1, link drops 1",
        "RAW_IMU 49.8 of 50 Hz",
        "VFR_HUD - of 4 Hz",  # asked, never received
        "STATUSTEXT 0.1 Hz (not asked)",
        "RMS 45.3 nT",
        "sensor 12.1 nT, tilt 0.120 deg, heading 0.500 deg",
        "123.4 +/- 5.6",
        "1.01230 +/- 0.00120",
        "b (nT)",
        "turn through 90 more degrees of heading; the scale of z",
        "the model fits",
        "over the last 120 s (12 000 epochs): time_lag p 0.0012 (significant)",
        "current_field p 0.31",
        "bias_drift not testable",
        "time_lag is missing. Add --effect time_lag.",
        "largest standard deviation 12.3 nT in b, 0.00340 in diag R",
        "resumed",
    ):
        assert shown in text, shown
    assert "link dropped" not in text  # only the last three events


def test_empty_status_shows_dashes_not_nan():
    for width in (100, 40):
        lines = render(_empty(), width)
        assert all(len(line) <= width for line in lines)
        assert not re.search(r"\bnan\b", "\n".join(lines), re.IGNORECASE)
    text = _words(render(_empty(), 100))
    for shown in ("at -;", "RMS - nT", "sensor - nT, tilt - deg, heading - deg", "- +/- -", "- % lost"):
        assert shown in text, shown
    assert "undetermined -" in text  # not started: nothing known, rather than "every direction determined"
    assert "time_lag not testable" in text
    assert "converged no target set: largest standard deviation - nT in b" in text


def test_default_status_renders():
    lines = render(LiveStatus())
    assert any("waiting for the first samples" in line for line in lines)
    assert any("0 used of 0; none refused" in line for line in lines)


def test_converged_said_in_words():
    status = _full()
    status.converged = True
    assert any("yes: every standard deviation below the target" in line for line in render(status))


class _Clock:
    """A clock the test moves by hand, s."""

    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


class _Terminal(io.StringIO):
    """A text stream that says it is a terminal (without a size: the screen falls back to its default width)."""

    def isatty(self):
        return True


def test_screen_on_terminal_redraws_in_place_at_most_once_per_interval():
    clock, stream = _Clock(), _Terminal()
    screen = Screen(stream, interval_s=1.0, clock=clock)
    written = []
    for t in np.arange(0.0, 3.05, 0.1):  # 31 calls over 3 s: frames at 0, 1, 2 and 3 s
        clock.now = float(t)
        written.append(screen.show(_full()))
    assert sum(written) == 4
    out = stream.getvalue()
    assert out.startswith(CLEAR_ALL + HOME)  # the first frame clears the screen once
    assert out.count(CLEAR_ALL) == 1
    assert out.count(HOME) == 4
    assert out.count(CLEAR_BELOW) == 4
    frame = out.split(HOME)[-1]
    lines = frame.removesuffix(CLEAR_BELOW).split("\n")[:-1]
    assert all(line.endswith(CLEAR_LINE) for line in lines)  # each line clears what a longer one left
    assert [line.removesuffix(CLEAR_LINE) for line in lines] == render(_full(), 100)


def test_screen_shorter_frame_clears_the_rest():
    clock, stream = _Clock(), _Terminal()
    screen = Screen(stream, interval_s=1.0, clock=clock)
    screen.show(_full())
    clock.now = 1.0
    screen.show(LiveStatus())
    last = stream.getvalue().split(HOME)[-1]
    assert last.endswith(CLEAR_BELOW)
    assert last.count("\n") == len(render(LiveStatus(), 100)) < len(render(_full(), 100))


def test_screen_close_writes_the_final_frame_once():
    clock, stream = _Clock(), _Terminal()
    screen = Screen(stream, interval_s=1.0, clock=clock)
    screen.show(_full())
    clock.now = 0.2  # within the interval: close writes anyway
    screen.close(_full())
    screen.close(_full())
    clock.now = 5.0
    assert not screen.show(_full())
    assert stream.getvalue().count(HOME) == 2


def test_screen_off_terminal_writes_plain_blocks():
    clock, stream = _Clock(), io.StringIO()
    screen = Screen(stream, interval_s=1.0, clock=clock, width=72)
    for t in (0.0, 0.5, 0.99, 1.0, 1.5):
        clock.now = t
        screen.show(_full())
    screen.close(LiveStatus())
    out = stream.getvalue()
    assert "\x1b" not in out
    blocks = out.split("\n\n")
    assert len(blocks) == 3  # at 0 and 1 s, and the final one
    assert blocks[0].split("\n") == render(_full(), 72)
    assert blocks[2].rstrip("\n").split("\n") == render(LiveStatus(), 72)


def test_json_line_is_one_compact_object_with_nan_as_null():
    line = json_line(_empty())
    assert "\n" not in line and "NaN" not in line
    data = json.loads(line)
    assert data["utc"] is None and data["b_nt"] == [None, None, None]
    assert data["noise"]["sensor_nt"] is None
    assert data["diagnosis"]["candidates"][0]["p_value"] is None


def test_json_lines_round_trip_at_most_once_per_interval():
    clock, stream = _Clock(), io.StringIO()
    writer = JsonLines(stream, interval_s=1.0, clock=clock)
    status = _full()
    status.b_nt = list(np.array([1.5, np.nan, -2.0]))  # numpy numbers as a session may give them
    status.counts = {"used": np.int64(7)}
    status.r_diag = (np.float64(1.0), np.inf, 1.0)  # a tuple, an infinity
    for t in (0.0, 0.4, 1.0, 1.9, 2.0):
        clock.now = t
        writer.show(status)
    writer.close(status)
    writer.close(status)
    rows = [json.loads(line) for line in stream.getvalue().splitlines()]
    assert len(rows) == 4  # at 0, 1 and 2 s, and the final one
    assert rows[0]["b_nt"] == [1.5, None, -2.0]
    assert rows[0]["counts"] == {"used": 7}
    assert rows[0]["r_diag"] == [1.0, None, 1.0]
    expected = _full().as_dict()
    assert rows[-1]["link"] == expected["link"]
    assert rows[-1]["diagnosis"]["candidates"][2]["p_value"] is None
    assert rows[-1]["diagnosis"]["candidates"][0] == expected["diagnosis"]["candidates"][0]
    assert rows[-1]["events"] == expected["events"] and rows[-1]["converged"] is False
    assert not any(isinstance(v, float) and math.isnan(v) for v in rows[-1]["b_std_nt"])


def test_a_live_sessions_status_renders_and_round_trips():
    """The status a real session gives (held for the start, then filtering) fits the width, has no NaN shown, and
    its JSON line reads back with the session's figures."""
    from magkf.config import FilterConfig
    from magkf.live.session import LiveSession
    from magkf.sim import DriveConfig, simulate_drive

    sim = simulate_drive(DriveConfig(duration_s=75, rate_hz=10, noise_nt=30.0, seed=5, disturbances=0))
    session = LiveSession(FilterConfig(bootstrap_s=60.0), None, diagnose_every_s=0)
    rows = sim.table.reset_index().to_dict("records")
    for row in rows[:150]:
        session.add(row)
    held = session.status({}, ["connected"])
    for row in rows[150:]:
        session.add(row)
    running = session.status({}, [])
    assert session.calibrator is not None  # started after a minute
    for status in (held, running):
        lines = render(status, 80)
        assert all(len(line) <= 80 for line in lines)
        assert not re.search(r"\bnan\b", "\n".join(lines), re.IGNORECASE)
    assert "150 held for the start" in _words(render(held))
    assert f"{running.b_nt[0]:.1f} +/- {running.b_std_nt[0]:.1f}" in _words(render(running))
    data = json.loads(json_line(running))
    assert data["b_nt"] == pytest.approx(running.b_nt) and data["counts"] == running.counts

"""Logs without GNSS placed at ``--site`` and ``--date`` (``magkf.io.site``)."""

import numpy as np
import pandas as pd
import pytest

import magkf
from magkf.errors import InputError
from magkf.io.drivelog import from_table, read_drive_log, write_drive_log
from magkf.io.readers import read_log
from magkf.io.site import Site, parse_date, parse_site, place_at_site
from magkf.reference import igrf_ned
from magkf.sim import DriveConfig, simulate_drive

START = parse_date("2025-03-14T09:30")
BOOT_S = 120.0


@pytest.fixture(scope="module")
def drive():
    sim = simulate_drive(DriveConfig(duration_s=300.0, rate_hz=10.0, motion="3d", seed=5, dop_bad_stretches=0))
    return sim.table.reset_index()


def boot_table(table: pd.DataFrame) -> pd.DataFrame:
    """The drive as a bench log: time since boot (the first epoch at ``BOOT_S``), no position."""
    return table.drop(columns=["lat", "lon", "alt"]).assign(time=table["time"] - table["time"].iloc[0] + BOOT_S)


def test_parse_site_and_date():
    assert parse_site("52.1,-1.3") == Site(lat=52.1, lon=-1.3, alt=0.0)
    assert parse_site("52.1, -1.3, 95", "2025-03-14") == Site(52.1, -1.3, 95.0, parse_date("2025-03-14"))
    assert parse_site(None, "2025-03-14T09:30") == Site(start=START)
    assert parse_site(None) is None
    assert parse_date("2025-03-14T11:30+02:00") == START


@pytest.mark.parametrize(
    ("site", "date", "message"),
    [
        ("52.1", None, "--site '52.1': give LAT,LON[,ALT] in degrees and metres (e.g. 52.1,-1.3,95)"),
        ("north,west", None, "--site 'north,west': give LAT,LON[,ALT] in degrees and metres (e.g. 52.1,-1.3,95)"),
        ("95,10", None, "--site '95,10': latitude in [-90, 90], longitude in [-180, 360], altitude in m"),
        ("52,10", "14/03/2025", "--date '14/03/2025': give YYYY-MM-DD or YYYY-MM-DDTHH:MM (UTC)"),
        ("52,10", "1985-01-01", "--date '1985-01-01': the year must lie in 1990 to 2099"),
    ],
)
def test_bad_site_or_date_is_one_line(site, date, message):
    with pytest.raises(InputError) as info:
        parse_site(site, date)
    assert str(info.value) == message


def test_boot_log_is_placed_at_the_site_and_date(drive):
    boot = boot_table(drive)
    provenance = {"time_base": "boot", "notes": []}
    placed = place_at_site(boot, provenance, Site(48.1, 11.6, 500.0, START), "bench.bin")
    np.testing.assert_array_equal(placed["time"].to_numpy(), START + boot["time"].to_numpy())
    assert (placed["lat"] == 48.1).all() and (placed["lon"] == 11.6).all() and (placed["alt"] == 500.0).all()
    assert provenance["site"] == {
        "given": True,
        "lat": 48.1,
        "lon": 11.6,
        "alt": 500.0,
        "start_utc": "2025-03-14T09:30:00Z",
    }
    assert provenance["time_base"].startswith("given: --date 2025-03-14T09:30:00Z")
    assert "lat" not in boot


def test_the_field_is_igrf_at_the_site_on_the_date(drive):
    log = from_table(
        boot_table(drive), "bench.csv", provenance={"time_base": "boot"}, site=Site(-33.9, 151.2, 40.0, START)
    )
    expected = igrf_ned(log.time, np.full(len(log), -33.9), np.full(len(log), 151.2), np.full(len(log), 40.0))
    np.testing.assert_allclose(log.reference_ned(), expected, rtol=0, atol=1e-6)
    assert log.site["lat"] == -33.9


@pytest.mark.parametrize(
    ("site", "message"),
    [
        (
            None,
            "bench.bin: the log has no GNSS time (its clock counts from boot), which the reference field needs: give "
            "--date YYYY-MM-DD[THH:MM], the UTC at its boot (the day is enough) and --site LAT,LON[,ALT] (no GNSS "
            "position either)",
        ),
        (
            Site(start=START),
            "bench.bin: the log has no GNSS position (nor a reference field): give --site LAT,LON[,ALT] where it was "
            "recorded",
        ),
        (
            Site(48.1, 11.6),
            "bench.bin: the log has no GNSS time (its clock counts from boot), which the reference field needs: give "
            "--date YYYY-MM-DD[THH:MM], the UTC at its boot (the day is enough)",
        ),
    ],
)
def test_what_is_missing_is_said_in_one_line(drive, site, message):
    with pytest.raises(InputError) as info:
        from_table(boot_table(drive), "bench.bin", provenance={"time_base": "boot"}, site=site)
    assert str(info.value) == message


def test_a_placed_log_calibrates_as_one_logged_at_the_site(drive, tmp_path):
    """Placing is exactly a log whose GNSS stood still at the site, clock at ``START``: the same R, b (1e-9)."""
    site = Site(48.1, 11.6, 500.0, START)
    boot = boot_table(drive)
    write_drive_log(boot, tmp_path / "bench.csv")
    placed = read_log(tmp_path / "bench.csv", site=site)
    still = from_table(boot.assign(time=START + boot["time"], lat=48.1, lon=11.6, alt=500.0), "still")
    a, b = magkf.calibrate_log(placed), magkf.calibrate_log(still)
    np.testing.assert_allclose(a.calibration.R, b.calibration.R, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(a.calibration.b, b.calibration.b, rtol=1e-9, atol=1e-6)
    assert a.calibration.site == placed.site and a.calibration.site["given"] is True
    a.calibration.save(tmp_path / "cal.json")
    assert magkf.Calibration.load(tmp_path / "cal.json").site == placed.site


def test_a_utc_log_keeps_its_time_and_notes_the_date(drive, tmp_path):
    table = drive.drop(columns=["lat", "lon", "alt"])
    write_drive_log(table, tmp_path / "nogps.csv")
    from magkf.errors import Note

    with pytest.warns(Note, match="nogps.csv: --date not used: the log's own time is UTC"):  # said, not only noted
        log = read_drive_log(tmp_path / "nogps.csv", site=Site(48.1, 11.6, 0.0, START))
    np.testing.assert_array_equal(log.time, table["time"].to_numpy())
    assert "--date not used: the log's own time is UTC" in log.provenance["notes"]


def test_a_reader_without_site_support_refuses_the_option(tmp_path, drive):
    from magkf.io.readers import LogReader
    from magkf.plugins import READERS

    class Plain(LogReader):
        name, title, extensions = "plain", "plain table", (".plain",)

        def read(self, path):  # pragma: no cover - refused before reading
            raise AssertionError

    (tmp_path / "a.plain").write_text("x")
    with READERS.restoring():
        READERS.register(Plain)
        with pytest.raises(InputError) as info:
            read_log(tmp_path / "a.plain", site=Site(1.0, 2.0))
    assert (
        str(info.value)
        == f"{tmp_path / 'a.plain'}: --site and --date do not apply to a plain table (its reader does not take them)"
    )


def test_a_time_cell_that_is_no_number_is_named_before_the_clock_is_set(drive):
    """Placing shifts the time column; a cell of text there is refused with its row and text first, not taken
    for an empty cell once shifted."""
    boot = boot_table(drive).astype({"time": object})
    boot.loc[3, "time"] = "12:00:01"
    with pytest.raises(InputError) as info:
        from_table(boot, "bench.csv", provenance={"time_base": "boot"}, site=Site(48.1, 11.6, 0.0, START))
    assert info.value.column == "time" and "12:00:01" in str(info.value)

"""DataFlash logs of every ArduPilot generation: a simulated drive written in the layouts of 3.1 (``TimeMS``, a GPS of
GPS time only, ``MAG``/``MAG2`` without motor offsets, ``ATT`` without ``DesRoll``), 3.2 (``TimeMS``, GPS with
boot ms ``T``), 3.5 (``TimeUS``, ``GMS``/``GWk``, ``MAG2``/``MAG3``) and 4.5 (``MAG`` with instance ``I``) reads back
within the storage precision, with the calibration in ``PARM`` undone; the refusals are one line each; the
decoded fields equal pymavlink's ``DFReader``.

Tolerances from the storage: a corrected field component is truncated to whole mG and centred by the reader,
so it is off by at most 0.5 mG = 50 nT (1 mG where it truncated to 0), which the inverse of the soft-iron matrix
and the scale carry into the raw field (``|M^-1| e / scale`` per axis); angles are stored in 0.01 deg counts
(0.005 deg at most off after rounding), latitude and longitude in 1e-7 deg, heights in cm. In the ``TimeMS``
generations every boot time is a whole ms and the GPS time of week too, each rounded from the drive's time, so
the boot-to-UTC offset (a median of their differences) and with it every epoch is off by at most 1 ms.
"""

import json
from datetime import UTC, datetime

import numpy as np
import pytest

from magkf.errors import InputError
from magkf.io.dataflash import (
    GENERATION_FIRMWARE,
    GENERATIONS,
    DataFlashWriter,
    _Log,
    compass_correct,
    read_dataflash,
    write_dataflash,
)
from magkf.io.readers import read_log
from magkf.io.site import Site
from magkf.sim import DriveConfig, simulate_drive

MAG = ["mag_x", "mag_y", "mag_z"]
#: Generations whose clock counts whole milliseconds (``TimeMS``).
MILLISECOND = {"3.1", "3.2"}
#: One calibration per compass parameter set; only offsets before 3.3 (no COMPASS_DIA/ODI yet), no
#: COMPASS_SCALE before 4.0.
OFFSETS = ({"X": 120.5, "Y": -40.25, "Z": 300.0}, {"X": -75.0, "Y": 210.0, "Z": -30.5}, {"X": 5.0, "Y": 0.0, "Z": 80.0})
SOFT_IRON = (
    {"DIA": (1.1, 0.95, 1.02), "ODI": (0.03, -0.02, 0.01)},
    {"DIA": (0.97, 1.04, 0.99), "ODI": (-0.01, 0.02, 0.0)},
)
SCALE = (1.1, 0.9)


def parameters(generation: str, compasses: int) -> dict:
    """``COMPASS_*`` parameters of ``compasses`` parameter sets, as the firmware of ``generation`` has them."""
    out = {}
    for k in range(compasses):
        suffix = ("", "2", "3")[k]
        out |= {f"COMPASS_OFS{suffix}_{a}": v for a, v in OFFSETS[k].items()}
        if generation in ("3.5", "4.5") and k < len(SOFT_IRON):
            for q in ("DIA", "ODI"):
                out |= {f"COMPASS_{q}{suffix}_{a}": v for a, v in zip("XYZ", SOFT_IRON[k][q])}
        if generation == "4.5" and k < len(SCALE):
            out[f"COMPASS_SCALE{suffix}"] = SCALE[k]
    return out


def calibration(params: dict, k: int) -> tuple:
    """Offsets, diagonals, off-diagonals and scale of parameter set ``k`` as float32 (as ``PARM`` holds them)."""
    suffix = ("", "2", "3")[k]

    def get(name, default):
        return float(np.float32(params.get(name, default)))

    ofs = np.array([get(f"COMPASS_OFS{suffix}_{a}", 0.0) for a in "XYZ"])
    dia = np.array([get(f"COMPASS_DIA{suffix}_{a}", 1.0) for a in "XYZ"])
    odi = np.array([get(f"COMPASS_ODI{suffix}_{a}", 0.0) for a in "XYZ"])
    return ofs, dia, odi, get(f"COMPASS_SCALE{suffix}", 1.0)


def raw_bound_nt(raw_nt: np.ndarray, params: dict, k: int) -> np.ndarray:
    """(N, 3) largest raw error (nT) the int16 truncation allows: 50 nT per corrected component (100 nT where it
    truncated to 0) through ``|M^-1| / scale``; 1e-6 nT of floating-point slack."""
    ofs, dia, odi, scale = calibration(params, k)
    logged = np.trunc(compass_correct(raw_nt / 100.0, ofs, dia, odi, scale))
    mat = np.array([[dia[0], odi[0], odi[1]], [odi[0], dia[1], odi[2]], [odi[1], odi[2], dia[2]]])
    component = np.where(logged == 0, 100.0, 50.0)
    return component @ np.abs(np.linalg.inv(mat)).T / scale + 1e-6


@pytest.fixture(scope="module")
def drive():
    """A 60 s drive at 10 Hz (3-D motion, seeded), with an HDOP."""
    sim = simulate_drive(DriveConfig(duration_s=60.0, rate_hz=10.0, motion="3d", seed=21))
    return sim.table.assign(hdop=sim.table["dop"])


def compasses_of(generation: str) -> int:
    """ArduPlane 3.1 logged two compasses (MAG, MAG2); the others up to three."""
    return 2 if generation == "3.1" else 3


@pytest.mark.parametrize("generation", list(GENERATIONS))
def test_a_drive_reads_back_in_every_generation(tmp_path, drive, generation):
    """Every compass's raw field (its own parameter set undone), time, attitude, position and DOP of the drive."""
    n = compasses_of(generation)
    params = parameters(generation, n)
    path = tmp_path / f"drive-{generation}.bin"
    write_dataflash(drive, path, parameters=params, generation=generation, compasses=n)
    t = drive.index.to_numpy()
    for k in range(n):
        df, prov = read_dataflash(path, mag=k)
        err = df[MAG].to_numpy() - drive[MAG].to_numpy()
        assert np.all(np.abs(err) <= raw_bound_nt(drive[MAG].to_numpy(), params, k)), (generation, k)
        assert prov["magnetometer"]["calibrated"] is False and prov["magnetometer"]["instance"] == k
        assert f"COMPASS_OFS{('', '2', '3')[k]}" in prov["raw_reconstruction"]
    np.testing.assert_allclose(df["time"], t, rtol=0, atol=1e-3 if generation in MILLISECOND else 1e-6)
    assert prov["time_base"].startswith("gnss") and prov["firmware"] == GENERATION_FIRMWARE[generation]
    for column, half_count in (("roll", 0.005), ("pitch", 0.005), ("lat", 5e-8), ("lon", 5e-8), ("alt", 0.005)):
        np.testing.assert_allclose(df[column], drive[column], rtol=0, atol=half_count + 1e-9, err_msg=column)
    yaw_error = (df["yaw"].to_numpy() - drive["yaw"].to_numpy() + 180.0) % 360.0 - 180.0
    assert np.abs(yaw_error).max() <= 0.005 + 1e-9
    np.testing.assert_allclose(df["hdop"], drive["hdop"], rtol=0, atol=0.005 + 1e-9)
    assert (df["fix_type"] == 3).all()
    assert json.loads(json.dumps(prov)) == prov  # JSON-able
    messages = [m["message"] for m in prov["magnetometers"]]
    assert messages == (["MAG"] * n if generation == "4.5" else ["MAG", "MAG2", "MAG3"][:n])


@pytest.mark.parametrize("generation", list(GENERATIONS))
def test_auxiliary_channels_in_every_generation(tmp_path, drive, generation):
    """Temperature (BARO, 0.01 degC), current (BAT, or CURR in centiamperes before 3.3: 0.005 A) and throttle
    (CTUN where the generation has one: ThO float, 3.2's ThrOut in 0..1000: 0.0005)."""
    table = drive.assign(throttle=np.linspace(0.0, 1.0, len(drive)))
    path = tmp_path / f"aux-{generation}.bin"
    write_dataflash(table, path, generation=generation)
    df, prov = read_dataflash(path)
    np.testing.assert_allclose(df["temp_c"], table["temp_c"], rtol=0, atol=0.005 + 1e-9)
    centi = generation in MILLISECOND
    np.testing.assert_allclose(
        df["current_a"], table["current_a"], rtol=0 if centi else 2**-23, atol=0.005 if centi else 0
    )
    if "CTUN" in GENERATIONS[generation]:
        np.testing.assert_allclose(df["throttle"], table["throttle"], rtol=2**-23, atol=0.0005 if centi else 0)
    else:
        assert "throttle" not in df


@pytest.mark.parametrize("generation", list(GENERATIONS))
def test_without_parameters_the_field_is_read_as_logged(tmp_path, drive, generation):
    """No PARM: the calibration cannot be undone; the field is the logged one, and says so."""
    path = tmp_path / f"noparm-{generation}.bin"
    write_dataflash(drive, path, generation=generation)
    df, prov = read_dataflash(path)
    logged, _ = read_dataflash(path, raw=False)
    np.testing.assert_array_equal(df[MAG].to_numpy(), logged[MAG].to_numpy())
    assert prov["magnetometer"]["calibrated"] is True
    assert prov["raw_reconstruction"] == "not done: no PARM messages (field as logged, calibrated)"
    assert "as logged, calibrated" in prov["columns"]["mag_x"]
    assert any("cannot be undone" in note for note in prov["notes"])


@pytest.mark.parametrize("generation", ["3.2", "3.5", "4.5"])
def test_without_logged_offsets_the_parameters_are_undone(tmp_path, drive, generation):
    """A MAG layout without offset and motor fields: the PARM offsets alone are undone."""
    params = parameters(generation, 1)
    path = tmp_path / f"noofs-{generation}.bin"
    write_dataflash(drive, path, parameters=params, generation=generation, mag_offsets=False)
    df, prov = read_dataflash(path)
    assert "OfsX" not in _Log(path).columns("MAG")
    err = df[MAG].to_numpy() - drive[MAG].to_numpy()
    assert np.all(np.abs(err) <= raw_bound_nt(drive[MAG].to_numpy(), params, 0))
    assert prov["magnetometer"]["calibrated"] is False


@pytest.mark.parametrize("generation", list(GENERATIONS))
@pytest.mark.parametrize("gnss_time", [True, False], ids=["time-without-fix", "no-time"])
def test_no_gnss_fix_reads_in_boot_time(tmp_path, drive, generation, gnss_time):
    """GPS that never gets a fix (with or without a GPS time): seconds since boot (10 s at the first row), no
    position columns, a note; read_log places it at the --site and --date given."""
    table = drive.drop(columns=["lat", "lon"])
    path = tmp_path / f"nofix-{generation}.bin"
    write_dataflash(table, path, generation=generation, gnss_time=gnss_time)
    df, prov = read_dataflash(path)
    assert prov["time_base"] == "boot" and not {"lat", "lon", "alt", "fix_type"} & set(df)
    boot = 10.0 + drive.index.to_numpy() - drive.index[0]
    np.testing.assert_allclose(df["time"], boot, rtol=0, atol=5e-4 if generation in MILLISECOND else 1e-6)
    assert json.loads(json.dumps(prov)) == prov
    expected = "its GPS time without a fix puts the boot at" if gnss_time else "never had a 3-D fix nor a GPS week"
    assert any(expected in note for note in prov["notes"])
    start = datetime(2025, 1, 3, tzinfo=UTC).timestamp()
    log = read_log(path, site=Site(lat=48.1, lon=11.5, alt=500.0, start=start))
    np.testing.assert_allclose(log.time, start + df["time"].to_numpy(), rtol=0, atol=1e-6)
    assert np.all(log.table["lat"] == 48.1)


def mag_log(path, columns="TimeMS,MagX,MagY,MagZ", fields=None, second=None, n=50):
    """A 3.2-layout log of ``n`` MAG messages at 10 Hz (``fields``: name -> (n,) values) and, if given, MAG2
    messages of ``second``; an ATT and a GPS without fix."""
    w = DataFlashWriter(GENERATIONS["3.2"])
    fmt = "I" + "h" * (len(columns.split(",")) - 1)
    w.define("MAG", fmt, columns)
    if second is not None:
        w.define("MAG2", fmt, columns)
    for message in ("ATT", "GPS", "MSG"):
        w.define(message)
    w.write("MSG", Message="ArduCopter V3.2.1 (36b405fb)")
    ms = 1000 + 100 * np.arange(n)
    w.write("MAG", TimeMS=ms, **(fields or {}))
    if second is not None:
        w.write("MAG2", TimeMS=ms, **second)
    w.write("ATT", TimeMS=ms, Roll=1.0, Pitch=2.0, Yaw=3.0)
    w.write("GPS", order_us=ms * 1000, Status=1, T=ms)
    return w.save(path)


def varying(n=50):
    return {"MagX": 100 + np.arange(n), "MagY": -50 + np.arange(n) % 7, "MagZ": 400 - np.arange(n)}


def test_refusals_are_one_line(tmp_path):
    """What the log lacks and what to do, in one line naming the file."""
    cases = []
    w = DataFlashWriter(GENERATIONS["3.2"])
    w.define("ATT")
    w.write("ATT", TimeMS=1000, Roll=0.0, Pitch=0.0, Yaw=0.0)
    nomag = w.save(tmp_path / "nomag.bin")
    cases.append(
        (
            nomag,
            {},
            "no MAG, MAG2 or MAG3 message: the compass was not logged; record a log with the compass bit of "
            "LOG_BITMASK set",
        )
    )
    constant = mag_log(tmp_path / "constant.bin", fields={"MagX": 300, "MagY": -100, "MagZ": 400})
    cases.append(
        (
            constant,
            {},
            "MAG (magnetometer instance 0) reads (300, -100, 400) mG in all 50 samples, so no compass "
            "works there; the log has no other compass",
        )
    )
    zero = mag_log(tmp_path / "zero.bin", second=varying())
    cases.append(
        (
            zero,
            {"mag": 0},
            "MAG (magnetometer instance 0) reads (0, 0, 0) mG in all 50 samples, so no compass works there; "
            "choose another with --mag (the log has [0, 1])",
        )
    )
    cases.append((zero, {"mag": 2}, "no magnetometer instance 2; the log has [0, 1]"))
    nameless = mag_log(tmp_path / "nameless.bin", columns="TimeMS,X,Y,Z", fields={"X": np.arange(50)})
    cases.append(
        (
            nameless,
            {},
            "MAG (magnetometer instance 0) has no MagX, MagY, MagZ fields (its columns: TimeMS, X, Y, Z); "
            "choose another magnetometer with --mag or convert the log to the canonical CSV",
        )
    )
    for path, options, message in cases:
        with pytest.raises(InputError) as err:
            read_dataflash(path, **options)
        assert str(err.value) == f"{path}: {message}"
    df, prov = read_dataflash(zero)  # unasked, the first working compass of that log is read
    assert len(df) == 50 and prov["magnetometer"]["message"] == "MAG2"
    assert (
        prov["notes"][0]
        == "not read: MAG (magnetometer instance 0) reads (0, 0, 0) mG in all 50 samples, so no compass works there"
    )


def test_zero_samples_are_dropped_and_noted(tmp_path):
    """A compass that reads (0, 0, 0) before it starts: those samples are dropped, in a note."""
    fields = varying()
    for axis in fields.values():
        axis[:5] = 0
    df, prov = read_dataflash(mag_log(tmp_path / "late.bin", fields=fields))
    assert len(df) == 45 and df["time"].iloc[0] == pytest.approx(1.5)
    assert "5 MAG samples of exactly (0, 0, 0) mG (not read) dropped" in prov["notes"]


def test_layouts_without_needed_fields_read_with_notes(tmp_path):
    """An ATT without Yaw and a GPS without position or week: no attitude, boot time, never a KeyError."""
    w = DataFlashWriter(GENERATIONS["3.2"])
    w.define("MAG")
    w.define("ATT", "Icc", "TimeMS,Roll,Pitch")
    w.define("GPS", "IB", "TimeMS,Status")
    ms = 1000 + 100 * np.arange(30)
    w.write("MAG", TimeMS=ms, **varying(30))
    w.write("ATT", TimeMS=ms, Roll=1.0, Pitch=2.0)
    w.write("GPS", order_us=ms * 1000, TimeMS=ms, Status=3)
    df, prov = read_dataflash(w.save(tmp_path / "partial.bin"))
    assert "roll" not in df and prov["time_base"] == "boot" and prov["firmware"] == "unknown"
    assert "no ATT message with Roll, Pitch and Yaw: no attitude" in prov["notes"]


@pytest.mark.parametrize(
    ("message", "firmware"),
    [
        ("MSG", "APM:Copter V3.1.5 (3c57e771)"),
        ("MSG", "ArduCopter V3.2.1 (36b405fb)"),
        ("MSG", "ArduRover v2.49"),
        ("MSG", "ArduPlane V3.3.0 (1d2b0c4b)"),
        ("VER", "ArduSub V4.1.2 (8b3fc2ab)"),
    ],
)
def test_firmware_string_of_every_generation(tmp_path, drive, message, firmware):
    """The firmware named by the first MSG of a vehicle and version (any generation), or by VER.FWS (4.x)."""
    path = tmp_path / "fw.bin"
    if message == "MSG":
        write_dataflash(drive.iloc[:20], path, generation="3.2", firmware=firmware)
    else:
        w = DataFlashWriter()
        w.define("VER", "QBHBBBBIZH", "TimeUS,BT,BST,Maj,Min,Pat,FWT,GH,FWS,APJ")
        w.define("MAG")
        w.write("VER", TimeUS=1000, FWS=firmware)
        w.write("MAG", TimeUS=2000 + 1000 * np.arange(20), I=0, **varying(20))
        w.save(path)
    assert read_dataflash(path)[1]["firmware"] == firmware


def pymavlink_messages(path, names):
    """``{name: [message, ...]}`` of the messages ``names`` as pymavlink's DFReader decodes them."""
    from pymavlink import DFReader

    out = {name: [] for name in names}
    with DFReader.DFReader_binary(str(path)) as reader:
        while (m := reader.recv_match(type=list(names))) is not None:
            out[m.get_type()].append(m)
    return out


@pytest.mark.parametrize("generation", list(GENERATIONS))
def test_decoding_matches_pymavlink(tmp_path, drive, generation):
    """Every field of MAG, MAG2, ATT and GPS decodes to pymavlink's values (same scaling), and the epochs' UTC
    to pymavlink's timestamps where it has a clock of the log's own (3.2: GPS T; 3.5, 4.5: TimeUS; for 3.1, a
    GPS without boot time, pymavlink interpolates by message rate, and the times are checked against the
    drive instead)."""
    params = parameters(generation, 2)
    path = tmp_path / f"pm-{generation}.bin"
    write_dataflash(drive, path, parameters=params, generation=generation, compasses=2)
    names = ["MAG", "ATT", "GPS"] + ([] if generation == "4.5" else ["MAG2"])
    theirs = pymavlink_messages(path, names)
    with _Log(path) as log:
        for name in names:
            ours = log.table(name)
            for column in theirs[name][0].get_fieldnames():
                expected = np.array([getattr(m, column) for m in theirs[name]], float)
                np.testing.assert_array_equal(np.asarray(ours[column], float), expected, err_msg=f"{name}.{column}")
    df, _ = read_dataflash(path, mag=0)
    mags = [m for m in theirs["MAG"] if getattr(m, "I", 0) == 0]
    if generation != "3.1":
        np.testing.assert_allclose(df["time"], [m._timestamp for m in mags], rtol=0, atol=1e-6)
    raw_logged = np.array([[m.MagX, m.MagY, m.MagZ] for m in mags], float)
    logged, _ = read_dataflash(path, mag=0, raw=False)
    np.testing.assert_array_equal(np.trunc(logged[MAG].to_numpy() / 100.0), raw_logged)


@pytest.mark.parametrize(("firmware", "motor_first"), [("ArduCopter V3.5.7", True), ("ArduCopter V3.6.0", False)])
def test_motor_compensation_order_follows_the_firmware(tmp_path, firmware, motor_first):
    """3.3-3.5 added the logged motor offsets (MOfsX) before the soft-iron matrix, 3.6 on after it: a log written
    with that firmware's order reads back within the field's truncation bound (50 nT per component through
    |M^-1|; the motor offsets are made the values the reader centres their truncated logging to, so they add
    nothing); read in the other order it would be off by more than that."""
    rng = np.random.default_rng(4)
    raw_mg = rng.normal([200.0, -100.0, 400.0], 150.0, (100, 3))
    motor = np.column_stack([np.linspace(0, 80, 100), np.linspace(0, -40, 100), np.linspace(0, 120, 100)])
    motor = np.trunc(motor) + 0.5 * np.sign(np.trunc(motor))  # centred, as the reader takes them
    params = parameters("3.5", 1)
    ofs, dia, odi, _ = calibration(params, 0)
    field = np.trunc(compass_correct(raw_mg, ofs, dia, odi, 1.0, motor, motor_first=motor_first))
    w = DataFlashWriter(GENERATIONS["3.5"])
    for message in ("MSG", "PARM", "MAG"):
        w.define(message)
    w.write("MSG", TimeUS=1000, Message=firmware)
    w.write("PARM", TimeUS=2000, Name=np.array(list(params)), Value=np.array(list(params.values()), np.float32))
    axes = {f"Mag{a}": field[:, j] for j, a in enumerate("XYZ")}
    motors = {f"MOfs{a}": np.trunc(motor[:, j]) for j, a in enumerate("XYZ")}
    offsets = {f"Ofs{a}": np.trunc(ofs[j]) for j, a in enumerate("XYZ")}
    w.write("MAG", TimeUS=10_000 + 100_000 * np.arange(100), **axes, **motors, **offsets)
    df, prov = read_dataflash(w.save(tmp_path / "motor.bin"))
    mat = np.array([[dia[0], odi[0], odi[1]], [odi[0], dia[1], odi[2]], [odi[1], odi[2], dia[2]]])
    bound = 50.0 * np.abs(np.linalg.inv(mat)).sum(axis=1) + 1e-6
    assert np.all(np.abs(df[MAG].to_numpy() - raw_mg * 100.0) <= bound)
    other = compass_correct(raw_mg, ofs, dia, odi, 1.0, motor, motor_first=not motor_first)
    assert np.abs(other - field).max() > 1.0  # the orders differ by more than the truncation here
    assert any(f"motor {'before' if motor_first else 'after'} the matrix" in n for n in prov["notes"])


@pytest.mark.parametrize("generation", list(GENERATIONS))
def test_any_missing_field_reads_or_is_refused_in_one_line(tmp_path, monkeypatch, drive, generation):
    """Each field of each message a generation writes, left out of its layout in turn: the log reads (the
    reader falls back: another time, no attitude, boot time, ...) or is refused with an InputError; no other
    exception (KeyError, IndexError) escapes."""
    table = drive.iloc[:30].assign(throttle=0.5)
    layouts = GENERATIONS[generation]
    refused = []
    for message, (fmt, columns) in layouts.items():
        for column in columns.split(",") if len(fmt) > 1 else ():  # a message of no fields cannot be declared
            pairs = [(c, n) for c, n in zip(fmt, columns.split(",")) if n != column]
            reduced = dict(layouts) | {message: ("".join(c for c, _ in pairs), ",".join(n for _, n in pairs))}
            monkeypatch.setitem(GENERATIONS, generation, reduced)
            path = tmp_path / f"{message}-{column}.bin"
            write_dataflash(table, path, parameters=parameters(generation, 1), generation=generation)
            try:
                read_dataflash(path)
            except InputError as err:
                assert "\n" not in str(err) and str(path) in str(err)
                refused.append(f"{message}.{column}")
    assert set(refused) <= {"MAG.MagX", "MAG.MagY", "MAG.MagZ"}, refused


def test_a_boot_clock_running_slow_is_mapped_by_a_line(tmp_path):
    """A boot clock that runs at 1/1.08 of GPS time (as on the PXF boards of 2014): UTC - boot time drifts by
    seconds over the log, so a straight line through the GPS samples maps it, within the 1 ms steps of TimeMS
    and GPS ms (each up to 0.5 ms off, times 1.08: under 2 ms)."""
    true_s = 100.0 + np.arange(3000) * 0.1  # s since some instant, 10 Hz for 300 s
    boot_ms = np.rint(10_000 + 1000 * (true_s - true_s[0]) / 1.08).astype(np.int64)
    utc = datetime(2014, 12, 5, 10, 54, tzinfo=UTC).timestamp() + true_s
    gps_ms = np.rint((utc - datetime(1980, 1, 6, tzinfo=UTC).timestamp() + 16.0) * 1000).astype(np.int64)
    week, ms = np.divmod(gps_ms, 604_800_000)  # GPS - UTC = 16 s in 2014
    w = DataFlashWriter(GENERATIONS["3.2"])
    for message in ("MAG", "GPS"):
        w.define(message)
    w.write("MAG", TimeMS=boot_ms, **varying(3000))
    t_field = np.where(np.arange(0, 3000, 2) < 6, 0, boot_ms[::2])  # the first three with T unset (0): not used
    w.write("GPS", order_us=boot_ms[::2] * 1000, Status=3, TimeMS=ms[::2], Week=week[::2], T=t_field, Lat=43.0)
    df, prov = read_dataflash(w.save(tmp_path / "slow.bin"))
    np.testing.assert_allclose(df["time"], utc, rtol=0, atol=2e-3)
    assert "the boot clock runs at 0.9259 of GPS time" in prov["time_base"]
    assert any(note.startswith("the boot clock runs at 0.9259 of GPS time") for note in prov["notes"])


#: The exact refusal of a log timed since boot that has its own position (magkf.io.site.place_at_site).
DATE_ONLY = (
    "the log has no GNSS time (its clock counts from boot), which the reference field needs: give --date "
    "YYYY-MM-DD[THH:MM], the UTC at its boot (the day is enough)"
)
#: Lat/Lng are int32 1e-7 deg: rounding to nearest is off by at most 0.5e-7 deg (plus the double arithmetic).
LATLON_ATOL_DEG = 0.5e-7 + 1e-12


@pytest.mark.parametrize("generation", list(GENERATIONS))
def test_fix_without_gps_week_keeps_its_positions_in_boot_time(tmp_path, drive, generation):
    """GPS with a 3-D fix (Status 3, Lat/Lng) but week and ms 0 (a receiver without time): seconds since boot,
    the positions and fix kept, so read_log asks for --date only; with it the logged positions are read."""
    path = tmp_path / f"noweek-{generation}.bin"
    write_dataflash(drive, path, generation=generation, gnss_time=False)
    df, prov = read_dataflash(path)
    assert prov["time_base"] == "boot"
    np.testing.assert_allclose(df["lat"], drive["lat"], rtol=0, atol=LATLON_ATOL_DEG)
    np.testing.assert_allclose(df["lon"], drive["lon"], rtol=0, atol=LATLON_ATOL_DEG)
    assert (df["fix_type"] == 3).all()
    assert (
        "the GNSS has a 3-D fix but never a GPS week (no GNSS time): time is in seconds since boot and the GPS "
        "positions with a 3-D fix are kept on that time base (give --date)"
    ) in prov["notes"]
    with pytest.raises(InputError) as refused:
        read_log(path)
    assert str(refused.value) == f"{path}: {DATE_ONLY}"
    start = datetime(2025, 1, 3, tzinfo=UTC).timestamp()
    log = read_log(path, site=Site(start=start))
    np.testing.assert_array_equal(log.table["lat"].to_numpy(), df["lat"].to_numpy())
    np.testing.assert_allclose(log.time, start + df["time"].to_numpy(), rtol=0, atol=1e-6)
    assert "site" not in prov or "lat" not in prov["site"]


def test_gps_at_5_hz_bridges_a_lost_sample(tmp_path, drive):
    """A 5 Hz GPS (every other row of a 10 Hz drive) with one sample lost: the epochs in that 0.4 s gap, over
    max_gap_s = 0.3 s but under 3 of the GPS's 0.2 s intervals, get a position linear between the samples
    around the gap (int32 1e-7 deg storage); one note counts them. Without the loss there is no note."""
    fix = np.where(np.arange(len(drive)) % 2 == 0, 3.0, np.nan)
    lost = 200  # an even row: a GPS sample
    path = tmp_path / "gps5hz.bin"
    write_dataflash(drive.assign(fix_type=np.where(np.arange(len(drive)) == lost, np.nan, fix)), path)
    df, prov = read_dataflash(path, max_gap_s=0.3)
    inside = slice(0, -1)  # the last row, after the last GPS sample (row 598), has none
    assert np.isfinite(df["lat"][inside]).all() and (df["fix_type"][inside] == 3).all()
    expected = np.interp([1.0, 2.0, 3.0], [0.0, 4.0], drive["lat"].to_numpy()[[lost - 2, lost + 2]])
    np.testing.assert_allclose(df["lat"].to_numpy()[lost - 1 : lost + 2], expected, rtol=0, atol=LATLON_ATOL_DEG)
    assert (
        "3 epochs lie in GPS gaps longer than max_gap_s = 0.3 s: their position, DOP and fix are interpolated "
        "across gaps up to 0.60 s (3 of the GPS's median interval, 0.20 s)"
    ) in prov["notes"]
    full = tmp_path / "gps5hz_full.bin"
    write_dataflash(drive.assign(fix_type=fix), full)
    _, prov_full = read_dataflash(full, max_gap_s=0.3)
    assert not any("gaps longer than max_gap_s" in n for n in prov_full["notes"])

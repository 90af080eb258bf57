"""``magkf.live.replay`` and ``magkf replay`` over a loopback UDP socket: the replay runs in a thread, a pymavlink
connection of the test receives it and asks what a ground station asks. Every wait is bounded."""

import argparse
import threading
import time

import numpy as np
import pandas as pd
import pytest
from pymavlink import mavutil

from magkf.cli import replay as replay_cli
from magkf.errors import Note
from magkf.io.mavlink_packets import REBOOT_START_US, START_US, VehiclePackets
from magkf.live import replay as replay_module
from magkf.live.replay import replay
from magkf.sim import DriveConfig, simulate_drive

RATE_HZ = 20.0
SPEED = 20.0
#: No wait in these tests lasts longer (s): a replay of a few seconds of log at 20 times real time takes under 1 s.
TIMEOUT_S = 5.0
PARAMS = {"COMPASS_OFS_X": 12.5, "COMPASS_OFS_Y": -3.0, "COMPASS_OFS_Z": 4.0, "COMPASS_MOTCT": 0}
STREAMS = {"HEARTBEAT", "AUTOPILOT_VERSION", "PARAM_VALUE", "RAW_IMU", "ATTITUDE", "GPS_RAW_INT", "SYSTEM_TIME"}
STREAMS |= {"BATTERY_STATUS", "VFR_HUD"}


@pytest.fixture(scope="module")
def flight() -> pd.DataFrame:
    """A seeded 10 s 3-D drive at 20 Hz with a throttle column: 0.5 s of replay at 20 times real time."""
    sim = simulate_drive(DriveConfig(duration_s=10.0, rate_hz=RATE_HZ, motion="3d", seed=11))
    t = sim.table.index.to_numpy()
    return sim.table.assign(throttle=0.4 + 0.1 * np.sin(t - t[0]))


def receiver():
    """A ground station's link listening on a free loopback port, and the replay's connection towards it."""
    rx = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=255, source_component=190)
    return rx, f"udpout:127.0.0.1:{rx.port.getsockname()[1]}"


def in_thread(target, **kwargs) -> tuple[threading.Thread, dict]:
    """``target(**kwargs)`` in a thread; its result (or exception) in the dict."""
    out: dict = {}

    def run():
        try:
            out["result"] = target(**kwargs)
        except BaseException as exc:  # noqa: BLE001 - handed to the test, which raises it
            out["error"] = exc

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread, out


def receive(rx, thread, on_message=None) -> list:
    """``(monotonic s, message)`` of everything received until the replay's thread ends (and 0.1 s more), at most
    ``TIMEOUT_S``; ``on_message(message)`` is called on each."""
    got, deadline, quiet_since = [], time.monotonic() + TIMEOUT_S, None
    while time.monotonic() < deadline:
        message = rx.recv_match(blocking=True, timeout=0.02)
        if message is not None and message.get_type() != "BAD_DATA":
            got.append((time.monotonic(), message))
            if on_message is not None:
                on_message(message)
            continue
        if not thread.is_alive():
            quiet_since = quiet_since or time.monotonic()
            if time.monotonic() - quiet_since > 0.1:
                break
    thread.join(TIMEOUT_S)
    assert not thread.is_alive(), "the replay did not end"
    return got


def finished(out: dict):
    if "error" in out:
        raise out["error"]
    return out["result"]


def test_every_message_arrives_paced_and_requests_are_answered(flight):
    rx, connection = receiver()
    thread, out = in_thread(
        replay, log_or_table=flight, connection=connection, speed=SPEED, params=PARAMS, firmware="4.5.1", linger_s=0.2
    )
    asked: dict = {}

    def ask(message):  # once the stream runs: a read by name, a read by index, a set and a message interval
        if message.get_type() == "RAW_IMU" and not asked:
            asked["at"] = time.monotonic()
            rx.mav.param_request_read_send(1, 1, b"COMPASS_OFS_Y", -1)
            rx.mav.param_request_read_send(1, 1, b"", 2)
            rx.mav.param_set_send(1, 1, b"COMPASS_OFS_X", 33.0, 9)
            rx.mav.command_long_send(1, 1, 511, 0, 27, 10_000, 0, 0, 0, 0, 0)
            rx.mav.param_request_read_send(7, 1, b"COMPASS_OFS_Y", -1)  # another vehicle's: not answered

    got = receive(rx, thread, ask)
    stats = finished(out)
    rx.close()
    names = [m.get_type() for _, m in got]
    assert STREAMS <= set(names)
    assert stats.completed and stats.packets_dropped == 0
    assert stats.packets_sent == len(VehiclePackets(flight, params=PARAMS, firmware="4.5.1", ground_station=False))
    assert len([n for n in names if n not in ("PARAM_VALUE", "COMMAND_ACK")]) + len(PARAMS) == stats.packets_sent
    answers = [m for t, m in got if t > asked["at"] and m.get_type() in ("PARAM_VALUE", "COMMAND_ACK")]
    values = {(m.param_id, m.param_index): m.param_value for m in answers if m.get_type() == "PARAM_VALUE"}
    assert values == {("COMPASS_OFS_Y", 1): -3.0, ("COMPASS_OFS_Z", 2): 4.0, ("COMPASS_OFS_X", 0): 33.0}
    # the readings carry the offset as set from its echo on, as ArduPilot's correct_field applies it
    echoes = [t for t, m in got if m.get_type() == "PARAM_VALUE" and m.param_id == "COMPASS_OFS_X"]
    echo = max(echoes)  # the announcement came first, the echo after the request
    old, new = (
        VehiclePackets(flight, params=p, firmware="4.5.1").sent_field()
        for p in (PARAMS, PARAMS | {"COMPASS_OFS_X": 33.0})
    )
    checked = []
    for t, m in got:
        if m.get_type() == "RAW_IMU" and (t < asked["at"] or t > echo):
            row = round((m.time_usec - START_US) * 1e-6 * RATE_HZ)
            assert [m.xmag, m.ymag, m.zmag] == list((old if t < asked["at"] else new)[row])
            checked.append(t > echo)
    assert 0 < sum(checked) < len(checked) and np.any(old[:, 0] != new[:, 0])
    acks = [m for m in answers if m.get_type() == "COMMAND_ACK"]
    assert [(m.command, m.result) for m in acks] == [(511, 0)]
    assert stats.requests_answered == 4 and stats.requests["PARAM_REQUEST_READ"] == 2
    # pacing: the magnetometer's receipt times against its boot times. The replay is never early, and each packet
    # is late by its wake-up delay (milliseconds); over the 0.5 s of the run a delay of 5 ms at either end moves
    # the fitted slope by about 2 x 5 / 500 = 2 %: a 5 % bound holds it with room for a loaded machine.
    imu = [(t, m.time_usec * 1e-6) for t, m in got if m.get_type() == "RAW_IMU"]
    received, boot = np.array(imu).T
    slope = np.polyfit(boot - boot[0], received - received[0], 1)[0]
    assert slope == pytest.approx(1.0 / SPEED, rel=0.05)
    # the replay waits for each packet's time, so its last is sent no sooner than the log's span over the speed;
    # it is late by the wake-up delay of its thread, milliseconds, up to tens under a full load of both cores
    assert stats.log_s / SPEED <= stats.elapsed_s <= stats.log_s / SPEED + 0.1


def test_the_dropped_share_is_binomial_and_seen_as_sequence_gaps(flight):
    rx, connection = receiver()
    thread, out = in_thread(replay, log_or_table=flight, connection=connection, speed=SPEED, loss=0.05, seed=3)
    got = receive(rx, thread)
    stats = finished(out)
    rx.close()
    n = stats.packets_sent + stats.packets_dropped
    # each packet dropped with probability 0.05 independently: the count is Binomial(n, 0.05); 4 standard
    # deviations leave a chance of 6e-5 to a fair generator
    assert abs(stats.packets_dropped - 0.05 * n) <= 4.0 * np.sqrt(n * 0.05 * 0.95)
    seqs = np.array([m.get_seq() for _, m in got])
    assert len(seqs) == stats.packets_sent  # the loopback itself lost nothing
    # the sender counts every packet, sent or dropped: the gaps the receiver sees (before the first, between, after
    # the last) are the dropped packets (no run of 256 drops in a row, whose chance is 0.05**256)
    gaps = int(seqs[0]) + int(np.sum((np.diff(seqs) - 1) % 256)) + (n - 1 - int(seqs[-1])) % 256
    assert gaps == stats.packets_dropped


def test_stop_ends_the_replay(flight):
    rx, connection = receiver()
    stop = threading.Event()
    thread, out = in_thread(replay, log_or_table=flight, connection=connection, speed=1.0, stop=stop)
    time.sleep(0.2)
    stop.set()
    thread.join(TIMEOUT_S)
    stats = finished(out)
    rx.close()
    # it looks at stop at least every POLL_S: it ends within that of being asked, far from the 10 s of the log
    assert not stats.completed and stats.elapsed_s < 0.2 + 10 * replay_module.POLL_S
    assert 0 < stats.packets_sent < len(VehiclePackets(flight, ground_station=False))


def test_a_keyboard_interrupt_ends_the_replay_cleanly(flight, monkeypatch):
    rx, connection = receiver()
    calls = {"n": 0}
    serve = replay_module._Vehicle._serve_until

    def interrupted_after_ten(self, due, stop):
        calls["n"] += 1
        if calls["n"] > 10:
            raise KeyboardInterrupt
        return serve(self, due, stop)

    monkeypatch.setattr(replay_module._Vehicle, "_serve_until", interrupted_after_ten)
    stats = replay(flight, connection, speed=float("inf"))
    rx.close()
    assert stats.interrupted_by == 2 and not stats.completed and stats.packets_sent == 10 * replay_module.BURST


def test_the_command_replays_a_log_file_with_a_reboot(flight, tmp_path, capsys):
    log = tmp_path / "flight.csv"
    flight.reset_index().to_csv(log, index=False)
    params = tmp_path / "vehicle.param"
    params.write_text("COMPASS_OFS_X,12.5\nCOMPASS_OFS_Y,-3\n")
    rx, connection = receiver()
    parser = argparse.ArgumentParser()
    replay_cli.add_parsers(parser.add_subparsers())
    args = parser.parse_args(
        ["replay", str(log), connection, "--speed", "40", "--params", str(params), "--reboot-at", "5", "--seed", "1"]
    )
    with pytest.warns(Note, match="2 parameters given: applied to the field as ArduPilot does"):
        thread, out = in_thread(replay_cli.run_replay, args=args)
        got = receive(rx, thread)
    assert finished(out) == 0
    rx.close()
    line = capsys.readouterr().out.strip()
    assert line.startswith("replayed ") and "packets sent, 0 dropped" in line and "(whole log)" in line
    boot = np.array([m.time_usec for _, m in got if m.get_type() == "RAW_IMU"])
    falls = np.flatnonzero(np.diff(boot) < 0)
    assert len(falls) == 1 and boot[falls[0] + 1] == REBOOT_START_US
    assert len(boot) == len(flight)


def test_refusals_name_the_connection(flight):
    from magkf.errors import InputError

    with pytest.raises(InputError, match="not a MAVLink connection"):
        replay(flight, "flight.tlog")
    with pytest.raises(InputError, match=r"loss 1 is not a share"):
        replay(flight, "udpout:127.0.0.1:9", loss=1.0)


@pytest.mark.parametrize("raw", [True, False])
def test_a_telemetry_log_is_sent_again_as_its_vehicle_sent_it(flight, tmp_path, raw):
    """A tlog read raw (its calibration undone) is sent with its own COMPASS_* parameters applied again; read as
    the autopilot calibrated it, with them announced only: either way the RAW_IMU fields are the log's, to the
    count (the reader centres a truncated int16 within its 1 mG step, and the encoder truncates again: a value
    may come back one count away where the calibration, applied again in float64, lands on a step's edge)."""
    from magkf.io.mavlink_packets import VehiclePackets
    from magkf.io.readers import read_log
    from magkf.io.tlog import mavlink_dialect, write_tlog
    from magkf.live.replay import _log_firmware, log_parameters

    calibration = {"COMPASS_OFS_X": 120.0, "COMPASS_OFS_Y": -80.0, "COMPASS_DIA_X": 1.05, "COMPASS_SCALE": 1.1}
    path = tmp_path / "flight.tlog"
    write_tlog(flight, path, params=calibration, firmware="4.5.1")
    log = read_log(path, raw=raw)
    notes: list = []
    params, apply = log_parameters(log, "ardupilot", None, notes)
    assert params == pytest.approx(calibration) and apply is raw
    assert _log_firmware(log, "ardupilot", notes) == "4.5.1"
    parser = mavlink_dialect().MAVLink(None)
    sent, again = (
        np.array(
            [[m.xmag, m.ymag, m.zmag] for m in map(parser.decode, map(bytearray, packets)) if m.get_type() == "RAW_IMU"]
        )
        for packets in (
            [p.data for p in VehiclePackets(flight, params=calibration, firmware="4.5.1")],
            [p.data for p in VehiclePackets(log.table, params=params, apply_params=apply, firmware="4.5.1")],
        )
    )
    assert np.max(np.abs(sent - again)) <= 1


def test_over_tcp_the_replay_stops_when_the_receiver_closes(flight):
    rx = mavutil.mavlink_connection("tcpin:127.0.0.1:0", source_system=255, source_component=190)
    connection = f"tcp:127.0.0.1:{rx.listen.getsockname()[1]}"
    thread, out = in_thread(replay, log_or_table=flight, connection=connection, speed=SPEED)
    first = rx.recv_match(type="RAW_IMU", blocking=True, timeout=TIMEOUT_S)
    rx.close()
    thread.join(TIMEOUT_S)
    stats = finished(out)
    assert first is not None and not stats.completed
    assert "the receiver closed the connection: the replay stopped" in stats.notes


def test_listening_on_tcp_the_replay_waits_for_its_receiver(flight):
    import socket

    with socket.socket() as probe:  # a port free a moment ago; the replay listens on it
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    thread, out = in_thread(replay, log_or_table=flight, connection=f"tcpin:127.0.0.1:{port}", speed=float("inf"))
    time.sleep(0.1)
    rx = mavutil.mavlink_connection(f"tcp:127.0.0.1:{port}", source_system=255, retries=20, reconnect_delay=0.05)
    got = receive(rx, thread)
    stats = finished(out)
    rx.close()
    # nothing is sent before the receiver connects, and TCP loses nothing after
    assert stats.completed and len(got) == stats.packets_sent
    assert any(n.startswith("waited ") for n in stats.notes)


def test_ardupilot_parameters_take_the_firmware_types():
    """A parameter file's 0 for an offset is ArduPilot's float (announced and set as REAL32, so that 12.5 is kept);
    the compass's settings are its integers."""
    from magkf.live.replay import ardupilot_typed

    typed = ardupilot_typed({"COMPASS_OFS_X": 0, "COMPASS_DIA2_Y": 1, "COMPASS_ORIENT": 4.0, "COMPASS_MOTCT": 2,
                             "COMPASS_DEV_ID": 97539.0, "AHRS_ORIENTATION": 0.0, "COMPASS_DEC": 0})  # fmt: skip
    assert typed == {"COMPASS_OFS_X": 0.0, "COMPASS_DIA2_Y": 1.0, "COMPASS_ORIENT": 4, "COMPASS_MOTCT": 2,
                     "COMPASS_DEV_ID": 97539, "AHRS_ORIENTATION": 0, "COMPASS_DEC": 0.0}  # fmt: skip
    assert [type(v) for v in typed.values()] == [float, float, int, int, int, int, float]


@pytest.mark.parametrize(
    "firmware, mav_type",
    [
        ("ArduPlane V4.2.3 (55685c43)", 1),
        ("APM:Copter V3.5.7 (b11c6af3)", 2),
        ("ArduRover V4.5.1", 10),
        ("ArduSub V4.1.1 BETA5 (66c674c1)", 12),
        ("PX4 1.15.0", None),
        (None, None),
    ],
)
def test_the_heartbeat_names_the_logs_vehicle(firmware, mav_type, flight):
    """The replay's HEARTBEAT carries the type of the vehicle the log's firmware names, by which a receiver names
    the firmware (``tlog.VEHICLE_OF_TYPE``: an ArduPlane log was announced as ArduCopter); a quadrotor where the
    log does not say."""
    from types import SimpleNamespace

    from magkf.io.mavlink_packets import VEHICLE_TYPE
    from magkf.io.tlog import VEHICLE_OF_TYPE, mavlink_dialect
    from magkf.live.replay import log_vehicle_type

    found = log_vehicle_type(SimpleNamespace(provenance={"firmware": firmware}))
    assert found == mav_type
    packets = VehiclePackets(flight, vehicle_type=VEHICLE_TYPE if found is None else found, ground_station=False)
    parser = mavlink_dialect().MAVLink(None)
    beats = [m for m in (parser.decode(bytearray(p.data)) for p in packets) if m.get_type() == "HEARTBEAT"]
    assert beats and {m.type for m in beats} == {VEHICLE_TYPE if found is None else found}
    if firmware is not None and found is not None:
        assert firmware.replace("APM:", "Ardu").startswith(f"Ardu{VEHICLE_OF_TYPE[found]}")

"""``MavlinkSource`` against a small vehicle in the test: a thread with a pymavlink ``udpin`` connection on the
loopback address that waits for the ground station's first packet, then streams a seeded simulated flight as an
ArduPilot vehicle would (``magkf.io.mavlink_packets.VehiclePackets``: ``RAW_IMU`` with the ``COMPASS_*``
calibration applied, ``ATTITUDE`` twice a row, ``GPS_RAW_INT``, ``SYSTEM_TIME``, ``BATTERY_STATUS``, ``VFR_HUD``)
faster than real time, numbering its packets with one sequence counter as a vehicle does, and answers
``PARAM_REQUEST_READ`` and ``PARAM_SET`` from a dict. One run drops a seeded share of packets, delays one, pauses
(a link that drops and comes back) and reboots; each test checks a part of what came out of it.

Precision of what the messages carry (the bounds below):

* ``xmag, ymag, zmag``: int16 mG truncated towards zero by the vehicle, centred by the reader: at most 0.5 mG off
  (1 mG where the field truncated to 0), i.e. at most 1 mG through the firmware's correction; undoing it maps that
  through the inverse model, at most ``sum_j |M^-1|_ij x 1 mG / SCALE`` per axis (as ``test_tlog`` derives).
* ``ATTITUDE``: float32 radians (half a spacing, 2**-23 rad, below 4 rad); the rows' magnetometer times have an
  attitude message at the same time, where the interpolation returns it.
* ``GPS_RAW_INT``: 1e-7 deg, mm, DOP in hundredths (half a count each); ``current_battery`` cA, ``throttle`` percent.
* Time: ``time_usec`` in us, ``SYSTEM_TIME`` exact for whole-ms rows: the table's times to float64 rounding.
"""

from __future__ import annotations

import contextlib
import dataclasses
import socket
import threading
import time

import numpy as np
import pandas as pd
import pytest

from magkf.conventions import euler_to_quaternion
from magkf.errors import InputError
from magkf.io.drivelog import from_table
from magkf.io.mavlink_packets import VEHICLE, VehiclePackets, param_value_message, with_sequence
from magkf.io.tlog import mavlink_dialect
from magkf.io.vehicle_calibration import logged_calibration
from magkf.live.source import ARDUPILOT_PARAMETERS, PARAM_ROUND_S, PARAM_ROUNDS, PX4_PARAMETERS, MavlinkSource
from magkf.sim import DriveConfig, simulate_drive

from ..conftest import truncation_bound_nt

RATE_HZ = 20.0
DURATION_S = 10.0
#: Vehicle seconds per wall second.
SPEED = 15.0
#: Seconds of the flight after its first row at which the link pauses, and at which the vehicle reboots.
PAUSE_AT_S, REBOOT_AT_S = 1.5, 7.0
#: Wall seconds of the pause, and the link timeout of the source (a pause is two timeouts long).
PAUSE_S, LINK_TIMEOUT_S = 0.5, 0.25
#: Wall seconds a rebooted vehicle leaves parameter requests unanswered (``Vehicle``'s ``rebooted_params``).
MUTE_AFTER_REBOOT_S = 0.1
#: Share of the magnetometer and between-rows attitude packets dropped.
DROP_SHARE = 0.03
HALF_FLOAT32_RAD = 2.0**-23
#: Seconds a poll reads for.
POLL_S = 0.05
CALIBRATION = {
    "COMPASS_OFS_X": 120.0,
    "COMPASS_OFS_Y": -80.0,
    "COMPASS_OFS_Z": 35.0,
    "COMPASS_DIA_X": 1.05,
    "COMPASS_DIA_Y": 0.97,
    "COMPASS_DIA_Z": 1.01,
    "COMPASS_ODI_X": 0.02,
    "COMPASS_ODI_Y": -0.01,
    "COMPASS_ODI_Z": 0.03,
    "COMPASS_SCALE": 1.1,
}
#: Every other compass parameter the source asks for, at the firmware's defaults.
DEFAULTS = {
    name: 1.0 if "_DIA" in name or name.startswith("COMPASS_SCALE") else 0
    for name in ARDUPILOT_PARAMETERS
    if name not in CALIBRATION
}


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Vehicle(threading.Thread):
    """The vehicle's side of the link (see the module docstring); ``sent_seq`` are the packets' indices sent,
    ``requests`` the names of the messages received from the ground station, ``done`` set after the last packet.

    Parameters
    ----------
    port : int
        Its ``udpin`` port on 127.0.0.1.
    packets : list of VehiclePacket
        What it streams (the vehicle's only), paced by ``time_us`` at ``SPEED``.
    params : dict
        Its parameters, answered on request and changed by ``PARAM_SET`` except those of ``read_only``.
    drop : set of int
        Packets (indices) numbered but not sent.
    delay : dict of int to int
        Packets (indices) sent that many packets later than their turn.
    pause_at_us : int or None
        The first packet at or after this ``time_us`` waits ``PAUSE_S`` wall seconds (nothing is sent meanwhile).
    transport : {"udpin", "tcpin"}
        Its end of the link.
    close_at_us : int or None
        ``tcpin``: before the first packet at or after this ``time_us`` it closes the ground station's connection,
        then waits for it to connect again.
    autopilot : str
        How its parameters are encoded (PX4 sends an integer's bytes).
    queue : int or None
        As ArduPilot (``param_requests`` in ``GCS_Param.cpp``): parameter requests wait in a queue of this many,
        those that do not fit are dropped, and a few are answered between packets. None: each answered at once.
    rebooted_params : dict or None
        Its parameters after the reboot (of the packets' second boot), which it leaves unanswered for
        ``MUTE_AFTER_REBOOT_S`` wall seconds after the reboot, as a vehicle still starting.
    """

    def __init__(
        self,
        port,
        packets,
        params,
        *,
        drop=(),
        delay=None,
        pause_at_us=None,
        read_only=(),
        transport="udpin",
        close_at_us=None,
        autopilot="ardupilot",
        queue=None,
        rebooted_params=None,
    ):
        super().__init__(daemon=True)
        from pymavlink import mavutil

        self.conn = mavutil.mavlink_connection(f"{transport}:127.0.0.1:{port}", source_system=1, source_component=1)
        self.packets, self.params, self.read_only = packets, dict(params), set(read_only)
        self.drop, self.delay, self.pause_at_us = set(drop), dict(delay or {}), pause_at_us
        self.close_at_us, self.autopilot = close_at_us, autopilot
        self.queue, self.waiting, self.dropped = queue, [], 0
        self.rebooted_params, self.muted_until = rebooted_params, -1.0
        self.packer = mavlink_dialect().MAVLink(None, srcSystem=1, srcComponent=1)
        self.seq, self.boot = 0, 0
        self.requests: list[str] = []
        self.done, self.stop = threading.Event(), threading.Event()
        self.deadline = time.monotonic() + 30.0

    def run(self) -> None:
        try:
            while not self.requests and not self._over():
                self._serve()
                time.sleep(0.002)
            self._stream()
            self.done.set()
            while not self._over():
                self._serve()
                time.sleep(0.005)
        finally:
            self.conn.close()

    def _over(self) -> bool:
        return self.stop.is_set() or time.monotonic() > self.deadline

    def _stream(self) -> None:
        if not self.packets:
            return
        first, start, held = self.packets[0].time_us, time.monotonic(), []
        for i, packet in enumerate(self.packets):
            if self.pause_at_us is not None and packet.time_us >= self.pause_at_us:
                self.pause_at_us = None
                self._wait_until(time.monotonic() + PAUSE_S)
                start += PAUSE_S
            if self.close_at_us is not None and packet.time_us >= self.close_at_us:
                self.close_at_us = None
                start += self._close_and_wait()
            self._wait_until(start + (packet.time_us - first) * 1e-6 / SPEED)
            if packet.boot != self.boot:
                self.boot, self.seq = packet.boot, 0  # the counter starts again at a reboot
                if self.rebooted_params is not None:
                    self.params = dict(self.rebooted_params)
                    self.muted_until = time.monotonic() + MUTE_AFTER_REBOOT_S
            data = with_sequence(packet.data, self._next_seq())
            if i in self.delay:
                held.append([self.delay[i], data])
            elif i not in self.drop:
                self.conn.write(data)
            for item in held:
                item[0] -= 1
                if item[0] < 0:
                    self.conn.write(item[1])
            held = [item for item in held if item[0] >= 0]
            if self._over():
                return

    def _close_and_wait(self) -> float:
        """Close the ground station's TCP connection; wait (bounded) for it to connect and send again. Returns the
        wall seconds this took."""
        began, asked = time.monotonic(), len(self.requests)
        self._close_gracefully(self.conn.port)
        self.conn.port, self.conn.fd = None, self.conn.listen.fileno()  # pymavlink's tcpin accepts again
        while len(self.requests) == asked and not self._over():
            self._serve()
            time.sleep(0.002)
        return time.monotonic() - began

    def _close_gracefully(self, port) -> None:
        """Close the connection as a vehicle's TCP stack does: the end of what was sent (FIN) after the packets sent,
        then what the ground station still sends read and left unanswered until it closes its end (at most 2 s).
        Closed at once with its bytes unread, the socket would reset the connection, and the ground station's
        system would drop the packets it had received but not yet handed to it: a loss that a busy machine makes
        likely, and not one the source can prevent."""
        with contextlib.suppress(OSError):
            port.shutdown(socket.SHUT_WR)
        until = time.monotonic() + 2.0
        while time.monotonic() < until and not self._over():
            try:
                if not port.recv(4096):
                    break  # the ground station closed its end
            except BlockingIOError:
                time.sleep(0.002)
            except OSError:
                break
        port.close()

    def _wait_until(self, when: float) -> None:
        while time.monotonic() < when and not self._over():
            self._serve()
            time.sleep(min(max(when - time.monotonic(), 0.0), 0.002))

    def _next_seq(self) -> int:
        seq, self.seq = self.seq, (self.seq + 1) % 256
        return seq

    def _serve(self) -> None:
        while (msg := self.conn.recv_msg()) is not None:
            name = msg.get_type()
            self.requests.append(name)
            if name == "PARAM_REQUEST_READ" and time.monotonic() < self.muted_until:
                continue
            if name == "PARAM_REQUEST_READ" and self.queue is not None:
                if len(self.waiting) < self.queue:
                    self.waiting.append(msg.param_id)
                else:
                    self.dropped += 1
            elif name == "PARAM_REQUEST_READ" and msg.param_id in self.params:
                self._answer(msg.param_id)
            elif name == "PARAM_SET" and msg.param_id in self.params:
                if msg.param_id not in self.read_only:
                    value = msg.param_value
                    self.params[msg.param_id] = int(value) if msg.param_type == 6 else value
                self._answer(msg.param_id)

        for name in self.waiting[:2]:  # a few answered now, the rest wait
            if name in self.params:
                self._answer(name)
        del self.waiting[:2]

    def _answer(self, name: str) -> None:
        names = list(self.params)
        message = param_value_message(name, self.params[name], len(names), names.index(name), self.autopilot)
        self.conn.write(with_sequence(message.pack(self.packer), self._next_seq()))


def vehicle_packets(table, **kwargs) -> list:
    return [p for p in VehiclePackets(table, ground_station=False, **kwargs) if p.source == VEHICLE]


def stream(source, vehicle, link_drops: int, limit_s: float = 15.0) -> tuple[list, list]:
    """Poll ``source`` until the vehicle has sent everything and ``link_drops`` links were lost (the stream's end
    is the last: the last sample waits for it), at most ``limit_s`` s; the samples and events. ``source.out_at_end``
    is how many samples it had handed out when the vehicle had sent its last packet."""
    samples, events = [], []
    deadline = time.monotonic() + limit_s
    source.out_at_end = None
    while time.monotonic() < deadline:
        if vehicle.done.is_set() and source.out_at_end is None:
            source.out_at_end = len(samples)
        samples += source.poll(POLL_S)
        events += source.take_events()
        if vehicle.done.is_set() and source.counters["link_drops"] >= link_drops:
            break
    return samples, events


@pytest.fixture(scope="module")
def flight():
    """A seeded 10 s 3-D flight at 20 Hz with a throttle, HDOP and VDOP."""
    sim = simulate_drive(DriveConfig(duration_s=DURATION_S, rate_hz=RATE_HZ, motion="3d", seed=11))
    t = sim.table.index.to_numpy()
    throttle = 0.5 + 0.3 * np.sin(2 * np.pi * (t - t[0]) / 7.0)
    return sim.table.assign(hdop=sim.table["dop"], vdop=1.5 * sim.table["dop"], throttle=throttle)


def faults(packets, flight) -> tuple[set, dict]:
    """Seeded drops of magnetometer and between-rows attitude packets, away from the start, the pause, the reboot
    and the end (where a loss cannot be seen by the sequence numbers); one magnetometer packet delayed by three
    packets, and the old boot's last packet (an attitude) delayed past the first clock message of the new boot."""
    rows_us = set(np.rint(flight.index.to_numpy() * 1e6).astype(np.int64).tolist())
    t0 = packets[0].time_us
    at = np.array([(p.time_us - t0) * 1e-6 for p in packets])
    away = (at > 1.0) & (np.abs(at - PAUSE_AT_S) > 0.5) & (np.abs(at - REBOOT_AT_S - 0.5) > 1.0) & (at < at[-1] - 1)
    candidates = [
        i
        for i, p in enumerate(packets)
        if away[i] and (p.name == "RAW_IMU" or (p.name == "ATTITUDE" and p.time_us not in rows_us))
    ]
    rng = np.random.default_rng(2032)
    drop = {i for i in candidates if rng.random() < DROP_SHARE}
    delayed = next(i for i in candidates if at[i] > 2.0 and i not in drop and not drop & set(range(i, i + 5)))
    last_old = max(i for i, p in enumerate(packets) if p.boot == 0)
    new_clock = next(i for i, p in enumerate(packets) if p.boot == 1 and p.name == "RAW_IMU")
    assert packets[last_old].name == "ATTITUDE"
    return drop, {delayed: 3, last_old: new_clock - last_old + 3}


@pytest.fixture(scope="module")
def run(flight):
    """The flight streamed with drops, a delayed packet, a pause and a reboot; what the source made of it."""
    packets = vehicle_packets(flight, params=CALIBRATION, firmware="4.5.7", reboot_at_s=REBOOT_AT_S)
    drop, delay = faults(packets, flight)
    port = free_udp_port()
    pause_at = packets[0].time_us + int(PAUSE_AT_S * 1e6)
    vehicle = Vehicle(port, packets, CALIBRATION | DEFAULTS, drop=drop, delay=delay, pause_at_us=pause_at)
    vehicle.start()
    source = MavlinkSource(f"udpout:127.0.0.1:{port}", rate_hz=RATE_HZ, link_timeout_s=LINK_TIMEOUT_S)
    try:
        source.open(timeout_s=5.0)
        samples, events = stream(source, vehicle, link_drops=2)
        counters, provenance = dict(source.counters), dict(source.provenance)
        params, firmware, asked = dict(source.params), source.firmware, dict(source.asked_hz)
    finally:
        source.close()
        vehicle.stop.set()
        vehicle.join(5.0)
    return {
        "samples": samples,
        "events": events,
        "counters": counters,
        "provenance": provenance,
        "params": params,
        "firmware": firmware,
        "asked": asked,
        "drop": drop,
        "packets": packets,
        "requests": vehicle.requests,
    }


def rows_of(samples, flight) -> np.ndarray:
    """Index of each sample's row in the flight (its time equal to 1e-6 s: the module docstring)."""
    t = flight.index.to_numpy()
    times = np.array([s["time"] for s in samples])
    rows = np.clip(np.searchsorted(t, times - 5e-7), 0, len(t) - 1)
    assert np.all(np.abs(t[rows] - times) <= 1e-6)
    return rows


def wrapped(d):
    return (d + 180.0) % 360.0 - 180.0


# ------------------------------------------------------------------ the samples
def test_every_magnetometer_packet_sent_is_one_sample_at_its_time(run, flight):
    sent_mag = [i for i, p in enumerate(run["packets"]) if p.name == "RAW_IMU" and i not in run["drop"]]
    samples = run["samples"]
    rows = rows_of(samples, flight)
    assert len(samples) == len(sent_mag) == run["counters"]["samples"]
    assert np.all(np.diff([s["time"] for s in samples]) > 0)
    expected = {int(np.rint((run["packets"][i].time_us * 1e-6 - flight.index[0]) * RATE_HZ)) for i in sent_mag}
    assert set(rows.tolist()) == expected
    assert run["counters"]["late"] == 0  # the delayed packet came while its neighbours waited: still useful


def test_fields_match_the_flight_with_the_compass_calibration_undone(run, flight):
    samples = run["samples"]
    rows = rows_of(samples, flight)
    bound = truncation_bound_nt(CALIBRATION)
    got = np.array([[s["mag_x"], s["mag_y"], s["mag_z"]] for s in samples])
    error = np.abs(got - flight[["mag_x", "mag_y", "mag_z"]].to_numpy()[rows])
    assert np.all(error <= bound + 1e-6)
    assert error.max() > 1.0  # the truncation is there: not a copy
    provenance = run["provenance"]
    assert provenance["magnetometer"]["calibrated"] is False
    assert provenance["raw_reconstruction"].startswith("AP_Compass_Backend::correct_field of ArduCopter V4.5.7")
    assert run["firmware"] == "ArduCopter V4.5.7"
    assert all(run["params"][k] == pytest.approx(v, rel=1e-7) for k, v in CALIBRATION.items())


def test_provenance_reads_as_a_telemetry_logs(run, flight):
    """What reads a telemetry log's provenance reads the live one alike: the vehicle's own calibration, rebuilt
    from it, corrects the raw samples to the field the firmware computed, M ((raw + OFS) x SCALE)."""
    provenance = run["provenance"]
    assert provenance["format"] == "mavlink-tlog" and provenance["live"] is True
    assert provenance["magnetometer"] | {"instance": 0} == {
        "message": "RAW_IMU",
        "instance": 0,
        "autopilot": "ardupilot",
        "message_calibrated": True,
        "calibrated": False,
        "compass": 1,
        "parameter_set": "COMPASS_OFS, COMPASS_DIA, COMPASS_ODI, COMPASS_SCALE",
    }
    assert provenance["vehicle"]["firmware"] == "4.5.7"
    table = pd.DataFrame(run["samples"])
    log = from_table(table, source=provenance["connection"], provenance=provenance)
    vehicle_cal = logged_calibration(log)
    raw = table[["mag_x", "mag_y", "mag_z"]].to_numpy()
    p = {k: float(np.float32(v)) for k, v in CALIBRATION.items()}
    m = np.array(
        [
            [p["COMPASS_DIA_X"], p["COMPASS_ODI_X"], p["COMPASS_ODI_Y"]],
            [p["COMPASS_ODI_X"], p["COMPASS_DIA_Y"], p["COMPASS_ODI_Z"]],
            [p["COMPASS_ODI_Y"], p["COMPASS_ODI_Z"], p["COMPASS_DIA_Z"]],
        ]
    )
    offsets = np.array([p[f"COMPASS_OFS_{a}"] for a in "XYZ"]) * 100.0
    firmware_field = (raw + offsets) * p["COMPASS_SCALE"] @ m.T
    np.testing.assert_allclose(vehicle_cal.correct(raw), firmware_field, rtol=0, atol=1e-6)


def test_attitude_position_and_auxiliary_match_the_flight(run, flight):
    samples = run["samples"]
    rows = rows_of(samples, flight)
    for column in ("roll", "pitch", "yaw"):
        got = np.array([s[column] for s in samples])
        difference = wrapped(got - flight[column].to_numpy()[rows])
        assert np.max(np.abs(difference)) <= np.degrees(HALF_FLOAT32_RAD) + 1e-9, column
    # The slow streams are compared at the rows where they were sent (there the latest value is the row's own).
    sent_at = {name: {p.time_us for p in run["packets"] if p.name == name} for name in ("GPS_RAW_INT", "VFR_HUD")}
    row_us = np.rint(flight.index.to_numpy()[rows] * 1e6).astype(np.int64)
    gps = np.array([u in sent_at["GPS_RAW_INT"] for u in row_us])
    hud = np.array([u in sent_at["VFR_HUD"] for u in row_us])
    assert gps.sum() > 20 and hud.sum() > 10
    for column, half, where in (
        ("lat", 5e-8, gps),
        ("lon", 5e-8, gps),
        ("alt", 0.5e-3, gps),
        ("hdop", 0.005, gps),
        ("vdop", 0.005, gps),
        ("throttle", 0.005, hud),
        ("current_a", 0.005, hud),
    ):
        got = np.array([s[column] for s in samples])[where]
        assert np.max(np.abs(got - flight[column].to_numpy()[rows][where])) <= half + 1e-9, column
    got_temp = np.array([s["temp_c"] for s in samples])
    assert np.max(np.abs(got_temp - flight["temp_c"].to_numpy()[rows])) <= 0.005 + 1e-9


# ------------------------------------------------------------------ the faults
def test_sequence_gaps_are_the_packets_dropped_and_the_delayed_one_is_reordered(run):
    """The old boot's attitude delayed past the reboot is neither a loss nor reordered: its counter is not the new
    boot's."""
    counters = run["counters"]
    assert run["drop"]
    assert counters["lost"] == len(run["drop"])
    assert counters["reordered"] == 1
    assert counters["packets"] > len(run["packets"]) - len(run["drop"])  # and the parameters answered


def test_a_reboot_is_reported_and_survived(run, flight):
    """Once: the old boot's attitude that comes after the new boot's first clock message is not a second one."""
    assert run["counters"]["reboots"] == 1
    assert any(e.startswith("the vehicle rebooted") for e in run["events"])
    t = np.array([s["time"] for s in run["samples"]]) - flight.index[0]
    after = t > REBOOT_AT_S
    assert after.sum() > 0.9 * (DURATION_S - REBOOT_AT_S) * RATE_HZ  # the streams go on after it
    assert run["requests"].count("REQUEST_DATA_STREAM") >= 2 * 5  # asked again (five groups each time)


def test_after_a_reboot_samples_wait_for_the_parameters_in_force(flight):
    """The vehicle reboots at 4 s with another offset (as after a calibration uploaded) and answers parameters
    only after a while: every sample is undone with the parameters of its own boot (within the bound of the
    firmware's truncation), none with the old offset, 5 000 nT off."""
    new = CALIBRATION | {"COMPASS_OFS_X": CALIBRATION["COMPASS_OFS_X"] + 50.0}
    old_boot = vehicle_packets(flight, params=CALIBRATION, firmware="4.5.7", reboot_at_s=4.0)
    new_boot = vehicle_packets(flight, params=new, firmware="4.5.7", reboot_at_s=4.0)
    # the new boot's parameters only as answers (its announced PARAM_VALUEs would come before its clock says
    # it rebooted)
    packets = [p for p in old_boot if p.boot == 0] + [p for p in new_boot if p.boot == 1 and p.name != "PARAM_VALUE"]
    port = free_udp_port()
    vehicle = Vehicle(port, packets, CALIBRATION | DEFAULTS, rebooted_params=new | DEFAULTS)
    vehicle.start()
    source = MavlinkSource(f"udpout:127.0.0.1:{port}", rate_hz=RATE_HZ, link_timeout_s=LINK_TIMEOUT_S)
    try:
        source.open(timeout_s=5.0)
        samples, events = stream(source, vehicle, link_drops=1)
        samples += source.drain()
    finally:
        source.close()
        vehicle.stop.set()
        vehicle.join(5.0)
    assert source.counters["reboots"] == 1 and source.params["COMPASS_OFS_X"] == pytest.approx(170.0)
    t = np.array([s["time"] for s in samples]) - flight.index[0]
    assert (t > 4.0).sum() > 0.9 * (DURATION_S - 4.0) * RATE_HZ
    bound = truncation_bound_nt(CALIBRATION)
    got = np.array([[s["mag_x"], s["mag_y"], s["mag_z"]] for s in samples])
    error = np.abs(got - flight[["mag_x", "mag_y", "mag_z"]].to_numpy()[rows_of(samples, flight)])
    assert np.all(error <= bound + 1e-6)


def test_a_link_that_pauses_is_reported_lost_and_back(run):
    """The pause, then the end of the stream (after which the last sample, whose attitude after it never comes, is
    handed out)."""
    assert run["counters"]["link_drops"] == 2
    link = [e.split(" after")[0].split(":")[0] for e in run["events"] if e.startswith("link ")]
    assert link == ["link lost", "link back", "link lost"]


def test_a_stream_at_another_rate_than_asked_is_reported_once(run):
    """ATTITUDE comes twice a row (40 Hz) against the 20 Hz asked; RAW_IMU at 20 Hz less 3 % dropped."""
    assert run["asked"]["ATTITUDE"] == RATE_HZ and run["asked"]["RAW_IMU"] == RATE_HZ
    rates = [e for e in run["events"] if " Hz, asked " in e]
    assert [e.split()[0] for e in rates] == ["ATTITUDE"]
    assert float(rates[0].split()[3]) == pytest.approx(2 * RATE_HZ, rel=0.05)


# ------------------------------------------------------------------ parameters and refusals
def test_set_parameters_is_confirmed_by_the_echo_and_a_refusal_reported(flight):
    packets = vehicle_packets(flight.iloc[:10], params=CALIBRATION)
    port = free_udp_port()
    vehicle = Vehicle(port, packets, CALIBRATION | DEFAULTS, read_only={"COMPASS_DEV_ID"})
    vehicle.start()
    source = MavlinkSource(f"udpout:127.0.0.1:{port}", rate_hz=RATE_HZ)
    try:
        source.open(timeout_s=5.0)
        assert source.params["COMPASS_OFS_X"] == 120.0 and source.params["COMPASS_DEV_ID"] == 0
        confirmed = source.set_parameters({"COMPASS_OFS_X": 12.5, "COMPASS_DEV_ID": 97539}, timeout_s=1.0)
        events = source.take_events()
    finally:
        source.close()
        vehicle.stop.set()
        vehicle.join(5.0)
    assert confirmed == {"COMPASS_OFS_X": True, "COMPASS_DEV_ID": False}
    assert vehicle.params["COMPASS_OFS_X"] == 12.5
    assert any(e.startswith("PARAM_SET COMPASS_DEV_ID = 97539 refused") for e in events)


def test_no_heartbeat_is_an_input_error_naming_the_connection():
    connection = f"udpin:127.0.0.1:{free_udp_port()}"
    source = MavlinkSource(connection)
    start = time.monotonic()
    with pytest.raises(InputError, match="no HEARTBEAT") as error:
        source.open(timeout_s=0.3)
    assert connection in str(error.value)
    assert time.monotonic() - start < 2.0


# ------------------------------------------------------------------ other vehicles and links
def sent_field_bound_nt(field_mg: np.ndarray) -> np.ndarray:
    """Largest storage error (nT) of a field sent as it is: 50 nT, 100 nT where it truncated to 0."""
    return np.where(np.abs(field_mg) < 1.0, 100.0, 50.0) + 1e-9


def test_px4_field_is_read_as_sent_with_its_cal_mag_parameters(flight):
    """PX4's SCALED_IMU is sensor_mag before its calibration: nothing to undo; CAL_MAGn_* read (the integer id
    decoded from its bytes)."""
    params = {name: 1.0 if "SCALE" in name else 0 for name in PX4_PARAMETERS} | {
        "CAL_MAG0_ID": 396825,
        "CAL_MAG0_XOFF": 0.25,
    }
    table = flight.iloc[:60]
    port = free_udp_port()
    vehicle = Vehicle(port, vehicle_packets(table, autopilot="px4", params=params), params, autopilot="px4")
    vehicle.start()
    source = MavlinkSource(f"udpout:127.0.0.1:{port}", rate_hz=RATE_HZ, link_timeout_s=LINK_TIMEOUT_S)
    try:
        source.open(timeout_s=5.0)
        samples, _ = stream(source, vehicle, link_drops=1)
        provenance, read = dict(source.provenance), dict(source.params)
    finally:
        source.close()
        vehicle.stop.set()
        vehicle.join(5.0)
    assert source.autopilot == "px4" and len(samples) == len(table)
    rows = rows_of(samples, table)
    truth = table[["mag_x", "mag_y", "mag_z"]].to_numpy()[rows]
    got = np.array([[s["mag_x"], s["mag_y"], s["mag_z"]] for s in samples])
    assert np.all(np.abs(got - truth) <= sent_field_bound_nt(truth / 100.0))
    assert read["CAL_MAG0_ID"] == 396825 and read["CAL_MAG0_XOFF"] == 0.25
    assert provenance["magnetometer"]["message"] == "SCALED_IMU"
    assert provenance["magnetometer"]["message_calibrated"] is False
    assert provenance["raw_reconstruction"].startswith("nothing to undo")


def test_without_system_time_the_receipt_clock_stands_in_and_keeps_the_order(flight):
    """Samples are held for the first SYSTEM_TIME for 2 s of the vehicle's clock, then timed by this computer's
    clock on receipt with one offset: the table's steps kept exactly (float64 rounding of UNIX s)."""
    table = flight.iloc[:60]
    port = free_udp_port()
    vehicle = Vehicle(port, vehicle_packets(table, params=CALIBRATION, system_time=False), CALIBRATION | DEFAULTS)
    vehicle.start()
    source = MavlinkSource(f"udpout:127.0.0.1:{port}", rate_hz=RATE_HZ, link_timeout_s=LINK_TIMEOUT_S)
    began = time.time()
    try:
        source.open(timeout_s=5.0)
        samples, events = stream(source, vehicle, link_drops=1)
    finally:
        source.close()
        vehicle.stop.set()
        vehicle.join(5.0)
    assert any(e.startswith("no SYSTEM_TIME within 2 s") for e in events)
    times = np.array([s["time"] for s in samples])
    assert len(times) == len(table)
    np.testing.assert_allclose(np.diff(times), np.diff(table.index.to_numpy()), rtol=0, atol=1e-6)
    assert abs(times[0] - began) < 5.0  # this computer's clock, not the table's (2026)


def free_tcp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_tcp_connection_closed_by_the_vehicle_is_opened_again(flight):
    table = flight.iloc[:80]
    packets = vehicle_packets(table, params=CALIBRATION)
    port = free_tcp_port()
    close_at = packets[0].time_us + 2_000_000
    vehicle = Vehicle(port, packets, CALIBRATION | DEFAULTS, transport="tcpin", close_at_us=close_at)
    vehicle.start()
    source = MavlinkSource(f"tcp:127.0.0.1:{port}", rate_hz=RATE_HZ, link_timeout_s=LINK_TIMEOUT_S)
    try:
        source.open(timeout_s=5.0)
        samples, events = stream(source, vehicle, link_drops=2)
        rates = source.rates_hz
    finally:
        source.close()
        vehicle.stop.set()
        vehicle.join(5.0)
    # Nothing dropped: each stream's measured rate is its sending rate, to float64 rounding.
    sending = {"RAW_IMU": RATE_HZ, "ATTITUDE": 2 * RATE_HZ, "GPS_RAW_INT": 5.0, "SYSTEM_TIME": 1.0, "VFR_HUD": 2.0}
    assert {name: rates[name] for name in sending} == pytest.approx(sending, rel=1e-9)
    link = [e.split(":")[0].split(" after")[0] for e in events if e.startswith("link ")]
    assert link == ["link lost", "link back", "link lost"]
    assert "closed by the other end" in next(e for e in events if e.startswith("link lost"))
    assert len(samples) == len(table)  # nothing was lost: the vehicle waited for the new connection


def test_a_ground_station_too_busy_to_read_for_a_while_loses_nothing(flight):
    """The source not polled for four link timeouts mid-stream (this computer busy): over TCP, the packets waiting in
    the socket are read when it polls again, not dropped with a connection opened again; the link is lost only at
    the stream's end."""
    table = flight.iloc[:80]
    packets = vehicle_packets(table, params=CALIBRATION)
    port = free_tcp_port()
    vehicle = Vehicle(port, packets, CALIBRATION | DEFAULTS, transport="tcpin")
    vehicle.start()
    source = MavlinkSource(f"tcp:127.0.0.1:{port}", rate_hz=RATE_HZ, link_timeout_s=LINK_TIMEOUT_S)
    try:
        source.open(timeout_s=5.0)
        samples, events = [], []
        while len(samples) < len(table) // 3:  # a third of the stream read, then nothing read for a while
            samples += source.poll(POLL_S)
            events += source.take_events()
        time.sleep(4 * LINK_TIMEOUT_S)
        more, later = stream(source, vehicle, link_drops=1)
        rates = source.rates_hz
    finally:
        source.close()
        vehicle.stop.set()
        vehicle.join(5.0)
    events += later
    sending = {"RAW_IMU": RATE_HZ, "ATTITUDE": 2 * RATE_HZ, "GPS_RAW_INT": 5.0, "SYSTEM_TIME": 1.0, "VFR_HUD": 2.0}
    assert {name: rates[name] for name in sending} == pytest.approx(sending, rel=1e-9)
    assert [e.split(":")[0] for e in events if e.startswith("link ")] == ["link lost"]  # the end's alone
    assert len(samples + more) == len(table)


def test_without_attitude_samples_go_after_wait_s_and_the_missing_stream_is_reported(flight):
    table = flight.iloc[:120]
    packets = [p for p in vehicle_packets(table, params=CALIBRATION) if p.name != "ATTITUDE"]
    port = free_udp_port()
    vehicle = Vehicle(port, packets, CALIBRATION | DEFAULTS)
    vehicle.start()
    source = MavlinkSource(f"udpout:127.0.0.1:{port}", rate_hz=RATE_HZ, link_timeout_s=LINK_TIMEOUT_S)
    try:
        source.open(timeout_s=5.0)
        samples, events = stream(source, vehicle, link_drops=1)
    finally:
        source.close()
        vehicle.stop.set()
        vehicle.join(5.0)
    assert len(samples) == len(table)
    rows_of(samples, table)
    # Each sample went once the vehicle's clock was wait_s past it, not at the link's loss after the end: when the
    # last packet was sent, at most wait_s of samples waited, plus those of the poll under way and the one before
    # it (2 x POLL_S wall seconds, SPEED times as many of the vehicle's).
    waiting = len(table) - source.out_at_end
    assert waiting <= (source.wait_s + 2 * POLL_S * SPEED) * RATE_HZ + 1
    assert all(np.isnan([s["roll"], s["pitch"], s["yaw"]]).all() for s in samples)
    assert np.isfinite([s["mag_x"] for s in samples]).all()
    assert f"ATTITUDE does not arrive (asked {RATE_HZ:g} Hz)" in events


def test_a_connection_that_cannot_be_opened_is_an_input_error_naming_it():
    connection = f"tcp:127.0.0.1:{free_tcp_port()}"  # nothing listens there
    with pytest.raises(InputError, match="cannot open the connection") as error:
        MavlinkSource(connection).open(timeout_s=1.0)
    assert str(error.value).startswith(connection)


def read_parameters(flight, params: dict, **vehicle_options) -> tuple:
    """Open a source against a vehicle with ``params`` (and ``vehicle_options``) and close it: the vehicle, the
    source, its events and the wall seconds ``open`` took (the parameter read)."""
    port = free_udp_port()
    vehicle = Vehicle(port, vehicle_packets(flight.iloc[:10]), params, **vehicle_options)
    vehicle.start()
    source = MavlinkSource(f"udpout:127.0.0.1:{port}", rate_hz=RATE_HZ)
    try:
        began = time.monotonic()
        source.open(timeout_s=5.0)
        took = time.monotonic() - began
        events = source.take_events()
    finally:
        source.close()
        vehicle.stop.set()
        vehicle.join(5.0)
    return vehicle, source, events, took


def test_parameters_a_vehicle_does_not_have_are_asked_in_rounds_then_reported(flight):
    """The vehicle has only the CALIBRATION set: the others are asked for in PARAM_ROUNDS rounds, each ending a
    few round trips after its last answer (on loopback, PARAM_MIN_S), not PARAM_ROUND_S; then reported."""
    vehicle, source, events, took = read_parameters(flight, CALIBRATION)
    missing = len(ARDUPILOT_PARAMETERS) - len(CALIBRATION)
    assert any(e.startswith(f"{missing} parameters not answered after {PARAM_ROUNDS} requests") for e in events)
    assert vehicle.requests.count("PARAM_REQUEST_READ") == len(ARDUPILOT_PARAMETERS) + (PARAM_ROUNDS - 1) * missing
    assert {k: source.params[k] for k in CALIBRATION} == pytest.approx(CALIBRATION, rel=1e-7)
    assert took < PARAM_ROUNDS * PARAM_ROUND_S


def test_parameter_requests_fit_ardupilots_queue(flight):
    """A vehicle that, as ArduPilot, queues 20 requests and drops the rest answers every one of the 51 asked in
    the first round: they go ``PARAM_WINDOW`` at a time."""
    vehicle, source, events, _ = read_parameters(flight, CALIBRATION | DEFAULTS, queue=20)
    assert vehicle.dropped == 0
    assert vehicle.requests.count("PARAM_REQUEST_READ") == len(ARDUPILOT_PARAMETERS)
    assert set(source.params) >= set(ARDUPILOT_PARAMETERS) and not source.missing_compass_parameters
    assert not any("not answered" in e for e in events)


def test_a_vehicle_that_answers_no_parameter_is_not_waited_for_window_by_window(flight):
    """No answer to the first window in its wait: the rest of each round goes at once, so the read takes one wait
    more than the rounds' (not one a window)."""
    vehicle, _, events, took = read_parameters(flight, {})
    assert vehicle.requests.count("PARAM_REQUEST_READ") == PARAM_ROUNDS * len(ARDUPILOT_PARAMETERS)
    assert any(e.startswith(f"{len(ARDUPILOT_PARAMETERS)} parameters not answered") for e in events)
    assert (PARAM_ROUNDS + 1) * PARAM_ROUND_S <= took < (PARAM_ROUNDS + 2) * PARAM_ROUND_S


def test_motor_compensation_is_undone_with_the_latest_throttle(flight):
    """COMPASS_MOTCT 1: the firmware adds COMPASS_MOT x throttle (the throttle of the moment) to the corrected
    field; live undoes it with the latest VFR_HUD throttle at or before the sample (sent every 0.5 s, in percent),
    which lags the throttle by under 0.5 s. The throttle 0.5 + 0.3 sin(2 pi t / 7 s) moves at most
    0.3 x 2 pi / 7 per second, so the throttle used is off by at most that x 0.5 s + 0.005 (rounding); through the
    inverse model that adds sum_j |M^-1|_ij |MOT_j| x that / SCALE to the truncation's bound per axis."""
    mot = {"COMPASS_MOT_X": 20.0, "COMPASS_MOT_Y": -15.0, "COMPASS_MOT_Z": 30.0}
    params = CALIBRATION | mot | {"COMPASS_MOTCT": 1}
    table = flight.iloc[:100]
    port = free_udp_port()
    vehicle = Vehicle(port, vehicle_packets(table, params=params, firmware="4.5.7"), DEFAULTS | params)
    vehicle.start()
    source = MavlinkSource(f"udpout:127.0.0.1:{port}", rate_hz=RATE_HZ, link_timeout_s=LINK_TIMEOUT_S)
    try:
        source.open(timeout_s=5.0)
        samples, _ = stream(source, vehicle, link_drops=1)
        text = source.provenance["raw_reconstruction"]
    finally:
        source.close()
        vehicle.stop.set()
        vehicle.join(5.0)
    assert "motor compensation COMPASS_MOT x throttle" in text
    p = {k: float(np.float32(v)) for k, v in params.items()}
    m = np.array(
        [
            [p["COMPASS_DIA_X"], p["COMPASS_ODI_X"], p["COMPASS_ODI_Y"]],
            [p["COMPASS_ODI_X"], p["COMPASS_DIA_Y"], p["COMPASS_ODI_Z"]],
            [p["COMPASS_ODI_Y"], p["COMPASS_ODI_Z"], p["COMPASS_DIA_Z"]],
        ]
    )
    inverse = np.abs(np.linalg.inv(m))
    throttle_error = 0.3 * 2 * np.pi / 7.0 * 0.5 + 0.005
    motor_mg = np.abs([p[k] for k in mot]) * throttle_error
    bound = (inverse.sum(axis=1) * 1.0 + inverse @ motor_mg) * 100.0 / p["COMPASS_SCALE"]
    rows = rows_of(samples, table)
    got = np.array([[s["mag_x"], s["mag_y"], s["mag_z"]] for s in samples])
    error = np.abs(got - table[["mag_x", "mag_y", "mag_z"]].to_numpy()[rows])
    assert len(samples) == len(table)
    assert np.all(error <= bound + 1e-6)
    # Left in, the motor term would be M^-1 MOT x throttle / SCALE: the error is well under it (RMS, z-axis).
    left_in = np.abs(np.linalg.inv(m) @ np.array([p[k] for k in mot]))[2] * table["throttle"].to_numpy()[rows]
    left_in_nt = left_in * 100.0 / p["COMPASS_SCALE"]
    assert np.sqrt(np.mean(error[:, 2] ** 2)) < 0.5 * np.sqrt(np.mean(left_in_nt**2))


def as_quaternion_packets(packets) -> list:
    """``packets`` with every ATTITUDE sent as ATTITUDE_QUATERNION (the same time and attitude, float32)."""
    dialect = mavlink_dialect()
    parser, packer = dialect.MAVLink(None), dialect.MAVLink(None, srcSystem=1, srcComponent=1)
    out = []
    for p in packets:
        if p.name == "ATTITUDE":
            a = parser.decode(bytearray(p.data))
            q = euler_to_quaternion(*np.degrees([a.yaw, a.pitch, a.roll]))
            message = dialect.MAVLink_attitude_quaternion_message(a.time_boot_ms, *q, 0.0, 0.0, 0.0)
            p = dataclasses.replace(p, name="ATTITUDE_QUATERNION", data=bytes(message.pack(packer)))
        out.append(p)
    return out


def test_attitude_quaternion_is_used_where_it_is_what_comes(flight):
    """q1..q4 as float32 (each off by at most 2**-25 below 1): the rotation between the sample's attitude and the
    table's is at most 2 |dq| <= 2 x 2 x 2**-25 = 2**-23 rad, plus the float32 radians of the ATTITUDE they were
    made from (2**-23 each of three angles, 3 x 2**-23 at most)."""
    table = flight.iloc[:60]
    packets = as_quaternion_packets(vehicle_packets(table, params=CALIBRATION))
    port = free_udp_port()
    vehicle = Vehicle(port, packets, CALIBRATION | DEFAULTS)
    vehicle.start()
    source = MavlinkSource(f"udpout:127.0.0.1:{port}", rate_hz=RATE_HZ, link_timeout_s=LINK_TIMEOUT_S)
    try:
        source.open(timeout_s=5.0)
        samples, _ = stream(source, vehicle, link_drops=1)
    finally:
        source.close()
        vehicle.stop.set()
        vehicle.join(5.0)
    assert len(samples) == len(table)
    rows = rows_of(samples, table)
    got = euler_to_quaternion(*np.array([[s["yaw"], s["pitch"], s["roll"]] for s in samples]).T)
    truth = euler_to_quaternion(*(table[c].to_numpy()[rows] for c in ("yaw", "pitch", "roll")))
    angle = 2 * np.arccos(np.clip(np.abs(np.sum(got * truth, axis=1)), 0.0, 1.0))
    assert np.max(angle) <= 4 * 2.0**-23 + 1e-12


def test_missing_compass_parameters_are_those_of_the_compass_read():
    """Only the offsets and matrices of the compass whose field is read keep --upload from sending: another
    compass's never answered do not matter to this calibration."""
    source = MavlinkSource("udpin:127.0.0.1:0")
    source._never_answered = ("COMPASS_OFS2_X", "COMPASS_DIA_Y", "COMPASS_MOT_X", "COMPASS_ODI3_Z")
    source.provenance["magnetometer"] = {"compass": 1}
    assert source.missing_compass_parameters == ("COMPASS_DIA_Y",)
    source.provenance["magnetometer"] = {"compass": 2}
    assert source.missing_compass_parameters == ("COMPASS_OFS2_X",)


def test_slerp_is_scipys_along_the_shorter_arc():
    """The live path's slerp of bracketed pairs gives the rotation of io.streams.interpolate_quaternions (scipy's
    Slerp) to rounding, for random pairs, either sign of the second quaternion, and a pair of equal rotations."""
    from scipy.spatial.transform import Rotation

    from magkf.io.streams import interpolate_quaternions
    from magkf.live.source import slerp

    rng = np.random.default_rng(71)
    q0 = Rotation.random(200, random_state=rng).as_quat()[:, [3, 0, 1, 2]]
    q1 = Rotation.random(200, random_state=rng).as_quat()[:, [3, 0, 1, 2]]
    q1[::2] *= -1.0
    q1[-1] = q0[-1]
    fraction = rng.uniform(0.0, 1.0, 200)
    got = slerp(q0, q1, fraction)
    for k in range(200):
        want, _ = interpolate_quaternions([fraction[k]], [0.0, 1.0], np.vstack([q0[k], q1[k]]))
        assert min(np.abs(got[k] - want[0]).max(), np.abs(got[k] + want[0]).max()) < 1e-12

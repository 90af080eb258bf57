"""A canonical table as the MAVLink packets an ArduPilot or PX4 vehicle streams, for a telemetry log
(``magkf.io.tlog.write_tlog``) or a replay over a link (``magkf.live.replay``).

What each message means and how each firmware fills it is told in ``magkf.io.tlog``'s docstring, which this
module follows in reverse: the magnetometer as ``RAW_IMU`` (ArduPilot, the field after ``correct_field`` with the
``COMPASS_*`` parameters) or ``SCALED_IMU`` (PX4, ``sensor_mag`` before its calibration), ``ATTITUDE``,
``GPS_RAW_INT``, ``SYSTEM_TIME``, ``BATTERY_STATUS``, ``VFR_HUD``, ``HEARTBEAT``, ``PARAM_VALUE`` and
``AUTOPILOT_VERSION`` (https://mavlink.io/en/messages/common.html).

Clocks
    The vehicle's boot clock reads ``START_US`` at the table's first row and follows ``time`` to 1 us. With a
    reboot at ``reboot_at_s`` (seconds of the table after its first row) it starts again from ``REBOOT_START_US``
    at the first row at or after that time, as after a power cycle; the vehicle's sequence numbers start again
    from 0 (https://mavlink.io/en/guide/serialization.html: ``seq`` counts the sender's packets), it sends a
    ``HEARTBEAT`` and its parameters again at once, and its periodic streams start again from that row.
    ``SYSTEM_TIME`` maps each boot's clock to the right UNIX time (``time_unix_usec``, ``time_boot_ms``).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from ..conventions import ALT, HDOP, LAT, LON, MAG, PITCH, ROLL, VDOP, YAW, euler_to_quaternion, quaternion_to_euler
from ..errors import InputError
from .dataflash import NT_PER_MILLIGAUSS, _firmware_compass, _state_index, compass_correct
from .drivelog import table_to_write
from .streams import interpolate_quaternions
from .tlog import (
    AUTOPILOT_COMPONENT,
    MAGIC_V2,
    MAV_AUTOPILOT_INVALID,
    MAV_TYPE_GCS,
    UNKNOWN_U16,
    VEHICLE_OF_TYPE,
    correction_model,
    mavlink_dialect,
)

__all__ = [
    "AUTOPILOT_CODES",
    "GROUND_STATION",
    "REBOOT_START_US",
    "START_US",
    "VEHICLE",
    "VehiclePacket",
    "VehiclePackets",
    "param_value_message",
    "with_sequence",
]

#: Boot time (us) of the table's first row.
START_US = 10_000_000
#: Boot time (us) of the first row after a reboot: the firmware streams about 2 s after power-on.
REBOOT_START_US = 2_000_000
#: ``MAV_AUTOPILOT`` of each autopilot name.
AUTOPILOT_CODES = {"ardupilot": 3, "px4": 12}
#: ``HEARTBEAT`` of the vehicle: ``MAV_TYPE_QUADROTOR`` by default, ``base_mode`` 81 (custom mode, stabilise,
#: armed bits as ArduPilot reports a disarmed copter), ``MAV_STATE_STANDBY``, MAVLink 3.
VEHICLE_TYPE, BASE_MODE, SYSTEM_STATUS, MAVLINK_VERSION = 2, 81, 4, 3
#: ``GPS_FIX_TYPE_NO_FIX``: what a row without a position is sent with.
NO_FIX = 1
#: ``MAV_PARAM_TYPE`` of integer and floating-point parameters (``INT32``, ``REAL32``).
PARAM_INT32, PARAM_REAL32 = 6, 9
#: Ground station's system and component (``MAV_COMP_ID_MISSIONPLANNER``), for the ``HEARTBEAT`` a tlog holds.
GCS_SYSID, GCS_COMPID = 255, 190
#: The sources of packets: the vehicle and the ground station.
VEHICLE, GROUND_STATION = 0, 1
#: Parameters a replay announces for each autopilot when it takes them from a log (its compass's and orientation).
PARAM_PREFIXES = {"ardupilot": ("COMPASS_", "AHRS_ORIENTATION"), "px4": ("CAL_MAG", "SENS_BOARD")}


@dataclass(frozen=True, slots=True)
class VehiclePacket:
    """One packet as sent.

    Parameters
    ----------
    time_us : int
        UNIX time (us) at which the vehicle sends it (the table's time; it goes on across a reboot).
    boot_us : int
        The vehicle's boot clock (us) then.
    stamp_us : int
        The ground station's receipt stamp (UNIX us): ``time_us`` plus the link's latency.
    boot : int
        0 before the reboot, 1 after it.
    source : int
        ``VEHICLE`` (0) or ``GROUND_STATION`` (1, its ``HEARTBEAT`` in a telemetry log).
    name : str
        The message's name (``RAW_IMU``).
    data : bytes
        The whole packet, its sequence number that of its source counted in time order.
    row : int
        The table's row a magnetometer message carries (``VehiclePackets.magnetometer_message``), else -1.
    """

    time_us: int
    boot_us: int
    stamp_us: int
    boot: int
    source: int
    name: str
    data: bytes
    row: int = -1


def with_sequence(packet: bytes, seq: int) -> bytes:
    """``packet`` (a whole MAVLink 1 or 2 packet, unsigned) with sequence number ``seq`` (0..255) and its checksum
    computed again (CRC-16/MCRF4XX over the header after the start byte and the payload, then the message's
    ``CRC_EXTRA``; https://mavlink.io/en/guide/serialization.html)."""
    from pymavlink.generator.mavcrc import x25crc

    v2 = packet[0] == MAGIC_V2
    header, at = (10, 4) if v2 else (6, 2)
    end = header + packet[1]
    body = bytearray(packet[:end])
    body[at] = seq % 256
    msgid = body[7] | body[8] << 8 | body[9] << 16 if v2 else body[5]
    crc = x25crc(bytes(body[1:]))
    crc.accumulate(bytes([mavlink_dialect().mavlink_map[msgid].crc_extra]))
    return bytes(body) + struct.pack("<H", crc.crc) + packet[end + 2 :]


def param_value_message(name: str, value, count: int, index: int, autopilot: str):
    """``PARAM_VALUE`` of parameter ``name`` (``index`` of ``count``): an integer (``int``, not ``bool``) as
    ``MAV_PARAM_TYPE_INT32``, else ``REAL32``; PX4 sends an integer's bytes in the float field, ArduPilot the
    float of the integer (https://mavlink.io/en/services/parameter.html, "parameter encoding")."""
    integer = isinstance(value, (int, np.integer)) and not isinstance(value, bool)
    number = float(value)
    if integer and autopilot == "px4":
        number = struct.unpack("<f", struct.pack("<i", int(value)))[0]
    kind = PARAM_INT32 if integer else PARAM_REAL32
    return mavlink_dialect().MAVLink_param_value_message(name.encode(), number, kind, count, index)


class VehiclePackets:
    """The MAVLink packets of a vehicle streaming a canonical table, in the order sent (``packets``).

    Parameters
    ----------
    table : pandas.DataFrame
        N rows; ``time`` a column or the index (UNIX s), rows at 10 to 50 Hz as a magnetometer stream comes.
    autopilot : {"ardupilot", "px4"}
        The firmware whose messages are sent.
    params : dict, optional
        Parameter name -> value, announced with ``PARAM_VALUE`` before the first row (float32; PX4's integers by
        their bytes) and after a reboot.
    apply_params : bool
        ArduPilot: apply the ``COMPASS_*`` calibration of ``params`` to the magnetometer as ``correct_field``
        does (``compass_correct``; motor compensation ``COMPASS_MOT`` x ``throttle`` or ``current_a`` for
        ``COMPASS_MOTCT`` 1 or 2, before or after the soft-iron matrix as ``correction_model`` says for the
        ``firmware`` of the vehicle of ``vehicle_type``; below 4.0 there is no ``COMPASS_SCALE``). False: the
        table's field is sent as it is (it holds the calibrated field already). PX4's ``SCALED_IMU`` is never
        calibrated.
    firmware : str, optional
        ``"4.5.0"`` (or ``"4.5"``): an ``AUTOPILOT_VERSION`` with that flight software version (release type 255,
        official) before the first row and after a reboot.
    attitude_per_row : int
        ``ATTITUDE`` messages per row (slerp between rows), radians as float32.
    gps_period_s, aux_period_s : float
        Periods (s) of ``GPS_RAW_INT``, and of ``BATTERY_STATUS`` (``current_a``) and ``VFR_HUD`` (``throttle``).
    system_time : bool
        Send ``SYSTEM_TIME`` at 1 Hz.
    latency_s : float
        The link's latency (s): receipt stamp less sending time.
    mavlink1 : bool
        Pack MAVLink 1 packets (``alt_ellipsoid``, an extension field, then 0).
    sysid : int
        The vehicle's system id (component 1).
    ground_station : bool
        Add the ground station's ``HEARTBEAT`` at 1 Hz (system 255, component 190), as a telemetry log holds it.
    reboot_at_s : float, optional
        Seconds after the first row at which the vehicle reboots (see the module docstring); inside the table.
    source : str
        Names the table in errors.
    vehicle_type : int
        ``HEARTBEAT.type`` (``MAV_TYPE``; default 2, a quadrotor): a receiver names the firmware by it (1 a plane,
        10 a rover, 12 a submarine).

    Raises
    ------
    InputError
        An unknown autopilot, a firmware version not of the form 4.5.0, a reboot outside the table, a field that
        does not fit the int16 ``xmag`` field (naming the row and column).

    Notes
    -----
    The magnetometer: ArduPilot ``RAW_IMU`` (``time_usec`` boot us), PX4 ``SCALED_IMU`` (``time_boot_ms``), both
    in mG truncated to int16, ``temperature`` from ``temp_c`` (cdegC). ``GPS_RAW_INT``: ``fix_type`` (the column,
    else 3 with a position; at most 1, no fix, without one), ``lat, lon`` (1e-7 deg), ``alt`` and
    ``alt_ellipsoid`` (mm, both from ``alt``), ``eph/epv`` from ``hdop/vdop`` (65535 where NaN), ``time_usec``
    UNIX us for ArduPilot, boot us for PX4. ``HEARTBEAT`` at 1 Hz, of ``vehicle_type``.
    """

    def __init__(
        self,
        table,
        autopilot: str = "ardupilot",
        params: dict | None = None,
        *,
        apply_params: bool = True,
        firmware: str | None = None,
        attitude_per_row: int = 2,
        gps_period_s: float = 0.2,
        aux_period_s: float = 0.5,
        system_time: bool = True,
        latency_s: float = 0.02,
        mavlink1: bool = False,
        sysid: int = 1,
        ground_station: bool = True,
        reboot_at_s: float | None = None,
        source: str = "table",
        vehicle_type: int = VEHICLE_TYPE,
    ):
        if autopilot not in AUTOPILOT_CODES:
            raise InputError(f"unknown autopilot {autopilot!r}; use ardupilot or px4", source)
        frame, t = table_to_write(table, source)
        self.dialect = mavlink_dialect()
        self.autopilot, self.mavlink1, self.sysid, self.source = autopilot, mavlink1, sysid, source
        self.vehicle_type = int(vehicle_type)
        self.params = dict(params or {})
        self.firmware = firmware
        self._version = _version_numbers(firmware, source) if firmware is not None else None
        self.unix0_us = int(round(float(t[0]) * 1e6))
        #: Log time (us) of each row: the boot clock of a vehicle that does not reboot.
        self.log_us = START_US + np.rint((t - t[0]) * 1e6).astype(np.int64)
        self.reboot_log_us = self._reboot_row(reboot_at_s)
        self.latency_us = int(round(latency_s * 1e6))
        self._packer = self.dialect.MAVLink(None, srcSystem=sysid, srcComponent=AUTOPILOT_COMPONENT)
        self._gcs_packer = self.dialect.MAVLink(None, srcSystem=GCS_SYSID, srcComponent=GCS_COMPID)
        self._records: list[tuple[int, int, int, str, bytes, int]] = []
        self._frame = frame
        #: Whether the magnetometer carries the ``COMPASS_*`` calibration of the parameters (ArduPilot, applied).
        self.applies_params = autopilot == "ardupilot" and apply_params
        self._heartbeats(ground_station)
        self._announce(self._start_rows())
        self._magnetometer(frame)
        self._attitude(frame, attitude_per_row)
        self._gnss(frame, gps_period_s)
        if system_time:
            self._system_time()
        self._auxiliary(frame, aux_period_s)
        self.packets = self._sequenced()

    def __len__(self) -> int:
        return len(self.packets)

    def __iter__(self):
        return iter(self.packets)

    # -------------------------------------------------------------- clocks
    def _reboot_row(self, reboot_at_s: float | None) -> int | None:
        """Log time (us) of the first row at or after ``reboot_at_s``; None without a reboot."""
        if reboot_at_s is None:
            return None
        finite = bool(np.isfinite(reboot_at_s))
        after = np.flatnonzero(self.log_us >= START_US + int(round(float(reboot_at_s) * 1e6))) if finite else []
        if not finite or reboot_at_s <= 0 or not len(after) or after[0] == 0:
            span = (self.log_us[-1] - START_US) * 1e-6
            raise InputError(
                f"reboot at {reboot_at_s:g} s is not inside the table (0 to {span:.6g} s after its first row): give a "
                "time between its first and last rows",
                self.source,
            )
        return int(self.log_us[after[0]])

    def boot_of(self, log_us):
        """The vehicle's boot clock (us, int64) at log times ``log_us`` (us)."""
        log_us = np.asarray(log_us, np.int64)
        if self.reboot_log_us is None:
            return log_us
        return np.where(log_us < self.reboot_log_us, log_us, REBOOT_START_US + log_us - self.reboot_log_us)

    def _boot_index(self, log_us: int) -> int:
        return int(self.reboot_log_us is not None and log_us >= self.reboot_log_us)

    def _unix_us(self, log_us: int) -> int:
        return self.unix0_us + int(log_us) - START_US

    def _start_rows(self) -> list[int]:
        """Log times (us) at which the vehicle announces itself: before the first row, and at the reboot."""
        starts = [int(self.log_us[0]) - 500_000]
        if self.reboot_log_us is not None:
            starts.append(self.reboot_log_us)
        return starts

    def _every(self, period_s: float) -> np.ndarray:
        """Indices of the rows at which a stream of period ``period_s`` sends (the first row of each period of
        each boot)."""
        boot = self.boot_of(self.log_us)
        after = self.log_us >= self.reboot_log_us if self.reboot_log_us is not None else np.zeros(len(boot), bool)
        first = np.where(after, REBOOT_START_US, boot[0])
        slot = (boot - first) // int(round(period_s * 1e6)) + after * (1 << 40)
        return np.flatnonzero(np.concatenate(([True], np.diff(slot) > 0)))

    # -------------------------------------------------------------- packets
    def _send(self, log_us: int, message, source: int = VEHICLE, row: int = -1) -> None:
        packer = self._packer if source == VEHICLE else self._gcs_packer
        packet = message.pack(packer, force_mavlink1=self.mavlink1)
        self._records.append((int(log_us), len(self._records), source, message.get_type(), packet, row))

    def _sequenced(self) -> list[VehiclePacket]:
        """The packets in time order (the order of sending at equal times), each source's sequence numbers
        counted in that order, the vehicle's from 0 again at the reboot."""
        self._records.sort(key=lambda r: (r[0], r[1]))
        seq, boot_of_seq, out = [0, 0], -1, []
        for log_us, _, source, name, packet, row in self._records:
            boot = self._boot_index(log_us)
            if source == VEHICLE and boot != boot_of_seq:
                seq[VEHICLE], boot_of_seq = 0, boot
            data = with_sequence(packet, seq[source])
            seq[source] = (seq[source] + 1) % 256
            time_us = self._unix_us(log_us)
            boot_us = int(self.boot_of(log_us))
            out.append(VehiclePacket(time_us, boot_us, time_us + self.latency_us, boot, source, name, data, row))
        self._records = []
        return out

    def _heartbeats(self, ground_station: bool) -> None:
        code = AUTOPILOT_CODES[self.autopilot]
        rows = [int(self.log_us[i]) for i in self._every(1.0)]
        for at in sorted(set(rows) | set(self._start_rows()[1:])):
            message = self.dialect.MAVLink_heartbeat_message(
                self.vehicle_type, code, BASE_MODE, 0, SYSTEM_STATUS, MAVLINK_VERSION
            )
            self._send(at, message)
            if ground_station and at in rows:
                gcs = self.dialect.MAVLink_heartbeat_message(
                    MAV_TYPE_GCS, MAV_AUTOPILOT_INVALID, 0, 0, 0, MAVLINK_VERSION
                )
                self._send(at, gcs, GROUND_STATION)

    def _announce(self, starts: list[int]) -> None:
        """``AUTOPILOT_VERSION`` (with ``firmware``) and every parameter at each of ``starts`` (log us): before
        the first row (the version 100 ms before the parameters), and at the reboot."""
        for k, at in enumerate(starts):
            if self._version is not None:
                self._send(at - (100_000 if k == 0 else 0), self.version_message())
            for index, (key, value) in enumerate(self.params.items()):
                self._send(at, param_value_message(key, value, len(self.params), index, self.autopilot))

    def version_message(self):
        """``AUTOPILOT_VERSION`` of ``firmware`` (``flight_sw_version``: major, minor, patch in bytes 4 to 2, release
        type 255 official in the lowest), or None without one."""
        if self._version is None:
            return None
        major, minor, patch = self._version
        flight_sw = major << 24 | minor << 16 | patch << 8 | 255
        zeros = [0] * 8
        return self.dialect.MAVLink_autopilot_version_message(0, flight_sw, 0, 0, 0, zeros, zeros, zeros, 0, 0, 0)

    def _magnetometer(self, frame) -> None:
        sent = self.sent_field()
        rows = np.all(np.isfinite(sent), axis=1)
        too_large = np.argwhere(rows[:, None] & (np.abs(sent) > np.iinfo(np.int16).max))
        if too_large.size:
            i, axis = too_large[0]
            raise InputError(
                f"field {sent[i, axis]:g} mG does not fit the int16 xmag field", self.source, int(i) + 1, MAG[axis]
            )
        temp = _column(frame, "temp_c")
        self._temp_cdeg = np.where(np.isfinite(temp), np.rint(temp * 100.0), 0).astype(int)
        for i in np.flatnonzero(rows):
            self._send(int(self.log_us[i]), self.magnetometer_message(i, sent[i]), row=int(i))

    def sent_field(self, params: dict | None = None) -> np.ndarray:
        """(N, 3) the field the magnetometer message carries at each row (mG, truncated towards zero as the int16
        field is filled; NaN at rows without a reading): the table's, with the ``COMPASS_*`` calibration of
        ``params`` (default the vehicle's) applied where ``applies_params``."""
        mag_mg = np.column_stack([_column(self._frame, c) for c in MAG]) / NT_PER_MILLIGAUSS
        rows = np.all(np.isfinite(mag_mg), axis=1)
        if self.applies_params:
            mag_mg[rows] = self._corrected(mag_mg[rows], self.params if params is None else params, rows)
        return np.trunc(mag_mg)

    def magnetometer_message(self, row: int, field_mg):
        """The magnetometer message of table row ``row`` carrying ``field_mg`` (3,) (int16 mG): ArduPilot
        ``RAW_IMU`` (``time_usec`` boot us), PX4 ``SCALED_IMU`` (``time_boot_ms``); ``temperature`` from
        ``temp_c``."""
        b, (x, y, z) = int(self.boot_of(self.log_us[row])), (int(v) for v in field_mg)
        temp = int(self._temp_cdeg[row])
        if self.autopilot == "ardupilot":
            return self.dialect.MAVLink_raw_imu_message(b, 0, 0, -1000, 0, 0, 0, x, y, z, 0, temp)
        return self.dialect.MAVLink_scaled_imu_message(b // 1000, 0, 0, -1000, 0, 0, 0, x, y, z, temp)

    def _corrected(self, raw_mg: np.ndarray, params: dict, rows: np.ndarray) -> np.ndarray:
        """ArduPilot's ``correct_field`` of ``params`` on ``raw_mg`` (M, 3) mG at ``rows``."""
        offsets, diagonals, offdiagonals, scale = _firmware_compass(params)
        motor = _motor_sent(params, self._frame)[rows]
        version = ".".join(map(str, self._version)) if self._version is not None else None
        kind = VEHICLE_OF_TYPE.get(self.vehicle_type, "Copter")  # the vehicle a receiver names by the HEARTBEAT
        first, scale_applies = correction_model(f"Ardu{kind} V{version}" if version else None)
        return compass_correct(
            raw_mg, offsets, diagonals, offdiagonals, scale if scale_applies else 1.0, motor, motor_first=first
        )

    def _attitude(self, frame, per_row: int) -> None:
        angles = [_column(frame, c) for c in (YAW, PITCH, ROLL)]
        rows = np.flatnonzero(np.all(np.isfinite(angles), axis=0))
        if not len(rows):
            return
        q = euler_to_quaternion(*(a[rows] for a in angles))
        t_rows = self.log_us[rows].astype(float)
        steps = np.arange(per_row) / per_row
        t_send = (t_rows[:-1, None] + np.diff(t_rows)[:, None] * steps).ravel()
        t_send = np.rint(np.append(t_send, t_rows[-1]))
        q_send, valid = interpolate_quaternions(t_send, t_rows, q)
        yaw, pitch, roll = quaternion_to_euler(q_send[valid])
        yaw = (yaw + 180.0) % 360.0 - 180.0
        at = t_send[valid].astype(np.int64)
        for L, b, r, p, y in zip(at, self.boot_of(at), np.radians(roll), np.radians(pitch), np.radians(yaw)):
            self._send(int(L), self.dialect.MAVLink_attitude_message(int(b) // 1000, r, p, y, 0.0, 0.0, 0.0))

    def _gnss(self, frame, period_s: float) -> None:
        lat, lon, alt = _column(frame, LAT), _column(frame, LON), _column(frame, ALT)
        if not np.isfinite(lat).any() and "fix_type" not in frame:
            return
        hdop, vdop, fix_col = _column(frame, HDOP), _column(frame, VDOP), _column(frame, "fix_type")
        for i in self._every(period_s):
            L = int(self.log_us[i])
            has = bool(np.isfinite(lat[i]) and np.isfinite(lon[i]))
            fix = int(fix_col[i]) if np.isfinite(fix_col[i]) else (3 if has else 1)
            if not has:  # no position: no fix, whatever the column says (a fix at 0 N 0 E would be taken)
                fix = min(fix, NO_FIX)
            time_usec = self._unix_us(L) if self.autopilot == "ardupilot" else int(self.boot_of(L))
            alt_mm = int(round(alt[i] * 1000.0)) if has and np.isfinite(alt[i]) else 0
            ellipsoid_mm = 0 if self.mavlink1 else alt_mm  # a MAVLink 1 sender drops the extension fields
            message = self.dialect.MAVLink_gps_raw_int_message(
                time_usec,
                fix,
                int(round(lat[i] * 1e7)) if has else 0,
                int(round(lon[i] * 1e7)) if has else 0,
                alt_mm,
                _dop_counts(hdop[i]),
                _dop_counts(vdop[i]),
                0,
                0,
                12,
                ellipsoid_mm,
            )
            self._send(L, message)

    def _system_time(self) -> None:
        for i in self._every(1.0):
            L = int(self.log_us[i])
            b = int(self.boot_of(L))
            self._send(L, self.dialect.MAVLink_system_time_message(self._unix_us(L), b // 1000))

    def _auxiliary(self, frame, period_s: float) -> None:
        current, throttle = _column(frame, "current_a"), _column(frame, "throttle")
        for i in self._every(period_s):
            L = int(self.log_us[i])
            if np.isfinite(current).any():
                centi = int(round(current[i] * 100.0)) if np.isfinite(current[i]) else -1
                cells = [UNKNOWN_U16] * 10
                self._send(L, self.dialect.MAVLink_battery_status_message(0, 0, 0, 32767, cells, centi, -1, -1, -1))
            if np.isfinite(throttle).any() and np.isfinite(throttle[i]):
                self._send(
                    L, self.dialect.MAVLink_vfr_hud_message(0.0, 0.0, 0, int(round(throttle[i] * 100.0)), 0.0, 0.0)
                )


def _version_numbers(firmware: str, source: str) -> tuple[int, int, int]:
    """``(major, minor, patch)`` of ``"4.5.0"`` or ``"4.5"``; InputError otherwise."""
    parts = str(firmware).strip().split(".")
    if not 2 <= len(parts) <= 3 or not all(p.isdigit() and int(p) < 256 for p in parts):
        raise InputError(f"firmware {firmware!r} is not a version such as 4.5.0 or 1.15", source)
    numbers = [int(p) for p in parts] + [0] * (3 - len(parts))
    return numbers[0], numbers[1], numbers[2]


def _motor_sent(params: dict, frame) -> np.ndarray:
    """ArduPilot's motor compensation (N, 3) mG at the rows of ``frame``: ``COMPASS_MOT`` (of the parameter set
    of priority 0, as float32) times ``throttle`` (``COMPASS_MOTCT`` 1) or ``current_a`` (2), else zero."""
    channel = {1: "throttle", 2: "current_a"}.get(int(params.get("COMPASS_MOTCT", 0)))
    if channel is None:
        return np.zeros((len(frame), 3))
    k = _state_index({key: (np.zeros(1), np.array([float(v)])) for key, v in params.items()}, 0)
    suffix = ("", "2", "3")[k] if k < 3 else ""
    mot = np.array([float(np.float32(params.get(f"COMPASS_MOT{suffix}_{a}", 0.0))) for a in "XYZ"])
    return np.nan_to_num(_column(frame, channel))[:, None] * mot


def _column(frame, column: str) -> np.ndarray:
    return frame[column].to_numpy(float) if column in frame else np.full(len(frame), np.nan)


def _dop_counts(dop: float) -> int:
    return int(min(round(dop * 100.0), UNKNOWN_U16 - 1)) if np.isfinite(dop) else UNKNOWN_U16

"""MAVLink telemetry logs (``.tlog``) read into the canonical drive log, and written from one.

Format
    A telemetry log is what a ground station (Mission Planner, QGroundControl, MAVProxy) received over its
    MAVLink link, packet by packet: each packet is preceded by an 8-byte big-endian unsigned integer, the
    ground station's UNIX time of receipt in microseconds (MAVProxy keeps its link number in the two lowest
    bits). A packet starts with ``0xFE`` (MAVLink 1: 6 header bytes, payload, 2 checksum bytes) or ``0xFD``
    (MAVLink 2: 10 header bytes, payload, 2 checksum bytes and 13 signature bytes when the first
    incompatibility flag is set); https://mavlink.io/en/guide/serialization.html. The file has no header of
    its own. magkf walks these records itself (so that it can decode only the messages it needs and find
    its way past damage) and has pymavlink (``pymavlink.dialects.v20.ardupilotmega``) check each packet's
    checksum and decode it. Message and field meanings: the MAVLink common message set
    (https://mavlink.io/en/messages/common.html).

Which vehicle
    A log can hold several systems (``sysid``) and components (``compid``): the ground station's own
    ``HEARTBEAT`` (type ``MAV_TYPE_GCS``), cameras, gimbals, other vehicles. The reader takes the autopilot
    (``compid`` 1) of the first vehicle that sends a ``HEARTBEAT``; ``HEARTBEAT.autopilot`` says whether it
    runs ArduPilot (``MAV_AUTOPILOT_ARDUPILOTMEGA`` = 3) or PX4 (``MAV_AUTOPILOT_PX4`` = 12).

Magnetometer messages (``xmag, ymag, zmag``)
    ========  ================  ===========================================  ==========================
    instance  message           ArduPilot                                    PX4
    ========  ================  ===========================================  ==========================
    0         ``RAW_IMU``       ``Compass::get_field(0)``: calibrated, mG    not sent
    0         ``SCALED_IMU``    the same field, ms time stamps               ``sensor_mag`` 0, mG: raw
    1         ``SCALED_IMU2``   ``get_field(1)``: calibrated, mG             ``sensor_mag`` 1, mG: raw
    2         ``SCALED_IMU3``   ``get_field(2)``: calibrated, mG             ``sensor_mag`` 2, mG: raw
    3         ``HIGHRES_IMU``   ``get_field()`` x 1000 (see below)           ``vehicle_magnetometer``
                                                                             less the EKF's bias, G:
                                                                             calibrated
    ========  ================  ===========================================  ==========================

    ArduPilot (``libraries/GCS_MAVLink/GCS_Common.cpp``, ``GCS_MAVLINK::send_raw_imu`` and
    ``send_scaled_imu``) sends ``Compass::get_field(i)``, the field after ``correct_field`` (offsets, scale,
    soft-iron matrix and motor compensation, in milligauss), despite the message's name; since 4.0 ``i`` is
    a priority (``_get_state(Priority(i))``), so the parameter set is found through ``COMPASS_PRIOn_ID`` as
    for DataFlash logs. The float is passed to the message's ``int16_t`` field, i.e. truncated towards zero.
    ``send_highres_imu`` multiplies ``get_field()`` (mG) by 1000 although its comment says gauss; the unit
    of ``HIGHRES_IMU`` is therefore taken from the magnitudes (about 0.5 G, or 5e5 of those units).
    PX4 (``src/modules/mavlink/streams/SCALED_IMU.hpp``, ``SCALED_IMU2.hpp``, ``SCALED_IMU3.hpp``) sends
    ``sensor_mag`` instance 0, 1, 2 times 1000 (G to mG, truncated to int16): the driver's reading before
    the ``CAL_MAGn`` calibration (PX4 v1.12 on; up to v1.11 the driver applied the offsets and scales
    itself, see ``magkf.io.ulog``); ``HIGHRES_IMU.hpp`` sends ``vehicle_magnetometer`` (calibrated and
    rotated into the body frame) less the estimator's magnetometer bias, in gauss.

    With ``raw=True`` an ArduPilot field is uncorrected with the ``COMPASS_*`` values the log's own
    ``PARAM_VALUE`` messages give (``magkf.io.dataflash.compass_uncorrect``; the value in effect at each
    epoch); motor compensation is undone where ``COMPASS_MOTCT`` is 1 (throttle) or 2 (current) and that
    stream is in the log (its accuracy limited by that stream's rate, 1 to 2 Hz in telemetry, noted when its
    interval exceeds ``max_gap_s``). The model undone is that of the firmware (the ``STATUSTEXT`` banner,
    ``APM:Copter V3.5.7 (b11c6af3)``, else ``AUTOPILOT_VERSION`` with the vehicle of ``HEARTBEAT.type``), as
    ``magkf.io.dataflash`` models it: Copter 3.3 to 3.5 (and the other vehicles' releases of those years) added
    the motor compensation before the soft-iron matrix, and there is no ``COMPASS_SCALE`` before 4.0; 4.x is
    assumed, and noted, where the log names no version. A field whose calibration cannot be undone (no parameters; PX4's
    ``HIGHRES_IMU``) is read as it is, and the provenance says so (``magnetometer.calibrated``).

Time
    ``time_usec`` fields are microseconds since boot, or UNIX time when larger than ``UNIX_MIN_US`` (the
    MAVLink convention: "the receiving end can infer the format by checking the magnitude"; ArduPilot's
    ``GPS_RAW_INT`` is UNIX time); ``time_boot_ms`` fields are milliseconds since boot (the autopilot's
    clock truncated to ms). UTC = boot time + the median over ``SYSTEM_TIME`` messages of
    ``time_unix_usec - time_boot_ms`` (messages with a UNIX time). Without ``SYSTEM_TIME`` the ground
    station's receipt stamps are used instead: UTC = boot time + the median of ``receipt - boot time`` over
    the vehicle's time-stamped messages, which is the ground station's clock and includes the link's
    latency. Messages without a time field (``BATTERY_STATUS``, ``SYS_STATUS``, ``VFR_HUD``,
    ``PARAM_VALUE``) are placed at their receipt time less that median. A boot time that falls back while
    receipt time less boot time jumps by more than ``REBOOT_S`` marks a reboot; the boot with the most
    magnetometer samples is read. Parameters are stored on the vehicle and persist across a reboot: the value
    in force at an epoch is the last ``PARAM_VALUE`` received (by receipt time) before it from that boot or an
    earlier one, else the first received later in that boot; the firmware banner and ``AUTOPILOT_VERSION`` of
    an earlier boot name the firmware where the boot read does not.

Streams (interpolated onto the magnetometer's epochs with ``magkf.io.streams``)
    ``ATTITUDE`` ``roll, pitch, yaw`` (rad), else ``ATTITUDE_QUATERNION`` ``q1..q4`` (scalar first),
    body FRD in NED, across gaps up to ``max_gap_s``. The slower streams (GNSS, battery, throttle; 1 to 5 Hz
    in telemetry) across gaps up to ``SLOW_GAP_INTERVALS`` of their median intervals where that is longer.
    ``GPS_RAW_INT``: ``fix_type`` (``GPS_FIX_TYPE``: 3 = 3-D), ``lat, lon`` (1e-7 deg),
    ``alt`` (mm above MSL), ``alt_ellipsoid`` (mm above WGS-84; MAVLink 2 extension, 0 when not given),
    ``eph, epv`` (HDOP and VDOP x 100, 65535 unknown). ``BATTERY_STATUS.current_battery`` (battery 0) else
    ``SYS_STATUS.current_battery`` (cA, -1 unknown); ``VFR_HUD.throttle`` (percent); the magnetometer
    message's own ``temperature`` (cdegC, the IMU's; 0 = not given) else ``SCALED_PRESSURE.temperature``.

Writing
    ``write_tlog`` turns a canonical table (a simulation) into a telemetry log as an ArduPilot or PX4
    vehicle would stream it, for tests: see its docstring. The packets are ``magkf.io.mavlink_packets``'s, which
    ``magkf.live.replay`` also sends over a link.
"""

from __future__ import annotations

import re
import struct
from collections import deque
from typing import TYPE_CHECKING

import numpy as np

from ..conventions import (
    ALT,
    HDOP,
    LAT,
    LON,
    MAG,
    NT_PER_UNIT,
    PITCH,
    ROLL,
    VDOP,
    YAW,
    euler_to_quaternion,
    quaternion_to_euler,
)
from ..errors import InputError
from .dataflash import (
    _CAL_DEFAULTS,
    _CAL_PARAMS,
    NT_PER_MILLIGAUSS,
    _effective_scale,
    _motor_first,
    _param_at,
    _param_name,
    _state_index,
    _untruncate,
    _version,
    compass_uncorrect,
    unmatched_priority,
)
from .drivelog import AutopilotLog
from .streams import bracket, interpolate_linear, interpolate_quaternions, slow_gap, time_order

if TYPE_CHECKING:
    import pandas as pd

__all__ = [
    "STORAGE_SIGMA_NT",
    "TelemetryLogReader",
    "boot_time_us",
    "correction_model",
    "highres_unit",
    "is_calibrated",
    "magnetometer_instances",
    "mavlink_dialect",
    "not_calibrated",
    "param_value",
    "read_tlog",
    "uncorrect_ardupilot",
    "why_not_undone",
    "write_tlog",
]

MAGIC_V1, MAGIC_V2 = 0xFE, 0xFD
STAMP_BYTES = 8
#: ``MAV_AUTOPILOT`` codes and the names magkf gives them (``magkf export --to``).
AUTOPILOTS = {3: "ardupilot", 12: "px4"}
MAV_AUTOPILOT_INVALID = 8
MAV_TYPE_GCS = 6
AUTOPILOT_COMPONENT = 1
#: A ``time_usec`` above this (2001-09-09) is UNIX time, below it time since boot.
UNIX_MIN_US = 10**15
UNKNOWN_U16 = 65_535
#: A packet identical to one received this recently (us) is the same packet logged twice.
DUPLICATE_WINDOW_US = 2_000_000
#: Where the height comes from when ``GPS_RAW_INT`` sends ``alt_ellipsoid``.
ELLIPSOID_HEIGHT = "GPS_RAW_INT.alt_ellipsoid (mm above WGS-84; alt, above MSL, where it is 0)"
#: A boot time that falls back while the receipt time less the boot time jumps by more than this (s) is a reboot.
REBOOT_S = 5.0
#: The messages whose boot time is the vehicle's clock when it sent them, which alone can show a reboot: others
#: carry the time of an earlier event (``GPS_RAW_INT.time_usec`` the last fix, stale by seconds when the fix is
#: lost; ``HOME_POSITION`` and ``GPS_GLOBAL_ORIGIN`` when they were set).
CLOCK_MESSAGES = frozenset(
    {
        "SYSTEM_TIME",
        "ATTITUDE",
        "ATTITUDE_QUATERNION",
        "RAW_IMU",
        "SCALED_IMU",
        "SCALED_IMU2",
        "SCALED_IMU3",
        "HIGHRES_IMU",
    }
)
#: The messages of earlier boots that still hold after a reboot: the parameters (stored on the vehicle) and the
#: firmware's identity (``STATUSTEXT`` banner, ``AUTOPILOT_VERSION``), which the vehicle may not send again.
PERSISTING = frozenset({"PARAM_VALUE", "STATUSTEXT", "AUTOPILOT_VERSION"})
#: An attitude stream slower than ``max_gap_s`` (telemetry at 1 to 4 Hz) is interpolated across gaps up to this many
#: of its median intervals: one sample lost between two is bridged, a longer loss is not.
SLOW_ATTITUDE_INTERVALS = 2.5
#: Keys of the auxiliary channels' dict (``_auxiliary``) that are not channels: their streams' median intervals (s)
#: and ``max_gap_s``.
INTERVALS, MAX_GAP = "_intervals_s", "_max_gap_s"
#: Receipt stamps further than this (us) from the last good one are not a record's stamp (resynchronising).
STAMP_JUMP_US = 86_400 * 10**6
#: Magnetometer messages: (instance, message, unit), in the order a default is chosen.
MAG_MESSAGES = (
    (0, "RAW_IMU", "mG"),
    (0, "SCALED_IMU", "mG"),
    (1, "SCALED_IMU2", "mG"),
    (2, "SCALED_IMU3", "mG"),
    (3, "HIGHRES_IMU", "G"),
)
MAG_NAMES = tuple(m for _, m, _ in MAG_MESSAGES)
WANTED = (
    "HEARTBEAT",
    "SYSTEM_TIME",
    "PARAM_VALUE",
    "ATTITUDE",
    "ATTITUDE_QUATERNION",
    "GPS_RAW_INT",
    "BATTERY_STATUS",
    "SYS_STATUS",
    "VFR_HUD",
    "SCALED_PRESSURE",
    "AUTOPILOT_VERSION",
    "STATUSTEXT",
    *MAG_NAMES,
)
#: Storage error (nT, per axis, standard deviation) of the magnetometer as a tlog holds it: the int16 mG
#: field truncated and centred by the reader is uniform over 1 mG = 100 nT (100 / sqrt(12)), combined with
#: the attitude's float32 radians (a rounding of 2**-22 rad at most near pi, uniform, times the largest
#: Earth field, 66 000 nT), which is negligible beside it.
STORAGE_SIGMA_NT = float(np.hypot(100.0 / np.sqrt(12.0), 2.0**-22 / np.sqrt(12.0) * 66_000.0))


# ------------------------------------------------------------------ records and packets
def mavlink_dialect():
    """pymavlink's ArduPilot dialect (``ardupilotmega``: the common message set and ArduPilot's own), imported on
    first use."""
    from pymavlink.dialects.v20 import ardupilotmega

    return ardupilotmega


_dialect = mavlink_dialect


def _packet_length(data: bytes, at: int) -> int:
    """Length (bytes) of the MAVLink packet starting at ``data[at]``, 0 if no packet starts there."""
    if at + 3 > len(data):
        return 0
    if data[at] == MAGIC_V1:
        return 8 + data[at + 1]
    if data[at] == MAGIC_V2:
        return 12 + data[at + 1] + (13 if data[at + 2] & 1 else 0)
    return 0


#: What became of a record's packet (``_Records._take``).
DECODED, UNCHECKED, BAD, UNKNOWN = 1, 0, -1, -2


def _header(packet: bytes) -> tuple[int, int, int]:
    """``(msgid, sysid, compid)`` of a whole packet."""
    if packet[0] == MAGIC_V1:
        return packet[5], packet[3], packet[4]
    return packet[7] | packet[8] << 8 | packet[9] << 16, packet[5], packet[6]


class _Records:
    """The wanted packets of a telemetry log, decoded: ``messages`` is a list of ``(receipt_us, msg)`` in file
    order; ``skipped`` bytes that were no record, ``bad`` packets that failed their checksum, ``duplicates``
    packets logged twice, ``cut`` True when the last record runs past the end of the file."""

    def __init__(self, path):
        self.path = str(path)
        try:
            with open(path, "rb") as f:
                self.data = f.read()
        except OSError as exc:
            raise InputError(f"cannot read the file ({exc.strerror})", self.path) from None
        dialect = _dialect()
        self.parser = dialect.MAVLink(None)
        self.wanted = {cls.msgname: i for i, cls in dialect.mavlink_map.items() if cls.msgname in WANTED}
        self.wanted_ids = frozenset(self.wanted.values())
        self.known_ids = frozenset(dialect.mavlink_map)
        self.messages: list = []
        self.skipped = self.bad = self.duplicates = self.packets = self.decoded = 0
        self.cut = False
        self._walk()

    def _walk(self) -> None:
        data, pos, last = self.data, 0, None
        recent: deque = deque()
        seen: dict = {}
        while pos + STAMP_BYTES < len(data):
            length = _packet_length(data, pos + STAMP_BYTES)
            stamp = int.from_bytes(data[pos : pos + STAMP_BYTES], "big")
            end = pos + STAMP_BYTES + length
            plausible = last is None or abs(stamp - last) <= STAMP_JUMP_US
            if not length or not plausible:
                pos = self._resync(pos, last)
                continue
            if end > len(data):
                self.cut = True
                break
            packet = data[pos + STAMP_BYTES : end]
            outcome = self._take(packet, stamp, recent, seen)
            if outcome >= UNCHECKED:
                last = stamp if outcome == DECODED else last  # only a checked packet's stamp guides resynchronising
                pos = end
            elif _packet_length(data, end + STAMP_BYTES):
                self.skipped += (end - pos) if outcome == UNKNOWN else 0
                pos = end  # a damaged or unknown packet in its place: the next record follows it
            else:
                pos = self._resync(pos, last)

    def _resync(self, pos: int, last) -> int:
        """The next position after ``pos`` where a record could start (a start byte after 8 bytes); the bytes
        passed over are counted in ``skipped``."""
        data, start = self.data, pos + 1 + STAMP_BYTES
        while start < len(data):
            found = [i for i in (data.find(b"\xfe", start), data.find(b"\xfd", start)) if i >= 0]
            if not found:
                break
            at = min(found) - STAMP_BYTES
            stamp = int.from_bytes(data[at : at + STAMP_BYTES], "big")
            if last is None or abs(stamp - last) <= STAMP_JUMP_US:
                self.skipped += at - pos
                return at
            start = at + STAMP_BYTES + 1
        self.skipped += len(data) - pos
        return len(data)

    def _take(self, packet: bytes, stamp: int, recent: deque, seen: dict) -> int:
        """Decode ``packet`` if it is of a wanted type and not a duplicate: ``DECODED`` (its checksum checked),
        ``UNCHECKED`` (a known message magkf does not read), ``BAD`` (failed its checksum) or ``UNKNOWN`` (no
        message of the dialect: damage, or another dialect's message)."""
        msgid = _header(packet)[0]
        if msgid not in self.known_ids:
            return UNKNOWN
        if msgid not in self.wanted_ids:
            self.packets += 1
            return UNCHECKED
        try:
            msg = self.parser.decode(bytearray(packet))
        except Exception:  # noqa: BLE001 - pymavlink raises MAVError, struct.error or others on a bad packet
            self.bad += 1
            return BAD
        self.packets += 1
        self.decoded += 1
        while recent and recent[0][0] < stamp - DUPLICATE_WINDOW_US:
            seen.pop(recent.popleft()[1], None)
        if packet in seen:
            self.duplicates += 1
            return DECODED
        seen[packet] = stamp
        recent.append((stamp, packet))
        self.messages.append((stamp, msg))
        return DECODED


# ------------------------------------------------------------------ the vehicle's streams
def is_autopilot_heartbeat(msg) -> bool:
    """Whether ``msg`` is a vehicle's autopilot's ``HEARTBEAT``: of component 1, neither a ground station's
    (``MAV_TYPE_GCS``) nor one of no autopilot (``MAV_AUTOPILOT_INVALID``)."""
    return (
        msg.get_type() == "HEARTBEAT"
        and msg.get_srcComponent() == AUTOPILOT_COMPONENT
        and msg.type != MAV_TYPE_GCS
        and msg.autopilot != MAV_AUTOPILOT_INVALID
    )


def _choose_vehicle(messages: list, notes: list) -> tuple[int, int, int | None]:
    """``(sysid, compid, MAV_AUTOPILOT code or None)`` of the first vehicle's autopilot: the first
    ``HEARTBEAT`` of component 1 that is not a ground station, else the source of the first magnetometer
    message; other sources but ground stations are noted."""
    chosen = next(
        ((m.get_srcSystem(), AUTOPILOT_COMPONENT, int(m.autopilot)) for _, m in messages if is_autopilot_heartbeat(m)),
        None,
    )
    if chosen is None:
        first = next((m for _, m in messages if m.get_type() in MAG_NAMES), None)
        if first is None:
            return 0, 0, None
        chosen = (first.get_srcSystem(), first.get_srcComponent(), None)
        notes.append(
            f"no HEARTBEAT of a vehicle's autopilot (component 1): read the source of the first magnetometer "
            f"message, system {chosen[0]} component {chosen[1]}, autopilot unknown"
        )
    _note_other_sources(messages, chosen, notes)
    return chosen


def _note_other_sources(messages: list, chosen: tuple, notes: list) -> None:
    """Note the systems/components besides ``chosen`` whose messages are left aside (a ground station's own
    ``HEARTBEAT``, in every telemetry log, is not worth a note)."""
    sources = {(m.get_srcSystem(), m.get_srcComponent()) for _, m in messages}
    stations = {
        (m.get_srcSystem(), m.get_srcComponent())
        for _, m in messages
        if m.get_type() == "HEARTBEAT" and m.type == MAV_TYPE_GCS
    }
    others = sorted(s for s in sources - stations if s != chosen[:2])
    if others:
        listed = ", ".join(f"{s}:{c}" for s, c in others)
        notes.append(
            f"the log holds messages of several systems/components: read system {chosen[0]} component "
            f"{chosen[1]} (the first vehicle's autopilot); left aside those of {listed} (sysid:compid)"
        )


def boot_time_us(msg) -> int | None:
    """Boot time (us) a message carries (``time_boot_ms`` or a boot-time ``time_usec``), else None."""
    if hasattr(msg, "time_boot_ms"):
        return int(msg.time_boot_ms) * 1000
    t = getattr(msg, "time_usec", None)
    if t is not None and 0 < t < UNIX_MIN_US:
        return int(t)
    return None


_boot_time_us = boot_time_us


def _boot_segments(records: list) -> np.ndarray:
    """Per record (receipt order): the number of the vehicle's boot it belongs to (0, 1, ...); a new boot
    starts where the boot time of a ``CLOCK_MESSAGES`` message falls back while receipt time less boot time jumps by
    more than ``REBOOT_S`` (a packet that is merely late falls back by no more than it was delayed)."""
    segment, last, out = 0, None, np.zeros(len(records), int)
    for k, (receipt, msg) in enumerate(records):
        boot = _boot_time_us(msg) if msg.get_type() in CLOCK_MESSAGES else None
        if boot is not None:
            if last is not None and boot < last[1] and (receipt - boot) - (last[0] - last[1]) > REBOOT_S * 1e6:
                segment += 1
            last = (receipt, boot)
        out[k] = segment
    return out


class _Vehicle:
    """The chosen vehicle's messages of one boot: ``tables[name]`` is ``{field: (M,) array, "receipt_us": ...}``
    in receipt order; ``autopilot`` its name (``ardupilot``, ``px4`` or None); ``params`` the
    ``PARAM_VALUE`` values as ``{name: (receipt_us (K,), value (K,))}``."""

    def __init__(self, records: _Records, notes: list):
        self.path = records.path
        sysid, compid, code = _choose_vehicle(records.messages, notes)
        self.sysid, self.compid, self.autopilot_code = sysid, compid, code
        self.autopilot = AUTOPILOTS.get(code) if code is not None else None
        own = [(t, m) for t, m in records.messages if (m.get_srcSystem(), m.get_srcComponent()) == (sysid, compid)]
        own, earlier = self._one_boot(own, notes)
        grouped: dict[str, list] = {}
        for t, m in own:
            grouped.setdefault(m.get_type(), []).append((t, m))
        self.tables = {name: _table(rows) for name, rows in grouped.items() if name != "PARAM_VALUE"}
        self.params = self._parameters(grouped.get("PARAM_VALUE", []))
        earlier_rows: dict[str, list] = {}
        for t, m in earlier:
            earlier_rows.setdefault(m.get_type(), []).append((t, m))
        #: ``STATUSTEXT`` and ``AUTOPILOT_VERSION`` of earlier boots, for a firmware the boot read does not name.
        self.earlier_tables = {n: _table(r) for n, r in earlier_rows.items() if n != "PARAM_VALUE"}
        self._persisting(earlier, notes)

    @staticmethod
    def _one_boot(own: list, notes: list) -> tuple[list, list]:
        """The messages of the boot read, and those of the boots before it that persist across a reboot
        (``PERSISTING``), both in receipt order."""
        segments = _boot_segments(own)
        if not len(segments) or segments[-1] == 0:
            return own, []
        counts = np.bincount(segments, weights=[m.get_type() in MAG_NAMES for _, m in own])
        keep = int(np.argmax(counts))
        earlier = [r for r, s in zip(own, segments) if s < keep and r[1].get_type() in PERSISTING]
        notes.append(
            f"the vehicle rebooted {int(segments[-1])} time(s) during the log (boot time fell back): read boot "
            f"{keep + 1} of {int(segments[-1]) + 1}, the one with the most magnetometer messages; "
            f"{int(np.count_nonzero(segments != keep)) - len(earlier)} messages of the other boots left aside"
            + (
                f" ({len(earlier)} PARAM_VALUE, STATUSTEXT and AUTOPILOT_VERSION of earlier boots kept)"
                if earlier
                else ""
            )
        )
        return [r for r, s in zip(own, segments) if s == keep], earlier

    def _persisting(self, earlier: list, notes: list) -> None:
        """Add the ``PARAM_VALUE`` values of earlier boots to ``params`` (parameters are stored on the vehicle
        and persist across a reboot; ``_param_at`` then gives the last value received before an epoch from any
        boot, else the first received later in the boot read) and note which were used."""
        before = self._parameters([(t, m) for t, m in earlier if m.get_type() == "PARAM_VALUE"])
        if not before:
            return
        starts = [self.tables[m]["receipt_us"][0] for m in MAG_NAMES if m in self.tables]
        start = min(starts) if starts else np.inf
        used = sorted(n for n in before if n not in self.params or self.params[n][0][0] > start)
        for name, (t, v) in before.items():
            t_now, v_now = self.params.get(name, (np.zeros(0, np.int64), np.zeros(0)))
            times, values = np.concatenate((t, t_now)), np.concatenate((v, v_now))
            order = np.argsort(times, kind="stable")
            self.params[name] = (times[order], values[order])
        if not used:
            return
        compass = [n for n in used if n.startswith(("COMPASS_", "AHRS_ORIENTATION"))]
        notes.append(
            f"parameters from an earlier boot were used: {len(used)} parameters ({len(compass)} of them "
            "COMPASS_*/AHRS_ORIENTATION) were last received before the reboot and not again before the first "
            "magnetometer epoch of the boot read; parameters persist across a reboot, so the value in force at an "
            "epoch is the last received before it from any boot (by receipt time)"
        )

    def _parameters(self, rows: list) -> dict:
        out: dict[str, tuple[list, list]] = {}
        for t, m in rows:
            name = m.param_id.rstrip("\x00") if isinstance(m.param_id, str) else str(m.param_id)
            ts, vs = out.setdefault(name, ([], []))
            ts.append(t)
            vs.append(self._param_value(m))
        params = {}
        for name, (ts, vs) in out.items():
            order = np.argsort(np.array(ts, np.int64), kind="stable")  # receipt order; a late packet goes back
            params[name] = (np.array(ts, np.int64)[order], np.array(vs, float)[order])
        return params

    def _param_value(self, m) -> float:
        return param_value(m, self.autopilot)


def param_value(m, autopilot: str | None) -> float:
    """A ``PARAM_VALUE``'s value: PX4 sends integer parameters as their bytes in the float field
    (``MAV_PARAM_TYPE`` 1..8), ArduPilot as the float of the integer."""
    kind = int(m.param_type)
    if autopilot != "px4" or not 1 <= kind <= 8:
        return float(m.param_value)
    code = "BbHhIiQq"[kind - 1] if kind <= 6 else "i"
    raw = struct.pack("<f", m.param_value)
    return float(struct.unpack("<" + code, raw[: struct.calcsize(code)].ljust(struct.calcsize(code), b"\0"))[0])


def _table(rows: list) -> dict[str, np.ndarray]:
    """``{field: (M,) array}`` of messages of one type (``(receipt_us, msg)`` rows) and ``receipt_us``."""
    msg = rows[0][1]
    out = {"receipt_us": np.array([t for t, _ in rows], np.int64)}
    for name in msg.get_fieldnames():
        values = [getattr(m, name) for _, m in rows]
        if isinstance(values[0], (bytes, list)):  # arrays and raw bytes are not read; text (STATUSTEXT) is
            continue
        out[name] = np.array(values)
    return out


# ------------------------------------------------------------------ clock
class _Clock:
    """Boot time to UTC, and receipt time to boot time, of one vehicle's log.

    ``receipt_offset_us``: median of ``receipt - boot`` over the time-stamped messages (the ground station's
    clock less the vehicle's, plus the link's latency); ``utc_offset_us``: UTC - boot time, from
    ``SYSTEM_TIME`` where it has a UNIX time, else ``receipt_offset_us``."""

    def __init__(self, vehicle: _Vehicle, notes: list):
        pairs = [(t["receipt_us"], self.boot_of(t)) for name, t in vehicle.tables.items() if _has_boot(t)]
        receipt = np.concatenate([p[0] for p in pairs]) if pairs else np.zeros(0, np.int64)
        boot = np.concatenate([p[1] for p in pairs]) if pairs else np.zeros(0)
        ok = np.isfinite(boot)
        diff = receipt[ok] - boot[ok]
        self.receipt_offset_us = float(np.median(diff)) if diff.size else 0.0
        spread = float(np.median(np.abs(diff - self.receipt_offset_us))) if diff.size else 0.0
        st = vehicle.tables.get("SYSTEM_TIME")
        valid = st["time_unix_usec"] > UNIX_MIN_US if st else np.zeros(0, bool)
        if valid.any():
            offsets = st["time_unix_usec"][valid].astype(float) - st["time_boot_ms"][valid] * 1000.0
            self.utc_offset_us = float(np.median(offsets))
            mad = float(np.median(np.abs(offsets - self.utc_offset_us)))
            self.time_base = (
                f"utc: boot time + {self.utc_offset_us * 1e-6:.6f} s, the median over {int(valid.sum())} "
                f"SYSTEM_TIME messages of time_unix_usec - time_boot_ms (median absolute deviation "
                f"{mad * 1e-3:.1f} ms)"
            )
            return
        self.utc_offset_us = self.receipt_offset_us
        self.time_base = (
            f"utc-ground-station: boot time + {self.utc_offset_us * 1e-6:.6f} s, the median over "
            f"{int(diff.size)} time-stamped messages of the ground station's receipt stamp - boot time "
            f"(median absolute deviation {spread * 1e-3:.1f} ms)"
        )
        notes.append(
            "no SYSTEM_TIME with a UNIX time: UTC is the ground station's clock on receipt (the tlog's own "
            "stamps), which is late by the link's latency and off by the ground station clock's error"
        )

    @staticmethod
    def boot_of(table: dict) -> np.ndarray:
        """Boot time (us, float; NaN where the message has none) of every message of ``table``."""
        if "time_boot_ms" in table:
            return table["time_boot_ms"].astype(float) * 1000.0
        t = table.get("time_usec")
        if t is None:
            return np.full(len(table["receipt_us"]), np.nan)
        t = t.astype(float)
        return np.where((t > 0) & (t < UNIX_MIN_US), t, np.nan)

    def boot_us(self, table: dict) -> np.ndarray:
        """Boot time (us) of every message of ``table``: its own, else from a UNIX ``time_usec`` (less
        ``utc_offset_us``), else its receipt (less ``receipt_offset_us``)."""
        boot = self.boot_of(table)
        if "time_usec" in table and "time_boot_ms" not in table:
            t = table["time_usec"].astype(float)
            boot = np.where(t >= UNIX_MIN_US, t - self.utc_offset_us, boot)
        return np.where(np.isfinite(boot), boot, table["receipt_us"] - self.receipt_offset_us)

    def utc_s(self, boot_us) -> np.ndarray:
        """UNIX time (s) of boot times ``boot_us`` (us)."""
        return (np.asarray(boot_us, float) + self.utc_offset_us) * 1e-6


def _has_boot(table: dict) -> bool:
    return "time_boot_ms" in table or "time_usec" in table


def _in_time_order(table: dict, boot_us: np.ndarray) -> tuple[dict, np.ndarray, int, int]:
    """``table`` sorted by boot time with the later of messages of equal boot time dropped: ``(table, boot_us,
    dropped, backwards)``, ``backwards`` the places where the receipt order went back in time."""
    backwards = int(np.count_nonzero(np.diff(boot_us) < 0))
    keep = time_order(boot_us)
    dropped = len(boot_us) - len(keep)
    return {k: v[keep] for k, v in table.items()}, boot_us[keep], dropped, backwards


# ------------------------------------------------------------------ magnetometers
def _mag_streams(vehicle: _Vehicle) -> list[dict]:
    """Each magnetometer message type in the log with a field other than zero: ``{instance, message, unit}``
    (``SCALED_IMU`` only where there is no ``RAW_IMU``)."""
    streams, taken = [], set()
    for instance, message, unit in MAG_MESSAGES:
        table = vehicle.tables.get(message)
        if table is None or instance in taken:
            continue
        if not np.any([table[c] != 0 for c in ("xmag", "ymag", "zmag")]):
            continue  # ArduPilot sends zeros for a compass it does not have
        taken.add(instance)
        streams.append({"instance": instance, "message": message, "unit": unit})
    return streams


def _summary(vehicle: _Vehicle, clock: _Clock, stream: dict) -> dict:
    boot = np.unique(clock.boot_us(vehicle.tables[stream["message"]]))
    span = (boot[-1] - boot[0]) * 1e-6 if len(boot) > 1 else 0.0
    return {
        "instance": stream["instance"],
        "message": stream["message"],
        "samples": int(len(boot)),
        "rate_hz": round(float((len(boot) - 1) / span), 3) if span > 0 else None,
    }


def _no_magnetometer(vehicle: _Vehicle) -> str:
    present = [m for m in MAG_NAMES if m in vehicle.tables]
    looked = ", ".join(MAG_NAMES)
    if present:
        return (
            f"{', '.join(present)} carry a zero magnetic field throughout (looked for {looked}): the vehicle "
            "reports no compass on them"
        )
    return (
        f"no magnetometer message from the vehicle (looked for {looked}): the ground station must request the "
        "RAW_IMU stream (ArduPilot: SRn_RAW_SENS > 0 for its link, e.g. SR0_RAW_SENS; PX4: the SCALED_IMU or "
        "HIGHRES_IMU stream)"
    )


def highres_unit(field: np.ndarray, autopilot: str | None, notes: list) -> tuple[float, str]:
    """nT per count of a ``HIGHRES_IMU`` field (M, 3) and its description: gauss where the magnitudes are
    those of the Earth's field in gauss, else ArduPilot's ``get_field() * 1000`` (1e-3 mG = 0.1 nT)."""
    median = float(np.median(np.linalg.norm(field, axis=1))) if len(field) else 0.0
    if median > 1e3:
        notes.append(
            f"HIGHRES_IMU field magnitudes of {median:.4g}: taken as ArduPilot's milligauss x 1000 "
            "(send_highres_imu), not the gauss of the message definition"
        )
        return NT_PER_MILLIGAUSS / 1000.0, "mG x 1000 -> x0.1 nT"
    if autopilot == "ardupilot":
        notes.append(f"HIGHRES_IMU field magnitudes of {median:.4g}: taken as gauss")
    return NT_PER_UNIT["G"], "G -> x1e5 nT"


def _firmware(vehicle: _Vehicle) -> tuple[int, int, int] | None:
    """``(major, minor, patch)`` of the vehicle's ``AUTOPILOT_VERSION.flight_sw_version`` (bytes 4, 3, 2 of the
    uint32, the lowest the release type) in the boot read, else in an earlier boot; None where the log has none."""
    for tables in (vehicle.tables, vehicle.earlier_tables):
        table = tables.get("AUTOPILOT_VERSION")
        if table is None or not len(table["flight_sw_version"]) or table["flight_sw_version"][-1] == 0:
            continue
        v = int(table["flight_sw_version"][-1])
        return v >> 24 & 0xFF, v >> 16 & 0xFF, v >> 8 & 0xFF
    return None


#: The banner an ArduPilot or PX4 vehicle sends as STATUSTEXT at boot and on connection ("ArduSub V4.1.1 (66c674c1)").
FIRMWARE_BANNER = re.compile(r"^(Ardu\w+|APM:\w+|PX4\w*)\s+V?\d+\.\d+")


def _firmware_text(vehicle: _Vehicle) -> str | None:
    """The firmware in words: the vehicle's STATUSTEXT banner, else ``AUTOPILOT_VERSION``'s version with the
    autopilot's name, else None."""
    banner = _banner(vehicle)
    if banner is not None:
        return banner
    version = _firmware(vehicle)
    if version is None:
        return None
    name = {"ardupilot": "ArduPilot", "px4": "PX4"}.get(vehicle.autopilot or "", "autopilot")
    return f"{name} {'.'.join(map(str, version))}"


def _banner(vehicle: _Vehicle) -> str | None:
    """The first firmware banner among the ``STATUSTEXT`` of the boot read, else of the earlier boots."""
    for tables in (vehicle.tables, vehicle.earlier_tables):
        texts = tables.get("STATUSTEXT", {}).get("text", [])
        banner = next((str(t).strip() for t in texts if FIRMWARE_BANNER.match(str(t).strip())), None)
        if banner is not None:
            return banner
    return None


#: ArduPilot's vehicle of each ``HEARTBEAT.type`` (``MAV_TYPE``): the name its banner gives (``ArduCopter``).
VEHICLE_OF_TYPE = {1: "Plane", 2: "Copter", 3: "Copter", 4: "Copter", 10: "Rover", 11: "Rover", 12: "Sub"} | {
    t: "Copter" for t in (13, 14, 15)
}


def _ardupilot_firmware(vehicle: _Vehicle) -> str | None:
    """ArduPilot's firmware as its banner names it (``APM:Copter V3.5.7 (b11c6af3)``): the ``STATUSTEXT`` banner,
    else ``Ardu<vehicle> V<version>`` from ``AUTOPILOT_VERSION`` and ``HEARTBEAT.type``; None where neither is
    in the log."""
    banner = _banner(vehicle)
    if banner is not None and banner.startswith(("Ardu", "APM:")):
        return banner
    version = _firmware(vehicle)
    if version is None:
        return None
    types = vehicle.tables.get("HEARTBEAT", {}).get("type", [])
    kind = VEHICLE_OF_TYPE.get(int(types[0]), "Pilot") if len(types) else "Pilot"
    return f"Ardu{kind} V{'.'.join(map(str, version))}"


def correction_model(firmware: str | None) -> tuple[bool, bool]:
    """``(motor_first, scale_applies)`` of ArduPilot's ``correct_field`` in ``firmware`` (the banner's
    words, or None): motor compensation before the soft-iron matrix in the releases of
    ``magkf.io.dataflash._MOTOR_FIRST`` (Copter 3.3 to 3.5); ``COMPASS_SCALE`` only from 4.0; the 4.x model
    where the version is unknown."""
    version = _version(firmware) if firmware else None
    if version is None:
        return False, True
    return _motor_first(firmware), version >= (4, 0)


_correction_model = correction_model


def is_calibrated(message: str, autopilot: str | None, firmware) -> bool | None:
    """Whether ``message`` carries the autopilot's calibrated field (None: autopilot unknown); PX4 up to v1.11
    calibrated ``sensor_mag`` in the driver."""
    if message == "HIGHRES_IMU":
        return True
    if autopilot == "px4":
        return firmware is not None and firmware[:2] < (1, 12)
    return {"ardupilot": True}.get(autopilot)


_is_calibrated = is_calibrated


def uncorrect_ardupilot(
    field_mg, boot_us, params: dict, instance: int, aux: dict, firmware: str | None, notes: list
) -> tuple[np.ndarray, str, int]:
    """Undo ArduPilot's ``correct_field`` of ``firmware`` (``_correction_model``) on ``field_mg`` (N, 3) with the
    ``COMPASS_*`` parameter set of priority ``instance`` in effect at ``boot_us``; returns the raw field, the
    description and the compass parameter set's number (1..3)."""
    k = _state_index(params, instance)
    if (unmatched := unmatched_priority(params, instance)) is not None:
        notes.append(unmatched)
    suffix = ("", "2", "3")[k] if k < 3 else ""
    p = {q: _param_at(params, _param_name(q, suffix), boot_us, _CAL_DEFAULTS[q]) for q in _CAL_PARAMS}
    stack = lambda q: np.column_stack([p[f"{q}_{a}"] for a in "XYZ"])  # noqa: E731
    motor, motor_text = _motor(params, suffix, boot_us, aux, notes)
    first, scale_applies = _correction_model(firmware)
    scale = p["SCALE"] if scale_applies else 1.0
    raw = compass_uncorrect(field_mg, stack("OFS"), stack("DIA"), stack("ODI"), scale, motor, motor_first=first)
    return raw, _model_text(firmware, suffix, first, scale_applies, scale, motor_text), k + 1


_uncorrect_ardupilot = uncorrect_ardupilot


def _model_text(firmware, suffix, motor_first, scale_applies, scale, motor_text) -> str:
    """What ``_uncorrect_ardupilot`` undid, in words."""
    if motor_first:
        model = f"M (raw + COMPASS_OFS{suffix} + motor) (3.3 to 3.5: motor compensation before the matrix; no SCALE)"
    elif scale_applies:
        model = f"M ((raw + COMPASS_OFS{suffix}) * COMPASS_SCALE{suffix}) + motor"
    else:
        model = f"M (raw + COMPASS_OFS{suffix}) + motor (before 4.0: no COMPASS_SCALE)"
    unused = scale_applies and not np.any(_effective_scale(scale) != 1.0)
    scale_note = "; SCALE outside [1/1.5, 1.5] or 1, not applied" if unused else ""
    if firmware is None or _version(firmware) is None:
        head = "ArduPilot 4.x AP_Compass_Backend::correct_field assumed (no firmware version in the log)"
    else:
        head = f"AP_Compass_Backend::correct_field of {firmware}"
    return (
        f"{head}: field = {model}, M from COMPASS_DIA{suffix}/"
        f"COMPASS_ODI{suffix} (PARAM_VALUE values in effect at each epoch{scale_note}). Undone: {motor_text}, "
        f"soft-iron matrix{', scale' if scale_applies else ''} and offsets; the int16 truncation taken as +-0.5 mG "
        "away from zero. Raw is in the vehicle-aligned frame after the firmware's rotation (COMPASS_ORIENT, "
        "AHRS_ORIENTATION)."
    )


def _motor(params: dict, suffix: str, boot_us, aux: dict, notes: list) -> tuple[np.ndarray | float, str]:
    """ArduPilot's motor compensation (N, 3) mG at ``boot_us`` (``COMPASS_MOTCT`` 1: ``COMPASS_MOT`` x
    throttle 0..1, 2: x current in A) and what was done about it. With ``COMPASS_PMOT_EN`` 1 the first compass's
    compensation is per motor instead (``AP_Compass_Backend::correct_field``, ``_per_motor.enabled() && i == 0``),
    which telemetry cannot undo: nothing is undone, and a note says so."""
    per_motor = int(_param_at(params, "COMPASS_PMOT_EN", boot_us[:1], 0.0)[0]) if len(boot_us) else 0
    if per_motor == 1 and suffix == "":  # 4.x: per-motor compensation replaces COMPASS_MOTCT for the first compass
        notes.append(
            "COMPASS_PMOT_EN = 1: the first compass's motor compensation is per motor (from each motor's output), "
            "which a telemetry log cannot undo: the field keeps it"
        )
        return 0.0, "per-motor compensation (COMPASS_PMOT_EN) not undone"
    motct = int(_param_at(params, "COMPASS_MOTCT", boot_us[:1], 0.0)[0]) if len(boot_us) else 0
    mot = np.column_stack([_param_at(params, f"COMPASS_MOT{suffix}_{a}", boot_us, 0.0) for a in "XYZ"])
    if motct == 0 or not np.any(mot):
        return 0.0, "no motor compensation (COMPASS_MOTCT 0 or COMPASS_MOT zero)"
    channel = {1: "throttle", 2: "current_a"}.get(motct)
    values = aux.get(channel)
    if values is None:
        notes.append(
            f"COMPASS_MOTCT = {motct}: the motor compensation is not undone ("
            + ("per-motor compensation is not modelled)" if channel is None else f"no {channel} in the log)")
        )
        return 0.0, "motor compensation not undone"
    interval = aux.get(INTERVALS, {}).get(channel, float("nan"))
    if interval > aux.get(MAX_GAP, np.inf):
        notes.append(
            f"the motor compensation is undone with {channel} sent every {interval:.3g} s (median), longer than "
            f"max_gap_s = {aux[MAX_GAP]:g} s: its accuracy is limited by that stream, which misses changes of "
            f"{channel} between its samples (COMPASS_MOT{suffix} = {_mot_text(mot)} mG per unit)"
        )
    unknown = int(np.count_nonzero(~np.isfinite(values)))
    if unknown:
        notes.append(
            f"{unknown} epochs have no {channel} (outside its stream or across a gap): their motor compensation "
            "cannot be undone, so their field is left empty"
        )
    return mot * values[:, None], f"motor compensation COMPASS_MOT{suffix} x {channel}"


def _mot_text(mot: np.ndarray) -> str:
    """``COMPASS_MOT`` (N, 3) as ``(x, y, z)`` of its largest row."""
    row = mot[int(np.argmax(np.abs(mot).sum(axis=1)))]
    return "(" + ", ".join(f"{v:.3g}" for v in row) + ")"


# ------------------------------------------------------------------ reading
def read_tlog(path, *, mag: int | None = None, raw: bool = True, max_gap_s: float = 0.5):
    """Read a MAVLink telemetry log into the canonical drive log.

    Parameters
    ----------
    path : str or pathlib.Path
        The ``.tlog`` file.
    mag : int, optional
        Magnetometer instance (0 ``RAW_IMU``/``SCALED_IMU``, 1 ``SCALED_IMU2``, 2 ``SCALED_IMU3``, 3
        ``HIGHRES_IMU``); default the first present.
    raw : bool
        Undo the autopilot's calibration where the message carries it and the log gives its parameters.
    max_gap_s : float
        Longest gap (s) of a stream across which it is interpolated.

    Returns
    -------
    (pandas.DataFrame, dict)
        One row per magnetometer epoch (N rows): ``time`` (UNIX s), ``mag_x, mag_y, mag_z`` (nT),
        ``roll, pitch, yaw`` (deg), ``lat, lon, alt`` (deg, m; only with a 3-D fix in the log), ``hdop``,
        ``vdop``, ``fix_type``, ``current_a``, ``throttle`` (0..1), ``temp_c`` where the log has them; and
        the JSON-able provenance (``ardupilot_firmware``: the ArduPilot firmware whose correction model was
        undone, as its banner names it, or None).

    Raises
    ------
    InputError
        One line naming the file: not a telemetry log, no magnetometer message, no such instance.
    """
    import pandas as pd

    notes: list[str] = []
    vehicle, clock = _open(path, notes)
    frame, provenance = _read(vehicle, clock, mag, raw, max_gap_s, notes)
    order = ["time", *MAG, *(c for c in frame if c not in ("time", *MAG))]
    return pd.DataFrame({c: frame[c] for c in order}), provenance


def _open(path, notes: list) -> tuple[_Vehicle, _Clock]:
    """The vehicle's messages and clock of the telemetry log at ``path``; InputError if it holds no MAVLink
    packet that magkf reads."""
    records = _Records(path)
    if not records.decoded:
        raise InputError(
            "not a MAVLink telemetry log: no valid MAVLink packet (an 8-byte time stamp, then 0xFE or 0xFD) of "
            f"the messages magkf reads ({', '.join(WANTED)})",
            records.path,
        )
    _record_notes(records, notes)
    vehicle = _Vehicle(records, notes)
    clock = _Clock(vehicle, notes)
    vehicle.params = {k: (t - clock.receipt_offset_us, v) for k, (t, v) in vehicle.params.items()}
    return vehicle, clock


def _record_notes(records: _Records, notes: list) -> None:
    if records.cut:
        notes.append("truncated: the last packet is cut off by the end of the file and was dropped")
    if records.skipped:
        notes.append(
            f"{records.skipped} bytes were not a record of a known MAVLink message (damage, or messages of another "
            "dialect than ArduPilot's and the common set) and were skipped"
        )
    if records.bad:
        notes.append(f"{records.bad} packets failed their checksum and were dropped")
    if records.duplicates:
        notes.append(
            f"{records.duplicates} packets were logged twice (the same bytes within "
            f"{DUPLICATE_WINDOW_US * 1e-6:g} s, e.g. received over two links): the repeats were dropped"
        )


def _read(vehicle: _Vehicle, clock: _Clock, mag, raw: bool, max_gap_s: float, notes: list) -> tuple[dict, dict]:
    streams = _mag_streams(vehicle)
    if not streams:
        raise InputError(_no_magnetometer(vehicle), vehicle.path)
    stream = _choose_stream(streams, mag, vehicle.path)
    table, boot = _mag_table(vehicle, clock, stream, notes)
    t = clock.utc_s(boot)
    frame = {"time": t}
    columns = {"time": f"{stream['message']}.{_time_field(table)} (boot time -> UTC s; {clock.time_base})"}
    _attitude(vehicle, clock, boot, max_gap_s, frame, columns, notes)
    _position(vehicle, clock, boot, max_gap_s, frame, columns, notes)
    aux = _auxiliary(vehicle, clock, boot, table, stream, max_gap_s, frame, columns)
    magnetometer, raw_text = _magnetometer_columns(vehicle, table, boot, stream, raw, aux, frame, columns, notes)
    magnetometer |= _summary(vehicle, clock, stream)
    wanted = ("COMPASS_", "CAL_MAG", "AHRS_ORIENTATION", "SENS_BOARD_ROT")
    provenance = {
        "format": "mavlink-tlog",
        "file": vehicle.path,
        "firmware": _firmware_text(vehicle),
        "columns": columns,
        "magnetometer": magnetometer,
        "magnetometers": [_summary(vehicle, clock, s) for s in streams],
        "vehicle": {
            "sysid": vehicle.sysid,
            "compid": vehicle.compid,
            "autopilot": vehicle.autopilot,
            "firmware": ".".join(map(str, _firmware(vehicle))) if _firmware(vehicle) else None,
        },
        "parameters": {k: float(v[-1]) for k, (_, v) in sorted(vehicle.params.items()) if k.startswith(wanted)},
        "ardupilot_firmware": _ardupilot_firmware(vehicle) if vehicle.autopilot == "ardupilot" else None,
        "raw_reconstruction": raw_text,
        "time_base": clock.time_base,
        "notes": notes,
    }
    return frame, provenance


def _choose_stream(streams: list[dict], mag, path: str) -> dict:
    instances = [s["instance"] for s in streams]
    chosen = instances[0] if mag is None else int(mag)
    if chosen not in instances:
        raise InputError(f"no magnetometer instance {chosen}; the log has {instances}", path)
    return next(s for s in streams if s["instance"] == chosen)


def _time_field(table: dict) -> str:
    return "time_boot_ms" if "time_boot_ms" in table else "time_usec"


def _mag_table(vehicle: _Vehicle, clock: _Clock, stream: dict, notes: list) -> tuple[dict, np.ndarray]:
    """The chosen magnetometer's messages in boot-time order, repeats dropped (noted), and their boot times."""
    message = stream["message"]
    table, boot, dropped, backwards = _in_time_order(vehicle.tables[message], clock.boot_us(vehicle.tables[message]))
    if backwards:
        notes.append(f"{message} messages out of time order at {backwards} place(s) in the log: read sorted by time")
    if dropped:
        notes.append(f"{dropped} {message} messages with a repeated time stamp dropped (the first kept)")
    return table, boot


def _magnetometer_columns(
    vehicle: _Vehicle, table: dict, boot, stream: dict, raw: bool, aux: dict, frame: dict, columns: dict, notes: list
) -> tuple[dict, str]:
    """Add ``mag_x, mag_y, mag_z`` (nT) to ``frame``; returns the provenance's ``magnetometer`` and what was
    undone."""
    message = stream["message"]
    field = np.column_stack([table[c].astype(float) for c in ("xmag", "ymag", "zmag")])
    firmware = _firmware(vehicle)
    calibrated = _is_calibrated(message, vehicle.autopilot, firmware)
    info = {"autopilot": vehicle.autopilot, "message_calibrated": calibrated}
    if message == "HIGHRES_IMU":
        per_count, unit_text = highres_unit(field, vehicle.autopilot, notes)
        nt = field * per_count
    else:
        nt, unit_text = _untruncate(field) * NT_PER_MILLIGAUSS, "mG, int16 truncation centred, x100 -> nT"
    zero = np.all(field == 0, axis=1)
    if zero.any():  # the autopilot sends zeros while it has no reading of that compass
        nt[zero] = np.nan
        notes.append(f"{int(zero.sum())} {message} messages carry a zero field (no reading): left empty")
    text, undone = _undo(vehicle, nt, boot, stream, raw, calibrated, aux, info, notes)
    for axis, name in zip("xyz", MAG):
        columns[name] = f"{message}.{axis}mag ({unit_text}; {'as sent' if undone is None else 'calibration undone'})"
    frame.update({name: undone[:, i] if undone is not None else nt[:, i] for i, name in enumerate(MAG)})
    info["calibrated"] = bool(calibrated) and undone is None if calibrated is not None else None
    return info, text


def _undo(vehicle, nt, boot, stream, raw, calibrated, aux, info, notes) -> tuple[str, np.ndarray | None]:
    """The raw field (nT) where the autopilot's calibration can be undone (else None) and what was done;
    ``info`` gets the compass parameter set (``compass``) of an ArduPilot magnetometer."""
    message, instance = stream["message"], stream["instance"]
    has_compass = any(k.startswith("COMPASS_") for k in vehicle.params)
    if vehicle.autopilot == "ardupilot" and message != "HIGHRES_IMU":
        k = _state_index(vehicle.params, instance) if has_compass else instance
        info["compass"] = k + 1
        info["parameter_set"] = "COMPASS_OFS{0}, COMPASS_DIA{0}, COMPASS_ODI{0}, COMPASS_SCALE{0}".format(
            ("", "2", "3")[k]
        )
    if not calibrated:
        return _not_calibrated(message, calibrated, _firmware(vehicle), notes), None
    if not raw:
        return "not done (raw=False): the field as the autopilot corrected it", None
    why = _why_not_undone(message, vehicle.autopilot, has_compass)
    if why is not None:
        notes.append(
            f"{message} carries the autopilot's calibrated field and its calibration cannot be undone ({why}): "
            "read as sent; a calibration fitted to it is relative to the autopilot's"
        )
        return f"not done ({why}): the field as the autopilot corrected it", None
    firmware = _ardupilot_firmware(vehicle)
    raw_mg, text, _ = _uncorrect_ardupilot(nt / NT_PER_MILLIGAUSS, boot, vehicle.params, instance, aux, firmware, notes)
    if firmware is None or _version(firmware) is None:
        notes.append(
            f"ArduPilot firmware {firmware or 'unknown'} (no AUTOPILOT_VERSION or STATUSTEXT banner with a version): "
            "the 4.x correction model was assumed; before 4.0 there was no COMPASS_SCALE, and Copter 3.3 to 3.5 "
            "added the motor compensation before the soft-iron matrix"
        )
    return text, raw_mg * NT_PER_MILLIGAUSS


def not_calibrated(message: str, calibrated: bool | None, firmware, notes: list) -> str:
    """What is done to a field that is not known to be calibrated (``calibrated`` None: autopilot unknown;
    False: PX4's ``sensor_mag``), noted."""
    if calibrated is None:
        notes.append(
            f"the autopilot is unknown (no HEARTBEAT of a known one): whether {message} is calibrated is not known"
        )
        return "not known whether the field is calibrated: read as sent"
    if firmware is None:
        notes.append(
            f"{message} of PX4 is sensor_mag, the reading before the CAL_MAG calibration (PX4 v1.12 on; up to "
            "v1.11 the driver applied the CAL_MAG offsets and scales before publishing it; the log has no "
            "AUTOPILOT_VERSION to tell)"
        )
        return "nothing to undo: PX4 sends sensor_mag uncalibrated"
    return f"nothing to undo: PX4 {'.'.join(map(str, firmware))} sends sensor_mag uncalibrated"


_not_calibrated = not_calibrated


def why_not_undone(message: str, autopilot: str | None, has_compass: bool) -> str | None:
    """Why a calibrated field cannot be undone, in words; None where it can (ArduPilot with its parameters)."""
    if message == "HIGHRES_IMU":
        return (
            "HIGHRES_IMU is the selected compass's corrected field, less PX4's estimated bias, of which the "
            "telemetry gives neither the compass nor the bias"
        )
    if autopilot == "px4":
        return (
            "PX4 up to v1.11 applied the CAL_MAG offsets and scales in the driver, for a device the telemetry "
            "does not name"
        )
    if not has_compass:
        return "no COMPASS_* PARAM_VALUE in the log"
    return None


_why_not_undone = why_not_undone


def _attitude(vehicle, clock, boot, max_gap_s, frame, columns, notes) -> None:
    """``roll, pitch, yaw`` (deg) at the epochs from ``ATTITUDE`` (radians) or ``ATTITUDE_QUATERNION`` (slerp)."""
    if "ATTITUDE" in vehicle.tables:
        table, t_src, _, _ = _in_time_order(vehicle.tables["ATTITUDE"], clock.boot_us(vehicle.tables["ATTITUDE"]))
        q = euler_to_quaternion(*(np.degrees(table[k].astype(float)) for k in ("yaw", "pitch", "roll")))
        source = "ATTITUDE.{} (rad -> deg; slerp of quaternions)"
    elif "ATTITUDE_QUATERNION" in vehicle.tables:
        raw_table = vehicle.tables["ATTITUDE_QUATERNION"]
        table, t_src, _, _ = _in_time_order(raw_table, clock.boot_us(raw_table))
        q = np.column_stack([table[k].astype(float) for k in ("q1", "q2", "q3", "q4")])
        source = "ATTITUDE_QUATERNION.q1..q4 ({}; slerp)"
    else:
        notes.append("no ATTITUDE or ATTITUDE_QUATERNION message: no attitude")
        return
    step = float(np.median(np.diff(t_src))) * 1e-6 if len(t_src) > 1 else float("nan")
    gap = max(max_gap_s, SLOW_ATTITUDE_INTERVALS * step) if np.isfinite(step) else max_gap_s
    if gap > max_gap_s:
        notes.append(
            f"ATTITUDE comes every {step:.3g} s (median): it is interpolated across gaps up to {gap:.3g} s "
            f"({SLOW_ATTITUDE_INTERVALS:g} intervals, beyond max_gap_s = {max_gap_s:g} s), which blurs fast turns; "
            "ask the vehicle for a faster attitude stream (ArduPilot SRn_EXTRA1, e.g. 10 Hz) for a better calibration"
        )
    q_t, valid = interpolate_quaternions(boot * 1e-6, t_src * 1e-6, q, gap)
    if not valid.all():
        notes.append(
            f"{int(np.count_nonzero(~valid))} epochs have no attitude: outside the attitude stream or between "
            f"samples more than {gap:.3g} s apart (median interval {step:.3g} s)"
        )
    yaw, pitch, roll = quaternion_to_euler(q_t)
    frame.update(roll=roll, pitch=pitch, yaw=yaw)
    for name in (ROLL, PITCH, YAW):
        columns[name] = source.format(name)


def _position(vehicle, clock, boot, max_gap_s, frame, columns, notes) -> None:
    """``lat, lon, alt`` (3-D fix only), ``hdop``, ``vdop`` and ``fix_type`` at the epochs from ``GPS_RAW_INT``."""
    gps = vehicle.tables.get("GPS_RAW_INT")
    if gps is None:
        notes.append("no GPS_RAW_INT message: no position (the site must be given)")
        return
    gps, t_gps, _, _ = _in_time_order(gps, clock.boot_us(gps))
    t, t_gps = boot * 1e-6, t_gps * 1e-6
    max_gap_s = slow_gap(t_gps, max_gap_s)  # telemetry sends it at 1 to 5 Hz; the position changes slowly
    fix = gps["fix_type"] >= 3
    i, _, valid = bracket(t, t_gps, max_gap_s)
    frame["fix_type"] = np.where(valid, gps["fix_type"][i], np.nan)
    columns["fix_type"] = "GPS_RAW_INT.fix_type of the sample at or before the epoch (GPS_FIX_TYPE: 3 = 3-D)"
    for name, counts in ((HDOP, gps["eph"]), (VDOP, gps["epv"])):
        dop = np.where(fix & (counts != UNKNOWN_U16), counts / 100.0, np.nan)
        if np.isfinite(dop).any():
            frame[name] = interpolate_linear(t, t_gps, dop, max_gap_s)[0]
            columns[name] = f"GPS_RAW_INT.{'eph' if name == HDOP else 'epv'} (/100; 65535 unknown), 3-D fix only"
    if not fix.any():
        notes.append("GPS_RAW_INT never reports a 3-D fix: no position (the site must be given)")
        return
    ell = gps.get("alt_ellipsoid", np.zeros(len(fix)))
    use_ell = bool(np.any(fix & (ell != 0)))
    alt = np.where(ell != 0, ell, gps["alt"]) / 1000.0 if use_ell else gps["alt"] / 1000.0
    if use_ell and np.any(fix & (ell == 0)):
        notes.append(
            f"GPS_RAW_INT.alt_ellipsoid is 0 in {int(np.count_nonzero(fix & (ell == 0)))} fixed samples: the "
            "height above mean sea level (alt) is used there"
        )
    for name, values, text in (
        (LAT, gps["lat"] / 1e7, "GPS_RAW_INT.lat (1e-7 deg)"),
        (LON, gps["lon"] / 1e7, "GPS_RAW_INT.lon (1e-7 deg)"),
        (
            ALT,
            alt,
            "GPS_RAW_INT.alt_ellipsoid (mm above WGS-84; alt where it is 0)"
            if use_ell
            else "GPS_RAW_INT.alt (mm above MSL)",
        ),
    ):
        frame[name] = interpolate_linear(t, t_gps, np.where(fix, values, np.nan), max_gap_s)[0]
        columns[name] = f"{text}, 3-D fix only, linear across gaps up to {max_gap_s:.3g} s"
    if not use_ell:
        notes.append("GPS_RAW_INT has no alt_ellipsoid: alt is above mean sea level, not the WGS-84 ellipsoid")


def _auxiliary(vehicle, clock, boot, table, stream, max_gap_s, frame, columns) -> dict:
    """``current_a``, ``throttle`` (0..1) and ``temp_c`` at the epochs where the log has them; returns them, with
    ``INTERVALS`` (``{column: median interval of its stream, s}``) and ``MAX_GAP`` (``max_gap_s``)."""
    candidates = {
        "current_a": [
            ("BATTERY_STATUS", "current_battery", 0.01, "cA -> A; -1 unknown"),
            ("SYS_STATUS", "current_battery", 0.01, "cA -> A; -1 unknown"),
        ],
        "throttle": [("VFR_HUD", "throttle", 0.01, "percent -> 0..1")],
        "temp_c": [("SCALED_PRESSURE", "temperature", 0.01, "cdegC -> degC")],
    }
    out, intervals = {}, {}
    t = boot * 1e-6
    own_temp = table.get("temperature")
    if own_temp is not None and np.any(own_temp != 0):
        values = np.where(own_temp != 0, own_temp * 0.01, np.nan)
        out["temp_c"] = values
        columns["temp_c"] = f"{stream['message']}.temperature (cdegC -> degC, the IMU's; 0 not given)"
        candidates.pop("temp_c")
    for name, options in candidates.items():
        for message, field, factor, text in options:
            source = vehicle.tables.get(message)
            if source is None or field not in source:
                continue
            if message == "BATTERY_STATUS":  # the first battery: id 0, else the lowest id sent
                source = {k: v[source["id"] == source["id"].min()] for k, v in source.items()}
            source, t_src, _, _ = _in_time_order(source, clock.boot_us(source))
            values = source[field].astype(float)
            values = np.where(values == -1, np.nan, values * factor) if name == "current_a" else values * factor
            if not len(values) or not np.isfinite(values).any():
                continue
            t_src = t_src * 1e-6
            intervals[name] = float(np.median(np.diff(t_src))) if len(t_src) > 1 else float("nan")
            out[name] = interpolate_linear(t, t_src, values, slow_gap(t_src, max_gap_s))[0]
            timed = "" if _has_boot(source) else ", placed at receipt time"
            columns[name] = f"{message}.{field} ({text}{timed}, linear)"
            break
    frame.update(out)
    return out | {INTERVALS: intervals, MAX_GAP: max_gap_s}


# ------------------------------------------------------------------ instances
def magnetometer_instances(path) -> list[dict]:
    """The magnetometers of a telemetry log: one dict per instance with ``instance`` (0 ``RAW_IMU`` or
    ``SCALED_IMU``, 1 ``SCALED_IMU2``, 2 ``SCALED_IMU3``, 3 ``HIGHRES_IMU``), ``message``, ``samples`` and
    ``rate_hz``."""
    vehicle, clock = _open(path, [])
    return [_summary(vehicle, clock, s) for s in _mag_streams(vehicle)]


class TelemetryLogReader(AutopilotLog):
    """A ground station's MAVLink telemetry log (``read_tlog``): the chosen magnetometer message's epochs, with
    attitude, position and DOP interpolated to them and ArduPilot's calibration undone where the log holds
    its parameters (``raw``)."""

    name = "tlog"
    title = "MAVLink telemetry log"
    extensions = (".tlog",)
    read_table = staticmethod(read_tlog)
    instances = staticmethod(magnetometer_instances)

    def recognises(self, path, head: bytes) -> bool:
        """A ``.tlog`` has no magic bytes: its first record is an 8-byte time stamp of this century (UNIX
        microseconds between 2000 and 2100), then a MAVLink start byte whose header holds a whole packet."""
        if len(head) < STAMP_BYTES + 3 or head[STAMP_BYTES] not in (MAGIC_V1, MAGIC_V2):
            return False
        stamp = int.from_bytes(head[:STAMP_BYTES], "big")
        return 946_684_800 * 10**6 <= stamp <= 4_102_444_800 * 10**6


# ------------------------------------------------------------------ writing
def write_tlog(
    table: pd.DataFrame,
    path,
    autopilot: str = "ardupilot",
    params: dict | None = None,
    *,
    attitude_per_row: int = 2,
    gps_period_s: float = 0.2,
    aux_period_s: float = 0.5,
    system_time: bool = True,
    latency_s: float = 0.02,
    mavlink1: bool = False,
    sysid: int = 1,
    firmware: str | None = None,
) -> None:
    """Write a canonical table as a MAVLink telemetry log of an ArduPilot or PX4 vehicle (for tests).

    ``table`` (N rows; ``time`` a column or the index, UNIX s; its rows at 10 to 50 Hz as a magnetometer
    stream comes) is sent by vehicle 1, component 1, boot time 10 s at the first row, following ``time`` to
    1 us (``sysid``: another vehicle); the ground station (system 255, component 190) stamps each packet at its
    time plus ``latency_s``:

    * ``HEARTBEAT`` at 1 Hz from the vehicle (``autopilot`` ``ardupilot`` or ``px4``) and the ground station;
      ``PARAM_VALUE`` for each of ``params`` before the first row (float32; PX4's integers by their bytes).
    * magnetometer at every row with a finite field: ArduPilot ``RAW_IMU`` (``time_usec`` boot us) with the
      ``COMPASS_*`` calibration of ``params`` applied as the firmware does (``compass_correct``; motor
      compensation ``COMPASS_MOT`` x ``throttle`` or ``current_a`` for ``COMPASS_MOTCT`` 1 or 2; the vehicle
      is a quadcopter, so Copter ``firmware`` 3.3 to 3.5 adds it before the soft-iron matrix and below 4.0
      there is no ``COMPASS_SCALE``), PX4
      ``SCALED_IMU`` (``time_boot_ms``), uncalibrated; both in mG truncated to int16, ``temperature`` from
      ``temp_c``. InputError where a value does not fit in int16.
    * ``ATTITUDE`` ``attitude_per_row`` times a row (slerp between rows), radians as float32.
    * ``GPS_RAW_INT`` every ``gps_period_s``: ``fix_type`` (the column, else 3 with a position; at most 1,
      no fix, without one), ``lat, lon`` (1e-7 deg), ``alt`` and ``alt_ellipsoid`` (mm, both from ``alt``),
      ``eph/epv`` from ``hdop/vdop`` (65535 where NaN); ``time_usec`` UNIX us for ArduPilot, boot us for PX4.
    * ``SYSTEM_TIME`` at 1 Hz (``system_time``); ``BATTERY_STATUS`` (``current_a``) and ``VFR_HUD``
      (``throttle``) every ``aux_period_s`` where the table has them.

    ``firmware`` (``"4.5.0"``) adds an ``AUTOPILOT_VERSION`` with that flight software version (release type
    255, official). ``mavlink1`` packs MAVLink 1 packets (``alt_ellipsoid``, an extension field, then 0).
    """
    from .mavlink_packets import VehiclePackets

    packets = VehiclePackets(
        table,
        autopilot,
        params,
        firmware=firmware,
        attitude_per_row=attitude_per_row,
        gps_period_s=gps_period_s,
        aux_period_s=aux_period_s,
        system_time=system_time,
        latency_s=latency_s,
        mavlink1=mavlink1,
        sysid=sysid,
        source=str(path),
    )
    with open(path, "wb") as f:
        for packet in packets:
            f.write(packet.stamp_us.to_bytes(STAMP_BYTES, "big"))
            f.write(packet.data)

"""Any log magkf reads, sent over a MAVLink link as a vehicle would stream it, answering what a vehicle answers.

The packets are ``magkf.io.mavlink_packets.VehiclePackets``' (what each message carries and how ArduPilot or PX4
fill it: ``magkf.io.tlog``; the ``HEARTBEAT`` of the vehicle an ArduPilot log's firmware names, ``log_vehicle_type``),
sent at the times of the log divided by the speed. Meanwhile the replay answers:

* ``PARAM_REQUEST_READ`` (by ``param_index``, or by ``param_id`` where the index is -1) and ``PARAM_REQUEST_LIST``
  with ``PARAM_VALUE``; ``PARAM_SET`` of a parameter the vehicle has by setting it and sending its ``PARAM_VALUE``
  back, as the parameter protocol asks (https://mavlink.io/en/services/parameter.html). A name the vehicle does not
  have is not answered, as ArduPilot does; nor is a request addressed to another system or component.
* ``COMMAND_LONG`` ``MAV_CMD_SET_MESSAGE_INTERVAL`` (511) with ``COMMAND_ACK`` ``MAV_RESULT_ACCEPTED``; the log's
  own rates are kept (https://mavlink.io/en/services/message_interval.html: the vehicle may send at another rate
  than asked, and a receiver must cope). ``REQUEST_DATA_STREAM`` (ArduPilot's older request, which has no
  acknowledgement) is counted, its rates not applied either. ``MAV_CMD_REQUEST_MESSAGE`` (512) of
  ``AUTOPILOT_VERSION`` (148) and ``MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES`` (520) send ``AUTOPILOT_VERSION`` where
  the firmware is known; any other command is acknowledged ``MAV_RESULT_UNSUPPORTED``.

The parameters: those given (``params``, autopilot names -> values, e.g. from
``magkf.io.autopilot.read_param_file``), which an ArduPilot vehicle applies to its field as ``correct_field``
does; else the log's own compass parameters where its reader gives them (``DriveLog.provenance["parameters"]``:
``COMPASS_*`` of DataFlash and telemetry logs, ``CAL_MAG*`` of ULogs), applied to a field read raw and only
announced for a field read as the autopilot calibrated it; else none, and the reading is sent as it is. Where
the parameters are applied, a ``PARAM_SET`` of a ``COMPASS_*`` parameter changes the readings sent from then on,
as the firmware's ``correct_field`` would (the int16 field then saturates rather than overflow); elsewhere it
changes what the vehicle answers, not its readings.
"""

from __future__ import annotations

import re
import signal
import struct
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io.dataflash import firmware_vehicle
from ..io.mavlink_packets import AUTOPILOT_CODES, PARAM_PREFIXES, VehiclePackets, param_value_message, with_sequence
from ..io.tlog import AUTOPILOT_COMPONENT, VEHICLE_OF_TYPE, mavlink_dialect

__all__ = ["ReplayStats", "replay", "log_parameters", "log_vehicle_type", "CONNECTION_HELP"]

#: What ``connection`` may be.
CONNECTION_HELP = (
    "udpout:HOST:PORT (towards a receiver listening with udpin:), udpin:HOST:PORT, udpbcast:HOST:PORT, "
    "tcp:HOST:PORT, tcpin:HOST:PORT, or a serial device (/dev/ttyUSB0, COM3)"
)
PREFIXES = ("udpout:", "udpin:", "udp:", "udpbcast:", "tcp:", "tcpin:")
#: ``MAV_CMD`` and ``MAV_RESULT`` codes of the commands answered.
SET_MESSAGE_INTERVAL, REQUEST_MESSAGE, REQUEST_AUTOPILOT_CAPABILITIES = 511, 512, 520
AUTOPILOT_VERSION_ID = 148
MAV_RESULT_ACCEPTED, MAV_RESULT_UNSUPPORTED = 0, 3
#: Longest wait (s) on the link between two looks at ``stop``.
POLL_S = 0.02
#: Packets sent between two looks at the link and ``stop`` when sending as fast as possible.
BURST = 64
VERSION = re.compile(r"(\d+)\.(\d+)(?:\.(\d+))?")


@dataclass
class ReplayStats:
    """What a replay did.

    Parameters
    ----------
    packets_sent, packets_dropped : int
        Packets of the log sent and dropped on purpose (``loss``); the answers are counted apart.
    elapsed_s : float
        Wall-clock seconds from sending the first packet to sending the last (``linger_s`` not counted).
    log_s : float
        Seconds of the log sent (the last packet's time less the first's).
    requests : dict of str to int
        Requests received by message name (``PARAM_REQUEST_READ``, ``COMMAND_LONG``, ...).
    requests_answered : int
        Requests answered with a message (``PARAM_VALUE``, ``COMMAND_ACK``, ``AUTOPILOT_VERSION``).
    completed : bool
        The whole log was sent.
    interrupted_by : int or None
        The signal that stopped the replay (``signal.SIGINT`` for a ``KeyboardInterrupt``), else None.
    notes : list of str
        Where the parameters and firmware came from, and what could not be done as asked.
    """

    packets_sent: int = 0
    packets_dropped: int = 0
    elapsed_s: float = 0.0
    log_s: float = 0.0
    requests: dict = field(default_factory=dict)
    requests_answered: int = 0
    completed: bool = False
    interrupted_by: int | None = None
    notes: list = field(default_factory=list)

    def line(self) -> str:
        """The replay in one line."""
        total = self.packets_sent + self.packets_dropped
        share = f" ({self.packets_dropped / total:.1%})" if total else ""
        how = "whole log" if self.completed else "stopped"
        return (
            f"replayed {self.log_s:.1f} s of log in {self.elapsed_s:.1f} s ({how}): {self.packets_sent} packets sent, "
            f"{self.packets_dropped} dropped{share}, {self.requests_answered} requests answered"
        )


def replay(
    log_or_table,
    connection: str,
    *,
    speed: float = 1.0,
    loss: float = 0.0,
    seed: int = 0,
    autopilot: str = "ardupilot",
    params: dict | None = None,
    firmware: str | None = None,
    reboot_at_s: float | None = None,
    sysid: int = 1,
    baud: int = 115200,
    stop=None,
    linger_s: float = 0.0,
    attitude_per_row: int = 2,
    gps_period_s: float = 0.2,
    aux_period_s: float = 0.5,
) -> ReplayStats:
    """Send a log over ``connection`` as a vehicle's MAVLink stream, answering requests, until its end.

    Parameters
    ----------
    log_or_table : DriveLog, pandas.DataFrame, str or pathlib.Path
        A log read by magkf, a canonical table (``time`` UNIX s, ``mag_x..z`` nT, ...), or a log's path
        (``magkf.io.readers.read_log`` with its defaults).
    connection : str
        Where to send: see ``CONNECTION_HELP`` (pymavlink's ``mavutil.mavlink_connection``).
    speed : float
        Times faster than the log's own time (20: a minute of log in 3 s); 0, a negative number or infinity: as
        fast as the link takes them.
    loss : float
        Share of the log's packets dropped at random (0 to 1; the answers are never dropped). A dropped packet
        still takes its sequence number, so the receiver sees the gap.
    seed : int
        Seed of the generator that chooses the dropped packets.
    autopilot : {"ardupilot", "px4"}
        The firmware whose messages are sent.
    params : dict, optional
        The vehicle's parameters (name -> value); default the log's compass parameters (see the module docstring).
    firmware : str, optional
        The firmware's version (``4.5.0``): sent as ``AUTOPILOT_VERSION``, and for ArduPilot the correction model
        applied (before 4.0 no ``COMPASS_SCALE``; 3.3 to 3.5 motor compensation first); default the log's.
    reboot_at_s : float, optional
        Seconds of the log after its first row at which the vehicle reboots (its boot clock and sequence numbers
        start again; ``magkf.io.mavlink_packets``).
    sysid : int
        The vehicle's system id (component 1).
    baud : int
        Bits per second of a serial device.
    stop : threading.Event, optional
        Set it to end the replay (from another thread).
    linger_s : float
        Seconds to go on answering requests after the last packet.
    attitude_per_row, gps_period_s, aux_period_s : int, float, float
        As ``VehiclePackets``.

    Returns
    -------
    ReplayStats
        Packets sent and dropped, seconds, requests answered. A ``KeyboardInterrupt`` (Ctrl-C, or SIGTERM under
        the ``magkf`` command) ends the replay cleanly: the stats say so in ``interrupted_by``.

    Raises
    ------
    InputError
        A log that cannot be read, a connection that cannot be opened, an argument out of range.
    """
    if not 0.0 <= loss < 1.0:
        raise InputError(f"loss {loss:g} is not a share of packets in [0, 1)", connection)
    if autopilot not in AUTOPILOT_CODES:
        raise InputError(f"unknown autopilot {autopilot!r}; use ardupilot or px4", connection)
    if np.isnan(speed):
        raise InputError("speed is not a number: give a factor >= 0 (0 or inf: as fast as possible)", connection)
    if not 1 <= sysid <= 255:
        raise InputError(f"system id {sysid} is not in 1 to 255", connection)
    log = _as_log(log_or_table)
    stats = ReplayStats()
    vehicle_params, apply = log_parameters(log, autopilot, params, stats.notes)
    firmware = firmware if firmware is not None else _log_firmware(log, autopilot, stats.notes)
    vehicle_type = log_vehicle_type(log) if autopilot == "ardupilot" else None
    packets = VehiclePackets(
        log.table,
        autopilot,
        vehicle_params,
        apply_params=apply,
        firmware=firmware,
        attitude_per_row=attitude_per_row,
        gps_period_s=gps_period_s,
        aux_period_s=aux_period_s,
        sysid=sysid,
        ground_station=False,
        reboot_at_s=reboot_at_s,
        source=log.source,
        **({} if vehicle_type is None else {"vehicle_type": vehicle_type}),
    )
    link = _open(connection, baud, sysid)
    vehicle = _Vehicle(link, packets, autopilot, sysid, stats)
    try:
        vehicle.stream(speed, np.random.default_rng(seed).random(len(packets.packets)) < loss, stop, linger_s)
    except KeyboardInterrupt as exc:
        stats.interrupted_by = getattr(exc, "signum", signal.SIGINT)
    finally:
        link.close()
    return stats


# ------------------------------------------------------------------ inputs
def _as_log(log_or_table):
    """A ``DriveLog`` (``table``, ``source``, ``provenance``) of a log, a table or a path."""
    from ..io.drivelog import DriveLog

    if isinstance(log_or_table, DriveLog):
        return log_or_table
    if isinstance(log_or_table, (str, Path)):
        from ..io.readers import read_log

        return read_log(log_or_table)
    return DriveLog(log_or_table, "table", {})


def log_parameters(log, autopilot: str, params: dict | None, notes: list) -> tuple[dict, bool]:
    """``(parameters, apply)``: the vehicle's parameters and whether an ArduPilot vehicle applies them to the
    table's field (see the module docstring); ``notes`` say which were taken."""
    if params is not None:
        ardupilot = autopilot == "ardupilot"
        done = "applied to the field as ArduPilot does" if ardupilot else "SCALED_IMU sent raw, as PX4 does"
        notes.append(f"{len(params)} parameters given: {done}")
        return (ardupilot_typed(params) if ardupilot else dict(params)), ardupilot
    provenance = getattr(log, "provenance", None) or {}
    logged = provenance.get("parameters") if isinstance(provenance.get("parameters"), dict) else {}
    own = {k: float(v) for k, v in logged.items() if k.startswith(PARAM_PREFIXES[autopilot])}
    magnetometer = provenance.get("magnetometer") if isinstance(provenance.get("magnetometer"), dict) else {}
    calibrated = magnetometer.get("calibrated")
    if not own or calibrated is None:
        notes.append("no compass parameters of the log for this autopilot: none announced, the reading sent as it is")
        return {}, False
    if calibrated:
        notes.append(f"the log's {len(own)} compass parameters announced; its field, read calibrated, sent as it is")
        return own, False
    compass = magnetometer.get("compass")
    if autopilot == "ardupilot" and compass not in (None, 1):
        notes.append(
            f"the log's magnetometer is compass {compass}: it is sent as RAW_IMU, whose parameters are those of the "
            "compass of priority 1 (COMPASS_PRIO1_ID), which may not be its own"
        )
    if autopilot == "px4":
        notes.append(
            f"the log's {len(own)} compass parameters announced; SCALED_IMU carries its raw field, as PX4 sends it"
        )
        return own, False
    notes.append(f"the log's {len(own)} compass parameters announced and applied to its raw field")
    return ardupilot_typed(own), True


#: ArduPilot's integer compass settings (AP_Int8/16/32 in ``libraries/AP_Compass/AP_Compass.cpp``), by the part of the
#: name after ``COMPASS_``; the other compass parameters (offsets, scales, matrices, motor factors, declination) are
#: floats, whatever their value looks like in a parameter file.
ARDUPILOT_INTEGER_STEMS = (
    "ORIENT", "EXTERN", "USE", "MOTCT", "DEV_ID", "PRIO", "AUTODEC", "LEARN", "TYPEMASK", "OPTIONS", "AUTO_ROT",
    "ENABLE", "DISBLMSK",
)  # fmt: skip


def ardupilot_typed(params: dict) -> dict:
    """ArduPilot's parameters with the type the firmware gives each (a parameter file does not say): the compass's
    integer settings and ``AHRS_ORIENTATION`` as integers, every other as a float (so that a ``COMPASS_OFS_X`` of
    0 in a file is announced, and set, as the float it is)."""

    def integer(name: str) -> bool:
        stem = name.removeprefix("COMPASS_")
        return name == "AHRS_ORIENTATION" or (stem != name and stem.startswith(ARDUPILOT_INTEGER_STEMS))

    return {k: (int(round(float(v))) if integer(k) else float(v)) for k, v in params.items()}


def _log_firmware(log, autopilot: str, notes: list) -> str | None:
    """The version of the log's firmware (``4.5.0``) where it is the autopilot's, else None."""
    provenance = getattr(log, "provenance", None) or {}
    texts = (
        [provenance.get("ardupilot_firmware"), provenance.get("firmware")]
        if autopilot == "ardupilot"
        else [provenance.get("px4_version"), (provenance.get("vehicle") or {}).get("firmware")]
    )
    for text in texts:
        if not isinstance(text, str) or (autopilot == "ardupilot" and not text.startswith(("Ardu", "APM:"))):
            continue
        found = VERSION.search(text)
        if found:
            version = ".".join(g or "0" for g in found.groups())
            notes.append(f"firmware {version}, from the log ({text})")
            return version
    return None


def log_vehicle_type(log) -> int | None:
    """``MAV_TYPE`` of the vehicle an ArduPilot log's firmware names (``ArduPlane V4.2.3``, ``APM:Copter V3.5.7``;
    ``dataflash.firmware_vehicle``): the lowest type a receiver names so (``tlog.VEHICLE_OF_TYPE``), or None where
    the log does not say."""
    provenance = getattr(log, "provenance", None) or {}
    for text in (provenance.get("ardupilot_firmware"), provenance.get("firmware")):
        kind = firmware_vehicle(text)
        if kind is not None:
            return min(t for t, k in VEHICLE_OF_TYPE.items() if k == kind)
    return None


def _open(connection: str, baud: int, sysid: int):
    """pymavlink's connection of ``connection``; InputError for another kind of text or a link that cannot open."""
    from pymavlink import mavutil

    serial = connection.startswith("/dev/") or re.fullmatch(r"COM\d+", connection)
    if not (connection.startswith(PREFIXES) or serial):
        raise InputError(f"not a MAVLink connection: give {CONNECTION_HELP}", connection)
    try:
        return mavutil.mavlink_connection(
            connection, baud=baud, source_system=sysid, source_component=AUTOPILOT_COMPONENT, retries=0
        )
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot open the connection ({exc})", connection) from None


# ------------------------------------------------------------------ the vehicle
class _Vehicle:
    """The replayed vehicle on its link: sends the packets, answers the requests, counts in ``stats``."""

    def __init__(self, link, packets: VehiclePackets, autopilot: str, sysid: int, stats: ReplayStats):
        self.link, self.packets, self.autopilot, self.sysid, self.stats = link, packets, autopilot, sysid, stats
        self.params = dict(packets.params)
        self.names = list(self.params)
        self.packer = mavlink_dialect().MAVLink(None, srcSystem=sysid, srcComponent=AUTOPILOT_COMPONENT)
        self.seq = 0
        self.boot = 0
        self.closed = False
        #: (N, 3) the magnetometer readings (int16 mG) with the parameters as set, once a PARAM_SET changed them.
        self.fields = None
        if hasattr(link, "handle_eof"):  # tcp: the receiver closed the connection; pymavlink would only print it
            link.handle_eof = link.handle_disconnect = self._closed

    def _closed(self) -> None:
        if not self.closed:
            self.stats.notes.append("the receiver closed the connection: the replay stopped")
        self.closed = True

    def stream(self, speed: float, dropped: np.ndarray, stop, linger_s: float) -> None:
        """Send every packet at its time (divided by ``speed``) but those ``dropped``, then answer for
        ``linger_s``; returns early when ``stop`` is set."""
        packets = self.packets.packets
        if not packets:
            return
        if not self._wait_for_receiver(stop):
            return
        paced = np.isfinite(speed) and speed > 0
        first_us, start = packets[0].time_us, time.monotonic()
        for k, packet in enumerate(packets):
            if paced:
                due = start + (packet.time_us - first_us) * 1e-6 / speed
                if not self._serve_until(due, stop):
                    break
            elif k % BURST == 0 and not self._serve_until(time.monotonic(), stop):
                break
            self._send_packet(packet, bool(dropped[k]))
            self.stats.log_s = (packet.time_us - first_us) * 1e-6
            self.stats.elapsed_s = time.monotonic() - start
        else:
            self.stats.completed = True
            self._serve_until(time.monotonic() + linger_s, stop)

    def _wait_for_receiver(self, stop) -> bool:
        """On a link that listens (``tcpin:``, ``udpin:``), wait until a receiver has connected or sent a packet,
        as a vehicle on such a port only reaches a ground station that has; False when ``stop`` is set first."""
        from pymavlink import mavutil

        def known() -> bool:
            if isinstance(self.link, mavutil.mavtcpin):
                return self.link.port is not None
            if isinstance(self.link, mavutil.mavudp) and self.link.udp_server:
                return bool(self.link.clients)
            return True

        waited = time.monotonic()
        while not known():
            if not self._serve_until(time.monotonic() + POLL_S, stop):
                return False
        if time.monotonic() - waited > POLL_S:
            self.stats.notes.append(f"waited {time.monotonic() - waited:.1f} s for a receiver on the listening link")
        return True

    def _send_packet(self, packet, dropped: bool) -> None:
        if packet.boot != self.boot:  # the vehicle rebooted: its sequence numbers start again
            self.boot, self.seq = packet.boot, 0
        seq, self.seq = self.seq, (self.seq + 1) % 256
        if dropped:
            self.stats.packets_dropped += 1
            return
        if self.fields is not None and packet.row >= 0:  # a reading of the calibration as set
            self.packer.seq = seq
            data = self.packets.magnetometer_message(packet.row, self.fields[packet.row]).pack(self.packer)
        else:
            data = with_sequence(packet.data, seq)
        self.link.write(data)
        self.stats.packets_sent += 1

    def _answer(self, message) -> None:
        self.packer.seq = self.seq
        self.link.write(message.pack(self.packer))
        self.seq = (self.seq + 1) % 256
        self.stats.requests_answered += 1

    def _serve_until(self, due: float, stop) -> bool:
        """Answer what arrives until the monotonic time ``due``; False when ``stop`` is set."""
        while True:
            self._drain()
            if self.closed or stop is not None and stop.is_set():
                return False
            remaining = due - time.monotonic()
            if remaining <= 0:
                return True
            self.link.select(min(remaining, POLL_S))

    def _drain(self) -> None:
        """Handle every message waiting on the link."""
        while not self.closed:
            try:
                message = self.link.recv_msg()
            except OSError:  # a TCP connection reset by the receiver
                self._closed()
                return
            if message is None:
                return
            self._handle(message)

    def _handle(self, message) -> None:
        kind = message.get_type()
        handler = {
            "PARAM_REQUEST_READ": self._param_read,
            "PARAM_REQUEST_LIST": self._param_list,
            "PARAM_SET": self._param_set,
            "COMMAND_LONG": self._command,
            "REQUEST_DATA_STREAM": lambda m: None,
        }.get(kind)
        if handler is None or not self._for_me(message):
            return
        self.stats.requests[kind] = self.stats.requests.get(kind, 0) + 1
        handler(message)

    def _for_me(self, message) -> bool:
        system = getattr(message, "target_system", 0)
        component = getattr(message, "target_component", 0)
        return system in (0, self.sysid) and component in (0, AUTOPILOT_COMPONENT)

    def _value(self, name: str):
        index = self.names.index(name)
        return param_value_message(name, self.params[name], len(self.names), index, self.autopilot)

    def _param_read(self, message) -> None:
        index = int(message.param_index)
        if index >= 0:
            name = self.names[index] if index < len(self.names) else None
        else:
            name = _text(message.param_id)
        if name in self.params:
            self._answer(self._value(name))

    def _param_list(self, message) -> None:
        for name in self.names:
            self._answer(self._value(name))

    def _param_set(self, message) -> None:
        name = _text(message.param_id)
        if name not in self.params:
            return
        self.params[name] = _set_value(self.params[name], message, self.autopilot)
        if self.packets.applies_params and name.startswith("COMPASS_"):
            limit = np.iinfo(np.int16)
            self.fields = np.clip(self.packets.sent_field(self.params), limit.min, limit.max)
        self._answer(self._value(name))

    def _command(self, message) -> None:
        dialect = mavlink_dialect()
        command = int(message.command)
        version = self.packets.version_message()
        wants_version = command == REQUEST_AUTOPILOT_CAPABILITIES or (
            command == REQUEST_MESSAGE and int(message.param1) == AUTOPILOT_VERSION_ID
        )
        accepted = command == SET_MESSAGE_INTERVAL or (wants_version and version is not None)
        result = MAV_RESULT_ACCEPTED if accepted else MAV_RESULT_UNSUPPORTED
        self._answer(
            dialect.MAVLink_command_ack_message(
                command, result, 0, 0, message.get_srcSystem(), message.get_srcComponent()
            )
        )
        if accepted and wants_version:
            self._answer(version)


def _text(value) -> str:
    """A ``char[16]`` field as text (pymavlink gives str or bytes), without its trailing NULs."""
    if isinstance(value, bytes):
        value = value.decode("utf-8", "replace")
    return str(value).rstrip("\x00")


def _set_value(old, message, autopilot: str):
    """The new value of a parameter whose value was ``old``, from ``PARAM_SET``: an integer parameter stays an
    integer (PX4 sends its bytes in the float field, ``MAV_PARAM_TYPE`` 1 to 6; ArduPilot its float)."""
    number = float(message.param_value)
    integer = isinstance(old, (int, np.integer)) and not isinstance(old, bool)
    if not integer:
        return float(np.float32(number))
    if autopilot == "px4" and 1 <= int(message.param_type) <= 6:
        return struct.unpack("<i", struct.pack("<f", number))[0]
    return int(round(number))

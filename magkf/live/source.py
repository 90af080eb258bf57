"""A vehicle's MAVLink link as samples of the canonical columns: ``MavlinkSource``.

What is asked for
    On ``open`` magkf waits for the vehicle's ``HEARTBEAT`` (its autopilot, component 1, that is not a ground
    station: as ``magkf.io.tlog`` chooses the vehicle of a log), then asks for its streams twice over:

    * ArduPilot: ``REQUEST_DATA_STREAM`` for the stream groups that hold them (``ArduCopter/GCS_Mavlink.cpp``,
      ``STREAM_*_msgs``: ``RAW_SENSORS`` ``RAW_IMU``, ``SCALED_IMU2/3``; ``EXTRA1`` ``ATTITUDE``;
      ``EXTENDED_STATUS`` ``GPS_RAW_INT``; ``EXTRA2`` ``VFR_HUD``; ``EXTRA3`` ``SYSTEM_TIME``, ``BATTERY_STATUS``);
    * every autopilot: ``COMMAND_LONG`` ``MAV_CMD_SET_MESSAGE_INTERVAL`` (511) for each message, ``param1`` its id
      and ``param2`` the interval in us (https://mavlink.io/en/services/message_interval.html), which overrides
      a group's rate where the firmware supports it; and ``MAV_CMD_REQUEST_MESSAGE`` (512) for
      ``AUTOPILOT_VERSION``, whose ``flight_sw_version`` names the firmware.

    The magnetometer asked for is the message of instance ``mag`` (``magkf.io.tlog``'s table: 0 ``RAW_IMU``, PX4's
    ``SCALED_IMU``; 1 ``SCALED_IMU2``; 2 ``SCALED_IMU3``; 3 ``HIGHRES_IMU``); with ``mag`` None the first message
    of that table that arrives with a field other than zero is read (``take_events`` says which). ``ATTITUDE`` is
    asked for; ``ATTITUDE_QUATERNION`` is used where it is what comes.

Compass parameters
    Read one by one with ``PARAM_REQUEST_READ`` (``param_index`` -1, by name; the vehicle answers with
    ``PARAM_VALUE``; https://mavlink.io/en/services/parameter.html), in up to ``PARAM_ROUNDS`` rounds that ask again
    for the names not answered (a request or its answer may be lost; a firmware without a parameter does not
    answer), ``PARAM_WINDOW`` requests at a time (ArduPilot drops what its queue of 20 cannot hold; a vehicle that
    answers none of the first window is asked the rest at once). The next requests go as soon as those
    in flight are answered, else ``PARAM_ROUND_S`` after them or, once an answer has shown the link's round trip,
    ``PARAM_ROUND_TRIPS`` round trips (at least ``PARAM_MIN_S``) after them or their last answer. ArduPilot's
    ``ARDUPILOT_PARAMETERS`` (the ``COMPASS_*`` set that ``magkf.io.tlog`` undoes), PX4's ``PX4_PARAMETERS``
    (``CAL_MAGn_*``). ``open`` returns once they are answered or their rounds are over; a reboot asks for them
    again, and the new boot's samples wait for the answers (a calibration uploaded before the reboot is in force
    after it). ArduPilot's field is then uncorrected exactly as ``magkf.io.tlog`` uncorrects it (the same functions,
    with the values in force when the sample is handed out); where it cannot be undone it is passed as sent and
    ``provenance`` says so. Motor compensation (``COMPASS_MOTCT`` 1 or 2) is undone with the throttle
    (``VFR_HUD``) or current (``BATTERY_STATUS``) latest at or before the sample, which lags by up to their interval
    (1 to 2 Hz in telemetry), where ``magkf.io.tlog`` interpolates between the values around it.

Time
    The vehicle's boot clock (``time_boot_ms``, boot-time ``time_usec``) is mapped to UNIX time by the median over
    the last ``SYSTEM_TIME_KEPT`` ``SYSTEM_TIME`` messages of ``time_unix_usec - time_boot_ms``, as
    ``magkf.io.tlog`` maps it. Samples are held until the first ``SYSTEM_TIME``, for up to ``HOLD_S`` of the
    vehicle's clock; after that this computer's clock on receipt stands in (the median of receipt less boot time
    over the last ``RECEIPT_KEPT`` clock messages then, kept fixed so that the times keep their order), which is
    late by the link's latency, and an event says so. A ``SYSTEM_TIME`` that comes later takes over (the times
    may step there; a sample not after the last handed out is then ``late``).

Samples
    One per magnetometer message of the chosen stream: the field, attitude interpolated to its time (slerp between
    the attitude messages around it, across gaps up to ``ATTITUDE_GAP_INTERVALS`` of their median interval and at
    least ``ATTITUDE_GAP_S``), and each slow stream's value (GNSS fix, current, throttle, temperature) latest at or
    before its time, NaN when older than ``STALE_INTERVALS`` of that stream's interval (a GNSS position only with
    a 3-D fix). A sample waits until an attitude message after its time has come (by then the slow streams' values
    of its time, sent before it, have come too), until the vehicle's clock is ``wait_s`` past it, or until the link
    is lost (then it goes without attitude where no bracket exists). No sample is handed out before the first
    parameter read is over (its field could not be undone); they wait for it, in order.

Faults (each an event, none fatal)
    * packets lost: gaps in the sequence numbers of the vehicle's component (``seq`` counts the sender's packets
      modulo 256, https://mavlink.io/en/guide/serialization.html; a gap of 128 or more reads as a packet behind,
      so a loss of more than 127 packets in a row is not counted whole); a packet behind the last is ``reordered``
      and takes back the loss its gap had counted;
    * a message older than the last of its stream: used where still useful (a magnetometer sample not yet handed
      out, an attitude inside the buffer), a sample older than the last handed out is counted ``late`` and dropped;
    * a stream at a rate more than ``RATE_TOLERANCE`` off the rate asked, over ``RATE_WINDOW_S`` of the vehicle's
      clock (once per stream and boot), or that does not come at all;
    * a reboot: a clock message's boot time more than ``REBOOT_BACK_S`` behind the vehicle's clock; the samples
      waiting are handed out with what they have, the buffers and time base start again, the streams and the
      parameters are asked for again; the sequence counting is redone over the packets since the last clock message
      so that the new boot's counter starting at 0 is not counted as loss; for ``REBOOT_STALE_S`` after it, a clock
      message of the old boot delayed past the reboot is dropped (a magnetometer one counted ``late``);
    * a link that drops: no packet for ``link_timeout_s`` (this computer's clock) with none waiting to be read (a
      poll that comes late reads what waited first), or a TCP connection closed by its other end: "link lost", and
      the samples waiting are handed out; reading goes on (a TCP connection is opened again every ``RECONNECT_S``:
      one attempt, which can block for the system's connect timeout where the host does not answer); "link back"
      when packets come again, and the streams are asked for again.
"""

from __future__ import annotations

import bisect
import contextlib
import io
import math
import socket
import statistics
import struct
import time
from collections import deque

import numpy as np

from ..conventions import MAG, euler_to_quaternion, quaternion_to_euler
from ..errors import InputError
from ..io.dataflash import NT_PER_MILLIGAUSS, _state_index, _untruncate, _version
from ..io.streams import bracket
from ..io.tlog import (
    AUTOPILOT_COMPONENT,
    AUTOPILOTS,
    CLOCK_MESSAGES,
    FIRMWARE_BANNER,
    INTERVALS,
    MAG_MESSAGES,
    MAG_NAMES,
    MAV_AUTOPILOT_INVALID,
    MAV_TYPE_GCS,
    MAX_GAP,
    UNIX_MIN_US,
    UNKNOWN_U16,
    VEHICLE_OF_TYPE,
    boot_time_us,
    highres_unit,
    is_autopilot_heartbeat,
    is_calibrated,
    not_calibrated,
    param_value,
    uncorrect_ardupilot,
    why_not_undone,
)

__all__ = ["ARDUPILOT_PARAMETERS", "PX4_PARAMETERS", "MavlinkSource"]

#: ``HEARTBEAT.base_mode`` bit of an armed vehicle (MAV_MODE_FLAG, https://mavlink.io/en/messages/common.html).
MAV_MODE_FLAG_SAFETY_ARMED = 128
#: ArduPilot's compass parameters whose value the reading depends on: one not read leaves the field partly
#: calibrated, and parameters computed from it would not undo what the vehicle applies.
ESSENTIAL = ("COMPASS_OFS", "COMPASS_DIA", "COMPASS_ODI")

#: The messages whose arrival may complete the samples waiting for attitude, and the samples waiting beyond which
#: they do so at once rather than at the end of the poll.
ATTITUDE_MESSAGES = ("ATTITUDE", "ATTITUDE_QUATERNION")
BACKLOG = 16

#: ArduPilot's compass parameters read (``magkf.io.tlog`` and ``magkf.io.dataflash`` undo with these): each
#: compass's offsets, soft-iron diagonal and off-diagonal, scale, motor compensation, device id and orientation,
#: the priorities, the motor compensation's type and the board's orientation.
ARDUPILOT_PARAMETERS = tuple(
    [
        f"COMPASS_{q}{s}" + (f"_{a}" if a else "")
        for s in ("", "2", "3")
        for q, axes in (("OFS", "XYZ"), ("DIA", "XYZ"), ("ODI", "XYZ"), ("MOT", "XYZ"), ("SCALE", ""), ("DEV_ID", ""))
        for a in (axes or [""])
    ]
    + [f"COMPASS_ORIENT{s}" for s in ("", "2", "3")]
    + [f"COMPASS_PRIO{i}_ID" for i in (1, 2, 3)]
    + ["COMPASS_MOTCT", "COMPASS_PMOT_EN", "AHRS_ORIENTATION"]
)
#: PX4's magnetometer calibration parameters read (``CAL_MAGn_*``, n = 0..3) and the board's rotation.
PX4_PARAMETERS = tuple(
    f"CAL_MAG{n}_{q}"
    for n in range(4)
    for q in ("ID", "PRIO", "ROT", "XOFF", "YOFF", "ZOFF", "XSCALE", "YSCALE", "ZSCALE", "XODIAG", "YODIAG", "ZODIAG")
) + ("SENS_BOARD_ROT",)
#: Seconds (this computer's clock) between rounds of parameter requests, and rounds at most.
PARAM_ROUND_S, PARAM_ROUNDS = 1.0, 3
#: Once an answer has shown the link's round trip, a round ends this many round trips (at least ``PARAM_MIN_S``)
#: after its requests or its last answer, whichever is later.
PARAM_ROUND_TRIPS, PARAM_MIN_S = 4.0, 0.2
#: Requests sent together: a round asks its names this many at a time, the next ones once these are answered or their
#: wait is over (some may then still be in the vehicle's queue: the wait is a few round trips). ArduPilot queues 20
#: requests for all its links together and drops what does not fit (``param_requests`` in
#: ``libraries/GCS_MAVLink/GCS_Param.cpp``); this leaves room for another ground station. A vehicle that has answered
#: none of the first window in its wait (one that does not answer parameters: a one-way forwarded port) is asked the
#: rest of each round at once, so that it is not waited for window by window.
PARAM_WINDOW = 16
#: ``MAV_CMD``s and the ``MAV_DATA_STREAM`` groups of ArduPilot asked for, with the messages magkf reads in each.
MAV_CMD_SET_MESSAGE_INTERVAL, MAV_CMD_REQUEST_MESSAGE = 511, 512
COMMAND_NAMES = {
    511: ("MAV_CMD_SET_MESSAGE_INTERVAL", ": the streams come at the rates of their groups"),
    512: ("MAV_CMD_REQUEST_MESSAGE", ": the firmware is named by its banner, if it sends one"),
}
#: ``MAV_RESULT`` of a command that is not refused.
MAV_RESULT_ACCEPTED, MAV_RESULT_IN_PROGRESS = 0, 5
ARDUPILOT_GROUPS = {1: ("RAW_IMU", "SCALED_IMU2", "SCALED_IMU3"), 2: ("GPS_RAW_INT",), 10: ("ATTITUDE",)} | {
    11: ("VFR_HUD",),
    12: ("SYSTEM_TIME", "BATTERY_STATUS"),
}
#: Rates (Hz) asked for the slow streams; the magnetometer and attitude are asked at ``rate_hz``.
SLOW_RATES_HZ = {"GPS_RAW_INT": 5.0, "SYSTEM_TIME": 1.0, "BATTERY_STATUS": 2.0, "VFR_HUD": 2.0}
#: Seconds of the vehicle's clock to hold samples for the first ``SYSTEM_TIME``; ``SYSTEM_TIME`` messages whose
#: offsets make the median; receipt offsets kept for the fallback.
HOLD_S, SYSTEM_TIME_KEPT, RECEIPT_KEPT = 2.0, 20, 50
#: A clock message this far (s) behind the vehicle's clock is a reboot; for this long (s, this computer's clock)
#: after one, a clock message of the boot before (delayed past it) is told apart and dropped.
REBOOT_BACK_S, REBOOT_STALE_S = 1.0, 2.0
#: Messages kept from before the vehicle's HEARTBEAT, handled once it has come.
EARLY_KEPT = 1000
#: Rates are measured over this many seconds of the vehicle's clock; a rate this far off (relative) is reported.
RATE_WINDOW_S, RATE_TOLERANCE = 5.0, 0.2
#: Attitude is interpolated across gaps up to this many of its median intervals, and at least this many seconds;
#: attitude messages kept at most (samples wait for them at most ``HOLD_S``: 2.5 s at 400 Hz).
ATTITUDE_GAP_INTERVALS, ATTITUDE_GAP_S, ATTITUDE_KEPT = 2.5, 0.5, 1000
#: A GNSS fix, current, throttle or temperature older than this many intervals of its stream (at least
#: ``STALE_MIN_S``) is not given to a sample.
STALE_INTERVALS, STALE_MIN_S = 3.0, 1.0
#: Values kept of each slow stream (GNSS, current, throttle, temperature) for the samples waiting.
SLOW_KEPT = 16
#: Seconds between the ground station's ``HEARTBEAT``s, and between attempts to open a TCP connection again.
HEARTBEAT_S, RECONNECT_S = 1.0, 1.0
#: Packets kept for redoing the sequence counting at a reboot; receive buffer asked for a UDP socket (bytes).
SEQUENCE_HISTORY, UDP_BUFFER_BYTES = 256, 1 << 21
#: The link is read in bursts: once what has arrived is handled, the reader sleeps this long (s) before reading
#: again, rather than waking at each packet (a vehicle streaming 300 packets a second would wake it 300 times);
#: after a burst of ``BURST_PACKETS`` or more it reads on at once (a fast replay, a backlog), so that what waits
#: in the receive buffer stays far below its size.
BURST_S, BURST_PACKETS = 0.02, 64
#: ``MAV_PARAM_TYPE_REAL32``.
PARAM_REAL32 = 9


def slerp(q0: np.ndarray, q1: np.ndarray, fraction: np.ndarray) -> np.ndarray:
    """Spherical linear interpolation (N, 4) between unit quaternions ``q0`` and ``q1`` (N, 4, scalar first) at
    ``fraction`` (N,) of the way, along the shorter arc: the rotation ``io.streams.interpolate_quaternions`` gives
    (scipy's ``Slerp``), for pairs already bracketed, without building an interpolator over every sample kept
    (a tenth of the cost at the few samples a poll completes)."""
    dot = np.einsum("ij,ij->i", q0, q1)
    q1 = np.where(dot[:, None] < 0.0, -q1, q1)
    angle = np.arccos(np.clip(np.abs(dot), -1.0, 1.0))
    sin = np.sin(angle)
    tiny = sin < 1e-12  # the same rotation: either end
    safe = np.where(tiny, 1.0, sin)
    w0 = np.where(tiny, 1.0 - fraction, np.sin((1.0 - fraction) * angle) / safe)
    w1 = np.where(tiny, fraction, np.sin(fraction * angle) / safe)
    q = w0[:, None] * q0 + w1[:, None] * q1
    return q / np.linalg.norm(q, axis=1, keepdims=True)


class _SequenceCount:
    """Lost and reordered packets of one sender from its sequence numbers (0..255, one per packet)."""

    def __init__(self):
        self.last: int | None = None
        self.lost = self.reordered = 0
        self.history: deque = deque(maxlen=SEQUENCE_HISTORY)  # (seq, lost added, reordered added)

    def add(self, seq: int) -> None:
        lost, reordered, self.last = _count_step(seq, self.last, self.lost)
        self.lost += lost
        self.reordered += reordered
        self.history.append((seq, lost, reordered))

    def restart(self, packets: int) -> None:
        """The sender's counter started again from 0 somewhere in its last ``packets`` packets (a reboot): count
        them again, split where the count comes out smallest."""
        span = list(self.history)[-packets:] if packets else []
        if not span:
            return
        self.lost -= sum(s[1] for s in span)
        self.reordered -= sum(s[2] for s in span)
        before = list(self.history)[: len(self.history) - len(span)]
        last = before[-1][0] if before else None
        seqs = [s[0] for s in span]
        best = min(range(len(seqs) + 1), key=lambda k: _count(seqs[:k], last)[0] + _count(seqs[k:], -1)[0])
        old, new = _count(seqs[:best], last), _count(seqs[best:], -1)
        self.lost += old[0] + new[0]
        self.reordered += old[1] + new[1]
        self.last = new[2] if best < len(seqs) else old[2]
        self.history.clear()


def _count_step(seq: int, last: int | None, lost_so_far: int) -> tuple[int, int, int | None]:
    """``(lost added, reordered added, new last)`` for packet ``seq`` after ``last`` (None: the first)."""
    if last is None:
        return 0, 0, seq
    gap = (seq - last - 1) % 256
    if gap < 128:
        return gap, 0, seq
    return (-1 if lost_so_far > 0 else 0), 1, last


def _count(seqs: list[int], last: int | None) -> tuple[int, int, int | None]:
    lost = reordered = 0
    for seq in seqs:
        a, b, last = _count_step(seq, last, lost)
        lost, reordered = lost + a, reordered + b
    return lost, reordered, last


class MavlinkSource:
    """A vehicle's MAVLink link: its streams asked for, its compass parameters, its messages as samples.

    Parameters
    ----------
    connection : str
        Anything ``pymavlink.mavutil.mavlink_connection`` opens: ``udpin:127.0.0.1:14550``, ``udpout:HOST:PORT``,
        ``tcp:HOST:PORT``, a serial device.
    baud : int
        Serial link's baud rate.
    mag : int or None
        Magnetometer instance (0 ``RAW_IMU``/PX4 ``SCALED_IMU``, 1 ``SCALED_IMU2``, 2 ``SCALED_IMU3``, 3
        ``HIGHRES_IMU``); None: the first that comes with a field.
    raw : bool
        Undo the autopilot's calibration where the message carries it and its parameters are read.
    rate_hz : float
        Rate asked for the magnetometer and attitude streams, Hz.
    link_timeout_s : float
        Seconds without a packet after which the link is reported lost.
    wait_s : float
        Seconds of the vehicle's clock a sample waits for an attitude message at or after its time.
    source_system, source_component : int
        This ground station's MAVLink ids (250, 190): not 255, the ground stations' usual system id, which
        ArduPilot's ground-station failsafe follows (``SYSID_MYGCS``): a session that ends must not look like the
        pilot's ground station going silent.

    Attributes
    ----------
    counters : dict of str to int
        ``packets`` (of the vehicle's autopilot), ``lost``, ``reordered``, ``samples`` (handed out), ``late``,
        ``reboots``, ``link_drops``.
    asked_hz : dict of str to float
        Rate asked per message name.
    params : dict of str to float
        The parameters read (``PARAM_VALUE``; PX4's integers decoded from their bytes).
    autopilot : str or None
        ``"ardupilot"`` or ``"px4"`` (None: another).
    firmware : str or None
        The firmware's ``STATUSTEXT`` banner, else ``"ArduCopter V4.5.7"`` / ``"PX4 1.15.0"`` from
        ``AUTOPILOT_VERSION``; None until one comes.
    provenance : dict
        JSON-ready, with the keys of ``magkf.io.tlog``'s (``format`` ``mavlink-tlog``: the messages a telemetry log
        holds) and ``live`` True, ``connection``: the vehicle, magnetometer message, what was undone
        (``raw_reconstruction``), time base, compass parameters, notes.
    """

    def __init__(
        self,
        connection: str,
        *,
        baud: int = 57600,
        mag: int | None = None,
        raw: bool = True,
        rate_hz: float = 50.0,
        link_timeout_s: float = 3.0,
        wait_s: float = 0.5,
        source_system: int = 250,
        source_component: int = 190,
    ):
        self.connection, self.baud, self.mag, self.raw = str(connection), baud, mag, raw
        self.rate_hz, self.link_timeout_s, self.wait_s = float(rate_hz), float(link_timeout_s), float(wait_s)
        self.source_system, self.source_component = source_system, source_component
        self.counters = dict.fromkeys(("packets", "lost", "reordered", "samples", "late", "reboots", "link_drops"), 0)
        self.asked_hz: dict[str, float] = {}
        self.params: dict[str, float] = {}
        self.autopilot: str | None = None
        self.firmware: str | None = None
        self.provenance: dict = {"format": "mavlink-tlog", "live": True, "connection": self.connection, "notes": []}
        self._conn = None
        self._opened = False
        self._events: list[str] = []
        self._vehicle: tuple[int, int] | None = None
        self._type: int | None = None
        self._never_answered: tuple = ()
        self.armed = False  # HEARTBEAT.base_mode's MAV_MODE_FLAG_SAFETY_ARMED, the vehicle's last
        self._version: tuple[int, int, int] | None = None
        self._param_types: dict[str, int] = {}
        self._param_wanted: set[str] = set()
        self._param_queue: list[str] = []  # the round's names not asked yet
        self._param_window: set[str] = set()
        self._param_window_sent = False
        self._param_next = 0.0
        self._param_sent = -math.inf
        self._param_round_trip: float | None = None
        self._param_asked = 0
        self._param_reading = False
        self._params_read = False  # the first read is over: samples are handed out from then on
        self._made: list[dict] = []  # samples handed out at a reboot, before the parameters are read again
        self._collect_echoes = False
        self._sequence = _SequenceCount()
        self._since_clock = 0
        self._early: deque = deque(maxlen=EARLY_KEPT)  # messages before the vehicle's HEARTBEAT
        self._last_packet = self._last_heartbeat = self._last_reconnect = -math.inf
        self._link_down = self._peer_closed = False
        self._is_tcp = self.connection.startswith("tcp:")
        self._stream: str | None = None
        self._highres_per_count: float | None = None
        self._highres_notes: list[str] = []
        self._ready: list[dict] = []
        self._last_out = -math.inf
        self._undo_notes: set[str] = set()
        self._echoes: list = []
        self._old_boot_end_us: float | None = None
        self._reboot_wall = -math.inf
        self._reset_boot()

    # ------------------------------------------------------------------ opening and closing
    def open(self, timeout_s: float = 30.0) -> None:
        """Connect, wait for the vehicle's ``HEARTBEAT``, ask for the streams and read the compass parameters.

        Raises
        ------
        InputError
            Naming the connection: it cannot be opened, or no vehicle's ``HEARTBEAT`` came within ``timeout_s``.
        """
        deadline = time.monotonic() + timeout_s
        self._conn = self._connect()
        self._opened = True
        while self._vehicle is None:
            if time.monotonic() > deadline:
                self.close()
                raise InputError(
                    f"no HEARTBEAT of a vehicle's autopilot (component 1) within {timeout_s:g} s: check that the "
                    "vehicle is on, that this is its link (port, baud rate) and that nothing else holds the port",
                    self.connection,
                )
            self._read_for(0.05)
        self._ask_streams()
        self._ask_parameters()
        while self._param_reading and time.monotonic() < deadline:
            self._read_for(0.05)

    def _connect(self):
        from pymavlink import mavutil

        try:
            with contextlib.redirect_stdout(io.StringIO()):
                conn = mavutil.mavlink_connection(
                    self.connection,
                    baud=self.baud,
                    source_system=self.source_system,
                    source_component=self.source_component,
                    dialect="ardupilotmega",
                    retries=0,
                )
        except ModuleNotFoundError as exc:  # pymavlink imports pyserial only for a serial device
            raise InputError(
                f"cannot open a serial device without the {exc.name} module (pip install pyserial); a network link is "
                "udpin:HOST:PORT, udpout:HOST:PORT or tcp:HOST:PORT",
                self.connection,
            ) from None
        except (OSError, ValueError) as exc:
            raise InputError(
                f"cannot open the connection ({exc}); a connection is udpin:HOST:PORT, udpout:HOST:PORT, "
                "tcp:HOST:PORT or a serial device with its baud rate",
                self.connection,
            ) from None
        if hasattr(conn, "handle_eof"):  # TCP: know when the other end closes (instead of pymavlink's print and
            # reconnection inside its read)
            conn.handle_eof = conn.handle_disconnect = self._peer_closed_connection
        port = getattr(conn, "port", None)
        if isinstance(port, socket.socket) and port.type == socket.SOCK_DGRAM:
            with contextlib.suppress(OSError):
                port.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, UDP_BUFFER_BYTES)
        return conn

    def close(self) -> None:
        """Close the connection (the samples not handed out are dropped)."""
        self._opened = False
        self._drop_connection()

    def _drop_connection(self) -> None:
        if self._conn is not None:
            with contextlib.suppress(Exception):
                self._conn.close()
            self._conn = None

    # ------------------------------------------------------------------ reading
    def poll(self, timeout_s: float = 0.1) -> list[dict]:
        """Read what arrives for up to ``timeout_s`` s; return the samples now complete, in time order.

        Returns
        -------
        list of dict
            Each ``time`` (UNIX s), ``mag_x, mag_y, mag_z`` (nT), ``roll, pitch, yaw`` (deg; NaN without
            attitude), ``lat, lon`` (deg), ``alt`` (m), ``hdop``, ``vdop`` (NaN without a recent 3-D fix), and
            ``current_a`` (A), ``throttle`` (0..1), ``temp_c`` (degC) where the vehicle sends them.
        """
        if not self._opened:
            raise InputError("the connection is not open: call open() first", self.connection)
        self._read_for(timeout_s)
        return self._hand_out()

    @property
    def missing_compass_parameters(self) -> tuple:
        """ArduPilot's offsets and matrices of the compass the samples come from that the vehicle never answered
        for (the field is then partly its calibration, and parameters computed from it would not undo what it
        applies)."""
        compass = (self.provenance.get("magnetometer") or {}).get("compass", 1)
        suffix = "" if compass in (None, 1) else str(compass)
        own = tuple(f"{stem}{suffix}_" for stem in ESSENTIAL)
        return tuple(n for n in self._never_answered if n.startswith(own))

    def drain(self) -> list[dict]:
        """The samples still waiting for attitude, handed out now (attitude where it brackets them, else NaN), with
        those ready: at the end of a session, so that none is left unaccounted for."""
        if self._pending and self._time_base_ready():
            self._finish(self._pending)
            self._pending = []
        return self._hand_out()

    def take_events(self) -> list[str]:
        """What happened since the last call, in words, one line each."""
        events, self._events = self._events, []
        return events

    def _event(self, text: str) -> None:
        self._events.append(text)

    def _read_for(self, timeout_s: float) -> None:
        """Handle the messages that arrive within ``timeout_s`` s, and the link's housekeeping."""
        end = time.monotonic() + max(timeout_s, 0.0)
        burst = 0
        while True:
            msg = self._receive()
            self._housekeeping(idle=msg is None)
            if msg is not None:
                burst += 1
                self._handle(msg)
                if len(self._pending) >= BACKLOG and msg.get_type() in ATTITUDE_MESSAGES:
                    # a backlog (the link read through after a stall) completed as its attitude comes, while a
                    # slow stream's kept values (SLOW_KEPT) still cover it; else once a poll (each completion
                    # interpolates the attitude: 10 a second, not one a sample)
                    self._complete()
                continue
            remaining = end - time.monotonic()
            if remaining <= 0:
                break
            if burst >= BURST_PACKETS and self._conn is not None and not self._peer_closed:
                with contextlib.suppress(Exception):
                    self._conn.select(min(remaining, BURST_S))
            else:
                time.sleep(min(remaining, BURST_S))
            burst = 0
        self._complete()
        self._check_rates()

    def _receive(self):
        if self._conn is None or self._peer_closed:
            return None
        try:
            return self._conn.recv_msg()
        except (OSError, struct.error, ValueError):
            return None

    def _housekeeping(self, idle: bool) -> None:
        """The ground station's heartbeat, parameter rounds and, when nothing is waiting to be read (``idle``: the
        last read found no message), the link's state and a TCP reconnection. A silence is judged only then: after
        this computer was too busy to read for a while, the packets waiting in the socket are read, not dropped
        with a connection opened again."""
        now = time.monotonic()
        if now - self._last_heartbeat >= HEARTBEAT_S and self._conn is not None:
            self._last_heartbeat = now
            self._send("heartbeat_send", MAV_TYPE_GCS, MAV_AUTOPILOT_INVALID, 0, 0, 0)
        if idle and not self._link_down and self._vehicle is not None and now - self._last_packet > self.link_timeout_s:
            self._link_lost(f"no packet for {now - self._last_packet:.1f} s; still listening")
        reopen = (self._link_down or self._peer_closed) and self._is_tcp and now - self._last_reconnect >= RECONNECT_S
        if idle and reopen:
            self._reconnect(now)
        if self._param_reading and now >= self._param_next:
            self._parameter_round(now)

    def _link_lost(self, why: str) -> None:
        """Report the link lost and hand out the samples waiting (no more attitude is coming for them)."""
        self._link_down = True
        self.counters["link_drops"] += 1
        self._event(f"link lost: {why}")
        if self._pending and self._time_base_ready():
            self._finish(self._pending)
            self._pending = []

    def _peer_closed_connection(self) -> None:
        """pymavlink's TCP connection saw its other end close it (end of file, reset)."""
        self._peer_closed = True
        if not self._link_down and self._vehicle is not None:
            self._link_lost("the TCP connection was closed by the other end; opening it again")

    def _reconnect(self, now: float) -> None:
        """Open the TCP connection again (one attempt every ``RECONNECT_S``)."""
        self._last_reconnect = now
        self._drop_connection()
        with contextlib.suppress(InputError):
            self._conn = self._connect()
            self._peer_closed = False
            self._last_heartbeat = -math.inf  # announce this ground station at once

    def _send(self, method: str, *args) -> None:
        if self._conn is None:
            return
        with contextlib.suppress(OSError):
            getattr(self._conn.mav, method)(*args)

    # ------------------------------------------------------------------ messages
    def _handle(self, msg) -> None:
        name = msg.get_type()
        if name == "BAD_DATA":
            return
        source = (msg.get_srcSystem(), msg.get_srcComponent())
        if self._vehicle is None:
            self._choose(msg, name, source)
            return
        if source != self._vehicle:
            return
        boot_us = boot_time_us(msg)
        stale = name in CLOCK_MESSAGES and boot_us is not None and self._before_reboot(boot_us)
        self._packet(msg, sequence=not stale)  # the old boot's counter is not the new one's
        if stale:
            self.counters["late"] += name == self._stream
            return
        if name in CLOCK_MESSAGES and boot_us is not None:
            if self._clock_us is not None and boot_us < self._clock_us - REBOOT_BACK_S * 1e6:
                self._reboot(boot_us)
            self._since_clock = 0
            self._receipt.append(time.time() * 1e6 - boot_us)
            if self._clock_us is None and not math.isfinite(self._rates_since_us):
                self._rates_since_us = float(boot_us)
            self._clock_us = boot_us if self._clock_us is None else max(self._clock_us, boot_us)
        self._arrived(name)
        handler = getattr(self, f"_on_{name.lower()}", None)
        if handler is not None:
            handler(msg, boot_us)
        elif name in MAG_NAMES:
            self._on_magnetometer(msg, boot_us)

    def _choose(self, msg, name: str, source: tuple[int, int]) -> None:
        """Keep the messages before the vehicle's HEARTBEAT; on it, take that vehicle and handle them."""
        self._early.append(msg)
        if is_autopilot_heartbeat(msg):
            self._vehicle, self._type = source, int(msg.type)
            self.autopilot = AUTOPILOTS.get(int(msg.autopilot))
            self.provenance["vehicle"] = {"sysid": source[0], "compid": source[1], "autopilot": self.autopilot}
            self._event(
                f"vehicle: system {source[0]} component {source[1]}, "
                f"{self.autopilot or f'autopilot MAV_AUTOPILOT {int(msg.autopilot)}'}"
            )
            early, self._early = list(self._early), deque(maxlen=EARLY_KEPT)
            for m in early:
                self._handle(m)

    def _packet(self, msg, sequence: bool = True) -> None:
        now = time.monotonic()
        if self._link_down:
            self._link_down = False
            self._event(f"link back after {now - self._last_packet:.1f} s")
            self._sequence.last = None  # a counter that went on through the outage: its gap is not a count of losses
            self._ask_streams()
        self._last_packet = now
        self.counters["packets"] += 1
        if not sequence:
            return
        self._sequence.add(msg.get_seq())
        self._since_clock += 1
        self.counters["lost"], self.counters["reordered"] = self._sequence.lost, self._sequence.reordered

    def _vehicle_us(self) -> float:
        """The vehicle's clock (us): the latest boot time of its clock messages, else this computer's."""
        return float(self._clock_us) if self._clock_us is not None else time.time() * 1e6

    def _arrived(self, name: str) -> None:
        if self._clock_us is None:
            return  # no time of the vehicle's to count it by yet
        times = self._arrivals.setdefault(name, deque())
        times.append(self._vehicle_us())
        while times and times[0] < times[-1] - RATE_WINDOW_S * 1e6:
            times.popleft()

    def _on_heartbeat(self, msg, boot_us) -> None:
        self._type = int(msg.type)
        self.armed = bool(msg.base_mode & MAV_MODE_FLAG_SAFETY_ARMED)

    def _on_system_time(self, msg, boot_us) -> None:
        if msg.time_unix_usec <= UNIX_MIN_US:
            return
        first = not self._utc
        self._utc.append(float(msg.time_unix_usec) - float(msg.time_boot_ms) * 1000.0)
        if first and self._fallback:
            self._event("SYSTEM_TIME arrived: times are the vehicle's UNIX clock from now on")
        self._fallback = False

    def _on_param_value(self, msg, boot_us) -> None:
        name = msg.param_id.rstrip("\x00") if isinstance(msg.param_id, str) else str(msg.param_id)
        self.params[name] = param_value(msg, self.autopilot)
        self._param_types[name] = int(msg.param_type)
        if self._param_reading and name in self._param_wanted:
            now = time.monotonic()
            if self._param_round_trip is None and math.isfinite(self._param_sent):
                self._param_round_trip = now - self._param_sent
            self._param_window.discard(name)
            # the next requests go once these are answered; else the round goes on while answers come
            self._param_next = now if not self._param_window else now + self._round_wait()
        self._param_wanted.discard(name)
        if self._collect_echoes:
            self._echoes.append((name, self.params[name]))
        if self._param_reading and not self._param_wanted:
            self._end_parameter_read()

    def _on_statustext(self, msg, boot_us) -> None:
        text = str(msg.text).rstrip("\x00").strip()
        if FIRMWARE_BANNER.match(text) and not (self.firmware and FIRMWARE_BANNER.match(self.firmware)):
            self.firmware = text
            self._event(f"firmware: {text}")

    def _on_autopilot_version(self, msg, boot_us) -> None:
        v = int(msg.flight_sw_version)
        if v == 0:
            return
        self._version = (v >> 24 & 0xFF, v >> 16 & 0xFF, v >> 8 & 0xFF)
        if self.firmware is None:
            numbers = ".".join(map(str, self._version))
            kind = VEHICLE_OF_TYPE.get(self._type, "Pilot") if self._type is not None else "Pilot"
            self.firmware = f"Ardu{kind} V{numbers}" if self.autopilot == "ardupilot" else f"PX4 {numbers}"
            self._event(f"firmware: {self.firmware} (AUTOPILOT_VERSION)")

    def _on_command_ack(self, msg, boot_us) -> None:
        command, result = int(msg.command), int(msg.result)
        if result not in (MAV_RESULT_ACCEPTED, MAV_RESULT_IN_PROGRESS) and command not in self._refused:
            self._refused.add(command)
            what, meaning = COMMAND_NAMES.get(command, (f"MAV_CMD {command}", ""))
            self._event(f"the vehicle refused {what} (MAV_RESULT {result}){meaning}")

    def _on_attitude(self, msg, boot_us) -> None:
        q = euler_to_quaternion(math.degrees(msg.yaw), math.degrees(msg.pitch), math.degrees(msg.roll))
        self._attitude_in(boot_us, q, "ATTITUDE")

    def _on_attitude_quaternion(self, msg, boot_us) -> None:
        if "ATTITUDE" in self._arrivals:
            return
        self._attitude_in(boot_us, np.array([msg.q1, msg.q2, msg.q3, msg.q4], float), "ATTITUDE_QUATERNION")

    def _attitude_in(self, boot_us, q, name: str) -> None:
        if boot_us is None:
            return
        at = bisect.bisect_left(self._att_t, boot_us)
        if at < len(self._att_t) and self._att_t[at] == boot_us:
            return  # the same time twice
        self._att_t.insert(at, boot_us)
        self._att_q.insert(at, q)
        self._att_source = name
        if len(self._att_t) > ATTITUDE_KEPT:  # no samples to use them (no magnetometer stream): keep the latest
            del self._att_t[0], self._att_q[0]

    def _on_gps_raw_int(self, msg, boot_us) -> None:
        t = float(msg.time_usec)
        if t >= UNIX_MIN_US:
            offset = self._utc_offset()
            t = t - offset if offset is not None else self._vehicle_us()
        elif t <= 0:
            t = self._vehicle_us()
        ellipsoid = getattr(msg, "alt_ellipsoid", 0)
        fix = {
            "fix": int(msg.fix_type),
            "lat": msg.lat / 1e7,
            "lon": msg.lon / 1e7,
            "alt": (ellipsoid if ellipsoid else msg.alt) / 1000.0,
            "hdop": msg.eph / 100.0 if msg.eph != UNKNOWN_U16 else math.nan,
            "vdop": msg.epv / 100.0 if msg.epv != UNKNOWN_U16 else math.nan,
        }
        self._keep("gnss", t, fix, "GPS_RAW_INT")

    def _keep(self, key: str, t: float, value, message: str) -> None:
        """A slow stream's value at the vehicle's time ``t`` (us), kept for the samples around it (none before the
        vehicle's first clock message: there is no time to place it at)."""
        if self._clock_us is None:
            return
        self._slow.setdefault(key, deque(maxlen=SLOW_KEPT)).append((t, value, message))

    def _on_battery_status(self, msg, boot_us) -> None:
        if msg.id == 0 and msg.current_battery != -1:
            self._keep("current_a", self._vehicle_us(), msg.current_battery * 0.01, "BATTERY_STATUS")

    def _on_sys_status(self, msg, boot_us) -> None:
        if msg.current_battery != -1 and "BATTERY_STATUS" not in self._arrivals:
            self._keep("current_a", self._vehicle_us(), msg.current_battery * 0.01, "SYS_STATUS")

    def _on_vfr_hud(self, msg, boot_us) -> None:
        self._keep("throttle", self._vehicle_us(), msg.throttle * 0.01, "VFR_HUD")

    def _on_scaled_pressure(self, msg, boot_us) -> None:
        self._keep("pressure_temp_c", self._vehicle_us(), msg.temperature * 0.01, "SCALED_PRESSURE")

    def _on_magnetometer(self, msg, boot_us) -> None:
        name = msg.get_type()
        if boot_us is None or not self._is_chosen(msg, name):
            return
        if boot_us <= self._last_out_boot:
            self.counters["late"] += 1
            return
        pending = self._pending
        if not pending or boot_us > pending[-1]["boot_us"]:
            at = len(pending)  # in order, as nearly always
        else:
            at = bisect.bisect_left([s["boot_us"] for s in pending], boot_us)
            if pending[at]["boot_us"] == boot_us:
                return  # the same message twice
        field = np.array([msg.xmag, msg.ymag, msg.zmag], float)
        sample = {"boot_us": boot_us, "field": field, "message": name}
        temperature = getattr(msg, "temperature", 0) if name != "HIGHRES_IMU" else 0  # HIGHRES_IMU's is degC
        if temperature:
            sample["temp_c"] = temperature * 0.01
        self._pending.insert(at, sample)

    def _is_chosen(self, msg, name: str) -> bool:
        """Whether ``msg`` is of the magnetometer stream read (chosen on the first with a field)."""
        if self._stream is not None:
            return name == self._stream
        if msg.xmag == 0 and msg.ymag == 0 and msg.zmag == 0:
            return False
        instance = next(i for i, m, _ in MAG_MESSAGES if m == name)
        if self.mag is not None and instance != self.mag:
            return False
        self._stream = name
        self.provenance["magnetometer"] = {"message": name, "instance": instance, "autopilot": self.autopilot}
        self._event(f"magnetometer: {name} (instance {instance})")
        return True

    def _slow_values(self, sample: dict) -> dict:
        """The GNSS fix and auxiliary values at a sample: each stream's latest at or before its time (NaN where
        stale or absent; a column the vehicle never sent is left out)."""
        boot_us = sample["boot_us"]
        out = dict.fromkeys(("lat", "lon", "alt", "hdop", "vdop"), math.nan)
        fix = self._latest("gnss", boot_us)
        if fix is not None and fix["fix"] >= 3:
            out |= {k: fix[k] for k in out}
        for column in ("current_a", "throttle"):
            if column in self._slow:
                value = self._latest(column, boot_us)
                out[column] = value if value is not None else math.nan
        if "temp_c" not in sample and "pressure_temp_c" in self._slow:
            value = self._latest("pressure_temp_c", boot_us)
            out["temp_c"] = value if value is not None else math.nan
        return out

    def _latest(self, key: str, boot_us: float):
        """The value of slow stream ``key`` at ``boot_us``: the latest at or before it, else the first after it;
        None where there is none within ``STALE_INTERVALS`` of its interval."""
        kept = self._slow.get(key)
        if not kept:
            return None
        for entry in reversed(kept):  # the latest received at or before it
            if entry[0] <= boot_us:
                break
        else:
            entry = min(kept, key=lambda e: e[0])
        t, value, message = entry
        return value if abs(boot_us - t) <= self._stale_us(message) else None

    def _stale_us(self, name: str) -> float:
        """How far (us) a slow stream's value may lie from a sample: ``STALE_INTERVALS`` of its median interval
        (at least ``STALE_MIN_S``), the median taken again once a second of the vehicle's clock."""
        now = self._vehicle_us()
        cached = self._stale.get(name)
        if cached is not None and now - cached[0] < 1e6:
            return cached[1]
        times = self._arrivals.get(name, ())
        interval = float(np.median(np.diff(times))) if len(times) > 2 else 0.0
        stale = max(STALE_INTERVALS * interval, STALE_MIN_S * 1e6)
        self._stale[name] = (now, stale)
        return stale

    # ------------------------------------------------------------------ time
    def _utc_offset(self) -> float | None:
        """UNIX us less boot us: ``SYSTEM_TIME``'s median, else the receipt clock's once it stands in."""
        if self._utc:
            return statistics.median(self._utc)
        if self._fallback:
            return self._fallback_offset
        return None

    def _time_base_ready(self) -> bool:
        if self._utc or self._fallback:
            return True
        if self._pending and self._vehicle_us() - self._pending[0]["boot_us"] > HOLD_S * 1e6 and self._receipt:
            self._fallback = True
            self._fallback_offset = statistics.median(self._receipt)
            self._event(
                f"no SYSTEM_TIME within {HOLD_S:g} s: times are this computer's clock on receipt (late by the "
                "link's latency) until one comes"
            )
            return True
        return False

    # ------------------------------------------------------------------ samples
    def _complete(self) -> None:
        """Move the samples now complete from the front of the waiting ones to those ready."""
        if not self._pending or not self._time_base_ready():
            return
        latest_attitude = self._att_t[-1] if self._att_t else -math.inf
        now = self._vehicle_us()
        done = 0
        for sample in self._pending:
            if latest_attitude > sample["boot_us"] or now >= sample["boot_us"] + self.wait_s * 1e6:
                done += 1
            else:
                break
        if done:
            self._finish(self._pending[:done])
            del self._pending[:done]

    def _finish(self, samples: list[dict]) -> None:
        """Samples given their UNIX time and interpolated attitude, put among those ready (late ones dropped)."""
        offset = self._utc_offset()
        boot = np.array([s["boot_us"] for s in samples], float)
        angles = self._attitude_at(boot)
        for sample, (yaw, pitch, roll) in zip(samples, angles):
            t = (sample["boot_us"] + offset) * 1e-6
            self._last_out_boot = max(self._last_out_boot, sample["boot_us"])
            if t <= self._last_out:
                self.counters["late"] += 1
                continue
            self._last_out = t
            self._ready.append(
                sample | self._slow_values(sample) | {"time": t, "roll": roll, "pitch": pitch, "yaw": yaw}
            )
        self._prune_attitude(boot[-1])

    def _attitude_at(self, boot_us: np.ndarray) -> np.ndarray:
        """(N, 3) yaw, pitch, roll (deg) at ``boot_us``, NaN where no attitude brackets it."""
        if len(self._att_t) < 2:
            return np.full((len(boot_us), 3), np.nan)
        t_src = np.array(self._att_t, float) * 1e-6
        gap = max(ATTITUDE_GAP_S, ATTITUDE_GAP_INTERVALS * float(np.median(np.diff(t_src))))
        i, frac, valid = bracket(boot_us * 1e-6, t_src, gap)
        out = np.full((len(boot_us), 3), np.nan)
        if valid.any():
            q = np.array(self._att_q, float)
            q /= np.linalg.norm(q, axis=1, keepdims=True)
            yaw, pitch, roll = quaternion_to_euler(slerp(q[i[valid]], q[i[valid] + 1], frac[valid]))
            out[valid] = np.column_stack([yaw, pitch, roll])
        return out

    def _prune_attitude(self, handed_out_us: float) -> None:
        """Keep the attitude from the one before the last sample handed out on (and a few more for the median)."""
        keep_from = max(bisect.bisect_right(self._att_t, handed_out_us) - 8, 0)
        del self._att_t[:keep_from]
        del self._att_q[:keep_from]

    def _hand_out(self) -> list[dict]:
        """The ready samples with their field in nT (calibration undone where it can be), once the parameter read
        is over (after a reboot, once the parameters in force are read again); those made at the reboot first."""
        made, self._made = self._made, []
        if not self._ready or not self._params_read:
            return made
        ready, self._ready = self._ready, []
        fields = self._fields(ready)
        out = []
        for sample, field in zip(ready, fields):
            row = {"time": sample["time"], **dict(zip(MAG, (float(v) for v in field)))}
            row |= {k: float(sample[k]) for k in ("roll", "pitch", "yaw", "lat", "lon", "alt", "hdop", "vdop")}
            row |= {k: float(sample[k]) for k in ("current_a", "throttle", "temp_c") if k in sample}
            out.append(row)
        self.counters["samples"] += len(out)
        return made + out

    def _fields(self, samples: list[dict]) -> np.ndarray:
        """(N, 3) nT of ``samples`` (all of one message): as sent, or with ArduPilot's calibration undone."""
        message = samples[0]["message"]
        counts = np.array([s["field"] for s in samples])
        if message == "HIGHRES_IMU":
            if self._highres_per_count is None:  # the unit judged once, on the first samples, as the log reader does
                self._highres_per_count, _ = highres_unit(counts, self.autopilot, self._highres_notes)
            nt = counts * self._highres_per_count
        else:
            nt = _untruncate(counts) * NT_PER_MILLIGAUSS
        nt[np.all(counts == 0, axis=1)] = np.nan
        undone, text, notes = self._undo(nt, samples, message)
        notes += self._highres_notes
        self.provenance["raw_reconstruction"] = text
        self._magnetometer_provenance(message, undone is not None)
        for note in notes:
            if note not in self._undo_notes:
                self._undo_notes.add(note)
                self.provenance["notes"].append(note)
                self._event(note)
        return undone if undone is not None else nt

    def _undo(self, nt: np.ndarray, samples: list[dict], message: str) -> tuple[np.ndarray | None, str, list]:
        """The raw field (nT) where ArduPilot's calibration can be undone (else None), what was done, notes."""
        notes: list[str] = []
        calibrated = is_calibrated(message, self.autopilot, self._version)
        if not calibrated:
            return None, not_calibrated(message, calibrated, self._version, notes), notes
        if not self.raw:
            return None, "not done (raw=False): the field as the autopilot corrected it", notes
        has_compass = any(k.startswith("COMPASS_") for k in self.params)
        why = why_not_undone(message, self.autopilot, has_compass)
        if why is not None:
            notes.append(
                f"{message} carries the autopilot's calibrated field and its calibration cannot be undone ({why}): "
                "read as sent; a calibration fitted to it is relative to the autopilot's"
            )
            return None, f"not done ({why}): the field as the autopilot corrected it", notes
        boot = np.array([s["boot_us"] for s in samples], float)
        params = {k: (np.zeros(1, np.int64), np.array([v], float)) for k, v in self.params.items()}
        aux: dict = {INTERVALS: {}, MAX_GAP: math.inf}
        for column in ("throttle", "current_a"):
            if column in self._slow:
                aux[column] = np.array([s.get(column, math.nan) for s in samples], float)
        instance = next(i for i, m, _ in MAG_MESSAGES if m == message)
        if self.firmware is None or _version(self.firmware) is None:
            notes.append(
                f"ArduPilot firmware {self.firmware or 'unknown'} (no AUTOPILOT_VERSION or STATUSTEXT banner with a "
                "version): the 4.x correction model was assumed; before 4.0 there was no COMPASS_SCALE, and Copter "
                "3.3 to 3.5 added the motor compensation before the soft-iron matrix"
            )
        raw_mg, text, _ = uncorrect_ardupilot(nt / NT_PER_MILLIGAUSS, boot, params, instance, aux, self.firmware, notes)
        return raw_mg * NT_PER_MILLIGAUSS, text + " Parameters: the values read when each sample was handed out.", notes

    def _magnetometer_provenance(self, message: str, undone: bool) -> None:
        """The provenance as ``magkf.io.tlog`` gives a telemetry log's (the same messages; ``live`` True, the
        ``connection`` instead of a ``file``), so that what reads a log's provenance reads this one alike."""
        calibrated = is_calibrated(message, self.autopilot, self._version)
        info = self.provenance.setdefault("magnetometer", {"message": message})
        info |= {
            "message_calibrated": calibrated,
            "calibrated": (bool(calibrated) and not undone) if calibrated is not None else None,
        }
        instance = info.get("instance", 0)
        if self.autopilot == "ardupilot" and message != "HIGHRES_IMU":
            params = {k: (np.zeros(1), np.array([v], float)) for k, v in self.params.items()}
            k = _state_index(params, instance) if any(n.startswith("COMPASS_") for n in self.params) else instance
            info["compass"] = k + 1
            info["parameter_set"] = "COMPASS_OFS{0}, COMPASS_DIA{0}, COMPASS_ODI{0}, COMPASS_SCALE{0}".format(
                ("", "2", "3")[min(k, 2)]
            )
        wanted = ("COMPASS_", "CAL_MAG", "AHRS_ORIENTATION", "SENS_BOARD")
        self.provenance["parameters"] = {k: v for k, v in sorted(self.params.items()) if k.startswith(wanted)}
        self.provenance["firmware"] = self.firmware
        self.provenance["ardupilot_firmware"] = self.firmware if self.autopilot == "ardupilot" else None
        self.provenance.setdefault("vehicle", {})["firmware"] = (
            ".".join(map(str, self._version)) if self._version else None
        )
        self.provenance["time_base"] = (
            "utc: boot time + the median over the last SYSTEM_TIME messages of time_unix_usec - time_boot_ms"
            if not self._fallback
            else "utc-ground-station: boot time + the median of this computer's receipt time - boot time"
        )

    # ------------------------------------------------------------------ rates
    @property
    def rates_hz(self) -> dict[str, float]:
        """Measured rate (Hz) per message name over the last ``RATE_WINDOW_S`` of the vehicle's clock."""
        if self._clock_us is None:
            return {}
        now = self._vehicle_us()
        out = {}
        for name, times in self._arrivals.items():
            recent = [t for t in times if t >= now - RATE_WINDOW_S * 1e6]
            span = (recent[-1] - recent[0]) * 1e-6 if len(recent) > 1 else 0.0
            out[name] = (len(recent) - 1) / span if span > 0 else 0.0
        return out

    def _check_rates(self) -> None:
        """An event once per stream and boot whose rate is more than ``RATE_TOLERANCE`` off the rate asked."""
        now = self._vehicle_us()
        if self._clock_us is None or now - self._rates_since_us < RATE_WINDOW_S * 1e6:
            return
        if 0.0 <= now - self._rates_checked_us < 1e6:  # once a second of the vehicle's clock
            return
        self._rates_checked_us = now
        rates = self.rates_hz
        for name, asked in self.asked_hz.items():
            if name in self._rate_reported or (name in MAG_NAMES and self._stream not in (None, name)):
                continue
            got = rates.get(name, 0.0)
            if name == "ATTITUDE" and self._att_source == "ATTITUDE_QUATERNION":
                got = rates.get("ATTITUDE_QUATERNION", 0.0)
            if abs(got / asked - 1.0) > RATE_TOLERANCE:
                self._rate_reported.add(name)
                self._event(
                    f"{name} arrives at {got:.3g} Hz, asked {asked:g} Hz"
                    if got > 0
                    else f"{name} does not arrive (asked {asked:g} Hz)"
                )

    # ------------------------------------------------------------------ asking
    def _target(self) -> tuple[int, int]:
        return self._vehicle if self._vehicle is not None else (1, AUTOPILOT_COMPONENT)

    def _mag_asked(self) -> list[str]:
        if self.mag is None:
            return ["SCALED_IMU" if self.autopilot == "px4" else "RAW_IMU"]
        instance = int(self.mag)
        names = [m for i, m, _ in MAG_MESSAGES if i == instance]
        if instance == 0:
            names = ["SCALED_IMU"] if self.autopilot == "px4" else ["RAW_IMU"]
        return names

    def _ask_streams(self) -> None:
        """``REQUEST_DATA_STREAM`` (ArduPilot) and ``MAV_CMD_SET_MESSAGE_INTERVAL`` for each message read, and
        ``AUTOPILOT_VERSION``."""
        from ..io.tlog import mavlink_dialect

        dialect = mavlink_dialect()
        asked = dict.fromkeys(self._mag_asked(), self.rate_hz) | {"ATTITUDE": self.rate_hz} | SLOW_RATES_HZ
        self.asked_hz = asked
        system, component = self._target()
        if self.autopilot == "ardupilot":
            for group, names in ARDUPILOT_GROUPS.items():
                rate = max((asked[n] for n in names if n in asked), default=0.0)
                if rate > 0:
                    self._send("request_data_stream_send", system, component, group, max(int(round(rate)), 1), 1)
        ids = {cls.msgname: i for i, cls in dialect.mavlink_map.items()}
        for name, rate in asked.items():
            self._send(
                "command_long_send", system, component, MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                ids[name], 1e6 / rate, 0, 0, 0, 0, 0,
            )  # fmt: skip
        self._send(
            "command_long_send", system, component, MAV_CMD_REQUEST_MESSAGE, 0, ids["AUTOPILOT_VERSION"],
            0, 0, 0, 0, 0, 0,
        )  # fmt: skip
        self._rates_since_us = self._vehicle_us() if self._clock_us is not None else math.inf
        self._rate_reported = set()

    def _ask_parameters(self) -> None:
        names = {"ardupilot": ARDUPILOT_PARAMETERS, "px4": PX4_PARAMETERS}.get(self.autopilot or "", ())
        self._param_wanted = set(names)
        self._param_queue, self._param_window, self._param_window_sent = [], set(), False
        self._param_asked = 0
        self._param_reading = bool(names)
        self._param_next = time.monotonic()
        self._params_read = not names  # samples wait for the values in force

    def _parameter_round(self, now: float) -> None:
        """Ask for the next ``PARAM_WINDOW`` parameters of the round not answered yet, or start the next round
        (``PARAM_ROUNDS`` rounds: a request or its answer may be lost); after the last round's wait, say which never
        were answered (its offsets and matrices among them: ``missing_compass_parameters``, and ``--upload`` is
        refused)."""
        self._param_queue = [name for name in self._param_queue if name in self._param_wanted]
        if not self._param_queue and self._param_asked < PARAM_ROUNDS:
            self._param_queue = sorted(self._param_wanted)
            self._param_asked += 1
        if not self._param_queue:
            missing = sorted(self._param_wanted)
            if missing:
                self._event(
                    f"{len(missing)} parameters not answered after {PARAM_ROUNDS} requests (the firmware's defaults "
                    f"taken): {', '.join(missing[:8])}{' ...' if len(missing) > 8 else ''}"
                )
            self._never_answered = tuple(missing)
            self._end_parameter_read()
            return
        paced = self._param_round_trip is not None or not self._param_window_sent
        size = PARAM_WINDOW if paced else len(self._param_queue)
        window, self._param_queue = self._param_queue[:size], self._param_queue[size:]
        self._param_window_sent = True
        self._param_window = set(window)
        system, component = self._target()
        for name in window:
            self._send("param_request_read_send", system, component, name.encode(), -1)
        self._param_sent = now
        self._param_next = now + self._round_wait()

    def _round_wait(self) -> float:
        """Seconds a round of parameter requests waits after its requests or its last answer."""
        if self._param_round_trip is None:
            return PARAM_ROUND_S
        return max(PARAM_ROUND_TRIPS * self._param_round_trip, PARAM_MIN_S)

    def _end_parameter_read(self) -> None:
        self._param_reading, self._params_read = False, True
        self._param_wanted = set()

    # ------------------------------------------------------------------ reboot
    def _before_reboot(self, boot_us: float) -> bool:
        """Whether a clock message is of the boot before a reboot, delayed past it: within ``REBOOT_STALE_S`` of
        the reboot (this computer's clock), a time ahead of the new boot's clock by more than ``REBOOT_BACK_S``
        and not before the old boot's last time less that."""
        if self._old_boot_end_us is None or time.monotonic() - self._reboot_wall > REBOOT_STALE_S:
            return False
        back = REBOOT_BACK_S * 1e6
        return boot_us > self._clock_us + back and boot_us >= self._old_boot_end_us - back

    def _reboot(self, boot_us: int) -> None:
        """The vehicle restarted: hand out what waits, start the buffers and the time base again, ask again."""
        self.counters["reboots"] += 1
        self._event(
            f"the vehicle rebooted (its boot clock went back from {self._clock_us * 1e-6:.3f} s to "
            f"{boot_us * 1e-6:.3f} s): streams and parameters asked for again"
        )
        if self._pending and self._time_base_ready():
            self._finish(self._pending)
        self._made += self._hand_out()  # the old boot's samples, with the old boot's parameters
        self._sequence.restart(self._since_clock)
        self.counters["lost"], self.counters["reordered"] = self._sequence.lost, self._sequence.reordered
        self._old_boot_end_us, self._reboot_wall = self._clock_us, time.monotonic()
        self._reset_boot()
        self._ask_streams()
        self._ask_parameters()
        self._clock_us = boot_us
        self._rates_since_us = float(boot_us)

    def _reset_boot(self) -> None:
        """The state of one boot of the vehicle."""
        self._clock_us: float | None = None
        self._utc: deque = deque(maxlen=SYSTEM_TIME_KEPT)
        self._receipt: deque = deque(maxlen=RECEIPT_KEPT)
        self._fallback = False
        self._fallback_offset = math.nan
        self._pending: list[dict] = []
        self._att_t: list = []
        self._att_q: list = []
        self._att_source = "ATTITUDE"
        self._slow: dict[str, deque] = {}
        self._arrivals: dict[str, deque] = {}
        self._stale: dict[str, tuple[float, float]] = {}
        self._last_out_boot = -math.inf
        self._rates_since_us = math.inf
        self._rates_checked_us = -math.inf
        self._rate_reported: set = set()
        self._refused: set = set()

    # ------------------------------------------------------------------ parameters
    def set_parameters(self, values: dict, timeout_s: float = 2.0, retries: int = 3) -> dict[str, bool]:
        """Send each parameter with ``PARAM_SET`` and confirm it by the ``PARAM_VALUE`` the vehicle echoes.

        Parameters
        ----------
        values : dict of str to float
            Parameter name -> value.
        timeout_s : float
            Seconds to wait for the echoes of one attempt.
        retries : int
            Attempts at most for a parameter that is not echoed.

        Returns
        -------
        dict of str to bool
            True where the echo carries the value sent (compared as float32, the field's type); False where it
            carries another (the vehicle refused it: an event says so) or never came.
        """
        if not self._opened:
            raise InputError("the connection is not open: call open() first", self.connection)
        result: dict[str, bool] = {}
        waiting = {str(k): float(v) for k, v in values.items()}
        self._collect_echoes = True
        for _ in range(max(retries, 1)):
            if not waiting:
                break
            self._echoes = []
            for name, value in waiting.items():
                self._send_parameter(name, value)
            deadline = time.monotonic() + timeout_s
            while waiting and time.monotonic() < deadline:
                self._read_for(0.02)
                for name, echoed in self._echoes:
                    if name in waiting:
                        result[name] = _same_float32(echoed, waiting[name])
                        if not result[name]:
                            self._event(f"PARAM_SET {name} = {waiting[name]:g} refused: the vehicle kept {echoed:g}")
                        del waiting[name]
                self._echoes = []
        self._collect_echoes = False
        for name in waiting:
            result[name] = False
            self._event(f"PARAM_SET {name}: no PARAM_VALUE echoed after {max(retries, 1)} attempts")
        return result

    def _send_parameter(self, name: str, value: float) -> None:
        kind = self._param_types.get(name, PARAM_REAL32)
        number = value
        if self.autopilot == "px4" and 1 <= kind <= 6:  # PX4 sends an integer's bytes in the float field
            number = struct.unpack("<f", struct.pack("<i", int(round(value))))[0]
        system, component = self._target()
        self._send("param_set_send", system, component, name.encode(), number, kind)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _same_float32(a: float, b: float) -> bool:
    return bool(np.float32(a) == np.float32(b))

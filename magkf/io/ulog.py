"""PX4 ULog files: the magnetometer, attitude, GNSS and auxiliary streams as a canonical drive log.

Format
    ULog (https://docs.px4.io/main/en/dev_log/ulog_file_format.html) is PX4's binary log: a 16-byte
    header (magic ``ULog\\x01\\x12\\x35``, version, start time), definitions (flag bits ``B``, message
    formats ``F``, information ``I``/``M`` and parameters ``P``) and a data section of subscriptions ``A``
    and samples ``D`` of uORB topics, each sample starting with its ``uint64 timestamp``. Every message
    has a 3-byte header: ``uint16`` payload size and a ``uint8`` type. Files are parsed with pyulog.

Time
    Timestamps are microseconds since boot. UTC comes from the GNSS topic: ``time_utc_usec`` is the
    receiver's UTC time of the instant ``timestamp + timestamp_time_relative`` (PX4 msg/SensorGps.msg; in the
    first ULogs of 2016 the absolute ``uint64 timestamp_time``); the offset is the median of ``time_utc_usec``
    minus that instant over samples with a fix (``fix_type >= 2``) and a non-zero UTC time. A log without a GNSS
    topic, or whose GNSS never has a UTC time, is read on the boot time base of the drive-log contract: ``time``
    in seconds since boot, ``provenance["time_base"]`` ``"boot"`` and a note saying what is missing;
    ``magkf.io.site`` sets its clock (``--date``). The positions, DOP and fix of a GNSS that has a fix but no
    UTC time (a simulator's, or a receiver that never decoded the time) are kept on that time base; without any
    position there are no ``lat, lon, alt`` (nor DOP or fix) and ``--site`` places the log too.

Generations (PX4's msg/*.msg history; ``magkf.io.ulog_write`` writes each)
    * Up to v1.7 (2016 to April 2018) the magnetometer reached the log in ``sensor_combined.magnetometer_ga``
      (body frame, PX4's calibration applied), in three layouts (``magkf.io.ulog_combined``), unless
      ``sensor_mag`` was logged too. With ``raw`` the calibration is undone from the logged ``CAL_MAGn_*`` and
      ``SENS_BOARD_*`` parameters where the calibration slot of the magnetometer is known
      (``magkf.io.px4_sensors``); otherwise the values are read as calibrated and a note says why.
    * From v1.8 ``vehicle_magnetometer`` holds the calibrated field (``timestamp_sample`` from v1.12).
    * Up to v1.5 ``vehicle_attitude`` held ``roll, pitch, yaw`` (rad) besides an optional ``q`` (``q_valid``);
      samples without a valid quaternion take the Euler angles.
    * ``vehicle_gps_position`` always logged ``hdop, vdop``; a firmware without them gives no DOP column (noted).

Topics and units (PX4 msg/*.msg)
    * ``sensor_mag`` (one instance per magnetometer): ``x, y, z`` in Gauss (``[Gauss]`` in
      SensorMag.msg), ``temperature`` in degC, ``device_id``. Converted to nT with 1 G = 1e5 nT.
    * ``vehicle_magnetometer``: ``magnetometer_ga[3]``, Gauss, the calibrated field of the selected
      magnetometer in the body FRD frame.
    * ``vehicle_attitude.q``: Hamilton quaternion, scalar first, rotating body FRD into NED.
    * ``vehicle_gps_position`` (else ``sensor_gps``): ``lat, lon`` as int32 1e-7 deg and ``alt`` /
      ``alt_ellipsoid`` as int32 mm (PX4 up to v1.13), or ``latitude_deg, longitude_deg`` as double deg and
      ``altitude_msl_m`` / ``altitude_ellipsoid_m`` in m (newer); ``eph`` (m), ``hdop``, ``vdop``,
      ``fix_type`` (0-1 none, 2 2-D, 3 3-D, >3 differential/RTK).
    * ``battery_status.current_a`` in A (-1 if unknown); ``actuator_controls_0.control[3]`` (throttle,
      0..1), else the magnitude of ``vehicle_thrust_setpoint.xyz`` (normalised thrust).

Frames of the magnetometer
    ``sensor_mag`` is published by the driver after its fixed chip-to-board rotation, never rotated by
    ``SENS_BOARD_ROT`` (internal magnetometers) or ``CAL_MAGn_ROT`` (external ones): PX4 applies those,
    with the ``CAL_MAGn`` offsets and scales, when it forms ``vehicle_magnetometer``
    (``calibration::Magnetometer::Correct``: ``rotation * (scale * (m - offset))``, src/lib/sensor_calibration).
    Up to PX4 v1.11 the sensors module instead loaded the ``CAL_MAGn`` offsets and scales into the driver
    (``apply_mag_calibration``, ioctl ``MAGIOCSSCALE`` in src/modules/sensors/voted_sensors_update.cpp), which
    applied them before publishing ``sensor_mag``, and rotated the result itself. The sample log of magkf's
    tests (PX4 v1.11.2) agrees: its ``vehicle_magnetometer`` equals ``sensor_mag`` of the external
    magnetometer (``CAL_MAG1_ROT`` = 0) although ``CAL_MAG1_YOFF`` is 0.56 G. magkf's ``R`` absorbs the
    rotation, so ``sensor_mag`` is the measurement it wants; the reader reports the parameters, applies none.
"""

from __future__ import annotations

import contextlib
import io
import struct
import warnings
from typing import NamedTuple

import numpy as np
import pandas as pd

from ..conventions import (
    ALT,
    HDOP,
    LAT,
    LON,
    MAG,
    NT_PER_UNIT,
    PITCH,
    ROLL,
    TIME,
    VDOP,
    YAW,
    euler_to_quaternion,
    quaternion_to_euler,
)
from ..errors import InputError
from .drivelog import AutopilotLog
from .site import BOOT
from .streams import SLOW_GAP_INTERVALS, bracket, interpolate_linear, interpolate_quaternions, slow_gap, time_order
from .ulog_combined import combined_instances, combined_samples, undo
from .ulog_write import write_ulog

__all__ = ["magnetometer_instances", "read_ulog", "write_ulog"]

NT_PER_GAUSS = NT_PER_UNIT["G"]
#: The topics read; pyulog is told to skip the others.
TOPICS = (
    "sensor_mag",
    "vehicle_magnetometer",
    "vehicle_attitude",
    "vehicle_gps_position",
    "sensor_gps",
    "battery_status",
    "actuator_controls_0",
    "vehicle_thrust_setpoint",
)
_MAG_TOPICS = ("sensor_mag", "vehicle_magnetometer")
_GNSS_TOPICS = ("vehicle_gps_position", "sensor_gps")
#: Read only from a log without ``vehicle_magnetometer`` whose ``sensor_combined`` format has a magnetometer (PX4 up
#: to v1.7): the topic is logged at the gyro's rate, so it is not parsed otherwise.
_COMBINED_TOPICS = ("sensor_combined", "sensor_selection")


# ---------------------------------------------------------------- loading
class _ReadTracker:
    """A binary file wrapper that records whether a read returned fewer bytes than asked for, which is
    how a file cut inside a message shows (pyulog stops there silently)."""

    def __init__(self, handle):
        self._handle = handle
        self.short_read = False

    def read(self, size: int = -1) -> bytes:
        data = self._handle.read(size)
        if 0 < len(data) < size:
            self.short_read = True
        return data

    def seek(self, offset: int, whence: int = 0) -> int:
        return self._handle.seek(offset, whence)

    def tell(self) -> int:
        return self._handle.tell()

    def close(self) -> None:
        self._handle.close()


def _load(path, topics=TOPICS):
    """Parse ``path`` with pyulog (only ``topics``, and ``sensor_combined`` and ``sensor_selection`` of an older log
    whose calibrated magnetometer is there); InputError if it is not a ULog, a warning if damaged."""
    ulog, damage = _parse(path, topics)
    combined = ulog.message_formats.get("sensor_combined")
    older = combined is not None and any(field[2] == "magnetometer_ga" for field in combined.fields)
    if older and not _datasets(ulog, "vehicle_magnetometer"):  # raw=False reads it, and without sensor_mag also raw
        ulog, damage = _parse(path, tuple(topics) + _COMBINED_TOPICS)
    if damage is not None:
        warnings.warn(damage, stacklevel=3)
    return ulog


def _parse(path, topics):
    """``(ulog, damage)``: ``path`` parsed by pyulog (only ``topics``) and, for a truncated or damaged file, what
    to warn; InputError if it is not a ULog."""
    from pyulog import ULog
    from pyulog.exceptions import ULogException

    name = str(path)
    chatter = io.StringIO()
    try:
        with open(path, "rb") as handle, contextlib.redirect_stdout(chatter):
            tracker = _ReadTracker(handle)
            ulog = ULog(tracker, list(topics))
    except OSError as exc:
        raise InputError(f"cannot read: {exc.strerror}", name) from None
    except ULogException as exc:
        raise InputError(f"not a PX4 ULog file ({exc})", name) from None
    except (UnicodeDecodeError, ValueError, KeyError, IndexError, OverflowError, struct.error) as exc:
        raise InputError(f"unreadable ULog file ({type(exc).__name__}: {exc})", name) from None
    if not (tracker.short_read or ulog.file_corruption):
        return ulog, None
    said = " ".join(chatter.getvalue().split())
    return ulog, f"{name}: the ULog file is truncated or damaged; read up to the damage" + (
        f" ({said})" if said else ""
    )


def _datasets(ulog, topic: str) -> dict[int, dict[str, np.ndarray]]:
    """``{instance: {field: array}}`` of a topic (empty if not logged)."""
    return {d.multi_id: d.data for d in ulog.data_list if d.name == topic}


def _sample_us(data: dict) -> np.ndarray:
    """Sample times (us since boot, int64): ``timestamp_sample`` where logged and non-zero, else ``timestamp``."""
    t = data["timestamp"].astype(np.int64)
    if "timestamp_sample" in data:
        ts = data["timestamp_sample"].astype(np.int64)
        if np.all(ts > 0):
            return ts
    return t


def _rate_hz(t_us: np.ndarray) -> float | None:
    span = (t_us[-1] - t_us[0]) * 1e-6 if len(t_us) > 1 else 0.0
    return float((len(t_us) - 1) / span) if span > 0 else None


def _combined(ulog) -> dict[int, dict]:
    """``{instance: data}`` of the magnetometers in ``sensor_combined`` (PX4 up to v1.7; ``ulog_combined``)."""
    data = _datasets(ulog, "sensor_combined").get(0)
    return {} if data is None else dict.fromkeys(combined_instances(data), data)


def _instances(ulog) -> list[dict]:
    out = []
    for topic in _MAG_TOPICS:
        for instance, data in sorted(_datasets(ulog, topic).items()):
            t = _sample_us(data)
            ident = int(data["device_id"][0]) if "device_id" in data else None
            item = {
                "topic": topic,
                "instance": int(instance),
                "device_id": ident,
                "rate_hz": _rate_hz(t),
                "samples": len(t),
            }
            if "is_external" in data:
                item["is_external"] = bool(data["is_external"][0])
            out.append(item)
    for instance, data in _combined(ulog).items():  # parsed only without vehicle_magnetometer (``_load``)
        t = combined_samples(data, instance).us
        out.append(
            {
                "topic": "sensor_combined",
                "instance": instance,
                "device_id": None,
                "rate_hz": _rate_hz(t),
                "samples": len(t),
            }
        )
    return out


def magnetometer_instances(path) -> list[dict]:
    """The magnetometers a ULog file holds: one dict per topic instance with ``topic`` (``sensor_mag``,
    ``vehicle_magnetometer``, or ``sensor_combined`` in a log of PX4 up to v1.7 without the latter), ``instance``
    (uORB multi-instance index, or the magnetometer's index in ``sensor_combined``; what ``read_ulog(mag=...)``
    takes), ``device_id`` (None where not logged), ``rate_hz`` (mean logged rate), ``samples`` and, where
    logged, ``is_external``."""
    return _instances(_load(path, _MAG_TOPICS))


# ---------------------------------------------------------------- streams
def _utc_offset_us(gnss: dict, fix: np.ndarray, topic: str) -> tuple[float, str] | str:
    """Median of UTC minus boot time (us) over samples with a fix and a UTC time, and how it was found; or why
    there is none (a sentence). The boot time of a UTC time is ``timestamp_time`` in the first ULogs (2016, uint64),
    else ``timestamp + timestamp_time_relative``, else ``timestamp``."""
    if "time_utc_usec" not in gnss:
        return f"{topic} has no time_utc_usec field"
    utc = gnss["time_utc_usec"].astype(np.int64)
    if "timestamp_time" in gnss:
        at, stamp = gnss["timestamp_time"].astype(np.int64), "timestamp_time"
    elif "timestamp_time_relative" in gnss:
        at = gnss["timestamp"].astype(np.int64) + gnss["timestamp_time_relative"].astype(np.int64)
        stamp = "timestamp - timestamp_time_relative"
    else:
        at, stamp = _position_us(gnss), "timestamp"
    ok = (utc > 0) & (fix >= 2) & (at > 0)
    if not ok.any():
        return f"no {topic} sample has a fix and a non-zero time_utc_usec"
    diff = utc[ok] - at[ok]
    offset = float(np.median(diff))
    spread_ms = float(np.max(np.abs(diff - offset))) * 1e-3
    text = (
        f"UTC = boot time + median({topic}.time_utc_usec - {stamp}) over "
        f"{int(ok.sum())} samples with fix_type >= 2 (largest deviation {spread_ms:.3f} ms)"
    )
    return offset, text


#: A GNSS topic's height fields, in the order tried: above the WGS-84 ellipsoid, then above mean sea level
#: (field, factor to m, unit in words).
_ELLIPSOID_HEIGHTS = (("altitude_ellipsoid_m", 1.0, "m"), ("alt_ellipsoid", 1e-3, "mm -> m"))
_MSL_HEIGHTS = (("altitude_msl_m", 1.0, "m"), ("alt", 1e-3, "mm -> m"))


def _gnss_fields(g: dict, topic: str, notes: list) -> tuple[dict, dict, np.ndarray]:
    """Position, DOP and fix of the GNSS samples (lat/lon NaN below a 2-D fix, alt below a 3-D fix), their
    provenance and ``fix_type`` (float)."""
    n = len(g["timestamp"])
    fix = g["fix_type"].astype(float) if "fix_type" in g else np.full(n, 3.0)
    if "fix_type" not in g:
        notes.append(f"{topic} has no fix_type; every sample is taken as a 3-D fix")
    values, source = {}, {}
    if "latitude_deg" in g:
        values[LAT], values[LON] = g["latitude_deg"].astype(float), g["longitude_deg"].astype(float)
        source[LAT], source[LON] = f"{topic}.latitude_deg (deg)", f"{topic}.longitude_deg (deg)"
    else:
        values[LAT], values[LON] = g["lat"] * 1e-7, g["lon"] * 1e-7
        source[LAT], source[LON] = f"{topic}.lat (x 1e-7 deg)", f"{topic}.lon (x 1e-7 deg)"
    ellipsoid = next(((f, k, u) for f, k, u in _ELLIPSOID_HEIGHTS if f in g), None)
    msl = next(((f, k, u) for f, k, u in _MSL_HEIGHTS if f in g), None)
    if ellipsoid is not None:
        field, scale, unit = ellipsoid
        values[ALT], source[ALT] = g[field] * scale, f"{topic}.{field} ({unit})"
        unset = g[field] == 0  # a driver that never fills it, or before the geoid is known
        if unset.any() and msl is not None:
            values[ALT] = np.where(unset, g[msl[0]] * msl[1], values[ALT])
            source[ALT] += f", else {topic}.{msl[0]} ({msl[2]}) where it is 0"
            notes.append(
                f"{topic}.{field} is 0 in {int(unset.sum())} of {unset.size} samples: the height above mean sea "
                f"level ({msl[0]}) is used there"
            )
    elif msl is not None:
        field, scale, unit = msl
        values[ALT], source[ALT] = g[field] * scale, f"{topic}.{field} ({unit})"
        notes.append(f"alt is the height above mean sea level ({topic}.{field}): no ellipsoidal height was logged")
    values[LAT][fix < 2] = np.nan
    values[LON][fix < 2] = np.nan
    if ALT in values:
        values[ALT][fix < 3] = np.nan
    for field, column in (("hdop", HDOP), ("vdop", VDOP), ("eph", "eph")):
        if field in g:
            values[column], source[column] = g[field].astype(float), f"{topic}.{field}"
    lacking = [field for field in ("hdop", "vdop") if field not in g]
    if lacking:
        kept = "the horizontal accuracy eph (m) is kept as the auxiliary column eph" if "eph" in g else "nor eph"
        notes.append(f"{topic} has no {' or '.join(lacking)} field: no such DOP column for the DOP gate; {kept}")
    return values, source, fix


def _battery(ulog, t, ref_us, max_gap_s) -> tuple[np.ndarray, str] | None:
    for instance, b in sorted(_datasets(ulog, "battery_status").items()):
        current = b["current_a"].astype(float)
        current[current == -1.0] = np.nan
        if np.isfinite(current).any():
            t_src = (b["timestamp"].astype(np.int64) - ref_us) * 1e-6
            values, _ = interpolate_linear(t, t_src, current, slow_gap(t_src, max_gap_s))
            return values, f"battery_status[{instance}].current_a (A; -1 = unknown -> missing)"
    return None


def _throttle(ulog, t, ref_us, max_gap_s) -> tuple[np.ndarray, str] | None:
    controls = _datasets(ulog, "actuator_controls_0")
    thrust = _datasets(ulog, "vehicle_thrust_setpoint")
    if 0 in controls and "control[3]" in controls[0]:
        data, values = controls[0], controls[0]["control[3]"].astype(float)
        text = "actuator_controls_0.control[3] (throttle, 0..1)"
    elif 0 in thrust:
        data = thrust[0]
        values = np.linalg.norm(np.column_stack([data[f"xyz[{k}]"].astype(float) for k in range(3)]), axis=1)
        text = "|vehicle_thrust_setpoint.xyz| (normalised thrust, 0..1)"
    else:
        return None
    t_src = (_sample_us(data) - ref_us) * 1e-6
    out, _ = interpolate_linear(t, t_src, values, slow_gap(t_src, max_gap_s))
    return out, text


def _version(ulog) -> str | None:
    version = ulog.get_version_info()
    return None if version is None else f"{version[0]}.{version[1]}.{version[2]}"


def _calibration_index(params: dict, device_id: int | None) -> int | None:
    for n in range(8):
        if device_id is not None and params.get(f"CAL_MAG{n}_ID") == device_id:
            return n
    return None


#: The refusal of a log without any magnetometer.
NO_MAGNETOMETER = (
    "no magnetometer in the log (no sensor_mag, vehicle_magnetometer or sensor_combined.magnetometer_ga): "
    "record the flight with PX4's logger logging sensor_mag or vehicle_magnetometer"
)
#: The refusal of ``raw=False`` for a log with only the raw ``sensor_mag``.
NO_CALIBRATED = (
    "no calibrated magnetometer in the log (no vehicle_magnetometer or sensor_combined.magnetometer_ga), "
    "only the raw sensor_mag: read it with raw=True"
)


def _pick_magnetometer(ulog, mag: int | None, raw: bool, name: str) -> tuple[str, int, dict, str | None]:
    """``(topic, instance, data, why)`` of the magnetometer to read: instance ``mag``, or by default the one
    ``_default_instance`` gives; ``why`` says in words why a default other than the lowest instance was read.
    ``sensor_mag`` (raw) before ``vehicle_magnetometer`` before ``sensor_combined`` (older PX4)."""
    sensor, vehicle, combined = _datasets(ulog, "sensor_mag"), _datasets(ulog, "vehicle_magnetometer"), _combined(ulog)
    if raw and sensor:
        topic, sets = "sensor_mag", sensor
    elif vehicle:
        topic, sets = "vehicle_magnetometer", vehicle
    elif combined:
        topic, sets = "sensor_combined", combined
    else:
        raise InputError(NO_CALIBRATED if sensor else NO_MAGNETOMETER, name)
    instance, why = min(sets), None
    if mag is not None:
        instance = mag
    elif topic == "sensor_mag":
        instance, why = _default_instance(sets, ulog.initial_parameters)
    if instance not in sets:
        raise InputError(f"{topic} has no instance {mag}; instances: {sorted(sets)}", name)
    if why is not None:
        why = f"{topic}[{instance}] read: {why}; --mag {min(sets)} reads instance {min(sets)}"
    return topic, instance, sets[instance], why


def _default_instance(sets: dict, params: dict) -> tuple[int, str | None]:
    """The ``sensor_mag`` instance read when none is asked for, and why when it is not the lowest: PX4's primary
    magnetometer, the one whose ``device_id`` is ``CAL_MAG_PRIME`` (up to PX4 1.11), if it is logged and not
    disabled; else the one of highest ``CAL_MAGn_PRIO`` (PX4 1.12 on: 0 disables, the highest is preferred);
    else the lowest instance not disabled (``CAL_MAGn_EN = 0`` or ``CAL_MAGn_PRIO = 0``); else the lowest."""

    def device(instance):
        ids = sets[instance].get("device_id")
        return int(ids[0]) if ids is not None and len(ids) else None

    def slot(instance):
        return _calibration_index(params, device(instance))

    def enabled(instance):
        n = slot(instance)
        return n is None or (params.get(f"CAL_MAG{n}_EN") != 0 and params.get(f"CAL_MAG{n}_PRIO") != 0)

    lowest, prime = min(sets), params.get("CAL_MAG_PRIME")
    on = [i for i in sorted(sets) if enabled(i)]
    for instance in on:
        if prime is not None and device(instance) == prime:
            return instance, None if instance == lowest else f"PX4's primary magnetometer (CAL_MAG_PRIME = {prime})"
    priority = {i: params[f"CAL_MAG{slot(i)}_PRIO"] for i in on if f"CAL_MAG{slot(i)}_PRIO" in params}
    if prime is None and priority:
        instance = max(priority, key=lambda i: (priority[i], -i))  # the lowest instance among equals
        why = f"PX4's highest-priority magnetometer (CAL_MAG{slot(instance)}_PRIO = {priority[instance]:g})"
        return instance, None if instance == lowest else why
    instance = on[0] if on else lowest
    return instance, None if instance == lowest else "the lowest instance not disabled in PX4"


class _Magnetometer(NamedTuple):
    """The magnetometer stream read: its topic and instance, and its samples in time order."""

    topic: str
    instance: int
    #: The topic's logged fields (arrays over all its samples).
    data: dict
    #: The three field names of x, y, z.
    fields: tuple[str, ...]
    #: (n,) sample times, us since boot (int64, strictly increasing).
    us: np.ndarray
    #: (n, 3) field, G.
    gauss: np.ndarray
    #: (n,) indices of the kept samples into ``data``.
    rows: np.ndarray
    #: True where PX4's calibration is in the values read (``vehicle_magnetometer``, ``sensor_combined`` not undone).
    calibrated: bool
    #: Where the sample times come from, in words.
    time_text: str
    #: The temperature field (degC), None if not logged.
    temp_field: str | None
    #: The ``CAL_MAGn`` slot of a ``sensor_combined`` magnetometer whose calibration was undone, else None.
    slot: int | None = None


class _Gnss(NamedTuple):
    """The GNSS stream read: topic, instance, logged fields, and its position, DOP and fix (``_gnss_fields``)."""

    topic: str
    instance: int
    data: dict
    #: Canonical column -> (m,) values per GNSS sample.
    values: dict
    #: Canonical column -> ``topic.field (conversion)``.
    source: dict
    #: (m,) ``fix_type`` (float).
    fix: np.ndarray


def _magnetometer(ulog, mag: int | None, raw: bool, name: str, notes: list) -> _Magnetometer:
    """The chosen magnetometer (``_pick_magnetometer``) in time order, repeated times dropped; why it was
    chosen, whether it is calibrated and what was dropped go to ``notes``."""
    topic, instance, m, why = _pick_magnetometer(ulog, mag, raw, name)
    if why is not None:
        notes.append(why)
    if topic == "sensor_combined":
        return _combined_magnetometer(ulog, instance, m, raw, name, notes)
    calibrated = topic == "vehicle_magnetometer"
    if calibrated:
        notes.append(
            "the magnetometer is PX4's calibrated vehicle_magnetometer (offsets, scales and rotation "
            "to the body FRD frame applied by PX4), not the raw sensor_mag" + ("" if raw else " (raw=False)")
        )
    mag_us = _sample_us(m)
    fields = ("x", "y", "z") if topic == "sensor_mag" else tuple(f"magnetometer_ga[{k}]" for k in range(3))
    mag_g = np.column_stack([m[f].astype(float) for f in fields])
    rows = time_order(mag_us)
    if len(rows) < len(mag_us):
        notes.append(f"{len(mag_us) - len(rows)} {topic} samples with a repeated timestamp were dropped")
    stamp = "timestamp_sample" if "timestamp_sample" in m and np.all(m["timestamp_sample"] > 0) else "timestamp"
    temp = "temperature" if "temperature" in m else None
    return _Magnetometer(
        topic,
        instance,
        m,
        fields,
        mag_us[rows],
        mag_g[rows],
        rows,
        calibrated,
        f"{topic}.{stamp} (us since boot)",
        temp,
    )


def _combined_magnetometer(ulog, instance: int, data: dict, raw: bool, name: str, notes: list) -> _Magnetometer:
    """Magnetometer ``instance`` of ``sensor_combined`` (PX4 up to v1.7): calibrated as logged, or with ``raw``
    the driver's readings where the calibration can be undone from the logged parameters (notes say which)."""
    samples = combined_samples(data, instance)
    notes.extend(samples.notes)
    if not len(samples.us):
        raise InputError(
            "sensor_combined has no valid magnetometer sample (every magnetometer time is 0 or marked invalid): "
            "the magnetometer never published; use a log in which it did",
            name,
        )
    where = f"sensor_combined.magnetometer_ga (PX4 up to v1.7; {', '.join(samples.fields)})"
    gauss, calibrated, slot = samples.gauss, True, None
    if raw:
        three = "magnetometer_ga[3]" in data
        selection = _datasets(ulog, "sensor_selection").get(0)
        undone = undo(samples, ulog.initial_parameters, selection, instance, three)
        if isinstance(undone, str):
            notes.append(
                f"the magnetometer is {where}, in the body FRD frame with PX4's offsets, scales and rotation applied; "
                f"read as calibrated: the calibration cannot be undone because {undone}"
            )
        else:
            gauss, how, slot = undone
            calibrated = False
            notes.append(
                f"the magnetometer is {where}; PX4's calibration was undone from the logged parameters "
                f"(m = S^-1 R^T magnetometer_ga + offset: {how}), giving the driver's reading in the board's axes"
            )
    else:
        notes.append(
            f"the magnetometer is {where}, in the body FRD frame with PX4's offsets, scales and rotation applied "
            "(raw=False)"
        )
    return _Magnetometer(
        "sensor_combined",
        instance,
        data,
        samples.fields,
        samples.us,
        gauss,
        samples.rows,
        calibrated,
        samples.time_text,
        samples.temp_field,
        slot,
    )


def _gnss(ulog, notes: list) -> _Gnss | None:
    """The lowest instance of the first GNSS topic logged (``_GNSS_TOPICS``), with its position, DOP and fix;
    None if there is none."""
    topic = next((tp for tp in _GNSS_TOPICS if _datasets(ulog, tp)), None)
    if topic is None:
        return None
    sets = _datasets(ulog, topic)
    instance = min(sets)
    values, source, fix = _gnss_fields(sets[instance], topic, notes)
    return _Gnss(topic, instance, sets[instance], values, source, fix)


def _magnetometer_columns(mag: _Magnetometer, offset_us: float | None) -> tuple[dict, dict]:
    """``time`` (UNIX s, or s since boot where ``offset_us`` is None) and ``mag_x, mag_y, mag_z`` (nT) of every
    epoch, and their provenance."""
    if offset_us is None:
        table = {TIME: mag.us.astype(float) / 1e6}
        columns = {TIME: f"{mag.time_text} -> s since boot (no GNSS UTC time)"}
    else:
        table = {TIME: (mag.us.astype(float) + offset_us) / 1e6}
        columns = {TIME: f"{mag.time_text} + GNSS UTC offset"}
    for k, column in enumerate(MAG):
        table[column] = mag.gauss[:, k] * NT_PER_GAUSS
        undone = "" if mag.calibrated or mag.topic != "sensor_combined" else ", PX4's calibration undone"
        columns[column] = f"{mag.topic}.{mag.fields[k]} (G x 1e5 -> nT{undone})"
    return table, columns


def _attitude_columns(
    ulog, t: np.ndarray, ref_us: int, max_gap_s: float, notes: list, name: str = "log"
) -> tuple[dict, dict]:
    """``roll, pitch, yaw`` (deg) at the epochs ``t`` (s after ``ref_us``) from ``vehicle_attitude`` by slerp, and
    their provenance; empty (noted) without the topic or without an attitude in it. Samples of a repeated time
    are dropped (noted); times that go backwards are an InputError naming the file ``name``."""
    att = _datasets(ulog, "vehicle_attitude")
    if 0 not in att:
        notes.append("no vehicle_attitude topic: roll, pitch and yaw are absent")
        return {}, {}
    found = _attitude_quaternions(att[0], notes)
    if found is None:
        notes.append("vehicle_attitude has neither q nor roll, pitch and yaw: roll, pitch and yaw are absent")
        return {}, {}
    q_src, text = found
    att_us = _increasing(_sample_us(att[0]), "vehicle_attitude", name)
    rows = time_order(att_us)
    if len(rows) < len(att_us):
        notes.append(f"{len(att_us) - len(rows)} vehicle_attitude samples with a repeated timestamp were dropped")
    q, _ = interpolate_quaternions(t, (att_us[rows] - ref_us) * 1e-6, q_src[rows], max_gap_s)
    yaw, pitch, roll = quaternion_to_euler(q)
    return {ROLL: roll, PITCH: pitch, YAW: yaw}, dict.fromkeys((ROLL, PITCH, YAW), text)


def _increasing(t_us: np.ndarray, topic: str, name: str) -> np.ndarray:
    """``t_us`` (us since boot) when it never decreases; otherwise InputError naming the file ``name``: a damaged
    log, whose samples cannot be put on one time line."""
    back = np.flatnonzero(np.diff(t_us) < 0)
    if len(back):
        k = int(back[0]) + 1
        raise InputError(
            f"the {topic} timestamps go backwards ({'once' if len(back) == 1 else f'{len(back)} times'}; first at "
            f"sample {k}, {t_us[k] * 1e-6:.6f} s since boot after {t_us[k - 1] * 1e-6:.6f} s): the log is damaged; "
            "read a log whose clock runs forward",
            name,
        )
    return t_us


#: A logged quaternion is taken as valid when its norm is within this of 1 (float32 components: ~1e-7).
Q_NORM_TOLERANCE = 1e-3


def _attitude_quaternions(a: dict, notes: list) -> tuple[np.ndarray, str] | None:
    """(m, 4) body-FRD-to-NED quaternions of the ``vehicle_attitude`` samples and their source in words, or None.

    ``q[4]`` (scalar first) where it is valid: ``q_valid`` (PX4 up to v1.5) set, or not logged, and a unit norm.
    PX4 up to v1.5 also logged ``roll, pitch, yaw`` (rad, Tait-Bryan ZYX, always valid, the quaternion optional):
    a sample without a valid quaternion takes those, turned into a quaternion (``euler_to_quaternion``)."""
    has_q = "q[0]" in a
    has_euler = all(field in a for field in ("roll", "pitch", "yaw"))
    if not (has_q or has_euler):
        return None
    n = len(a["timestamp"])
    q = np.column_stack([a[f"q[{k}]"].astype(float) for k in range(4)]) if has_q else np.zeros((n, 4))
    valid = np.abs(np.linalg.norm(q, axis=1) - 1.0) <= Q_NORM_TOLERANCE
    if "q_valid" in a:
        valid &= a["q_valid"].astype(bool)
    then = "; slerp; ZYX Euler, deg)"
    text = "vehicle_attitude.q (scalar first, FRD -> NED" + then
    if valid.all() or not has_euler:
        return q, text
    euler = euler_to_quaternion(*(np.degrees(a[f].astype(float)) for f in ("yaw", "pitch", "roll")))
    q[~valid] = euler[~valid]
    euler_text = "vehicle_attitude.roll, pitch, yaw (rad, ZYX, FRD -> NED; as quaternions" + then
    if not valid.any():
        return q, euler_text
    notes.append(f"{int((~valid).sum())} vehicle_attitude samples without a valid q: their roll, pitch and yaw used")
    return q, f"{text}, else {euler_text}"


def _position_us(g: dict) -> np.ndarray:
    """(m,) times of the GNSS positions, us since boot: ``timestamp_position`` where the first ULogs (2016) logged
    it (the time the GNSS driver gave the position; ``timestamp`` only later took its place), else ``timestamp``."""
    if "timestamp_position" in g and np.all(g["timestamp_position"] > 0):
        return g["timestamp_position"].astype(np.int64)
    return g["timestamp"].astype(np.int64)


def _gnss_columns(gnss: _Gnss, t: np.ndarray, ref_us: int, max_gap_s: float, notes: list) -> tuple[dict, dict]:
    """Position, DOP (linear) and ``fix_type`` (the lower of the bracketing samples) at the epochs ``t`` (s after
    ``ref_us``), and their provenance.

    Positions change slowly, so the GNSS stream is interpolated across gaps up to the longer of ``max_gap_s`` and
    ``SLOW_GAP_INTERVALS`` of its median sample interval: a 1 to 2 Hz receiver, or one whose samples
    alternate 0.4 and 0.6 s apart, still places every epoch. Epochs placed only thanks to that longer gap are noted.
    """
    t_gnss = (_position_us(gnss.data) - ref_us) * 1e-6
    gap = slow_gap(t_gnss, max_gap_s)
    table, columns = {}, {}
    for column, values in gnss.values.items():
        table[column], _ = interpolate_linear(t, t_gnss, values, gap)
        columns[column] = gnss.source[column] + " (linear)"
    i, _, valid = bracket(t, t_gnss, gap)
    fix = gnss.fix
    table["fix_type"] = np.where(valid, np.minimum(fix[i], fix[np.minimum(i + 1, len(fix) - 1)]), np.nan)
    columns["fix_type"] = f"{gnss.topic}.fix_type (lower of the bracketing samples)"
    bridged = int(valid.sum() - bracket(t, t_gnss, max_gap_s)[2].sum())
    if bridged:
        interval = float(np.median(np.diff(t_gnss)))
        notes.append(
            f"{bridged} epochs lie in {gnss.topic} gaps longer than max_gap_s = {max_gap_s:g} s: their position, DOP "
            f"and fix are interpolated across gaps up to {gap:.2f} s ({SLOW_GAP_INTERVALS:g} of the stream's median "
            f"interval, {interval:.2f} s)"
        )
    return table, columns


def _auxiliary_columns(
    ulog, mag: _Magnetometer, t: np.ndarray, ref_us: int, max_gap_s: float, notes: list
) -> tuple[dict, dict]:
    """``current_a`` (A), ``throttle`` (0..1) and the magnetometer's ``temp_c`` (degC), each where logged, and
    their provenance; a temperature field of NaN only is noted."""
    table, columns = {}, {}
    for column, found in (
        ("current_a", _battery(ulog, t, ref_us, max_gap_s)),
        ("throttle", _throttle(ulog, t, ref_us, max_gap_s)),
    ):
        if found is not None:
            table[column], columns[column] = found
    if mag.temp_field is not None:
        temp = mag.data[mag.temp_field].astype(float)[mag.rows]
        if np.isfinite(temp).any():
            table["temp_c"], columns["temp_c"] = temp, f"{mag.topic}.{mag.temp_field} (degC)"
        else:
            notes.append(f"{mag.topic}.{mag.temp_field} is not logged (NaN): no temp_c")
    return table, columns


def _px4_calibration(ulog, mag: _Magnetometer, notes: list) -> tuple[dict, int | None, int | None, dict]:
    """``(parameters, device_id, calibration_index, rotation)`` of the chosen magnetometer: the logged
    ``CAL_MAG*``, its ``CAL_MAGn`` slot and the rotation parameters; a disabled or non-primary choice is noted."""
    params = {k: v for k, v in sorted(ulog.initial_parameters.items()) if k.startswith("CAL_MAG")}
    device_id = int(mag.data["device_id"][0]) if "device_id" in mag.data else None
    cal_index = mag.slot if mag.topic == "sensor_combined" else _calibration_index(params, device_id)
    rotation = {k: v for k, v in sorted(ulog.initial_parameters.items()) if k.startswith("SENS_BOARD_")}
    if cal_index is not None:
        rotation[f"CAL_MAG{cal_index}_ROT"] = params.get(f"CAL_MAG{cal_index}_ROT")
        for key in (f"CAL_MAG{cal_index}_EN", f"CAL_MAG{cal_index}_PRIO"):
            if params.get(key) == 0:
                notes.append(f"the chosen magnetometer is disabled in PX4 ({key} = 0)")
    if "CAL_MAG_PRIME" in params and device_id is not None and params["CAL_MAG_PRIME"] != device_id:
        notes.append(
            f"the chosen magnetometer (device_id {device_id}) is not PX4's primary one "
            f"(CAL_MAG_PRIME = {params['CAL_MAG_PRIME']})"
        )
    rotation["applied"] = mag.calibrated
    rotation["meaning"] = (
        "CAL_MAGn_ROT (external) or SENS_BOARD_ROT (internal, -1 in CAL_MAGn_ROT) rotate "
        "the sensor frame into the body frame; PX4 applies them to vehicle_magnetometer "
        "(and, up to v1.7, to sensor_combined.magnetometer_ga) only"
    )
    return params, device_id, cal_index, rotation


def _px4_version(ulog, topic: str, calibrated: bool, notes: list) -> str | None:
    """PX4's version (``major.minor.patch``, None if not logged); notes that ``sensor_mag`` may be
    offset-corrected before v1.12, and the calibration parameters changed during the log."""
    version = _version(ulog)
    if topic == "sensor_mag" and version is not None and tuple(map(int, version.split("."))) < (1, 12):
        notes.append(
            f"PX4 {version}: up to v1.11 the driver applied the CAL_MAGn offsets and scales before "
            "publishing sensor_mag, so the values may already be offset-corrected (not rotated)"
        )
    changed = sorted({k for _, k, _ in ulog.changed_parameters if k.startswith(("CAL_MAG", "SENS_BOARD"))})
    if changed:
        used = " and used to undo PX4's calibration" if topic == "sensor_combined" and not calibrated else ""
        notes.append(f"parameters changed during the log (initial values reported{used}): {', '.join(changed)}")
    return version


def _provenance(
    ulog, name: str, mag: _Magnetometer, gnss: _Gnss | None, columns: dict, time_base: str, notes: list
) -> dict:
    """The JSON-able provenance of ``read_ulog`` (see there); PX4's calibration and version notes go to
    ``notes`` first."""
    params, device_id, cal_index, rotation = _px4_calibration(ulog, mag, notes)
    version = _px4_version(ulog, mag.topic, mag.calibrated, notes)
    return {
        "format": "px4-ulog",
        "file": name,
        "px4_version": version,
        "columns": columns,
        "magnetometer": {
            "topic": mag.topic,
            "instance": int(mag.instance),
            "device_id": device_id,
            "rate_hz": _rate_hz(mag.us),
            "calibrated": mag.calibrated,
            "fields": ", ".join(f"{mag.topic}.{f}" for f in mag.fields),
            "calibration_index": cal_index,
            # the logged rotation travels with a calibration of this magnetometer (``magkf export`` compares it)
            "rotation": {k: v for k, v in rotation.items() if k not in ("applied", "meaning")},
        },
        "magnetometers": _instances(ulog),
        "gnss": None if gnss is None else {"topic": gnss.topic, "instance": int(gnss.instance)},
        "parameters": params,
        "rotation": rotation,
        "time_base": time_base,
        "notes": notes,
    }


def read_ulog(path, *, mag: int | None = None, raw: bool = True, max_gap_s: float = 0.5) -> tuple[pd.DataFrame, dict]:
    """Read a PX4 ULog file as a canonical drive log.

    Rows are the epochs of the chosen magnetometer (``timestamp_sample``), with ``time`` in UNIX seconds
    (UTC), ``mag_x, mag_y, mag_z`` in nT, ``roll, pitch, yaw`` in degrees (ZYX, body FRD to NED; yaw in
    [0, 360)), ``lat, lon`` (deg), ``alt`` (m above the ellipsoid where logged, else above MSL with a
    note), ``hdop, vdop`` and the auxiliary ``eph`` (m), ``fix_type`` (the lower of the two bracketing
    GNSS samples), ``current_a`` (A), ``throttle`` (0..1) and ``temp_c`` (degC), each where logged.

    ``raw=True`` (default) returns ``sensor_mag`` instance ``mag`` (default PX4's primary magnetometer,
    ``CAL_MAG_PRIME`` or the highest ``CAL_MAGn_PRIO``, unless it is disabled; else the lowest instance not
    disabled: ``_default_instance``):
    the measurement in the magnetometer's own sensor frame, not rotated by
    ``SENS_BOARD_ROT`` / ``CAL_MAGn_ROT`` (see the module docstring; up to PX4 v1.11 the ``CAL_MAGn`` offsets
    and scales may already be subtracted). Without ``sensor_mag``, or with ``raw=False``, the calibrated
    ``vehicle_magnetometer`` is returned instead: body FRD frame, PX4's calibration applied
    (``provenance["magnetometer"]["calibrated"]`` True, and a note). A log of PX4 up to v1.7 with neither gives
    ``sensor_combined.magnetometer_ga`` (``mag`` its index there): with ``raw`` the driver's reading, PX4's
    calibration undone from the logged parameters where they say which calibration was applied, else (and with
    ``raw=False``) as logged, calibrated; the notes say which and why.

    Attitude is interpolated by slerp, GNSS and DOP linearly; an epoch outside a stream's span or across a
    gap longer than ``max_gap_s`` (s) gets NaN (the slow GNSS and auxiliary streams use the longer of
    ``max_gap_s`` and ``SLOW_GAP_INTERVALS`` of their own median sample interval; GNSS epochs placed only so are
    noted). Rows with a repeated time are dropped (noted).

    Returns ``(table, provenance)``; the provenance is JSON-able: ``format``, ``file``, ``px4_version``,
    ``columns`` (canonical column -> ``topic.field (conversion)``), ``magnetometer`` (topic, instance,
    device_id, rate_hz, calibrated, calibration_index), ``magnetometers`` (all, as
    ``magnetometer_instances``), ``parameters`` (the logged ``CAL_MAG*``), ``rotation`` (``SENS_BOARD_*``,
    ``CAL_MAGn_ROT`` of the chosen magnetometer, whether it is applied), ``time_base`` and ``notes``.

    Without GNSS UTC time, ``time`` is seconds since boot and ``time_base`` is ``"boot"``; the GNSS positions are
    kept where it has a fix, else there are no ``lat, lon, alt`` (see the module docstring).

    Raises InputError (one line: what the log lacks and what to do) for a file that is not a ULog, has no
    magnetometer (``NO_MAGNETOMETER``), only a raw one with ``raw=False`` (``NO_CALIBRATED``), no instance
    ``mag`` or no valid ``sensor_combined`` magnetometer sample; warns (and reads up to the damage) for a
    truncated or damaged file.
    """
    name = str(path)
    ulog = _load(path)
    notes: list[str] = []
    magnetometer = _magnetometer(ulog, mag, raw, name, notes)
    gnss = _gnss(ulog, notes)
    clock = _utc_offset_us(gnss.data, gnss.fix, gnss.topic) if gnss is not None else None
    offset_us = None if clock is None or isinstance(clock, str) else clock[0]
    ref_us = int(magnetometer.us[0])
    t = (magnetometer.us - ref_us) * 1e-6
    table, columns = _magnetometer_columns(magnetometer, offset_us)
    streams = [_attitude_columns(ulog, t, ref_us, max_gap_s, notes, name)]
    positioned = gnss is not None and bool(np.isfinite(gnss.values[LAT]).any())
    if positioned:
        streams.append(_gnss_columns(gnss, t, ref_us, max_gap_s, notes))
    if offset_us is not None:
        time_base = clock[1]
    else:
        notes.append(_boot_time_note(gnss, clock, positioned))
        time_base = BOOT
    streams.append(_auxiliary_columns(ulog, magnetometer, t, ref_us, max_gap_s, notes))
    for values, sources in streams:
        table |= values
        columns |= sources
    for column in (HDOP, VDOP, "eph"):
        if column in table and not np.isfinite(table[column]).any():
            del table[column], columns[column]
    provenance = _provenance(ulog, name, magnetometer, gnss, columns, time_base, notes)
    return pd.DataFrame(table).reset_index(drop=True), provenance


def _boot_time_note(gnss: _Gnss | None, why: str | None, positioned: bool) -> str:
    """Why ``time`` is seconds since boot, whether the GNSS positions are kept (``positioned``) and what to give."""
    if gnss is None:
        lacks = "no GNSS topic (vehicle_gps_position or sensor_gps)"
    else:
        lacks = f"no GNSS UTC time ({why})"
    if positioned:
        return (
            f"time is seconds since boot: {lacks}; the positions of {gnss.topic} are kept on that time base; "
            "give the date (--date YYYY-MM-DD[THH:MM], the UTC at boot)"
        )
    return (
        f"time is seconds since boot and the log has no lat, lon or alt: {lacks}; "
        "give the site and date (--site LAT,LON[,ALT] --date YYYY-MM-DD)"
    )


class ULogReader(AutopilotLog):
    """PX4's ULog (``read_ulog``) of every generation: the chosen magnetometer's epochs (``sensor_mag``,
    ``vehicle_magnetometer`` or, up to PX4 v1.7, ``sensor_combined``), with attitude, position and DOP
    interpolated to them; PX4's calibration undone (``raw``) where the log allows."""

    name = "ulog"
    title = "ULog"
    magic = (b"ULog\x01\x12\x35",)
    extensions = (".ulg",)
    read_table = staticmethod(read_ulog)
    instances = staticmethod(magnetometer_instances)

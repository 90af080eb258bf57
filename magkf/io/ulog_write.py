"""Writing a canonical drive-log table as a PX4 ULog of a chosen PX4 generation (for tests and simulations).

A generation is the set of message formats (the ULog ``F`` definitions) a PX4 version logged for the
magnetometer, attitude and GNSS, taken from PX4's ``msg/*.msg`` of that version with the fields in the order
its generator laid them out (largest type first), as real logs of those versions show them:

========  ===========================================================================================
``1.4``   the first ULogs (May to July 2016): ``sensor_combined.magnetometer_ga[9]`` with ``uint64
          magnetometer_timestamp[3]`` (magnetometer 0 written), ``vehicle_attitude`` with ``roll, pitch,
          yaw`` (rad) and an unset quaternion (``q_valid`` false), ``vehicle_gps_position`` with ``uint64
          timestamp_position`` and ``timestamp_time``.
``1.6``   PX4 v1.5 to v1.6: ``sensor_combined.magnetometer_ga[3]`` with ``magnetometer_timestamp_relative``,
          ``vehicle_attitude.q``, ``vehicle_gps_position`` with ``timestamp_time_relative``.
``1.7``   ``1.6`` and ``sensor_selection.mag_device_id`` (logged by PX4 v1.7's default topics).
``1.8``   PX4 v1.8 to v1.11: ``vehicle_magnetometer.magnetometer_ga[3]`` only (calibrated, no
          ``timestamp_sample``), ``vehicle_attitude.q`` with ``delta_q_reset``.
``1.13``  PX4 v1.12 to v1.14 (the default): ``sensor_mag`` instance 0 (raw), ``vehicle_attitude`` with
          ``timestamp_sample``, ``vehicle_gps_position`` in 1e-7 deg and mm.
``1.15``  PX4 v1.15 on: ``sensor_mag`` and ``vehicle_gps_position`` with ``latitude_deg, longitude_deg`` (double,
          deg) and ``altitude_msl_m, altitude_ellipsoid_m`` (double, m).
========  ===========================================================================================

Fields that carry nothing of the table are left out of the formats, except where a generation is recognised by
them. ``sensor_combined`` is written twice per row, the second copy halfway to the next row and pointing back to
the same magnetometer sample, as PX4 repeated it at the gyro's rate.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np
import pandas as pd

from ..conventions import ALT, LAT, LON, MAG, NT_PER_UNIT, PITCH, ROLL, YAW, euler_to_quaternion
from ..errors import InputError
from .drivelog import table_to_write
from .px4_sensors import SensorsCalibration, calibrated_slots, calibration_of_slot

__all__ = ["GENERATIONS", "write_ulog"]

NT_PER_GAUSS = NT_PER_UNIT["G"]
_HEADER = b"ULog\x01\x12\x35"
_NUMPY = {
    "uint64_t": "<u8",
    "int64_t": "<i8",
    "double": "<f8",
    "int32_t": "<i4",
    "uint32_t": "<u4",
    "float": "<f4",
    "int16_t": "<i2",
    "uint16_t": "<u2",
    "uint8_t": "u1",
    "bool": "u1",
}

_GPS_INT = (
    "uint64_t timestamp; uint64_t time_utc_usec; int32_t lat; int32_t lon; int32_t alt; int32_t alt_ellipsoid; "
    "float eph; float epv; float hdop; float vdop; int32_t timestamp_time_relative; uint8_t fix_type; "
    "uint8_t satellites_used"
)
_GPS_2016 = (
    "uint64_t timestamp; uint64_t timestamp_position; uint64_t timestamp_time; uint64_t time_utc_usec; int32_t lat; "
    "int32_t lon; int32_t alt; int32_t alt_ellipsoid; float eph; float epv; float hdop; float vdop; uint8_t fix_type; "
    "uint8_t satellites_used"
)
_GPS_DEG = (
    "uint64_t timestamp; uint64_t timestamp_sample; double latitude_deg; double longitude_deg; double altitude_msl_m; "
    "double altitude_ellipsoid_m; uint64_t time_utc_usec; uint32_t device_id; float eph; float epv; float hdop; "
    "float vdop; int32_t timestamp_time_relative; uint8_t fix_type; uint8_t satellites_used"
)
_SENSOR_MAG = (
    "uint64_t timestamp; uint64_t timestamp_sample; uint32_t device_id; float x; float y; float z; float temperature; "
    "uint32_t error_count; bool is_external"
)
_COMBINED_1_6 = (
    "uint64_t timestamp; float[3] gyro_rad; float gyro_integral_dt; int32_t accelerometer_timestamp_relative; "
    "float[3] accelerometer_m_s2; float accelerometer_integral_dt; int32_t magnetometer_timestamp_relative; "
    "float[3] magnetometer_ga; int32_t baro_timestamp_relative; float baro_alt_meter; float baro_temp_celcius"
)
_BATTERY = "uint64_t timestamp; float voltage_v; float current_a; bool connected"
_CONTROLS = "uint64_t timestamp; uint64_t timestamp_sample; float[8] control"


@dataclass(frozen=True)
class Generation:
    """The message formats one PX4 generation logged: topic -> ``"type[n] field; ..."``."""

    #: PX4's version (major, minor, patch), written as ``ver_sw_release``.
    version: tuple[int, int, int]
    magnetometer: dict
    attitude: str
    gnss: dict


GENERATIONS = {
    "1.4": Generation(
        (1, 4, 0),
        {
            "sensor_combined": "uint64_t timestamp; uint64_t[3] magnetometer_timestamp; float[9] magnetometer_ga; "
            "float[3] magnetometer_range_ga; float[3] magnetometer_temp; uint32_t[3] magnetometer_priority; "
            "uint32_t[3] magnetometer_errcount; int16_t[9] magnetometer_raw; int16_t[3] magnetometer_mode"
        },
        "uint64_t timestamp; float roll; float pitch; float yaw; float rollspeed; float pitchspeed; float yawspeed; "
        "float[9] R; float[4] q; bool R_valid; bool q_valid",
        {"vehicle_gps_position": _GPS_2016},
    ),
    "1.6": Generation(
        (1, 6, 5),
        {"sensor_combined": _COMBINED_1_6},
        "uint64_t timestamp; float rollspeed; float pitchspeed; float yawspeed; float[4] q; uint8_t[4] _padding0",
        {"vehicle_gps_position": _GPS_INT},
    ),
    "1.7": Generation(
        (1, 7, 3),
        {
            "sensor_combined": _COMBINED_1_6,
            "sensor_selection": "uint64_t timestamp; uint32_t accel_device_id; uint32_t baro_device_id; "
            "uint32_t gyro_device_id; uint32_t mag_device_id",
        },
        "uint64_t timestamp; float rollspeed; float pitchspeed; float yawspeed; float[4] q; float[4] delta_q_reset; "
        "uint8_t quat_reset_counter; uint8_t[7] _padding0",
        {"vehicle_gps_position": _GPS_INT},
    ),
    "1.8": Generation(
        (1, 8, 2),
        {"vehicle_magnetometer": "uint64_t timestamp; float[3] magnetometer_ga; uint8_t[4] _padding0"},
        "uint64_t timestamp; float[4] q; float[4] delta_q_reset; uint8_t quat_reset_counter; uint8_t[7] _padding0",
        {"vehicle_gps_position": _GPS_INT},
    ),
    "1.13": Generation(
        (1, 13, 0),
        {"sensor_mag": _SENSOR_MAG},
        "uint64_t timestamp; uint64_t timestamp_sample; float[4] q",
        {"vehicle_gps_position": _GPS_INT},
    ),
    "1.15": Generation(
        (1, 15, 0),
        {"sensor_mag": _SENSOR_MAG},
        "uint64_t timestamp; uint64_t timestamp_sample; float[4] q",
        {"vehicle_gps_position": _GPS_DEG},
    ),
}


def _fields(text: str) -> list[tuple[str, int, str]]:
    """``[(type, array length or 0, name)]`` of a format ``"type[n] name; ..."``."""
    out = []
    for item in text.split(";"):
        kind, name = item.split()
        size = int(kind[kind.index("[") + 1 : -1]) if "[" in kind else 0
        out.append((kind.split("[")[0], size, name))
    return out


def _topics(table: pd.DataFrame, generation: Generation, drop: set[str]) -> dict[str, list[tuple[str, int, str]]]:
    """The topics (name -> fields) that a table's columns fill in ``generation``, without the fields ``drop``
    (``"topic.field"``)."""
    texts = dict(generation.magnetometer)
    if all(c in table for c in (ROLL, PITCH, YAW)):
        texts["vehicle_attitude"] = generation.attitude
    if LAT in table and LON in table:
        texts |= generation.gnss
    if "current_a" in table:
        texts["battery_status"] = _BATTERY
    if "throttle" in table:
        texts["actuator_controls_0"] = _CONTROLS
    return {
        topic: [
            f
            for f in _fields(text)
            if f"{topic}.{f[2]}" not in drop or f[2] == "timestamp" or topic == "sensor_selection"
        ]
        for topic, text in texts.items()
    }


class _Rows:
    """What the table gives every topic, per row: boot times (us), the magnetometer (G) and the other columns."""

    def __init__(self, table: pd.DataFrame, boot_us: np.ndarray, utc0_us: int, gnss_utc: bool, combined_g, euler: bool):
        self.table, self.boot_us, self.combined_g, self.euler = table, boot_us, combined_g, euler
        self.utc_us = utc0_us + (boot_us - boot_us[0]) if gnss_utc else np.zeros_like(boot_us)

    def column(self, column: str, default: float = np.nan) -> np.ndarray:
        return self.table[column].to_numpy(float) if column in self.table else np.full(len(self.table), default)

    def values(self, topic: str, field: str) -> np.ndarray | float | None:
        """The values of ``topic.field`` (None: left zero)."""
        if topic in ("sensor_mag", "vehicle_magnetometer", "sensor_combined"):
            return self._magnetometer(topic, field)
        if topic == "vehicle_attitude":
            return self._attitude(field)
        if topic == "vehicle_gps_position":
            return self._gnss(field)
        if topic == "battery_status":
            current = self.column("current_a")
            return {"current_a": np.where(np.isfinite(current), current, -1.0), "connected": 1}.get(field)
        if topic == "actuator_controls_0":
            return {"timestamp_sample": self.boot_us, "control[3]": self.column("throttle")}.get(field)
        return None

    def _magnetometer(self, topic: str, field: str):
        axes = {f"magnetometer_ga[{k}]": k for k in range(3)} | {a: k for k, a in enumerate("xyz")}
        if field in axes:
            k = axes[field]
            return self.combined_g[:, k] if topic == "sensor_combined" else self.column(MAG[k]) / NT_PER_GAUSS
        return {
            "timestamp_sample": self.boot_us,
            "temperature": self.column("temp_c"),
            "magnetometer_temp[0]": self.column("temp_c"),
            "magnetometer_timestamp[0]": self.boot_us,
            "magnetometer_priority[0]": 50,
        }.get(field)

    def _attitude(self, field: str):
        if field in ("roll", "pitch", "yaw"):
            degrees = self.column(field)
            return (
                np.radians(np.where(degrees > 180.0, degrees - 360.0, degrees))
                if field == "yaw"
                else np.radians(degrees)
            )
        if field.startswith("q[") and not self.euler:  # the first ULogs: an unset quaternion, q_valid false
            q = euler_to_quaternion(self.column(YAW), self.column(PITCH), self.column(ROLL))
            return q[:, int(field[2])]
        return {"timestamp_sample": self.boot_us}.get(field)

    def _gnss(self, field: str):
        lat, lon, alt = self.column(LAT), self.column(LON), self.column(ALT)
        fix, has_alt = np.isfinite(lat) & np.isfinite(lon), np.isfinite(alt)
        alt_mm = np.where(fix & has_alt, np.round(np.nan_to_num(alt) * 1e3), 0)
        alt_m = np.where(fix & has_alt, np.nan_to_num(alt), 0.0)
        return {
            "timestamp_position": self.boot_us,
            "timestamp_time": self.boot_us,
            "timestamp_sample": self.boot_us,
            "time_utc_usec": self.utc_us,
            "lat": np.where(fix, np.round(np.nan_to_num(lat) * 1e7), 0),
            "lon": np.where(fix, np.round(np.nan_to_num(lon) * 1e7), 0),
            "alt": alt_mm,
            "alt_ellipsoid": alt_mm,
            "latitude_deg": np.where(fix, np.nan_to_num(lat), 0.0),
            "longitude_deg": np.where(fix, np.nan_to_num(lon), 0.0),
            "altitude_msl_m": alt_m,
            "altitude_ellipsoid_m": alt_m,
            "eph": self.column("eph"),
            "epv": np.nan,
            "hdop": self.column("hdop"),
            "vdop": self.column("vdop"),
            "fix_type": np.where(fix, np.where(has_alt, 3, 2), 0),
            "satellites_used": np.where(fix, 12, 0),
        }.get(field)


def _message(kind: bytes, payload: bytes) -> bytes:
    return struct.pack("<HB", len(payload), kind[0]) + payload


def _parameter_messages(parameters: dict) -> tuple[list[bytes], dict]:
    """``P`` messages of ``parameters`` (int -> ``int32_t``, else ``float``) and the values as logged (float32)."""
    messages, logged = [], {}
    for key, value in parameters.items():
        if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
            kind, packed, logged[key] = "int32_t", struct.pack("<i", int(value)), int(value)
        else:
            kind, packed = "float", struct.pack("<f", float(value))
            logged[key] = struct.unpack("<f", packed)[0]
        name = f"{kind} {key}".encode()
        messages.append(_message(b"P", bytes([len(name)]) + name + packed))
    return messages, logged


def _info(key: str, kind: str, value: bytes) -> bytes:
    name = f"{kind} {key}".encode()
    return _message(b"I", bytes([len(name)]) + name + value)


def _calibration(params: dict, device_id: int | None, name: str) -> tuple[SensorsCalibration, int | None]:
    """The calibration PX4 applied to the ``sensor_combined`` magnetometer (see ``px4_sensors``) and its slot."""
    slots = calibrated_slots(params)
    if device_id is not None:
        slot = next((s for s, d in slots.items() if d == device_id), None)
        if slot is None:
            raise InputError(f"device_id {device_id} is no CAL_MAGn_ID of the parameters", name)
    elif len(slots) > 1:
        raise InputError("several CAL_MAGn_ID: give device_id, the voted magnetometer's", name)
    else:
        slot = next(iter(slots), None)
    model = calibration_of_slot(params, slot)
    if isinstance(model, str):
        raise InputError(f"the parameters do not say how PX4 calibrated the magnetometer: {model}", name)
    return model, slot


def _payload_fields(fields: list) -> list:
    """The fields of a format that a data message carries: PX4's logger leaves out a trailing padding field."""
    return fields[:-1] if fields and fields[-1][2].startswith("_padding") else fields


def _records(topics: dict, rows: _Rows, combined_twice: bool) -> np.ndarray:
    """All data messages, one structured record per table row (``sensor_combined`` twice)."""
    topics = {topic: _payload_fields(fields) for topic, fields in topics.items()}
    boot = rows.boot_us
    mid = np.r_[(boot[:-1] + boot[1:]) // 2, boot[-1] + 1000]
    slots = [(topic, msg_id, boot) for msg_id, topic in enumerate(topics) if topic != "sensor_selection"]
    if combined_twice:
        msg_id = list(topics).index("sensor_combined")
        slots.insert(msg_id + 1, ("sensor_combined", msg_id, mid))
    dtype = []
    for n, (topic, _, _) in enumerate(slots):
        dtype += [(f"{n}._size", "<u2"), (f"{n}._type", "u1"), (f"{n}._id", "<u2")]
        for kind, size, field in topics[topic]:
            names = [f"{field}[{k}]" for k in range(size)] if size else [field]
            dtype += [(f"{n}.{f}", _NUMPY[kind]) for f in names]
    record = np.zeros(len(boot), dtype=np.dtype(dtype))
    for n, (topic, msg_id, stamp) in enumerate(slots):
        fields = topics[topic]
        payload = sum(np.dtype(_NUMPY[kind]).itemsize * max(size, 1) for kind, size, _ in fields)
        record[f"{n}._size"], record[f"{n}._type"], record[f"{n}._id"] = 2 + payload, ord("D"), msg_id
        record[f"{n}.timestamp"] = stamp
        for _, size, field in fields:
            for name in [f"{field}[{k}]" for k in range(size)] if size else [field]:
                value = rows.values(topic, name)
                if value is not None and name != "timestamp":
                    record[f"{n}.{name}"] = value
        if f"{n}.magnetometer_timestamp_relative" in record.dtype.names:
            record[f"{n}.magnetometer_timestamp_relative"] = boot - stamp
    return record


def write_ulog(
    table: pd.DataFrame,
    path,
    *,
    start_boot_us: int = 10_000_000,
    generation: str = "1.13",
    parameters: dict | None = None,
    device_id: int | None = None,
    gnss_utc: bool = True,
    drop_fields=(),
) -> None:
    """Write a canonical drive-log table as a ULog file of PX4 ``generation`` (``GENERATIONS``).

    Every row becomes one sample, at the same boot time, of each topic its columns fill: the generation's
    magnetometer topic (``mag_*`` nT -> Gauss float32; ``temp_c`` -> its temperature where it has one), attitude
    (``roll, pitch, yaw`` -> float32 quaternion, scalar first, body FRD to NED, or float32 radians for ``1.4``),
    GNSS if ``lat, lon`` are present (``alt`` in both MSL and ellipsoid fields since the table has no geoid height;
    ``eph, hdop, vdop``; ``fix_type`` 3, 2 without ``alt``, 0 where lat/lon are NaN; ``time_utc_usec`` from
    ``time``, or 0 throughout with ``gnss_utc`` False), ``battery_status.current_a`` (-1 where NaN) and
    ``actuator_controls_0.control[3]`` (``throttle``) where present.

    ``parameters`` (name -> value; int as ``int32_t``, else float32) are logged as PX4 parameters. For the
    ``sensor_combined`` generations the table's magnetometer is the driver's reading and the calibration those
    parameters describe is applied before it is written, as PX4 did (``px4_sensors``): the slot of CAL_MAGn_ID =
    ``device_id`` (default: the only calibrated slot, else the board rotation only); ``1.7`` logs that
    ``device_id`` in ``sensor_selection``. ``drop_fields`` (``"topic.field"``, not ``timestamp`` nor those of
    ``sensor_selection``) leaves fields out of the formats, as a firmware without them. Boot time starts at
    ``start_boot_us`` (us) at the first row and follows ``time`` (UNIX s) rounded to 1 us. Messages follow the
    ULog file format (docs.px4.io, "ULog File Format"): header, flag bits, formats, information, parameters,
    subscriptions, data, all laid out at once in a numpy structured array.
    """
    name = str(path)
    if generation not in GENERATIONS:
        raise InputError(f"unknown PX4 generation {generation!r}; use one of {', '.join(GENERATIONS)}", name)
    chosen = GENERATIONS[generation]
    table, time_s = table_to_write(table, name)
    boot_us = start_boot_us + np.round((time_s - time_s[0]) * 1e6).astype(np.int64)
    topics = _topics(table, chosen, set(drop_fields))
    parameter_messages, logged = _parameter_messages(parameters or {})
    combined_g, slot = None, None
    if "sensor_combined" in topics:
        model, slot = _calibration(logged, device_id, name)
        combined_g = model.apply(table[list(MAG)].to_numpy(float) / NT_PER_GAUSS)
    rows = _Rows(table, boot_us, round(time_s[0] * 1e6), gnss_utc, combined_g, "q_valid" in chosen.attitude)
    definitions = [
        _HEADER + struct.pack("<BQ", 1, start_boot_us),
        _message(b"B", bytes(16) + struct.pack("<3Q", 0, 0, 0)),
    ]
    for topic, fields in topics.items():
        text = "".join(f"{kind}[{size}] {field};" if size else f"{kind} {field};" for kind, size, field in fields)
        definitions.append(_message(b"F", f"{topic}:{text}".encode()))
    definitions.append(_info("sys_name", "char[5]", b"magkf"))
    major, minor, patch = chosen.version
    definitions.append(
        _info("ver_sw_release", "uint32_t", struct.pack("<I", major << 24 | minor << 16 | patch << 8 | 255))
    )
    definitions += parameter_messages
    for msg_id, topic in enumerate(topics):
        definitions.append(_message(b"A", struct.pack("<BH", 0, msg_id) + topic.encode()))
    if "sensor_selection" in topics:
        selected = device_id if device_id is not None else logged.get(f"CAL_MAG{slot}_ID", 0)
        payload = struct.pack("<QIIII", int(boot_us[0]), 0, 0, 0, int(selected or 0))
        definitions.append(_message(b"D", struct.pack("<H", list(topics).index("sensor_selection")) + payload))
    record = _records(topics, rows, "sensor_combined" in topics)
    with open(path, "wb") as out:
        out.write(b"".join(definitions))
        out.write(record.tobytes())

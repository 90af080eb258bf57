"""The magnetometer of ``sensor_combined`` in ULogs of PX4 v1.4 to v1.7: its layouts, samples and calibration.

``msg/sensor_combined.msg`` carried the magnetometer until PX4 v1.8 (April 2018, when it moved to
``vehicle_magnetometer``), in three layouts:

* May to July 2016 (the first ULogs, v1.4 development): ``magnetometer_ga[9]`` and ``uint64
  magnetometer_timestamp[3]`` (and ``magnetometer_temp[3]``), three magnetometers side by side, the ``k``-th in
  elements ``3k .. 3k + 2``, each with its absolute time since boot (us);
* July 2016, briefly: ``magnetometer_ga[3]`` with ``uint64 magnetometer_timestamp``;
* v1.5 to v1.7: ``magnetometer_ga[3]`` of the voted magnetometer with ``int32 magnetometer_timestamp_relative``
  (us after the sample's ``timestamp``; ``0x7fffffff`` = ``RELATIVE_TIMESTAMP_INVALID``, no valid magnetometer).

Always Gauss, in the body FRD frame, with PX4's offsets, scales and rotation applied (``magkf.io.px4_sensors``).
``sensor_combined`` is published at the gyro's rate, so every magnetometer sample is repeated until the next one:
the samples are the distinct magnetometer times.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .px4_sensors import SensorsCalibration, calibrated_slots, calibration_of_slot

__all__ = ["RELATIVE_TIMESTAMP_INVALID", "CombinedSamples", "combined_instances", "combined_samples", "undo"]

#: ``sensor_combined_s::RELATIVE_TIMESTAMP_INVALID``: the relative timestamp of a sensor without valid data.
RELATIVE_TIMESTAMP_INVALID = 0x7FFFFFFF


def combined_instances(data: dict) -> list[int]:
    """The magnetometers a ``sensor_combined`` dataset (pyulog's ``{field: array}``) holds: ``[0]`` for one
    ``magnetometer_ga[3]``, the indices with a non-zero time for the three-magnetometer layout, ``[]`` for none."""
    if "magnetometer_ga[0]" not in data:
        return []
    if "magnetometer_ga[3]" not in data:
        return [0]
    return [k for k in range(3) if np.any(data.get(f"magnetometer_timestamp[{k}]", np.zeros(1)) > 0)]


class CombinedSamples(NamedTuple):
    """One magnetometer's samples in ``sensor_combined``, one per distinct magnetometer time, in time order."""

    #: (n,) sample times, us since boot (int64, strictly increasing).
    us: np.ndarray
    #: (n, 3) field, G, body frame, PX4's calibration applied.
    gauss: np.ndarray
    #: (n,) indices of the kept samples into the dataset.
    rows: np.ndarray
    #: The three field names of x, y, z.
    fields: tuple[str, ...]
    #: Where the sample times come from, in words.
    time_text: str
    #: The temperature field (degC), if logged.
    temp_field: str | None
    #: What was dropped and why (sentences).
    notes: list


def _sample_times(data: dict, instance: int) -> tuple[np.ndarray, np.ndarray, str]:
    """(n,) magnetometer times (us since boot, int64), (n,) validity and their source in words."""
    t = data["timestamp"].astype(np.int64)
    if "magnetometer_ga[3]" in data:
        field = f"magnetometer_timestamp[{instance}]"
        us = data[field].astype(np.int64)
        return us, us > 0, f"sensor_combined.{field} (us since boot)"
    if "magnetometer_timestamp_relative" in data:
        relative = data["magnetometer_timestamp_relative"].astype(np.int64)
        valid = relative != RELATIVE_TIMESTAMP_INVALID
        return t + relative, valid, "sensor_combined.timestamp + magnetometer_timestamp_relative (us since boot)"
    if "magnetometer_timestamp" in data:
        us = data["magnetometer_timestamp"].astype(np.int64)
        return us, us > 0, "sensor_combined.magnetometer_timestamp (us since boot)"
    return t, np.ones(len(t), bool), "sensor_combined.timestamp (us since boot; no magnetometer time logged)"


def combined_samples(data: dict, instance: int) -> CombinedSamples:
    """The samples of magnetometer ``instance`` (``combined_instances``) of a ``sensor_combined`` dataset: the
    first of each run of repeated magnetometer times, invalid times left out (both noted)."""
    us, valid, time_text = _sample_times(data, instance)
    base = 3 * instance if "magnetometer_ga[3]" in data else 0
    fields = tuple(f"magnetometer_ga[{base + k}]" for k in range(3))
    gauss = np.column_stack([data[f].astype(float) for f in fields])
    notes = []
    if not valid.all():
        notes.append(
            f"{int((~valid).sum())} sensor_combined samples without a valid magnetometer time were left out "
            "(the magnetometer had not published yet, or its time was marked invalid)"
        )
    candidates = np.flatnonzero(valid)
    order = candidates[np.argsort(us[candidates], kind="stable")]
    keep = np.r_[True, np.diff(us[order]) > 0] if len(order) else np.zeros(0, bool)
    rows = order[keep]
    repeats = len(order) - len(rows)
    if repeats:
        notes.append(
            f"sensor_combined repeats each magnetometer sample until the next one (it is published at the gyro's "
            f"rate): {repeats} repeats were left out, one row per magnetometer time"
        )
    temp = f"magnetometer_temp[{instance}]" if "magnetometer_ga[3]" in data else None
    temp = temp if temp in data else None
    return CombinedSamples(us[rows], gauss[rows], rows, fields, time_text, temp, notes)


def _selected_devices(selection: dict | None, us: np.ndarray) -> np.ndarray | None:
    """(n,) ``sensor_selection.mag_device_id`` in force at each time ``us`` (the latest published at or before it;
    the first one before any was), or None without the topic or a non-zero id."""
    if selection is None or "mag_device_id" not in selection:
        return None
    ids = selection["mag_device_id"].astype(np.int64)
    at = selection["timestamp"].astype(np.int64)
    known = ids != 0
    if not known.any():
        return None
    ids, at = ids[known], at[known]
    index = np.clip(np.searchsorted(at, us, side="right") - 1, 0, len(ids) - 1)
    return ids[index]


def _slots(params: dict, selection: dict | None, instance: int, three: bool, us: np.ndarray):
    """(n,) calibration slot of each sample (-1: a magnetometer without a slot) and how they were found, or a
    sentence saying why they are unknown."""
    slots = calibrated_slots(params)
    by_device = {device: slot for slot, device in slots.items()}
    n = len(us)
    if three:
        slot = instance if instance in slots else -1
        how = (
            f"slot {instance} for /dev/mag{instance} (the calibration numbered its slots by device)"
            if slot >= 0
            else f"no calibration slot for /dev/mag{instance} (CAL_MAG{instance}_ID is 0 or not logged)"
        )
        return np.full(n, slot), how
    devices = _selected_devices(selection, us)
    if devices is not None:
        unknown = sorted(set(devices.tolist()) - set(by_device))
        if unknown:
            return f"sensor_selection.mag_device_id {unknown[0]} has no CAL_MAGn_ID"
        named = ", ".join(f"{d} -> CAL_MAG{by_device[d]}" for d in sorted(set(devices.tolist())))
        return np.array([by_device[d] for d in devices]), f"slot of sensor_selection.mag_device_id ({named})"
    if len(slots) > 1:
        ids = ", ".join(f"CAL_MAG{s}_ID = {d}" for s, d in slots.items())
        return (
            f"sensor_combined holds the voted magnetometer without its device id, the log has {len(slots)} "
            f"calibrated magnetometers ({ids}) and no sensor_selection topic to say which one was voted"
        )
    if slots:
        ((slot, device),) = slots.items()
        return np.full(n, slot), f"the only calibrated magnetometer (CAL_MAG{slot}_ID = {device})"
    return np.full(n, -1), "no calibrated magnetometer (no CAL_MAGn_ID): board rotation only"


def undo(
    samples: CombinedSamples, params: dict, selection: dict | None, instance: int, three: bool
) -> tuple[np.ndarray, str, int | None] | str:
    """The driver's readings (G, board axes, before offsets and scales) of ``samples``, how the calibration was
    found (a sentence) and its slot (None where several or none); or a sentence saying why it cannot be undone.

    ``params`` are the log's initial parameters, ``selection`` the ``sensor_selection`` dataset (None if not
    logged), ``three`` True for the three-magnetometer layout."""
    found = _slots(params, selection, instance, three, samples.us)
    if isinstance(found, str):
        return found
    slots, how = found
    raw = np.empty_like(samples.gauss)
    texts = []
    for slot in np.unique(slots):
        model = calibration_of_slot(params, None if slot < 0 else int(slot))
        if not isinstance(model, SensorsCalibration):
            return model
        rows = slots == slot
        raw[rows] = model.undo(samples.gauss[rows])
        texts.append(model.text)
    used = np.unique(slots)
    slot = int(used[0]) if len(used) == 1 and used[0] >= 0 else None
    return raw, f"{how}; undone: {'; '.join(texts)}", slot

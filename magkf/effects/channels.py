"""The kind of an auxiliary channel, read from its name, and which effects may use it.

Candidates in the diagnosis are formed only from channels of a kind the effect declares
(``Effect.channels``): a temperature effect on a temperature, a load effect on a current or throttle, an
angle effect on an angle. The kind comes from the column name as the data contract writes them (a unit
suffix: ``temp_c``, ``current_a``, ``speed_mps``, ``wheel_deg``) or a key word in it (``throttle``,
``temp``); a channel whose kind cannot be read is not tried, and the diagnosis says so.
"""

from __future__ import annotations

__all__ = ["KINDS", "UNIT_SUFFIXES", "channel_kind", "channel_unit"]

#: Kind -> (unit suffixes, words in the name), in the order they are tried.
KINDS = {
    "temperature": (("_c", "_degc", "_k"), ("temp",)),
    "current": (("_a", "_ma"), ("current", "curr")),
    "throttle": (("_pct",), ("throttle", "thr", "pwm", "rpm")),
    "voltage": (("_v", "_mv"), ("volt",)),
    "speed": (("_mps", "_kmh", "_kph"), ("speed", "velocity")),
    "angle": (("_deg", "_rad"), ("angle",)),
}


#: Unit suffix of a column name -> the unit it names, longest suffixes first.
UNIT_SUFFIXES = {
    "_degc": "degC",
    "_mps": "m/s",
    "_kmh": "km/h",
    "_kph": "km/h",
    "_pct": "%",
    "_deg": "deg",
    "_rad": "rad",
    "_ma": "mA",
    "_mv": "mV",
    "_nt": "nT",
    "_c": "degC",
    "_k": "K",
    "_a": "A",
    "_v": "V",
}


def channel_unit(name: str) -> str | None:
    """The unit the column ``name``'s suffix names (``current_a``: ``A``), or None when it names none."""
    lower = name.lower()
    return next((unit for suffix, unit in UNIT_SUFFIXES.items() if lower.endswith(suffix)), None)


def channel_kind(name: str) -> str | None:
    """The kind of the channel ``name`` (a key of ``KINDS``), or None when the name does not tell."""
    lower = name.lower()
    for kind, (suffixes, _) in KINDS.items():
        if lower.endswith(suffixes):
            return kind
    for kind, (_, words) in KINDS.items():
        if any(w in lower.split("_") or lower.startswith(w) for w in words):
            return kind
    return None

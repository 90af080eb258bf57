"""Physical effects: blocks of parameters that add to the raw magnetometer reading.

Built-ins (``--effect NAME[:COLUMN]``): ``temperature_bias``, ``temperature_scale``, ``current_field``,
``time_lag``, ``field_anomaly``, ``bias_drift``, ``eddy_current``. A user effect is a subclass of
``Effect`` (or ``LinearEffect``) in a file of its own, loaded with ``load_effect_file``.
"""

from __future__ import annotations

import importlib.util
import inspect
from pathlib import Path

from ..errors import InputError
from .base import Effect, EpochData
from .bias_drift import BiasDrift
from .core import SoftHardIron
from .current_field import CurrentField
from .eddy_current import EddyCurrent
from .field_anomaly import FieldAnomaly
from .linear import LinearEffect
from .temperature_bias import TemperatureBias
from .temperature_scale import TemperatureScale
from .time_lag import TimeLag

BUILTIN = {
    cls.name: cls
    for cls in (TemperatureBias, TemperatureScale, CurrentField, TimeLag, FieldAnomaly, BiasDrift, EddyCurrent)
}


def make_effect(spec: str, registry: dict | None = None) -> Effect:
    """An effect from ``NAME`` or ``NAME:COLUMN`` (built-ins, or a registry of user effect classes)."""
    registry = {**BUILTIN, **(registry or {})}
    name, _, column = spec.partition(":")
    if name not in registry:
        raise InputError(f"unknown effect {name!r}; known: {', '.join(sorted(registry))}")
    cls = registry[name]
    takes_column = "column" in inspect.signature(cls.__init__).parameters
    if column and not takes_column:
        raise InputError(f"effect {name!r} takes no column (got {spec!r})")
    return cls(column=column) if column else cls()


def load_effect_file(path) -> dict:
    """The ``Effect`` subclasses defined in a Python file, by name (``{name: class}``)."""
    path = Path(path)
    if not path.is_file():
        raise InputError("no such effect file", str(path))
    spec = importlib.util.spec_from_file_location(f"magkf_user_effect_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    try:
        spec.loader.exec_module(module)
    except Exception as exc:  # the user's code: report it on one line
        raise InputError(f"the effect file failed to load: {type(exc).__name__}: {exc}", str(path)) from None
    found = {
        obj.name: obj
        for obj in vars(module).values()
        if inspect.isclass(obj)
        and issubclass(obj, Effect)
        and obj.__module__ == module.__name__
        and obj.name not in ("effect", "core")
    }
    if not found:
        raise InputError("the file defines no Effect subclass with a name", str(path))
    return found


def candidates(columns, registry: dict | None = None) -> list[Effect]:
    """Every effect that can be tried on a log with these auxiliary ``columns``: built-ins on their
    default columns, column effects on each other numeric column too, and the registry's effects."""
    registry = {**BUILTIN, **(registry or {})}
    defaults = {name: _default_column(cls) for name, cls in registry.items()}
    out = []
    for name, cls in registry.items():
        default = defaults[name]
        if default is None:
            out.append(cls())
            continue
        for column in columns:
            # A channel that is another effect's default is tried only with the effects made for it, and an
            # effect made for one kind of channel (temperature) only on its own.
            owned = {defaults[n] for n in registry if defaults[n] is not None and defaults[n] != default}
            if column == default or (column not in owned and not cls.owns_channel):
                out.append(cls(column=column))
    return out


def _default_column(cls):
    parameter = inspect.signature(cls.__init__).parameters.get("column")
    return None if parameter is None else parameter.default


__all__ = [
    "Effect",
    "EpochData",
    "LinearEffect",
    "SoftHardIron",
    "BUILTIN",
    "make_effect",
    "load_effect_file",
    "candidates",
]

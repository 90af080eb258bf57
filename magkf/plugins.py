"""magkf's plug-ins: one registry for each of its four kinds, all found and loaded the same way.

==================  ======================  ==============================================  ======================
kind                registry                interface                                       entry-point group
==================  ======================  ==============================================  ======================
log readers         ``READERS``             ``magkf.io.readers.LogReader``                  ``magkf.readers``
filters             ``FILTERS``             ``magkf.online.filters.Filter``                 ``magkf.filters``
measurement models  ``MEASUREMENTS``        ``magkf.online.measurements.MeasurementModel``  ``magkf.measurements``
physical effects    ``EFFECTS``             ``magkf.effects.base.Effect``                   ``magkf.effects``
==================  ======================  ==============================================  ======================

A plug-in is a class with a ``name`` that subclasses its kind's interface. It is made known in one of three
ways, as pytest's and Dask's plug-ins are:

* magkf's own: listed below by ``"module:Class"``, imported the first time they are asked for, so that
  ``import magkf`` and ``magkf --help`` load none of them;
* another package's: an entry point in that package's ``pyproject.toml``, read on first use::

      [project.entry-points."magkf.effects"]
      hull_current = "mypackage.effects:HullCurrent"

* a class in the running program: ``EFFECTS.register(HullCurrent)`` (or as a decorator), and for an effect
  in a file of its own, ``magkf.effects.load_effect_file`` (``--effect-file`` on the command line).

A registry is a read-only mapping from a name to its class: ``FILTERS["ekf"]``, ``"ukf" in FILTERS``,
``list(MEASUREMENTS)`` (the names, magkf's first, in their listed order). This module imports nothing of
magkf's but its errors, so that every layer may use it.
"""

from __future__ import annotations

import importlib
from collections.abc import Iterator, Mapping
from importlib import metadata
from typing import Generic, TypeVar

__all__ = ["Registry", "PluginError", "READERS", "FILTERS", "MEASUREMENTS", "EFFECTS", "REGISTRIES"]

T = TypeVar("T")


class PluginError(ValueError):
    """A plug-in that cannot be loaded or registered: its name, and why."""


class Registry(Mapping[str, type[T]], Generic[T]):
    """Name -> class of one kind of plug-in, loaded on first use.

    Parameters
    ----------
    kind : str
        What the plug-ins are, in words (``"log reader"``): used in messages.
    group : str
        The entry-point group other packages register under (``"magkf.readers"``).
    interface : str
        ``"module:Class"`` of the kind's interface; every plug-in must subclass it.
    builtins : dict of str to str
        magkf's own plug-ins, ``name -> "module:Class"``, in the order listings give them.
    """

    def __init__(self, kind: str, group: str, interface: str, builtins: dict[str, str]):
        self.kind, self.group, self.interface = kind, group, interface
        self._specs: dict[str, str] = dict(builtins)
        self._origins: dict[str, str] = dict.fromkeys(builtins, "magkf")
        self._builtin = frozenset(builtins)
        self._loaded: dict[str, type[T]] = {}
        self._entry_points_read = False

    # ------------------------------------------------------------------ the mapping
    def __getitem__(self, name: str) -> type[T]:
        if name in self._loaded:
            return self._loaded[name]
        if name not in self._specs:
            self._read_entry_points()
        if name not in self._specs:
            raise KeyError(name)
        cls = _load(self._specs[name], f"{self.kind} {name!r}")
        self._check(cls, name)
        self._loaded[name] = cls
        return cls

    def __iter__(self) -> Iterator[str]:
        self._read_entry_points()
        return iter(list(self._specs))

    def __len__(self) -> int:
        self._read_entry_points()
        return len(self._specs)

    def __contains__(self, name) -> bool:
        if name in self._specs:
            return True
        self._read_entry_points()
        return name in self._specs

    def __repr__(self) -> str:
        return f"Registry({self.kind!r}: {', '.join(self)})"

    # ------------------------------------------------------------------ adding plug-ins
    def register(self, cls: type[T] | None = None, *, replace: bool = False):
        """Make ``cls`` available under ``cls.name``; usable as a decorator.

        Parameters
        ----------
        cls : type
            A subclass of the kind's interface with a ``name`` attribute.
        replace : bool
            Take the place of a plug-in of another package or an earlier registration of that name. magkf's
            own plug-ins are never replaced.

        Returns
        -------
        type
            ``cls``, so that ``@REGISTRY.register`` leaves the class as it is.

        Raises
        ------
        PluginError
            ``cls`` is not a subclass of the interface, has no ``name``, or its name is taken.
        """
        if cls is None:
            return lambda c: self.register(c, replace=replace)
        name = getattr(cls, "name", None)
        if not isinstance(name, str) or not name:
            raise PluginError(f"a {self.kind} needs a name (a class attribute 'name')")
        self._check(cls, name)
        present = self._loaded.get(name)
        if present is not cls and name in self:
            if name in self._builtin:
                raise PluginError(f"{self.kind} {name!r} is one of magkf's own: give yours another name")
            if not replace and not _same_definition(present, cls):
                raise PluginError(f"a {self.kind} named {name!r} is registered already ({self._specs[name]})")
        self._specs[name] = f"{cls.__module__}:{cls.__qualname__}"
        self._origins[name] = "registered"
        self._loaded[name] = cls
        return cls

    def unregister(self, name: str) -> None:
        """Forget the plug-in ``name`` (a registered or another package's one; magkf's own stay)."""
        if name in self._builtin:
            raise PluginError(f"{self.kind} {name!r} is one of magkf's own and stays")
        if name not in self:
            raise KeyError(name)
        del self._specs[name]
        self._origins.pop(name, None)
        self._loaded.pop(name, None)

    __delitem__ = unregister

    def is_builtin(self, name: str) -> bool:
        """Whether ``name`` is one of magkf's own plug-ins of this kind."""
        return name in self._builtin

    def source(self, name: str) -> str:
        """Where the plug-in ``name`` is defined: its ``"module:Class"``."""
        if name not in self:
            raise KeyError(name)
        return self._specs[name]

    def origin(self, name: str) -> str:
        """How the plug-in ``name`` became known: ``magkf`` (magkf's own), ``entry point DIST`` (an installed
        package's entry point), or ``registered`` (by the running program, or an effect file)."""
        if name not in self:
            raise KeyError(name)
        return self._origins[name]

    # ------------------------------------------------------------------ inside
    def _read_entry_points(self) -> None:
        if self._entry_points_read:
            return
        self._entry_points_read = True
        for ep in metadata.entry_points(group=self.group):
            if ep.name not in self._specs:
                self._specs[ep.name] = ep.value
                dist = getattr(ep, "dist", None)
                self._origins[ep.name] = f"entry point of {dist.name}" if dist is not None else "entry point"

    def _check(self, cls, name: str) -> None:
        base = _load(self.interface, f"the {self.kind} interface")
        if not (isinstance(cls, type) and issubclass(cls, base)):
            raise PluginError(f"{self.kind} {name!r} is not a subclass of {self.interface.replace(':', '.')}")
        if getattr(cls, "name", None) != name:
            raise PluginError(f"{self.kind} registered as {name!r} calls itself {getattr(cls, 'name', None)!r}")


def _load(spec: str, what: str):
    """The object ``"module:attribute"`` names."""
    module, _, attribute = spec.partition(":")
    try:
        obj = importlib.import_module(module)
        for part in attribute.split("."):
            obj = getattr(obj, part)
    except (ImportError, AttributeError) as exc:
        raise PluginError(f"{what} cannot be loaded from {spec!r}: {exc}") from None
    return obj


def _same_definition(a, b) -> bool:
    """The same class defined again (a file loaded twice): same module name and qualified name."""
    return a is not None and (a.__module__, a.__qualname__) == (b.__module__, b.__qualname__)


READERS: Registry = Registry(
    "log reader",
    "magkf.readers",
    "magkf.io.readers:LogReader",
    {
        "csv": "magkf.io.drivelog:CanonicalCsv",
        "parquet": "magkf.io.drivelog:CanonicalParquet",
        "ulog": "magkf.io.ulog:ULogReader",
        "dataflash": "magkf.io.dataflash:DataFlashReader",
        "mapped": "magkf.io.columnmap:MappedTable",
    },
)

FILTERS: Registry = Registry(
    "filter",
    "magkf.filters",
    "magkf.online.filters:Filter",
    {"ekf": "magkf.online.filters:EKF", "ukf": "magkf.online.filters:UKF"},
)

MEASUREMENTS: Registry = Registry(
    "measurement model",
    "magkf.measurements",
    "magkf.online.measurements:MeasurementModel",
    {
        "magnitude": "magkf.online.measurements:Magnitude",
        "vector": "magkf.online.measurements:Vector",
        "both": "magkf.online.measurements:Both",
    },
)

EFFECTS: Registry = Registry(
    "effect",
    "magkf.effects",
    "magkf.effects.base:Effect",
    {
        "temperature_bias": "magkf.effects.temperature_bias:TemperatureBias",
        "temperature_scale": "magkf.effects.temperature_scale:TemperatureScale",
        "current_field": "magkf.effects.current_field:CurrentField",
        "time_lag": "magkf.effects.time_lag:TimeLag",
        "field_anomaly": "magkf.effects.field_anomaly:FieldAnomaly",
        "bias_drift": "magkf.effects.bias_drift:BiasDrift",
        "eddy_current": "magkf.effects.eddy_current:EddyCurrent",
    },
)

#: Every registry by the kind's plural, as the command line and the docs list them.
REGISTRIES = {"readers": READERS, "filters": FILTERS, "measurements": MEASUREMENTS, "effects": EFFECTS}

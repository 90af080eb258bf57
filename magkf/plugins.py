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

import contextlib
import importlib
import inspect
import threading
from collections.abc import Iterator, Mapping
from importlib import metadata
from typing import Generic, TypeVar

__all__ = ["Registry", "PluginError", "PluginWarning", "READERS", "FILTERS", "MEASUREMENTS", "EFFECTS", "REGISTRIES"]

T = TypeVar("T")


class PluginError(ValueError):
    """A plug-in that cannot be loaded or registered: its name, and why."""


class PluginWarning(UserWarning):
    """A plug-in left out because it cannot be loaded."""


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
        self._lock = threading.RLock()  # entry points read, plug-ins registered and first loads: one at a time

    # ------------------------------------------------------------------ the mapping
    def __getitem__(self, name: str) -> type[T]:
        if name in self._loaded:
            return self._loaded[name]
        with self._lock:
            if name not in self._specs:
                self._read_entry_points()
            if name not in self._specs:
                raise KeyError(name)
            if name not in self._loaded:
                cls = _load(self._specs[name], f"{self.kind} {name!r}")
                self._check(cls, name)
                self._loaded[name] = cls
            return self._loaded[name]

    def loadable(self) -> Iterator[tuple[str, type[T]]]:
        """Every plug-in that loads, ``(name, class)``, in listing order; one that cannot be loaded is skipped
        with a ``PluginWarning`` saying why, so that another package's broken plug-in stops nothing else."""
        import warnings

        for name in self:
            try:
                yield name, self[name]
            except PluginError as exc:
                warnings.warn(f"{exc}; it is left out", PluginWarning, stacklevel=2)

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
        with self._lock:
            if name in self and self._specs[name] == _spec(cls) and self._loaded.get(name, cls) is cls:
                self._loaded[name] = cls
                return cls  # the class that name stands for already: nothing changes
            if name in self._builtin:
                raise PluginError(f"{self.kind} {name!r} is one of magkf's own: give yours another name")
            present = self._loaded.get(name)
            if name in self and not replace and not _same_definition(present, cls):
                raise PluginError(f"a {self.kind} named {name!r} is registered already ({self._specs[name]})")
            self._specs[name] = _spec(cls)
            self._origins[name] = "registered"
            self._loaded[name] = cls
        return cls

    @contextlib.contextmanager
    def restoring(self):
        """A scope after which the registry is as it was before: what was registered or unregistered inside it
        is undone (a command's ``--effect-file``, one task of a fleet), so that nothing of one run changes
        the next in the same process."""
        with self._lock:
            saved = dict(self._specs), dict(self._origins), dict(self._loaded)
        try:
            yield self
        finally:
            with self._lock:
                # entry points first read inside the scope stay known (they are read once)
                read = {
                    n: (self._specs[n], origin)
                    for n, origin in self._origins.items()
                    if n not in saved[0] and origin.startswith("entry point")
                }
                self._specs, self._origins, self._loaded = (dict(d) for d in saved)
                for n, (spec, origin) in read.items():
                    self._specs[n], self._origins[n] = spec, origin

    def unregister(self, name: str) -> None:
        """Forget the plug-in ``name`` (a registered or another package's one; magkf's own stay)."""
        if name in self._builtin:
            raise PluginError(f"{self.kind} {name!r} is one of magkf's own and stays")
        with self._lock:
            if name not in self:
                raise KeyError(name)
            del self._specs[name]
            self._origins.pop(name, None)
            self._loaded.pop(name, None)

    __delitem__ = unregister

    def builtin_names(self) -> list[str]:
        """The names of magkf's own plug-ins of this kind, in listing order (no entry point is read)."""
        return [name for name in self._specs if name in self._builtin]

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
        with self._lock:
            if self._entry_points_read:
                return
            for ep in metadata.entry_points(group=self.group):
                if ep.name not in self._specs:
                    self._specs[ep.name] = ep.value
                    dist = getattr(ep, "dist", None)
                    self._origins[ep.name] = f"entry point of {dist.name}" if dist is not None else "entry point"
            self._entry_points_read = True

    def _check(self, cls, name: str) -> None:
        base = _load(self.interface, f"the {self.kind} interface")
        if not (isinstance(cls, type) and issubclass(cls, base)):
            raise PluginError(f"{self.kind} {name!r} is not a subclass of {self.interface.replace(':', '.')}")
        if getattr(cls, "name", None) != name:
            raise PluginError(f"{self.kind} registered as {name!r} calls itself {getattr(cls, 'name', None)!r}")


def _load(spec: str, what: str):
    """The object ``"module:attribute"`` names; PluginError whatever importing it raises (a plug-in's code is
    another package's: its failure is reported in one line, not as magkf's)."""
    module, _, attribute = spec.partition(":")
    try:
        obj = importlib.import_module(module)
        for part in attribute.split("."):
            obj = getattr(obj, part)
    except Exception as exc:
        what_failed = " ".join(str(exc).split())
        raise PluginError(f"{what} cannot be loaded from {spec!r}: {type(exc).__name__}: {what_failed}") from None
    return obj


def _spec(cls) -> str:
    """``"module:Class"`` of a class."""
    return f"{cls.__module__}:{cls.__qualname__}"


def _source_file(cls) -> str | None:
    """The file that defines ``cls``: that of its first method's code (a module run from a file, as an effect
    file is, is not in ``sys.modules``), else its module's; None for neither."""
    for value in vars(cls).values():
        code = getattr(getattr(value, "__func__", value), "__code__", None)
        if code is not None:
            return code.co_filename
    try:
        return inspect.getfile(cls)
    except (TypeError, OSError):
        return None


def _same_definition(a, b) -> bool:
    """The same class defined again (a file loaded twice): the same module, qualified name and file."""
    return a is not None and (_spec(a), _source_file(a)) == (_spec(b), _source_file(b))


READERS: Registry = Registry(
    "log reader",
    "magkf.readers",
    "magkf.io.readers:LogReader",
    {
        "csv": "magkf.io.drivelog:CanonicalCsv",
        "parquet": "magkf.io.drivelog:CanonicalParquet",
        "ulog": "magkf.io.ulog:ULogReader",
        "dataflash": "magkf.io.dataflash:DataFlashReader",
        "tlog": "magkf.io.tlog:TelemetryLogReader",
        "rosbag": "magkf.io.rosbag:RosBagReader",
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

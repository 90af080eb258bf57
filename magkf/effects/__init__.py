"""Physical effects: blocks of parameters that add to the raw magnetometer reading.

Built-ins (``--effect NAME[:COLUMN]``): ``temperature_bias``, ``temperature_scale``, ``current_field``,
``time_lag``, ``field_anomaly``, ``bias_drift``, ``eddy_current``. Every effect is registered in
``magkf.plugins.EFFECTS``: magkf's own, another package's (entry-point group ``magkf.effects``), one
registered in the program (``EFFECTS.register``), and those of a file of its own loaded with
``load_effect_file`` (``--effect-file``). Every function here finds effects there.
"""

from __future__ import annotations

import importlib.util
import inspect
from pathlib import Path

import numpy as np

from ..calibration import Calibration, StoredEffect
from ..errors import InputError
from ..plugins import EFFECTS, PluginError
from .base import Effect, EpochData, missing_column
from .channels import channel_kind
from .core import SoftHardIron
from .linear import LinearEffect

#: magkf's own effects, by name (each also in ``EFFECTS``).
BUILTIN = {name: EFFECTS[name] for name in EFFECTS.builtin_names()}


def _effect_class(name: str, source=None):
    """The registered effect class ``name``; InputError (naming ``source``) when it is unknown or fails to load."""
    if name not in EFFECTS:
        raise InputError(f"unknown effect {name!r}; known: {', '.join(sorted(EFFECTS))}", source)
    try:
        return EFFECTS[name]
    except PluginError as exc:
        raise InputError(str(exc), source) from None


def make_effect(spec: str) -> Effect:
    """An effect from ``NAME`` or ``NAME:COLUMN`` of a registered effect (``EFFECTS``)."""
    name, _, column = spec.partition(":")
    cls = _effect_class(name)
    takes_column = "column" in inspect.signature(cls.__init__).parameters
    if column and not takes_column:
        raise InputError(f"effect {name!r} takes no column (got {spec!r})")
    return cls(column=column) if column else cls()


def load_effect_file(path) -> dict:
    """Register the ``Effect`` subclasses a Python file defines (in ``EFFECTS``) and return them by name.

    The file is run as Python with the user's rights, as ``import`` would: load only files you trust. Each
    class found is tried on a few plausible epochs (``_tried``) before it is registered. Loading the same
    file again registers its classes again. They stay registered (and so are candidates of every later
    diagnosis) until unregistered, or until the end of an ``EFFECTS.restoring()`` scope, which every command
    and every fleet task runs in.

    Parameters
    ----------
    path : str or pathlib.Path
        A ``.py`` file.

    Returns
    -------
    dict of str to type
        The effect classes the file defines, by ``name``.

    Raises
    ------
    InputError
        Naming the file: it is missing or not Python, it fails to load (``sys.exit`` included), it defines no
        effect, an effect's name is a built-in's or an installed package's, an effect lacks a method of
        ``Effect``, or an effect fails on the test epochs.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("no such effect file", str(path))
    if path.suffix != ".py":
        raise InputError("an effect file is Python source ending in .py", str(path))
    found = _effect_classes(_run_file(path), str(path))
    for name, cls in found.items():
        _tried(name, cls, str(path))
    for cls in found.values():
        EFFECTS.register(cls, replace=True)
    return found


def _effect_classes(module, source: str) -> dict:
    """The effect classes ``module`` defines, by name; InputError naming ``source`` for none, one that lacks a
    method of ``Effect``, or one named like a built-in or an installed package's effect."""
    defined = [
        obj
        for obj in vars(module).values()
        if inspect.isclass(obj)
        and issubclass(obj, Effect)
        and obj.__module__ == module.__name__
        and obj.name not in ("effect", "core")
    ]
    for cls in filter(inspect.isabstract, defined):
        missing = ", ".join(f"{m}()" for m in sorted(cls.__abstractmethods__))
        raise InputError(f"effect {cls.name!r} does not implement {missing}", source)
    found = {cls.name: cls for cls in defined}
    if not found:
        raise InputError("the file defines no Effect subclass with a name", source)
    for name in sorted(found):
        if EFFECTS.is_builtin(name):
            raise InputError(f"effect {name!r} is a built-in effect's name: give yours another", source)
        if name in EFFECTS and EFFECTS.origin(name).startswith("entry"):
            what = f"effect {name!r} is the name of an installed package's effect ({EFFECTS.origin(name)})"
            raise InputError(f"{what}: give yours another", source)
    return found


def _run_file(path: Path):
    """The module the Python file ``path`` makes; InputError naming it when running it fails."""
    spec = importlib.util.spec_from_file_location(f"magkf_user_effect_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    try:
        spec.loader.exec_module(module)
    except KeyboardInterrupt:
        raise
    except BaseException as exc:  # the user's code, sys.exit included: reported on one line
        what = " ".join(str(exc).split())
        raise InputError(f"the effect file failed to load: {type(exc).__name__}: {what}", str(path)) from None
    return module


def _test_epochs(effect: Effect, n: int) -> EpochData:
    """``n`` plausible epochs for trying ``effect``: a mid-latitude field, small rates, its columns from 1 to 2."""
    rng = np.random.default_rng(0)
    field_ned = np.tile([20_000.0, 1_000.0, 43_000.0], (n, 1))
    return EpochData(
        time=1.78e9 + np.arange(n, dtype=float),
        field_body=field_ned + rng.normal(0, 100, (n, 3)),
        field_ned=field_ned,
        columns={c: np.linspace(1.0, 2.0, n) for c in effect.columns},
        mag=field_ned + rng.normal(0, 100, (n, 3)),
        c_nb=np.tile(np.eye(3), (n, 1, 1)),
        field_body_rate=rng.normal(0, 10, (n, 3)),
    )


def _tried(name: str, cls, source: str) -> None:
    """Raise InputError naming ``source`` unless the effect class ``cls`` can be made with its defaults and, at
    its prior mean on a few plausible epochs, gives a finite ``contribution`` (N, 3) and ``jacobian``
    (N, 3, size), linear or not."""
    n = 4
    try:
        effect = cls()
        data = _test_epochs(effect, n)
        theta = np.asarray(effect.prior()[0], dtype=float)
        values = {
            "contribution()": (np.asarray(effect.contribution(theta, data), dtype=float), (n, 3)),
            "jacobian()": (np.asarray(effect.jacobian(theta, data), dtype=float), (n, 3, effect.size)),
        }
    except Exception as exc:  # the user's code: reported on one line
        what = " ".join(str(exc).split())
        raise InputError(f"effect {name!r} fails on test epochs: {type(exc).__name__}: {what}", source) from None
    for method, (value, shape) in values.items():
        if value.shape != shape:
            raise InputError(
                f"effect {name!r}: {method} gives shape {value.shape} for {n} epochs, expected {shape}", source
            )
        if not np.isfinite(value).all() or np.abs(value).max(initial=0.0) > 1e9:
            raise InputError(
                f"effect {name!r}: {method} gives values that are not finite or beyond 1e9 on test epochs", source
            )


def candidates(columns) -> list[Effect]:
    """Every effect that can be tried on a log with these auxiliary ``columns``: effects without a column
    once; an effect of a column on every column of a kind it declares (``Effect.channels``, read by
    ``channel_kind``), or on its default column only when it declares none. Every registered effect
    (``EFFECTS``) that loads is a candidate."""
    out = []
    for _, cls in EFFECTS.loadable():
        default = _default_column(cls)
        if default is None:
            out.append(cls())
            continue
        for column in columns:
            kinds = cls.channels
            if column == default if not kinds else channel_kind(column) in kinds:
                out.append(cls(column=column))
    return out


def untried_columns(columns) -> list[str]:
    """The ``columns`` no candidate of ``candidates`` uses (their kind is unknown or fits no effect)."""
    used = {c for e in candidates(columns) for c in e.columns}
    return [c for c in columns if c not in used]


def stored_effect(effect: Effect, values, stds) -> StoredEffect:
    """``effect`` with its estimated ``values`` and standard deviations ``stds`` (k,), as a file holds it."""
    units = tuple(effect.units[j] if j < len(effect.units) else "" for j in range(effect.size))
    return StoredEffect(
        effect.label,
        effect.settings(),
        tuple(effect.parameter_names),
        tuple(float(v) for v in values),
        tuple(float(s) for s in stds),
        units,
    )


def restore_effects(cal: Calibration) -> tuple[Effect, ...]:
    """The effects a calibration file stores, rebuilt with their settings (user effects need their classes
    registered, e.g. by ``load_effect_file``). Each remembers the calibration file (``Effect.stored_in``), which
    its errors name (a column the log lacks).

    Raises
    ------
    InputError
        Naming the calibration file (``Calibration.file``; None for one not read from a file): an effect that is
        not registered, settings that its schema refuses (``check_settings``) or its class does not take, or
        parameters that are not the effect's.
    """
    out = []
    source = cal.file
    for i, stored in enumerate(cal.effects):
        where = f"calibration effect {stored.label!r}"
        if stored.name not in EFFECTS:
            raise InputError(f"{where} is not a built-in; give the --effect-file that defines it", source)
        cls = _effect_class(stored.name, source)
        check_settings(cls, stored.settings, source, f"effects[{i}].settings")
        try:
            effect = cls(**stored.settings)
        except Exception as exc:  # a constructor (the user's code, for a plug-in) that refuses the settings
            what = " ".join(str(exc).split())
            raise InputError(f"{where}: its settings do not fit {cls.__name__} ({what})", source) from None
        if tuple(effect.parameter_names) != tuple(stored.names):
            raise InputError(
                f"{where} stores parameters {', '.join(stored.names)}; the effect has "
                f"{', '.join(effect.parameter_names)}",
                source,
            )
        effect.stored_in = source
        out.append(effect)
    return tuple(out)


def check_columns(effects, columns, log: str | None = None) -> None:
    """InputError unless a log with the auxiliary ``columns`` has every column the ``effects`` read: it names the
    calibration file an effect was restored from (``Effect.stored_in``) and the column, else the ``log``."""
    columns = list(columns)
    for effect in effects:
        for column in effect.columns:
            if column not in columns:
                raise missing_column(effect, column, columns, log)


def check_settings(cls, settings: dict, source, root: str = "settings") -> None:
    """InputError naming ``source`` unless ``settings`` are what the effect class ``cls`` takes: its settings'
    schema (``Effect.settings_json_schema``: no unknown key, each of its type) and finite numbers. ``root`` is
    the settings' path in their file (``effects[0].settings``), named in the error."""
    from ..schema import check

    check(settings, cls.settings_json_schema(), source, root, finite=True)


def _default_column(cls):
    parameter = inspect.signature(cls.__init__).parameters.get("column")
    return None if parameter is None else parameter.default


__all__ = [
    "Effect",
    "EpochData",
    "LinearEffect",
    "SoftHardIron",
    "BUILTIN",
    "EFFECTS",
    "make_effect",
    "load_effect_file",
    "candidates",
    "untried_columns",
    "stored_effect",
    "restore_effects",
    "check_settings",
    "check_columns",
    "channel_kind",
]


def __getattr__(name: str):
    """magkf's own effect classes by class name (``from magkf.effects import TimeLag``), from ``EFFECTS``."""
    for cls in BUILTIN.values():
        if cls.__name__ == name:
            return cls
    raise AttributeError(f"module 'magkf.effects' has no attribute {name!r}")

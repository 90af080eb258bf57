"""The physical-effect interface: one block of parameters and its contribution to the raw field.

Every part of magkf that models the magnetometer (the Kalman filters, the batch solver, the simulator,
the diagnostics) sees the sensor as a sum of effects:

    m = sum over effects of contribution(theta_effect, data) + noise      (nT, sensor axes)

The core effect (``magkf.effects.core.SoftHardIron``) contributes ``R B_b + b`` and is always the first
block of the state; any further effect adds its own block without a change to the filter code.

Every method that gives values per epoch (``contribution``, ``jacobian``, ``regressors``) takes ``rows``: the
epochs of ``data`` to give them at (a slice, an integer array or a boolean mask; None, the default: all of
them, the range [0, N)). An effect computed epoch by epoch gives at ``rows`` what it gives on
``data.take(rows)``; one that needs other epochs (a spline along the log's time, the log's time span) reads
them from ``data`` and gives only the rows asked for, so that a long log can be gone through a stretch at a
time with the same numbers as at once.
"""

from __future__ import annotations

import functools
import inspect
from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np

from ..conventions import epochs_of
from ..errors import InputError

__all__ = [
    "FD_STEP",
    "EpochData",
    "at_rows",
    "rate_of_change",
    "Effect",
    "ROW_METHODS",
    "missing_column",
    "effect_file",
]

#: Relative and absolute step of the finite-difference Jacobian default.
FD_STEP = 1e-6


@dataclass(frozen=True)
class EpochData:
    """What an effect may use at N epochs.

    ``time`` (N,) UNIX s; ``field_body`` (N, 3) nT, the reference field in the body frame (NaN where
    there is no attitude); ``field_ned`` (N, 3) nT, the reference field; ``columns`` maps auxiliary
    column names to (N,) arrays; ``mag`` (N, 3) the raw reading, nT; ``c_nb`` (N, 3, 3) the attitude;
    ``field_body_rate`` (N, 3) nT/s, the rate of change of ``field_body``; ``R0`` (3, 3) the initial
    calibration's ``R`` (effects acting through the sensor's axes use it to stay linear);
    ``field_body_accel`` (N, 3) nT/s^2, the rate of ``field_body_rate`` (None where it is not known, as in
    real time).
    """

    time: np.ndarray
    field_body: np.ndarray
    field_ned: np.ndarray
    columns: dict = field(default_factory=dict)
    mag: np.ndarray | None = None
    c_nb: np.ndarray | None = None
    field_body_rate: np.ndarray | None = None
    R0: np.ndarray = field(default_factory=lambda: np.eye(3))
    field_body_accel: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.time)

    def take(self, index, lazy: bool = False) -> EpochData:
        """The same data at the epochs ``index`` (an integer array, a slice or a boolean mask; None: all, this
        data itself). Attitude matrices made when read (``conventions.AttitudeMatrices``) are made here for these
        epochs (a block's or a chunk's, which its users read several times), or with ``lazy`` stay so."""
        if index is None:
            return self

        def cut(a):
            if a is None:
                return None
            return epochs_of(a, index) if lazy else a[index]

        return EpochData(
            self.time[index],
            self.field_body[index],
            self.field_ned[index],
            {k: v[index] for k, v in self.columns.items()},
            cut(self.mag),
            cut(self.c_nb),
            cut(self.field_body_rate),
            self.R0,
            cut(self.field_body_accel),
        )


def at_rows(values: np.ndarray, rows) -> np.ndarray:
    """One per-epoch array of an ``EpochData`` at the epochs ``rows`` (None: all of it, itself), without taking
    the data's other arrays as ``EpochData.take`` does."""
    return values if rows is None else values[rows]


def rate_of_change(time_s: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Time derivative (N, 3) of ``values`` (N, 3) by central differences, one-sided at the ends and beside a
    missing value (an epoch next to a gap in the attitude takes its rate from the side that has data); NaN
    where the epoch's own value or both its neighbours are missing."""
    if len(time_s) < 2:
        return np.zeros_like(values)
    rate = _gradient(time_s, values)
    beside_gap = ~np.isfinite(rate) & np.isfinite(values)
    if beside_gap.any():
        step = np.diff(values, axis=0) / np.diff(time_s)[:, None]  # (N - 1, 3): from each epoch to the next
        gap = np.full((1, values.shape[1]), np.nan)
        backward, forward = np.vstack([gap, step]), np.vstack([step, gap])
        one_sided = np.where(np.isfinite(backward), backward, forward)
        rate[beside_gap] = one_sided[beside_gap]
    return rate


def _gradient(t: np.ndarray, f: np.ndarray) -> np.ndarray:
    """``np.gradient(f, t, axis=0)`` (N >= 2 rows) by its formula for uneven steps whatever the steps: second-order
    central differences inside, one-sided at the ends. numpy takes another formula where every step of ``t`` is
    equal, which rounds differently: a few rows of a log with even steps would then differ in their last bits from
    the same rows of the whole log (``online.prepared_rows`` prepares a log's rows in parts)."""
    out = np.empty(np.shape(f))
    dt = np.diff(t)[:, None]
    out[0], out[-1] = (f[1] - f[0]) / dt[0], (f[-1] - f[-2]) / dt[-1]
    if len(t) > 2:
        dx1, dx2 = dt[:-1], dt[1:]
        a = -dx2 / (dx1 * (dx1 + dx2))
        b = (dx2 - dx1) / (dx1 * dx2)
        c = dx1 / (dx2 * (dx1 + dx2))
        out[1:-1] = a * f[:-2] + b * f[1:-1] + c * f[2:]
    return out


#: Largest value (nT, or nT per unit of a parameter) a user's effect may give on a log, as on its test epochs.
VALUE_MAX, VALUE_MAX_TEXT = 1e9, "1e9"

#: The per-epoch methods of an effect, each taking the epochs ``rows`` of its ``data``.
ROW_METHODS = ("contribution", "jacobian", "regressors")


def _data_argument(args, kwargs) -> EpochData:
    """The ``data`` argument of a per-epoch method called with ``args`` and ``kwargs`` (it comes last)."""
    return kwargs["data"] if "data" in kwargs else args[-1]


def missing_column(effect, column: str, columns, log: str | None = None) -> InputError:
    """The error for ``effect`` needing ``column``, which a log with the auxiliary ``columns`` lacks: it names the
    calibration file the effect was restored from (``Effect.stored_in``), else the ``log``."""
    where = "the log" if log is None or effect.stored_in is None else log
    listed = ", ".join(columns) or "none"
    instead = "a calibration without the effect" if effect.stored_in else "leave the effect out"
    return InputError(
        f"effect {effect.label!r} needs column {column!r}, which {where} lacks (its auxiliary columns: {listed}); "
        f"give a log that records it, or {instead}",
        effect.stored_in or log,
    )


def _guarded(method):
    """A per-epoch method that first checks the log has the effect's columns (InputError naming the calibration
    file the effect came from, not a KeyError); for an effect whose class is not magkf's own (a user's, even
    where the method is inherited from ``LinearEffect``), what its code raises, and values that are not finite
    where its inputs are, are errors naming its file."""

    @functools.wraps(method)
    def checked(self, *args, rows=None, **kwargs):
        data = _data_argument(args, kwargs)
        for column in self.columns:
            if column not in data.columns:
                raise missing_column(self, column, list(data.columns))
        if type(self).__module__.startswith("magkf."):
            return method(self, *args, rows=rows, **kwargs)
        try:
            out = method(self, *args, rows=rows, **kwargs)
        except (InputError, KeyboardInterrupt):
            raise
        except BaseException as exc:  # the user's code (sys.exit included): reported on one line, naming its file
            what = " ".join(str(exc).split())
            raise InputError(
                f"effect {self.name!r} fails on the log in {method.__name__}(): {type(exc).__name__}: {what}",
                effect_file(type(self)),
            ) from None
        _check_finite(self, method.__name__, out, data, rows, args)
        return out

    return checked


def effect_file(cls) -> str:
    """The file that defines the effect class ``cls`` (its ``--effect-file``), as errors name it."""
    from ..plugins import _source_file

    return _source_file(cls) or cls.__module__


def _check_finite(effect, name: str, out, data: EpochData, rows, args) -> None:
    """InputError naming the effect's file where the per-epoch values ``out`` of its method ``name`` are infinite,
    or NaN at an epoch whose field, reading and the effect's columns are all known."""
    try:
        values = np.asarray(out, dtype=float)
        axis = 1 if name == "contribution" and np.ndim(args[0]) == 2 else 0
        known = np.ones(values.shape[axis], bool)
        for given in (data.field_body, data.mag):  # either may be absent (a data set made for one effect)
            if given is not None:
                known &= np.all(np.isfinite(np.asarray(at_rows(given, rows), float)), axis=1)
        per_epoch = np.moveaxis(values, axis, 0).reshape(len(known), -1)
    except (TypeError, ValueError, IndexError, np.exceptions.AxisError):
        raise InputError(
            f"effect {effect.name!r}: {name}() gives values of shape {np.shape(out)}, not a value per epoch of the log",
            effect_file(type(effect)),
        ) from None
    for column in effect.columns:
        known &= np.isfinite(np.asarray(at_rows(data.columns[column], rows), float))
    with np.errstate(invalid="ignore"):
        absurd = (np.abs(per_epoch) > VALUE_MAX).any(axis=1)
    bad = absurd | np.isinf(per_epoch).any(axis=1) | (np.isnan(per_epoch).any(axis=1) & known)
    if bad.any():
        raise InputError(
            f"effect {effect.name!r}: {name}() gives values that are not finite or beyond {VALUE_MAX_TEXT} at "
            f"{int(bad.sum())} of {len(bad)} epochs of the log whose inputs are finite (first at epoch "
            f"{int(np.argmax(bad))}); the effect must give finite values wherever its inputs are",
            effect_file(type(effect)),
        )


def _epoch_by_epoch(method):
    """A per-epoch method written without ``rows`` (``contribution(theta, data)``, as a user's effect may be):
    evaluated on ``data.take(rows)``, the effect being computed epoch by epoch."""

    @functools.wraps(method)
    def at_rows(self, *args, rows=None, **kwargs):
        if rows is not None:
            if "data" in kwargs:
                kwargs["data"] = kwargs["data"].take(rows)
            else:
                args = (*args[:-1], args[-1].take(rows))
        return method(self, *args, **kwargs)

    return at_rows


class Effect(ABC):
    """The interface of a physical effect (a plug-in kind: ``magkf.plugins.EFFECTS``).

    Subclass it in a file of its own. Methods to implement: ``contribution``; optionally ``jacobian`` (finite
    differences by default), ``prior`` and ``random_walk``. The per-epoch methods (``ROW_METHODS``) take
    ``rows``, the epochs of ``data`` to evaluate (see the module's docstring); one written without it is
    taken to be computed epoch by epoch and is evaluated on ``data.take(rows)``.

    Attributes
    ----------
    name : str
        Class attribute: the name accepted by ``--effect``.
    parameter_names : tuple of str
        Class attribute: names of the parameters, in state order.
    columns : tuple of str
        Class attribute: log columns the effect needs.
    units : tuple of str
        Class attribute: unit of each parameter, for reports.
    linear : bool
        Class attribute: True when ``contribution`` is linear in the effect's own parameters and independent
        of the other blocks; the filters then compute its Jacobian once for each epoch.
    channels : tuple of str
        Class attribute: the kinds of channel an effect of a column accepts
        (``magkf.effects.channels.KINDS``: ``temperature``, ``current``, ``throttle``, ``angle``, ``speed``,
        ``voltage``); the diagnosis forms candidates only from columns of these kinds. Empty: the effect's
        default column only.
    wanders : bool
        Class attribute: True when the parameters follow a random walk rather than holding a value (a
        drifting offset): the diagnosis then tests their constancy (Nyblom's test on the scores of
        ``jacobian``) and ``regressors`` is the slow basis over which the wander is fitted for the held-out
        residual.
    """

    name: str = "effect"
    parameter_names: tuple = ()
    columns: tuple = ()
    units: tuple = ()
    linear: bool = True
    channels: tuple = ()
    wanders: bool = False
    #: How many true parameters ``simulate`` accepts (default: the effect's own parameters).
    simulation_sizes: tuple = ()

    #: JSON Schema properties of the settings (``settings``; constructor argument -> schema, ``magkf.schema``),
    #: by which a calibration file's settings of the effect are checked; None: read from ``__init__``'s
    #: defaults (a number, a string, true or false), every argument without a default required.
    settings_schema: dict | None = None
    #: The calibration file the effect was restored from (``magkf.effects.restore_effects``), named in its errors.
    stored_in: str | None = None

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        for name in ROW_METHODS:
            method = cls.__dict__.get(name)
            if callable(method) and "rows" not in inspect.signature(method).parameters:
                method = _epoch_by_epoch(method)
            if callable(method):
                setattr(cls, name, _guarded(method))

    @classmethod
    def settings_json_schema(cls) -> dict:
        """The JSON Schema (``magkf.schema``) of the settings a calibration file stores for this effect: an object
        of exactly the constructor's arguments (``settings_schema``, else read from ``__init__``'s defaults)."""
        from ..schema import BOOLEAN, NUMBER, STRING, strict

        if cls.settings_schema is not None:
            return strict(dict(cls.settings_schema))
        properties, required, open_ = {}, [], False
        if cls.__init__ is not object.__init__:
            for name, p in inspect.signature(cls.__init__).parameters.items():
                if name == "self" or p.kind is p.VAR_POSITIONAL:
                    continue
                if p.kind is p.VAR_KEYWORD:
                    open_ = True
                    continue
                default = p.default
                if default is p.empty:
                    required.append(name)
                kind = next(
                    (s for t, s in ((bool, BOOLEAN), ((int, float), NUMBER), (str, STRING)) if isinstance(default, t)),
                    {},
                )
                properties[name] = kind
        return strict(properties, required, additionalProperties=open_)

    @property
    def label(self) -> str:
        """The name as ``--effect`` accepts it: ``name``, or ``name:COLUMN`` for an effect of a column."""
        return f"{self.name}:{self.columns[0]}" if self.columns else self.name

    @property
    def size(self) -> int:
        return len(self.parameter_names)

    def prior(self) -> tuple[np.ndarray, np.ndarray]:
        """Prior mean and standard deviation of the parameters, each (k,)."""
        return np.zeros(self.size), np.ones(self.size)

    def random_walk(self) -> np.ndarray:
        """Random-walk standard deviation of each parameter per square root of a second, (k,)."""
        return np.zeros(self.size)

    @abstractmethod
    def contribution(self, theta, data: EpochData, rows=None) -> np.ndarray:
        """Raw-field contribution in nT at the epochs ``rows`` of ``data`` (None: all N): (N, 3) for ``theta``
        of shape (k,), (S, N, 3) for (S, k)."""

    def jacobian(self, theta, data: EpochData, rows=None) -> np.ndarray:
        """Derivative of ``contribution`` with respect to ``theta`` at the epochs ``rows`` (None: all): (N, 3,
        k). Finite differences by default."""
        theta = np.asarray(theta, float)
        step = FD_STEP * np.maximum(np.abs(theta), 1.0)
        plus = theta + np.diag(step)
        minus = theta - np.diag(step)
        diff = self.contribution(plus, data, rows=rows) - self.contribution(minus, data, rows=rows)  # (k, N, 3)
        return np.moveaxis(diff / (2 * step)[:, None, None], 0, -1)

    def regressors(self, data: EpochData, rows=None) -> np.ndarray:
        """What the diagnostics test for this effect at the epochs ``rows`` (None: all N): (N, 3, q) columns
        the residual would follow.

        By default the Jacobian at the prior mean (exact for an effect linear in its parameters); an
        effect whose Jacobian cannot be told apart from the core offset (a slow drift) overrides it.
        """
        return self.jacobian(self.prior()[0], data, rows=rows)

    def increments(self) -> np.ndarray | None:
        """For an effect that ``wanders``: the matrix (m, q) taking ``regressors``' coefficients to the
        wander's increments between knots, whose smallness is the random walk's prior (a held-out stretch
        is then predicted by interpolating its neighbours). None otherwise."""
        return None

    def accepts_simulation(self, theta) -> bool:
        """True when ``simulate`` takes ``theta`` (its length is one of ``simulation_sizes``, else ``size``)."""
        return len(theta) in (self.simulation_sizes or (self.size,))

    def simulate(self, theta, data: EpochData, rng: np.random.Generator) -> np.ndarray:
        """Raw-field contribution (N, 3) nT the simulator adds for true parameters ``theta``."""
        return self.contribution(np.asarray(theta, float), data)

    def settings(self) -> dict:
        """The constructor arguments that rebuild this effect (stored in calibration files): the public
        attributes named like ``__init__``'s parameters, ``column`` for the first column."""
        import inspect

        out = {}
        for name in inspect.signature(type(self).__init__).parameters:
            if name == "column" and self.columns:
                out[name] = self.columns[0]
            elif name != "self" and hasattr(self, name):
                out[name] = getattr(self, name)
        return out

    def describe(self) -> dict:
        return {"name": self.label, "parameters": list(self.parameter_names), "columns": list(self.columns)}

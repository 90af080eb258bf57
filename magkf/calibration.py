"""The calibration value ``m = R B_b + b`` and its versioned JSON file.

A calibration file is one JSON object. The data contract requires ``R`` (3x3, row-major) and ``b``
(3 values, nT); magkf adds ``format``, ``version``, ``method``, and optionally ``covariance`` (12x12 over
``R`` row-major then ``b``), ``parameters``, ``standard_errors``, ``quality`` and ``source``.

Version 2 adds the physical effects estimated with the core: ``effects``, a list of objects
``{"effect": "NAME[:COLUMN]", "settings": {...}, "parameters": {NAME: {"value", "std", "unit"}}}`` in state
order, and ``state_covariance``, the covariance over the core and then every effect's parameters, and optionally
``field_unit`` (absent: nT) and ``model`` (the model family the data determined). Every
command that uses a calibration restores them (``magkf.effects.restore_effects``). Version 1 files are read
as they are (their effects, under ``parameters.effects``, are kept there for information only).
Files are written with Python's shortest round-trip float representation, so reading a written file
gives back the same numbers bit for bit.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from .conventions import calibrated_field
from .errors import InputError

__all__ = ["FORMAT", "VERSION", "PARAMETER_NAMES", "StoredEffect", "Calibration", "jsonable"]

FORMAT = "magkf-calibration"
VERSION = 2
#: What a calibration's field may be measured in: nT, or no physical unit (a fit to the unit sphere, or to
#: the sensor's counts without a field magnitude to scale to).
FIELD_UNITS = ("nT", "unit-sphere", "counts")
#: Names of the 12 core parameters in state order: R row-major, then b.
PARAMETER_NAMES = tuple(f"R{i}{j}" for i in range(1, 4) for j in range(1, 4)) + ("b_x", "b_y", "b_z")


def _schema() -> dict:
    """The JSON Schema (``magkf.schema``) of a calibration file: every key of the data contract, of its type;
    any other key is refused. ``parameters``, ``standard_errors``, ``quality`` and ``model`` are the method's
    records, objects kept as they are; ``magnetometer`` is the log reader's record, whose keys that ``export``
    reads are checked (a reader's own others are kept)."""
    from .schema import BOOLEAN, INTEGER, NUMBER, OBJECT, STRING, nullable, numbers, strict

    def index(least: int, most: int | None = None) -> dict:
        return nullable(INTEGER | {"minimum": least} | ({} if most is None else {"maximum": most}))

    magnetometer = {
        "type": "object",
        "properties": {
            "format": nullable(STRING),
            "instance": index(0),
            "calibration_index": index(0),
            "compass": index(1, 3),
            "device_id": nullable(INTEGER),
            "orientation": index(0),
            "external": {"type": ["integer", "boolean", "null"]},
            "calibrated": nullable(BOOLEAN),
            "rotation": nullable(OBJECT),
            "autopilot": nullable(STRING),
            "message": nullable(STRING),
            "topic": nullable(STRING),
        },
    }
    site = strict({"given": BOOLEAN, "lat": NUMBER, "lon": NUMBER, "alt": NUMBER, "start_utc": STRING}, ["given"])
    parameter = strict({"value": NUMBER, "std": NUMBER, "unit": STRING}, ["value"])
    array = {"type": "array"}
    wander = strict(
        {
            "effect": STRING,
            "walk": strict(
                {"value": NUMBER, "std": nullable(NUMBER), "interval_95": array, "unit": STRING, "learned": BOOLEAN},
                ["value"],
            ),
            "departure": strict({"mean": array, "rms": array, "unit": STRING}, ["rms"]),
            "span": numbers((2,)),
            "fingerprint": strict({"first": NUMBER, "last": NUMBER, "n_epochs": INTEGER, "time": array, "mag": array}),
            "path": strict({"time": array, "values": array, "std": array}, ["time", "values", "std"]),
        },
        ["walk", "departure", "path"],
    )
    effect = strict(
        {
            "effect": STRING | {"minLength": 1},
            "settings": OBJECT,
            "parameters": {"type": "object", "additionalProperties": parameter, "minProperties": 1},
            "wander": wander,
        },
        ["effect", "parameters"],
    )
    square = {"type": "array", "items": {"type": "array", "items": NUMBER}}
    records = _records()
    return strict(
        {
            "format": {"const": FORMAT},
            "version": INTEGER | {"minimum": 1},
            "method": STRING,
            "R": numbers((3, 3)),
            "b": numbers((3,)),
            "covariance": numbers((12, 12)),
            "parameters": OBJECT,
            "standard_errors": records["standard_errors"],
            "quality": records["quality"],
            "source": STRING,
            "magnetometer": magnetometer,
            "site": site,
            "effects": {"type": "array", "items": effect},
            "state_covariance": square,
            "field_unit": {"enum": list(FIELD_UNITS)},
            "model": records["model"],
        },
        ["R", "b"],
    )


#: Names of the parameters whose standard errors a calibration may hold: the core's (``calibrate``), the sine
#: fit's and the ellipsoid or ellipse fit's (``docs/data-contract.md``, named parameters).
STANDARD_ERROR_NAMES = (
    PARAMETER_NAMES
    + ("alpha_deg", "beta_deg", "gamma_deg", "phi_deg", "kx", "ky", "kz")
    + tuple(f"S0_{a}" for a in "xyz")
)


def _records() -> dict:
    """The schemas of a calibration file's records: ``standard_errors`` (strict: the known parameters' names,
    each a number or null), ``quality`` (the figures ``calibrate`` writes typed, its ``status_counts`` and
    ``residual_rms_axis_nt`` strict; other methods' figures kept) and ``model`` (strict: the keys of the data
    contract's model table and what the whole-log estimate adds)."""
    from .schema import BOOLEAN, INTEGER, NUMBER, OBJECT, STRING, nullable, numbers, strict
    from .status import STATUS_NAMES

    rms = nullable(NUMBER)
    count = INTEGER | {"minimum": 0}
    quality = {
        "type": "object",
        "properties": {
            **dict.fromkeys(("residual_rms_nt", "residual_rms_magnitude_nt", "residual_rms_all_nt", "nis_mean"), rms),
            "used_share": nullable(NUMBER | {"minimum": 0, "maximum": 1}),
            "n_epochs": count,
            "status_counts": strict(dict.fromkeys(STATUS_NAMES, count)),
            "residual_rms_axis_nt": strict(dict.fromkeys(("north", "east", "down"), rms)),
            "verdict": STRING,
            "undetermined": STRING,
        },
    }
    candidate = strict({"worst_std_nt": rms, "determined": BOOLEAN, "held_out_rms_nt": rms, "free": count})
    model = strict(
        {
            **dict.fromkeys(("family", "asked", "estimated", "held", "text", "misfit", "effects_held"), STRING),
            "held_at": nullable(STRING),
            "held_core": numbers((12,)),
            "candidates": {"type": "object", "additionalProperties": candidate},
            "std_given_held": strict(dict.fromkeys(PARAMETER_NAMES, NUMBER)),
            "wandering": OBJECT,
        }
    )
    return {
        "standard_errors": strict(dict.fromkeys(STANDARD_ERROR_NAMES, nullable(NUMBER))),
        "quality": quality,
        "model": model,
    }


@dataclass(frozen=True)
class StoredEffect:
    """A physical effect as a calibration file holds it: ``label`` (``NAME[:COLUMN]``, as ``--effect``
    takes it), the constructor ``settings`` that rebuild it (``Effect.settings``), and its parameters'
    ``names``, ``values``, ``stds`` and ``units``.

    A wandering offset (``bias_drift``) also holds ``wander`` (None for every other effect, and in files written
    before it): its learned rate ``walk`` (``value``, ``std``, ``interval_95``, nT/sqrt(s)), its ``departure``
    from ``b`` (``mean`` zero by construction, ``rms`` per axis, nT), and its smoothed ``path`` on the log it was
    learned on (``time`` (K,) UNIX s, ``values`` and ``std`` (K, 3) nT) with that log's ``span`` (first, last
    UNIX s) and ``fingerprint`` (``first``, ``last``, ``n_epochs``); see ``magkf.online.drift_path``."""

    label: str
    settings: dict
    names: tuple
    values: tuple
    stds: tuple
    units: tuple
    wander: dict | None = None

    @property
    def name(self) -> str:
        return self.label.partition(":")[0]

    def to_dict(self) -> dict:
        params = {
            n: {"value": float(v), **({"std": float(s)} if math.isfinite(s) else {}), "unit": u}  # NaN: not JSON
            for n, v, s, u in zip(self.names, self.values, self.stds, self.units)
        }
        out = {"effect": self.label, "settings": jsonable(self.settings), "parameters": params}
        if self.wander is not None:
            out["wander"] = jsonable({k: v for k, v in self.wander.items() if k != "effect"})
        return out

    @classmethod
    def from_dict(cls, data, source: str) -> StoredEffect:
        where = "key 'effects'"
        if not isinstance(data, dict) or not isinstance(data.get("effect"), str):
            raise InputError(f"{where}: each entry must be an object with an 'effect' name", source)
        settings = data.get("settings", {})
        params = data.get("parameters")
        if not isinstance(settings, dict) or not isinstance(params, dict) or not params:
            raise InputError(f"{where}: effect {data['effect']!r} needs 'settings' and 'parameters' objects", source)
        if "column" in settings and not isinstance(settings["column"], str):
            raise InputError(f"{where}: setting 'column' must be a column name (a string)", source)
        names, values, stds, units = [], [], [], []
        for name, p in params.items():
            std = p.get("std") if isinstance(p, dict) else None  # absent: unknown; null is not a number
            if not (isinstance(p, dict) and _numbers(p.get("value"), 0) and ("std" not in p or _numbers(std, 0))):
                raise InputError(f"{where}: {data['effect']}.{name} needs a numeric 'value' (and 'std')", source)
            try:
                value, std = float(p["value"]), math.nan if std is None else float(std)
            except OverflowError:  # an integer beyond the float range
                value = math.inf
            if not math.isfinite(value):
                raise InputError(f"{where}: {data['effect']}.{name} is not finite", source)
            names.append(str(name))
            values.append(value)
            stds.append(std)
            units.append(str(p.get("unit", "")))
        wander = _wander(data, source) if "wander" in data else None
        return cls(data["effect"], dict(settings), tuple(names), tuple(values), tuple(stds), tuple(units), wander)


def _wander(data: dict, source: str) -> dict:
    """The checked ``wander`` record of a calibration file's effect entry ``data`` (``StoredEffect.wander``):
    a ``walk`` value, a ``departure`` rms, a ``span`` and a ``path`` of increasing times with values and
    standard deviations of three axes at each; InputError naming ``source`` otherwise."""
    where = f"key 'effects': effect {data['effect']!r}, 'wander'"
    wander = data["wander"]
    if not isinstance(wander, dict) or not all(isinstance(wander.get(k), dict) for k in ("walk", "departure", "path")):
        raise InputError(f"{where} must be an object with 'walk', 'departure' and 'path' objects", source)
    walk, path = wander["walk"], wander["path"]
    if not (_numbers(walk.get("value"), 0) and math.isfinite(float(walk["value"])) and walk["value"] >= 0):
        raise InputError(f"{where}: 'walk' needs a 'value' (nT/sqrt(s), at least 0)", source)
    if not _numbers(wander["departure"].get("rms"), 1) or len(wander["departure"]["rms"]) != 3:
        raise InputError(f"{where}: 'departure' needs 'rms' of three axes (nT)", source)
    span = wander.get("span")
    if not (_numbers(span, 1) and len(span) == 2 and span[0] <= span[1]):
        raise InputError(f"{where}: 'span' must be [first, last] UNIX seconds", source)
    time = path.get("time")
    if not (_numbers(time, 1) and len(time) >= 1 and np.all(np.diff(np.asarray(time, float)) > 0)):
        raise InputError(f"{where}: 'path' needs increasing 'time' (UNIX s)", source)
    for key in ("values", "std"):
        value = path.get(key)
        if not (_numbers(value, 2) and np.shape(value) == (len(time), 3) and np.all(np.isfinite(value))):
            raise InputError(f"{where}: 'path' needs {key!r} of three axes at each of its {len(time)} times", source)
    return dict(wander, effect=data["effect"])


@dataclass(frozen=True)
class Calibration:
    """A magnetometer calibration: raw ``m = R @ B_b + b`` (nT), correction ``B_b = R^-1 (m - b)``.

    An immutable value: ``R``, ``b`` and the covariances are stored as read-only arrays. Saved and loaded
    as the versioned JSON calibration file of the data contract, losslessly.

    Parameters
    ----------
    R : array_like
        (3, 3), dimensionless.
    b : array_like
        (3,), nT.
    method : str, optional
        How it was obtained (``sinefit-exact``, ``ellipsoid``, ...).
    covariance : array_like or None, optional
        (12, 12) over ``R`` row-major then ``b``, or None.
    parameters : dict, optional
        Method-specific named parameters (for example ``alpha_deg``).
    standard_errors : dict, optional
        Standard errors of those named parameters.
    quality : dict, optional
        Fit statistics (``residual_rms``, ``coverage``, ...).
    source : str or None, optional
        The data the calibration was computed from.
    magnetometer : dict or None, optional
        Which of an autopilot log's magnetometers it calibrates (``DriveLog.magnetometer``: the log's
        ``format``, the ``instance`` read and what the reader knows of it, such as PX4's
        ``calibration_index`` or ArduPilot's ``parameter_set``), or None; ``magkf export`` writes that
        magnetometer's parameters by default.
    site : dict or None, optional
        The place and date the user gave for a log without GNSS (``DriveLog.site``: ``given`` True, ``lat``,
        ``lon``, ``alt``, ``start_utc``), or None when the log's own GNSS placed it.
    field_unit : str, optional
        What the field of ``b`` and of the corrected field is measured in: ``"nT"`` (a physical field, the
        default), or ``"unit-sphere"`` / ``"counts"`` for a fit that had no physical field to scale to (an
        ellipsoid without ``--field``); only a calibration in nT can be exported as autopilot parameters.
    model : dict or None, optional
        The model family the data determined (``magkf.families``): ``family`` (``offsets``, ``scale``,
        ``soft-iron`` or ``full``), ``held`` (what was held and at which calibration), ``text`` (in words), or
        None when not recorded.
    effects : tuple of StoredEffect, optional
        ``StoredEffect`` of each physical effect estimated with the core, in state order.
    state_covariance : array_like or None, optional
        (n, n) over the core then every effect's parameters, or None.
    file : str or None, optional
        The calibration file it was read from (``load``), named in the errors of its effects; never written.

    Raises
    ------
    ValueError
        ``R`` not 3x3 or ``b`` not of length 3, either not finite, ``R`` singular, or a covariance of the
        wrong shape.

    Examples
    --------
    >>> import numpy as np
    >>> cal = Calibration(R=np.eye(3), b=[100.0, -50.0, 20.0], method="example")
    >>> cal.correct([20100.0, -50.0, 45020.0])
    array([20000.,     0., 45000.])
    """

    R: np.ndarray
    b: np.ndarray
    method: str = "unspecified"
    covariance: np.ndarray | None = None
    parameters: dict = field(default_factory=dict)
    standard_errors: dict = field(default_factory=dict)
    quality: dict = field(default_factory=dict)
    source: str | None = None
    magnetometer: dict | None = None
    site: dict | None = None
    field_unit: str = "nT"
    model: dict | None = None
    effects: tuple = ()
    state_covariance: np.ndarray | None = None
    file: str | None = field(default=None, compare=False, repr=False)

    def __post_init__(self):
        R = np.array(self.R, dtype=float)
        b = np.array(self.b, dtype=float).reshape(-1)
        if R.shape != (3, 3) or b.shape != (3,):
            raise ValueError(f"R must be 3x3 and b of length 3, got {R.shape} and {b.shape}")
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(b))):
            raise ValueError("R and b must be finite")
        if abs(np.linalg.det(R)) < 1e-12 * max(1.0, np.abs(R).max() ** 3):
            raise ValueError("R is singular: the calibration cannot be inverted")
        R.setflags(write=False)
        b.setflags(write=False)
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "b", b)
        if self.covariance is not None:
            cov = np.array(self.covariance, dtype=float)
            if cov.shape != (12, 12):
                raise ValueError(f"covariance must be 12x12, got {cov.shape}")
            cov.setflags(write=False)
            object.__setattr__(self, "covariance", cov)
        effects, model = _wander_kept_with_effects(tuple(self.effects), self.model)
        object.__setattr__(self, "effects", effects)
        object.__setattr__(self, "model", model)
        if self.state_covariance is not None:
            n = 12 + sum(len(e.values) for e in self.effects)
            cov = np.array(self.state_covariance, dtype=float)
            if cov.shape != (n, n):
                raise ValueError(f"state_covariance must be {n}x{n} (the core and the effects), got {cov.shape}")
            cov.setflags(write=False)
            object.__setattr__(self, "state_covariance", cov)

    # ------------------------------------------------------------ use
    def correct(self, mag_nt) -> np.ndarray:
        """Calibrated body field ``R^-1 (m - b)`` (nT) of raw readings.

        Parameters
        ----------
        mag_nt : array_like
            Raw readings ``(N, 3)`` or ``(3,)``, nT.

        Returns
        -------
        numpy.ndarray
            The body field, nT, of the readings' shape.
        """
        return calibrated_field(self.R, self.b, mag_nt)

    def distort(self, field_body_nt) -> np.ndarray:
        """Raw reading ``R B + b`` (nT) of body-frame fields.

        Parameters
        ----------
        field_body_nt : array_like
            Body-frame fields ``(N, 3)`` or ``(3,)``, nT.

        Returns
        -------
        numpy.ndarray
            The raw readings, nT, of the fields' shape.
        """
        return np.asarray(field_body_nt, dtype=float) @ self.R.T + self.b

    @property
    def state(self) -> np.ndarray:
        """The 12 core parameters, ``R`` row-major then ``b``, shape (12,)."""
        return np.concatenate([self.R.ravel(), self.b])

    @property
    def full_state(self) -> np.ndarray:
        """The core then every stored effect's parameters, shape (12 + k,)."""
        return np.concatenate([self.state, *(np.asarray(e.values, float) for e in self.effects)])

    def without_effects(self) -> Calibration:
        """The same calibration with its core only.

        Returns
        -------
        Calibration
            Without effects and without the state covariance.
        """
        return replace(self, effects=(), state_covariance=None)

    # ------------------------------------------------------------ file
    def to_dict(self) -> dict:
        """A JSON-ready dictionary with the contract's keys.

        Returns
        -------
        dict
            ``format``, ``version``, ``method``, ``R``, ``b``, and each optional key that has a value.
        """
        out = {"format": FORMAT, "version": VERSION, "method": self.method, "R": self.R.tolist(), "b": self.b.tolist()}
        if self.covariance is not None:
            out["covariance"] = self.covariance.tolist()
        for key in ("parameters", "standard_errors", "quality"):
            value = getattr(self, key)
            if value:
                out[key] = jsonable(value)
        if self.source is not None:
            out["source"] = self.source
        if self.magnetometer is not None:
            out["magnetometer"] = jsonable(self.magnetometer)
        if self.site is not None:
            out["site"] = jsonable(self.site)
        if self.field_unit != "nT":
            out["field_unit"] = self.field_unit
        if self.model is not None:
            out["model"] = jsonable(self.model)
        if self.effects:
            out["effects"] = [e.to_dict() for e in self.effects]
        if self.state_covariance is not None:
            out["state_covariance"] = self.state_covariance.tolist()
        return out

    def save(self, path) -> None:
        """Write the calibration file ``path``, replacing it only once complete (``magkf.files``).

        Parameters
        ----------
        path : str or path-like
            The file (JSON, UTF-8); ``-``: standard output.
        """
        from .files import output_text

        output_text(path, json.dumps(self.to_dict(), indent=2) + "\n")

    @classmethod
    def from_dict(cls, data, source: str = "calibration") -> Calibration:
        """Build a calibration from a parsed JSON object.

        Parameters
        ----------
        data : dict
            The parsed JSON object (``to_dict``'s keys).
        source : str, optional
            What it was read from, named in errors.

        Returns
        -------
        Calibration
            The calibration it holds.

        Raises
        ------
        InputError
            The object is malformed (not an object, another format or a newer version, a key the data contract
            does not define (with the nearest one it does), a key of the wrong type or shape, values beyond a
            calibration's range, an effect stored twice, a built-in effect's settings or parameters that are not
            its own).
        """
        _check_format(data, source)
        from .schema import check

        check(data, _schema(), source)
        R, b, cov = _core(data, source)
        stored = _stored_fields(data, source)
        effects = _stored_effects(data, source)
        state_cov = _state_covariance(data, effects, source)
        try:
            return cls(R=R, b=b, covariance=cov, effects=effects, state_covariance=state_cov, **stored)
        except ValueError as exc:
            raise InputError(str(exc), source) from None

    @classmethod
    def load(cls, path) -> Calibration:
        """Read a calibration file.

        Parameters
        ----------
        path : str or path-like
            The calibration file (JSON, UTF-8).

        Returns
        -------
        Calibration
            The calibration it holds.

        Raises
        ------
        InputError
            The file is missing or malformed; it names the file.
        """
        name = str(path)
        return replace(cls.from_dict(read_json(path, "calibration file"), name), file=name)


def read_json(path, what: str = "file"):
    """The JSON document in ``path`` (UTF-8), or InputError naming the file: unreadable, not UTF-8, not
    JSON, nested too deeply, or holding an integer too long to read."""
    name = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise InputError(f"cannot read the {what} ({exc.strerror})", name) from None
    except UnicodeDecodeError as exc:
        raise InputError(f"not UTF-8 text (byte {exc.start + 1} of the file)", name) from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(f"not valid JSON: {exc.msg} at line {exc.lineno}, column {exc.colno}", name) from None
    except RecursionError:
        raise InputError("not a usable JSON document: nested too deeply", name) from None
    except ValueError as exc:  # an integer of more digits than Python converts
        raise InputError(f"not a usable JSON document: {' '.join(str(exc).split())}", name) from None


#: Largest element of R (a sensitivity relative to the field) and of b (nT) a calibration file may hold.
R_MAX, B_MAX_NT = 1e3, 1e8


def _check_format(data, source: str) -> None:
    """InputError naming ``source`` unless ``data`` is a JSON object of this format and a version this magkf
    reads (both optional)."""
    if not isinstance(data, dict):
        raise InputError("a calibration file must hold one JSON object", source)
    fmt = data.get("format", FORMAT)
    if fmt != FORMAT:
        raise InputError(f"key 'format' is {_shown(fmt)}, expected {FORMAT!r}", source)
    version = data.get("version", VERSION)
    if isinstance(version, bool) or not isinstance(version, int) or version < 1 or version > VERSION:
        raise InputError(f"key 'version' is {_shown(version)}; this magkf reads versions 1 to {VERSION}", source)


def _core(data: dict, source: str) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """``R`` (3, 3), ``b`` (3,) nT within ``R_MAX`` and ``B_MAX_NT``, and the checked ``covariance`` (12, 12) or
    None, of a calibration file's object; InputError naming ``source`` otherwise."""
    R = _matrix(data, "R", (3, 3), source)
    b = _matrix(data, "b", (3,), source)
    for key, value, limit in (("R", R, R_MAX), ("b", b, B_MAX_NT)):
        if np.abs(value).max() > limit:
            raise InputError(
                f"key {key!r} holds {np.abs(value).max():.3g}, beyond {limit:g}: not a calibration", source
            )
    cov = _matrix(data, "covariance", (12, 12), source) if "covariance" in data else None
    if cov is not None:
        _covariance_checked(cov, "covariance", source)
    return R, b, cov


def _stored_fields(data: dict, source: str) -> dict:
    """``parameters``, ``standard_errors``, ``quality``, ``source``, ``magnetometer``, ``site`` and ``method`` of a
    calibration file's object, as ``Calibration`` takes them; InputError naming ``source`` for a wrong type."""
    stored = {}
    for key in ("parameters", "standard_errors", "quality"):
        value = data.get(key, {})
        if not isinstance(value, dict):
            raise InputError(f"key {key!r} must be a JSON object", source)
        stored[key] = value
    if not isinstance(data.get("source", ""), str):
        raise InputError("key 'source' must be a string", source)
    for key in ("magnetometer", "site", "model"):
        if not isinstance(data.get(key, {}), dict):
            raise InputError(f"key {key!r} must be a JSON object", source)
    field_unit = data.get("field_unit", "nT")
    if field_unit not in FIELD_UNITS:
        raise InputError(f"key 'field_unit' is {_shown(field_unit)}; expected one of {', '.join(FIELD_UNITS)}", source)
    method = data.get("method", "unspecified")
    if not isinstance(method, str):
        raise InputError("key 'method' must be a string", source)
    return stored | {
        "source": data.get("source"),
        "magnetometer": data.get("magnetometer"),
        "site": data.get("site"),
        "field_unit": field_unit,
        "model": data.get("model"),
        "method": method,
    }


def _wander_kept_with_effects(effects: tuple, model: dict | None) -> tuple[tuple, dict | None]:
    """``(effects, model)`` with each wandering effect's record, as the whole-log estimate gives it in its model
    record (``model['wandering']``, label -> record; ``magkf.online.drift_path``), kept with the stored effect
    it describes (``StoredEffect.wander``) and no longer in the model record (neither is changed in place)."""
    if not model or "wandering" not in model:
        return effects, model
    records = model["wandering"]
    kept = tuple(_with_wander(e, records[e.label]) if e.label in records and e.wander is None else e for e in effects)
    return kept, {k: v for k, v in model.items() if k != "wandering"}


def _with_wander(effect: StoredEffect, record: dict) -> StoredEffect:
    """``effect`` with its wandering ``record``; a ``walk`` setting takes the rate learned, so that what is rebuilt
    from the file (a filter started from it, ``validate``'s test of the rate) walks as the log showed."""
    settings = effect.settings
    if "walk" in settings and record.get("walk", {}).get("learned"):
        settings = dict(settings, walk=float(record["walk"]["value"]))
    return replace(effect, settings=settings, wander=record)


def _stored_effects(data: dict, source: str) -> tuple[StoredEffect, ...]:
    """The ``effects`` of a calibration file's object (``StoredEffect.from_dict``), in state order; InputError
    naming ``source`` for a key that is not a list or an effect stored twice."""
    stored = data.get("effects", [])
    if not isinstance(stored, list):
        raise InputError("key 'effects' must be a list", source)
    effects = tuple(StoredEffect.from_dict(e, source) for e in stored)
    for i, effect in enumerate(effects):
        _builtin_checked(effect, i, source)
    labels = [e.label for e in effects]
    if len(set(labels)) < len(labels):
        twice = next(label for label in labels if labels.count(label) > 1)
        raise InputError(f"effect {twice!r} is stored twice", source)
    return effects


def _builtin_checked(effect: StoredEffect, i: int, source: str) -> None:
    """InputError naming ``source`` unless the ``i``-th stored ``effect``, when it is one of magkf's own, has the
    settings its schema takes, the column its label names, and its own parameters (``export`` reads them without
    rebuilding the effect); a plug-in's are checked when it is rebuilt (``magkf.effects.restore_effects``)."""
    from .plugins import EFFECTS

    column = effect.label.partition(":")[2]
    if column and effect.settings.get("column", column) != column:
        raise InputError(
            f"key 'effects[{i}]': effect {effect.label!r} has setting column {effect.settings['column']!r}; "
            "the label and the setting must name the same column",
            source,
        )
    if not EFFECTS.is_builtin(effect.name):
        return
    from .schema import check

    cls = EFFECTS[effect.name]
    check(effect.settings, cls.settings_json_schema(), source, f"effects[{i}].settings", finite=True)
    if tuple(effect.names) != tuple(cls.parameter_names):
        raise InputError(
            f"key 'effects[{i}].parameters': effect {effect.label!r} has parameters "
            f"{', '.join(cls.parameter_names)}, not {', '.join(effect.names)}",
            source,
        )


def _state_covariance(data: dict, effects: tuple, source: str) -> np.ndarray | None:
    """The checked ``state_covariance`` (n, n) over the core and the ``effects``' parameters, or None."""
    if "state_covariance" not in data:
        return None
    n = 12 + sum(len(e.values) for e in effects)
    state_cov = _matrix(data, "state_covariance", (n, n), source)
    _covariance_checked(state_cov, "state_covariance", source)
    return state_cov


def _matrix(data: dict, key: str, shape: tuple, source: str) -> np.ndarray:
    if key not in data:
        raise InputError(f"required key {key!r} is missing", source)
    if not _numbers(data[key], len(shape)):  # no booleans, text or null (numpy would take True and "1")
        raise InputError(f"key {key!r} must hold numbers, shape {shape}", source)
    try:
        value = np.array(data[key], dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"key {key!r} must hold numbers, shape {shape}", source) from None
    except OverflowError:  # an integer beyond the float range
        raise InputError(f"key {key!r} holds a non-finite number", source) from None
    if value.shape != shape:
        raise InputError(f"key {key!r} has shape {value.shape}, expected {shape}", source)
    if not np.all(np.isfinite(value)):
        raise InputError(f"key {key!r} holds a non-finite number", source)
    return value


def _shown(value) -> str:
    """A short repr of a value from a file (an integer of thousands of digits or a deep nest has none)."""
    try:
        text = repr(value)
    except (ValueError, RecursionError):
        return f"a {type(value).__name__} too large to show"
    return text if len(text) <= 60 else f"{text[:57]}..."


def _numbers(value, depth: int) -> bool:
    """Whether ``value`` is a number, or lists (or an array) of numbers nested at most ``depth`` deep."""
    if isinstance(value, np.ndarray):
        return value.ndim <= depth and value.dtype.kind in "iuf"
    if isinstance(value, (list, tuple)):
        return depth > 0 and all(_numbers(v, depth - 1) for v in value)
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)


#: Largest variance a stored covariance may hold (a standard deviation of 1e9: nT for b, far beyond any R).
COVARIANCE_MAX = 1e18


def _covariance_checked(cov: np.ndarray, key: str, source: str) -> None:
    """InputError unless ``cov`` is symmetric and positive semi-definite (to rounding) with a positive
    diagonal (every parameter uncertain: a filter cannot start from a certainty)."""
    if not np.all(np.diag(cov) > 0):
        raise InputError(f"key {key!r} has a diagonal element that is not positive", source)
    if np.diag(cov).max() > COVARIANCE_MAX:
        raise InputError(f"key {key!r} has a variance beyond {COVARIANCE_MAX:g}: not an uncertainty", source)
    scale = max(float(np.abs(cov).max()), 1e-300)
    if not np.allclose(cov, cov.T, rtol=1e-8, atol=1e-12 * scale):
        raise InputError(f"key {key!r} is not symmetric", source)
    if np.linalg.eigvalsh((cov + cov.T) / 2).min() < -1e-9 * scale:
        raise InputError(f"key {key!r} is not positive semi-definite", source)


def jsonable(value):
    """Numpy scalars and arrays turned into JSON-serialisable Python values (NaN becomes None)."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, (np.floating, float)):
        return None if not math.isfinite(float(value)) else float(value)
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value

"""Property tests of the calibration file (``Calibration.load``, ``Calibration.from_dict``).

A valid calibration saved and loaded comes back equal, bit for bit, in strict JSON. Any other file (keys
missing, booleans or strings for numbers, NaN, integers of 400 or 5000 digits, deep nesting, a covariance that
is not one, wrong shapes, Latin-1 bytes, unknown effects) is loaded as a valid calibration or refused with an
InputError naming the file; never another exception; and the file is not changed.
"""

from __future__ import annotations

import atexit
import copy
import json
import math
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import event, given, settings
from hypothesis import strategies as st

from magkf.calibration import FORMAT, STANDARD_ERROR_NAMES, VERSION, Calibration, StoredEffect
from magkf.errors import InputError

FOLDER = Path(tempfile.mkdtemp(prefix="magkf-property-"))
atexit.register(shutil.rmtree, FOLDER, ignore_errors=True)
PROPERTY = settings(max_examples=60, deadline=None, derandomize=True, database=None)

FINITE = st.floats(allow_nan=False, allow_infinity=False)
JSON_LEAF = st.one_of(st.none(), st.booleans(), st.integers(-(2**63), 2**63), FINITE, st.text(max_size=6))
JSON = st.recursive(
    JSON_LEAF,
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=4), inner, max_size=3),
    max_leaves=6,
)
LABELS = st.sampled_from(["temperature_bias:temp_c", "time_lag", "bias_drift", "no_such_effect", "mine:x"])


def covariances(n: int) -> st.SearchStrategy[np.ndarray]:
    """Symmetric positive definite n x n matrices, ``A A^T`` plus a small diagonal, scaled."""
    return st.builds(
        lambda a, scale: (a @ a.T + 1e-6 * np.eye(n)) * scale,
        st.lists(st.floats(-1, 1), min_size=n * n, max_size=n * n).map(lambda v: np.reshape(v, (n, n))),
        st.sampled_from([1e-12, 1e-4, 1.0, 1e4]),
    )


@st.composite
def stored_effects(draw) -> StoredEffect:
    """A stored effect: one of magkf's own with its own parameters and default settings (their schema is strict),
    or a plug-in's (any label, settings and names: checked when the plug-in rebuilds it)."""
    from magkf.plugins import EFFECTS

    label = draw(LABELS | st.text(min_size=1, max_size=8))
    name = label.partition(":")[0]
    if EFFECTS.is_builtin(name):
        names, settings = list(EFFECTS[name].parameter_names), {}
    else:
        k = draw(st.integers(1, 3))
        names = draw(st.lists(st.text(min_size=1, max_size=5), min_size=k, max_size=k, unique=True))
        settings = draw(st.dictionaries(st.text(max_size=5), JSON, max_size=2))
    k = len(names)
    return StoredEffect(
        label,
        settings,
        tuple(names),
        tuple(draw(st.lists(FINITE, min_size=k, max_size=k))),
        tuple(draw(st.lists(FINITE | st.just(math.nan), min_size=k, max_size=k))),  # NaN: not known
        tuple(draw(st.lists(st.text(max_size=3), min_size=k, max_size=k))),
    )


@st.composite
def calibrations(draw) -> Calibration:
    """Valid calibrations: R diagonally dominant (so invertible) at scales to 300 (elements to 1e3), b to 1e8 nT
    (the limits of the file), and some of
    covariance, parameters, standard errors, quality, source, effects and their state covariance."""
    off = np.reshape(draw(st.lists(st.floats(-0.3, 0.3), min_size=9, max_size=9)), (3, 3))
    R = (np.eye(3) * draw(st.lists(st.floats(0.7, 1.3), min_size=3, max_size=3)) + off - np.diag(np.diag(off))) * draw(
        st.sampled_from([1e-3, 1.0, 300.0])
    )
    effects = tuple(draw(st.lists(stored_effects(), max_size=2, unique_by=lambda e: e.label)))  # each once
    n = 12 + sum(len(e.values) for e in effects)
    return Calibration(
        R=R[draw(st.permutations(range(3)))],
        b=draw(st.lists(st.floats(-1e8, 1e8), min_size=3, max_size=3)),
        method=draw(st.text(max_size=8)),
        covariance=draw(st.none() | covariances(12)),
        parameters=draw(st.dictionaries(st.text(max_size=6), JSON, max_size=3)),
        standard_errors=draw(st.dictionaries(st.sampled_from(STANDARD_ERROR_NAMES), FINITE, max_size=2)),
        quality=draw(st.dictionaries(st.text(max_size=6), JSON, max_size=2)),
        source=draw(st.none() | st.text(max_size=8)),
        effects=effects,
        state_covariance=draw(st.none() | covariances(n)) if effects else None,
    )


def strict_json(text: str):
    """JSON as RFC 8259 has it: no NaN or Infinity."""

    def refuse(token):
        raise AssertionError(f"the file holds {token}, which is not JSON")

    return json.loads(text, parse_constant=refuse)


def same(a: Calibration, b: Calibration) -> None:
    for name in ("R", "b", "covariance", "state_covariance"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            np.testing.assert_array_equal(x, y, err_msg=name)
    assert json.dumps(a.to_dict()) == json.dumps(b.to_dict())


@pytest.mark.slow
@settings(PROPERTY, max_examples=60)
@given(calibrations())
def test_a_calibration_saved_and_loaded_is_the_same(cal):
    path = FOLDER / "saved.json"
    cal.save(path)
    text = path.read_text(encoding="utf-8")
    data = strict_json(text)
    assert data["format"] == FORMAT and data["version"] == VERSION
    back = Calibration.load(path)
    assert path.read_text(encoding="utf-8") == text
    same(back, cal)
    assert back.method == cal.method and back.source == cal.source and back.parameters == cal.parameters
    same(Calibration.from_dict(data, "data"), cal)


# ---------------------------------------------------------------- damaged files
class Raw:
    """JSON text written as it is (an integer too long for ``str(int)``, a deep nest) and its Python value."""

    def __init__(self, text: str, value):
        self.text, self.value = text, value

    def __repr__(self):
        return f"Raw({self.text[:12]!r}... {len(self.text)} characters)"


def nest(depth: int) -> list:
    value = [1]
    for _ in range(depth - 1):
        value = [value]
    return value


HUGE = (Raw("1" + "0" * 5000, 10**5000), Raw("-" + "9" * 400, -(10**400 - 1)), Raw("9" * 400, 10**400 - 1))
DEEP = tuple(Raw("[" * depth + "1" + "]" * depth, nest(depth)) for depth in (50, 2_000, 100_000))
BAD_NUMBERS = st.one_of(
    st.sampled_from([True, False, None, "1", "1.5", "", "x", math.nan, math.inf, -math.inf, 1e308, [], {}, *HUGE]),
    st.integers(-(2**70), 2**70),
    FINITE,
)
KEYS = ("format", "version", "method", "R", "b", "covariance", "parameters", "standard_errors", "quality", "source")
KEYS += ("effects", "state_covariance")


def leaves(value, path=()):
    """(path, leaf) of every number, text, boolean or null in a nest of lists, dicts and arrays."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, list):
        for k, v in enumerate(value):
            yield from leaves(v, (*path, k))
    elif isinstance(value, dict):
        for k, v in value.items():
            yield from leaves(v, (*path, k))
    else:
        yield path, value


def replace_at(value, path, new):
    if not path:
        return new
    value[path[0]] = replace_at(value[path[0]], path[1:], new)
    return value


@st.composite
def damaged(draw, cal: Calibration):
    """The JSON object of ``cal`` damaged up to three times: a key deleted or set to anything; one number of
    a matrix or of an effect made a boolean, a string, NaN, a 400- or 5000-digit integer; a shape changed;
    a covariance made non-symmetric or indefinite; the effects made strange."""
    data = copy.deepcopy(cal.to_dict())
    for _ in range(draw(st.integers(0, 3))):
        kind = draw(st.sampled_from(["delete", "set", "leaf", "leaf", "shape", "covariance", "effect", "version"]))
        key = draw(st.sampled_from(KEYS))
        if kind == "delete" and key in data:
            del data[key]
        elif kind == "set":
            data[key] = draw(BAD_NUMBERS | JSON | st.sampled_from(DEEP))
        elif kind == "leaf":
            top = draw(st.sampled_from(["R", "b", "covariance", "effects"]))
            found = [p for p, v in leaves(data.get(top)) if isinstance(v, float)]
            if found:
                data[top] = replace_at(
                    data[top], draw(st.sampled_from(found)), draw(BAD_NUMBERS | st.sampled_from(DEEP))
                )
        elif kind == "shape" and isinstance(data.get(key), list) and data[key]:
            data[key] = draw(st.sampled_from([data[key][:-1], [*data[key], data[key][0]], [data[key]], data[key][0]]))
        elif kind == "covariance":
            n = 12 if key != "state_covariance" else 12 + sum(len(e.values) for e in cal.effects)
            c = np.eye(n)
            c[draw(st.integers(0, n - 1)), draw(st.integers(0, n - 1))] = draw(st.sampled_from([-1.0, 2.0, 5.0]))
            data["covariance" if key != "state_covariance" else key] = c.tolist()
        elif kind == "effect":
            entry = draw(
                st.fixed_dictionaries(
                    {},
                    optional={
                        "effect": LABELS | JSON,
                        "settings": st.dictionaries(st.text(max_size=3), JSON, max_size=2) | JSON,
                        "parameters": st.dictionaries(
                            st.text(max_size=3),
                            st.fixed_dictionaries({}, optional={"value": BAD_NUMBERS, "std": BAD_NUMBERS, "unit": JSON})
                            | JSON,
                            max_size=2,
                        ),
                    },
                )
            )
            data.setdefault("effects", [])
            if isinstance(data["effects"], list):
                data["effects"].append(entry)
        elif kind == "version":
            data["version"] = draw(st.sampled_from([0, 1, 2, 3, True, "2", 1.0, None, *HUGE]))
    return data


def dumps(data) -> str:
    """JSON text of ``data`` (NaN and Infinity as Python writes them), ``Raw`` values written verbatim."""
    raws = []

    def mark(value):
        if isinstance(value, Raw):
            raws.append(value.text)
            return f"@@raw{len(raws) - 1}@@"
        raise TypeError(type(value))

    text = json.dumps(data, default=mark)
    for k, raw in enumerate(raws):
        text = text.replace(f'"@@raw{k}@@"', raw)
    return text


def check_valid(cal: Calibration, data) -> None:
    """What a loaded calibration must be: R invertible and b finite; a covariance symmetric and positive
    semi-definite; numbers in the file that were numbers (not booleans or strings); names and texts as text."""
    assert cal.R.shape == (3, 3) and cal.b.shape == (3,)
    assert np.all(np.isfinite(cal.R)) and np.all(np.isfinite(cal.b)) and abs(np.linalg.det(cal.R)) > 0
    for c in (cal.covariance, cal.state_covariance):
        if c is not None:
            assert np.all(np.isfinite(c)) and np.allclose(c, c.T, rtol=1e-8, atol=0), "a covariance not symmetric"
            eigen = np.linalg.eigvalsh((c + c.T) / 2)
            assert eigen.min() >= -1e-8 * max(abs(eigen).max(), 1e-300), f"a covariance not positive: {eigen.min()}"
    assert isinstance(cal.method, str) and (cal.source is None or isinstance(cal.source, str))
    if isinstance(data, dict):
        assert type(data.get("version", VERSION)) is int, "the version is not an integer"
        for key in ("R", "b", "covariance", "state_covariance"):
            for _, v in leaves(data.get(key, [])):
                assert type(v) in (int, float), f"{key} holds {v!r}, not a number"
        for stored, entry in zip(cal.effects, data.get("effects", [])):
            assert isinstance(stored.label, str) and all(isinstance(n, str) for n in stored.names)
            assert all(math.isfinite(v) for v in stored.values)
            for p in entry["parameters"].values():
                for key in ("value", "std"):
                    assert key not in p or type(p[key]) in (int, float), f"an effect's {key} is {p[key]!r}"


def loaded(text: bytes):
    path = FOLDER / "calibration.json"
    path.write_bytes(text)
    try:
        result = Calibration.load(path)
    except InputError as exc:
        result = exc
    assert path.read_bytes() == text, "load changed the file"
    return result, str(path)


@pytest.mark.slow
@settings(PROPERTY, max_examples=150)
@given(st.data())
def test_a_damaged_calibration_file_is_loaded_validly_or_refused_naming_it(data):
    cal = data.draw(calibrations())
    obj = data.draw(damaged(cal))
    text = dumps(obj).encode("utf-8")
    if data.draw(st.integers(0, 5)) == 0:  # Latin-1 text, a byte-order mark or a few odd bytes
        k = data.draw(st.integers(0, len(text)))
        text = (
            text[:k] + data.draw(st.sampled_from([b"\xe9", b"\xb5T", b"\xef\xbb\xbf", b"\x00", b"\xff\xfe"])) + text[k:]
        )
    result, path = loaded(text)
    event("refused" if isinstance(result, InputError) else "loaded")
    try:  # the object in the file, as load is to read it (UTF-8)
        parsed = json.loads(text.decode("utf-8"))
    except (ValueError, RecursionError):
        parsed = None
    if isinstance(result, InputError):
        message = str(result)
        assert result.source == path and message.startswith(path) and "\n" not in message, message
        if parsed is not None:  # the same object given directly is refused too, naming what it was told
            try:
                Calibration.from_dict(parsed, "given")
            except InputError as exc:
                assert exc.source == "given" and str(exc).startswith("given: ")
            else:
                raise AssertionError(f"from_dict accepts what load refuses: {message}")
        return
    check_valid(result, parsed)
    check_valid(Calibration.from_dict(parsed, "given"), parsed)
    # what was accepted is saved and read again unchanged (a second save gives the same text)
    first, second = FOLDER / "again.json", FOLDER / "again2.json"
    result.save(first)
    strict_json(first.read_text(encoding="utf-8"))
    again = Calibration.load(first)
    again.save(second)
    assert second.read_text(encoding="utf-8") == first.read_text(encoding="utf-8")
    same(again, result)


def array(value):
    """``value`` as a numpy array where numpy makes one."""
    try:
        return np.asarray(value)
    except (ValueError, TypeError, OverflowError, RecursionError):
        return value


def python(value):
    """``value`` with every Raw replaced by its Python value."""
    if isinstance(value, Raw):
        return value.value
    if isinstance(value, list):
        return [python(v) for v in value]
    if isinstance(value, dict):
        return {k: python(v) for k, v in value.items()}
    return value


@settings(PROPERTY, max_examples=80)
@given(st.data())
def test_from_dict_of_any_object_gives_a_valid_calibration_or_an_input_error(data):
    """Objects no JSON text gives too: 10**5000, nests 100 000 deep, numpy arrays."""
    obj = python(data.draw(damaged(data.draw(calibrations())) | BAD_NUMBERS | JSON))
    if isinstance(obj, dict) and data.draw(st.booleans()):
        obj = {k: array(v) if k in ("R", "b") and data.draw(st.booleans()) else v for k, v in obj.items()}
    source = data.draw(st.sampled_from(["given", "R.json"]))
    try:
        cal = Calibration.from_dict(obj, source)
    except InputError as exc:
        assert exc.source == source and str(exc).startswith(f"{source}: ") and "\n" not in str(exc)
        return
    check_valid(cal, obj)

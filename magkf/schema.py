"""Validation of magkf's input documents (calibration files, study specs, effect settings) by JSON Schema.

Every document magkf reads that is not a table has a schema (JSON Schema, Draft 2020-12), declared beside what
reads it: the calibration file in ``magkf.calibration``, the study spec in ``magkf.study``, each effect's
settings by its class (``Effect.settings_schema``). Objects are strict: a key the schema does not list is
refused (``additionalProperties: false``), naming the nearest known key, so that a misspelt key never passes
silently as one left out. ``check`` validates a document and turns the first error into one ``InputError`` line
that names the file, the key's path, what is wrong and what would be right::

    study.toml: unknown key 'study.replicate' (did you mean 'replicates'?)
    cal.json: key 'effects[0].settings.T0' must be a number, not 'abc'

The validation itself is the ``jsonschema`` package's (a maintained implementation of the standard, whose
errors carry the path and the rule that failed); the schemas are plain dictionaries, so that a plug-in declares
its own in the same terms. The helpers below build the common pieces.
"""

from __future__ import annotations

import difflib
import math

from .errors import InputError

__all__ = ["check", "strict", "NUMBER", "INTEGER", "STRING", "BOOLEAN", "OBJECT", "numbers", "nullable", "key_path"]

#: JSON Schema of a number (booleans are not numbers in JSON Schema).
NUMBER = {"type": "number"}
#: A whole number (1.0 counts, 1.7 does not).
INTEGER = {"type": "integer"}
STRING = {"type": "string"}
BOOLEAN = {"type": "boolean"}
#: An object whose keys are not checked (a record kept for information).
OBJECT = {"type": "object"}

#: What each JSON type is called in messages.
TYPE_WORDS = {
    "number": "a number",
    "integer": "a whole number",
    "string": "a string",
    "boolean": "true or false",
    "array": "a list",
    "object": "an object",
    "null": "null",
}


def strict(properties: dict, required=(), **more) -> dict:
    """The schema of an object with exactly the keys ``properties`` (name -> schema), ``required`` among them."""
    return {
        "type": "object",
        "properties": properties,
        "required": list(required),
        "additionalProperties": False,
    } | more


def nullable(schema: dict) -> dict:
    """``schema`` (of one JSON type), or null; its other rules (a minimum) apply to a value of that type."""
    return schema | {"type": [schema["type"], "null"]}


def numbers(shape: tuple) -> dict:
    """The schema of nested lists of numbers of ``shape`` (``()``: one number; ``(3, 3)``: 3 lists of 3)."""
    return _nested(shape) | {"x-shape": list(shape)}


def _nested(shape: tuple) -> dict:
    if not shape:
        return NUMBER
    return {"type": "array", "items": _nested(shape[1:]), "minItems": shape[0], "maxItems": shape[0]}


def key_path(path) -> str:
    """The path of a key as messages give it: ``effects[0].settings.T0`` (an index in brackets)."""
    out = ""
    for part in path:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out


def check(document, schema: dict, source: str | None, root: str = "", finite: bool = False) -> None:
    """Validate ``document`` against ``schema``; InputError naming ``source`` (the file) for the first error.

    Parameters
    ----------
    document : object
        The parsed JSON or TOML document (or a part of one).
    schema : dict
        Its JSON Schema (Draft 2020-12).
    source : str or None
        The file, named in the error.
    root : str, optional
        The path of ``document`` within its file (``effects[0].settings``), prefixed to every key named.
    finite : bool, optional
        Refuse numbers that are not finite too (JSON's ``NaN``, ``Infinity``), which JSON Schema takes as numbers.

    Raises
    ------
    InputError
        One line: the key's path, what is wrong and, for an unknown key, the nearest known one.
    """
    from jsonschema import Draft202012Validator
    from jsonschema.exceptions import best_match

    if _depth(document) > MAX_DEPTH:  # the validator recurses into every level
        raise InputError(
            f"{key_path([root]) if root else 'the file'} nests lists or tables more than {MAX_DEPTH} deep", source
        )
    error = best_match(Draft202012Validator(schema).iter_errors(document), key=_relevance)
    if error is not None:
        prefix = [root] if root else []
        shaped = _shaped(schema, list(error.absolute_path))
        if shaped is not None:  # an array of numbers: its shape named, whichever element is wrong
            raise InputError(_shape_message(error, prefix, *shaped), source)
        raise InputError(_message(error, prefix + list(error.absolute_path)), source)
    if finite:
        _check_finite(document, [root] if root else [], source)


#: Deepest nesting of lists and tables a document may have (magkf's own files nest four deep at most).
MAX_DEPTH = 32


def _depth(document) -> int:
    """How deep lists and tables nest in ``document`` (0 for a number or a string), found without recursion."""
    deepest, stack = 0, [(document, 0)]
    while stack:
        value, level = stack.pop()
        deepest = max(deepest, level)
        if level > MAX_DEPTH:
            break
        if isinstance(value, dict):
            stack.extend((item, level + 1) for item in value.values())
        elif isinstance(value, (list, tuple)):
            stack.extend((item, level + 1) for item in value)
    return deepest


def _check_finite(value, path: list, source: str | None) -> None:
    """InputError naming ``source`` and the key for the first number in ``value`` that is not finite."""
    if isinstance(value, dict):
        for key, item in value.items():
            _check_finite(item, [*path, key], source)
    elif isinstance(value, list):
        for i, item in enumerate(value):
            _check_finite(item, [*path, i], source)
    elif isinstance(value, float) and not math.isfinite(value):
        raise InputError(f"key {key_path(path)!r} must be a finite number, not {value!r}", source)


def _shaped(schema: dict, path: list) -> tuple[int, list] | None:
    """``(depth, shape)`` of the first schema along ``path`` (keys and indices) that is an array of numbers of a
    shape (``numbers``), or None."""
    for depth in range(len(path) + 1):
        if "x-shape" in schema:
            return depth, schema["x-shape"]
        if depth == len(path):
            return None
        part = path[depth]
        if isinstance(part, int):
            schema = schema.get("items", {})
        else:
            schema = schema.get("properties", {}).get(part, schema.get("additionalProperties", {}))
        if not isinstance(schema, dict):
            return None
    return None


def _shape_message(error, prefix: list, depth: int, shape: list) -> str:
    """The message for an ``error`` within an array of numbers of ``shape`` that lies ``depth`` keys down the
    error's path (below ``prefix``, the document's own path in its file)."""
    path = list(error.absolute_path)
    found = f"{len(error.instance)} items" if error.validator in ("minItems", "maxItems") else _shown(error.instance)
    whole = key_path(prefix + path[:depth])
    return f"key {whole!r} must hold numbers, shape {tuple(shape)}; {key_path(prefix + path)} holds {found}"


def _relevance(error):
    """The error to report is the shallowest (an unknown key before what is wrong inside the objects it holds),
    then the most relevant by jsonschema's own order."""
    from jsonschema.exceptions import relevance

    return (-len(error.absolute_path), relevance(error))


def _message(error, path: list) -> str:
    """One line for the jsonschema ``error`` at the key ``path``."""
    where = key_path(path)
    rule, value, expected = error.validator, error.instance, error.validator_value
    if rule == "additionalProperties":
        return _unknown_key(value, error.schema, where)
    if rule == "required":
        missing = next(k for k in expected if k not in value)
        needs = [repr(k) for k in expected]
        listed = f" ({key_path(path) or 'the document'} needs {', '.join(needs[:-1])} and {needs[-1]})"
        return f"required key {key_path([*path, missing])!r} is missing{listed if len(needs) > 1 else ''}"
    subject = f"key {where!r}" if where else "the document"
    if rule == "type":
        return f"{subject} must be {_type_words(expected)}, not {_shown(value)}"
    if rule in ("anyOf", "oneOf"):
        return f"{subject} must be {_alternatives(error.schema[rule])}, not {_shown(value)}"
    if rule in ("enum", "const"):
        choices = expected if rule == "enum" else [expected]
        return f"{subject} is {_shown(value)}; expected {' or '.join(_shown(c) for c in choices)}"
    if rule in ("minimum", "exclusiveMinimum", "maximum", "exclusiveMaximum"):
        bound = {"minimum": "at least", "exclusiveMinimum": "above", "maximum": "at most"}.get(rule, "below")
        return f"{subject} must be {bound} {expected:g}, not {_shown(value)}"
    if rule in ("minItems", "maxItems", "minProperties", "maxProperties"):
        return _count_message(subject, rule, error.schema, value)
    if rule == "minLength":
        return f"{subject} must not be empty"
    return f"{subject}: {' '.join(error.message.split())}"


def _count_message(subject: str, rule: str, schema: dict, value) -> str:
    """The message for a list or an object of too few or too many items (keys)."""
    kind = "Items" if rule.endswith("Items") else "Properties"
    low, high = schema.get(f"min{kind}"), schema.get(f"max{kind}")
    what = "item" if kind == "Items" else "key"
    if low == high:
        count = f"exactly {low}"
    else:
        count = f"at least {low}" if rule.startswith("min") else f"at most {high}"
    number = int(count.split()[-1])
    keys = f" (of {', '.join(schema['properties'])})" if kind == "Properties" and schema.get("properties") else ""
    return f"{subject} must hold {count} {what}{'s' if number != 1 else ''}{keys}, not {len(value)}"


def _unknown_key(value: dict, schema: dict, where: str) -> str:
    """The message for the first key of ``value`` that ``schema`` does not list, with the nearest known one."""
    known = list(schema.get("properties", {}))
    unknown = next(k for k in value if k not in known)
    near = difflib.get_close_matches(str(unknown), known, n=1, cutoff=0.6)
    full = key_path([where, unknown] if where else [unknown])
    if near:
        return f"unknown key {full!r} (did you mean {near[0]!r}?)"
    return f"unknown key {full!r} (known: {', '.join(known) or 'none'})"


def _type_words(expected) -> str:
    types = [expected] if isinstance(expected, str) else list(expected)
    return " or ".join(TYPE_WORDS.get(t, t) for t in types)


def _alternatives(schemas: list) -> str:
    """The alternatives of an ``anyOf`` in words (their types)."""
    words = []
    for schema in schemas:
        text = _type_words(schema["type"]) if "type" in schema else "another value"
        if "minimum" in schema:
            text += f" of at least {schema['minimum']:g}"
        words.append(text)
    return " or ".join(dict.fromkeys(words))


def _shown(value) -> str:
    """A short repr of a value from a file (an integer of thousands of digits or a deep nest has none)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, dict):
        return "an object"
    if isinstance(value, list):
        return "a list"
    try:
        text = repr(value)
    except (ValueError, RecursionError):
        return f"a {type(value).__name__} too large to show"
    return text if len(text) <= 40 else f"{text[:37]}..."

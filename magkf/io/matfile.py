"""A numeric array of a MATLAB ``.mat`` file as a table: one record per row, one channel per column.

Published calibration sets often ship as MATLAB files holding one matrix, ``[t, x, y, z]`` per sample. A
MATLAB v7.3 file is HDF5 (with a 512-byte MATLAB header first) and is read with h5py; MATLAB stores arrays
column-major, so the HDF5 dataset of an N x 4 MATLAB matrix has shape (4, N). A v4, v5 or v7 file (not HDF5)
is read with ``scipy.io.loadmat``. Neither orientation is assumed: the records lie along the longer dimension
(a calibration set has more samples than channels), and a square array is refused.

Versions are told by ``scipy.io.matlab.matfile_version`` (the header's version field: 0 for v4, 1 for v5 and
v7, 2 for v7.3; https://www.mathworks.com/help/matlab/import_export/mat-file-versions.html).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError

__all__ = ["MatArray", "read_mat_array"]

#: HDF5 objects of a v7.3 file that MATLAB writes for itself, not variables.
_INTERNAL = ("#refs#", "#subsystem#")
#: What to do with a file magkf cannot read as MATLAB numbers.
_HINT = "save it in MATLAB with save(..., '-v7.3') or export the matrix as CSV"


@dataclass(frozen=True)
class MatArray:
    """The records of one numeric MATLAB variable.

    Attributes
    ----------
    values : numpy.ndarray
        (N, k) floats: N records (the longer dimension of the stored array), k channels; NaN is kept.
    variable : str
        The variable's name (``a.b`` for the field ``b`` of a struct ``a``).
    stored_shape : tuple of int
        The array's shape as stored (HDF5's for v7.3, MATLAB's for older files).
    version : str
        ``"v7.3 (HDF5)"``, or ``"v5"`` / ``"v4"`` (v7 files are v5 files with compression).
    """

    values: np.ndarray
    variable: str
    stored_shape: tuple
    version: str

    def description(self) -> str:
        """Where the records came from, in words."""
        n, k = self.values.shape
        along = "rows" if self.stored_shape[0] == n else "columns"
        return (
            f"MATLAB {self.version} variable {self.variable!r}, stored {' x '.join(map(str, self.stored_shape))}: "
            f"{n} records (its {along}) of {k} channel{'s' if k > 1 else ''}"
        )


def read_mat_array(path, variable: str | None = None) -> MatArray:
    """The numeric matrix ``variable`` of the MATLAB file ``path``, records as rows.

    Parameters
    ----------
    path : str or Path
        A ``.mat`` file (v7.3/HDF5 through h5py; v4, v5, v7 through ``scipy.io.loadmat``).
    variable : str, optional
        The variable (``a.b`` for a struct's field). By default the file's only real numeric matrix of at least
        two rows and two columns (scalars and vectors saved beside it are passed over).

    Returns
    -------
    MatArray
        (N, k) float values, N the longer of the two dimensions.

    Raises
    ------
    InputError
        One line naming the file (and the variable) for a file that is not a MATLAB file, a variable that is
        missing, not numeric, complex, of more than two dimensions or square, or none chosen among several.
    """
    path = Path(path)
    name = str(path)
    if not path.is_file():
        raise InputError("no such file", name)
    version = _version(path, name)
    if version == "v7.3 (HDF5)":
        variables = _hdf5_variables(path, name, variable)
    else:
        if version == "v5":
            _check_v5_elements(path.read_bytes(), name)
        variables = _loadmat_variables(path, name)
    chosen = _choose(variables, variable, name)
    stored = variables[chosen]
    return MatArray(_records(stored, name, chosen), chosen, tuple(np.shape(stored)), version)


def _version(path: Path, name: str) -> str:
    """``"v7.3 (HDF5)"`` (any HDF5 file: MATLAB's, or one written without MATLAB's header, by h5py say),
    ``"v5"`` or ``"v4"``; InputError naming ``name`` for any other file."""
    import h5py
    from scipy.io.matlab import MatReadError, matfile_version

    if h5py.is_hdf5(path):
        return "v7.3 (HDF5)"
    try:
        major, _ = matfile_version(str(path))
    except (MatReadError, ValueError, OSError, TypeError, IndexError) as exc:  # too short, not a MATLAB header
        raise InputError(f"not a MATLAB .mat file ({' '.join(str(exc).split())}): {_HINT}", name) from None
    if major == 2:  # MATLAB's header says v7.3, but h5py finds no HDF5 after it
        raise InputError(f"a MATLAB v7.3 file whose HDF5 part is damaged: {_HINT}", name)
    return "v5" if major == 1 else "v4"


def _hdf5_variables(path: Path, name: str, variable: str | None) -> dict:
    """Every dataset of a v7.3 file by its MATLAB name (``a.b`` for the field ``b`` of struct ``a``); a
    variable MATLAB marks as text, a cell, sparse, empty or complex is held as a string saying so, and only
    ``variable`` (or, when None, every candidate) is read."""
    import h5py

    found: dict = {}
    try:
        with h5py.File(path, "r") as f:

            def visit(key, item):
                if any(part in _INTERNAL for part in key.split("/")):
                    return
                matlab_name = key.replace("/", ".")
                if isinstance(item, h5py.Dataset) and variable in (None, matlab_name):
                    found[matlab_name] = _hdf5_dataset(item)
                elif isinstance(item, h5py.Dataset):
                    found[matlab_name] = "not read"
                elif "MATLAB_sparse" in item.attrs:
                    found[key.replace("/", ".")] = "a sparse matrix"

            f.visititems(visit)
    except Exception as exc:  # a damaged HDF5 file: h5py raises OSError, RuntimeError, KeyError, ValueError...
        raise InputError(f"not a readable MATLAB v7.3 (HDF5) file ({_reason(exc)}): {_HINT}", name) from None
    return found


def _hdf5_dataset(item):
    """The values of one HDF5 dataset, or a string saying why they are not a numeric matrix."""
    kind = item.attrs.get("MATLAB_class", b"")
    kind = kind.decode() if isinstance(kind, bytes) else str(kind)
    if "MATLAB_empty" in item.attrs:
        return "an empty array"
    if kind in ("char", "cell", "struct", "function_handle") or item.dtype.kind in "OSUV":
        return f"a MATLAB {kind or item.dtype.name} array, not numbers"
    if item.dtype.names is not None:  # MATLAB's complex numbers: a compound of real and imag
        return "a complex array"
    return item[()]


#: MAT v5 data types (``miINT8`` 1 ... ``miUTF32`` 18; 8, 10 and 11 are reserved), of the MAT-file format
#: (https://www.mathworks.com/help/pdf_doc/matlab/matfile_format.pdf, "Data Element Types").
_V5_TYPES = frozenset({1, 2, 3, 4, 5, 6, 7, 9, 12, 13, 14, 16, 17, 18})
_MI_MATRIX, _MI_COMPRESSED = 14, 15
_V5_HEADER_BYTES = 128


#: MATLAB classes (the low byte of a matrix's flags) whose matrix holds exactly these parts besides the
#: optional imaginary one: flags, dimensions, name and data (char and numeric classes, 4 and 6 to 15), and
#: sparse (5) with its row and column indices.
_V5_PARTS = {4: 4, 5: 6, **{klass: 4 for klass in range(6, 16)}}
_MI_INT32, _MI_UINT32 = 5, 6
_COMPLEX_FLAG = 0x800


@dataclass(frozen=True)
class _Tag:
    """One MAT v5 data element: its type, where its data start, its size in bytes and where its tag is."""

    kind: int
    body: int
    size: int
    at: int


class _V5Elements:
    """The data elements of a MAT v5 file (``https://www.mathworks.com/help/pdf_doc/matlab/matfile_format.pdf``),
    walked to refuse what ``scipy.io.loadmat`` cannot read safely: it takes a tag's type as an index into a table
    without checking it, and reads a complex matrix's imaginary part whether it is there or not, so that a damaged
    file can crash the process (scipy/scipy#25349)."""

    def __init__(self, name: str, order: str):
        self.name, self.order = name, order

    def refuse(self, what: str, at: int):
        raise InputError(f"not a readable MATLAB v5 file ({what} at byte {at}): {_HINT}", self.name)

    def tags(self, data: bytes, start: int, end: int, nested: bool) -> list[_Tag]:
        """The elements in ``data[start:end]`` (``nested``: a matrix's parts, each padded to 8 bytes; else the
        file's top level, where compressed elements may be), each of a known type and within its container."""
        import struct

        found, at = [], start
        while at < end:
            if end - at < 8:
                self.refuse("a data element cut short", at)
            first, second = struct.unpack_from(self.order + "II", data, at)
            small = first >> 16 != 0  # a small data element: type and size in one word, data in the next
            kind, size = (first & 0xFFFF, first >> 16) if small else (first, second)
            step = 8 if small else 8 + (-(-size // 8) * 8 if nested else size)
            known = kind in _V5_TYPES or (kind == _MI_COMPRESSED and not nested)
            if not known or (small and size > 4) or at + step > end:
                self.refuse("a damaged data element", at)
            found.append(_Tag(kind, at + (4 if small else 8), size, at))
            at += step
        return found

    def check(self, data: bytes, start: int, end: int) -> None:
        """Check the top-level elements of ``data[start:end]`` and every matrix in them."""
        import zlib

        for tag in self.tags(data, start, end, nested=False):
            if tag.kind == _MI_MATRIX:
                self.matrix(data, tag)
            elif tag.kind == _MI_COMPRESSED:
                try:
                    inner = zlib.decompress(data[tag.body : tag.body + tag.size])
                except zlib.error:
                    self.refuse("a damaged compressed element", tag.at)
                self.check(inner, 0, len(inner))

    def matrix(self, data: bytes, tag: _Tag) -> None:
        """Check one matrix: flags and dimensions first, the parts its class has, and the matrices in it."""
        import struct

        parts = self.tags(data, tag.body, tag.body + tag.size, nested=True)
        if tag.size == 0:
            return  # an empty element, which MATLAB writes for an empty cell
        if len(parts) < 3 or (parts[0].kind, parts[0].size, parts[1].kind) != (_MI_UINT32, 8, _MI_INT32):
            self.refuse("a matrix without its flags and dimensions", tag.at)
        (flags,) = struct.unpack_from(self.order + "I", data, parts[0].body)
        expected = _V5_PARTS.get(flags & 0xFF)
        if expected is not None:
            expected += bool(flags & _COMPLEX_FLAG)
            if len(parts) != expected or any(p.kind == _MI_MATRIX for p in parts):
                self.refuse("a matrix whose parts do not match its class", tag.at)
        for part in parts[3:]:
            if part.kind == _MI_MATRIX:
                self.matrix(data, part)


def _check_v5_elements(data: bytes, name: str) -> None:
    """InputError naming the file ``name`` for a MAT v5 file whose data elements are not well formed
    (``_V5Elements``)."""
    order = ">" if data[126:128] == b"MI" else "<"
    _V5Elements(name, order).check(data, _V5_HEADER_BYTES, len(data))


def _loadmat_variables(path: Path, name: str) -> dict:
    """Every variable of a v4/v5/v7 file by name (a struct's fields as ``a.b``)."""
    from scipy.io import loadmat

    try:
        data = loadmat(str(path), simplify_cells=True)
    except Exception as exc:  # a damaged file: scipy raises MatReadError, ValueError, IndexError, zlib.error...
        raise InputError(f"not a readable MATLAB file ({_reason(exc)}): {_HINT}", name) from None
    found: dict = {}

    def add(prefix: str, value) -> None:
        if isinstance(value, dict):
            for key, inner in value.items():
                add(f"{prefix}.{key}" if prefix else key, inner)
        else:
            found[prefix] = value

    add("", {k: v for k, v in data.items() if not k.startswith("__")})
    return found


def _reason(exc: Exception) -> str:
    """An exception of a damaged file's reader in a few words on one line: its type and message."""
    return f"{type(exc).__name__}: {' '.join(str(exc).split())}"[:200]


def _is_matrix(value) -> bool:
    """Whether a variable is a real numeric matrix of at least two rows and two columns (what a table of records
    is; not a scalar or a vector of settings saved beside it)."""
    return isinstance(value, np.ndarray) and value.dtype.kind in "biuf" and value.ndim == 2 and min(value.shape) >= 2


def _choose(variables: dict, variable: str | None, name: str) -> str:
    """The name of the variable to read; InputError naming the file and the variables it holds otherwise."""
    listed = ", ".join(sorted(variables)) or "none"
    if variable is not None:
        if variable not in variables:
            raise InputError(f"no variable {variable!r} (the file holds: {listed})", name)
        return variable
    matrices = [k for k, v in variables.items() if _is_matrix(v)]
    if len(matrices) != 1:
        raise InputError(
            f"{'several' if matrices else 'no'} numeric matrices (the file holds: {listed}): name one with "
            '[file] variable = "NAME" in the column map',
            name,
        )
    return matrices[0]


def _records(value, name: str, variable: str) -> np.ndarray:
    """(N, k) floats of one variable, records along the longer dimension; InputError naming the variable."""
    where = f"variable {variable!r}"
    if isinstance(value, str):
        raise InputError(f"{where} is {value}: a column map reads a real numeric matrix", name)
    if not isinstance(value, np.ndarray) or value.dtype.kind not in "biufc":
        raise InputError(f"{where} is not a numeric matrix ({type(value).__name__}): {_HINT}", name)
    if value.dtype.kind == "c":
        raise InputError(f"{where} is a complex array: a column map reads a real numeric matrix", name)
    if value.ndim > 2 or value.size == 0:
        shape = " x ".join(map(str, value.shape)) or "a scalar"
        raise InputError(f"{where} has the shape {shape}: a column map reads a matrix of records", name)
    if value.ndim < 2:
        return np.asarray(value, dtype=float).reshape(-1, 1)
    rows, columns = value.shape
    if rows == columns:
        raise InputError(
            f"{where} is {rows} x {columns}: records and channels cannot be told apart by shape "
            "(magkf takes the records along the longer dimension)",
            name,
        )
    values = np.asarray(value, dtype=float)
    return values if rows > columns else values.T

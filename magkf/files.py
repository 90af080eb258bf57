"""Output files written so that nothing is destroyed: each is checked before any work starts (not an
input, in a folder that exists, not a folder itself) and written to a temporary file beside it that
replaces the target only once complete, so a failure mid-write leaves the old file (or none) in place.
``-`` means standard output (or input, for a log)."""

from __future__ import annotations

import os
import sys
import tempfile
from contextlib import contextmanager, redirect_stdout
from pathlib import Path

from .errors import InputError

__all__ = ["STDIO", "check_outputs", "written", "output_text", "standard_output", "messages_to_stderr"]

#: The path that means standard output (or standard input, where a log is read).
STDIO = "-"

_stdout = None  # standard output while a command's messages go to standard error


def standard_output():
    """Where an output named ``-`` is written."""
    return _stdout or sys.stdout


@contextmanager
def messages_to_stderr():
    """Within the block, what is printed goes to standard error; ``standard_output()`` stays standard output
    (a command that writes its result to ``-`` keeps its messages out of the result)."""
    global _stdout
    _stdout = sys.stdout
    try:
        with redirect_stdout(sys.stderr):
            yield
    finally:
        _stdout = None


def _same(a: Path, b: Path) -> bool:
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def check_outputs(outputs: dict, inputs=()) -> None:
    """Refuse, before anything is computed, output paths that would destroy an input or cannot be written.

    ``outputs`` maps an option's name (``-o``, ``--states`` ...) to its path (None: not asked); ``inputs``
    are the files read. Raises InputError naming the option for an empty path, a path equal to an input or
    to another output, a folder, or a folder that does not exist (it is not created)."""
    given = {opt: p for opt, p in outputs.items() if p is not None}
    seen: dict = {}
    for opt, path in given.items():
        if path == STDIO:
            if STDIO in seen:
                raise InputError(f"{opt} - and {seen[STDIO]} - would both write to standard output")
            seen[STDIO] = opt
            continue
        if not str(path).strip():
            raise InputError(f"{opt}: an empty file name")
        p = Path(path)
        resolved = p.resolve()
        for source in inputs:
            if source is None or source == STDIO:
                continue
            if resolved == Path(source).resolve() or _same(p, Path(source)):
                raise InputError(f"{opt} {path} is an input of this command: it would be overwritten", str(path))
        if resolved in seen:
            raise InputError(f"{opt} and {seen[resolved]} name the same file", str(path))
        seen[resolved] = opt
        if p.is_dir():
            raise InputError(f"{opt}: is a folder, give a file name", str(path))
        folder = p.parent
        if not folder.is_dir():
            raise InputError(f"{opt}: folder {str(folder)!r} does not exist (it is not created)", str(path))
        if not os.access(folder, os.W_OK):
            raise InputError(f"{opt}: folder {str(folder)!r} is not writable", str(path))


@contextmanager
def written(path, suffix: str | None = None):
    """A temporary path beside ``path`` to write to; moved onto ``path`` when the block ends without an
    error, removed otherwise. OSError while writing becomes InputError naming ``path``."""
    target = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=suffix or target.suffix, dir=target.parent or ".")
    os.close(fd)
    try:
        yield tmp
        if target.exists():  # keep the target's permissions
            os.chmod(tmp, target.stat().st_mode & 0o7777)
        else:
            os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, target)
    except OSError as exc:
        raise InputError(f"cannot write: {exc.strerror or exc}", str(path)) from None
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def output_text(path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` safely, or to standard output when ``path`` is ``-``."""
    if path == STDIO:
        standard_output().write(text)
        standard_output().flush()
        return
    with written(path) as tmp:
        Path(tmp).write_text(text, encoding="utf-8")

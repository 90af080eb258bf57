"""Output files written so that nothing is destroyed and nothing is half-written.

Each output is checked before any work starts (not an input, a regular file or none yet, in a folder that
exists and can be written, not a folder itself) and written to a temporary file beside it, named
``.magkf-<host>-<pid>-<random>.tmp<suffix>`` (short, whatever the target's name: a 255-byte name works),
which replaces the target only once complete, so a failure mid-write leaves the old file (or none) in place.

**One command, one commit.** Within ``committed()`` (the ``magkf`` command opens one for its ``-o``,
``--states`` and ``--truth``) the complete temporaries are kept, and moved into place together when the
command ends without an error; on an error or an interruption they are all removed, so the targets keep
their old content. The moves follow one rule: every other output first, in the order they were completed,
and the command's main output (its ``-o``: the calibration of ``calibrate``) last, so that a new
calibration is never found beside old per-epoch states. A stopping signal (``magkf.interruption``) waits
for the moves; SIGKILL cannot wait, so before the first move the list of moves is written beside each
target (``.magkf-<host>-<pid>-<random>.commit``) and the next run completes it.

**What a killed run leaves.** Every ``magkf`` run that makes a temporary in a folder (beside an output, or
the system's temporary folder for a log read from standard input or the chunked path's working folder)
first removes the temporaries there that this host's processes no longer alive left, after completing
their interrupted commits. Temporaries of live processes and of other hosts (a shared folder) are left.

``-`` means standard output (or standard input, for an input).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import secrets
import shutil
import socket
import stat
import sys
import tempfile
from contextlib import contextmanager, redirect_stdout
from pathlib import Path

from .errors import InputError
from .interruption import held

__all__ = [
    "STDIO",
    "STDIN_NAME",
    "check_outputs",
    "written",
    "output_text",
    "committed",
    "uncommitted",
    "main_output",
    "temporary_folder",
    "read_input",
    "input_name",
    "remove_leftovers",
    "standard_output",
    "messages_to_stderr",
]

#: The path that means standard output (or standard input, where an input is read).
STDIO = "-"
#: How errors and outputs name standard input.
STDIN_NAME = "<stdin>"

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


# ---------------------------------------------------------------- checks before any work
def _same(a: Path, b: Path) -> bool:
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def _kind(path: Path) -> str | None:
    """What ``path`` is when it exists but is not a regular file (``"a FIFO"``...), else None."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return None
    kinds = ((stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"))
    for test, name in (*kinds, (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return None


def check_outputs(outputs: dict, inputs=()) -> None:
    """Refuse, before anything is computed, output paths that would destroy an input or cannot be written.

    ``outputs`` maps an option's name (``-o``, ``--states`` ...) to its path (None: not asked); ``inputs``
    are the files read. Raises InputError naming the option for an empty path, a path equal to an input or
    to another output, a folder, a device, FIFO or socket (which a regular file would replace: ``-`` is
    standard output), or a folder that does not exist (it is not created); and for more than one input
    read from standard input."""
    if sum(1 for source in inputs if source == STDIO) > 1:
        raise InputError("only one input can be read from standard input (-): give the others' file names")
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
        _check_target(opt, p)


def _check_target(opt: str, p: Path) -> None:
    """InputError unless ``p`` can become a regular file: not a folder, device, FIFO or socket, in a writable
    folder that exists."""
    if p.is_dir():
        raise InputError(f"{opt}: is a folder, give a file name", str(p))
    kind = _kind(p)
    if kind is not None:
        raise InputError(
            f"{opt}: is {kind}, not a regular file: magkf writes outputs as files (- writes to standard output)", str(p)
        )
    folder = p.parent
    if not folder.is_dir():
        raise InputError(f"{opt}: folder {str(folder)!r} does not exist (it is not created)", str(p))
    if not os.access(folder, os.W_OK):
        raise InputError(f"{opt}: folder {str(folder)!r} is not writable", str(p))


# ---------------------------------------------------------------- temporaries and what killed runs leave
PREFIX = ".magkf-"
#: This host, in temporaries' names: a run removes only its own host's leftovers (a folder may be shared).
HOST = hashlib.sha256(socket.gethostname().encode("utf-8", "replace")).hexdigest()[:6]
_NAME = re.compile(r"^\.magkf-([0-9a-f]{6})-(\d+)-[0-9a-f]{8}\.(tmp|commit)(\.[^./]{1,16})*$")
_SUFFIX_MAX = 16  # a target's suffix kept on its temporary (writers that choose the format by it) up to this
_swept: set = set()  # folders cleaned by this process


def _temporary_name(suffix: str = "", kind: str = "tmp") -> str:
    """``.magkf-<host>-<pid>-<random>.tmp<suffix>``: about 40 characters, whatever the target's name."""
    suffix = suffix if len(suffix) <= _SUFFIX_MAX and "/" not in suffix else ""
    return f"{PREFIX}{HOST}-{os.getpid()}-{secrets.token_hex(4)}.{kind}{suffix}"


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except PermissionError:  # another user's
        return True
    except (ProcessLookupError, OverflowError, ValueError):
        return False
    return True


def _dead_leftover(entry: os.DirEntry) -> str | None:
    """``"tmp"`` or ``"commit"`` for a temporary or a list of moves of this host's process that is no longer
    alive, owned by this user; None for anything else."""
    match = _NAME.match(entry.name)
    if match is None or match.group(1) != HOST or _alive(int(match.group(2))):
        return None
    try:
        if entry.stat(follow_symlinks=False).st_uid != os.getuid():
            return None
    except OSError:
        return None
    return match.group(3)


def remove_leftovers(folder) -> int:
    """Complete the interrupted commits and remove the temporaries left in ``folder`` by this host's
    processes that are no longer alive (killed by SIGKILL); returns how many entries
    were removed or completed. Errors are ignored (another run may be cleaning the same folder)."""
    folder = Path(folder or ".")
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return 0
    kinds = {entry.path: _dead_leftover(entry) for entry in entries if entry.name.startswith(PREFIX)}
    count = 0
    for path in (p for p, kind in kinds.items() if kind == "commit"):  # before the temporaries they move
        count += _complete_moves(Path(path))
    for path in (p for p, kind in kinds.items() if kind == "tmp"):
        count += _remove(Path(path))
    return count


def _remove(path: Path) -> int:
    try:
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink()
        return 1
    except OSError:
        return 0


def _sweep_once(folder: Path) -> None:
    key = os.path.abspath(folder)
    if key not in _swept:
        _swept.add(key)
        remove_leftovers(folder)


# ---------------------------------------------------------------- one command's outputs, committed together
class _Commit:
    """The outputs of one command: complete temporaries waiting to be moved onto their targets."""

    def __init__(self):
        self.moves: dict = {}  # target -> temporary, in the order completed
        self.last: set = set()  # targets moved after the others

    def add(self, tmp: Path, target: Path) -> None:
        earlier = self.moves.pop(target, None)
        if earlier is not None:  # written twice: the later one counts
            _remove(earlier)
        self.moves[target] = tmp

    def ordered(self) -> list:
        first = [(t, tmp) for t, tmp in self.moves.items() if t not in self.last]
        return first + [(t, tmp) for t, tmp in self.moves.items() if t in self.last]

    def discard(self) -> None:
        for tmp in self.moves.values():
            _remove(tmp)
        self.moves.clear()

    def apply(self) -> None:
        """Move every temporary onto its target (the list of moves written first where there are several)."""
        moves = self.ordered()
        journals: list = []
        try:
            if len(moves) > 1:
                _write_moves(moves, journals)
            for target, tmp in moves:
                os.replace(tmp, target)
        finally:
            for journal in journals:
                _remove(journal)
        self.moves.clear()


_commit: _Commit | None = None


def _key(path) -> Path:
    return Path(os.path.abspath(path))


@contextmanager
def committed(last=()):
    """Within the block, outputs written by ``written`` and ``output_text`` are kept as complete temporaries
    and moved into place together when the block ends without an error (``last``, and any path given to
    ``main_output``, after the others); on an error or an interruption they are removed and every target
    keeps its old content. Nested blocks join the outermost."""
    global _commit
    if _commit is not None:
        _commit.last.update(_key(p) for p in last if p not in (None, STDIO))
        yield
        return
    commit = _commit = _Commit()
    commit.last.update(_key(p) for p in last if p not in (None, STDIO))
    try:
        yield
    except BaseException:
        _commit = None
        with held():
            commit.discard()
        raise
    _commit = None
    with held():
        try:
            commit.apply()
        except OSError as exc:
            commit.discard()
            where = str(exc.filename2 or exc.filename) if exc.filename else None  # the target, if known
            raise InputError(f"cannot write: {exc.strerror or exc}", where) from None


@contextmanager
def uncommitted():
    """Within the block, ``written`` moves each complete temporary onto its target at once, as outside
    ``committed()``: for the scratch files a command writes and reads back itself (in a ``temporary_folder``),
    which are not its outputs."""
    global _commit
    outer, _commit = _commit, None
    try:
        yield
    finally:
        _commit = outer


def main_output(path) -> None:
    """Within ``committed()``: ``path`` is moved into place after the command's other outputs."""
    if _commit is not None and path not in (None, STDIO):
        _commit.last.add(_key(path))


def _write_moves(moves: list, written_lists: list) -> None:
    """Write the list of ``moves`` ``[(target, temporary), ...]`` into each target's folder (a temporary
    renamed, so that a list found is complete), appending each list's path to ``written_lists`` (also those
    written before an error)."""
    name = _temporary_name(kind="commit")
    folders = list(dict.fromkeys(target.parent for target, _ in moves))
    paths = [folder / name for folder in folders]
    record = {
        "moves": [[str(tmp), str(target), os.stat(tmp).st_ino, _state(target)] for target, tmp in moves],
        "lists": [str(p) for p in paths],
    }
    text = json.dumps(record)
    for path in paths:
        tmp = path.with_name(_temporary_name())
        written_lists.append(tmp)
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, path)
        written_lists[-1] = path


def _state(target: Path) -> list | None:
    """``[inode, modification time in ns]`` of ``target`` before a commit moves onto it; None when absent."""
    try:
        st = os.stat(target)
    except OSError:
        return None
    return [st.st_ino, st.st_mtime_ns]


def _complete_moves(journal: Path) -> int:
    """Complete the moves a killed run listed in ``journal``; when a temporary it lists is gone unmoved, the
    moves had not begun (the lists are all written before the first): their temporaries are removed instead.
    A target changed since the list was written (written again by the user or another run) is not moved onto:
    its temporary is removed. Removes every copy of the list; returns 1 when done, 0 when it could not be read."""
    try:
        record = json.loads(journal.read_text(encoding="utf-8"))
        moves = [(Path(tmp), Path(target), int(inode), before) for tmp, target, inode, before in record["moves"]]
        lists = [Path(p) for p in record["lists"]]
    except (OSError, ValueError, KeyError, TypeError):
        _remove(journal)
        return 0

    def moved(target: Path, inode: int) -> bool:
        try:
            return os.stat(target).st_ino == inode
        except OSError:
            return False

    complete = all(tmp.exists() or moved(target, inode) for tmp, target, inode, _ in moves)
    for tmp, target, _inode, before in moves:
        if complete and tmp.exists() and _state(target) == before:
            try:
                os.replace(tmp, target)
            except OSError:
                _remove(tmp)
        elif tmp.exists():
            _remove(tmp)
    for path in lists:
        _remove(path)
    return 1


# ---------------------------------------------------------------- writing one output
@contextmanager
def written(path, suffix: str | None = None):
    """A temporary path beside ``path`` to write to (``suffix``: its ending, the target's by default); moved
    onto ``path`` when the block ends without an error (within ``committed()``: when the command ends),
    removed otherwise. OSError while writing becomes InputError naming ``path``."""
    target = Path(path)
    folder = target.parent
    _sweep_once(folder)
    tmp = folder / _temporary_name(target.suffix if suffix is None else suffix)
    try:
        try:
            tmp.touch(mode=0o600, exist_ok=False)
            yield str(tmp)
            _set_mode(tmp, target)
            with held():
                if _commit is not None:
                    _commit.add(tmp, _key(target))
                else:
                    os.replace(tmp, target)
        except BaseException:
            with held():
                _remove(tmp)
            raise
    except OSError as exc:
        raise InputError(f"cannot write: {exc.strerror or exc}", str(path)) from None


def _set_mode(tmp: Path, target: Path) -> None:
    """Give ``tmp`` the target's permissions, or those a new file gets (the umask applied)."""
    try:
        mode = os.stat(target).st_mode & 0o7777
    except OSError:
        mode = 0o666 & ~_umask()
    os.chmod(tmp, mode)


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


# ---------------------------------------------------------------- working folders and standard input
@contextmanager
def temporary_folder(folder=None):
    """A new folder ``.magkf-<host>-<pid>-<random>.tmp`` in ``folder`` (None: the system's temporary folder),
    removed with what it holds when the block ends, however it ends; a later run removes it after SIGKILL."""
    where = Path(folder) if folder is not None else Path(tempfile.gettempdir())
    _sweep_once(where)
    path = where / _temporary_name()
    path.mkdir(mode=0o700)
    try:
        yield str(path)
    finally:
        with held():
            shutil.rmtree(path, ignore_errors=True)


def input_name(path) -> str:
    """How messages name the input ``path``: ``<stdin>`` for ``-``."""
    return STDIN_NAME if path == STDIO else str(path)


def read_input(read, path, suffix: str = ".csv"):
    """``read(path)``; for ``-``, ``read`` of a temporary copy of standard input (``suffix`` its ending, for
    readers that go by it), with errors naming ``<stdin>`` instead of the copy. InputError when standard
    input is empty."""
    if path != STDIO:
        return read(path)
    with temporary_folder() as folder:
        copy = Path(folder) / f"stdin{suffix}"
        with open(copy, "wb") as sink:
            shutil.copyfileobj(sys.stdin.buffer, sink)
        if copy.stat().st_size == 0:
            raise InputError("standard input is empty", STDIN_NAME)
        try:
            return read(str(copy))
        except InputError as exc:
            message = exc.message.replace(str(copy), STDIN_NAME)
            raise InputError(message, STDIN_NAME, exc.row, exc.column) from None

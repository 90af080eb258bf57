"""``magkf.files``: outputs checked before any work, written beside their targets, committed together, and
what a killed run leaves removed by the next; ``magkf.interruption``: a stopping signal waits for the moves."""

import io
import json
import os
import signal
import stat
import sys
from pathlib import Path

import pytest

from magkf import files, interruption
from magkf.errors import InputError


def _dead_pid() -> int:
    """A process number no process can have: above the kernel's largest."""
    try:
        return int(Path("/proc/sys/kernel/pid_max").read_text()) + 1
    except OSError:
        return 2**22 + 1


def _leftovers(folder: Path) -> list:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith(files.PREFIX))


@pytest.fixture
def fresh(monkeypatch):
    """Each test sweeps its folders again (the module remembers the folders it cleaned)."""
    monkeypatch.setattr(files, "_swept", set())


def test_written_replaces_once_complete(tmp_path, fresh):
    target = tmp_path / "out.csv"
    target.write_text("old")
    with pytest.raises(RuntimeError):
        with files.written(target) as tmp:
            Path(tmp).write_text("half")
            raise RuntimeError("stopped mid-write")
    assert target.read_text() == "old" and _leftovers(tmp_path) == []
    with files.written(target) as tmp:
        assert Path(tmp).parent == tmp_path and Path(tmp).name.endswith(".tmp.csv")
        Path(tmp).write_text("new")
    assert target.read_text() == "new" and _leftovers(tmp_path) == []


def test_uncommitted_scratch_lands_at_once_inside_a_commit(tmp_path, fresh):
    """A scratch file the command reads back itself (``uncommitted``) is in place when its block ends, inside the
    command's commit, whose own outputs still wait for the command's end."""
    output, scratch = tmp_path / "diagnosis.json", tmp_path / "states.parquet"
    with files.committed():
        files.output_text(output, "new")
        with files.uncommitted():
            files.output_text(scratch, "scratch")
        assert scratch.read_text() == "scratch" and not output.exists()
        files.output_text(tmp_path / "later.txt", "later")  # the commit is the command's again
        assert not (tmp_path / "later.txt").exists()
    assert output.read_text() == "new" and (tmp_path / "later.txt").read_text() == "later"
    assert _leftovers(tmp_path) == []


def test_long_names_fit(tmp_path, fresh):
    """A 244-byte name (the limit is 255) is written: the temporary's name does not grow with it."""
    target = tmp_path / ("a" * 240 + ".csv")
    files.output_text(target, "x\n")
    assert target.read_text() == "x\n"
    assert len(files._temporary_name(".csv")) < 50


def test_committed_moves_together_main_last(tmp_path, fresh, monkeypatch):
    cal, states, other = tmp_path / "cal.json", tmp_path / "states.csv", tmp_path / "truth.json"
    for path in (cal, states, other):
        path.write_text("old")
    with pytest.raises(KeyboardInterrupt):
        with files.committed(last=[cal]):
            files.output_text(cal, "new")
            files.output_text(states, "new")
            assert cal.read_text() == "old"  # nothing moved before the end
            raise KeyboardInterrupt
    assert [p.read_text() for p in (cal, states, other)] == ["old"] * 3 and _leftovers(tmp_path) == []
    order = []
    real_replace = os.replace

    def replace(src, dst):
        order.append(Path(dst).name)
        real_replace(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    with files.committed(last=[cal]):
        files.output_text(cal, "new")
        files.output_text(states, "new")
        files.output_text(other, "new")
    moves = [name for name in order if not name.startswith(files.PREFIX)]  # the lists of moves aside
    assert moves == ["states.csv", "truth.json", "cal.json"]
    assert [p.read_text() for p in (cal, states, other)] == ["new"] * 3 and _leftovers(tmp_path) == []


def _killed_commit(tmp_path, monkeypatch, moved: int, lists: bool = True):
    """The state a run killed by SIGKILL leaves: complete temporaries of a dead process, its lists of
    moves written (``lists``) and the first ``moved`` of them done. Returns the targets."""
    sub = tmp_path / "states"
    sub.mkdir()
    cal, states = tmp_path / "cal.json", sub / "states.csv"
    for path in (cal, states):
        path.write_text("old")
    with monkeypatch.context() as patch:
        patch.setattr(os, "getpid", _dead_pid)
        commit = files._Commit()
        for target in (states, cal):
            tmp = target.parent / files._temporary_name(target.suffix)
            tmp.write_text("new")
            commit.add(tmp, target)
        commit.last.add(cal)
        moves = commit.ordered()
        if lists:
            files._write_moves(moves, [])
        for target, tmp in moves[:moved]:
            os.replace(tmp, target)
    return cal, states


@pytest.mark.parametrize("moved", [0, 1, 2])
def test_next_run_completes_a_killed_commit(tmp_path, fresh, monkeypatch, moved):
    """Killed between the moves: the next run that writes beside either target completes them all."""
    cal, states = _killed_commit(tmp_path, monkeypatch, moved)
    files.output_text(states.parent / "unrelated.txt", "x")  # a later run writing into the states' folder
    assert cal.read_text() == "new" and states.read_text() == "new"
    assert _leftovers(tmp_path) == [] and _leftovers(states.parent) == []


def test_a_target_written_again_since_the_kill_is_not_overwritten(tmp_path, fresh, monkeypatch):
    """Killed after moving the states, before the calibration; the user then writes the calibration again: the
    next run writing beside it removes the killed run's temporary instead of moving it onto the newer file."""
    cal, states = _killed_commit(tmp_path, monkeypatch, 1)
    os.unlink(cal)
    cal.write_text("the user's")  # a new file: another inode and modification time than the list recorded
    files.output_text(tmp_path / "unrelated.txt", "x")
    assert cal.read_text() == "the user's" and states.read_text() == "new"
    assert _leftovers(tmp_path) == [] and _leftovers(states.parent) == []


def test_next_run_removes_temporaries_of_a_killed_run(tmp_path, fresh, monkeypatch):
    """Killed before the lists of moves were written: the temporaries go, the targets keep their old content."""
    cal, states = _killed_commit(tmp_path, monkeypatch, 0, lists=False)
    assert len(_leftovers(tmp_path)) == 1
    assert files.remove_leftovers(tmp_path) == 1 and files.remove_leftovers(states.parent) == 1
    assert cal.read_text() == "old" and states.read_text() == "old"
    assert _leftovers(tmp_path) == [] and _leftovers(states.parent) == []


def test_live_and_foreign_temporaries_are_kept(tmp_path, fresh):
    """Temporaries of a live process (this one) and of another host are not removed."""
    mine = tmp_path / files._temporary_name()
    foreign = tmp_path / f"{files.PREFIX}{'0' * 6 if files.HOST != '0' * 6 else '1' * 6}-{_dead_pid()}-ab.tmp"
    for path in (mine, foreign):
        path.write_text("x")
    assert files.remove_leftovers(tmp_path) == 0
    assert mine.exists() and foreign.exists()


def test_temporary_folder_removed(tmp_path, fresh):
    with pytest.raises(KeyboardInterrupt):
        with files.temporary_folder(tmp_path) as folder:
            (Path(folder) / "chunk").write_bytes(b"x" * 100)
            assert Path(folder).name.startswith(files.PREFIX)
            raise KeyboardInterrupt
    assert list(tmp_path.iterdir()) == []


def test_devices_and_fifos_refused(tmp_path):
    """A FIFO, /dev/null and a socket are refused before any work, and left as they are; ``-`` is accepted."""
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    for path, kind in ((fifo, "a FIFO"), (Path(os.devnull), "a character device")):
        before = os.stat(path)
        with pytest.raises(InputError, match=f"-o: is {kind}, not a regular file"):
            files.check_outputs({"-o": str(path)})
        after = os.stat(path)
        assert (after.st_mode, after.st_ino, after.st_rdev) == (before.st_mode, before.st_ino, before.st_rdev)
    assert stat.S_ISCHR(os.stat(os.devnull).st_mode)
    files.check_outputs({"-o": "-", "--states": str(tmp_path / "s.csv")})


def test_one_input_from_standard_input(tmp_path):
    with pytest.raises(InputError, match="only one input can be read from standard input"):
        files.check_outputs({}, ["-", "-"])


def _stdin(monkeypatch, data: bytes):
    monkeypatch.setattr(sys, "stdin", io.TextIOWrapper(io.BytesIO(data)))


def test_read_input_from_standard_input(monkeypatch, tmp_path, fresh):
    monkeypatch.setattr("tempfile.tempdir", str(tmp_path))
    _stdin(monkeypatch, b'{"a": 1}')
    assert files.read_input(lambda p: json.loads(Path(p).read_text()), "-", ".json") == {"a": 1}

    def refuse(path):
        raise InputError(f"cannot parse {path}", path, 2)

    _stdin(monkeypatch, b"x")
    with pytest.raises(InputError) as err:
        files.read_input(refuse, "-")
    assert str(err.value) == "<stdin>, row 2: cannot parse <stdin>"
    _stdin(monkeypatch, b"")
    with pytest.raises(InputError, match="standard input is empty"):
        files.read_input(refuse, "-")
    assert list(tmp_path.iterdir()) == []  # the copies are gone


@pytest.fixture
def signals():
    """Install magkf's handlers for the test, and put back the previous ones after it."""
    previous = interruption.stop_on_signals()
    yield
    interruption.restore(previous)


def test_signal_waits_for_held_block(signals):
    """SIGTERM within ``held()`` is raised when the block ends; a second one while stopping is ignored."""
    done = []
    with pytest.raises(interruption.Interrupted) as err:
        with interruption.held():
            signal.raise_signal(signal.SIGTERM)
            done.append("moves")
    assert done == ["moves"] and err.value.signum == signal.SIGTERM
    assert interruption.exit_status(err.value) == 128 + signal.SIGTERM
    signal.raise_signal(signal.SIGHUP)  # the command is stopping: ignored


def test_sighup_interrupts(signals):
    with pytest.raises(KeyboardInterrupt):
        signal.raise_signal(signal.SIGHUP)


def test_the_third_signal_stops_even_a_stopping_command(signals):
    """Once stopping, the second signal is ignored (the clean-up runs) and the third raises again (a clean-up that
    hangs, or a stop that was swallowed, can still be cut)."""
    with pytest.raises(interruption.Interrupted):
        signal.raise_signal(signal.SIGINT)
    signal.raise_signal(signal.SIGINT)  # the second: ignored
    with pytest.raises(interruption.Interrupted) as err:
        signal.raise_signal(signal.SIGTERM)
    assert err.value.signum == signal.SIGTERM


def test_an_error_raised_in_place_of_the_stop_is_the_stop(monkeypatch, capsys):
    """A SIGTERM that arrives while an extension module initialises comes out of the import as ``ImportError:
    initialization failed``: the command still stops as interrupted (128 + 15, "interrupted (SIGTERM)"), not with an
    internal error; an error with no stop under way is one."""
    from magkf import cli

    def imports_when_stopped(args):
        try:
            signal.raise_signal(signal.SIGTERM)
        except interruption.Interrupted:
            raise ImportError("initialization failed") from None

    def imports_badly(args):
        raise ImportError("initialization failed")

    parser = cli.build_parser()
    for func, status, words in (
        (imports_when_stopped, 128 + signal.SIGTERM, "magkf: interrupted (SIGTERM)"),
        (imports_badly, 1, "magkf: internal error: ImportError"),
    ):
        monkeypatch.setattr(cli, "build_parser", lambda func=func: _with_func(parser, func))
        assert cli.main(["check", "x.csv"]) == status
        assert words in capsys.readouterr().err
    assert interruption.stopping() is None  # main puts the handlers back; the next stop_on_signals starts afresh


def _with_func(parser, func):
    """``parser`` whose parsed arguments run ``func``."""
    parse = parser.parse_args

    def parse_args(argv):
        args = parse(argv)
        args.func = func
        return args

    parser.parse_args = parse_args
    return parser

"""The ``magkf`` command line: a thin layer over the Python API, one module per group of commands.

Exit status 0 on success; 2 on bad usage or bad input, with one line on standard error (``InputError``
names the file, row and column where it applies; ``ValueError`` is a setting that cannot be used; an
``OSError`` a file that cannot be read or written); 1 with one line for an internal error, whose traceback
``--debug`` shows. Output paths are checked before any work (``magkf.files``); ``-`` is standard
output for ``-o`` and ``--states``, standard input for a log or a calibration. A command's outputs are
moved into place together once it has succeeded (``magkf.files.committed``: the ``-o`` file last).
SIGINT, SIGTERM and SIGHUP stop a command alike (``magkf.interruption``): its temporaries are removed, the
targets keep their old content, ``magkf: interrupted (SIGTERM)`` is printed and the exit status is 128 +
the signal's number (130, 143, 129).
"""

from __future__ import annotations

import argparse
import contextlib
import signal
import sys
import warnings

from .. import __version__
from ..errors import InputError
from ..plugins import REGISTRIES
from . import apply, diagnostics, fleet, live, logs, offline, online, plugins, replay, simulate
from .common import Note

__all__ = ["main", "build_parser"]

#: The modules that add the commands, in the order ``--help`` lists them.
COMMANDS = (online, diagnostics, apply, logs, offline, simulate, fleet, live, replay, plugins)


#: Options that name files a command writes, and files it reads (argparse ``dest`` -> the option's name).
OUTPUTS = {"output": "-o", "states": "--states", "truth": "--truth", "params": "--params", "log": "--log"}
INPUTS = ("file", "cal", "init", "map", "curves", "truth_cal", "effect_file", "param_file")


class _Parser(argparse.ArgumentParser):
    """argparse with usage errors on one line, as every other error (exit status 2)."""

    def error(self, message: str, prog: str | None = None):
        prog = prog or self.prog
        command = prog.removeprefix("magkf").strip()  # "diagnose" for a command's parser, "" for magkf's
        where = f"{command}: " if command else ""
        print(f"magkf: error: {where}{_one_line(message)} (see {prog} --help)", file=sys.stderr)
        sys.exit(2)

    def parse_args(self, args=None, namespace=None):
        """As argparse's, with arguments no parser took named against the command given (its --help)."""
        parsed, extras = self.parse_known_args(args, namespace)
        if extras:
            command = getattr(parsed, "command", None)
            prog = f"{self.prog} {command}" if command else self.prog
            self.error(f"unrecognized arguments: {' '.join(extras)}", prog)
        return parsed


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="magkf",
        description="Magnetometer calibration for vehicles.",
        epilog="Each command's --help gives its options. The log columns, units and files are described in "
        "docs/data-contract.md.",
    )
    parser.add_argument("--version", action="version", version=f"magkf {__version__}")
    parser.add_argument("--debug", action="store_true", help="on an internal error, show the traceback")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module in COMMANDS:
        module.add_parsers(sub)
    return parser


def _files(args) -> tuple[dict, list]:
    """The output options given (option name -> path) and the input files of ``args``."""
    outputs = {flag: getattr(args, dest) for dest, flag in OUTPUTS.items() if getattr(args, dest, None) is not None}
    inputs = []
    for dest in INPUTS:
        value = getattr(args, dest, None)
        inputs.extend(value if isinstance(value, list) else [value])
    return outputs, [str(i) for i in inputs if i is not None]


def main(argv=None) -> int:
    """Run the command line; returns the exit status (0 done, 2 bad input or usage, 1 internal error)."""
    from ..allocator import pin_mmap_threshold
    from ..interruption import restore, stop_on_signals

    pin_mmap_threshold()  # freed chunk arrays of a long log given back to the system (``magkf.allocator``)
    previous = stop_on_signals()
    streams = sys.stdout, sys.stderr
    sys.stdout, sys.stderr = _ReaderMayLeave(sys.stdout), _ReaderMayLeave(sys.stderr)
    try:
        return _main(argv)
    except KeyboardInterrupt as exc:  # before or after the command (while parsing, printing the warnings)
        return _interrupted(exc)
    finally:
        sys.stdout, sys.stderr = streams
        restore(previous)  # main called from Python: its caller's handlers again


class _ReaderMayLeave:
    """Standard output (or error) whose reader may leave before the command ends (``magkf calibrate ... 2>&1 |
    head``): what is printed after it left is dropped, and the command goes on to write its files. (Stopped by
    SIGPIPE instead, as a filter would be, it lost the calibration it had computed.)"""

    def __init__(self, stream):
        self._stream = stream

    def write(self, text: str) -> int:
        try:
            return self._stream.write(text)
        except BrokenPipeError:
            self._left()
            return len(text)

    def flush(self) -> None:
        try:
            self._stream.flush()
        except BrokenPipeError:
            self._left()

    def _left(self) -> None:
        """The stream's descriptor pointed at the null device, so that no later write or flush fails."""
        import os

        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, self._stream.fileno())
        os.close(null)

    def __getattr__(self, name):
        return getattr(self._stream, name)


def _interrupted(exc: KeyboardInterrupt) -> int:
    """Say that the command was stopped by a signal; its exit status (128 + the signal's number)."""
    from ..interruption import exit_status

    name = getattr(exc, "signum", None)
    print("magkf: interrupted" + (f" ({signal.Signals(name).name})" if name else ""), file=sys.stderr)
    return exit_status(exc)


def _main(argv) -> int:
    parser = build_parser()
    args = parser.parse_args(_values_joined(sys.argv[1:] if argv is None else list(argv)))
    if getattr(args, "noise", 0) is None:
        args.noise = 30.0 if args.kind == "drive" else 0.0
    # Warnings and notes are printed once the command has succeeded; an error stays one line and carries
    # the warnings that came before it (a suspected unit often explains the error).
    pending = []

    def hold(message, category, *rest, **kw):
        pending.append(("note" if issubclass(category, Note) else "warning", _one_line(message)))

    warnings.showwarning = hold
    # numpy's floating-point warnings on degenerate data say nothing the checks do not say in words
    warnings.simplefilter("ignore", RuntimeWarning)
    status = _run(args, pending)
    if status == 0:
        for kind, text in pending:
            print(f"magkf: {kind}: {text}", file=sys.stderr)
    return status


def _run(args, pending: list) -> int:
    """Run the parsed command; returns its exit status, an error printed on one line (with the warnings
    ``pending`` before it)."""

    def error(text: str) -> None:
        before = [t for kind, t in pending if kind == "warning"]
        print(f"magkf: error: {text}" + (f" [warned before: {'; '.join(before)}]" if before else ""), file=sys.stderr)

    try:
        from ..files import STDIO, check_outputs, committed, messages_to_stderr

        outputs, inputs = _files(args)
        check_outputs(outputs, inputs)
        with contextlib.ExitStack() as scope:
            if outputs:  # written together once the command succeeded, its -o last
                scope.enter_context(committed(last=[outputs.get("-o")]))
            for registry in REGISTRIES.values():  # what the command registers (--effect-file) ends with it
                scope.enter_context(registry.restoring())
            if STDIO in outputs.values():  # the result goes to standard output, the messages to standard error
                scope.enter_context(messages_to_stderr())
            return args.func(args)
    except (InputError, ValueError) as exc:  # bad input, or a setting that cannot be used: one line
        import numpy as np

        if isinstance(exc, np.linalg.LinAlgError):  # degenerate numbers from the data or the settings
            where = f"{args.file}: " if getattr(args, "file", None) else ""
            exc = f"{where}the computation failed ({exc}): the data or the settings are degenerate"
        error(_one_line(exc))
        return 2
    except OSError as exc:  # a file that cannot be read or written
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        error(_one_line(f"{where}{exc.strerror or exc}"))
        return 2
    except KeyboardInterrupt as exc:  # Ctrl-C, SIGTERM, SIGHUP: the outputs' temporaries are removed
        return _interrupted(exc)
    except Exception as exc:  # a defect of magkf: one line, the traceback on request
        from ..interruption import stopping

        stop = stopping()
        if stop is not None:  # raised in place of the stop's Interrupted (``interruption.stopping``)
            return _interrupted(stop)
        if args.debug:
            raise
        print(
            f"magkf: internal error: {type(exc).__name__}: {_one_line(exc)} (run with --debug for the traceback)",
            file=sys.stderr,
        )
        return 1


#: Options whose value may start with '-' (a mounting such as -y,x,z), which argparse would take for an option.
DASH_VALUES = ("--mounting", "--site")


def _values_joined(argv: list) -> list:
    """``--mounting -y,x,z`` as ``--mounting=-y,x,z`` (and ``--site -33.9,151.2``, a southern latitude)."""
    out, i = [], 0
    while i < len(argv):
        if argv[i] in DASH_VALUES and i + 1 < len(argv):
            out.append(f"{argv[i]}={argv[i + 1]}")
            i += 2
        else:
            out.append(str(argv[i]))
            i += 1
    return out


def _one_line(exc) -> str:
    """``exc`` (an exception or a message) on one line, control characters escaped."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


if __name__ == "__main__":
    sys.exit(main())

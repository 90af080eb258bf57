"""The ``magkf`` command line: a thin layer over the Python API, one module per group of commands.

Exit status 0 on success; 2 on bad usage or bad input, with one line on standard error (``InputError``
names the file, row and column where it applies; ``ValueError`` is a setting that cannot be used).
"""

from __future__ import annotations

import argparse
import signal
import sys
import warnings

from .. import __version__
from ..errors import InputError
from . import apply, diagnostics, logs, offline, online, simulate

__all__ = ["main", "build_parser"]

#: The modules that add the commands, in the order ``--help`` lists them.
COMMANDS = (online, diagnostics, apply, logs, offline, simulate)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="magkf", description="Magnetometer calibration for vehicles.")
    parser.add_argument("--version", action="version", version=f"magkf {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module in COMMANDS:
        module.add_parsers(sub)
    return parser


def main(argv=None) -> int:
    if hasattr(signal, "SIGPIPE"):  # output piped into head and the like: stop quietly when it closes
        signal.signal(signal.SIGPIPE, signal.SIG_DFL)
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "noise", 0) is None:
        args.noise = 30.0 if args.kind == "drive" else 0.0
    warnings.showwarning = lambda message, category, *a, **k: print(f"magkf: warning: {message}", file=sys.stderr)
    try:
        return args.func(args)
    except (InputError, ValueError) as exc:  # bad input, or a setting that cannot be used: one line
        print(f"magkf: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

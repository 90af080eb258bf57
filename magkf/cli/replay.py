"""``magkf replay``: any log magkf reads sent over a MAVLink link as a vehicle's stream (``magkf.live.replay``)."""

from __future__ import annotations

from . import common

__all__ = ["add_parsers", "run_replay"]


def add_parsers(sub) -> None:
    """Register ``replay``."""
    from ..live.replay import CONNECTION_HELP

    p = common.command(
        sub,
        "replay",
        run_replay,
        "send a log as a vehicle's MAVLink stream (magnetometer, attitude, GNSS, time), answering parameter requests",
    )
    common.add_log_options(p)
    p.add_argument("connection", metavar="CONNECTION", help=f"where to send: {CONNECTION_HELP}")
    p.add_argument(
        "--speed",
        type=_speed,
        default=1.0,
        metavar="X",
        help="times faster than the log's own time (default 1; 0 or inf: as fast as the link takes them)",
    )
    p.add_argument(
        "--loss",
        type=common.number_in(0, 0.999),
        default=0.0,
        metavar="P",
        help="share of the log's packets dropped at random, 0 to 0.999 (default 0); the receiver sees the gaps in "
        "the sequence numbers",
    )
    p.add_argument(
        "--seed", type=common.count_in(0, 2**32 - 1), default=0, metavar="N", help="seed of the losses (default 0)"
    )
    p.add_argument(
        "--autopilot",
        choices=["ardupilot", "px4"],
        default="ardupilot",
        help="the firmware whose messages are sent (default ardupilot: RAW_IMU; px4: SCALED_IMU)",
    )
    p.add_argument(
        "--params",
        dest="param_file",
        metavar="FILE",
        help="the vehicle's parameters (.param/.parm or QGroundControl .params), answered on request; ArduPilot's "
        "COMPASS_* are applied to the field as the firmware does (default: the log's own compass parameters)",
    )
    p.add_argument(
        "--firmware",
        metavar="VERSION",
        help="the firmware version sent as AUTOPILOT_VERSION (e.g. 4.5.0; default the log's, else none)",
    )
    p.add_argument(
        "--reboot-at",
        type=common.number_in(0, 10**7, "s", open_low=True),
        metavar="S",
        help="the vehicle reboots S seconds into the log: its boot clock and sequence numbers start again",
    )
    p.add_argument(
        "--linger",
        type=common.number_in(0, 3600, "s"),
        default=0.0,
        metavar="S",
        help="go on answering requests for S seconds after the log's end (default 0)",
    )
    p.add_argument("--sysid", type=common.count_in(1, 255), default=1, help="the vehicle's system id (default 1)")
    p.add_argument("--baud", type=common.count_in(50, 10**8), default=115200, help="bits/s of a serial device")


def _speed(text: str) -> float:
    """An argparse type: a speed factor, a number >= 0 or ``inf``."""
    import argparse
    import math

    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if math.isnan(value) or value < 0:
        raise argparse.ArgumentTypeError(f"{text} is not a speed factor >= 0 (0 or inf: as fast as possible)")
    return value


def run_replay(args) -> int:
    """Send a log over a MAVLink link as the vehicle would have streamed it, at its own pace times --speed, so that
    magkf live (or any MAVLink tool) can be tried without a vehicle. The vehicle answers PARAM_REQUEST_READ,
    PARAM_REQUEST_LIST, PARAM_SET and the message-interval commands; it keeps the log's own rates. Ends at the
    log's end (after --linger) or on Ctrl-C, printing packets sent, dropped and seconds."""
    import warnings

    from ..interruption import Interrupted
    from ..io.autopilot import read_param_file
    from ..live.replay import replay

    log = common.open_log(args)
    params = read_param_file(args.param_file) if args.param_file else None
    stats = replay(
        log,
        args.connection,
        speed=args.speed,
        loss=args.loss,
        seed=args.seed,
        autopilot=args.autopilot,
        params=params,
        firmware=args.firmware,
        reboot_at_s=args.reboot_at,
        sysid=args.sysid,
        baud=args.baud,
        linger_s=args.linger,
    )
    print(stats.line(), flush=True)
    for note in stats.notes:
        warnings.warn(note, common.Note, stacklevel=1)
    if stats.interrupted_by is not None:
        raise Interrupted(stats.interrupted_by)
    return 0

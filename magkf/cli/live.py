"""``magkf live``: calibrate a vehicle while it flies, from its MAVLink stream."""

from __future__ import annotations

import contextlib
import math
import sys
import time
from pathlib import Path

from ..blas import one_thread
from . import common

__all__ = ["add_parsers", "run_live"]

#: Seconds between two statuses shown (the screen, --json-lines).
SHOWN_EVERY_S = 1.0
#: Seconds each poll of the link reads for; its samples are filtered as one step (see ``LiveSession.add_many``).
POLL_S = 0.1


def add_parsers(sub) -> None:
    """Register ``live``."""
    p = common.command(sub, "live", run_live, "calibrate a vehicle while it flies, from its MAVLink stream")
    p.add_argument(
        "connection",
        metavar="CONNECTION",
        help="what pymavlink's mavutil connects to: udpin:0.0.0.0:14550, udpout:HOST:PORT, tcp:HOST:PORT, tcpin:"
        "HOST:PORT, or a serial device (/dev/ttyUSB0) with --baud",
    )
    p.add_argument("--baud", type=int, default=57600, help="serial link speed, bit/s (default 57600)")
    p.add_argument(
        "--mag",
        type=common.count_in(0, 3),
        help="the magnetometer message read: 0 RAW_IMU, 1 SCALED_IMU2, 2 SCALED_IMU3, 3 HIGHRES_IMU (default: the "
        "first the vehicle sends with a field)",
    )
    p.add_argument("--init", help="calibration JSON to start from (default: bootstrapped from the first samples)")
    p.add_argument("--connect-timeout", type=float, default=30.0, metavar="S", help="seconds to wait for the vehicle")
    stop = p.add_argument_group("when to stop (and Ctrl-C, at any time)")
    stop.add_argument("--duration", type=float, metavar="S", help="stop after S seconds of the vehicle's clock")
    stop.add_argument(
        "--until-converged",
        type=float,
        metavar="FRACTION",
        help="stop once every standard deviation of R is below FRACTION and every one of b below FRACTION times the "
        "field (0.005: 250 nT at 50 000 nT)",
    )
    out = p.add_argument_group("outputs (written when it stops: the calibration calibrate writes for the samples)")
    out.add_argument("-o", "--output", metavar="FILE", help="write the calibration file")
    out.add_argument("--states", metavar="FILE", help="per-epoch states, as calibrate --states writes them")
    out.add_argument("--params", metavar="FILE", help="the autopilot's parameter file of the calibration")
    out.add_argument(
        "--upload",
        action="store_true",
        help="send the parameters to the vehicle (PARAM_SET, each confirmed by its echo); asks first on a terminal",
    )
    out.add_argument("--log", metavar="FILE", help="the samples received, as a canonical log (CSV, or .parquet)")
    out.add_argument("--json-lines", action="store_true", help="one JSON object a second instead of the screen")
    out.add_argument(
        "--checkpoint",
        metavar="FILE",
        help="checkpoint file (default: beside -o, .live), its samples in FILE.samples; both removed once the outputs "
        "are written",
    )
    out.add_argument("--checkpoint-every", type=float, default=5.0, metavar="S", help="seconds between checkpoints")
    out.add_argument("--resume", action="store_true", help="continue the session of --checkpoint")
    diag = p.add_argument_group("the running diagnosis")
    diag.add_argument("--diagnose-every", type=float, default=60.0, metavar="S", help="seconds between diagnoses")
    diag.add_argument("--window", type=float, default=120.0, metavar="S", help="seconds of samples diagnosed")
    diag.add_argument("--alpha", type=float, default=0.01, help="significance level over all candidates")
    common.add_model_options(p)
    p.add_argument("--quiet", action="store_true", help="no screen (the summary at the stop is still printed)")
    common.add_filter_options(p)
    common.add_effect_options(p, "effects to estimate with R and b (repeat the option)")
    p.set_defaults(batch=False, smooth=False, json=False)


@one_thread  # OpenBLAS's idle threads spin between the filter's small products: a few % of a core at any rate
def run_live(args) -> int:
    """Calibrate a vehicle while it flies, from its MAVLink stream (magkf.live; docs/live.md).

    The vehicle is asked for its magnetometer, attitude, GNSS, system time, battery and throttle streams and for its
    compass parameters, whose calibration is undone as the log readers undo it. Each sample goes through the
    real-time filter (magkf.online.realtime.OnlineCalibrator); about once a second the screen shows the epochs used
    and refused, the link, the residual and the learned noise, b and the diagonal of R, what the data do not
    determine yet, the verdict and the running diagnosis. On Ctrl-C, at --duration or --until-converged the samples
    received are calibrated as calibrate calibrates a log (the same estimate and plausibility rule), and -o, --states
    and --params are written. A checkpoint is written every few seconds; --resume continues from it."""
    from ..plausibility import check_start

    config = common.filter_config(args)
    init = common.load_calibration(args.init)
    check_start(init, args.init)
    added = common.effects(args, init)
    checkpoint = _checkpoint_path(args)
    session = _session(args, config, init, added, checkpoint)
    if args.resume:  # the session's own settings and start, for the calibration written too
        config, init, added = session.config, session.init, list(session.effects or [])
    source = _open_source(args)
    try:
        why = _run(args, session, source, checkpoint)
        upload = _finish(args, session, source, config, init, added, why, checkpoint)
        status = _upload(args, source, upload) if upload is not None else 0
    finally:
        source.close()
    _remove_checkpoint(checkpoint, session)
    return status


def _remove_checkpoint(checkpoint: Path, session) -> None:
    """The checkpoint and its samples removed: the session's outputs are written."""
    import shutil

    checkpoint.unlink(missing_ok=True)
    shutil.rmtree(session.recording.folder, ignore_errors=True)


def _checkpoint_path(args) -> Path:
    if args.checkpoint:
        return Path(args.checkpoint)
    if args.output and args.output != "-":
        return Path(args.output).with_suffix(".live")
    return Path("magkf.live")


def _session(args, config, init, added, checkpoint: Path):
    """The session: continued from ``checkpoint`` with --resume, else new (refused where an earlier session's
    checkpoint would be overwritten)."""
    from ..errors import InputError
    from ..live.recording import Recording
    from ..live.session import LiveSession

    if args.resume:
        if args.init or getattr(args, "effect", None):
            raise InputError("--resume continues a session with its own start and effects: drop --init and --effect")
        if not checkpoint.exists():
            raise InputError("no checkpoint to resume from; start without --resume", str(checkpoint))
        session = LiveSession.load(checkpoint)
        session.event(f"resumed from {checkpoint} after {sum(session.counts.values())} epochs")
        return session
    if checkpoint.exists():
        raise InputError(
            "an earlier session's checkpoint is there: give --resume to continue it, or remove it (and its .samples "
            "folder) to start again",
            str(checkpoint),
        )
    folder = checkpoint.with_name(checkpoint.name + ".samples")
    if folder.exists() and any(folder.iterdir()):
        raise InputError("samples of an earlier session are there: remove the folder to start again", str(folder))
    return LiveSession(
        config,
        init,
        added or None,
        target=args.until_converged,
        window_s=args.window,
        diagnose_every_s=args.diagnose_every,
        alpha=args.alpha,
        recording=Recording(folder),
        background=True,
    )


def _open_source(args):
    from ..live.source import MavlinkSource

    source = MavlinkSource(args.connection, baud=args.baud, mag=args.mag)
    try:
        source.open(timeout_s=args.connect_timeout)
    except BaseException:
        source.close()
        raise
    return source


def _display(args):
    """``show(status)`` and ``close(status)`` for the screen, the JSON lines, or nothing (--quiet)."""
    from ..live.screen import JsonLines, Screen

    if args.json_lines:
        return JsonLines(sys.stdout, interval_s=0.0)  # paced by the loop (SHOWN_EVERY_S)
    if args.quiet:
        return None
    return Screen(sys.stdout, interval_s=0.0)


def _run(args, session, source, checkpoint: Path) -> str:
    """Feed the samples until a stop; returns why it stopped, in words. The status is made only when it is shown
    (once a second): its figures (the observability's eigen-decomposition, the verdict) cost more than a
    second of samples."""
    from ..interruption import held

    display = _display(args)
    last_checkpoint = last_shown = time.monotonic()
    try:
        while True:
            with held():  # a Ctrl-C waits for the samples read to be filtered and counted, not half of one
                session.add_many(source.poll(POLL_S))
                for text in source.take_events():
                    session.event(text)
                now = time.monotonic()
                if now - last_checkpoint >= args.checkpoint_every:
                    session.save(checkpoint)
                    last_checkpoint = now
            if display is not None and now - last_shown >= SHOWN_EVERY_S:
                display.show(session.status(_link(source)))
                last_shown = now
            why = _stop(args, session)
            if why:
                break
    except KeyboardInterrupt as exc:
        why = f"stopped ({exc or 'SIGINT'})"
    session.add_many(source.drain())  # the samples still waiting for their attitude
    session.wait_for_diagnosis()
    session.save(checkpoint)
    if display is not None:
        display.close(session.status(_link(source), source.take_events()))
    return why


def _stop(args, session) -> str | None:
    """Why the session stops now (--duration, --until-converged), or None."""
    elapsed = session.last_time - session.first_time
    if args.duration is not None and math.isfinite(elapsed) and elapsed >= args.duration:
        return f"{args.duration:g} s of the vehicle's clock"
    if args.until_converged is not None and session.converged:
        return f"converged: every standard deviation below {args.until_converged:g}"
    return None


def _link(source) -> dict:
    """The link's figures for the status: counters, lost share, the rates measured and asked."""
    counters = dict(source.counters)
    packets, lost = counters.get("packets", 0), counters.get("lost", 0)
    counters["lost_share"] = lost / (packets + lost) if packets + lost else 0.0
    return counters | {"rates_hz": dict(source.rates_hz), "asked_hz": dict(source.asked_hz)}


def _finish(args, session, source, config, init, added, why: str, checkpoint: Path):
    """The samples received calibrated as ``calibrate`` calibrates a log, and the outputs written; the real-time
    estimate compared with it. Returns the parameter set to send with --upload (None without it)."""
    from ..errors import InputError
    from ..io.drivelog import from_table
    from .online import _calibrate_one

    table = session.recording.table()
    if len(table) == 0:
        _remove_checkpoint(checkpoint, session)  # nothing to resume
        raise InputError("no sample was received from the vehicle: nothing to calibrate", args.connection)
    log = from_table(table, source=args.connection, provenance=dict(source.provenance))
    if args.log:
        from ..io.drivelog import write_drive_log

        write_drive_log(log.table, args.log)
    out = sys.stderr if args.json_lines else sys.stdout
    with contextlib.redirect_stdout(out):
        print(f"live session ended ({why}) after {len(table)} samples; calibrating them as calibrate does:")
        run = _calibrate_one(args, log, config, init, added, args.output, args.states)
        _compare_realtime(session, run)
        if args.params or args.upload:
            return _parameters(args, source, run.calibration)
    return None


def _compare_realtime(session, run) -> None:
    """One line: how far the real-time filter's last estimate lies from the calibration written, in its standard
    deviations."""
    import numpy as np

    if session.calibrator is None:
        span = session.last_time - session.first_time
        why = session.no_start or (
            f"the samples span {span:.1f} s; a start is bootstrapped from {session.config.bootstrap_s:g} s"
            if span < session.config.bootstrap_s
            else "no start could be bootstrapped from the samples"
        )
        print(f"  the real-time filter never started ({why})")
        return
    x_live = session.calibrator.estimator.x[:12]
    std = np.sqrt(np.diag(run.calibration.covariance))
    worst = float(np.max(np.abs(x_live - run.calibration.state) / std))
    print(f"  the real-time filter's last estimate lies within {worst:.2f} standard deviations of the calibration")


def _parameters(args, source, cal):
    """The autopilot's parameter set of ``cal`` for the compass the samples came from (``export_instance``, which
    reads it from the samples' provenance), written to --params; returned for --upload (None without it)."""
    from ..errors import InputError
    from ..io.autopilot import export_instance, to_ardupilot, to_px4, write_param_file

    if source.autopilot not in ("ardupilot", "px4"):
        raise InputError(
            f"the vehicle's autopilot is {source.autopilot or 'not known'}: magkf writes ArduPilot and PX4 "
            "parameters; drop --params and --upload (the calibration file is written)",
            args.connection,
        )
    instance, why = export_instance(cal, source.autopilot)
    make = to_ardupilot if source.autopilot == "ardupilot" else to_px4
    params = make(cal, instance)
    print(f"  {source.autopilot} parameters of {why}")
    if args.params:
        write_param_file([params], args.params)
        print(f"  written to {args.params}")
    return params if args.upload else None


def _upload(args, source, params) -> int:
    """Send ``params`` (asked first on a terminal); 0 when every one is confirmed, else 2 with one line (the outputs
    are written either way, and say what was meant to be sent)."""
    values = params.values
    refusal = _upload_refused(source)
    if refusal:
        print(f"magkf: error: {args.connection}: parameters not sent: {refusal}", file=sys.stderr)
        return 2
    if sys.stdin.isatty():
        try:
            answer = input(f"send {len(values)} parameters to the vehicle ({', '.join(values)})? [y/N] ")
        except (EOFError, KeyboardInterrupt):
            answer = ""
        if answer.strip().lower() not in ("y", "yes"):
            print("  parameters not sent")
            return 0
    confirmed = source.set_parameters(values)
    refused = [name for name, ok in confirmed.items() if not ok]
    print(f"  {len(confirmed) - len(refused)} of {len(confirmed)} parameters sent and confirmed by the vehicle")
    if refused:
        print(
            f"magkf: error: {args.connection}: the vehicle did not confirm {', '.join(refused)}: check them before "
            "flying",
            file=sys.stderr,
        )
        return 2
    return 0


def _upload_refused(source) -> str | None:
    """Why the parameters may not be sent now, or None: an armed vehicle (its compass's calibration would change
    under its estimator), or one whose own compass parameters were not all read (the calibration is then relative
    to a field the parameters sent would not undo)."""
    if source.armed:
        return "the vehicle is armed: land and disarm, then send the parameter file written"
    missing = source.missing_compass_parameters
    if missing:
        return f"its compass parameters {', '.join(missing)} were not read, so the calibration is not of its raw field"
    return None

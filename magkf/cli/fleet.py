"""``magkf fleet`` and ``magkf study``: many logs, or many settings, on Dask (``magkf.fleet``, ``magkf.study``)."""

from __future__ import annotations

import contextlib
import sys
from pathlib import Path

from . import common

__all__ = ["add_parsers", "run_fleet", "run_study"]


def add_parsers(sub) -> None:
    """Register ``fleet`` and ``study``."""
    p = common.command(sub, "fleet", run_fleet, "calibrate (and diagnose) every log of a fleet, on Dask")
    p.add_argument("logs", nargs="+", metavar="LOG", help="log files, folders (every log below) or glob patterns")
    p.add_argument("-o", "--out", dest="out_dir", required=True, metavar="DIR", help="output folder (made if missing)")
    p.add_argument(
        "--diagnose",
        action="store_true",
        help="also diagnose each log (diagnosis.json per log) and pool each vehicle's diagnoses over its flights "
        "(DIR/pooled_diagnosis.json: a combined test per candidate, the coefficient's consistency across flights, "
        "the effect recommended for the vehicle and the flights that disagree)",
    )
    p.add_argument(
        "--alpha",
        type=common.probability,
        default=0.01,
        help="significance level of the diagnosis and of each vehicle's disagreement test (default 0.01)",
    )
    p.add_argument(
        "--vehicle-from",
        choices=["parent", "name", "none"],
        default="parent",
        help="a log's vehicle: the folder holding it (default), its file name up to the first '_', or one "
        "vehicle for all",
    )
    common.add_model_options(p)
    common.add_reading_options(p, many=True)
    common.add_filter_options(p)
    common.add_effect_options(p, "effects to estimate with R and b (repeat the option)")
    add_cluster_options(p)

    p = common.command(sub, "study", run_study, "filter-tuning study: settings x logs x seeds, on Dask")
    p.add_argument("spec", metavar="SPEC.toml", help="the study (see magkf.study and scripts/tuning_study.toml)")
    p.add_argument("-o", "--out", dest="out_dir", required=True, metavar="DIR", help="output folder (made if missing)")
    add_cluster_options(p)


def add_cluster_options(p) -> None:
    g = p.add_argument_group("Dask cluster (docs/fleet.md)")
    g.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="an existing Dask scheduler (tls://host:port, with --tls-*; tcp:// has no encryption nor "
        "authentication); its workers must see the inputs and DIR at the same paths (default: a local cluster, "
        "on 127.0.0.1 with TLS and a certificate of its own)",
    )
    g.add_argument("--tls-ca-file", metavar="CA.pem", help="with --scheduler tls://: the certificate authority's")
    g.add_argument("--tls-cert", metavar="CERT.pem", help="with --scheduler tls://: this client's certificate")
    g.add_argument("--tls-key", metavar="KEY.pem", help="with --scheduler tls://: this client's private key")
    g.add_argument(
        "--workers",
        type=common.count_in(0, 1024),
        help="worker processes of the local cluster (default: one per core; 0: one after the other in this "
        "process, without Dask)",
    )
    g.add_argument(
        "--memory-limit",
        default="auto",
        metavar="SIZE",
        help="memory limit of each local worker, such as 2GB (default auto: the machine's memory shared out; "
        "Dask restarts a worker that exceeds 95 %% of it, and that log's row says so)",
    )
    common.add_quiet_option(p)


def _client(args):
    """The Dask client the options ask for (a context manager giving None: serial, in this process)."""
    from contextlib import nullcontext

    from ..cluster import connect, local_client, tls_security
    from ..errors import InputError

    tls = (args.tls_ca_file, args.tls_cert, args.tls_key)
    if args.scheduler:
        if args.workers is not None:
            raise InputError("--workers is for the local cluster: leave it out with --scheduler")
        for path in tls:
            if path is not None and not Path(path).is_file():
                raise InputError("no such file", path)
        if not args.scheduler.startswith("tls://") and any(path is not None for path in tls):
            raise InputError(f"{args.scheduler}: --tls-ca-file, --tls-cert and --tls-key need a tls:// address")
        if not args.scheduler.startswith("tls://"):
            print(
                f"magkf: warning: {args.scheduler}: no encryption nor authentication: whoever reaches that address "
                "can run code as the workers' user; use tls:// (docs/fleet.md, 'On a multi-node cluster')",
                file=sys.stderr,
            )
        return connect(args.scheduler, security=tls_security(*tls))
    if any(path is not None for path in tls):
        raise InputError(
            "--tls-ca-file, --tls-cert and --tls-key are for --scheduler tls://...: the local cluster "
            "makes its own certificate"
        )
    if args.workers == 0:
        return nullcontext(None)
    limit = None if args.memory_limit.lower() in ("none", "0") else args.memory_limit
    return local_client(args.workers, limit)


def _progress(args):
    from ..online.run import terminal_progress

    return None if args.quiet else terminal_progress()


def _memory_line(peaks: dict, limits: dict) -> str:
    """``peak memory per worker: ...`` in MB, with the limit where there is one."""
    if not peaks:
        return "peak memory per worker: no log processed"
    parts = []
    for worker, peak in sorted(peaks.items()):
        limit = limits.get(worker, 0)
        parts.append(f"{worker} {peak:.0f} MB" + (f" (limit {limit / 1e6:.0f} MB)" if limit else ""))
    return "peak memory per worker: " + ", ".join(parts)


def run_fleet(args) -> int:
    """Calibrate every log (files, folders or glob patterns; any format the readers know), in batches of logs as tasks
    on a Dask cluster (local by default), and with --diagnose diagnose it. Per log, under DIR/<vehicle>/<log file>/:
    calibration.json, states.parquet, diagnosis.json and row.json. DIR/summary.parquet (a Parquet dataset: a folder of
    part files) and summary.csv hold one row per log (residuals, used share, verdict, estimates and standard deviations,
    undetermined directions, run time, the error of a log that failed, whether it disagrees with the rest of its
    vehicle, and the RMS magnitude and heading error of magkf's calibration and of the one the vehicle flew, read from
    the log); DIR/vehicles.png plots each vehicle's estimates over its flights. With --diagnose,
    DIR/pooled_diagnosis.json pools each vehicle's diagnoses over its flights (magkf.diagnostics.pooled): each
    candidate's combined test over the flights, its coefficient's consistency across them, and the effect recommended
    for the vehicle even when no single flight reaches significance, or the flights whose coefficient differs; one line
    per vehicle says it. A log that fails does not stop the others (exit status 2 only when every log failed). A log
    whose input and settings are unchanged since an earlier run into DIR (same content hash) and whose outputs are
    complete is not calibrated again: a run stopped part way resumes where it stopped."""
    from ..fleet import check_out_dir

    made = not Path(args.out_dir).exists()
    out_dir = check_out_dir(args.out_dir)
    with _removed_if_empty(out_dir if made else None):
        return _fleet(args, out_dir)


@contextlib.contextmanager
def _removed_if_empty(folder):
    """The ``folder`` this run made removed when the run fails before writing anything into it."""
    try:
        yield
    except BaseException:
        if folder is not None and folder.is_dir() and not any(folder.iterdir()):
            folder.rmdir()
        raise


def _fleet(args, out_dir) -> int:
    """``run_fleet`` into the checked output folder ``out_dir``."""
    from pathlib import Path

    from ..effects import make_effect
    from ..errors import InputError
    from ..fleet import FleetSettings, find_logs, improvement_lines, pooled_lines
    from ..fleet import run_fleet as run

    logs = find_logs(args.logs, exclude=out_dir)
    for path in (args.map, *args.effect_file):
        if path is not None and not Path(path).is_file():
            raise InputError("no such file", path)
    if not args.effect_file:  # a misspelt effect is refused before any log is read
        for spec in args.effect:
            make_effect(spec)
    reading = common.reading_options(args)
    settings = FleetSettings(
        config=common.filter_config(args),
        diagnose=args.diagnose,
        alpha=args.alpha,
        effects=tuple(args.effect),
        effect_files=tuple(str(Path(f).resolve()) for f in args.effect_file),
        format=args.format,
        mag=args.mag,
        **{**reading, "topic": tuple(sorted((reading["topic"] or {}).items()))},
    )
    with _client(args) as client:
        result = run(
            logs, out_dir, settings, client, vehicle_from=args.vehicle_from, alpha=args.alpha, progress=_progress(args)
        )
    n = result.counts()
    print(
        f"{n['logs']} logs of {n['vehicles']} vehicle(s): {n['logs'] - n['failed']} calibrated"
        f" ({n['reused']} unchanged since an earlier run, not calibrated again), {n['failed']} failed; "
        f"{n['flagged']} disagree with the rest of their vehicle"
    )
    failed = result.failed
    for row in failed.itertuples():
        print(f"  failed: {row.error}")
    for row in result.flagged.itertuples():
        print(f"  disagrees: {row.log}: {row.disagreement}")
    for line in improvement_lines(result.columns(["vehicle", "error", "improvement_nt", "improvement_deg"])):
        print(f"  {line}")
    for line in pooled_lines(result.pooled):
        print(f"  diagnosis pooled over the flights of {line}")
    print("  " + _memory_line(result.peak_memory_mb(), result.memory_limits))
    print(
        f"  summary: {result.files['summary_parquet']} and {result.files['summary_csv']}; plot: {result.files['plot']}"
        + (f"; pooled diagnosis: {result.files['pooled_diagnosis']}" if "pooled_diagnosis" in result.files else "")
    )
    if n["failed"] == n["logs"]:
        raise InputError(f"every log failed; the first: {failed['error'].iloc[0]}")
    return 0


def run_study(args) -> int:
    """Run a filter-tuning study: the settings of SPEC.toml (a grid, a list, a seeded random sample of FilterConfig
    fields and effects) crossed with simulated log recipes or given logs and seeds, each run a task on a Dask
    cluster (local by default). Writes DIR/runs.parquet and .csv (one row per run: final errors against truth,
    NEES, mean NIS, used share, time), DIR/summary.parquet and .csv (one row per setting, with 95 % intervals) and
    DIR/study.png (error, NEES and NIS against each setting). Seeds follow from the spec and each run's number:
    the tables do not depend on the cluster."""
    from ..fleet import check_out_dir
    from ..study import load_spec
    from ..study import run as run_spec

    spec = load_spec(args.spec)
    out_dir = check_out_dir(args.out_dir)
    print(
        f"study {spec.name}: {len(spec.settings)} settings x {spec.n_runs // len(spec.settings)} logs = "
        f"{spec.n_runs} runs"
    )
    with _client(args) as client:
        from ..cluster import memory_limits

        limits = memory_limits(client)
        result = run_spec(spec, client, progress=_progress(args))
    files = result.write(out_dir)
    runs = result.runs
    failed = runs[runs["error"] != ""]
    print(f"  {len(runs) - len(failed)} runs done, {len(failed)} failed")
    for row in failed.head(10).itertuples():
        print(f"  run {row.run} failed: {row.error}")
    print("  " + _memory_line(runs.groupby("worker")["peak_rss_mb"].max().to_dict(), limits))
    print(f"  written: {', '.join(files.values())}")
    if result.failure is not None:  # the tables say why each run failed; the exit status says that all did
        from ..errors import InputError

        raise InputError(result.failure, args.spec)
    return 0

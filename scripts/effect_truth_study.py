"""Add it and watch the error fall, judged against the truth: each built-in effect hidden in simulated logs
by a generator independent of magkf's effect classes (``tests/truth_effects.py``), diagnosed, calibrated
without an effect, with the recommended effects and with the true effect, each written calibration file
applied as ``magkf apply`` does, and the calibrated field compared with the true body field.

    python scripts/effect_truth_study.py [--seeds 3] [--minutes 10] [--rate 10] [--jobs 2] [--out DIR]

The default matrix (7 effects x 2 motions x 2 noises x 3 seeds, and 20 null logs: 104 logs of 10 minutes at
10 Hz) takes about 4 minutes with ``--jobs 2`` on two cores.

A log is magkf's simulator's (drone ``3d`` or car ``planar`` motion; white noise, or Gauss-Markov noise of
2 s with the logged yaw wandering by 0.2 deg; 30 nT noise; the simulator's six disturbances) without effects,
plus the hidden effect's contribution written from its physics and, with ``--early-disturbance on``, a
disturbance of 200 to 500 nT lasting 10 to 30 s in the first two minutes.

The truth-judged residual of a calibration file is the RMS (nT, of the vector: ``sqrt(mean |e|^2)``, as magkf
states its residuals) of ``e = field - B_true`` over the clean epochs: ``field`` the calibrated body field
``apply`` gives, ``B_true`` the true Earth field along the true attitude, the clean epochs those with status
``ok`` at least a second away from every disturbance. Its floor is the RMS of the sensor noise seen through
the true calibration, ``R^-1 n``, on the same epochs: what a perfect calibration leaves. ``B_true`` is the
reference's own field: ``apply`` takes a stored field anomaly out, so a file without it is judged with the
anomaly it leaves in. The calibration's own
error, ``e`` less the noise seen through the calibration, is reported as well (``err_*``).

"Reaching the noise level" is judged against the same log with the hidden effect taken out, calibrated without
effects (``rms_free``): with coloured noise the logged yaw wanders (a Gauss-Markov error of 60 s), and its mean
over the log is a turn of the attitude that no calibration can tell from the sensor's mounting, so even the
effect-free log's file stays above the noise floor by it (``ratio_true_noise`` gives the true effect's residual
over the bare noise floor too). The acceptance: ``rms_true <= 1.05 rms_free + tolerance_nt``.

"Needed": the file written without effects leaves more than the effect-free log's (``rms_free``) plus the
tolerance, so the core alone does not absorb the effect (a horizontal field anomaly on level motion is a turn
and scale of the horizontal field, which ``R`` holds); "missed": needed and not recommended.

"Worse" compares the file written with the recommended effects with the one written without effects: worse
when its truth-judged residual exceeds the other's by more than ``tolerance_nt`` (``rms_tolerance``), the
amount by which two RMS figures over this many epochs of this noise differ by chance at the 99 % level.

Prints the matrix per (hidden effect, motion, noise) and the false alarms on null logs against the 99 %
binomial bound of alpha; ``--out DIR`` writes ``rows.csv`` (one row a log), ``matrix.csv`` and
``summary.json``.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import stats

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from magkf.apply import apply_calibration  # noqa: E402
from magkf.calibration import Calibration  # noqa: E402
from magkf.config import FilterConfig  # noqa: E402
from magkf.diagnostics.diagnose import diagnose  # noqa: E402
from magkf.effects import make_effect  # noqa: E402
from magkf.errors import InputError  # noqa: E402
from magkf.io.drivelog import DriveLog  # noqa: E402
from magkf.online.run import calibrate_log  # noqa: E402
from magkf.plausibility import check_run, log_field_nt  # noqa: E402
from magkf.sim import DriveConfig, simulate_drive  # noqa: E402
from tests.truth_effects import EFFECT_NAMES, MAG_COLUMNS, NOISES, TRUE_PARAMETERS, TruthLog, hidden_log  # noqa: E402

MOTIONS = {"drone": "3d", "car": "planar"}
#: The one-sided 99 % normal quantile of the tolerance.
Z99 = float(stats.norm.ppf(0.99))
#: The acceptance: the true effect's truth-judged residual within this factor of the noise floor.
FLOOR_FACTOR = 1.05
NOISE_NT = 30.0


@dataclass(frozen=True)
class Case:
    """One simulated log: the hidden effects' names (empty: a null log), the motion (``3d`` or ``planar``),
    the noise (``NOISES`` key), the simulator's seed and whether a disturbance is put in the first two
    minutes."""

    hidden: tuple
    motion: str
    noise: str
    seed: int
    early: bool

    @property
    def name(self) -> str:
        return "+".join(self.hidden) or "none"


def case_log(case: Case, minutes: float, rate_hz: float) -> TruthLog:
    """The log of ``case``, ``minutes`` long at ``rate_hz``, with its truth."""
    config = DriveConfig(
        duration_s=60.0 * minutes,
        rate_hz=rate_hz,
        motion=case.motion,
        noise_nt=NOISE_NT,
        seed=case.seed,
        **NOISES[case.noise],
    )
    return hidden_log(simulate_drive(config), case.hidden, seed=case.seed, early=case.early)


def effective_epochs(n: int, rate_hz: float, correlation_s: float) -> float:
    """The number of independent epochs (float) an RMS over ``n`` epochs of Gauss-Markov noise of correlation
    time ``correlation_s`` (0: white) sampled at ``rate_hz`` is worth.

    The squares of a Gaussian AR(1) sequence of lag-one correlation ``rho`` are correlated by ``rho^(2k)`` at lag
    ``k``, so the variance of their mean is that of ``n (1 - rho^2) / (1 + rho^2)`` independent ones."""
    if correlation_s <= 0.0:
        return float(n)
    rho2 = np.exp(-2.0 / (rate_hz * correlation_s))
    return float(n * (1.0 - rho2) / (1.0 + rho2))


def rms_tolerance(floor_nt: float, n_effective: float) -> float:
    """How much (nT) two truth-judged RMS figures may differ by chance, at the one-sided 99 % level.

    An RMS ``s`` of the vector noise (three Gaussian components, ``s^2`` the mean of ``|e|^2``) over
    ``n_effective`` independent epochs has ``var(|e|^2) = 6 sigma^4`` against a mean ``3 sigma^2``, so its
    standard error is ``s / sqrt(6 n_effective)``; the difference of two has ``sqrt(2)`` times that."""
    return Z99 * np.sqrt(2.0) * floor_nt / np.sqrt(6.0 * n_effective)


def written_calibration(log: DriveLog, labels, folder: Path, tag: str):
    """The calibration file ``magkf calibrate`` writes with the effects ``labels``, saved and loaded back, or
    the reason it refuses (a str)."""
    try:
        run = calibrate_log(log, FilterConfig(), effects=[make_effect(label) for label in labels])
        check_run(run, log.source, log_field_nt(log))
    except InputError as exc:
        return f"refused: {exc.message}"
    path = folder / f"{tag}.json"
    run.calibration.save(path)
    return Calibration.load(path)


def effect_free_table(tlog: TruthLog):
    """The log's table with the hidden effects' contribution taken out of its reading (disturbances kept)."""
    table = tlog.table.copy()
    table[list(MAG_COLUMNS)] = table[list(MAG_COLUMNS)].to_numpy() - tlog.contributions
    return table


def truth_judged(tlog: TruthLog, log: DriveLog, cal) -> dict:
    """The truth-judged residual (nT) of the calibration ``cal`` on the clean epochs, the calibration's own
    error without the noise (nT), and the clean epochs' count; NaN for a refused calibration."""
    if not isinstance(cal, Calibration):
        return {"rms": float("nan"), "err": float("nan"), "n": 0}
    applied = apply_calibration(log, cal)
    use = tlog.clean & (applied["status"].to_numpy() == "ok")
    field = applied[["field_x", "field_y", "field_z"]].to_numpy()
    error = field[use] - tlog.field_body[use]
    noise_through = cal.correct(tlog.sensor_noise[use] + np.asarray(cal.b, float))  # R_hat^-1 n
    return {"rms": _rms(error), "err": _rms(error - noise_through), "n": int(use.sum())}


def _rms(vectors: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(vectors**2, axis=1)))) if len(vectors) else float("nan")


def z_scores(cal, tlog: TruthLog) -> list:
    """``(estimate - truth) / std`` of the hidden effects' parameters ``cal`` stores (those with a constant
    truth: a random walk's offsets have none)."""
    if not isinstance(cal, Calibration):
        return []
    out = []
    for name, theta in zip(tlog.hidden, tlog.thetas):
        stored = next((e for e in cal.effects if e.name == name), None)
        if stored is None or name == "bias_drift":
            continue
        values, stds = np.asarray(stored.values, float), np.asarray(stored.stds, float)
        with np.errstate(divide="ignore", invalid="ignore"):
            out.extend(((values - np.asarray(theta, float)) / stds).tolist())
    return [z for z in out if np.isfinite(z)]


def _rms_z(z: list) -> float:
    return float(np.sqrt(np.mean(np.square(z)))) if z else float("nan")


def diagnosis_row(case: Case, log: DriveLog, alpha: float) -> tuple[dict, list]:
    """The diagnosis's figures for ``case`` and the recommended labels."""
    d, _ = diagnose(log, alpha=alpha)
    hidden = {make_effect(h).label for h in case.hidden}
    recommended = [c.effect for c in d.recommended]
    top = d.candidates[0].effect if d.candidates else ""
    row = {
        "top_candidate": top,
        "recommended": ";".join(recommended),
        "ranked_first": bool(hidden) and top in hidden,
        "recommended_first": bool(recommended) and recommended[0] in hidden,
        "recommended_hidden": bool(hidden) and hidden <= set(recommended),
        "false_alarm": not hidden and bool(recommended),
    }
    return row, recommended


def run_case(case: Case, minutes: float, rate_hz: float, alpha: float) -> dict:
    """One log of the study: its diagnosis and the written calibrations judged against the truth."""
    started = time.perf_counter()
    tlog = case_log(case, minutes, rate_hz)
    log = DriveLog(tlog.table, source=f"{case.name}-{case.motion}-{case.noise}-{case.seed}")
    row = {"hidden": case.name, "motion": case.motion, "noise": case.noise, "seed": case.seed, "early": case.early}
    try:
        found, recommended = diagnosis_row(case, log, alpha)
    except InputError as exc:
        return row | {"error": f"diagnose: {exc.message}"}
    cals, judged = written_and_judged(tlog, log, recommended)
    row |= found | judgement(tlog, judged, rate_hz)
    row |= {
        "refused": ";".join(f"{k}: {c}" for k, c in cals.items() if not isinstance(c, Calibration)),
        "z_rms_true": _rms_z(z_scores(cals.get("true"), tlog)),
        "z_rms_rec": _rms_z(z_scores(cals["rec"], tlog)),
    }
    if tlog.hidden:
        row["missed"] = row["needed"] and not row["recommended_hidden"]
    return row | {"seconds": time.perf_counter() - started}


def written_and_judged(tlog: TruthLog, log: DriveLog, recommended: list) -> tuple[dict, dict]:
    """The calibration files written without effects (``none``), with the ``recommended`` labels (``rec``) and,
    with hidden effects, with the true ones (``true``); and each judged against the truth (``truth_judged``),
    with ``free`` the effect-free log's file."""
    true_labels = [make_effect(h).label for h in tlog.hidden]
    with tempfile.TemporaryDirectory() as name:
        folder = Path(name)
        cals = {"none": written_calibration(log, [], folder, "none")}
        cals["rec"] = written_calibration(log, recommended, folder, "rec") if recommended else cals["none"]
        if true_labels:
            cals["true"] = written_calibration(log, true_labels, folder, "true")
        judged = {k: truth_judged(tlog, log, c) for k, c in cals.items()}
        if true_labels:  # the same log with the hidden effects taken out, calibrated as it is
            free = DriveLog(effect_free_table(tlog), source=f"{log.source}-effect-free")
            judged["free"] = truth_judged(tlog, free, written_calibration(free, [], folder, "free"))
    return cals, judged


def judgement(tlog: TruthLog, judged: dict, rate_hz: float) -> dict:
    """The truth-judged figures of a log: the noise floor and the tolerance (nT), each file's residual and
    error, worse, and with hidden effects the true effect's ratios and whether the effect is needed."""
    floor = _rms(tlog.sensor_noise[tlog.clean] @ np.linalg.inv(tlog.R).T)
    tolerance = rms_tolerance(floor, effective_epochs(int(tlog.clean.sum()), rate_hz, tlog.noise_correlation_s))
    out = {
        "n_clean": judged["none"]["n"],
        "floor_nt": floor,
        "tolerance_nt": tolerance,
        **{f"rms_{k}": v["rms"] for k, v in judged.items()},
        **{f"err_{k}": v["err"] for k, v in judged.items()},
        "worse": bool(judged["rec"]["rms"] > judged["none"]["rms"] + tolerance),
    }
    if "true" in judged:
        out["ratio_true"] = judged["true"]["rms"] / judged["free"]["rms"]
        out["ratio_true_noise"] = judged["true"]["rms"] / floor
        out["needed"] = bool(judged["none"]["rms"] > judged["free"]["rms"] + tolerance)
        out["true_reaches"] = bool(judged["true"]["rms"] <= FLOOR_FACTOR * judged["free"]["rms"] + tolerance)
    return out


def cases(args) -> list:
    """The study's logs: each hidden effect (or combination) on each motion and noise for ``args.seeds``
    seeds, and ``args.null_seeds`` null logs per motion and noise."""
    early = {"on": (True,), "off": (False,), "both": (False, True)}[args.early_disturbance]
    motions = [MOTIONS.get(m, m) for m in (args.motion or MOTIONS)]
    out = []
    for motion in motions:
        for noise in args.noise or NOISES:
            for e in early:
                out += [Case((), motion, noise, 5000 + s, e) for s in range(args.null_seeds)]
                for spec in args.hidden or EFFECT_NAMES:
                    out += [Case(tuple(spec.split("+")), motion, noise, 1000 + s, e) for s in range(args.seeds)]
    return out


def run_all(todo: list, minutes: float, rate_hz: float, alpha: float, jobs: int, say=print) -> list:
    """Every case of ``todo``, on ``jobs`` processes; ``say`` is told each finished log."""
    rows = []
    if jobs <= 1:
        results = (run_case(c, minutes, rate_hz, alpha) for c in todo)
        for row in results:
            rows.append(row)
            say(_progress(row, len(rows), len(todo)))
        return rows
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        futures = [pool.submit(run_case, c, minutes, rate_hz, alpha) for c in todo]
        for f in futures:
            rows.append(f.result())
            say(_progress(rows[-1], len(rows), len(todo)))
    return rows


def _progress(row: dict, done: int, total: int) -> str:
    key = f"{row['hidden']} {row['motion']} {row['noise']} seed {row['seed']}{' early' if row['early'] else ''}"
    if "error" in row:
        return f"[{done}/{total}] {key}: {row['error']}"
    figures = " ".join(f"{k} {row[f'rms_{k}']:.1f}" for k in ("none", "rec", "true") if f"rms_{k}" in row)
    return (
        f"[{done}/{total}] {key}: floor {row['floor_nt']:.1f} {figures} nT; recommended [{row['recommended']}]"
        f"{' WORSE' if row['worse'] else ''}{' REFUSED ' + row['refused'][:100] if row['refused'] else ''} "
        f"({row['seconds']:.1f} s)"
    )


#: Counts of ``matrix``: its key, and the row's flag counted.
COUNTED = {
    "ranked_first": "ranked_first",
    "recommended": "recommended_hidden",
    "recommended_first": "recommended_first",
    "needed": "needed",
    "missed": "missed",
    "worse": "worse",
    "refused": "refused",
    "true_within_5pct": "true_reaches",
}
#: Medians of ``matrix``: its key, and the row's figure (NaN, a refused file's, left out).
MEDIANS = {
    "median_rms_none": "rms_none",
    "median_rms_rec": "rms_rec",
    "median_rms_true": "rms_true",
    "median_rms_free": "rms_free",
    "median_floor": "floor_nt",
    "median_ratio_true": "ratio_true",
    "median_ratio_true_noise": "ratio_true_noise",
    "median_z_rms_true": "z_rms_true",
}


def matrix(rows: list) -> list:
    """One summary a (hidden effect, motion, noise): counts (``COUNTED``) and medians (``MEDIANS``) over its
    logs, and the largest ratio of the true effect's residual to the effect-free one's."""
    groups = {}
    for row in rows:
        if row["hidden"] != "none":
            groups.setdefault((row["hidden"], row["motion"], row["noise"]), []).append(row)
    out = []
    for (hidden, motion, noise), group in groups.items():
        ok = [r for r in group if "error" not in r]
        ratios = _finite(ok, "ratio_true")
        out.append(
            {"hidden": hidden, "motion": motion, "noise": noise, "logs": len(group), "errors": len(group) - len(ok)}
            | {key: sum(bool(r[flag]) for r in ok) for key, flag in COUNTED.items()}
            | {key: float(np.median(_finite(ok, k))) if _finite(ok, k).size else np.nan for key, k in MEDIANS.items()}
            | {"max_ratio_true": float(ratios.max()) if ratios.size else np.nan}
        )
    return out


def _finite(rows: list, key: str) -> np.ndarray:
    values = np.array([r[key] for r in rows], float)
    return values[np.isfinite(values)]


def null_summary(rows: list, alpha: float) -> dict:
    """False alarms on the null logs against the 99 % binomial bound of ``alpha``, and the worse count there."""
    null = [r for r in rows if r["hidden"] == "none" and "error" not in r]
    return {
        "logs": len(null),
        "false_alarms": sum(r["false_alarm"] for r in null),
        "bound_99": int(stats.binom.ppf(0.99, len(null), alpha)) if null else 0,
        "worse": sum(r["worse"] for r in null),
        "alpha": alpha,
    }


def acceptance(rows: list) -> dict:
    """The issue's acceptance over the logs with a hidden effect: shares first-and-recommended, never worse,
    and the true effect within 5 % of the floor; with the 99 % Clopper-Pearson lower bound of the first."""
    hid = [r for r in rows if r["hidden"] != "none" and "error" not in r]
    n = len(hid)
    found = sum(r["ranked_first"] and r["recommended_hidden"] for r in hid)
    lower = float(stats.beta.ppf(0.01, found, n - found + 1)) if found else 0.0
    return {
        "logs": n,
        "first_and_recommended": found,
        "first_and_recommended_lower_99": lower,
        "needed": sum(r["needed"] for r in hid),
        "missed": sum(r["missed"] for r in hid),
        "worse": sum(r["worse"] for r in hid),
        "refused": sum(bool(r.get("refused")) for r in hid),
        "true_within_5pct": sum(r["true_reaches"] for r in hid),
        "errors": sum("error" in r for r in rows),
    }


#: The printed matrix: heading, key of ``matrix``'s rows, format.
MATRIX_COLUMNS = (
    ("hidden", "hidden", "18s"),
    ("motion", "motion", "6s"),
    ("noise", "noise", "8s"),
    ("logs", "logs", "4d"),
    ("first", "ranked_first", "5d"),
    ("rec", "recommended", "4d"),
    ("need", "needed", "4d"),
    ("miss", "missed", "4d"),
    ("worse", "worse", "5d"),
    ("refus", "refused", "5d"),
    ("none", "median_rms_none", "7.1f"),
    ("rec", "median_rms_rec", "7.1f"),
    ("true", "median_rms_true", "7.1f"),
    ("free", "median_rms_free", "7.1f"),
    ("noise", "median_floor", "6.1f"),
    ("true/free", "median_ratio_true", "9.3f"),
    ("max", "max_ratio_true", "6.3f"),
    ("<=1.05", "true_within_5pct", "6d"),
    ("true/noise", "median_ratio_true_noise", "10.3f"),
    ("RMS z", "median_z_rms_true", "6.2f"),
)


def print_report(rows: list, alpha: float) -> None:
    """The matrix (medians of the truth-judged residuals in nT), the null logs' false alarms and the acceptance."""
    width = [int(fmt.rstrip("sdf").split(".")[0]) for _, _, fmt in MATRIX_COLUMNS]
    print(" ".join(f"{h:{'<' if f.endswith('s') else '>'}{w}s}" for (h, _, f), w in zip(MATRIX_COLUMNS, width)))
    for m in matrix(rows):
        print(" ".join(f"{m[key]:{fmt}}" for _, key, fmt in MATRIX_COLUMNS))
    n = null_summary(rows, alpha)
    print(
        f"null logs: false alarms {n['false_alarms']} of {n['logs']} (99 % binomial bound of alpha {alpha:g}: "
        f"{n['bound_99']}); written with the recommended effect worse than without: {n['worse']}"
    )
    a = acceptance(rows)
    print(
        f"hidden effect ranked first and recommended in {a['first_and_recommended']} of {a['logs']} logs "
        f"(99 % lower bound {a['first_and_recommended_lower_99']:.3f}); missed where needed in {a['missed']} of "
        f"{a['needed']}; worse than without in {a['worse']}; "
        f"a calibration refused in {a['refused']}; "
        f"true effect within 5 % of the floor in {a['true_within_5pct']}; errors {a['errors']}"
    )


def write_results(folder: Path, rows: list, alpha: float) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for name, table in (("rows.csv", rows), ("matrix.csv", matrix(rows))):
        keys = list(dict.fromkeys(k for r in table for k in r))
        with open(folder / name, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=keys)
            writer.writeheader()
            writer.writerows(table)
    summary = {"null": null_summary(rows, alpha), "acceptance": acceptance(rows), "matrix": matrix(rows)}
    (folder / "summary.json").write_text(json.dumps(summary, indent=2, default=float) + "\n")


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=3, help="logs per hidden effect, motion and noise")
    p.add_argument("--null-seeds", type=int, default=5, help="null logs per motion and noise")
    p.add_argument("--minutes", type=float, default=10.0)
    p.add_argument("--rate", type=float, default=10.0, help="Hz")
    p.add_argument("--alpha", type=float, default=0.01)
    p.add_argument("--motion", choices=sorted(MOTIONS), action="append", help="default: each")
    p.add_argument("--noise", choices=sorted(NOISES), action="append", help="default: each")
    p.add_argument(
        "--hidden",
        action="append",
        help=f"an effect, or effects joined by + (default: each of {', '.join(EFFECT_NAMES)})",
    )
    p.add_argument("--early-disturbance", choices=("on", "off", "both"), default="on")
    p.add_argument("--jobs", type=int, default=1)
    p.add_argument("--out", type=Path, help="folder for rows.csv, matrix.csv and summary.json")
    return p


def main(argv=None) -> None:
    args = parser().parse_args(argv)
    for spec in args.hidden or []:
        unknown = [h for h in spec.split("+") if h not in TRUE_PARAMETERS]
        if unknown:
            parser().error(f"unknown effect {', '.join(unknown)}; known: {', '.join(EFFECT_NAMES)}")
    todo = cases(args)
    started = time.perf_counter()
    rows = run_all(todo, args.minutes, args.rate, args.alpha, args.jobs, say=lambda s: print(s, flush=True))
    print(f"\n{len(rows)} logs of {args.minutes:g} min at {args.rate:g} Hz in {time.perf_counter() - started:.0f} s\n")
    print_report(rows, args.alpha)
    if args.out:
        write_results(args.out, rows, args.alpha)


if __name__ == "__main__":
    main()

"""The diagnosis pooled over a vehicle's flights (``magkf.diagnostics.pooled``), on synthetic candidates whose
statistics have a known distribution (seeded).

Each synthetic flight's candidate is made as the correlation-robust test makes it: an estimate ``x ~ N(theta,
s^2 I)`` (q,) and a covariance estimated from ``K`` independent terms, ``S = s^2 W / K`` with ``W`` a Wishart
of ``K`` degrees of freedom; its ``F = x^T S^-1 x (K - q + 1) / (K q)`` follows Hotelling's noncentral
``F(q, K - q + 1, lambda)``, ``lambda = |theta|^2 / s^2``, and its reported standard deviations are
``sqrt(diag S)``."""

import json

import numpy as np
import pytest
from scipy import signal, stats

from magkf.calibration import jsonable
from magkf.diagnostics.diagnose import Candidate, Diagnosis
from magkf.diagnostics.pooled import combined_test, consistency, pool
from magkf.errors import InputError

ALPHA = 0.01
#: Parameters of the synthetic effect, cosine terms of each flight's covariance (the ``K`` of the robust test
#: on a few minutes of log: 35 to 46 on the simulated logs of ``tests/integration``), candidates a flight tests.
Q, K, M = 3, 40, 3
#: One-sided chance, per assertion, that a Monte Carlo rate falls outside its binomial band by chance.
TAIL = 1e-3


def _candidate(rng, theta, name="temperature_bias", s=1.0) -> Candidate:
    """One flight's candidate with true coefficients ``theta`` (q,) and standard deviation ``s`` each."""
    q = len(theta)
    x = np.asarray(theta, float) + s * rng.normal(size=q)
    z = rng.normal(size=(K, q))
    cov = s**2 * (z.T @ z) / K
    F = float(x @ np.linalg.solve(cov, x) * (K - q + 1) / (K * q))
    p = float(stats.f.sf(F, q, K - q + 1))
    estimate = {f"k_{j}": {"value": float(x[j]), "std": float(np.sqrt(cov[j, j]))} for j in range(q)}
    return Candidate(name, F, q, K - q + 1, p, K, 1.0, 30.0, 30.0, p < ALPHA / M, estimate)


def _fleet(rng, thetas) -> dict:
    """Flight name -> diagnosis summary: the effect with ``thetas[i]`` in flight i, and ``M - 1`` null candidates."""
    out = {}
    for i, theta in enumerate(thetas):
        found = [_candidate(rng, theta)] + [_candidate(rng, np.zeros(Q), f"null_{j}") for j in range(M - 1)]
        out[f"flight{i}"] = {"alpha": ALPHA, "level": ALPHA / M, "candidates": [c.as_dict() for c in found]}
    return out


def _effect(pooled, name="temperature_bias"):
    return next(c for c in pooled.candidates if c.effect == name)


def _band(n: int, p: float) -> tuple[int, int]:
    """The counts of ``n`` Bernoulli(p) trials outside which a count falls with probability below ``TAIL`` a side."""
    return int(stats.binom.ppf(TAIL, n, p)), int(stats.binom.isf(TAIL, n, p))


def derived_power(k: int, lam: float, level: float, flight_level: float | None = None, dy: float = 0.01) -> float:
    """The probability that Lancaster's combination of ``k`` flights, each an F test ``F(Q, K - Q + 1)`` of
    noncentrality ``lam``, is below ``level``; with ``flight_level``, given that no flight is below it alone.

    Each flight contributes ``Y = chi2.isf(p, Q)``, whose distribution function is ``P(Y <= y) =
    ncf.cdf(f.isf(chi2.sf(y, Q)))``: tabulated on a grid of ``dy``, truncated to ``Y < chi2.isf(flight_level, Q)``
    when conditioned, and convolved ``k`` times; the power is the mass of the sum beyond ``chi2.isf(level, k Q)``.
    The grid's error is below ``k dy`` in the sum (a few thousandths of the power here)."""
    d = K - Q + 1
    edges = np.arange(0.0, 150.0 + dy, dy)
    cdf = stats.ncf.cdf(stats.f.isf(stats.chi2.sf(edges, Q), Q, d), Q, d, lam)
    pmf = np.diff(cdf)
    pmf[-1] += 1.0 - cdf[-1]
    if flight_level is not None:
        pmf[edges[1:] > stats.chi2.isf(flight_level, Q)] = 0.0
    pmf /= pmf.sum()
    total = pmf
    for _ in range(k - 1):
        total = np.clip(signal.fftconvolve(total, pmf), 0.0, None)
    centres = (np.arange(len(total)) + k / 2) * dy  # the sum of k bin centres
    return float(total[centres > stats.chi2.isf(level, k * Q)].sum())


@pytest.mark.parametrize("k", [4, 8])
def test_combined_test_keeps_its_level_under_the_null(k):
    """20 000 null fleets of ``k`` flights whose tests have mixed degrees of freedom (1, 3, 9 parameters, robust
    denominators of 4 to 60): the share with a combined p below 0.05 and below ``alpha / 7`` lies within the
    two-sided binomial band of that level (each side ``TAIL``)."""
    rng = np.random.default_rng(11 + k)
    n = 20_000
    q = np.resize([1, 3, 9], k)
    d = rng.integers(4, 61, size=(n, k))
    p = stats.f.sf(stats.f.rvs(q, d, size=(n, k), random_state=rng), q, d)
    _, dof, combined = combined_test(p, q)
    assert np.all(dof == q.sum())
    for level in (0.05, ALPHA / 7):
        lo, hi = _band(n, level)
        assert lo <= np.sum(combined < level) <= hi, (level, np.sum(combined < level), lo, hi)


def test_whole_decision_false_alarm_rate_at_most_alpha():
    """150 null fleets of 4 to 8 flights, three candidates each: the share with any candidate recommended for the
    vehicle is within the binomial bound of ``alpha`` (Bonferroni over the candidates keeps it below alpha);
    measured 0 of 150 (bound 6)."""
    rng = np.random.default_rng(21)
    n = 150
    alarms = sum(bool(pool(_fleet(rng, [np.zeros(Q)] * int(rng.integers(4, 9)))).recommended) for _ in range(n))
    assert alarms <= _band(n, ALPHA)[1]


@pytest.mark.parametrize(("k", "lam"), [(4, 8.0), (8, 6.0)])
def test_derived_power_is_the_monte_carlo_power(k, lam):
    """``derived_power`` against 4 000 fleets whose flights' F are drawn from the noncentral F: the combined
    test's rejections, and among the fleets where no flight is significant alone the rejections given that,
    lie within the two-sided binomial bands of the derived figures."""
    rng = np.random.default_rng(31 + k)
    n, d, level = 4_000, K - Q + 1, ALPHA / M
    p = stats.f.sf(stats.ncf.rvs(Q, d, lam, size=(n, k), random_state=rng), Q, d)
    hits = combined_test(p, Q)[2] < level
    lo, hi = _band(n, derived_power(k, lam, level))
    assert lo <= hits.sum() <= hi
    quiet = np.all(p >= level, axis=1)
    lo, hi = _band(int(quiet.sum()), derived_power(k, lam, level, level))
    assert lo <= hits[quiet].sum() <= hi


def test_small_effect_in_every_flight_is_recommended_for_the_vehicle():
    """An effect of noncentrality 8 in each of 6 flights: significant alone in about 21 % of flights (the single
    flight's power at ``alpha / 3``), yet recommended for the vehicle with probability at least ``derived_power
    - 2 alpha - (M - 1) alpha / M`` (the combined test's power, less the chance of calling shared coefficients
    inconsistent, at most ``2 alpha`` by Bonferroni over Welch's Q and the flights' z, less the chance that a null
    candidate ranks first). The same bound, with the conditional power, holds among the fleets where *no* flight
    is significant alone. 150 fleets; each count must reach the lower binomial quantile of its bound."""
    rng = np.random.default_rng(41)
    n, k, lam, level = 150, 6, 8.0, ALPHA / M
    theta = np.full(Q, np.sqrt(lam / Q))
    slack = 2 * ALPHA + (M - 1) * level
    results = [_effect(pool(_fleet(rng, [theta] * k))) for _ in range(n)]
    recommended = np.array([c.verdict == "recommended" for c in results])
    alone = np.array([len(c.alone) for c in results])
    single = 1.0 - stats.ncf.cdf(stats.f.isf(level, Q, K - Q + 1), Q, K - Q + 1, lam)
    lo, hi = _band(n * k, single)
    assert lo <= alone.sum() <= hi
    assert recommended.sum() >= _band(n, derived_power(k, lam, level) - slack)[0]
    quiet = alone == 0
    assert quiet.sum() >= 10
    assert recommended[quiet].sum() >= _band(int(quiet.sum()), derived_power(k, lam, level, level) - slack)[0]


def test_heterogeneity_names_the_flight_far_off():
    """Five flights share a coefficient but flight 2's first parameter is 10 standard deviations off. Its ``z``
    has mean ``10 sqrt(1 - 1/5) = 8.9`` against a limit of 3.8 (t of 40 dof at ``alpha / 15``, two-sided); taking
    4.5 to allow for the spread of the estimated standard deviations, it is named first with probability at
    least ``P(N(8.9, 1) > 4.5)`` in each of 200 vehicles, and the count must reach that binomial's lower
    quantile. With every flight alike, a vehicle is called inconsistent in at most the binomial bound of
    ``2 alpha`` (Welch's Q at alpha, the flights' z at alpha)."""
    rng = np.random.default_rng(51)
    n, theta = 200, np.ones(Q)
    off = np.array([10.0, 0.0, 0.0])

    def judged(shifted: bool):
        flights = {f"flight{i}": _candidate(rng, theta + (off if shifted and i == 2 else 0.0)) for i in range(5)}
        return consistency({f: c.estimate for f, c in flights.items()}, ALPHA, {f: c.terms for f, c in flights.items()})

    named = sum(judged(True).disagreeing[:1] == ("flight2",) for _ in range(n))
    assert named >= _band(n, 1.0 - stats.norm.sf(10 * np.sqrt(0.8) - 4.5))[0]
    called = sum(judged(False).consistent is False for _ in range(n))
    assert called <= _band(n, 2 * ALPHA)[1]


def test_significant_but_inconsistent_is_reported_not_recommended():
    """A large effect in four flights, one of them with the opposite sign: significant combined, reported as
    differing between flights with that flight named, and not recommended."""
    rng = np.random.default_rng(61)
    thetas = [np.full(Q, 6.0)] * 3 + [np.full(Q, -6.0)]
    pooled = pool(_fleet(rng, thetas))
    c = _effect(pooled)
    assert c.significant and c.verdict == "differs between flights" and c.consistency.disagreeing[0] == "flight3"
    assert not pooled.recommended and "temperature_bias differs between flights: flight3" in pooled.text
    assert "differs between flights (flight3" in c.words()


def _diagnosis(candidates, alpha=ALPHA) -> Diagnosis:
    tested = sum(np.isfinite(c.statistic) for c in candidates)
    return Diagnosis(1.0, {}, 100, alpha, list(candidates), [], [], "", n_tested=tested, level=alpha / max(tested, 1))


def test_missing_and_untested_flights_and_a_wandering_effect():
    """A candidate absent from one flight's diagnosis (its channel missing) and not testable in another is pooled
    over the flight that tested it, and the words say which; a wandering effect (Nyblom's L) is pooled by its
    test alone; Diagnosis objects and their JSON summaries pool alike."""
    rng = np.random.default_rng(71)
    strong = np.full(Q, 5.0)
    drift = Candidate("bias_drift", 2.0, 3, 9, 1e-4, 9, 1.0, 30.0, 30.0, True, {}, "", "L")
    untestable = Candidate(
        "current_field:current_a", np.nan, 3, 0, 1.0, 0, np.nan, 30.0, 30.0, False, {}, "not testable"
    )
    flights = {
        "A": _diagnosis([_candidate(rng, strong), _candidate(rng, strong, "current_field:current_a"), drift]),
        "B": _diagnosis([_candidate(rng, strong), untestable, drift]),
        "C": _diagnosis([_candidate(rng, strong), drift]),
    }
    pooled = pool(flights)
    current = _effect(pooled, "current_field:current_a")
    assert current.flights == ("A",) and current.missing == ("C",) and "B" in current.untested
    assert "not in the diagnosis of C" in current.words() and "not tested in B" in current.words()
    assert current.consistent is None  # one flight: nothing to compare
    wander = _effect(pooled, "bias_drift")
    assert wander.consistency is None and wander.significant and wander.dof == 9
    assert pooled.recommended[0].effect == "temperature_bias"
    assert pooled.n_tested == 3 and pooled.level == pytest.approx(ALPHA / 3)
    as_json = {f: json.loads(json.dumps(jsonable(d.summary()))) for f, d in flights.items()}
    assert json.dumps(jsonable(pool(as_json).summary())) == json.dumps(jsonable(pooled.summary()))


def test_bad_input():
    with pytest.raises(InputError, match="no diagnosis"):
        pool({})
    with pytest.raises(InputError, match="alpha"):
        pool({"A": _diagnosis([])}, alpha=1.5)


def test_held_out_ratio_is_reported_not_decisive():
    """A consistent effect whose held-out residual (30 nT) is above each flight's model's (29 nT), as for an
    effect fitted to one short flight: the mean ratio is reported, the recommendation rests on the combined
    test and the consistency."""
    rng = np.random.default_rng(81)
    fleet = _fleet(rng, [np.full(Q, 5.0)] * 4)
    for summary in fleet.values():
        summary["residual_rms_held_out_nt"] = 29.0
    c = _effect(pool(fleet))
    assert c.held_out_ratio == pytest.approx(30.0 / 29.0) and c.as_dict()["held_out_ratio"] == c.held_out_ratio
    assert c.verdict == "recommended" and "held-out residual 103.4 %" in c.words()


def test_fleet_pools_each_vehicles_diagnosis_files(tmp_path):
    """``magkf.fleet.pooled_diagnoses`` reads each calibrated log's ``diagnosis.json`` and pools them per vehicle
    (a failed log left out); a vehicle whose file cannot be pooled is left out with a warning naming the file."""
    import pandas as pd

    from magkf.fleet import DIAGNOSIS, pooled_diagnoses

    rng = np.random.default_rng(91)
    rows = []
    for vehicle, thetas in (("V1", [np.full(Q, 5.0)] * 3), ("V2", [np.zeros(Q)] * 3)):
        for name, summary in _fleet(rng, thetas).items():
            folder = tmp_path / vehicle / name
            folder.mkdir(parents=True)
            (folder / DIAGNOSIS).write_text(json.dumps(summary))
            rows.append({"vehicle": vehicle, "output": str(folder), "error": "", "log": f"{name}.csv"})
    rows.append({"vehicle": "V1", "output": str(tmp_path / "nowhere"), "error": "x.csv: unreadable", "log": "x.csv"})
    summary = pd.DataFrame(rows)
    pooled = pooled_diagnoses(summary, ALPHA)
    assert sorted(pooled) == ["V1", "V2"] and pooled["V1"].flights == ("flight0", "flight1", "flight2")
    assert pooled["V1"].recommended[0].effect == "temperature_bias"
    (tmp_path / "V2" / "flight1" / DIAGNOSIS).write_text('{"alpha": 0.01, "candidates": [{"effect": "x"}]}')
    with pytest.warns(UserWarning, match=r"V2: its diagnoses are not pooled: .*flight1.*lacks statistic"):
        assert sorted(pooled_diagnoses(summary, ALPHA)) == ["V1"]

"""One vehicle's flights diagnosed together: each candidate effect's evidence pooled over the flights.

A small effect that every flight carries (a temperature coefficient of the vehicle's wiring) may miss the
single-flight level in each flight and still be certain over four of them. ``pool`` takes the diagnoses of
several flights of *one* vehicle (``magkf.diagnostics.diagnose.Diagnosis``, or its ``summary()`` as
``diagnosis.json`` holds it) and, for each candidate:

* **A combined test.** The flights are independent, and each flight's test gives a p-value that is uniform
  under the null. Each p-value is turned into the chi-square value of its own degrees of freedom that has
  that p-value, ``chi2.isf(p_i, q_i)``, and these are summed and referred to ``chi2(sum q_i)``: Lancaster's
  (1961) generalisation of Fisher's method, exact under the null whatever each flight's test was (the
  correlation-robust F of a value, Nyblom's constancy statistic of a wandering effect). Why this one: for
  a large denominator ``q_i F_i`` is a chi-square of noncentrality ``lambda_i``, and the derivative of the
  log of the noncentral chi-square density at ``lambda = 0`` is ``(x / q - 1) / 2``: for an effect small in
  every flight the sum of the chi-square values is the locally most powerful combination (a score test),
  and it weighs each flight's test by its degrees of freedom. Measured on 40 000 synthetic fleets each
  (``F(3, 37)`` tests, level 0.01 / 7): with the same noncentrality in every flight Stouffer's sum of normal
  quantiles has 1 to 2 points more power (0.77 against 0.75, four flights of noncentrality 8); with the
  noncentrality spread by +-70 % to +-95 % about its mean, as flights of different lengths and excitation
  give, Lancaster's has 1.5 to 5.5 points more (0.73 against 0.68); Fisher's lies between or below both
  (Loughin 2004 compares these combining functions at length). The level is corrected for the candidates
  tested, as ``diagnose`` does: ``alpha / m``, ``m`` the candidates tested in at least one flight
  (Bonferroni).
* **The coefficient's consistency.** The flights' estimates of each parameter (with the correlation-robust
  standard deviations of ``Candidate.estimate``) give the inverse-variance pooled estimate and Cochran's
  ``Q``, a chi-square of ``k - 1`` degrees of freedom when the flights share one coefficient and their
  standard deviations are exact; they are estimated from ``K`` cosine terms (``Candidate.terms``), so ``Q``
  is judged as Welch (1951) judges means of unequal, estimated variances. The effect is called inconsistent
  when the smallest of its parameters' p-values times their number is below ``alpha`` (Bonferroni over
  parameters), or when a flight's ``z`` (its estimate less the pooled one, over ``sqrt(s_i^2 - 1 /
  sum(w))``, which equals its distance from the mean of the *other* flights in their joint standard
  deviation), referred to Student's t of its ``K``, is beyond the two-sided level ``alpha`` shared among all
  the ``z``: so a vehicle whose flights share the coefficient is called inconsistent with probability at most
  about ``2 alpha``. Estimates with directions held at their prior (``diagnose`` notes "not determined") are
  the effect's part in the directions that flight determines, which differs between flights: they are left
  out of the consistency check. A wandering effect (``bias_drift``) has no estimate and is pooled by its test
  alone.
* **The recommendation for the vehicle.** An effect significant in the combined test and not found
  inconsistent is recommended, even when no single flight reaches significance: the one of lowest combined
  p-value; the others are "significant too", to be tested again with it in the model (the per-flight tests
  are each made without it, so two collinear effects, such as a temperature offset and a temperature scale,
  are both significant for the same cause). A significant effect whose coefficient differs between flights
  is reported so, naming the flights, and not recommended. Each flight's held-out residual with the effect
  (``held_out_ratio``, its mean ratio to the model's) is reported but does not decide: it measures the
  effect fitted to that one flight, whose estimate is several times less certain than the pooled one, and
  for an effect that only the pooled flights determine it hovers at 1 (required below 1, it cut the
  vehicles recommended a 0.6 nT/C temperature offset from 48 to 17 of 80; see docs/diagnosis.md).

Each flight's candidate is taken as its diagnosis reports it: after the effects that flight took into its
model. A candidate a flight did not test (a channel it needs is absent there, or its residual's correlation
left too few stretches) is pooled over the flights that tested it, and the result says which did not.

References: H. O. Lancaster, "The combination of probabilities: an application of orthonormal functions",
*Australian Journal of Statistics* 3 (1961) 20-33; T. M. Loughin, "A systematic comparison of methods for
combining p-values from independent tests", *Computational Statistics & Data Analysis* 47 (2004) 467-485;
W. G. Cochran, "The combination of estimates from different experiments", *Biometrics* 10 (1954) 101-129;
B. L. Welch, "On the comparison of several mean values: an alternative approach", *Biometrika* 38 (1951)
330-336.
"""

from __future__ import annotations

from dataclasses import MISSING, dataclass, fields, replace

import numpy as np
from scipy import special

from ..errors import InputError
from .diagnose import TESTS, Candidate

__all__ = ["PooledCandidate", "PooledDiagnosis", "candidates_of", "combined_test", "consistency", "pool"]

#: The smallest p-value turned into a chi-square value (a smaller one, or 0 from underflow, counts as this).
SMALLEST_P = 1e-300
#: What a flight's candidate note says when some directions of its parameters were held at their prior.
HELD = "not determined"


def candidates_of(diagnosis) -> tuple[list[Candidate], float, float]:
    """The candidates of a ``Diagnosis`` or of its ``summary()`` (``diagnosis.json``), that flight's level (the
    p-value below which a candidate is significant there) and its model's held-out residual RMS, nT."""
    if isinstance(diagnosis, dict):
        found = [_candidate(c) for c in diagnosis.get("candidates", [])]
        level, held_out = diagnosis.get("level"), diagnosis.get("residual_rms_held_out_nt")
        return found, _number(level), _number(held_out)
    return list(diagnosis.candidates), float(diagnosis.level), float(diagnosis.residual_rms_held_out_nt)


#: The fields a candidate of a diagnosis summary must have.
REQUIRED = tuple(f.name for f in fields(Candidate) if f.default is MISSING and f.default_factory is MISSING)


def _candidate(c: dict) -> Candidate:
    """A ``Candidate`` from its ``as_dict()`` (the test named in words, a NaN statistic as null)."""
    tests = {text: key for key, text in TESTS.items()}
    kept = {f.name: c[f.name] for f in fields(Candidate) if f.name in c}
    kept["test"] = tests.get(c.get("test"), c.get("test", "F"))
    if kept.get("statistic", 0.0) is None:
        kept["statistic"] = np.nan
    lacking = [name for name in REQUIRED if name not in kept]
    if lacking:
        raise InputError(f"a candidate of the diagnosis lacks {', '.join(lacking)}: diagnose the log again")
    return Candidate(**kept)


def _number(value) -> float:
    """A JSON number, NaN for null."""
    return float("nan") if value is None else float(value)


def _tested(c: Candidate) -> bool:
    return np.isfinite(c.statistic) and np.isfinite(c.p_value) and c.dof > 0


def combined_test(p_values, dofs) -> tuple[float, int, float]:
    """Lancaster's combination of independent tests: ``(statistic, dof, p)``, the sum of ``chi2.isf(p_i, q_i)``
    over the tests' p-values ``p_values`` (..., k) with their degrees of freedom ``dofs`` (..., k), its degrees
    of freedom ``sum q_i`` and its p-value under ``chi2(sum q_i)``, each of shape (...) (many sets of tests at
    once along the leading axes)."""
    p = np.clip(np.asarray(p_values, float), SMALLEST_P, 1.0)
    q = np.broadcast_to(np.asarray(dofs, int), p.shape)
    statistic = np.sum(special.chdtri(q, p), axis=-1)
    dof = np.sum(q, axis=-1)
    return statistic, dof, special.chdtrc(dof, statistic)


@dataclass(frozen=True)
class Consistency:
    """Whether the flights share one coefficient (``consistency``): ``estimate`` the pooled value and standard
    deviation of each parameter with Cochran's ``Q``, Welch's ``F`` from it, their degrees of freedom and
    p-value; ``p_value`` the smallest of those times their number (Bonferroni); ``z`` each flight's largest
    ``|z|`` and ``flight_p`` its smallest two-sided p-value; ``flight_level`` the p-value below which a flight
    disagrees; ``disagreeing`` those flights, largest ``|z|`` first; ``consistent`` None when it could not be
    judged (fewer than two flights with determined estimates: ``note`` says why)."""

    estimate: dict
    p_value: float
    z: dict
    flight_p: dict
    flight_level: float
    disagreeing: tuple
    consistent: bool | None
    note: str = ""


def consistency(estimates: dict, alpha: float, dofs: dict | None = None) -> Consistency:
    """Cochran's test of the flights' estimates ``{flight: {parameter: {"value", "std"}}}`` sharing one value per
    parameter, at level ``alpha``; ``dofs`` ``{flight: degrees of freedom}`` of each flight's standard deviations
    (missing or None: known exactly).

    A standard deviation estimated from ``d`` independent stretches makes ``Q`` and the ``z`` larger than their
    normal theory says. ``Q`` is therefore judged as Welch (1951) does, ``Q / (k - 1) / (1 + 2 (k - 2) A /
    (k^2 - 1))`` against ``F(k - 1, (k^2 - 1) / (3 A))`` with ``A = sum (1 - w_i / W)^2 / d_i``, and a flight's
    ``z`` against Student's t of its own ``d``. A flight disagrees when a ``z`` of its is beyond the two-sided
    level ``alpha`` shared among all the ``z`` (Bonferroni)."""
    names = list(dict.fromkeys(n for e in estimates.values() for n in e))
    per = {n: _parameter(n, estimates, dofs or {}) for n in names}
    per = {n: v for n, v in per.items() if v is not None}
    if not per:
        return Consistency({}, float("nan"), {}, {}, float("nan"), (), None, "fewer than two flights estimate it")
    flight_level = alpha / sum(len(v["z"]) for v in per.values())
    p = min(1.0, len(per) * min(v["p_value"] for v in per.values()))
    z, flight_p = {}, {}
    for v in per.values():
        for flight, (value, pz) in v.pop("z").items():
            z[flight] = max(z.get(flight, 0.0), abs(value))
            flight_p[flight] = min(flight_p.get(flight, 1.0), pz)
    off = tuple(sorted((f for f in z if flight_p[f] < flight_level), key=lambda f: -z[f]))
    if p < alpha and not off:
        off = (max(z, key=z.get),)
    return Consistency(per, p, z, flight_p, flight_level, off, not (p < alpha or off))


def _parameter(name: str, estimates: dict, dofs: dict) -> dict | None:
    """One parameter's pooled value, standard deviation, Cochran's ``Q`` with Welch's test of it, and each
    flight's ``z`` with its two-sided p-value, over the flights that estimate it with a positive standard
    deviation; None when fewer than two do."""
    pairs = {
        f: (e[name]["value"], e[name]["std"], dofs.get(f) or np.inf)
        for f, e in estimates.items()
        if name in e and np.isfinite(e[name]["value"]) and np.isfinite(e[name]["std"]) and e[name]["std"] > 0
    }
    if len(pairs) < 2:
        return None
    x, s, d = (np.array(v, float) for v in zip(*pairs.values()))
    k, w = len(x), 1.0 / s**2
    W = np.sum(w)
    mean = float(np.sum(w * x) / W)
    q = float(np.sum(w * (x - mean) ** 2))
    a = float(np.sum((1.0 - w / W) ** 2 / d))
    welch = q / (k - 1) / (1.0 + 2.0 * (k - 2) * a / (k**2 - 1))
    dof_denominator = (k**2 - 1) / (3.0 * a) if a > 0 else np.inf
    p = special.fdtrc(k - 1, dof_denominator, welch) if a > 0 else special.chdtrc(k - 1, q)
    z = (x - mean) / np.sqrt(s**2 - 1.0 / W)
    pz = 2.0 * special.stdtr(d, -np.abs(z))
    return {
        "value": mean,
        "std": float(np.sqrt(1.0 / W)),
        "cochran_q": q,
        "welch_f": float(welch),
        "dof": k - 1,
        "dof_denominator": float(dof_denominator),
        "p_value": float(p),
        "z": {f: (float(zi), float(pi)) for f, zi, pi in zip(pairs, z, pz)},
    }


def _pooled_estimate(estimates: dict) -> dict:
    """The inverse-variance pooled value and standard deviation of each parameter of ``estimates`` (as in
    ``consistency``), from the flights that estimate it, one flight included."""
    out = {}
    for name in dict.fromkeys(n for e in estimates.values() for n in e):
        pairs = [(e[name]["value"], e[name]["std"]) for e in estimates.values() if name in e]
        pairs = [(x, s) for x, s in pairs if np.isfinite(x) and np.isfinite(s) and s > 0]
        if pairs:
            x, s = (np.array(v, float) for v in zip(*pairs))
            w = 1.0 / s**2
            out[name] = {"value": float(np.sum(w * x) / np.sum(w)), "std": float(np.sqrt(1.0 / np.sum(w)))}
    return out


@dataclass(frozen=True)
class PooledCandidate:
    """One candidate effect over the flights of a vehicle.

    ``flights`` the flights whose test is pooled; ``missing`` those whose diagnosis has no such candidate (a
    channel it needs is absent there); ``untested`` those that have it but could not test it (flight: why);
    ``statistic`` Lancaster's sum on ``dof`` degrees of freedom with ``p_value`` (``combined_test``);
    ``significant`` below the pooled level; ``alone`` the flights where it is significant by itself (below that
    flight's level); ``estimate`` the pooled value and standard deviation of each parameter (with Cochran's
    ``Q`` where it was judged); ``consistency`` (None for a wandering effect, pooled by its test only);
    ``held_out_ratio`` the mean over the flights of its held-out residual over the model's (each flight's own
    fit; for information); ``verdict`` one of ``recommended``, ``significant too``, ``differs between flights``,
    ``not significant``, ``not tested``."""

    effect: str
    test: str
    flights: tuple
    missing: tuple
    untested: dict
    statistic: float
    dof: int
    p_value: float
    significant: bool
    alone: tuple
    estimate: dict
    consistency: Consistency | None
    left_out: tuple = ()
    held_out_ratio: float = float("nan")
    verdict: str = "not significant"

    @property
    def option(self) -> str:
        return f"--effect {self.effect}"

    @property
    def consistent(self) -> bool | None:
        return None if self.consistency is None else self.consistency.consistent

    @property
    def eligible(self) -> bool:
        """Significant over the flights and not found inconsistent."""
        return self.significant and self.consistent is not False

    def as_dict(self) -> dict:
        c = self.consistency
        return {
            "effect": self.effect,
            "option": self.option,
            "verdict": self.verdict,
            "test": TESTS[self.test],
            "statistic": self.statistic,
            "dof": self.dof,
            "p_value": self.p_value,
            "significant": self.significant,
            "flights": list(self.flights),
            "significant_alone": list(self.alone),
            "held_out_ratio": self.held_out_ratio,
            "missing": list(self.missing),
            "untested": self.untested,
            "estimate": self.estimate,
            "consistent": self.consistent,
            "heterogeneity_p_value": None if c is None else c.p_value,
            "flight_z": {} if c is None else c.z,
            "flight_p_value": {} if c is None else c.flight_p,
            "flight_level": None if c is None else c.flight_level,
            "disagreeing": [] if c is None else list(c.disagreeing),
            "left_out_of_consistency": list(self.left_out),
            "consistency_note": "" if c is None else c.note,
            "words": self.words(),
        }

    def words(self) -> str:
        """The verdict in a sentence: the combined test, what the flights did alone, the consistency."""
        if self.verdict == "not tested":
            return f"{self.effect}: not tested in any flight" + _absent(self)
        k = len(self.flights)
        text = (
            f"{self.effect}: {self.verdict}"
            + (f" ({', '.join(self.consistency.disagreeing)})" if self.verdict == "differs between flights" else "")
            + f"; over {k} flight{'s' if k > 1 else ''} chi2 = {self.statistic:.1f} on {self.dof} dof, "
            f"p = {self.p_value:.2g}; significant alone in {len(self.alone)} of {k}"
        )
        if np.isfinite(self.held_out_ratio):
            text += f"; held-out residual {100 * self.held_out_ratio:.1f} % of the model's (mean over the flights)"
        return text + _agreement(self) + _absent(self)


def _agreement(c: PooledCandidate) -> str:
    """The consistency part of ``PooledCandidate.words``."""
    if c.consistency is None:
        return "; a wandering effect: pooled by its test alone"
    con = c.consistency
    values = ", ".join(f"{n} {v['value']:.4g} +- {v['std']:.2g}" for n, v in c.estimate.items())
    if con.consistent is None:
        return f"; consistency not judged: {con.note}" + (f"; pooled {values}" if values else "")
    said = "agrees across flights" if con.consistent else "differs between flights"
    return (
        f"; its coefficient {said} (Cochran's Q, Welch's p = {con.p_value:.2g}; a flight disagrees at p < "
        f"{con.flight_level:.2g}); pooled {values}"
    )


def _absent(c: PooledCandidate) -> str:
    """The flights a candidate is missing from, or not tested in, or left out of the consistency check."""
    parts = []
    if c.missing:
        parts.append(f"not in the diagnosis of {', '.join(c.missing)} (a channel it needs is absent there)")
    if c.untested:
        parts.append("not tested in " + ", ".join(f"{f} ({why})" for f, why in c.untested.items()))
    if c.left_out:
        parts.append(f"estimate left out of the consistency check in {', '.join(c.left_out)} (directions held)")
    return ("; " + "; ".join(parts)) if parts else ""


@dataclass(frozen=True)
class PooledDiagnosis:
    """Outcome of ``pool``: ``flights`` (names, in the order given), ``alpha``, ``n_tested`` candidates tested in
    at least one flight, ``level`` ``alpha / n_tested``, ``candidates`` (``PooledCandidate``, the recommended
    first, then by combined p-value), ``text`` the advice in words."""

    flights: tuple
    alpha: float
    n_tested: int
    level: float
    candidates: list
    text: str = ""

    @property
    def recommended(self) -> list:
        """The candidate recommended for the vehicle (none or one)."""
        return [c for c in self.candidates if c.verdict == "recommended"]

    def summary(self) -> dict:
        return {
            "flights": list(self.flights),
            "alpha": self.alpha,
            "n_tested": self.n_tested,
            "level": self.level,
            "recommended": [c.option for c in self.recommended],
            "candidates": [c.as_dict() for c in self.candidates],
            "text": self.text,
        }


def pool(diagnoses: dict, alpha: float | None = None) -> PooledDiagnosis:
    """Pool the diagnoses of several flights of one vehicle, candidate by candidate (see the module docstring).

    Parameters
    ----------
    diagnoses : dict
        Flight name -> its ``Diagnosis``, or that diagnosis's ``summary()`` (``diagnosis.json``).
    alpha : float or None, optional
        The level over all candidates, in (0, 1) (default: the smallest of the diagnoses' own).

    Returns
    -------
    PooledDiagnosis

    Raises
    ------
    InputError
        No diagnosis, or ``alpha`` outside (0, 1).
    """
    if not diagnoses:
        raise InputError("no diagnosis to pool: give the diagnoses of one or more flights")
    flights = {str(name): candidates_of(d) for name, d in diagnoses.items()}
    if alpha is None:
        alpha = min(_alpha(d) for d in diagnoses.values())
    if not 0.0 < alpha < 1.0:
        raise InputError(f"alpha must lie strictly between 0 and 1, got {alpha:g}")
    effects = list(dict.fromkeys(c.effect for found, *_ in flights.values() for c in found))
    m = max(sum(any(_tested(c) for found, *_ in flights.values() for c in found if c.effect == e) for e in effects), 1)
    level = alpha / m
    pooled = [_pooled(e, flights, level, alpha) for e in effects]
    pooled = _decided(pooled)
    return PooledDiagnosis(tuple(flights), alpha, m, level, pooled, _text(pooled, len(flights), m, level, alpha))


def _alpha(diagnosis) -> float:
    return float(diagnosis["alpha"] if isinstance(diagnosis, dict) else diagnosis.alpha)


def _pooled(effect: str, flights: dict, level: float, alpha: float) -> PooledCandidate:
    """One candidate pooled over ``flights`` (name -> ``candidates_of``) at the pooled ``level``."""
    kind, missing, untested, tested = _sorted_out(effect, flights)
    if not tested:
        return PooledCandidate(effect, kind, (), missing, untested, np.nan, 0, np.nan, False, (), {}, None)
    combined = combined_test([c.p_value for c in tested.values()], [c.dof for c in tested.values()])
    statistic, dof, p = float(combined[0]), int(combined[1]), float(combined[2])
    alone = tuple(f for f, c in tested.items() if c.p_value < flights[f][1])
    test = (effect, kind, tuple(tested), missing, untested, statistic, dof, p, p < level, alone)
    if kind == "L":
        return PooledCandidate(*test, {}, None, (), _held_out_ratio(tested, flights))
    return PooledCandidate(*test, *_agreement_of(tested, alpha), _held_out_ratio(tested, flights))


def _sorted_out(effect: str, flights: dict) -> tuple:
    """``(test, missing, untested, tested)`` of ``effect`` over ``flights``: its test's kind (``F`` or ``L``), the
    flights whose diagnosis lacks it, those that could not test it (flight -> why), and those that did (flight ->
    Candidate)."""
    found = {f: next((c for c in cs if c.effect == effect), None) for f, (cs, *_) in flights.items()}
    present = {f: c for f, c in found.items() if c is not None}
    missing = tuple(f for f in found if f not in present)
    untested = {f: c.note or "not testable" for f, c in present.items() if not _tested(c)}
    tested = {f: c for f, c in present.items() if _tested(c)}
    kind = next(iter((tested or present).values())).test
    return kind, missing, untested, tested


def _held_out_ratio(tested: dict, flights: dict) -> float:
    """The mean over the ``tested`` flights' candidates of their held-out residual over their model's."""
    ratios = np.array([c.residual_rms_after_nt / flights[f][2] for f, c in tested.items()])
    return float(np.mean(ratios[np.isfinite(ratios)])) if np.isfinite(ratios).any() else float("nan")


def _agreement_of(tested: dict, alpha: float) -> tuple:
    """``(estimate, consistency, left_out)`` of a candidate's ``tested`` flights (flight -> Candidate): the pooled
    estimate, the consistency of the flights whose estimate is determined, and the flights left out of it."""
    determined = {f: c.estimate for f, c in tested.items() if c.estimate and HELD not in c.note}
    left_out = tuple(f for f, c in tested.items() if c.estimate and HELD in c.note)
    con = consistency(determined, alpha, {f: c.terms for f, c in tested.items()})
    estimate = {**_pooled_estimate(determined or {f: c.estimate for f, c in tested.items()}), **con.estimate}
    return estimate, con, left_out


def _decided(pooled: list) -> list:
    """The candidates with their verdicts: those significant and not found inconsistent first, the one of lowest
    combined p-value recommended; each group by combined p-value (ties: by how far the statistic lies above its
    degrees of freedom, in its standard deviations)."""

    def key(c):
        excess = (c.statistic - c.dof) / np.sqrt(2 * c.dof) if c.dof else -np.inf
        return (not c.eligible, np.nan_to_num(c.p_value, nan=2.0), -excess)

    ordered = sorted(pooled, key=key)
    out = []
    for c in ordered:
        if not c.flights:
            verdict = "not tested"
        elif c.eligible:
            verdict = "recommended" if not out or out[0].verdict != "recommended" else "significant too"
        elif c.significant:
            verdict = "differs between flights"
        else:
            verdict = "not significant"
        out.append(replace(c, verdict=verdict))
    return out


def _text(pooled: list, k: int, m: int, level: float, alpha: float) -> str:
    """The advice over the flights, in words."""
    best = next((c for c in pooled if c.verdict == "recommended"), None)
    flights = f"the {k} flights" if k > 1 else "its one flight"
    if best is None:
        text = (
            f"over {flights} no candidate is recommended for the vehicle ({m} tested, each at combined "
            f"p < {level:.2g}, alpha {alpha:g})"
        )
    else:
        text = (
            f"over {flights} {best.effect} explains the residual beyond chance (combined p = "
            f"{best.p_value:.2g} < {level:.2g}; significant alone in {len(best.alone)} of {len(best.flights)})"
            f" and holds for the vehicle: add {best.option}"
        )
        also = [c.effect for c in pooled if c.verdict == "significant too"]
        if also:
            text += f"; significant too, to be tested with it in the model: {', '.join(also)}"
    differ = [c for c in pooled if c.verdict == "differs between flights"]
    for c in differ:
        text += f"; {c.effect} differs between flights: {', '.join(c.consistency.disagreeing)}"
    return text

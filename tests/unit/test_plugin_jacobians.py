"""Every registered measurement model's and physical effect's Jacobian against central finite differences of
its own prediction, at seeded random states: a plug-in is checked by registering it (in the registries of
``magkf.plugins``, or by an entry point), with no test of its own.

* A measurement model (``MEASUREMENTS``): ``jacobian(x, blk)`` (k, r, n) against the differences of
  ``predict(x, blk)`` (k, r), on a block with a linear effect (``current_field``) and a nonlinear one
  (``time_lag``) after the core; and ``predict`` of a stack of states (the UKF's sigma points) equal to the
  states' one by one.
* An effect (``EFFECTS``): ``jacobian(theta, data)`` (N, 3, p) against the differences of
  ``contribution(theta, data)`` (N, 3); and both at some epochs (``rows``, ``ROW_METHODS``) equal to the
  same epochs of the whole.

Step and tolerance, per parameter ``j`` of scale ``s_j`` (its prior standard deviation, or its value where
larger). The central difference ``D(h) = (f(x + h) - f(x - h)) / 2h`` errs by its truncation, ``h^2 f''' / 6``
(the prediction's curvature), and by the rounding of ``f``, about ``eps_f / h`` with ``eps_f`` the noise of
the computed ``f`` (``2.2e-16 |f|`` at best, more where an input is rounded: a time lag's ``t - tau`` on
UNIX times is resolved to 2.4e-7 s). Neither is known beforehand, so ``D`` is taken on a ladder of steps
(``STEPS``: ``s_j`` times 0.1 down to 4e-10) and the step kept is the one whose neighbour agrees with it
best: above it the truncation grows as ``h^2``, below it the rounding as ``1 / h``, and where the two
balance, the change to the next step (``D(h) - D(h / 4)`` is 15/16 of ``D(h)``'s truncation, plus both
roundings) measures the error. Four times that change is allowed, and ``1e-7`` of the column's largest
derivative for the analytic side's own error (an effect's ``jacobian`` may be the base class's finite
difference, whose rounding is about ``eps_f / FD_STEP``). A wrong Jacobian (a sign, a factor, a missing
term) is off by its own size.

The measurement models' blocks count time from 0 (their check is of their own chain rule); the effects'
data is on UNIX times, as logs are. There a step below what ``f`` resolves leaves it unchanged (``time_lag``'s
``t - tau`` near 1.7e9 s is resolved to 2.4e-7 s), and the ladder stops at the first such step: its
difference of zero would otherwise agree with the next one's perfectly.
"""

import importlib
import importlib.util

import numpy as np
import pytest

from magkf.config import FilterConfig
from magkf.effects import BUILTIN, make_effect
from magkf.effects.base import EpochData
from magkf.online.measurements import MEASUREMENTS, Block, heading_axis
from magkf.online.state import StateLayout

from ..epochs import turning_epochs

EFFECTS = (
    getattr(importlib.import_module("magkf.plugins"), "EFFECTS", None)
    if importlib.util.find_spec("magkf.plugins")
    else None
)
if EFFECTS is None:
    EFFECTS = BUILTIN

#: Steps of the central differences, relative to each parameter's scale: 0.1 down to 4e-10, by factors of 4.
STEPS = 0.1 * 4.0 ** -np.arange(15)
EPOCHS = 30
STATES = 3
#: The effects after the core in a measurement model's check: a linear one and a nonlinear one.
MODEL_EFFECTS = ("current_field", "time_lag")
PLUGINS = [("measurement", name, cls) for name, cls in MEASUREMENTS.items()] + [
    ("effect", name, cls) for name, cls in EFFECTS.items()
]
#: Known defects, ``(kind, name) -> why``: expected to fail (strictly: a fix makes the test say so).
KNOWN: dict = {}


def _data(rng, columns, R0, t0: float = 1.7e9) -> EpochData:
    """``EPOCHS`` epochs of a manoeuvring vehicle from ``t0`` (s) with the auxiliary ``columns``."""
    return turning_epochs(rng, columns, R0, EPOCHS, t0)


def _states(rng, mean, std, count: int = STATES) -> list:
    """Random states about ``mean`` (p,), within a third of ``std`` (p,)."""
    return [mean + std * rng.normal(0, 0.3, len(mean)) for _ in range(count)]


def _finite_difference(f, x, scale) -> tuple[np.ndarray, np.ndarray]:
    """Central differences ``D`` (..., p) of ``f``: (p,) -> (...) at ``x`` (p,), each at the step where the next
    step agrees with it best, and four times that disagreement (p,): what ``D`` may be off by (see the
    module's docstring)."""
    D, tol = [], []
    for j in range(len(x)):
        ladder = []
        for h in scale[j] * STEPS:
            step = np.zeros(len(x))
            step[j] = h
            difference = f(x + step) - f(x - step)
            if ladder and not np.any(difference):  # below what f resolves (a time lag's t - tau on UNIX times)
                break
            ladder.append(difference / (2 * h))
        spread = [np.max(np.abs(a - b)) for a, b in zip(ladder, ladder[1:])]
        best = int(np.argmin(spread))
        D.append(ladder[best])
        tol.append(4.0 * spread[best])
    return np.stack(D, axis=-1), np.array(tol)


def _agrees(J, D, tol) -> bool:
    """``J`` (..., p) within ``tol`` (p,) of ``D`` (..., p), and ``1e-7`` of each column's largest derivative."""
    column = np.max(np.abs(D), axis=tuple(range(D.ndim - 1)))
    return bool(np.all(np.abs(J - D) <= tol + 1e-7 * column))


def _check_model(cls, rng) -> None:
    layout = StateLayout.with_core([make_effect(e) for e in MODEL_EFFECTS])
    mean, P = layout.prior()
    std = np.sqrt(np.diag(P))
    mean[layout.B_INDEX] = rng.normal(0, 300, 3)
    x0 = _states(rng, mean, std, 1)[0]
    R0 = layout.R(x0)
    data = _data(rng, [c for e in layout.extra() for c in e.columns], R0, t0=0.0)
    model = cls(FilterConfig(), layout, x0)
    heading = heading_axis(data.c_nb, data.field_ned)
    structure = model.structure(data.field_body, R0, heading)
    G, Gh, RRt, frame = structure if structure is not None else (None, None, None, None)
    H = layout.linear_jacobian(data)
    blk = Block(data.mag, np.linalg.norm(data.field_ned, axis=1), H, data.field_body, R0, heading, G, Gh, RRt, frame)
    blk.data = data
    states = _states(rng, x0, std)
    for x in states:
        blk.e = np.nan_to_num(layout.extra_terms(x, H, data))  # the effects' terms at the estimate
        D, tol = _finite_difference(lambda s: model.predict(s, blk), x, np.maximum(np.abs(x), std))
        assert _agrees(model.jacobian(x, blk), D, tol), "jacobian differs from the differences of predict"
    stack = model.predict(np.array(states), blk)
    one_by_one = np.stack([model.predict(x, blk) for x in states])
    assert np.allclose(stack, one_by_one, rtol=1e-12, atol=1e-12 * np.abs(one_by_one).max())


def _check_effect(cls, rng) -> None:
    effect = cls()
    data = _data(rng, effect.columns, np.eye(3) + rng.normal(0, 0.05, (3, 3)))
    mean, std = effect.prior()
    rows = np.sort(rng.choice(EPOCHS, EPOCHS // 3, replace=False))
    for theta in _states(rng, mean, std):
        J = effect.jacobian(theta, data)
        whole = effect.contribution(theta, data)
        assert np.allclose(effect.contribution(theta, data, rows=rows), whole[rows], rtol=1e-9, atol=1e-9)
        assert np.allclose(effect.jacobian(theta, data, rows=rows), J[rows], rtol=1e-9, atol=1e-9 * np.abs(J).max())
        D, tol = _finite_difference(lambda th: effect.contribution(th, data), theta, np.maximum(np.abs(theta), std))
        assert _agrees(J, D, tol), "jacobian differs from the differences of contribution"


@pytest.mark.parametrize(
    "kind,name,cls",
    [
        pytest.param(*p, id=f"{p[0]}-{p[1]}", marks=[pytest.mark.xfail(reason=KNOWN[p[:2]], strict=True)])
        if p[:2] in KNOWN
        else pytest.param(*p, id=f"{p[0]}-{p[1]}")
        for p in PLUGINS
    ],
)
def test_jacobian_matches_finite_differences(kind, name, cls):
    """The plug-in's Jacobian (analytic, or its own finite difference) is the derivative of its prediction."""
    rng = np.random.default_rng(sum(map(ord, name)))  # seeded by the name: the same states in every run
    if kind == "measurement":
        _check_model(cls, rng)
    else:
        _check_effect(cls, rng)

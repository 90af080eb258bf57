"""The measurement models' fast forms of the estimators' rows against the generic ones the base class builds
from ``measure``, ``predict``, ``jacobian`` and ``covariance`` (seeded).

For ``magnitude`` (as the run's only model and as a fallback), ``vector`` and ``both``, on random blocks of
epochs, without effects, with a linear one (``current_field``), a nonlinear one (``time_lag``) and both, at
several states: ``linearise``, ``sigma_predict`` and ``innovation`` of the model equal
``MeasurementModel``'s to rounding.

The batch solver's residuals of these models are their own (the patent's total-field and NED residuals
over a diagonal noise, see ``magkf.online.measurements``), not their filter rows whitened, so they cannot
equal the generic ones; what is compared instead is each side with what it must agree with: the generic
batch residuals and Jacobian with the fast ``linearise``'s rows (at the same whitening, unprojected), and
the built-in residuals, in nT, with the model's own ``predict`` and ``measure``.

Tolerance: both sides compute the same quantities in another order (whitening applied before or after a
product, an inverse by cofactors or by a solve), a few tens of floating-point operations, each with a
relative error of at most float64's epsilon (2.2e-16), amplified by at most the whitening's condition
number (the attitude noise across the field against the sensor noise along it: (0.5 deg x 50 000 nT / 10
nT)^2, below 2e3 here). So they agree to 100 x 2.2e-16 x 2e3 < 1e-10 of the array's scale (a Jacobian's
column by column: the columns of R, b and an effect differ by orders of magnitude); 1e-9 is asserted.
"""

import numpy as np
import pytest

from magkf.config import FilterConfig
from magkf.conventions import body_to_ned, inverse3
from magkf.effects import make_effect
from magkf.effects.base import EpochData
from magkf.online.measurements import (
    Block,
    Both,
    Magnitude,
    MeasurementModel,
    Vector,
    field_frame,
    heading_axis,
    heading_axis_ned,
    whitening,
)
from magkf.online.noise import NoiseLevels
from magkf.online.state import StateLayout

from ..epochs import turning_epochs

RTOL = 1e-9
EPOCHS = 40
EFFECTS = {"none": (), "linear": ("current_field",), "nonlinear": ("time_lag",), "both": ("current_field", "time_lag")}
MODELS = {
    "magnitude": lambda c, lay, x0: Magnitude(c, lay, x0),
    "fallback magnitude": lambda c, lay, x0: Magnitude(c, lay, x0, primary=False),
    "vector": Vector,
    "both": Both,
}
#: Learned-looking noise: a heading error apart from the tilt, and correlation inflations along the field's frame.
NOISE = NoiseLevels(12.0, np.radians(0.3), 5.0, 2.5, 1.7, np.radians(0.6), 4.0)


def close(a, b, column_scale: bool = False) -> bool:
    """``a`` equals ``b`` to ``RTOL`` of ``b``'s largest magnitude (of each of its last axis's columns)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    if a.shape != b.shape:
        return False
    axes = tuple(range(b.ndim - 1)) if column_scale else None
    scale = np.max(np.abs(b), axis=axes, keepdims=column_scale)
    return bool(np.all(np.abs(a - b) <= RTOL * np.maximum(scale, 1e-300)))


def _data(rng, layout: StateLayout, R0) -> EpochData:
    """``EPOCHS`` epochs of a manoeuvring vehicle with every column the layout's effects need."""
    return turning_epochs(rng, [c for e in layout.extra() for c in e.columns], R0, EPOCHS)


def _state(rng, layout: StateLayout) -> np.ndarray:
    """A random state near identity: ``R`` within 0.05, ``b`` within 300 nT, effects within their priors."""
    mean, P = layout.prior()
    x = mean + 0.3 * np.sqrt(np.diag(P)) * rng.standard_normal(layout.size)
    x[layout.R_INDEX] = (np.eye(3) + rng.normal(0, 0.05, (3, 3))).ravel()
    x[layout.B_INDEX] = rng.normal(0, 300, 3)
    return x


def _setup(model_name, effects, seed):
    """``(model, block, states)``: the model on a random block prepared as the estimator prepares it (noise
    structure at the start's ``R``, the effects' terms at the estimate, the whitening with the correlation
    folded in) and three states; the block's ``e`` is set for each state by ``_at``."""
    rng = np.random.default_rng(seed)
    layout = StateLayout.with_core([make_effect(e) for e in effects])
    x0 = _state(rng, layout)
    R0 = layout.R(x0)
    data = _data(rng, layout, R0)
    model = MODELS[model_name](FilterConfig(), layout, x0)
    model.set_noise(NOISE)
    heading = heading_axis(data.c_nb, data.field_ned)
    structure = model.structure(data.field_body, R0, heading)
    G, Gh, RRt, frame = structure if structure is not None else (None, None, None, None)
    H = layout.linear_jacobian(data)
    blk = Block(data.mag, np.linalg.norm(data.field_ned, axis=1), H, data.field_body, R0, heading, G, Gh, RRt, frame)
    blk.data = data
    model.whiten(x0, blk, NOISE.inflations)
    return model, blk, [_state(rng, layout) for _ in range(3)]


def _at(model, blk: Block, x) -> Block:
    """The block with the effects' terms at the estimate ``x``, as ``Estimator.process_block`` sets them."""
    layout = model.layout
    if layout.has_extra:
        blk.e = np.nan_to_num(layout.extra_terms(x, blk.H, blk.data))
    return blk


CASES = [(m, e, seed) for m in MODELS for e in EFFECTS for seed in range(2)]


@pytest.mark.parametrize("model_name,effects,seed", CASES)
def test_fast_rows_are_the_generic_rows(model_name, effects, seed):
    """The EKF's rows, the UKF's sigma-point predictions and the learner's innovations of each built-in model
    equal those the base class builds from the model's four methods, to rounding."""
    model, blk, states = _setup(model_name, EFFECTS[effects], seed)
    rng = np.random.default_rng(100 + seed)
    n = model.layout.size
    for x in states:
        _at(model, blk, x)
        y, H = model.linearise(x, blk)
        y_g, H_g = MeasurementModel.linearise(model, x, blk)
        assert close(y, y_g) and close(H, H_g, column_scale=True)
        sigmas = x + 0.01 * (np.abs(x) + 1e-3) * rng.standard_normal((2 * n + 1, n))  # steps of 1 % of x
        fast, generic = model.sigma_predict(sigmas, x, blk), MeasurementModel.sigma_predict(model, sigmas, x, blk)
        assert close(fast[0], generic[0]) and close(fast[1], generic[1])
        assert close(fast[2], generic[2], column_scale=True)
        assert close(model.innovation(x, blk), MeasurementModel.innovation(model, x, blk))


@pytest.mark.parametrize("model_name,effects,seed", [c for c in CASES if c[0] != "magnitude"])
def test_generic_batch_residuals_are_the_filter_rows(model_name, effects, seed):
    """The base class's batch residuals ``W (predict - measure)`` and Jacobian ``W jacobian`` are the fast
    ``linearise``'s rows (``-y`` and ``H``) at the same whitening, the inverse Cholesky factor of the
    covariance (the run's only magnitude is left out: its ``linearise`` projects the Jacobian, which the
    batch solver, with its prior on every direction, does not)."""
    model, blk, states = _setup(model_name, EFFECTS[effects], seed)
    for x in states:
        _at(model, blk, x)
        blk.W, blk.N = (None, None) if model.noise_depends_on_state else (whitening(model.covariance(x, blk)), None)
        y, H = model.linearise(x, blk)
        r, J = MeasurementModel.batch_residuals(model, x, blk, jacobian=True)
        assert close(r, -y) and close(J, H, column_scale=True)
        assert close(MeasurementModel.batch_residuals(model, x, blk), -y)


@pytest.mark.parametrize("model_name,effects,seed", CASES)
def test_built_in_batch_residuals_agree_with_the_model(model_name, effects, seed):
    """The built-in batch residuals, functions of the calibrated field, times their standard deviations are
    the model's own residuals taken to the frame they are in: the magnitude's ``predict - measure`` as it is,
    the vector's ``measure - predict = R (c - C_nb^T B_ref)`` in NED (``C_nb R^-1``), ``both``'s the magnitude's
    and the NED residual across the field (along ``h`` and ``v``)."""
    model, blk, states = _setup(model_name, EFFECTS[effects], seed)
    data = blk.data
    for x in states:
        r = model.batch_residuals(x, blk)
        ned = None
        if model.needs_attitude:
            d = model.measure(blk) - model.predict(x, blk)  # m - (R B + b + e) = R (c - B), sensor axes
            ned = body_to_ned(data.c_nb, d @ inverse3(model.layout.R(x)).T)
        if isinstance(model, Both):
            magnitude = model.fallback.predict(x, blk) - model.fallback.measure(blk)
            assert close(r[:, :1] * model._sigma_total(), magnitude)
            ref = data.field_ned
            basis = field_frame(ref, heading_axis_ned(ref))[:, 1:]
            var_h, var_v = model.noise.across_vars(blk.ref_mag**2, ref[:, 0] ** 2 + ref[:, 1] ** 2)
            cross = r[:, 1:] * np.sqrt(np.column_stack([var_h, var_v]))
            assert close(cross, np.einsum("nki,ni->nk", basis, ned))
        elif isinstance(model, Vector):
            assert close(r * model._sigma_cross(blk.ref_mag)[:, None], ned)
        else:
            assert close(r * model._sigma_total(), model.predict(x, blk) - model.measure(blk))


def test_a_model_must_implement_the_four_methods():
    """``MeasurementModel`` is abstract: a model without one of ``measure``, ``predict``, ``jacobian`` and
    ``covariance`` cannot be made."""

    class Incomplete(MeasurementModel):
        name = "incomplete"

        def measure(self, blk):
            return blk.ref_mag[:, None]

        def predict(self, x, blk):
            return np.zeros((len(blk.m), 1))

        def jacobian(self, x, blk):
            return np.zeros((len(blk.m), 1, self.layout.size))

    layout = StateLayout.with_core()
    with pytest.raises(TypeError, match="covariance"):
        Incomplete(FilterConfig(), layout, layout.prior()[0])

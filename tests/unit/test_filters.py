"""The filters' update and the smoother against textbook computations and FilterPy's own (seeded)."""

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from magkf.online.filters import EKF, FILTERS
from magkf.online.smoother import rts_smooth


def _problem(seed, n=6, r=4):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n))
    P = A @ A.T + n * np.eye(n)
    x = rng.normal(size=n)
    H = rng.normal(size=(r, n))
    B = rng.normal(size=(r, r))
    R = B @ B.T + r * np.eye(r)
    z = rng.normal(size=r)
    return x, P, H, R, z


def _textbook(x, P, H, R, z):
    """The Kalman update as textbooks write it, Joseph form for the covariance."""
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)
    x_new = x + K @ (z - H @ x)
    IKH = np.eye(len(x)) - K @ H
    return x_new, IKH @ P @ IKH.T + K @ R @ K.T


@pytest.mark.parametrize("seed", range(5))
def test_ekf_correct_equals_textbook_and_filterpy(seed):
    x, P, H, R, z = _problem(seed)
    ekf = EKF(x, P, np.zeros(len(x)))
    ekf.correct(z - H @ x, H, R)
    x_tb, P_tb = _textbook(x, P, H, R, z)
    kf = KalmanFilter(dim_x=len(x), dim_z=len(z))
    kf.x, kf.P, kf.H, kf.R = x.copy(), P.copy(), H, R
    kf.update(z)
    assert np.allclose(ekf.x, x_tb, rtol=1e-12, atol=1e-12)
    assert np.allclose(ekf.P, P_tb, rtol=1e-10, atol=1e-12)
    assert np.allclose(ekf.x, kf.x, rtol=1e-12, atol=1e-12)
    assert np.allclose(ekf.P, kf.P, rtol=1e-10, atol=1e-12)
    assert np.array_equal(ekf.P, ekf.P.T)  # exactly symmetric by construction


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("units", [1.0, 1e3])
def test_block_of_whitened_rows_folded_as_information_equals_textbook(seed, units):
    """75 whitened rows (a 0.25 s block at 100 Hz) on 12 states: the information update is the Kalman
    update; also in the units of a calibration, R's spreads near 1e-3 and b's near 1e3 nT (compared in units
    of each state's spread)."""
    rng = np.random.default_rng(seed)
    n, r = 12, 75
    A = rng.normal(size=(n, n))
    s = np.concatenate([np.full(9, 1.0 / units), np.full(3, units)])
    P = s[:, None] * (A @ A.T + n * np.eye(n)) * s[None, :]
    x, H, z = rng.normal(size=n) * s, rng.normal(size=(r, n)) / s, rng.normal(size=r)
    ekf = EKF(x, P, np.zeros(n))
    ekf.correct(z - H @ x, H)
    x_tb, P_tb = _textbook(x, P, H, np.eye(r), z)
    assert np.allclose(ekf.x / s, x_tb / s, rtol=1e-9, atol=1e-12)
    assert np.allclose(ekf.P / np.outer(s, s), P_tb / np.outer(s, s), rtol=1e-9, atol=1e-12)
    assert np.array_equal(ekf.P, ekf.P.T)


def _whitened(H, R, z, x):
    """Rows of the same problem whitened (unit noise), one row per 'epoch'."""
    W = np.linalg.inv(np.linalg.cholesky(R))
    Hw, yw = W @ H, W @ (z - H @ x)
    return Hw, yw, W @ z


class _Linear:
    """A linear model over whitened rows, one row an epoch, for driving both filters directly."""

    rows = 1

    def __init__(self, Hw, zw):
        self.Hw, self.zw = Hw, zw

    def linearise(self, x, blk):
        return (self.zw - self.Hw @ x)[:, None], self.Hw[:, None, :]

    def sigma_predict(self, sigmas, x, blk):
        return (sigmas @ self.Hw.T)[..., None], self.zw[:, None], self.Hw[:, None, :]


@pytest.mark.parametrize("name", sorted(FILTERS))
@pytest.mark.parametrize("seed", range(3))
def test_update_of_a_linear_measurement_is_the_textbook_update(name, seed):
    """For a linear measurement the UKF's update is exact: both filters give the textbook result, with
    every epoch's NIS equal to y_i^2 / (h_i P h_i^T + 1)."""
    x, P, H, R, z = _problem(seed)
    R = np.diag(np.diag(R))  # independent rows: per-epoch whitening is exact
    Hw, yw, zw = _whitened(H, R, z, x)
    kf = FILTERS[name](x, P, np.zeros(len(x)))
    lin = kf.linearise([(_Linear(Hw, zw), None)])
    expected_nis = yw**2 / (np.einsum("ri,ij,rj->r", Hw, P, Hw) + 1)
    assert np.allclose(lin.rows[0].nis, expected_nis, rtol=1e-9)
    kf.update(lin, [np.ones(len(z), bool)])
    x_tb, P_tb = _textbook(x, P, H, R, z)
    assert np.allclose(kf.x, x_tb, rtol=1e-9, atol=1e-9)
    assert np.allclose(kf.P, P_tb, rtol=1e-8, atol=1e-9)


@pytest.mark.parametrize("name", sorted(FILTERS))
def test_rejected_rows_do_not_update(name):
    x, P, H, R, z = _problem(7)
    R = np.diag(np.diag(R))
    Hw, _, zw = _whitened(H, R, z, x)
    kf = FILTERS[name](x, P, np.zeros(len(x)))
    keep = np.array([True, False, True, False])
    kf.update(kf.linearise([(_Linear(Hw, zw), None)]), [keep])
    x_tb, P_tb = _textbook(x, P, H[keep], R[np.ix_(keep, keep)], z[keep])
    assert np.allclose(kf.x, x_tb, rtol=1e-9, atol=1e-9)
    assert np.allclose(kf.P, P_tb, rtol=1e-8, atol=1e-9)


@pytest.mark.parametrize("name", sorted(FILTERS))
def test_filters_share_one_small_interface(name):
    kf = FILTERS[name](np.zeros(3), np.eye(3), np.full(3, 0.5))
    kf.predict(2.0)
    assert np.allclose(kf.P, 2.0 * np.eye(3))  # P += Q dt, x unchanged
    copy = kf.copy()
    copy.inflate(np.eye(3))
    assert np.allclose(kf.P, 2.0 * np.eye(3)) and np.allclose(copy.P, 3.0 * np.eye(3))
    public = {a for a in dir(kf) if not a.startswith("_")}
    assert {"x", "P", "predict", "linearise", "update", "inflate", "copy"} <= public
    assert not hasattr(kf, "update_sequential") and not hasattr(kf, "hx")  # nothing that cannot work


def test_rts_smoother_equals_filterpy():
    """A random walk filtered by FilterPy's KalmanFilter, smoothed by magkf and by FilterPy's rts_smoother."""
    rng = np.random.default_rng(11)
    n, steps = 3, 60
    q_rate = np.array([0.5, 0.1, 2.0])
    dt = rng.uniform(0.1, 1.0, steps)
    kf = KalmanFilter(dim_x=n, dim_z=2)
    kf.x, kf.P = np.zeros(n), np.eye(n) * 10.0
    kf.F = np.eye(n)
    kf.H = rng.normal(size=(2, n))
    kf.R = np.eye(2) * 0.3
    truth = np.cumsum(rng.normal(size=(steps, n)) * np.sqrt(q_rate * dt[:, None]), axis=0)
    xs, Ps, Qs = [], [], []
    for k in range(steps):
        kf.Q = np.diag(q_rate * dt[k])
        kf.predict()
        kf.update(kf.H @ truth[k] + rng.normal(scale=np.sqrt(0.3), size=2))
        xs.append(kf.x.copy())
        Ps.append(kf.P.copy())
        Qs.append(np.diag(q_rate * dt[k]))
    xs, Ps = np.array(xs), np.array(Ps)
    # Both predict from step k to k + 1 with the process noise of step k + 1 (Qs[k + 1], q_rate * dt[k + 1]).
    x_fp, P_fp, _, _ = kf.rts_smoother(xs, Ps, Fs=[np.eye(n)] * steps, Qs=Qs)
    x_mk, P_mk = rts_smooth(xs, Ps, dt, q_rate)
    assert np.allclose(x_mk, x_fp, rtol=1e-9, atol=1e-9)
    assert np.allclose(P_mk, P_fp, rtol=1e-9, atol=1e-9)


def _unscented_textbook(x, P, hx, z):
    """The unscented update with unit noise from FilterPy's sigma points and transform (fresh sigma points at
    the estimate, as magkf's UKF draws them)."""
    from filterpy.kalman import MerweScaledSigmaPoints, unscented_transform

    points = MerweScaledSigmaPoints(len(x), alpha=1.0, beta=2.0, kappa=0.0)
    sigmas = points.sigma_points(x, P)
    h = np.array([hx(s) for s in sigmas])
    zp, S = unscented_transform(h, points.Wm, points.Wc, np.eye(len(z)))
    Pxz = ((sigmas - x).T * points.Wc) @ (h - zp)
    K = Pxz @ np.linalg.inv(S)
    return x + K @ (z - zp), P - K @ S @ K.T


class _Curved:
    """One epoch of three rows that curve with the state (unit noise): the unscented update is then not the
    linear one."""

    rows = 3

    def __init__(self, z):
        self.z = z

    @staticmethod
    def h(x):
        x = np.asarray(x)
        return np.stack(
            [
                x[..., 0] + 0.3 * x[..., 1] ** 2,
                x[..., 1] + 0.2 * x[..., 0] * x[..., 1],
                x[..., 0] - x[..., 1] + 0.1 * x[..., 0] ** 2,
            ],
            -1,
        )

    def sigma_predict(self, sigmas, x, blk):
        H = np.zeros((3, len(x)))  # the rows depend on the first two states only
        H[:, :2] = [[1.0, 0.6 * x[1]], [0.2 * x[1], 1.0 + 0.2 * x[0]], [1.0 + 0.2 * x[0], -1.0]]
        return self.h(sigmas)[:, None, :], self.z[None], H[None]


@pytest.mark.parametrize("declared", [False, True])
@pytest.mark.parametrize("seed", range(3))
def test_ukf_folds_many_linear_rows_as_the_textbook_update(seed, declared):
    """75 linear whitened rows on 12 states: the unscented update folded in by information (statistical linear
    regression, no linearisation error) is the textbook update; and so is the fold of rows whose model
    declares them linear (``MeasurementModel.linear``), which skips the regression."""
    rng = np.random.default_rng(seed)
    n, r = 12, 75
    A = rng.normal(size=(n, n))
    P, x = A @ A.T + n * np.eye(n), rng.normal(size=n)
    Hw, zw = rng.normal(size=(r, n)), rng.normal(size=r)
    kf = FILTERS["ukf"](x, P, np.zeros(n))
    model = _Linear(Hw, zw)
    model.linear = declared
    lin = kf.linearise([(model, None)])
    assert lin.rows[0].linear is declared
    kf.update(lin, [np.ones(r, bool)])
    x_tb, P_tb = _textbook(x, P, Hw, np.eye(r), zw)
    assert np.allclose(kf.x, x_tb, rtol=1e-9, atol=1e-9)
    assert np.allclose(kf.P, P_tb, rtol=1e-8, atol=1e-9)


@pytest.mark.parametrize("seed", range(3))
def test_ukf_fold_keeps_the_linearisation_error_of_a_curved_epoch(seed):
    """Three curved rows of one epoch on two states (more rows than states, so they are folded in): the
    linearisation error that the sigma points see enters as noise, and the update is FilterPy's unscented one."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(2, 2))
    P, x = A @ A.T + np.eye(2), rng.normal(size=2)
    z = _Curved.h(x) + rng.normal(size=3)
    kf = FILTERS["ukf"](x, P, np.zeros(2))
    kf.update(kf.linearise([(_Curved(z), None)]), [np.ones(1, bool)])
    x_tb, P_tb = _unscented_textbook(x, P, _Curved.h, z)
    assert np.allclose(kf.x, x_tb, rtol=1e-9, atol=1e-9)
    assert np.allclose(kf.P, P_tb, rtol=1e-8, atol=1e-9)


@pytest.mark.parametrize("seed", range(3))
def test_ukf_update_of_linear_and_curved_rows_together_is_filterpys(seed):
    """Two rows declared linear (taken at the estimate, no sigma points) and three curved rows of one epoch:
    five rows on six states, fewer than the states, so the textbook update rather than the fold. It is
    FilterPy's unscented update of all five rows, whose sigma points predict the linear rows exactly."""
    rng = np.random.default_rng(seed)
    n = 6
    A = rng.normal(size=(n, n))
    P, x = A @ A.T + np.eye(n), rng.normal(size=n)
    Hw = rng.normal(size=(2, n))
    zw, z = Hw @ x + rng.normal(size=2), _Curved.h(x) + rng.normal(size=3)
    linear = _Linear(Hw, zw)
    linear.linear = True
    kf = FILTERS["ukf"](x, P, np.zeros(n))
    lin = kf.linearise([(linear, None), (_Curved(z), None)])
    assert lin.rows[0].h is None and lin.rows[1].h is not None
    kf.update(lin, [np.ones(2, bool), np.ones(1, bool)])
    x_tb, P_tb = _unscented_textbook(x, P, lambda s: np.concatenate([Hw @ s, _Curved.h(s)]), np.concatenate([zw, z]))
    assert np.allclose(kf.x, x_tb, rtol=1e-9, atol=1e-9)
    assert np.allclose(kf.P, P_tb, rtol=1e-8, atol=1e-9)


def test_ukf_of_linear_rows_alone_draws_no_sigma_points():
    """Rows declared linear alone: the UKF's update is the Kalman update, and no sigma points are drawn."""
    x, P, H, R, z = _problem(4)
    R = np.diag(np.diag(R))
    Hw, _, zw = _whitened(H, R, z, x)
    linear = _Linear(Hw, zw)
    linear.linear = True
    kf = FILTERS["ukf"](x, P, np.zeros(len(x)))
    lin = kf.linearise([(linear, None)])
    assert lin.sigmas is None and kf._points is None
    kf.update(lin, [np.ones(len(z), bool)])
    x_tb, P_tb = _textbook(x, P, H, R, z)
    assert np.allclose(kf.x, x_tb, rtol=1e-9, atol=1e-9)
    assert np.allclose(kf.P, P_tb, rtol=1e-8, atol=1e-9)


def test_one_epoch_field_frame_is_the_vectorised_one():
    """The real-time path's plain-float field frame (one epoch) equals the vectorised one, also where the
    heading axis lies along the field and where the field is near the x axis."""
    from magkf.online.measurements import field_frame

    rng = np.random.default_rng(3)
    for i in range(100):
        f, h = rng.normal(size=(1, 3)) * 3e4, rng.normal(size=(1, 3)) * 2e4
        if i % 5 == 0:
            h = 0.5 * f
        if i % 7 == 0:
            f[0, 0] = 0.95 * np.linalg.norm(f)
        for heading in (h, None):
            twice = None if heading is None else np.vstack([heading, heading])
            assert np.allclose(field_frame(f, heading), field_frame(np.vstack([f, f]), twice)[:1], atol=1e-12)


def test_stacked_whitening_and_nis_are_lapacks():
    """The whitening of a stack of 3x3 covariances written out over the stack equals the inverse of LAPACK's
    Cholesky factor, and a covariance that is not positive definite is refused as LAPACK refuses it; the NIS
    by cofactors equals the one through a general inverse."""
    from magkf.online.filters import _nis
    from magkf.online.measurements import whitening

    rng = np.random.default_rng(5)
    A = rng.normal(size=(50, 3, 3)) * rng.uniform(1.0, 1e3, size=(50, 1, 1))
    cov = A @ np.swapaxes(A, 1, 2) + 1e-3 * np.eye(3)  # condition numbers up to about 1e5
    W, lapack = whitening(cov), np.linalg.inv(np.linalg.cholesky(cov))
    assert (np.abs(W - lapack).max(axis=(1, 2)) <= 1e-10 * np.abs(lapack).max(axis=(1, 2))).all()
    assert np.allclose(W @ cov @ np.swapaxes(W, 1, 2), np.eye(3), atol=1e-9)
    bad = cov.copy()
    bad[7] = -bad[7]
    with pytest.raises(np.linalg.LinAlgError):
        whitening(bad)
    y = rng.normal(size=(50, 3)) * 30.0
    expected = np.einsum("ki,kij,kj->k", y, np.linalg.inv(cov), y)
    assert np.allclose(_nis(y, cov), expected, rtol=1e-9, atol=0)


def test_only_rows_linear_for_every_state_are_declared_linear():
    """The UKF folds rows declared linear with their own Jacobian, so only the built-in vector rows without a
    nonlinear effect say so: not the magnitude, not a layout with a time lag, not a subclass with its own
    prediction."""
    from magkf.config import FilterConfig
    from magkf.effects import make_effect
    from magkf.online.measurements import Vector, measurement_model
    from magkf.online.state import StateLayout

    class Curved(Vector):
        def sigma_predict(self, sigmas, x, blk):
            return super().sigma_predict(sigmas, x, blk)

    core = StateLayout.with_core()
    x0 = np.concatenate([np.eye(3).ravel(), np.zeros(3)])
    lag = StateLayout.with_core([make_effect("time_lag")])
    x_lag = np.concatenate([x0, lag.prior()[0][12:]])
    linear = {name: measurement_model(FilterConfig(measure=name), core, x0).linear for name in ("vector", "both")}
    assert linear == {"vector": True, "both": True}
    assert not measurement_model(FilterConfig(measure="magnitude"), core, x0).linear
    assert not measurement_model(FilterConfig(measure="vector"), lag, x_lag).linear
    assert not Curved(FilterConfig(), core, x0).linear

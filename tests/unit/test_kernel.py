"""The kernel's gates and update of one block (``magkf.online.kernel.gate_and_fold``, run here as plain Python)
against the numpy path's: ``filters._nis`` for the normalised innovation squared, the estimator's Huber weights
and the EKF's update (``EKF.correct``) for the state and covariance.

Tolerance: the two compute the same sums in another order (``H P H^T`` as ``(H L)(H L)^T`` with ``P = L L^T``,
the information ``H^T H`` epoch by epoch), so they differ by rounding: a few units of float64's 2.2e-16 for each
of the 12 to 36 products summed, relative to the largest term. 1e-12 relative leaves a margin of about a
hundred, and sits far below any difference in the logic (an epoch weighted or gated otherwise moves the state by
1 / k of its innovation, here over 1e-3).
"""

import numpy as np
import pytest

from magkf.online import kernel
from magkf.online.estimator import _huber
from magkf.online.filters import EKF, _nis

RTOL = 1e-12
BOUND, HUBER_Q = 11.34, 7.81  # the chi-square quantiles of 0.99 and 0.95 with 3 degrees of freedom


def _block(seed: int, k: int, r: int, n: int = 12, spread: float = 3.0):
    rng = np.random.default_rng(seed)
    H = rng.normal(size=(k, r, n))
    y = rng.normal(size=(k, r)) * spread
    A = rng.normal(size=(n, n))
    P = 0.01 * (A @ A.T + np.eye(n))
    B = rng.normal(size=(k, r, r)) * 0.3
    N = np.eye(r) + B @ np.swapaxes(B, 1, 2)  # the whitened noise of correlated rows: positive definite
    return y, H, N, rng.normal(size=n), P


def _numpy_path(y, H, N, x, P, inflation):
    """What the estimator and the EKF do with these rows: nis, refused, and the state after the update."""
    S = H @ P @ np.swapaxes(H, 1, 2) + (np.eye(H.shape[1]) if N is None else N)
    nis = _nis(y, S)
    refused = nis > BOUND
    weight = _huber(HUBER_Q, nis) / (inflation if N is None else 1.0)
    accept = ~refused
    root = np.sqrt(weight[accept])
    kf = EKF(x, P, np.zeros(len(x)))
    kf.correct((y[accept] * root[:, None]).ravel(), (H[accept] * root[:, None, None]).reshape(-1, len(x)))
    return nis, refused, kf.x, kf.P


@pytest.mark.parametrize("r", [1, 3])
@pytest.mark.parametrize("with_noise", [True, False])
def test_the_kernel_gives_the_numpy_paths_gates_and_update(r, with_noise):
    y, H, N, x, P = _block(seed=5 + r, k=40, r=r)
    N = N if with_noise else None
    outcome, nis, refused, x_new, P_new, J = kernel.gate_and_fold(
        y, H, np.zeros((1, 1, 1)) if N is None else N, N is not None, x, P, BOUND, HUBER_Q, 2.5
    )
    nis_ref, refused_ref, x_ref, P_ref = _numpy_path(y, H, N, x, P, 2.5)
    assert outcome == kernel.UPDATED
    assert 0 < refused.sum() < len(refused)  # some epochs gated, so that the gate is tested too
    np.testing.assert_array_equal(refused, refused_ref)
    np.testing.assert_allclose(nis, nis_ref, rtol=RTOL)
    scale = np.sqrt(np.diag(P_ref))
    np.testing.assert_allclose((x_new - x_ref) / scale, 0.0, atol=RTOL * np.abs(x_ref / scale).max())
    np.testing.assert_allclose(P_new, P_ref, rtol=0, atol=RTOL * np.abs(P_ref).max())
    weight = _huber(HUBER_Q, nis_ref)[~refused] / (2.5 if N is None else 1.0)
    Hs = H[~refused].reshape(len(weight), -1, H.shape[2])
    J_ref = np.einsum("k,kin,kim->nm", weight, Hs, Hs)
    np.testing.assert_allclose(J, J_ref, rtol=0, atol=RTOL * np.abs(J_ref).max())


def test_blocks_the_kernel_leaves_to_numpy_change_nothing():
    """Too few accepted rows to fold by their information, a covariance that is not positive definite, and no
    epoch accepted: the estimate is returned as it was."""
    y, H, N, x, P = _block(seed=1, k=3, r=3)
    few = kernel.gate_and_fold(y * 0.01, H, N, True, x, P, BOUND, HUBER_Q, 1.0)  # 9 rows for 12 states
    assert few[0] == kernel.USE_NUMPY and few[3] is x and few[4] is P
    not_positive = P.copy()
    not_positive[0, 0] = -1.0
    assert kernel.gate_and_fold(y, H, N, True, x, not_positive, BOUND, HUBER_Q, 1.0)[0] == kernel.USE_NUMPY
    none = kernel.gate_and_fold(y * 1e6, H, N, True, x, P, BOUND, HUBER_Q, 1.0)
    assert none[0] == kernel.NOTHING_ACCEPTED and none[2].all()

import numpy as np
import pytest

from magkf.errors import InputError
from magkf.offline.ellipsoid import EllipsoidCalibrator, parameter_names, patent_matrix, patent_parameters

from ..stats import assert_biased, assert_standard_normal

TRUTH3 = (np.array([1.1, 0.9, 1.05]), np.radians([2.0, -3.0, 1.5]), np.array([0.2, -0.1, 0.3]))
TRUTH2 = (np.array([1.1, 0.9]), np.radians([3.0]), np.array([0.2, -0.1]))


def _sample(truth, n, noise, rng):
    k, ang, b = truth
    if k.size == 3:
        u = rng.normal(size=(n, 3))
        u /= np.linalg.norm(u, axis=1)[:, None]
    else:
        th = rng.uniform(0, 2 * np.pi, n)
        u = np.column_stack([np.cos(th), np.sin(th)])
    return u @ patent_matrix(k, ang).T + b + rng.normal(scale=noise, size=u.shape)


def _vector(truth):
    k, ang, b = truth
    return np.concatenate([k, np.degrees(ang), b])


@pytest.mark.parametrize("truth", [TRUTH3, TRUTH2])
def test_patent_decomposition_round_trip(truth):
    k, ang, _ = truth
    K = patent_matrix(k, ang)
    k2, ang2 = patent_parameters(K @ K.T)
    assert np.allclose(k2, k) and np.allclose(ang2, ang)


@pytest.mark.parametrize("truth", [TRUTH3, TRUTH2])
def test_noiseless_fit_is_exact(truth):
    X = _sample(truth, 500, 0.0, np.random.default_rng(5))
    r = EllipsoidCalibrator(len(truth[0]), 1.0).fit(X).result_
    names = parameter_names(len(truth[0]))
    assert np.allclose([r.algebraic[n] for n in names], _vector(truth), atol=1e-9)
    assert np.allclose([r.parameters[n] for n in names], _vector(truth), atol=1e-9)
    assert r.residual_rms < 1e-9


@pytest.mark.slow
@pytest.mark.parametrize("truth,runs", [(TRUTH3, 100), (TRUTH2, 100)])
def test_refined_fit_unbiased_algebraic_biased(truth, runs):
    """Monte Carlo (seeded): refined errors are N(0, SE^2); the algebraic sensitivities are biased."""
    rng = np.random.default_rng(6)
    d = len(truth[0])
    names = parameter_names(d)
    z, alg_err = [], []
    for _ in range(runs):
        r = EllipsoidCalibrator(d, 1.0).fit(_sample(truth, 300, 0.05, rng)).result_
        est = np.array([r.parameters[n] for n in names])
        se = np.array([r.standard_errors[n] for n in names])
        z.append((est - _vector(truth)) / se)
        alg_err.append(r.algebraic["kx"] - truth[0][0])
    assert_standard_normal(z, label=f"{d}-axis refined")
    assert_biased(alg_err, label=f"{d}-axis algebraic kx")


def test_partial_coverage_is_reported():
    """A cap of the sphere: the fit runs, reports its coverage and names the poorly determined parameters."""
    rng = np.random.default_rng(9)
    k, ang, b = TRUTH3
    u = rng.normal(size=(600, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    u = u[u[:, 2] > 0.6]
    X = u @ patent_matrix(k, ang).T + b + rng.normal(scale=0.02, size=u.shape)
    r = EllipsoidCalibrator(3, 1.0).fit(X).result_
    assert r.coverage < 0.3
    assert r.poorly_determined and any("cover only" in w for w in r.warnings)


def test_too_few_samples():
    with pytest.raises(InputError, match="too few samples"):
        EllipsoidCalibrator(3).fit(np.random.default_rng(0).normal(size=(20, 3)))


@pytest.mark.slow
def test_a_patch_of_the_sphere_stops_unconverged():
    """The first 120 s of a simulated drive turn the field through under 1 % of the sphere: the refinement stops
    at its iteration limit instead of wandering for tens of thousands of iterations (16 s) to an ellipsoid with
    offsets of 1e9, says so, and marks every parameter poorly determined."""
    from magkf.sim import DriveConfig, simulate_drive

    sim = simulate_drive(DriveConfig(seed=1))
    t = sim.table.index.to_numpy()
    m = sim.table[["mag_x", "mag_y", "mag_z"]].to_numpy()[t <= t[0] + 120.0]
    r = EllipsoidCalibrator(3, 50_000.0).fit(m[np.all(np.isfinite(m), axis=1)]).result_
    assert not r.converged and r.coverage < 0.01
    assert len(r.poorly_determined) == 9 and any("did not converge" in w for w in r.warnings)

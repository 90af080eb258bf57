import numpy as np
import pytest

from magkf.offline.sinefit import PARAMETER_NAMES, SineFitCalibrator, fit_sine
from magkf.sim import PAPER_EXAMPLE, simulate_turntable

from ..stats import assert_standard_normal

B, INC = 50_000.0, 43.0
TRUTH = PAPER_EXAMPLE.as_vector()


def test_fit_sine_noiseless():
    angle = np.arange(0, 360, 10.0)
    c = fit_sine(angle, 123.0 * np.sin(np.radians(angle + 250.0)) - 7.0)
    assert (
        c.amplitude == pytest.approx(123.0) and c.phase_deg == pytest.approx(250.0) and c.offset == pytest.approx(-7.0)
    )


@pytest.mark.slow
def test_fit_sine_standard_errors_monte_carlo():
    rng = np.random.default_rng(3)
    angle = np.arange(0, 360, 7.5)
    z = []
    for _ in range(400):
        c = fit_sine(angle, 50 * np.sin(np.radians(angle + 30)) + 5 + rng.normal(scale=4, size=angle.size))
        z.append(
            [(c.amplitude - 50) / c.amplitude_se, (c.phase_deg - 30) / c.phase_se_deg, (c.offset - 5) / c.offset_se]
        )
    assert_standard_normal(z, label="sine curve")


@pytest.mark.slow
def test_exact_errors_match_standard_errors_monte_carlo():
    """With zero-mean noise the exact method's errors agree with its standard errors (seeded)."""
    rng = np.random.default_rng(4)
    z = []
    for _ in range(150):
        table = simulate_turntable(PAPER_EXAMPLE, B, INC, 5.0, 15.0, rng=rng, heading_offsets_deg=(20.0, 70.0))
        r = SineFitCalibrator(B, INC).fit(table).result_
        se = np.array([r.standard_errors[k] for k in PARAMETER_NAMES])
        z.append((r.parameters.as_vector() - TRUTH) / se)
    assert_standard_normal(z, label="sine fit")


def test_positive_sensitivities_resolve_the_flip_symmetry():
    """Sensor turned 180 deg about z with table headings + 180 deg fits equally: kx, ky, kz > 0 decide."""
    from magkf.offline.sinefit import SineFitParameters

    truth = SineFitParameters(1.2, 20.0, 0.8, 1.03, 0.98, 1.01, (250.0, -140.0, 320.0))
    table = simulate_turntable(truth, 48_000.0, 64.0, 5.0, 20.0, np.random.default_rng(1))
    r = SineFitCalibrator(48_000.0, 64.0).fit(table).result_
    p = r.parameters
    assert p.kx > 0 and p.ky > 0 and p.kz > 0
    z = (p.as_vector() - truth.as_vector()) / np.array([r.standard_errors[k] for k in PARAMETER_NAMES])
    assert np.all(np.abs(z) < 4.5)  # 9 parameters, |z| < 4.5 fails by chance with probability < 1e-4


def test_exact_jacobian_matches_finite_differences():
    from magkf.offline.sinefit import PLANES, _unpack, exact_jacobian, model_residuals

    table = simulate_turntable(PAPER_EXAMPLE, B, INC, 30.0, 5.0, np.random.default_rng(2))
    data = [
        (
            p,
            table[table.plane == p].angle_deg.to_numpy(),
            table[table.plane == p][["mag_x", "mag_y", "mag_z"]].to_numpy(),
        )
        for p in PLANES
    ]
    x = np.concatenate([np.radians(TRUTH[:3]), TRUTH[3:], np.radians([10.0, -20.0])])

    def resid(x):
        return model_residuals(_unpack(x), data, B, INC, np.degrees(x[9:11]), -1)

    step = 1e-7 * np.maximum(np.abs(x), 1.0)
    fd = np.column_stack(
        [(resid(x + np.eye(11)[j] * step[j]) - resid(x - np.eye(11)[j] * step[j])) / (2 * step[j]) for j in range(11)]
    )
    assert np.allclose(exact_jacobian(x, data, B, INC, -1), fd, rtol=1e-5, atol=1e-3)

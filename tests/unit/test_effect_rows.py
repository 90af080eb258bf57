"""Every effect at a range or a set of epochs equals the same rows of it on all of them (seeded)."""

from dataclasses import replace

import numpy as np
import pytest

from magkf.config import FilterConfig
from magkf.effects import BUILTIN, Effect, LinearEffect, SoftHardIron
from magkf.io.drivelog import DriveLog
from magkf.online.prepare import prepare
from magkf.online.state import StateLayout
from magkf.sim import DriveConfig, simulate_drive


class Wheel(LinearEffect):
    """A user's linear effect written without ``rows`` (as ``docs/examples/wheel_magnet.py``)."""

    name = "wheel"
    parameter_names = ("a_x", "a_y", "a_z")

    def design(self, data):
        angle = np.radians(data.columns["temp_c"] * 10.0)
        G = np.zeros((len(angle), 3, 3))
        G[:, [0, 1, 2], [0, 1, 2]] = np.cos(angle)[:, None]
        return G


class Squared(Effect):
    """A user's nonlinear effect written without ``rows``: its contribution and its Jacobian by the base's
    finite differences."""

    name = "squared"
    parameter_names = ("s",)
    linear = False

    def contribution(self, theta, data):
        theta = np.asarray(theta, float)
        return theta[:, :1, None] ** 2 * data.field_body if theta.ndim == 2 else theta[0] ** 2 * data.field_body


@pytest.fixture(scope="module")
def data():
    sim = simulate_drive(DriveConfig(duration_s=120.0, rate_hz=20, motion="3d", seed=5))
    d = prepare(DriveLog(sim.table), FilterConfig()).data
    gap = slice(700, 760)  # a stretch without attitude: the field and its rate unknown
    body, rate = d.field_body.copy(), d.field_body_rate.copy()
    body[gap], rate[gap] = np.nan, np.nan
    return replace(d, field_body=body, field_body_rate=rate, R0=np.diag([1.01, 0.99, 1.0]))


def _effects():
    rng = np.random.default_rng(3)
    out = [(SoftHardIron(), np.r_[np.eye(3).ravel() + rng.normal(0, 0.01, 9), rng.normal(0, 100, 3)])]
    for cls in BUILTIN.values():
        e = cls()
        out.append((e, rng.normal(0, 1, e.size) * e.prior()[1] * 0.1))
    out.append((BUILTIN["time_lag"](), np.array([-0.37])))  # a lead, across the gap
    out.append((BUILTIN["time_lag"](), np.array([2.3])))  # a lag of many epochs
    return out + [(Wheel(), np.array([1.0, 2.0, 3.0])), (Squared(), np.array([0.5]))]


def _rows(n):
    rng = np.random.default_rng(11)
    mask = rng.random(n) < 0.3
    return [slice(0, 1), slice(0, 100), slice(650, 720), slice(755, 1300), slice(n - 37, n), slice(n - 1, n)] + [
        np.sort(rng.choice(n, 200, replace=False)),
        mask,
    ]


@pytest.mark.parametrize("effect,theta", _effects(), ids=lambda v: getattr(v, "name", ""))
def test_rows_equal_the_whole_logs_rows(data, effect, theta):
    whole = {
        "regressors": effect.regressors(data),
        "jacobian": effect.jacobian(theta, data),
        "contribution": effect.contribution(theta, data),
        "sigma points": effect.contribution(np.stack([theta, 0.5 * theta]), data),
    }
    assert whole["regressors"].shape[:2] == (len(data), 3)
    for rows in _rows(len(data)):
        part = {
            "regressors": effect.regressors(data, rows=rows),
            "jacobian": effect.jacobian(theta, data, rows=rows),
            "contribution": effect.contribution(theta, data, rows=rows),
            "sigma points": effect.contribution(np.stack([theta, 0.5 * theta]), data, rows=rows),
        }
        for what, values in part.items():
            expected = whole[what][:, rows] if what == "sigma points" else whole[what][rows]
            np.testing.assert_array_equal(values, expected, err_msg=f"{effect.name} {what} at {rows!r}")


def test_layout_at_rows_equals_its_rows(data):
    layout = StateLayout.with_core([BUILTIN["time_lag"](), BUILTIN["temperature_bias"](), BUILTIN["bias_drift"]()])
    x = layout.prior()[0] + 0.01
    H = layout.linear_jacobian(data)
    rows = slice(300, 900)
    np.testing.assert_array_equal(layout.linear_jacobian(data, rows=rows), H[rows])
    np.testing.assert_array_equal(layout.extra_terms(x, H[rows], data, rows=rows), layout.extra_terms(x, H, data)[rows])

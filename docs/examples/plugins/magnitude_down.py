"""A measurement model: the calibrated field's magnitude and its down component, two rows that no heading error
changes. For logs whose logged heading came from this magnetometer (ArduPilot's and PX4's estimators fuse the
compass into yaw), where the vector model would partly calibrate the magnetometer against itself.

    FilterConfig(measure="magnitude_down")            in Python, once this module is imported
    magkf calibrate LOG.bin --measure magnitude_down  once a package installs it (group magkf.measurements)

It implements the four methods of ``MeasurementModel``; the EKF's, the UKF's, the batch solver's, the real-time
step's and the noise learner's rows all come from them.
"""

import numpy as np

from magkf.conventions import calibrated_field, inverse3
from magkf.online.measurements import MeasurementModel, register_measurement

DOWN = np.array([0.0, 0.0, 1.0])


@register_measurement
class MagnitudeAndDown(MeasurementModel):
    """``|c|`` and ``(C_nb c)_d`` of the calibrated body field ``c = R^-1 (m - b - e)`` against the reference's
    magnitude and down component (nT)."""

    name = "magnitude_down"
    rows = 2
    needs_attitude = True  # the down axis in the body frame comes from the logged roll and pitch
    needs_data = True  # it reads the epochs' attitude and reference field (``Block.data``)
    noise_depends_on_state = True  # the noise passes through R^-1

    def measure(self, blk):
        """(k, 2) nT: the reference's magnitude and down component."""
        return np.column_stack([blk.ref_mag, blk.data.field_ned[:, 2]])

    def predict(self, x, blk):
        """(k, 2) nT for a state (n,); (S, k, 2) for a stack of states (S, n)."""
        x = np.asarray(x, float)
        if x.ndim == 2:
            return np.stack([self.predict(state, blk) for state in x])
        c = self._calibrated(x, blk)
        down = np.einsum("ki,ki->k", self._down(blk), c)
        return np.column_stack([np.linalg.norm(c, axis=1), down])

    def jacobian(self, x, blk):
        """(k, 2, n): for a row ``a^T c`` (``a`` the unit field for the magnitude, the body-frame down axis for the
        down component) and ``w = a^T R^-1``: ``-w_i c_j`` for ``R_ij``, ``-w`` for ``b``, ``-w de/dtheta`` for an
        effect's parameters."""
        layout = self.layout
        c = self._calibrated(x, blk)
        Rinv = inverse3(layout.R(x))
        rows = np.stack([c / np.linalg.norm(c, axis=1)[:, None], self._down(blk)], axis=1)  # (k, 2, 3)
        w = rows @ Rinv
        H = np.zeros((len(c), 2, layout.size))
        H[:, :, layout.R_INDEX] = -(w[:, :, :, None] * c[:, None, None, :]).reshape(len(c), 2, 9)
        H[:, :, layout.B_INDEX] = -w
        if layout.has_extra:
            H[:, :, layout.EXTRA] = -w @ layout.jacobian(x, blk.data, blk.H)[:, :, layout.EXTRA]
        return H

    def covariance(self, x, blk):
        """(k, 2, 2) nT^2: the sensor noise through ``R^-1`` onto the two rows, the reference's uncertainty on
        both, and the tilt error's on the down component (a tilt turns the horizontal field into it)."""
        n = self.noise
        c = self._calibrated(x, blk)
        Rinv = inverse3(self.layout.R(x))
        w = np.stack([c / np.linalg.norm(c, axis=1)[:, None], self._down(blk)], axis=1) @ Rinv
        cov = n.sensor_nt**2 * (w @ np.swapaxes(w, 1, 2)) + n.reference_nt**2 * np.eye(2)
        horizontal = np.hypot(blk.data.field_ned[:, 0], blk.data.field_ned[:, 1])
        cov[:, 1, 1] += (n.attitude_rad * horizontal) ** 2
        return cov

    def structure(self, field_body, R, heading=None):
        """No field frame in these rows (the default is the sensor-frame vector's): the noise learner takes the
        magnitude row alone (``along_across``)."""
        return None

    def along_across(self, innovation, frame=None):
        """The magnitude row is along the field; the down component mixes along and across the field, and the
        learner leaves it out."""
        return innovation[:, 0], None

    def _calibrated(self, x, blk):
        """The calibrated body field (k, 3) nT at state ``x`` (n,), the added effects' terms taken off."""
        R, b = self.layout.R_b(x)
        e = np.nan_to_num(self.layout.extra_terms(x, blk.H, blk.data)) if self.layout.has_extra else 0.0
        return calibrated_field(R, b, blk.m, e)

    @staticmethod
    def _down(blk):
        """The down axis (k, 3) in the body frame: the last row of ``C_nb``."""
        return blk.data.c_nb[:, 2, :]

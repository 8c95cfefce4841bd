"""A constant-velocity Kalman filter on SE(3) that knows the object's symmetries.

State: translation ``t`` (3,) metres and its velocity (metres per frame); rotation ``R``
(3, 3) and its angular velocity (a rotation vector per frame, camera frame:
``R(k+1) = exp(w) R(k)``). Translation and rotation each run the same two-state
(position, velocity) Kalman filter per axis, the rotation on the tangent space at the
prediction (the residual is the rotation vector ``log(R_meas R_predᵀ)``). A constant-velocity
model has no steady-state lag on an object moving at constant velocity, so the filtered pose
lags it by well under one frame, unlike a low-pass filter. A residual far beyond the expected
noise (a change of motion) makes the filter forget faster (the covariance is scaled up by the
squared normalized residual over ``manoeuvre_gate``²), so the smoothing can be strong at rest
without lagging behind a manoeuvre.

Symmetries: before an update the measured pose is replaced by its symmetry-equivalent pose
(``R S_R``, ``R S_t + t`` for each model-frame symmetry ``S``) nearest the prediction, so a
flip between equivalent poses is no motion.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from dope_hope.inference.tracking_settings import TrackingSettings


def closest_equivalent(R: np.ndarray, t: np.ndarray, R_ref: np.ndarray,
                       symmetries: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """The symmetry-equivalent pose of (R, t) whose rotation is nearest ``R_ref``.

    Args:
        R: (3, 3), t: (3,) metres: a pose ``x_c = R x + t``.
        R_ref: (3, 3) the reference rotation (a track's prediction).
        symmetries: (S, 4, 4) model-frame symmetry transforms, metres, identity first.

    Returns:
        (R' (3, 3), t' (3,), angle between R' and R_ref in degrees).
    """
    S = np.asarray(symmetries, dtype=np.float64).reshape(-1, 4, 4)
    Rs = R @ S[:, :3, :3]                                  # (S, 3, 3)
    cos = (np.einsum("sij,ij->s", Rs, R_ref) - 1.0) / 2.0  # trace(R_s R_refᵀ)
    k = int(np.argmax(cos))
    angle = float(np.degrees(np.arccos(np.clip(cos[k], -1.0, 1.0))))
    return Rs[k], R @ S[k, :3, 3] + t, angle


class _ConstantVelocity:
    """Two-state (position, velocity) Kalman filter shared by three axes (isotropic noise).

    A residual larger than ``manoeuvre_gate`` standard deviations of its prediction (mean over
    the axes) scales the covariance up before the update: the filter forgets faster while the
    motion changes (an object starting, stopping or turning), and smooths hard while it does not.
    A residual beyond ``outlier_gate`` standard deviations is not applied (``correct`` returns
    False).
    """

    def __init__(self, x: np.ndarray, measurement_std: float, acceleration_std: float,
                 manoeuvre_gate: float = 2.0, outlier_gate: float = float("inf")):
        self.x = np.asarray(x, dtype=np.float64).reshape(3).copy()
        self.v = np.zeros(3)
        self.r = float(measurement_std) ** 2
        self.q = float(acceleration_std) ** 2
        self.gate2 = float(manoeuvre_gate) ** 2
        self.outlier2 = float(outlier_gate) ** 2
        # covariance of (position, velocity): the first measurement, velocity unknown
        self.P = np.array([[self.r, 0.0], [0.0, 1e6 * max(self.r, 1e-12)]])

    def predict(self, dt: float) -> None:
        F = np.array([[1.0, dt], [0.0, 1.0]])
        Q = self.q * np.array([[dt ** 4 / 4, dt ** 3 / 2], [dt ** 3 / 2, dt ** 2]])
        self.x = self.x + self.v * dt
        self.P = F @ self.P @ F.T + Q

    def correct(self, residual: np.ndarray, noise_scale: float = 1.0) -> bool:
        """Apply a measurement residual (measurement - prediction) whose noise is
        ``noise_scale`` times the usual; False when it is an outlier."""
        r = self.r * noise_scale ** 2
        s = self.P[0, 0] + r
        d2 = float(residual @ residual) / (3.0 * s)
        if d2 > self.outlier2:
            return False
        if d2 > self.gate2:
            self.P = self.P * (d2 / self.gate2)
            s = self.P[0, 0] + r
        gain = self.P[:, 0] / s
        self.x = self.x + gain[0] * residual
        self.v = self.v + gain[1] * residual
        self.P = self.P - np.outer(gain, self.P[0, :])
        return True


class PoseFilter:
    """Constant-velocity filter of one object's pose (module docstring).

    Args:
        R: (3, 3), t: (3,) metres: the first measurement.
        symmetries: (S, 4, 4) model-frame symmetries, metres, identity first.
        settings: the tracker's :class:`TrackingSettings`; the filter uses
            translation_std_m: measurement noise of t, metres.
            acceleration_m: change of velocity per frame the model allows (std), metres/frame².
            rotation_std_deg: measurement noise of R, degrees.
            angular_acceleration_deg: change of angular velocity per frame (std), degrees/frame².
            rotation_gate_deg: a measured rotation farther than this from the prediction (after
            the symmetries) is an outlier: the rotation is not corrected by it.
            rotation_reset: after this many outliers in a row the measured rotation is taken as is.
            manoeuvre_gate: residuals beyond this many standard deviations make the filter forget
            faster (see the module docstring).
            outlier_gate: a measured translation beyond this many standard deviations of the
            prediction is an outlier (a depth line search fooled by an occluder, say): not
            applied. After ``rotation_reset`` outliers in a row whose successive translations
            lie within ``gate_m`` metres of each other (the object did move there) the filter
            restarts from the measurements.
    """

    def __init__(self, R: np.ndarray, t: np.ndarray, symmetries: np.ndarray,
                 settings: TrackingSettings = TrackingSettings()):
        s = settings
        self.symmetries = np.asarray(symmetries, dtype=np.float64).reshape(-1, 4, 4)
        self._t_noise = (s.translation_std_m, s.acceleration_m, s.manoeuvre_gate, s.outlier_gate)
        self._t = _ConstantVelocity(t, *self._t_noise)
        self.jump_m = float(s.gate_m)
        self.translation_outliers: list[np.ndarray] = []
        self._rot_noise = (np.radians(s.rotation_std_deg), np.radians(s.angular_acceleration_deg), s.manoeuvre_gate)
        self._R = np.asarray(R, dtype=np.float64).reshape(3, 3).copy()
        self._w = _ConstantVelocity(np.zeros(3), *self._rot_noise)
        self.rotation_gate_deg = float(s.rotation_gate_deg)
        self.rotation_reset = int(s.rotation_reset)
        self.rotation_outliers = 0

    @property
    def t(self) -> np.ndarray:
        """(3,) filtered translation, metres."""
        return self._t.x.copy()

    @property
    def R(self) -> np.ndarray:
        """(3, 3) filtered rotation."""
        return Rotation.from_rotvec(self._w.x).as_matrix() @ self._R

    @property
    def velocity(self) -> np.ndarray:
        """(3,) translation velocity, metres per frame."""
        return self._t.v.copy()

    def predict(self, dt: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """Advance ``dt`` frames; returns the predicted (R (3, 3), t (3,))."""
        self._rebase()
        self._t.predict(dt)
        self._w.predict(dt)
        return self.R, self.t

    def update(self, R: np.ndarray, t: np.ndarray, noise_scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """Correct the prediction with a measured pose; returns the filtered (R, t).

        The measurement is first replaced by its symmetry-equivalent pose nearest the
        prediction (:func:`closest_equivalent`). ``noise_scale``: its noise relative to the
        configured measurement noise (a less certain detection moves the filter less)."""
        R_pred = self.R
        R_m, t_m, angle = closest_equivalent(np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64),
                                             R_pred, self.symmetries)
        if self._t.correct(t_m - self._t.x, noise_scale):
            self.translation_outliers = []
        else:
            self._translation_outlier(t_m)
        if angle <= self.rotation_gate_deg:
            self.rotation_outliers = 0
            self._w.correct(Rotation.from_matrix(R_m @ R_pred.T).as_rotvec(), noise_scale)
        else:
            self.rotation_outliers += 1
            if self.rotation_outliers >= self.rotation_reset:
                self._R, self.rotation_outliers = R_m, 0
                self._w = _ConstantVelocity(np.zeros(3), *self._rot_noise)
        return self.R, self.t

    def _translation_outlier(self, t_m: np.ndarray) -> None:
        """Count an outlying translation; restart from the last two when they agree."""
        out = self.translation_outliers
        if out and np.linalg.norm(t_m - out[-1]) > self.jump_m:
            out.clear()
        out.append(t_m)
        if len(out) >= self.rotation_reset:
            self._t = _ConstantVelocity(out[-2], *self._t_noise)
            self._t.predict(1.0)
            self._t.correct(out[-1] - self._t.x)
            out.clear()

    def _rebase(self) -> None:
        """Fold the rotation-vector offset into the reference rotation (keeps it small)."""
        self._R = self.R
        self._w.x = np.zeros(3)

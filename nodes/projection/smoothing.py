"""Pose smoothing for the tracker: a One Euro filter on translation and its rotation analogue."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def _one_euro_alpha(cutoff_hz: float, dt: float) -> float:
    tau = 1.0 / (2.0 * np.pi * cutoff_hz)
    return 1.0 / (1.0 + tau / dt)


class PoseSmoother:
    """One Euro filter on translation and its rotation analogue (adaptive slerp toward the new pose)."""

    def __init__(self, min_cutoff_hz: float, beta: float, d_cutoff_hz: float) -> None:
        self.min_cutoff, self.beta, self.d_cutoff = min_cutoff_hz, beta, d_cutoff_hz
        self.t_hat: np.ndarray | None = None
        self.r_hat: Rotation | None = None
        self.v_hat = 0.0  # filtered translation speed, mm/s
        self.w_hat = 0.0  # filtered angular speed, deg/s
        self.time = 0.0

    def reset(self) -> None:
        self.t_hat, self.r_hat, self.v_hat, self.w_hat = None, None, 0.0, 0.0

    def update(self, T: np.ndarray, time_s: float) -> np.ndarray:
        """Filtered pose for the raw pose ``T`` observed at ``time_s``."""
        t, r = T[:3, 3].copy(), Rotation.from_matrix(T[:3, :3])
        if self.t_hat is None or self.r_hat is None or time_s <= self.time:
            self.t_hat, self.r_hat, self.time = t, r, time_s
            return T.copy()
        dt = time_s - self.time
        self.time = time_s
        a_d = _one_euro_alpha(self.d_cutoff, dt)
        self.v_hat += a_d * (np.linalg.norm(t - self.t_hat) / dt - self.v_hat)
        a_t = _one_euro_alpha(self.min_cutoff + self.beta * self.v_hat, dt)
        self.t_hat = self.t_hat + a_t * (t - self.t_hat)
        delta = self.r_hat.inv() * r
        self.w_hat += a_d * (np.rad2deg(delta.magnitude()) / dt - self.w_hat)
        a_r = _one_euro_alpha(self.min_cutoff + self.beta * self.w_hat, dt)
        self.r_hat = self.r_hat * Rotation.from_rotvec(a_r * delta.as_rotvec())
        out = np.eye(4)
        out[:3, :3] = self.r_hat.as_matrix()
        out[:3, 3] = self.t_hat
        return out

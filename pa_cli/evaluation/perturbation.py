"""The pose perturbation model of the plane-adjustment papers (`pa perturb`).

Poses are T_world_scan (N, 4, 4), metres; sigmas are radians and metres inside the library.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

# The four perturbation levels of Zhou, "Efficient Second-Order Plane Adjustment", section 5.2:
# level -> (sigma_rot_deg, sigma_trans_m).
PERTURBATION_LEVELS: dict[int, tuple[float, float]] = {1: (0.1, 0.01), 2: (1.0, 0.1), 3: (2.0, 0.2), 4: (3.0, 0.3)}


def perturb_poses(T_world_scan: np.ndarray, sigma_rot_rad: float, sigma_trans_m: float,
                  rng: np.random.Generator, keep_first: bool = False) -> np.ndarray:
    """Perturb poses with the model of seed 000, section 5.2; returns new (N, 4, 4) poses.

    t <- t + N(0, sigma_trans_m^2 I) and R <- Exp(w) R with w ~ N(0, sigma_rot_rad^2 I) (a left,
    world-frame rotation perturbation). Noise is drawn for every pose (rotations first, then
    translations) so the noise of pose k does not depend on `keep_first`; with `keep_first`
    pose 0 is then restored unchanged.
    """
    if sigma_rot_rad < 0 or sigma_trans_m < 0:
        raise ValueError("perturbation sigmas must be non-negative")
    T = np.array(T_world_scan, dtype=np.float64, copy=True)
    n = len(T)
    w = rng.normal(0.0, 1.0, size=(n, 3)) * sigma_rot_rad
    dt = rng.normal(0.0, 1.0, size=(n, 3)) * sigma_trans_m
    T_out = T.copy()
    T_out[:, :3, :3] = Rotation.from_rotvec(w).as_matrix() @ T[:, :3, :3]
    T_out[:, :3, 3] = T[:, :3, 3] + dt
    if keep_first and n:
        T_out[0] = T[0]
    return T_out

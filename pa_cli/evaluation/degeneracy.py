"""Which directions of each scan's pose the planes constrain, from the information they carry.

For scan j the plane information is the 6x6 diagonal block of the (Gauss-Newton, positive
semi-definite) Hessian of the plane cost, H_j (m^2 per rad^2 and per m^2 of the left
retraction (omega, rho), world frame): how fast the sum of squared point-to-plane distances
grows when that scan alone moves. Rotations are turned into metres with a lever arm L
(`advanced.degeneracy.lever_arm_m`): omega = theta / L with theta in metres, so the scaled block
is S H_j S, S = diag(1/L, 1/L, 1/L, 1, 1, 1), and every eigenvalue is in m^2 per m^2. A point on
a plane square to a direction adds 2 to it (its squared distance grows as 1 * dx^2, and the
Hessian of x^2 is 2), so eigenvalue / 2 reads as "as constrained as that many points".

The eigenvector of the smallest eigenvalue is the weakest direction, put in words in a frame
of the trajectory: the vertical (world z), the direction of travel (from the neighbouring
poses; the sensor's x axis when standing) and the lateral axis (vertical x travel).

A scan is held only by odometry in a direction when, along an eigenvector v of its scaled plane
information, the odometry factors' information (their diagonal block, same scaling) exceeds the
planes': v^T H_odometry v > v^T H_planes v. Those directions follow the odometry, not the planes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pa_cli.adjust.newton import FeatureCost
from pa_cli.core.problem import FeatureProblem

MOSTLY = 0.8  # a direction is named after one axis when that axis carries this share of its length


@dataclass
class Degeneracy:
    """Per scan, the weakest direction of its feature information (`per_scan`: scan,
    smallest_eigenvalue, points_equivalent, direction in words), and the scans the odometry holds
    more than the features in some direction (`held_by_odometry`: scan, directions)."""

    lever_arm_m: float
    per_scan: list[dict[str, Any]]
    held_by_odometry: list[dict[str, Any]]

    @property
    def held_by_odometry_scans(self) -> list[int]:
        """The scans of `held_by_odometry`."""
        return [h["scan"] for h in self.held_by_odometry]

    def as_report(self) -> dict[str, Any]:
        """The `degeneracy` section of the refine report."""
        return {"lever_arm_m": self.lever_arm_m, "per_scan": self.per_scan, "held_by_odometry": self.held_by_odometry,
                "held_by_odometry_scans": self.held_by_odometry_scans}


def plane_information(problem: FeatureProblem, T_world_scan: np.ndarray) -> np.ndarray:
    """(N, 6, 6) per-scan information of the problem's features (planes, and edges when it has
    them): the diagonal blocks of the Gauss-Newton Hessian."""
    return FeatureCost(problem).scan_information(T_world_scan)


def scaled(H: np.ndarray, lever_arm_m: float) -> np.ndarray:
    """S H S with S = diag(1/L x3, 1 x3): rotation coordinates in metres at the lever arm."""
    s = np.r_[np.full(3, 1.0 / lever_arm_m), np.ones(3)]
    return H * s[:, None] * s[None, :]


def travel_frames(T_world_scan: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rows: vertical, direction of travel, lateral axis (world frame, unit)."""
    t = T_world_scan[:, :3, 3]
    n = len(t)
    idx = np.arange(n)
    travel = t[np.minimum(idx + 1, n - 1)] - t[np.maximum(idx - 1, 0)]
    up = np.array([0.0, 0.0, 1.0])
    travel = travel - np.outer(travel @ up, up)
    norm = np.linalg.norm(travel, axis=1)
    forward = T_world_scan[:, :3, 0] - np.outer(T_world_scan[:, :3, 0] @ up, up)
    standing = norm < 1e-6
    travel[standing] = forward[standing]
    travel /= np.maximum(np.linalg.norm(travel, axis=1, keepdims=True), 1e-12)
    lateral = np.cross(up, travel)
    return np.stack([np.broadcast_to(up, (n, 3)), travel, lateral], axis=1)


_TRANSLATION_WORDS = ("vertical translation", "translation along the direction of travel",
                      "sideways translation (across the direction of travel)")
_ROTATION_WORDS = ("rotation about the vertical (yaw)", "rotation about the direction of travel (roll)",
                   "rotation about the lateral axis (pitch)")


def describe(direction: np.ndarray, frame: np.ndarray) -> str:
    """Words for a unit 6-vector (scaled rotation, translation) in a frame (rows: up, travel, lateral)."""
    rot, trans = direction[:3], direction[3:]
    is_rotation = np.linalg.norm(rot) >= np.linalg.norm(trans)
    part = rot if is_rotation else trans
    words = _ROTATION_WORDS if is_rotation else _TRANSLATION_WORDS
    coords = frame @ (part / max(np.linalg.norm(part), 1e-300))
    axis = int(np.argmax(np.abs(coords)))
    text = words[axis]
    if abs(coords[axis]) < MOSTLY:
        text = "mostly " + text
    if min(np.linalg.norm(rot), np.linalg.norm(trans)) > (1.0 - MOSTLY) * np.linalg.norm(direction):
        text += " coupled with " + ("translation" if is_rotation else "rotation")
    return text


def scan_degeneracy(problem: FeatureProblem, T_world_scan: np.ndarray, lever_arm_m: float,
                    odometry_information: np.ndarray | None = None) -> Degeneracy:
    """Per scan: smallest scaled plane-information eigenvalue (m^2/m^2) and its direction in
    words, and the scans held only by odometry in some direction (with that direction).

    `odometry_information` (N, 6, 6): the odometry factors' diagonal Hessian blocks (same units
    as the plane cost); None: no factors, and a scan is listed when its smallest eigenvalue is 0.
    """
    H = scaled(plane_information(problem, T_world_scan), lever_arm_m)
    lam, vec = np.linalg.eigh(H)
    frames = travel_frames(T_world_scan)
    per_scan = []
    held: list[dict[str, Any]] = []
    for j in range(problem.n_scans):  # per-scan report: 6x6 work per scan
        v = vec[j, :, 0]
        per_scan.append({"scan": j, "smallest_eigenvalue": float(max(lam[j, 0], 0.0)),
                         "points_equivalent": float(max(lam[j, 0], 0.0) / 2.0),
                         "direction": describe(v, frames[j])})
        if odometry_information is not None:
            O = scaled(odometry_information[j], lever_arm_m)
            odo = np.einsum("ik,ij,jk->k", vec[j], O, vec[j])
            weak = np.flatnonzero(lam[j] < odo)
        else:
            weak = np.flatnonzero(lam[j] <= 0.0)
        if len(weak):
            held.append({"scan": j, "directions": [describe(vec[j, :, k], frames[j]) for k in weak]})
    return Degeneracy(lever_arm_m, per_scan, held)

"""Free-space consistency of a map: no scan's points may lie in space another scan saw through.

A LiDAR return at range r along a ray says the space in front of it, along that ray, is empty. For a
pair of scans (A, B) that overlap, scan A's points are moved into scan B's frame by the pose set
(T_world_B^-1 T_world_A) and projected into B's spherical range image; a point of A that lies in
front of B's return along B's ray by more than a margin is a *violation*: under these poses, scan A
saw a surface where scan B saw through. Two copies of a room turned against each other (a broken
start) put one copy's walls inside the other's free space; a sharp map of the wrong shape is
caught here while its mean map entropy improves. A blur moves surfaces by a few centimetres and
puts points just in front of other scans' returns too; the mean map entropy judges those, within
its neighbourhood radius. A violation must therefore lie deeper than that radius (`depth_m`) in
front of the return: there the map entropy cannot see it. Moving objects violate under any pose
set, so only the change between pose sets on the same points and pairs is read, with its
standard error.

The range image (`RangeImage`) has pixels of a fixed angular size for the whole sequence, one
beam spacing by one azimuth step, measured from the scans (`pixel_size_rad`). Per pixel it keeps
the nearest return (the space in front of it was seen empty by every ray of the pixel) and a
*footprint*: how much the range changes across one pixel, measured in B's own image as the
largest difference to its eight neighbours' nearest returns and between the returns of the pixel
itself (a surface seen at a grazing angle, or an edge, changes the range across one pixel by that
much; a pixel with no neighbouring return has no such measure and is not tested). The margin of
a point is `FREE_SPACE_SIGMAS` x sqrt(2) x the range noise (two ranges are compared) plus the
footprint of its pixel plus `depth_m`: no tuned distance.

Pairs (`scan_pairs`): every consecutive pair, and every pair whose scan origins are closer than
the median range of the scans' points under some pose set (revisits), at most `MAX_PAIRS` of them
(a fixed pseudo-random subset, the consecutive pairs first); both directions of a pair are scored,
each on at most `MAX_POINTS_PER_SCAN` points of the projected scan (a fixed pseudo-random subset).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

FREE_SPACE_SIGMAS = 3.0  # a point is in front of a return when it is beyond 3 sigma of their range difference
# the KD-tree's search radius exceeds near_m by this fraction, so no pair the strict test keeps is lost to rounding
NEAR_SEARCH_MARGIN = 1e-6
MAX_PAIRS = 200  # scan pairs scored at most (each in both directions): bounds the cost on long sequences
MAX_POINTS_PER_SCAN = 8000  # points of the projected scan per direction: the fraction's binomial error is < 0.6 %
PIXEL_SIZE_SCANS = 5  # scans whose point spacing decides the pixel size (spread over the sequence)
# A pair whose violation fraction exceeds the first pose set's by this factor (and by 3 binomial standard errors) is
# contradicted by its own free space: a moved copy of a surface, not chance or a moving object (present under both).
INCONSISTENT_FACTOR = 2.0
# A gap between sorted elevations this many times their mean gap separates two rings: R rings of N / R points have
# ring gaps of about N / R mean gaps, far above 100 for any spinning LiDAR (>= 100 points per ring), and no gap of a
# ring-less pattern reaches it
RING_GAP_RATIO = 100.0


@dataclass
class RangeImage:
    """A scan's spherical range image: per pixel the nearest return (m; inf: none) and the range
    change across the pixel (m; inf: not measurable). Row = elevation from -pi/2 in steps of
    `pixel_rad[0]`, column = azimuth from -pi in steps of `pixel_rad[1]` (sensor at the scan
    frame's origin)."""

    pixel_rad: tuple[float, float]
    nearest_m: np.ndarray
    footprint_m: np.ndarray

    @classmethod
    def of(cls, points_scan: np.ndarray, pixel_rad: tuple[float, float]) -> RangeImage:
        """The range image of (N, 3) points in the scan frame."""
        shape = _image_shape(pixel_rad)
        flat, r = _pixels(np.asarray(points_scan, dtype=np.float64), pixel_rad, shape)
        nearest = np.full(shape[0] * shape[1], np.inf)
        farthest = np.full(shape[0] * shape[1], -np.inf)
        np.minimum.at(nearest, flat, r)
        np.maximum.at(farthest, flat, r)
        nearest, farthest = nearest.reshape(shape), farthest.reshape(shape)
        seen = np.isfinite(nearest)
        footprint = np.full(shape, np.inf)
        rows = np.flatnonzero(seen.any(axis=1))
        if len(rows):  # the band of rows from the lowest to the highest return: no footprint outside it
            low, n_rows = rows[0], rows[-1] + 1 - rows[0]
            padded = np.pad(nearest, 1, constant_values=np.inf)
            padded[1:-1, 0], padded[1:-1, -1] = nearest[:, -1], nearest[:, 0]  # azimuth wraps around
            band = padded[low:low + n_rows + 2]
            neighbours = np.stack([band[1 + dr:1 + dr + n_rows, 1 + dc:1 + dc + shape[1]]
                                   for dr in (-1, 0, 1) for dc in (-1, 0, 1) if dr or dc])  # (8, n_rows, columns)
            centre, seen_band = nearest[low:low + n_rows], seen[low:low + n_rows]
            both = seen_band & np.isfinite(neighbours)
            with np.errstate(invalid="ignore"):  # inf - inf where either has no return: masked out by `both`
                change = np.where(both, np.abs(neighbours - centre), -np.inf).max(axis=0)
            spread = np.maximum(np.where(seen_band, farthest[low:low + n_rows] - centre, -np.inf), change)
            footprint[low:low + n_rows] = np.where(both.any(axis=0), spread, np.inf)
        return cls(pixel_rad, nearest, footprint)

    def violations(self, points_scan: np.ndarray, noise_m: float, depth_m: float) -> np.ndarray:
        """(N,) whether each point (this scan's frame) lies in front of the pixel's nearest return by
        more than FREE_SPACE_SIGMAS sqrt(2) noise_m + the pixel's footprint + depth_m."""
        flat, r = _pixels(np.asarray(points_scan, dtype=np.float64), self.pixel_rad, self.nearest_m.shape)
        with np.errstate(invalid="ignore"):  # inf - inf: no return or no footprint, no test
            limit = self.nearest_m.ravel()[flat] - self.footprint_m.ravel()[flat]
            return r < limit - FREE_SPACE_SIGMAS * np.sqrt(2.0) * noise_m - depth_m


def _image_shape(pixel_rad: tuple[float, float]) -> tuple[int, int]:
    return int(np.ceil(np.pi / pixel_rad[0])), int(np.ceil(2.0 * np.pi / pixel_rad[1]))


def _elevation_rad(points: np.ndarray) -> np.ndarray:
    return np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1]))


def _pixels(points: np.ndarray, pixel_rad: tuple[float, float], shape: tuple[int, int]
            ) -> tuple[np.ndarray, np.ndarray]:
    """Flat pixel index and range (m) of (N, 3) points in the scan frame."""
    r = np.linalg.norm(points, axis=1)
    row = np.clip(((_elevation_rad(points) + np.pi / 2) / pixel_rad[0]).astype(np.int64), 0, shape[0] - 1)
    col = ((np.arctan2(points[:, 1], points[:, 0]) + np.pi) / pixel_rad[1]).astype(np.int64) % shape[1]
    return row * shape[1] + col, r


def pixel_size_rad(scans: Sequence[np.ndarray]) -> tuple[float, float]:
    """(elevation, azimuth) size of a pixel (rad): one beam spacing by one azimuth step, the median
    over the scans.

    The elevations between their 1st and 99th percentiles (span s, N points) are sorted: a sensor of
    R rings has R - 1 gaps of about s / R between rings and near-zero gaps within a ring. The gaps
    above RING_GAP_RATIO times the mean gap s / N are ring gaps, and the beam spacing is their
    median; with fewer than two of them (no rings: a non-repetitive pattern, or thinned points) the
    pixel is square. The azimuth step then divides the covered solid angle 2 pi (sin el_high - sin
    el_low) among the points."""
    sizes = []
    for points in scans:
        points = np.asarray(points, dtype=np.float64)
        if len(points) < 100:
            continue
        el = _elevation_rad(points)
        low, high = np.percentile(el, [1.0, 99.0])
        solid_angle = 2.0 * np.pi * (np.sin(high) - np.sin(low))
        gaps = np.diff(np.sort(el[(el >= low) & (el <= high)]))
        ring_gaps = gaps[gaps > RING_GAP_RATIO * (high - low) / len(points)]
        per_point = solid_angle / len(points)
        elevation = float(np.median(ring_gaps)) if len(ring_gaps) >= 2 else np.sqrt(per_point)
        sizes.append((elevation, per_point / elevation))
    if not sizes:
        return np.deg2rad(1.0), np.deg2rad(1.0)
    elevation, azimuth = np.median(np.array(sizes), axis=0)
    return float(elevation), float(azimuth)


def scan_pairs(T_by_pose_set: dict[str, np.ndarray], near_m: float, max_pairs: int = MAX_PAIRS) -> np.ndarray:
    """(P, 2) scan pairs (a < b): every consecutive pair and every pair whose origins lie within
    near_m under some pose set; at most max_pairs, drawn by a generator seeded with 0 (consecutive
    pairs first), sorted."""
    n = len(next(iter(T_by_pose_set.values())))
    consecutive = np.column_stack([np.arange(n - 1), np.arange(1, n)])
    revisits = near_pairs(T_by_pose_set, near_m)
    rng = np.random.default_rng(0)
    if len(consecutive) > max_pairs:
        return consecutive[np.sort(rng.choice(len(consecutive), max_pairs, replace=False))]
    take = min(len(revisits), max_pairs - len(consecutive))
    chosen = revisits[np.sort(rng.choice(len(revisits), take, replace=False))]
    pairs = np.vstack([consecutive, chosen]).astype(np.int64)
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]


def near_pairs(T_by_pose_set: dict[str, np.ndarray], near_m: float) -> np.ndarray:
    """(K, 2) scan pairs (a, b), b >= a + 2, whose origins lie closer than near_m under some pose set,
    sorted by a then b. Found by a KD-tree per pose set (memory linear in the scans and the pairs found,
    not in all pairs), each candidate then kept by the strict distance test."""
    from scipy.spatial import cKDTree

    found = []
    for T in T_by_pose_set.values():
        origins = np.ascontiguousarray(T[:, :3, 3], dtype=np.float64)
        candidates = cKDTree(origins).query_pairs(near_m * (1.0 + NEAR_SEARCH_MARGIN), output_type="ndarray")
        candidates = candidates[candidates[:, 1] - candidates[:, 0] >= 2]
        near = np.linalg.norm(origins[candidates[:, 0]] - origins[candidates[:, 1]], axis=1) < near_m
        found.append(candidates[near].astype(np.int64))
    pairs = np.unique(np.vstack([np.empty((0, 2), dtype=np.int64), *found]), axis=0)
    return pairs.reshape(-1, 2)


def point_subset(n_points: int, scan: int, max_points: int = MAX_POINTS_PER_SCAN) -> np.ndarray:
    """Sorted indices of the points of a scan scored when it is projected: all when they fit, else
    max_points drawn by a generator seeded with the scan's index (the same for every pose set)."""
    if n_points <= max_points:
        return np.arange(n_points)
    return np.sort(np.random.default_rng(scan).choice(n_points, max_points, replace=False))


def free_space_check(scans_by_pose_set: dict[str, Sequence[np.ndarray]], T_by_pose_set: dict[str, np.ndarray],
                     noise_m: float, depth_m: float, max_pairs: int = MAX_PAIRS) -> dict[str, Any]:
    """The violation fractions of each pose set on the same pairs and points (module docstring).

    `scans_by_pose_set[name][k]`: scan k's (N_k, 3) points in its frame as that pose set sees them
    (the same points in the same order for every pose set; pose sets given one sequence object share
    its projected points and range images, which depend on the points alone); `T_by_pose_set[name]`: (N, 4, 4)
    T_world_scan; the first pose set is the reference of the changes. `noise_m`: the range noise
    (m); `depth_m`: how much deeper than the margin of noise and footprint a violation lies (m;
    the map entropy's radius). Returns `pixel_deg` (elevation, azimuth), `near_m`, `noise_m`,
    `depth_m`, `n_pairs`, `violation_fraction` (per pose set: the mean over the pairs' directions
    of violations / points projected), `change_standard_error` (per later pose set: the standard
    deviation of the per-direction changes over the square root of their count) and
    `inconsistent_pairs` (per later pose set: the pairs, either direction, whose fraction rose by
    more than INCONSISTENT_FACTOR times and by more than 3 binomial standard errors of its points;
    their violations then are neither chance nor a moving object the first pose set shares).
    """
    names = list(T_by_pose_set)
    first = scans_by_pose_set[names[0]]
    n = len(T_by_pose_set[names[0]])
    spread = np.linspace(0, n - 1, min(n, PIXEL_SIZE_SCANS)).astype(int)
    samples = [np.asarray(first[k], dtype=np.float64) for k in spread]
    pixel_rad = pixel_size_rad(samples)
    near_m = float(np.median(np.concatenate([np.linalg.norm(s, axis=1) for s in samples])))
    pairs = scan_pairs(T_by_pose_set, near_m, max_pairs)
    directions = np.vstack([pairs, pairs[:, ::-1]])  # (projected scan, image scan)
    sequences = {id(scans): scans for scans in scans_by_pose_set.values()}  # each distinct sequence once
    projected = {}
    for key, scans in sequences.items():
        points_of = {int(k): np.asarray(scans[int(k)], dtype=np.float64) for k in np.unique(directions[:, 0])}
        projected[key] = {k: p[point_subset(len(p), k)] for k, p in points_of.items()}
    fractions = {name: np.zeros(len(directions)) for name in names}
    n_points = np.zeros(len(directions))
    for b in np.unique(directions[:, 1]):
        images = {key: RangeImage.of(np.asarray(scans[int(b)], dtype=np.float64), pixel_rad)
                  for key, scans in sequences.items()}
        for name in names:
            key, T = id(scans_by_pose_set[name]), T_by_pose_set[name]
            T_b_world = np.linalg.inv(T[b])
            for i in np.flatnonzero(directions[:, 1] == b):
                a = int(directions[i, 0])
                T_b_a = T_b_world @ T[a]
                points = projected[key][a] @ T_b_a[:3, :3].T + T_b_a[:3, 3]
                fractions[name][i] = images[key].violations(points, noise_m, depth_m).mean() if len(points) else 0.0
                n_points[i] = len(points)
    reference = fractions[names[0]]
    se, inconsistent = {}, {}
    for name in names[1:]:
        change = fractions[name] - reference
        se[name] = float(change.std() / np.sqrt(len(change))) if len(change) >= 2 else None
        # the binomial standard error of each direction's change: its points violate independently at most
        counting = np.sqrt((fractions[name] * (1 - fractions[name]) + reference * (1 - reference))
                           / np.maximum(n_points, 1))
        rose = (fractions[name] > INCONSISTENT_FACTOR * reference) & (change > 3.0 * counting)
        rose = rose[:len(pairs)] | rose[len(pairs):]
        inconsistent[name] = [[int(a), int(b)] for a, b in pairs[rose]]
    return {"pixel_deg": [float(v) for v in np.rad2deg(pixel_rad)], "near_m": near_m, "noise_m": float(noise_m),
            "depth_m": float(depth_m),
            "n_pairs": int(len(pairs)),
            "violation_fraction": {name: float(f.mean()) for name, f in fractions.items()},
            "change_standard_error": se, "inconsistent_pairs": inconsistent}

"""Vegetation as volumetric scatter: tree crowns (ellipsoids) and hedges (boxes) that a ray enters
and may or may not come back from.

Inside a volume a ray meets leaves at a constant rate (a Poisson process along the ray, the
Beer-Lambert law): the distance it travels inside before a return is exponential with mean
1 / density. Every ray of every scan draws afresh, so the returns of a crown land somewhere
else in each scan, on no plane (label -1), and some rays pass through to what lies behind. A
ray's return is the first of: its leaf hit in any volume, and the mesh hit behind.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

CROWN_DENSITY_PER_M = 0.8  # leaf hits per metre inside a crown: 4 m of crown lets ~4 % of rays through
HEDGE_DENSITY_PER_M = 4.0  # a hedge is dense: 0.8 m of it lets ~4 % through


@dataclass(frozen=True)
class Vegetation:
    """Scatter volumes in the world frame (m): crowns as ellipsoids, hedges as axis-aligned boxes."""

    crown_center: np.ndarray  # (E, 3)
    crown_semi_axes: np.ndarray  # (E, 3)
    hedge_lo: np.ndarray  # (B, 3)
    hedge_hi: np.ndarray  # (B, 3)

    @property
    def n_volumes(self) -> int:
        return len(self.crown_center) + len(self.hedge_lo)

    def first_hits(self, origins: np.ndarray, dirs: np.ndarray, t_limit: np.ndarray,
                   rng: np.random.Generator, reach_m: float) -> np.ndarray:
        """(N,) distance of each ray's first leaf hit before `t_limit` (its mesh hit, inf for none),
        inf where it has none. Rays (N, 3) origins and unit directions, world frame. Volumes
        farther than `reach_m` from the first origin are skipped (they are out of range)."""
        t_first = np.full(len(dirs), np.inf)
        o0 = origins[0]
        near = np.linalg.norm(self.crown_center - o0, axis=1) - self.crown_semi_axes.max(axis=1) < reach_m
        for center, semi in zip(self.crown_center[near], self.crown_semi_axes[near], strict=True):
            entry, exit_ = _ray_ellipsoid(origins, dirs, center, semi)
            _sample(t_first, entry, exit_, t_limit, CROWN_DENSITY_PER_M, rng)
        half_diag = np.linalg.norm(self.hedge_hi - self.hedge_lo, axis=1) / 2
        near = np.linalg.norm((self.hedge_lo + self.hedge_hi) / 2 - o0, axis=1) - half_diag < reach_m
        for lo, hi in zip(self.hedge_lo[near], self.hedge_hi[near], strict=True):
            entry, exit_ = _ray_box(origins, dirs, lo, hi)
            _sample(t_first, entry, exit_, t_limit, HEDGE_DENSITY_PER_M, rng)
        return t_first


class VegetationBuilder:
    """Collects crowns and hedges while a scene is built."""

    def __init__(self) -> None:
        self._crowns: list[tuple[np.ndarray, np.ndarray]] = []
        self._hedges: list[tuple[np.ndarray, np.ndarray]] = []

    def crown(self, center: tuple[float, float, float], semi_axes_m: tuple[float, float, float]) -> None:
        self._crowns.append((np.asarray(center, dtype=np.float64), np.asarray(semi_axes_m, dtype=np.float64)))

    def hedge(self, lo: tuple[float, float, float], hi: tuple[float, float, float]) -> None:
        self._hedges.append((np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)))

    def build(self) -> Vegetation:
        def stack(items: list[tuple[np.ndarray, np.ndarray]], i: int) -> np.ndarray:
            return np.array([item[i] for item in items]).reshape(-1, 3)

        return Vegetation(stack(self._crowns, 0), stack(self._crowns, 1), stack(self._hedges, 0),
                          stack(self._hedges, 1))


def _sample(t_first: np.ndarray, entry: np.ndarray, exit_: np.ndarray, t_limit: np.ndarray,
            density_per_m: float, rng: np.random.Generator) -> None:
    """Draw a leaf hit for every ray inside this volume before its limit; keep the nearest."""
    inside = np.flatnonzero(exit_ > np.maximum(entry, 0.0))
    start = np.maximum(entry[inside], 0.0)
    inside = inside[start < t_limit[inside]]
    start = np.maximum(entry[inside], 0.0)
    t = start + rng.exponential(1.0 / density_per_m, len(inside))
    hit = (t < exit_[inside]) & (t < t_limit[inside])
    rays = inside[hit]  # distinct rays
    t_first[rays] = np.minimum(t_first[rays], t[hit])


def _ray_ellipsoid(origins: np.ndarray, dirs: np.ndarray, center: np.ndarray, semi_axes: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Entry and exit distances of rays through an axis-aligned ellipsoid (entry > exit: missed)."""
    o = (origins - center) / semi_axes
    d = dirs / semi_axes
    a = np.einsum("ij,ij->i", d, d)
    b = np.einsum("ij,ij->i", o, d)
    c = np.einsum("ij,ij->i", o, o) - 1.0
    disc = b * b - a * c
    root = np.sqrt(np.maximum(disc, 0.0))
    entry = np.where(disc > 0, (-b - root) / a, np.inf)
    exit_ = np.where(disc > 0, (-b + root) / a, -np.inf)
    return entry, exit_


def _ray_box(origins: np.ndarray, dirs: np.ndarray, lo: np.ndarray, hi: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """Entry and exit distances of rays through an axis-aligned box (slabs; entry > exit: missed)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / dirs
        t_a = (lo - origins) * inv
        t_b = (hi - origins) * inv
    # fmin/fmax skip the NaN of a ray lying in a slab's boundary plane (0 * inf)
    entry = np.fmax.reduce(np.fmin(t_a, t_b), axis=1)
    exit_ = np.fmin.reduce(np.fmax(t_a, t_b), axis=1)
    return entry, exit_

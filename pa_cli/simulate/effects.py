"""Sensor effects of a real LiDAR on the cast returns (all off by default).

- range-dependent noise: Gaussian along the ray with sigma = range_noise_m + range_noise_per_m * range;
- isotropic point noise: a Gaussian 3D offset of every point (sensor frame), like a noisy
  reconstruction or a poorly calibrated multi-beam head;
- mixed pixels: where a beam straddles a depth edge (its azimuth neighbour in the same beam row
  returns from at least `MIXED_PIXEL_MIN_STEP_M` nearer or farther), the return may land between
  the two surfaces; a set share of all returns is placed there, along the ray, label -1;
- dropouts: a set share of the returns is missing, at random.

Each effect draws from its own random stream per scan, so turning one on leaves every other
number of the scan as it was (a dropout removes points and moves none).
"""

from __future__ import annotations

import numpy as np

MIXED_PIXEL_MIN_STEP_M = 0.5  # a smaller step between neighbouring returns is one surface, not an edge


def azimuth_neighbours(column_of_ray: np.ndarray, beam_of_ray: np.ndarray, n_columns: int) -> np.ndarray:
    """(N, 2) index of each ray's neighbour in the same beam row one column before and after
    (wrapping around the turn), -1 where that ray is not cast (outside a horizontal field of view)."""
    n_beams = int(beam_of_ray.max()) + 1 if len(beam_of_ray) else 0
    grid = np.full((n_columns, n_beams), -1, dtype=np.int64)
    grid[column_of_ray, beam_of_ray] = np.arange(len(column_of_ray))
    before = grid[(column_of_ray - 1) % n_columns, beam_of_ray]
    after = grid[(column_of_ray + 1) % n_columns, beam_of_ray]
    return np.column_stack([before, after])


def range_sigma_m(range_m: np.ndarray, sigma_m: float, sigma_per_m: float) -> np.ndarray:
    """(N,) range noise sigma (m) of returns at `range_m` (non-finite ranges get `sigma_m`)."""
    r = np.where(np.isfinite(range_m), range_m, 0.0)
    return sigma_m + sigma_per_m * r


def mix_edge_returns(range_m: np.ndarray, valid: np.ndarray, neighbours: np.ndarray, fraction: float,
                     rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Ranges with round(fraction * valid returns) returns at depth edges moved between their own
    surface and their neighbour's (uniformly along the ray), and the (N,) mask of the moved ones.

    A return is at an edge when a valid azimuth neighbour's range differs by at least
    `MIXED_PIXEL_MIN_STEP_M`; it mixes with the neighbour of the larger step. If there are fewer
    edge returns than asked for, all of them are mixed.
    """
    out = range_m.copy()
    mixed = np.zeros(len(range_m), dtype=bool)
    n_wanted = int(round(fraction * int(valid.sum())))
    if n_wanted == 0:
        return out, mixed
    safe = np.where(valid, range_m, np.nan)
    other = np.where(neighbours >= 0, safe[np.maximum(neighbours, 0)], np.nan)  # (N, 2)
    step = np.abs(other - safe[:, None])
    step = np.where(np.isfinite(step), step, -1.0)
    pick = np.argmax(step, axis=1)
    best_step = step[np.arange(len(step)), pick]
    edge = np.flatnonzero(valid & (best_step >= MIXED_PIXEL_MIN_STEP_M))
    chosen = np.sort(rng.permutation(edge)[:n_wanted])
    u = rng.uniform(0.0, 1.0, len(chosen))
    far = other[chosen, pick[chosen]]
    out[chosen] = range_m[chosen] + u * (far - range_m[chosen])
    mixed[chosen] = True
    return out, mixed


def dropped_returns(n_rays: int, fraction: float, rng: np.random.Generator) -> np.ndarray:
    """(n_rays,) mask of the rays whose return goes missing (each with probability `fraction`)."""
    return rng.uniform(0.0, 1.0, n_rays) < fraction

"""Place descriptors of local maps and the initial alignment of a candidate pair.

- Polar height descriptor (Scan Context, Kim and Kim 2018): around the anchor, `rings` x
  `sectors` polar bins out to `range_m`; each bin holds the largest height above the ground
  (the 5th percentile of the local map's heights) of its points, 0 when empty. The distance of
  two descriptors is 1 - the mean cosine similarity of the columns occupied in both, at the
  circular column shift that maximises it; that shift is the relative yaw. All shifts of one
  query against all earlier local maps come from one FFT correlation, against the spectra of the
  earlier descriptors computed once (`descriptor_spectra`).
- Bird's-eye occupancy (cells holding a vertical structure: a height span of at least one
  cell) correlated by FFT after the yaw is applied gives the relative translation in x, y.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

GROUND_PERCENTILE = 5.0  # the ground height of a local map: most of a street scan is ground or above it


def _heights(points: np.ndarray) -> np.ndarray:
    return points[:, 2] - np.percentile(points[:, 2], GROUND_PERCENTILE)


def polar_descriptor(points_anchor: np.ndarray, range_m: float, rings: int, sectors: int) -> np.ndarray:
    """The (rings, sectors) polar height descriptor of a local map (anchor frame, metres)."""
    desc = np.zeros((rings, sectors))
    if len(points_anchor) == 0:
        return desc
    height = np.maximum(_heights(points_anchor), 0.0)
    r = np.hypot(points_anchor[:, 0], points_anchor[:, 1])
    keep = r < range_m
    ring = np.minimum((r[keep] / range_m * rings).astype(np.int64), rings - 1)
    theta = np.arctan2(points_anchor[keep, 1], points_anchor[keep, 0])
    sector = np.minimum(((theta + np.pi) / (2 * np.pi) * sectors).astype(np.int64), sectors - 1)
    np.maximum.at(desc, (ring, sector), height[keep])
    return desc


def _unit_columns(desc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    norms = np.linalg.norm(desc, axis=-2, keepdims=True)
    occupied = norms > 0
    return np.where(occupied, desc / np.where(occupied, norms, 1.0), 0.0), occupied[..., 0, :].astype(np.float64)


@dataclass
class DescriptorSpectra:
    """The column spectra of K descriptors (R, S), computed once for all the queries compared with them: the FFT
    along the sectors of the unit columns (K, R, S // 2 + 1) and of the occupancy of the columns (K, S // 2 + 1)."""

    unit: np.ndarray
    occupied: np.ndarray
    sectors: int


def descriptor_spectra(descs: np.ndarray) -> DescriptorSpectra:
    """The DescriptorSpectra of `descs` (K, R, S)."""
    unit, occupied = _unit_columns(descs)
    return DescriptorSpectra(np.fft.rfft(unit, axis=-1), np.fft.rfft(occupied, axis=-1), descs.shape[-1])


def spectra_distances(query: np.ndarray, refs: DescriptorSpectra) -> tuple[np.ndarray, np.ndarray]:
    """Distance of `query` (R, S) to each of the K descriptors of `refs` and the best column shift of each.

    Column c of the query matches column (c + shift) mod S of the reference, so the query's
    frame is turned by yaw = shift * 2 pi / S relative to the reference's (R_ref_query = Rz(yaw)).
    """
    sectors = refs.sectors
    q_unit, q_occ = _unit_columns(query)
    # The ring sum of the circular correlations is the correlation of the ring sum of the spectra products.
    cosines = np.fft.irfft(np.einsum("rf,krf->kf", np.conj(np.fft.rfft(q_unit, axis=-1)), refs.unit), n=sectors,
                           axis=-1)
    both = np.fft.irfft(np.conj(np.fft.rfft(q_occ))[None] * refs.occupied, n=sectors, axis=-1)
    similarity = np.where(both > 0.5, cosines / np.maximum(both, 1.0), 0.0)
    shift = np.argmax(similarity, axis=1)
    return 1.0 - similarity[np.arange(len(similarity)), shift], shift


def yaw_of_shift(shift: int, sectors: int) -> float:
    """The yaw (rad) of a query frame relative to its reference for a descriptor column shift."""
    return float(np.angle(np.exp(2j * np.pi * shift / sectors)))


def _structure_image(points: np.ndarray, range_m: float, cell_m: float) -> np.ndarray:
    n = int(np.ceil(2 * range_m / cell_m))
    image = np.zeros((2 * n, 2 * n))  # zero-padded twice over: the correlation does not wrap
    heights = _heights(points)
    ij = np.floor((points[:, :2] + range_m) / cell_m).astype(np.int64)
    keep = np.all((ij >= 0) & (ij < n), axis=1)
    flat = ij[keep, 0] * (2 * n) + ij[keep, 1]
    top = np.full(image.size, -np.inf)
    bottom = np.full(image.size, np.inf)
    np.maximum.at(top, flat, heights[keep])
    np.minimum.at(bottom, flat, heights[keep])
    image.ravel()[:] = (top - bottom) >= cell_m
    return image


def initial_alignment(ref_points: np.ndarray, query_points: np.ndarray, yaw_rad: float, range_m: float,
                      cell_m: float) -> np.ndarray:
    """T_ref_query (4, 4): the yaw, then the x, y shift maximising the overlap of structures."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    rotated = query_points @ T[:3, :3].T
    image_q = _structure_image(rotated, range_m, cell_m)
    image_r = _structure_image(ref_points, range_m, cell_m)
    corr = np.fft.irfft2(np.conj(np.fft.rfft2(image_q)) * np.fft.rfft2(image_r), s=image_q.shape)
    di, dj = np.unravel_index(np.argmax(corr), corr.shape)
    size = image_q.shape[0]
    di = di - size if di > size // 2 else di
    dj = dj - size if dj > size // 2 else dj
    T[0, 3], T[1, 3] = di * cell_m, dj * cell_m
    return T

"""Labelled triangle meshes: the `MeshBuilder` of the scenes and the `SceneMesh` it builds.

Every triangle carries a TRUE PLANE label: all coplanar faces share one label (a label denotes
one infinite plane n.x + d = 0 in the world frame); faces smaller than `MIN_LABEL_FACE_AREA_M2`
that lie on no larger face's plane, and all curved surfaces (cylinders, spheres,
superellipsoids, height fields), get label -1.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MIN_LABEL_FACE_AREA_M2 = 0.25  # smaller faces are clutter (label -1) unless on a larger plane
# A plane key rounds the canonical (normal, offset) to these resolutions to merge coplanar faces.
_NORMAL_KEY_RES = 1e-6
_OFFSET_KEY_RES = 1e-5


def rot_z(yaw_rad: float) -> np.ndarray:
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def closed_grid_faces(n_rows: int, n_columns: int, top_row: int) -> np.ndarray:
    """Triangles (K, 3) closing a latitude-longitude grid of vertices (row-major, `n_rows` x
    `n_columns`, the columns wrapping round) with two poles after it (the top pole, then the bottom
    one): two triangles per grid cell, a fan from each pole to the row next to it (`top_row` 0 or -1:
    which grid row is next to the top pole)."""
    idx = np.arange(n_rows * n_columns).reshape(n_rows, n_columns)
    nxt = np.roll(idx, -1, axis=1)
    quads_a = np.column_stack([idx[:-1].ravel(), idx[1:].ravel(), nxt[1:].ravel()])
    quads_b = np.column_stack([idx[:-1].ravel(), nxt[1:].ravel(), nxt[:-1].ravel()])
    top, bottom = n_rows * n_columns, n_rows * n_columns + 1
    bottom_row = -1 - top_row  # the other end: -1 for 0, 0 for -1
    caps_top = np.column_stack([np.full(n_columns, top), idx[top_row], nxt[top_row]])
    caps_bottom = np.column_stack([np.full(n_columns, bottom), nxt[bottom_row], idx[bottom_row]])
    return np.vstack([quads_a, quads_b, caps_top, caps_bottom])


class MeshBuilder:
    """Collects triangles (world frame, metres) with, per triangle, a candidate plane or none."""

    def __init__(self) -> None:
        self._vertices: list[np.ndarray] = []
        self._triangles: list[np.ndarray] = []
        self._face_planes: list[np.ndarray] = []  # (T, 4) per chunk: n, d or NaN (non-planar)
        self._face_areas: list[np.ndarray] = []  # (T,) area of the face the triangle belongs to
        self._n_vertices = 0

    def _add(self, vertices: np.ndarray, triangles: np.ndarray, planes: np.ndarray,
             areas: np.ndarray) -> None:
        self._vertices.append(np.asarray(vertices, dtype=np.float64))
        self._triangles.append(np.asarray(triangles, dtype=np.int64) + self._n_vertices)
        self._face_planes.append(planes)
        self._face_areas.append(areas)
        self._n_vertices += len(vertices)

    def box(self, min_xyz: tuple[float, float, float], max_xyz: tuple[float, float, float],
            yaw_deg: float = 0.0) -> None:
        """Add a box given by its axis-aligned extent, then rotated by yaw about its centre."""
        lo = np.asarray(min_xyz, dtype=np.float64)
        hi = np.asarray(max_xyz, dtype=np.float64)
        center = (lo + hi) / 2
        half = (hi - lo) / 2
        R = rot_z(np.deg2rad(yaw_deg))
        corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)],
                           dtype=np.float64)
        vertices = center + (corners * half) @ R.T
        # Faces: (axis, sign, four corner indices in cyclic order).
        faces = [(0, -1, [0, 1, 3, 2]), (0, 1, [4, 6, 7, 5]), (1, -1, [0, 4, 5, 1]),
                 (1, 1, [2, 3, 7, 6]), (2, -1, [0, 2, 6, 4]), (2, 1, [1, 5, 7, 3])]
        triangles, planes, areas = [], [], []
        size = 2 * half
        for axis, sign, q in faces:
            normal = sign * R[:, axis]
            offset = -normal @ (center + sign * half[axis] * R[:, axis])
            other = [a for a in range(3) if a != axis]
            area = size[other[0]] * size[other[1]]
            triangles += [[q[0], q[1], q[2]], [q[0], q[2], q[3]]]
            planes += [np.append(normal, offset)] * 2
            areas += [area] * 2
        self._add(vertices, np.array(triangles), np.array(planes), np.array(areas))

    def mesh(self, vertices: np.ndarray, triangles: np.ndarray) -> None:
        """Add a non-planar mesh (clutter): all its triangles get label -1."""
        n = len(triangles)
        self._add(vertices, triangles, np.full((n, 4), np.nan), np.zeros(n))

    def cylinder(self, center_xy: tuple[float, float], radius_m: float, z0: float, z1: float,
                 resolution: int = 16) -> None:
        angles = np.linspace(0, 2 * np.pi, resolution, endpoint=False)
        ring = np.column_stack([center_xy[0] + radius_m * np.cos(angles),
                                center_xy[1] + radius_m * np.sin(angles)])
        vertices = np.vstack([np.column_stack([ring, np.full(resolution, z0)]),
                              np.column_stack([ring, np.full(resolution, z1)])])
        i = np.arange(resolution)
        j = (i + 1) % resolution
        triangles = np.vstack([np.column_stack([i, j, j + resolution]),
                               np.column_stack([i, j + resolution, i + resolution])])
        self.mesh(vertices, triangles)

    def sphere(self, center: tuple[float, float, float], radius_m: float, resolution: int = 12) -> None:
        theta = np.linspace(0, np.pi, resolution + 1)[1:-1]
        phi = np.linspace(0, 2 * np.pi, 2 * resolution, endpoint=False)
        tt, pp = np.meshgrid(theta, phi, indexing="ij")
        ring = np.column_stack([np.sin(tt).ravel() * np.cos(pp).ravel(),
                                np.sin(tt).ravel() * np.sin(pp).ravel(), np.cos(tt).ravel()])
        vertices = np.vstack([ring, [[0, 0, 1], [0, 0, -1]]]) * radius_m + np.asarray(center)
        self.mesh(vertices, closed_grid_faces(len(theta), len(phi), top_row=0))

    def superellipsoid(self, center: tuple[float, float, float], semi_axes_m: tuple[float, float, float],
                       exponent: float = 1.0, yaw_deg: float = 0.0, resolution: int = 12) -> None:
        """A curved closed surface |x/a|^(2/e) + |y/b|^(2/e) + |z/c|^(2/e) = 1 (e = `exponent`:
        1 an ellipsoid, below 1 a rounded box), yawed about its centre: label -1."""
        theta = np.linspace(-np.pi / 2, np.pi / 2, resolution + 1)[1:-1]  # latitude
        phi = np.linspace(-np.pi, np.pi, 2 * resolution, endpoint=False)  # longitude
        tt, pp = np.meshgrid(theta, phi, indexing="ij")

        def signed_pow(v: np.ndarray) -> np.ndarray:
            return np.sign(v) * np.abs(v) ** exponent

        a, b, c = semi_axes_m
        unit = np.column_stack([(signed_pow(np.cos(tt)) * signed_pow(np.cos(pp))).ravel(),
                                (signed_pow(np.cos(tt)) * signed_pow(np.sin(pp))).ravel(),
                                signed_pow(np.sin(tt)).ravel()])
        local = np.vstack([unit, [[0, 0, 1], [0, 0, -1]]]) * [a, b, c]
        vertices = local @ rot_z(np.deg2rad(yaw_deg)).T + np.asarray(center, dtype=np.float64)
        self.mesh(vertices, closed_grid_faces(len(theta), len(phi), top_row=-1))

    def height_field(self, x_m: np.ndarray, y_m: np.ndarray, z_m: np.ndarray) -> None:
        """A curved sheet z(x, y) over the grid `x_m` (X,) by `y_m` (Y,) with heights `z_m` (X, Y): label -1."""
        xx, yy = np.meshgrid(x_m, y_m, indexing="ij")
        vertices = np.column_stack([xx.ravel(), yy.ravel(), np.asarray(z_m, dtype=np.float64).ravel()])
        idx = np.arange(len(x_m) * len(y_m)).reshape(len(x_m), len(y_m))
        a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
        self.mesh(vertices, np.vstack([np.column_stack([a, b, c]), np.column_stack([a, c, d])]))

    def build(self) -> SceneMesh:
        """Merge coplanar faces into plane labels and return the labelled mesh."""
        vertices = np.vstack(self._vertices)
        triangles = np.vstack(self._triangles)
        face_planes = np.vstack(self._face_planes)
        face_areas = np.concatenate(self._face_areas)
        planar = np.all(np.isfinite(face_planes), axis=1)
        canon = face_planes.copy()
        # Canonical sign: the first clearly non-zero normal component is positive.
        n = canon[:, :3]
        first = np.argmax(np.abs(n) > 1e-9, axis=1)
        sign = np.sign(n[np.arange(len(n)), first])
        sign[~planar | (sign == 0)] = 1.0
        canon *= sign[:, None]
        keys = np.column_stack([np.round(canon[:, :3] / _NORMAL_KEY_RES),
                                np.round(canon[:, 3] / _OFFSET_KEY_RES)])
        labels = np.full(len(triangles), -1, dtype=np.int32)
        planar_index = np.flatnonzero(planar)
        planes = np.empty((0, 4))
        if len(planar_index):
            _, inverse = np.unique(keys[planar_index], axis=0, return_inverse=True)
            inverse = inverse.ravel()
            n_keys = int(inverse.max()) + 1
            # A key becomes a label if at least one face on it is big; labels are numbered in
            # the order of the first big face, so they follow the scene description.
            is_big = face_areas[planar_index] >= MIN_LABEL_FACE_AREA_M2
            first_big = np.full(n_keys, len(triangles))
            np.minimum.at(first_big, inverse[is_big], planar_index[is_big])
            labelled_keys = np.flatnonzero(first_big < len(triangles))
            labelled_keys = labelled_keys[np.argsort(first_big[labelled_keys])]
            label_of_key = np.full(n_keys, -1, dtype=np.int32)
            label_of_key[labelled_keys] = np.arange(len(labelled_keys), dtype=np.int32)
            labels[planar_index] = label_of_key[inverse]
            planes = canon[first_big[labelled_keys]]
        return SceneMesh(vertices=vertices, triangles=triangles, triangle_label=labels,
                         planes_world=planes)


@dataclass
class SceneMesh:
    """Triangles in the world frame (metres), a plane label per triangle and the true planes.

    `planes_world[label]` = (nx, ny, nz, d) with unit normal n: n.x + d = 0 (world frame, m).
    """

    vertices: np.ndarray  # (V, 3) float64
    triangles: np.ndarray  # (T, 3) int64
    triangle_label: np.ndarray  # (T,) int32, -1 = no plane (clutter)
    planes_world: np.ndarray  # (P, 4) float64


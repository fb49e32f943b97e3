"""Ray-cast LiDAR sequences with exact ground truth (`pa simulate`).

A scene is a triangle mesh made of boxes (planar faces) and a little non-planar clutter
(cylinders, spheres). Every triangle carries a TRUE PLANE label: all coplanar faces share
one label (a label denotes one infinite plane n.x + d = 0 in the world frame); faces smaller
than `MIN_LABEL_FACE_AREA_M2` that lie on no larger face's plane, and all curved clutter,
get label -1.

The sensor follows a smooth closed path (periodic cubic spline through waypoints,
parametrised by arc length), at `step_m` metres per scan and one scan every
`SCAN_PERIOD_S` = 0.1 s, so the speed is step_m / 0.1 s. Yaw follows the path tangent;
roll and pitch are small sinusoids of the arc length. Sensor frame: x forward, y left,
z up; T_world_scan = [Rz(yaw) Ry(pitch) Rx(roll) | position].

Beam pattern of a spinning LiDAR: `beams` elevation angles evenly spaced over
[-vfov/2, +vfov/2], `azimuth_steps` columns over 360 degrees, swept counter-clockwise
from azimuth 0 (the x axis) during one scan period. Column c is fired at time
c / azimuth_steps * 0.1 s after the scan start. Points are stored column by column
(all beams of column 0, then column 1, ...). Returns closer than `min_range_m` (default
0.5 m) or farther than `max_range_m` are dropped, like a real sensor's blind zone.

Range noise: Gaussian along the ray, sigma `range_noise_m`. For labelled hits the
noise-free range is computed in float64 from the true plane equation (not from Open3D's
float32 hit distance), so the only error of a labelled point is the range noise (plus the
float32 rounding of the PCD).

Intensity is synthetic (0..255): a fixed pseudo reflectivity per plane label times
(0.3 + 0.7 |cos incidence|); clutter 0.5. It carries no physics; it only fills the field.

Motion distortion (off by default): when on, each column is cast from the sensor pose at
its own firing time, and the points are written in the sensor frame AT THAT TIME (raw,
not deskewed), with a per-point `time` field (seconds since the scan start). The ground
truth pose of a scan is the pose at the scan's start time (timestamp k * 0.1 s).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from pa_cli import __version__
from pa_cli.clusters import clusters_by_label
from pa_cli.errors import FormatError, InputError, OutputError, UsageError
from pa_cli.problem import FeatureProblem, make_problem

log = logging.getLogger(__name__)

SCAN_PERIOD_S = 0.1  # one sweep per 0.1 s (10 Hz), the usual spinning-LiDAR rate
MIN_LABEL_FACE_AREA_M2 = 0.25  # smaller faces are clutter (label -1) unless on a larger plane
BEAM_CHOICES = (16, 32, 64)
DEFAULT_VFOV_DEG = {16: 30.0, 32: 40.0, 64: 45.0}  # VLP-16 +-15, HDL-32-like, OS1-64 +-22.5
SCENES = ("office", "street")
# A plane key rounds the canonical (normal, offset) to these resolutions to merge coplanar faces.
_NORMAL_KEY_RES = 1e-6
_OFFSET_KEY_RES = 1e-5


# --------------------------------------------------------------------------------------------
# mesh building
# --------------------------------------------------------------------------------------------


def _rot_z(yaw_rad: float) -> np.ndarray:
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


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
        R = _rot_z(np.deg2rad(yaw_deg))
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
        n_t, n_p = len(theta), len(phi)
        idx = np.arange(n_t * n_p).reshape(n_t, n_p)
        nxt = np.roll(idx, -1, axis=1)
        quads_a = np.column_stack([idx[:-1].ravel(), idx[1:].ravel(), nxt[1:].ravel()])
        quads_b = np.column_stack([idx[:-1].ravel(), nxt[1:].ravel(), nxt[:-1].ravel()])
        top, bottom = n_t * n_p, n_t * n_p + 1
        caps_top = np.column_stack([np.full(n_p, top), idx[0], nxt[0]])
        caps_bottom = np.column_stack([np.full(n_p, bottom), nxt[-1], idx[-1]])
        self.mesh(vertices, np.vstack([quads_a, quads_b, caps_top, caps_bottom]))

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


@dataclass
class Scene:
    """A scene: its mesh, the sensor path and the per-scene defaults."""

    name: str
    mesh: SceneMesh
    waypoints_xy: np.ndarray  # (W, 2) metres, a closed loop (the last point joins the first)
    sensor_height_m: float
    default_step_m: float
    default_max_range_m: float
    roll_amplitude_deg: float = 1.5  # small body sway, like a hand-held or vehicle-mounted sensor
    pitch_amplitude_deg: float = 1.0
    roll_period_m: float = 7.0  # sway wavelengths along the path (m); incommensurate on purpose
    pitch_period_m: float = 11.0


# --------------------------------------------------------------------------------------------
# scenes
# --------------------------------------------------------------------------------------------


def _office() -> Scene:
    """An indoor floor, 30 x 20 m: corridor, rooms, doors, furniture, columns."""
    m = MeshBuilder()
    wall_h, t = 2.8, 0.15
    m.box((-0.5, -0.5, -0.2), (30.5, 20.5, 0.0))  # floor slab
    m.box((-0.5, -0.5, wall_h), (30.5, 20.5, wall_h + 0.2))  # ceiling slab
    # Outer walls.
    m.box((-0.5, -0.5, 0), (0.0, 20.5, wall_h))
    m.box((30.0, -0.5, 0), (30.5, 20.5, wall_h))
    m.box((0, -0.5, 0), (30, 0.0, wall_h))
    m.box((0, 20.0, 0), (30, 20.5, wall_h))
    # West lobby x 0..5 (open to the corridor); corridor y 9..11 from x 5 to 26; east lobby x 26..30.
    door_w, door_h = 1.0, 2.1

    def wall_x(y0: float, x0: float, x1: float, doors: list[float]) -> None:
        """A wall along x at y in [y0, y0 + t] from x0 to x1 with door openings centred at `doors`."""
        edges = [x0]
        for xd in doors:
            edges += [xd - door_w / 2, xd + door_w / 2]
        edges.append(x1)
        for a, b in zip(edges[0::2], edges[1::2], strict=True):
            m.box((a, y0, 0), (b, y0 + t, wall_h))
        for xd in doors:  # lintel above the door
            m.box((xd - door_w / 2, y0, door_h), (xd + door_w / 2, y0 + t, wall_h))

    def wall_y(x0: float, y0: float, y1: float) -> None:
        m.box((x0, y0, 0), (x0 + t, y1, wall_h))

    wall_x(11.0, 5.0, 26.0, doors=[14.0, 22.0])  # north side of the corridor
    wall_x(9.0 - t, 5.0, 26.0, doors=[8.0, 16.5, 23.0])  # south side
    wall_x(5.0, 0.0, 5.0, doors=[])  # lobby boundaries to the south/north rooms
    wall_x(15.0, 0.0, 5.0, doors=[])
    wall_y(5.0 - t, 0.0, 5.0)
    wall_y(5.0 - t, 15.0, 20.0)
    wall_y(26.0, 0.0, 5.0)
    wall_y(26.0, 15.0, 20.0)
    wall_x(5.0, 26.0, 30.0, doors=[])
    wall_x(15.0, 26.0, 30.0, doors=[])
    for x in (12.0, 24.0):  # north rooms: 5..12, 12..24 (large, with columns), 24..26
        wall_y(x, 11.0 + t, 20.0)
    for x in (11.0, 19.5):  # south rooms
        wall_y(x, 0.0, 9.0 - t)
    # Open door leaves (0.9 m x 4 cm, hinged at the door frame, swung into the room): planes
    # at odd angles.
    for hinge_x, hinge_y, angle_deg in ((13.5, 11.2, 110.0), (22.5, 11.2, 65.0), (7.5, 8.8, -110.0)):
        a = np.deg2rad(angle_deg)
        cx, cy = hinge_x + 0.47 * np.cos(a), hinge_y + 0.47 * np.sin(a)
        m.box((cx - 0.45, cy - 0.02, 0), (cx + 0.45, cy + 0.02, door_h), yaw_deg=angle_deg)
    # Columns in the large north room.
    for x in (15.5, 18.0, 20.5):
        for y in (13.5, 17.0):
            m.box((x - 0.2, y - 0.2, 0), (x + 0.2, y + 0.2, wall_h))
    # Furniture: tables (top + legs), cabinets, shelves (some rotated).
    tables = [(8.0, 15.0, 0.0), (8.5, 18.0, 15.0), (17.0, 19.0, 0.0), (3.0, 2.0, 30.0),
              (15.0, 4.0, 0.0), (22.0, 5.0, -20.0), (28.0, 18.0, 0.0)]
    for x, y, yaw in tables:
        m.box((x - 0.8, y - 0.4, 0.72), (x + 0.8, y + 0.4, 0.75), yaw_deg=yaw)
        R = _rot_z(np.deg2rad(yaw))
        for sx in (-0.7, 0.7):
            for sy in (-0.3, 0.3):
                cx, cy = np.array([x, y]) + R[:2, :2] @ np.array([sx, sy])
                m.box((cx - 0.03, cy - 0.03, 0), (cx + 0.03, cy + 0.03, 0.72), yaw_deg=yaw)
    cabinets = [((0.2, 6.0, 0), (0.8, 8.0, 1.9), 0.0), ((25.2, 12.0, 0), (25.8, 14.0, 1.2), 0.0),
                ((12.5, 19.2, 0), (14.5, 19.8, 2.0), 0.0), ((6.0, 1.0, 0), (7.5, 1.6, 1.0), 10.0),
                ((27.0, 6.0, 0), (29.5, 6.6, 1.6), 0.0), ((2.0, 16.0, 0), (3.0, 17.0, 1.1), 25.0)]
    for lo, hi, yaw in cabinets:
        m.box(lo, hi, yaw_deg=yaw)
    # Clutter: waste bins, plant pots with round crowns (label -1).
    for x, y in ((4.5, 10.8), (25.5, 9.3), (19.0, 12.0), (1.0, 13.5)):
        m.cylinder((x, y), 0.18, 0.0, 0.6)
    for x, y in ((29.3, 11.8), (0.8, 4.0)):
        m.cylinder((x, y), 0.2, 0.0, 0.5)
        m.sphere((x, y, 0.9), 0.4)
    waypoints = np.array([
        [2.5, 10.4], [6.0, 10.4], [10.0, 10.4], [13.0, 10.3], [14.0, 11.0], [14.3, 12.3],
        [16.8, 15.3], [19.2, 15.3], [21.6, 12.4], [22.0, 11.0], [23.0, 10.3], [26.5, 10.5],
        [28.2, 11.5], [28.4, 9.0], [26.0, 9.6], [20.0, 9.6], [12.0, 9.6], [6.0, 9.6],
        [4.0, 9.5], [2.0, 9.1], [1.2, 9.9],
    ])
    return Scene("office", m.build(), waypoints, sensor_height_m=1.2, default_step_m=0.1,
                 default_max_range_m=30.0)


def _street() -> Scene:
    """An outdoor street, about 150 m: facades with setbacks, cars, poles, trees, ground."""
    m = MeshBuilder()
    m.box((-30.0, -40.0, -0.3), (180.0, 40.0, 0.0))  # road and ground
    for side in (-1, 1):  # sidewalks with curbs, y from 6 to 10 on each side
        y0, y1 = sorted((side * 6.0, side * 10.0))
        m.box((-30.0, y0, 0.0), (180.0, y1, 0.15))
    # Facades: building blocks on both sides with deterministic lengths, setbacks and heights.
    rng = np.random.default_rng(12345)  # fixed: the scene is part of the program, not the seed
    for side in (-1, 1):
        x = -20.0
        while x < 170.0:
            length = float(rng.uniform(12.0, 26.0))
            setback = float(rng.choice([0.0, 1.5, 3.0]))
            height = float(rng.uniform(7.0, 20.0))
            depth = 12.0
            front = 10.0 + setback
            y0, y1 = sorted((side * front, side * (front + depth)))
            m.box((x, y0, 0.0), (x + length, y1, height))
            if rng.uniform() < 0.5:  # a ground-floor shop awning / balcony slab
                ya, yb = sorted((side * front, side * (front - 1.2)))
                m.box((x + 2.0, ya, 3.0), (x + length - 2.0, yb, 3.25))
            x += length + float(rng.choice([0.0, 0.0, 3.0, 5.0]))  # alleys between some blocks
    # Parked cars along both curbs (body + cabin), some gaps.
    for side in (-1, 1):
        for i, x in enumerate(np.arange(5.0, 130.0, 7.0)):
            if (i * 7 + (side > 0) * 3) % 5 == 0:
                continue
            yc = side * 4.9
            m.box((x - 2.1, yc - 0.9, 0.3), (x + 2.1, yc + 0.9, 1.0))
            m.box((x - 1.1, yc - 0.8, 1.0), (x + 1.0, yc + 0.8, 1.5))
            for wx in (x - 1.4, x + 1.4):  # wheels: clutter
                m.cylinder((wx, yc - 0.85 * side), 0.3, 0.0, 0.3, resolution=8)
    # Poles (street lights, signs) and trees: clutter.
    for x in np.arange(0.0, 150.0, 12.0):
        for side in (-1, 1):
            m.cylinder((float(x), side * 6.6), 0.08, 0.0, 6.0, resolution=10)
    for x in np.arange(6.0, 150.0, 24.0):
        m.cylinder((float(x), -8.5), 0.2, 0.0, 3.0, resolution=10)
        m.sphere((float(x), -8.5, 4.2), 1.6)
    waypoints = np.array([
        [0.0, -2.5], [35.0, -2.4], [70.0, -2.6], [105.0, -2.4], [138.0, -2.5], [145.0, -1.2],
        [146.5, 1.0], [143.0, 2.6], [138.0, 2.5], [105.0, 2.4], [70.0, 2.6], [35.0, 2.4],
        [0.0, 2.5], [-7.0, 1.2], [-8.5, -1.0], [-5.0, -2.6],
    ])
    return Scene("street", m.build(), waypoints, sensor_height_m=1.8, default_step_m=1.0,
                 default_max_range_m=100.0, roll_amplitude_deg=1.0, pitch_amplitude_deg=0.8)


_SCENE_BUILDERS: dict[str, Callable[[], Scene]] = {"office": _office, "street": _street}


def make_scene(name: str) -> Scene:
    """The built-in scene `name` (one of `SCENES`)."""
    if name not in _SCENE_BUILDERS:
        raise UsageError(f"unknown scene '{name}'; choose one of {', '.join(SCENES)}.")
    return _SCENE_BUILDERS[name]()


# --------------------------------------------------------------------------------------------
# sensor path
# --------------------------------------------------------------------------------------------


class SensorPath:
    """A smooth closed path: position, yaw along the tangent, small roll/pitch, by arc length."""

    _SAMPLES = 20000

    def __init__(self, scene: Scene) -> None:
        from scipy.interpolate import CubicSpline

        pts = np.vstack([scene.waypoints_xy, scene.waypoints_xy[:1]])
        chord = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))]
        self._spline = CubicSpline(chord, pts, bc_type="periodic")
        u = np.linspace(0.0, chord[-1], self._SAMPLES + 1)
        speed = np.linalg.norm(self._spline(u, 1), axis=1)
        length = np.r_[0.0, np.cumsum((speed[1:] + speed[:-1]) / 2 * np.diff(u))]
        self._u, self._s = u, length
        self.length_m = float(length[-1])
        self.height_m = scene.sensor_height_m
        self.roll_amp_rad = np.deg2rad(scene.roll_amplitude_deg)
        self.pitch_amp_rad = np.deg2rad(scene.pitch_amplitude_deg)
        self.roll_period_m = scene.roll_period_m
        self.pitch_period_m = scene.pitch_period_m

    def poses(self, s_m: np.ndarray) -> np.ndarray:
        """T_world_sensor (K, 4, 4) at arc lengths `s_m` (metres, wrapped around the loop)."""
        s = np.mod(np.asarray(s_m, dtype=np.float64), self.length_m)
        u = np.interp(s, self._s, self._u)
        xy = self._spline(u)
        dxy = self._spline(u, 1)
        yaw = np.arctan2(dxy[:, 1], dxy[:, 0])
        roll = self.roll_amp_rad * np.sin(2 * np.pi * s / self.roll_period_m)
        pitch = self.pitch_amp_rad * np.sin(2 * np.pi * s / self.pitch_period_m + 0.5)
        cy, sy = np.cos(yaw), np.sin(yaw)
        cp, sp = np.cos(pitch), np.sin(pitch)
        cr, sr = np.cos(roll), np.sin(roll)
        T = np.zeros((len(s), 4, 4))
        # R = Rz(yaw) Ry(pitch) Rx(roll)
        T[:, 0, 0] = cy * cp
        T[:, 0, 1] = cy * sp * sr - sy * cr
        T[:, 0, 2] = cy * sp * cr + sy * sr
        T[:, 1, 0] = sy * cp
        T[:, 1, 1] = sy * sp * sr + cy * cr
        T[:, 1, 2] = sy * sp * cr - cy * sr
        T[:, 2, 0] = -sp
        T[:, 2, 1] = cp * sr
        T[:, 2, 2] = cp * cr
        T[:, 0, 3] = xy[:, 0]
        T[:, 1, 3] = xy[:, 1]
        T[:, 2, 3] = self.height_m
        T[:, 3, 3] = 1.0
        return T


# --------------------------------------------------------------------------------------------
# simulation
# --------------------------------------------------------------------------------------------


@dataclass
class SimOptions:
    """Options of a simulation; None means the scene's or beam count's default."""

    scene: str = "office"
    scans: int = 50
    step_m: float | None = None
    beams: int = 16
    vfov_deg: float | None = None
    azimuth_steps: int = 1024
    range_noise_m: float = 0.01
    max_range_m: float | None = None
    min_range_m: float = 0.5
    seed: int = 0
    motion_distortion: bool = False

    def validate(self) -> None:
        """Raise `UsageError` (exit 2) naming the flag of the first bad value."""
        if self.scene not in SCENES:
            raise UsageError(f"unknown scene '{self.scene}'; choose one of {', '.join(SCENES)}.")
        if self.beams not in BEAM_CHOICES:
            raise UsageError(f"--beams must be one of 16, 32, 64; got {self.beams}.")
        checks = [("--scans", self.scans, 1), ("--azimuth-steps", self.azimuth_steps, 8)]
        for flag, value, least in checks:
            if value < least:
                raise UsageError(f"{flag} must be at least {least}; got {value}.")
        positive = [("--step-m", self.step_m), ("--vfov-deg", self.vfov_deg),
                    ("--max-range-m", self.max_range_m)]
        for flag, value in positive:
            if value is not None and not (np.isfinite(value) and value > 0):
                raise UsageError(f"{flag} must be a positive number; got {value}.")
        for flag, value in (("--range-noise-m", self.range_noise_m), ("--min-range-m", self.min_range_m)):
            if not (np.isfinite(value) and value >= 0):
                raise UsageError(f"{flag} must be zero or positive; got {value}.")
        if self.vfov_deg is not None and self.vfov_deg >= 180:
            raise UsageError(f"--vfov-deg must be below 180; got {self.vfov_deg}.")
        if self.max_range_m is not None and self.max_range_m <= self.min_range_m:
            raise UsageError(f"--max-range-m ({self.max_range_m}) must exceed --min-range-m "
                             f"({self.min_range_m}).")
        if self.seed < 0:
            raise UsageError(f"--seed must be zero or positive; got {self.seed}.")

    def resolved(self, scene: Scene) -> SimOptions:
        """A copy with every None replaced by its default."""
        out = SimOptions(**asdict(self))
        out.step_m = scene.default_step_m if self.step_m is None else self.step_m
        out.vfov_deg = DEFAULT_VFOV_DEG[self.beams] if self.vfov_deg is None else self.vfov_deg
        out.max_range_m = scene.default_max_range_m if self.max_range_m is None else self.max_range_m
        return out


@dataclass
class SimScan:
    """One simulated scan. Points in the sensor frame (metres), ordered column by column."""

    points_scan: np.ndarray  # (M, 3) float64
    labels: np.ndarray  # (M,) int32 true plane label or -1
    intensity: np.ndarray  # (M,) float32, 0..255
    time: np.ndarray | None  # (M,) float64 seconds since the scan start (motion distortion only)
    T_world_sensor: np.ndarray  # (M, 4, 4) pose of each point's firing time if distorted, else (1, 4, 4)


@dataclass
class SimulatedSequence:
    """An in-memory simulated sequence (see `simulate_sequence`)."""

    scans: list[SimScan]
    T_world_scan: np.ndarray  # (N, 4, 4) ground truth, pose at each scan's start time
    timestamps: np.ndarray  # (N,) seconds, k * SCAN_PERIOD_S
    planes_world: np.ndarray  # (P, 4): n.x + d = 0, world frame
    options: SimOptions = field(default_factory=SimOptions)


class Simulator:
    """Casts the scans of one scene with one set of options (the scene is built once)."""

    def __init__(self, options: SimOptions) -> None:
        from pa_cli._open3d import open3d

        options.validate()
        o3d = open3d()
        self.scene = make_scene(options.scene)
        self.options = options.resolved(self.scene)
        self.path = SensorPath(self.scene)
        mesh = self.scene.mesh
        self._raycaster = o3d.t.geometry.RaycastingScene()
        self._raycaster.add_triangles(
            o3d.core.Tensor(mesh.vertices.astype(np.float32)),
            o3d.core.Tensor(mesh.triangles.astype(np.uint32)))
        self._o3d = o3d
        opt = self.options
        elevation = np.deg2rad(np.linspace(-opt.vfov_deg / 2, opt.vfov_deg / 2, opt.beams))
        azimuth = 2 * np.pi * np.arange(opt.azimuth_steps) / opt.azimuth_steps
        az, el = np.meshgrid(azimuth, elevation, indexing="ij")  # (A, B): column-major order
        self.dirs_sensor = np.column_stack([(np.cos(el) * np.cos(az)).ravel(),
                                            (np.cos(el) * np.sin(az)).ravel(), np.sin(el).ravel()])
        self.column_of_ray = np.repeat(np.arange(opt.azimuth_steps), opt.beams)
        self.column_time_s = np.arange(opt.azimuth_steps) / opt.azimuth_steps * SCAN_PERIOD_S
        self.speed_mps = opt.step_m / SCAN_PERIOD_S
        # A pseudo reflectivity per plane label (0.2..1.0), clutter 0.5.
        n_labels = len(mesh.planes_world)
        self._reflectivity = np.r_[0.2 + 0.8 * np.mod(np.arange(n_labels) * 0.618034, 1.0), 0.5]

    @property
    def planes_world(self) -> np.ndarray:
        return self.scene.mesh.planes_world

    def gt_poses(self) -> np.ndarray:
        """T_world_scan (N, 4, 4): the sensor pose at each scan's start time."""
        k = np.arange(self.options.scans)
        return self.path.poses(k * self.options.step_m)

    def poses_at_times(self, time_s: np.ndarray) -> np.ndarray:
        """T_world_sensor (K, 4, 4) at times (seconds since the start of scan 0)."""
        return self.path.poses(self.speed_mps * np.asarray(time_s, dtype=np.float64))

    def scan(self, k: int) -> SimScan:
        """Cast scan k (deterministic for a given seed and k)."""
        opt = self.options
        rng = np.random.default_rng([opt.seed, k])
        t0 = k * SCAN_PERIOD_S
        if opt.motion_distortion:
            T_cols = self.poses_at_times(t0 + self.column_time_s)  # (A, 4, 4)
            T_rays = T_cols[self.column_of_ray]
            dirs_world = np.einsum("nij,nj->ni", T_rays[:, :3, :3], self.dirs_sensor)
            origins = T_rays[:, :3, 3]
        else:
            T0 = self.poses_at_times(np.array([t0]))[0]
            dirs_world = self.dirs_sensor @ T0[:3, :3].T
            origins = np.broadcast_to(T0[:3, 3], dirs_world.shape)
        rays = np.hstack([origins, dirs_world]).astype(np.float32)
        hit = self._raycaster.cast_rays(self._o3d.core.Tensor(rays), nthreads=0)
        t_hit = hit["t_hit"].numpy().astype(np.float64)
        prim = hit["primitive_ids"].numpy()
        finite = np.isfinite(t_hit)
        labels = np.full(len(t_hit), -1, dtype=np.int32)
        labels[finite] = self.scene.mesh.triangle_label[prim[finite]]
        # Exact float64 range for labelled hits: intersect the ray with the true plane.
        rng_m = t_hit.copy()
        lab = labels >= 0
        planes = self.planes_world[labels[lab]]
        denom = np.einsum("ij,ij->i", planes[:, :3], dirs_world[lab])
        rng_m[lab] = -(np.einsum("ij,ij->i", planes[:, :3], origins[lab]) + planes[:, 3]) / denom
        noise = rng.normal(0.0, opt.range_noise_m, len(t_hit)) if opt.range_noise_m > 0 else \
            np.zeros(len(t_hit))
        keep = finite & (rng_m >= opt.min_range_m) & (rng_m <= opt.max_range_m) & (rng_m + noise > 0)
        r = rng_m[keep] + noise[keep]
        d_sensor = self.dirs_sensor[keep]
        points_scan = d_sensor * r[:, None]
        labels = labels[keep]
        cos_incidence = np.ones(len(r))
        if np.any(lab[keep]):
            cos_incidence[labels >= 0] = np.abs(denom[keep[lab]])
        refl = self._reflectivity[labels]  # label -1 picks the last entry (clutter)
        intensity = (255.0 * refl * (0.3 + 0.7 * cos_incidence)).astype(np.float32)
        if opt.motion_distortion:
            time = self.column_time_s[self.column_of_ray[keep]]
            T_points = T_rays[keep]
        else:
            time = None
            T_points = T0[None]
        return SimScan(points_scan=points_scan, labels=labels, intensity=intensity, time=time,
                       T_world_sensor=T_points)

    def iter_scans(self) -> Iterator[SimScan]:
        for k in range(self.options.scans):
            yield self.scan(k)


def simulate_sequence(options: SimOptions) -> SimulatedSequence:
    """Simulate a whole sequence in memory (for tests and benchmarks)."""
    sim = Simulator(options)
    scans = list(sim.iter_scans())
    return SimulatedSequence(scans=scans, T_world_scan=sim.gt_poses(),
                             timestamps=np.arange(sim.options.scans) * SCAN_PERIOD_S,
                             planes_world=sim.planes_world, options=sim.options)


def _check_out_dir(out_dir: Path, force: bool) -> None:
    if out_dir.exists() and not out_dir.is_dir():
        raise OutputError(f"{out_dir} exists and is not a folder; choose another OUT_DIR.")
    if out_dir.is_dir() and any(out_dir.iterdir()) and not force:
        raise OutputError(f"{out_dir} is not empty; pass --force to replace its contents, "
                          "or choose another OUT_DIR.")
    parent = out_dir.parent
    if not parent.is_dir():
        raise OutputError(f"{out_dir}: the parent folder {parent} does not exist; create it first.")


def simulate(options: SimOptions, out_dir: Path | str, force: bool = False,
             progress: Callable[[int, int], None] | None = None) -> dict:
    """Simulate a sequence and write it to `out_dir` atomically; returns the meta dict.

    Layout: `scans/%06d.pcd` (binary, float32 x y z intensity [time], sensor frame),
    `labels/%06d.npy` (int32 per point), `gt_poses_kitti.txt`, `gt_poses_tum.txt`, `times.txt`
    (timestamps k * 0.1 s), `planes.npy` ((P, 4) float64 rows n_x n_y n_z d, world frame,
    row = label), `meta.json`. The folder is built beside `out_dir` and renamed into place.
    """
    from pa_cli.io.scans import write_pcd
    from pa_cli.io.trajectory import write_kitti, write_tum

    options.validate()
    out_dir = Path(out_dir)
    _check_out_dir(out_dir, force)
    sim = Simulator(options)
    opt = sim.options
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", suffix=".tmp", dir=out_dir.parent))
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o777 & ~umask)  # mkdtemp makes 0700; give the folder the usual permissions
    try:
        (tmp / "scans").mkdir()
        (tmp / "labels").mkdir()
        n_points = 0
        for k, scan in enumerate(sim.iter_scans()):
            write_pcd(tmp / "scans" / f"{k:06d}.pcd", scan.points_scan, time=scan.time,
                      intensity=scan.intensity)
            np.save(tmp / "labels" / f"{k:06d}.npy", scan.labels.astype(np.int32))
            n_points += len(scan.labels)
            if progress is not None:
                progress(k + 1, opt.scans)
        T = sim.gt_poses()
        write_kitti(tmp / "gt_poses_kitti.txt", T)
        timestamps_s = np.arange(opt.scans) * SCAN_PERIOD_S
        write_tum(tmp / "gt_poses_tum.txt", T, timestamps_s)
        # one scan start time per line: `pa refine OUT_DIR/scans` finds it and writes real TUM times
        (tmp / "times.txt").write_text("".join(f"{t:.9f}\n" for t in timestamps_s))
        np.save(tmp / "planes.npy", sim.planes_world.astype(np.float64))
        meta = {
            "pa_version": __version__,
            "scene": opt.scene,
            "options": asdict(opt),
            "scan_period_s": SCAN_PERIOD_S,
            "n_scans": opt.scans,
            "n_points": n_points,
            "n_planes": len(sim.planes_world),
            "path_length_m": sim.path.length_m,
            "sensor_frame": "x forward, y left, z up; points are in the sensor frame",
            "gt_pose": "T_world_scan at the scan's start time (timestamp k * scan_period_s)",
            "point_order": "column by column (azimuth counter-clockwise from +x), beams bottom to top",
            "time_field": "seconds since the scan start (only with motion_distortion)",
            "planes": "planes.npy row i = label i: n_x n_y n_z d with n.x + d = 0 (world frame, m)",
            "labels": "labels/%06d.npy int32 per PCD point: true plane label, -1 = no plane",
        }
        (tmp / "meta.json").write_text(json.dumps(meta, indent=2, sort_keys=True) + "\n")
        _replace_dir(tmp, out_dir)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)
    return meta


def _replace_dir(new: Path, out_dir: Path) -> None:
    """Rename `new` onto `out_dir`; an existing `out_dir` is moved aside first, then removed."""
    old = None
    if out_dir.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", suffix=".old", dir=out_dir.parent))
        os.replace(out_dir, old / "x")
    try:
        os.replace(new, out_dir)
    except OSError:
        if old is not None:
            os.replace(old / "x", out_dir)
        raise
    if old is not None:
        shutil.rmtree(old)


# --------------------------------------------------------------------------------------------
# exact-association plane problems
# --------------------------------------------------------------------------------------------


def _read_pcd_xyz(path: Path) -> np.ndarray:
    from pypcd4 import PointCloud

    try:
        cloud = PointCloud.from_path(path)
        return cloud.numpy(("x", "y", "z")).astype(np.float64)
    except (OSError, ValueError, KeyError) as exc:
        raise FormatError(f"{path}: not a readable PCD with x y z fields ({exc}).") from None


def build_problem_from_labels(source: Path | str | SimulatedSequence, min_points: int = 10
                              ) -> FeatureProblem:
    """Exact-association plane problem of a simulated sequence, with the GT poses.

    `source` is a `pa simulate` output folder or a `SimulatedSequence`. One observation per
    (true plane label, scan) with at least `min_points` points; the cluster is built from the
    points in the sensor frame as stored. With motion distortion the stored points are raw
    (not deskewed), so such a problem is NOT exactly consistent with the GT poses.
    """
    plane_parts, scan_parts, cluster_parts = [], [], []
    if isinstance(source, SimulatedSequence):
        T = source.T_world_scan
        if source.options.motion_distortion:
            log.warning("simulated sequence has motion distortion: clusters use raw points.")
        for k, scan in enumerate(source.scans):
            lab, cl = clusters_by_label(scan.points_scan, scan.labels, min_points)
            plane_parts.append(lab)
            scan_parts.append(np.full(len(lab), k, np.int64))
            cluster_parts.append(cl)
        name = "simulated sequence"
    else:
        from pa_cli.io.trajectory import read_trajectory

        folder = Path(source)
        if not folder.is_dir():
            raise InputError(f"{folder}: not a folder; expected the OUT_DIR of `pa simulate`.")
        T = read_trajectory(folder / "gt_poses_kitti.txt").T_world_scan
        meta_path = folder / "meta.json"
        if meta_path.exists() and json.loads(meta_path.read_text()).get("options", {}).get(
                "motion_distortion"):
            log.warning("%s has motion distortion: clusters use raw (not deskewed) points.", folder)
        for k in range(len(T)):
            pcd = folder / "scans" / f"{k:06d}.pcd"
            lab_path = folder / "labels" / f"{k:06d}.npy"
            if not pcd.exists() or not lab_path.exists():
                raise InputError(f"{folder}: missing {pcd.name} or labels/{lab_path.name} for pose {k}; "
                                 "expected one scan and one label file per GT pose.")
            points = _read_pcd_xyz(pcd)
            labels = np.load(lab_path, allow_pickle=False)
            if labels.shape != (len(points),):
                raise FormatError(f"{lab_path}: {labels.shape[0] if labels.ndim else 0} labels for "
                                  f"{len(points)} points in {pcd.name}; expected one label per point.")
            lab, cl = clusters_by_label(points, labels, min_points)
            plane_parts.append(lab)
            scan_parts.append(np.full(len(lab), k, np.int64))
            cluster_parts.append(cl)
        name = str(folder)
    return make_problem(np.concatenate(plane_parts), np.concatenate(scan_parts),
                        np.concatenate(cluster_parts), n_scans=len(T), T_world_scan=T, source=name)

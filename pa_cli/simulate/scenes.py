"""Scenes for `pa simulate`: labelled triangle meshes and the built-in scene catalogue.

A scene is a triangle mesh made of boxes (planar faces) and a little non-planar clutter
(cylinders, spheres). Every triangle carries a TRUE PLANE label: all coplanar faces share
one label (a label denotes one infinite plane n.x + d = 0 in the world frame); faces smaller
than `MIN_LABEL_FACE_AREA_M2` that lie on no larger face's plane, and all curved clutter,
get label -1. A scene also holds the closed sensor path (waypoints) and its defaults.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from pa_cli.errors import UsageError

MIN_LABEL_FACE_AREA_M2 = 0.25  # smaller faces are clutter (label -1) unless on a larger plane
SCENES = ("office", "street", "town", "blocks")
# Each scene's sensor paths by name, the default first (`pa simulate --path`).
SCENE_PATHS = {"office": ("loop",), "street": ("loop",), "town": ("circuit", "figure8"),
               "blocks": ("circuit", "figure8")}
# A plane key rounds the canonical (normal, offset) to these resolutions to merge coplanar faces.
_NORMAL_KEY_RES = 1e-6
_OFFSET_KEY_RES = 1e-5


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
    """A scene: its mesh, its sensor paths and the per-scene defaults.

    `paths` maps a path name to its waypoints (W, 2), metres, a closed loop (the last point joins
    the first); the first entry is the scene's default path.
    """

    name: str
    mesh: SceneMesh
    paths: dict[str, np.ndarray]
    sensor_height_m: float
    default_step_m: float
    default_max_range_m: float
    roll_amplitude_deg: float = 1.5  # small body sway, like a hand-held or vehicle-mounted sensor
    pitch_amplitude_deg: float = 1.0
    roll_period_m: float = 7.0  # sway wavelengths along the path (m); incommensurate on purpose
    pitch_period_m: float = 11.0



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
    return Scene("office", m.build(), {"loop": waypoints}, sensor_height_m=1.2, default_step_m=0.1,
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
    return Scene("street", m.build(), {"loop": waypoints}, sensor_height_m=1.8, default_step_m=1.0,
                 default_max_range_m=100.0, roll_amplitude_deg=1.0, pitch_amplitude_deg=0.8)


# The town grid: street centrelines (m) and the half-width of a street (road and sidewalk).
_TOWN_STREETS_X = (0.0, 66.0, 132.0)
_TOWN_STREETS_Y = (0.0, 56.0, 112.0)
_TOWN_OUTER_BLOCK_M = 50.0  # depth of the ring of blocks outside the outer streets
_STREET_HALF_WIDTH_M = 8.0
_TEMPLATE_BLOCK_XY_M = (50.0, 40.0)  # the inner blocks' footprint: one street spacing less a street width
_CORNER_RADIUS_M = 10.0  # turns are rounded over this distance before and after a corner


def _town_block(m: MeshBuilder, x0: float, y0: float, x1: float, y1: float, rng: np.random.Generator) -> None:
    """Buildings on a block footprint: strips along x, a building at each street side of a strip."""
    edges = [x0]
    while x1 - edges[-1] > 24.0:
        edges.append(edges[-1] + float(rng.uniform(10.0, 22.0)))
    edges.append(x1)
    half_depth = (y1 - y0) / 2
    for i, (a, b) in enumerate(zip(edges[:-1], edges[1:], strict=True)):
        gap = float(rng.choice([0.0, 0.0, 3.0]))  # an alley after some strips
        b_end = b - (gap if i < len(edges) - 2 else 0.0)
        for side in (-1, 1):
            setback = float(rng.choice([0.0, 1.5, 3.0]))
            depth = float(rng.uniform(8.0, half_depth - 1.0))
            height = float(rng.uniform(6.0, 22.0))
            end_setback = float(rng.choice([0.0, 2.0]))
            lo_x = a + (end_setback if i == 0 else 0.0)
            hi_x = b_end - (end_setback if i == len(edges) - 2 else 0.0)
            if side < 0:
                ya, yb = y0 + setback, y0 + setback + depth
            else:
                ya, yb = y1 - setback - depth, y1 - setback
            m.box((lo_x, ya, 0.0), (hi_x, yb, height))
            if rng.uniform() < 0.4:  # a ground-floor awning on the street side
                y_face = ya if side < 0 else yb
                m.box((lo_x + 1.0, min(y_face, y_face - side * 1.2), 3.0),
                      (hi_x - 1.0, max(y_face, y_face - side * 1.2), 3.25))
    for _ in range(3):  # street furniture on the sidewalk: poles and a tree (clutter)
        x = float(rng.uniform(x0 + 2.0, x1 - 2.0))
        y = y0 - 1.5 if rng.uniform() < 0.5 else y1 + 1.5
        m.cylinder((x, y), 0.1, 0.0, float(rng.uniform(3.0, 7.0)), resolution=10)
    tx = float(rng.uniform(x0 + 3.0, x1 - 3.0))
    m.cylinder((tx, y0 - 2.0), 0.2, 0.0, 3.0, resolution=10)
    m.sphere((tx, y0 - 2.0, 4.0), 1.5)


def _rounded_loop(corners: list[tuple[float, float]], spacing_m: float = 15.0) -> np.ndarray:
    """Waypoints of a closed polyline through `corners`, with turns rounded over _CORNER_RADIUS_M.

    Straight segments get a waypoint every `spacing_m` so the periodic spline stays on them; a
    corner where the polyline goes straight on (a crossing) is a plain waypoint.
    """
    c = np.asarray(corners, dtype=np.float64)
    out: list[np.ndarray] = []
    n = len(c)
    for i in range(n):
        a, b = c[i], c[(i + 1) % n]
        length = float(np.linalg.norm(b - a))
        direction = (b - a) / length
        start, stop = _CORNER_RADIUS_M, length - _CORNER_RADIUS_M
        k = max(int(np.ceil((stop - start) / spacing_m)), 1)
        out += [a + direction * s for s in np.linspace(start, stop, k + 1)]
    return np.array(out)


def _town(identical_blocks: bool) -> Scene:
    """A grid of city blocks (3 x 3 streets, 4 x 4 blocks) with two looping paths.

    Paths: `circuit` drives the outer ring of streets (about 490 m a lap); `figure8` crosses the
    centre intersection straight on twice a lap (about 490 m). With `identical_blocks` every block
    is the same copy (same buildings, same clutter): a place looks like the places one block away.
    """
    m = MeshBuilder()
    xs = (_TOWN_STREETS_X[0] - _STREET_HALF_WIDTH_M - _TOWN_OUTER_BLOCK_M, *_TOWN_STREETS_X,
          _TOWN_STREETS_X[-1] + _STREET_HALF_WIDTH_M + _TOWN_OUTER_BLOCK_M)
    ys = (_TOWN_STREETS_Y[0] - _STREET_HALF_WIDTH_M - _TOWN_OUTER_BLOCK_M, *_TOWN_STREETS_Y,
          _TOWN_STREETS_Y[-1] + _STREET_HALF_WIDTH_M + _TOWN_OUTER_BLOCK_M)
    m.box((xs[0] - 10.0, ys[0] - 10.0, -0.3), (xs[-1] + 10.0, ys[-1] + 10.0, 0.0))  # ground
    rng = np.random.default_rng(2024)  # fixed: the scene is part of the program, not the seed
    for i in range(len(xs) - 1):
        for j in range(len(ys) - 1):
            x0 = xs[i] + (_STREET_HALF_WIDTH_M if i > 0 else 0.0)
            x1 = xs[i + 1] - (_STREET_HALF_WIDTH_M if i < len(xs) - 2 else 0.0)
            y0 = ys[j] + (_STREET_HALF_WIDTH_M if j > 0 else 0.0)
            y1 = ys[j + 1] - (_STREET_HALF_WIDTH_M if j < len(ys) - 2 else 0.0)
            if identical_blocks:  # every block one copy of a template, kept against its inner streets
                x0, x1 = (x1 - _TEMPLATE_BLOCK_XY_M[0], x1) if i == 0 else (x0, x0 + _TEMPLATE_BLOCK_XY_M[0])
                y0, y1 = (y1 - _TEMPLATE_BLOCK_XY_M[1], y1) if j == 0 else (y0, y0 + _TEMPLATE_BLOCK_XY_M[1])
                rng = np.random.default_rng(7)
            _town_block(m, x0, y0, x1, y1, rng)
    sx, sy = _TOWN_STREETS_X, _TOWN_STREETS_Y
    circuit = _rounded_loop([(sx[0], sy[0]), (sx[2], sy[0]), (sx[2], sy[2]), (sx[0], sy[2])])
    figure8 = _rounded_loop([(sx[0], sy[1]), (sx[2], sy[1]), (sx[2], sy[2]), (sx[1], sy[2]),
                             (sx[1], sy[0]), (sx[0], sy[0])])
    name = "blocks" if identical_blocks else "town"
    return Scene(name, m.build(), dict(zip(SCENE_PATHS[name], (circuit, figure8), strict=True)), sensor_height_m=1.8,
                 default_step_m=1.0, default_max_range_m=100.0, roll_amplitude_deg=1.0,
                 pitch_amplitude_deg=0.8)


_SCENE_BUILDERS: dict[str, Callable[[], Scene]] = {
    "office": _office, "street": _street, "town": lambda: _town(identical_blocks=False),
    "blocks": lambda: _town(identical_blocks=True)}


def make_scene(name: str) -> Scene:
    """The built-in scene `name` (one of `SCENES`)."""
    if name not in _SCENE_BUILDERS:
        raise UsageError(f"unknown scene '{name}'; choose one of {', '.join(SCENES)}.")
    return _SCENE_BUILDERS[name]()

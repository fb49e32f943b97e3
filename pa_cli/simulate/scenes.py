"""Scenes for `pa simulate`: the built-in scene catalogue.

A scene is a labelled triangle mesh (`mesh.py`: boxes with true plane labels, curved clutter
with label -1), the closed sensor paths (waypoints) and its defaults. The street scenes
(`street`, `avenue`) take optional features (`streetscape.SceneFeatures`: vegetation, curved
cars, a cambered and undulating road, facade relief and gaps); off, a scene is exactly as before.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from pa_cli.errors import UsageError
from pa_cli.simulate.mesh import MIN_LABEL_FACE_AREA_M2, MeshBuilder, SceneMesh, rot_z
from pa_cli.simulate.streetscape import Cars, Facades, SceneFeatures, plant_street
from pa_cli.simulate.vegetation import Vegetation

__all__ = ["MIN_LABEL_FACE_AREA_M2", "SCENES", "SCENE_PATHS", "STREET_SCENES", "MeshBuilder", "Scene",
           "SceneFeatures", "SceneMesh", "make_scene"]

SCENES = ("office", "street", "town", "blocks", "avenue", "hall")
# Each scene's sensor paths by name, the default first (`pa simulate --path`).
SCENE_PATHS = {"office": ("loop",), "street": ("loop",), "town": ("circuit", "figure8"),
               "blocks": ("circuit", "figure8"), "avenue": ("loop",), "hall": ("loop", "sharp")}
STREET_SCENES = ("street", "avenue")  # the scenes that take `SceneFeatures`


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
    vegetation: Vegetation | None = None  # scatter volumes (street scenes with vegetation)
    # z (m) of the ground under the vehicle at world (x, y), when the road is not flat: the path rides on it
    ground_height: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None



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
        R = rot_z(np.deg2rad(yaw))
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


def _street(features: SceneFeatures = SceneFeatures()) -> Scene:
    """An outdoor street, about 150 m: facades with setbacks, cars, poles, trees, ground."""
    m = MeshBuilder()
    road = features.road(half_width_m=6.0)
    if road is None:
        m.box((-30.0, -40.0, -0.3), (180.0, 40.0, 0.0))  # road and ground
        kerb_bottom = 0.0
    else:  # the ground beyond the kerbs, the road sheet between them
        m.box((-30.0, -40.0, -0.3), (180.0, -6.0, 0.0))
        m.box((-30.0, 6.0, -0.3), (180.0, 40.0, 0.0))
        road.add_to(m, -30.0, 180.0)
        kerb_bottom = road.lowest_m - 0.3
    for side in (-1, 1):  # sidewalks with curbs, y from 6 to 10 on each side
        y0, y1 = sorted((side * 6.0, side * 10.0))
        m.box((-30.0, y0, kerb_bottom), (180.0, y1, 0.15))
    # Facades: building blocks on both sides with deterministic lengths, setbacks and heights.
    rng = np.random.default_rng(12345)  # fixed: the scene is part of the program, not the seed
    facades = Facades(m, features)
    for side in (-1, 1):
        x = -20.0
        while x < 170.0:
            length = float(rng.uniform(12.0, 26.0))
            setback = float(rng.choice([0.0, 1.5, 3.0]))
            height = float(rng.uniform(7.0, 20.0))
            depth = 12.0
            front = 10.0 + setback
            stands = facades.place_next()
            if stands:
                facades.building(x, x + length, side, front, depth, height)
            if rng.uniform() < 0.5 and stands:  # a ground-floor shop awning / balcony slab
                ya, yb = sorted((side * front, side * (front - 1.2)))
                m.box((x + 2.0, ya, 3.0), (x + length - 2.0, yb, 3.25))
            x += length + float(rng.choice([0.0, 0.0, 3.0, 5.0]))  # alleys between some blocks
    # Parked cars along both curbs (body + cabin), some gaps.
    cars = Cars(m, features.curved_cars, road)
    for side in (-1, 1):
        for i, x in enumerate(np.arange(5.0, 130.0, 7.0)):
            if (i * 7 + (side > 0) * 3) % 5 == 0:
                continue
            yc = side * 4.9
            if cars.curved:
                cars.curved_car(float(x), yc)
                continue
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
    vegetation = None
    if features.vegetation > 0:
        vegetation = plant_street(m, features.vegetation, -20.0, 170.0, tree_m=8.2, hedge_m=(9.0, 9.9),
                                  sidewalk_top_m=0.15).build()
    waypoints = np.array([
        [0.0, -2.5], [35.0, -2.4], [70.0, -2.6], [105.0, -2.4], [138.0, -2.5], [145.0, -1.2],
        [146.5, 1.0], [143.0, 2.6], [138.0, 2.5], [105.0, 2.4], [70.0, 2.6], [35.0, 2.4],
        [0.0, 2.5], [-7.0, 1.2], [-8.5, -1.0], [-5.0, -2.6],
    ])
    return Scene("street", m.build(), {"loop": waypoints}, sensor_height_m=1.8, default_step_m=1.0,
                 default_max_range_m=100.0, roll_amplitude_deg=1.0, pitch_amplitude_deg=0.8,
                 vegetation=vegetation, ground_height=None if road is None else road.height)


_AVENUE_X_M = (-40.0, 360.0)  # the avenue's extent along x
_AVENUE_MODULE_M = (22.0, 12.0, 14.0)  # every building: length, depth, height (identical copies)
_AVENUE_BUILDING_PITCH_M = 80.0  # a building every 80 m on each side (staggered): few facades


def _avenue(features: SceneFeatures = SceneFeatures()) -> Scene:
    """A long straight avenue, about 330 m, with few facades and repeated structure.

    Identical buildings every 80 m on each side (staggered by 40 m: about a quarter of each side
    has a facade), identical lamp posts every 20 m, low garden walls along the open lots with a
    gate every 40 m, box cars parked in a repeating pattern. Along the avenue a place looks like
    the places 20, 40 or 80 m on: what pins the position along it is scarce and repetitive.
    """
    m = MeshBuilder()
    x0, x1 = _AVENUE_X_M
    half_width, walk = 7.0, 4.0  # road half width, sidewalk width (m)
    road = features.road(half_width_m=half_width)
    if road is None:
        m.box((x0, -45.0, -0.3), (x1, 45.0, 0.0))
        kerb_bottom = 0.0
    else:
        m.box((x0, -45.0, -0.3), (x1, -half_width, 0.0))
        m.box((x0, half_width, -0.3), (x1, 45.0, 0.0))
        road.add_to(m, x0, x1)
        kerb_bottom = road.lowest_m - 0.3
    for side in (-1, 1):
        y0, y1 = sorted((side * half_width, side * (half_width + walk)))
        m.box((x0, y0, kerb_bottom), (x1, y1, 0.15))
    facades = Facades(m, features)
    length, depth, height = _AVENUE_MODULE_M
    front = half_width + walk + 0.5
    standing: dict[int, list[tuple[float, float]]] = {-1: [], 1: []}
    for side in (-1, 1):
        for bx in np.arange(10.0 if side < 0 else 50.0, 320.0, _AVENUE_BUILDING_PITCH_M):
            if facades.place_next():
                facades.building(float(bx), float(bx) + length, side, front, depth, height)
                standing[side].append((float(bx), float(bx) + length))
    # Garden walls (0.9 m high) along the open lots, 3 m behind the sidewalk, a 4 m gate every 40 m.
    for side in (-1, 1):
        edges = [x0 + 10.0]
        for a, b in standing[side]:
            edges += [a - 1.0, b + 1.0]
        edges.append(x1 - 10.0)
        y0, y1 = sorted((side * (front + 3.0), side * (front + 3.25)))
        for a, b in zip(edges[0::2], edges[1::2], strict=True):
            cuts = [a] + [g for gx in np.arange(0.0, x1, 40.0) if a + 2 < gx < b - 2 for g in (gx - 2.0, gx + 2.0)]
            cuts.append(b)
            for ca, cb in zip(cuts[0::2], cuts[1::2], strict=True):
                m.box((ca, y0, 0.0), (cb, y1, 0.9))
    for x in np.arange(0.0, 330.0, 20.0):  # identical lamp posts: a mast and an arm over the road
        for side in (-1, 1):
            m.cylinder((float(x), side * (half_width + 0.6)), 0.09, 0.15, 8.0, resolution=10)
            ya, yb = sorted((side * (half_width + 0.6), side * (half_width - 0.9)))
            m.box((float(x) - 0.08, ya, 7.8), (float(x) + 0.08, yb, 7.95))
    cars = Cars(m, features.curved_cars, road)
    for side in (-1, 1):
        for i, x in enumerate(np.arange(15.0, 310.0, 6.5)):
            if (i + (side > 0) * 2) % 3 == 0 or (i // 6) % 2 == 1:  # small groups, long gaps
                continue
            yc = side * (half_width - 1.1)
            if cars.curved:
                cars.curved_car(float(x), yc)
                continue
            m.box((x - 2.1, yc - 0.9, 0.3), (x + 2.1, yc + 0.9, 1.0))
            m.box((x - 1.1, yc - 0.8, 1.0), (x + 1.0, yc + 0.8, 1.5))
    vegetation = None
    if features.vegetation > 0:
        vegetation = plant_street(m, features.vegetation, 0.0, 320.0, tree_m=half_width + 1.8,
                                  hedge_m=(half_width + walk - 0.9, half_width + walk - 0.1),
                                  sidewalk_top_m=0.15).build()
    waypoints = np.array([
        [0.0, -3.5], [80.0, -3.4], [160.0, -3.6], [240.0, -3.4], [300.0, -3.5], [310.0, -2.0],
        [312.0, 1.0], [307.0, 3.6], [300.0, 3.5], [240.0, 3.4], [160.0, 3.6], [80.0, 3.4],
        [0.0, 3.5], [-8.0, 2.0], [-10.0, -1.0], [-6.0, -3.6],
    ])
    return Scene("avenue", m.build(), {"loop": waypoints}, sensor_height_m=1.8, default_step_m=1.0,
                 default_max_range_m=100.0, roll_amplitude_deg=1.0, pitch_amplitude_deg=0.8,
                 vegetation=vegetation, ground_height=None if road is None else road.height)


_HALL_XYZ_M = (60.0, 30.0, 8.0)  # the hall's inside: length, width, wall height
_HALL_SHARP_TURN_DEG = 22.5  # the sharp path's tightest turn per 0.9 m scan


def _hall() -> Scene:
    """A large empty hall, 60 x 30 m, 8 m walls and a floor, nothing else (no ceiling).

    Paths: `loop` (a rounded rectangle 8 m inside the walls, gentle turns) and `sharp` (a slalom
    down the hall and a tight return: at the default 0.9 m per scan its tightest turns yaw the
    sensor by about 22.5 deg per scan).
    """
    m = MeshBuilder()
    length, width, height = _HALL_XYZ_M
    t = 0.3
    m.box((-t, -t, -0.2), (length + t, width + t, 0.0))  # floor
    m.box((-t, -t, 0.0), (0.0, width + t, height))
    m.box((length, -t, 0.0), (length + t, width + t, height))
    m.box((0.0, -t, 0.0), (length, 0.0, height))
    m.box((0.0, width, 0.0), (length, width + t, height))
    loop = np.array([[12.0, 8.0], [30.0, 8.0], [48.0, 8.0], [52.0, 11.0], [52.0, 19.0], [48.0, 22.0],
                     [30.0, 22.0], [12.0, 22.0], [8.0, 19.0], [8.0, 11.0]])
    # The sharp path: a slalom y = 11 - A cos(k (x - 12)) from x 12 to 44 (two periods of 16 m; A such
    # that its tightest curvature A k^2 turns the sensor by _HALL_SHARP_TURN_DEG per 0.9 m), a half
    # circle north, back west along the far side and a half circle south to the start.
    k = 2 * np.pi / 16.0
    amplitude = np.deg2rad(_HALL_SHARP_TURN_DEG) / 0.9 / k**2
    xs = np.arange(12.0, 44.01, 1.0)
    slalom = np.column_stack([xs, 11.0 - amplitude * np.cos(k * (xs - 12.0))])
    y_low, y_high = 11.0 - amplitude, 21.5
    radius, y_mid = (y_high - y_low) / 2, (y_high + y_low) / 2
    turn = np.deg2rad(np.arange(-70.0, 71.0, 20.0))
    east = np.column_stack([46.0 + radius * np.cos(turn), y_mid + radius * np.sin(turn)])
    back = np.column_stack([np.arange(44.0, 11.9, -4.0), np.full(9, y_high)])
    west = np.column_stack([10.0 - radius * np.cos(turn), y_mid - radius * np.sin(turn)])
    sharp = np.vstack([slalom, east, back, west])
    return Scene("hall", m.build(), {"loop": loop, "sharp": sharp}, sensor_height_m=1.5, default_step_m=0.9,
                 default_max_range_m=100.0)


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


_SCENE_BUILDERS: dict[str, Callable[[SceneFeatures], Scene]] = {
    "office": lambda f: _office(), "street": _street, "town": lambda f: _town(identical_blocks=False),
    "blocks": lambda f: _town(identical_blocks=True), "avenue": _avenue, "hall": lambda f: _hall()}


def make_scene(name: str, features: SceneFeatures | None = None) -> Scene:
    """The built-in scene `name` (one of `SCENES`), with the street `features` (street scenes only)."""
    if name not in _SCENE_BUILDERS:
        raise UsageError(f"unknown scene '{name}'; choose one of {', '.join(SCENES)}.")
    features = SceneFeatures() if features is None else features
    if features.any() and name not in STREET_SCENES:
        raise UsageError(f"scene '{name}' has no street: vegetation, cars, road and facade features apply to "
                         f"{', '.join(STREET_SCENES)}.")
    return _SCENE_BUILDERS[name](features)
